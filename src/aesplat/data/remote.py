"""Shards behind an http(s) URL, read through a node-local cache (docs/data.md, "Data on a server").

``data.root`` may be the URL of a shard folder (the one holding ``manifest.json``). The manifest is fetched
afresh by every process that opens the folder (it is small, and a folder whose shards were replaced must not be
read with the old list); the shards are fetched only when a stream opens one (:meth:`RemoteShards.fetch`), so
each rank and each DataLoader worker downloads only the shards it reads. The rest of the data code reads the
local copies.

A shard is downloaded to ``NAME.tar.part``, resumed with a Range request after a cut, checked against the
manifest's SHA-256, renamed into place and then marked verified by ``NAME.tar.sha256`` (its SHA-256 and size):
a later run reuses a shard whose marker matches the manifest and whose size matches the marker, without hashing
it again. A lock file per shard (``fcntl.flock``) makes two processes of one node that want the same shard
download it once. Nothing is ever evicted: a shard an epoch reads stays.

Credentials come from the environment only (never from the configuration, so they are never saved with a
run): a bearer token in ``AESPLAT_DATA_TOKEN``, or ``AESPLAT_DATA_USER`` and ``AESPLAT_DATA_PASSWORD`` for basic
authentication. Every failure is one line (:class:`FetchError`) naming the file and its URL, never the
credentials.
"""

from __future__ import annotations

import atexit
import fcntl
import hashlib
import logging
import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ..errors import UserError, os_error_line
from ..files import atomic_write
from .manifest import read_manifest, sha256

log = logging.getLogger("aesplat.data")

SCHEMES = ("http", "https")
TOKEN_ENV = "AESPLAT_DATA_TOKEN"
USER_ENV = "AESPLAT_DATA_USER"
PASSWORD_ENV = "AESPLAT_DATA_PASSWORD"
RETRY_STATUS = {408, 425, 429, 500, 502, 503, 504}  # answers worth asking again; other errors are final
CHUNK = 1 << 20
MANIFEST = "the manifest"  # how messages name it
_MANIFESTS: dict[str, Path] = {}  # URL -> the folder this process fetched its manifest into


class FetchError(UserError):
    """A file behind ``data.root`` that could not be fetched or verified, in one line.

    Raised in a DataLoader worker, it reaches the main process rebuilt by torch from a message of several lines
    ("Caught FetchError in DataLoader worker process 0. Original Traceback ... FetchError: LINE"): the line is
    taken back from there, so the command still reports one line."""

    def __init__(self, message: str) -> None:
        if "\n" in message:
            last = message.strip().splitlines()[-1]
            message = last.split(f"{type(self).__name__}: ", 1)[-1]
        super().__init__(message)


def is_url(root: str | Path) -> bool:
    """Whether ``data.root`` names a URL (``scheme://…``) rather than a folder."""
    return isinstance(root, str) and "://" in root


def check_url(url: str) -> str:
    """``url`` without a trailing slash, or a one-line error: a scheme other than http(s), credentials or a
    query in the URL (they would be saved with the run's configuration)."""
    parts = urlsplit(url)
    if parts.scheme not in SCHEMES:
        raise UserError(f"data.root {url}: only http:// and https:// URLs are read (or give a local folder); "
                        f"copy {parts.scheme}:// data to a folder or an http(s) server")  # fmt: skip
    if parts.username is not None or parts.password is not None:
        raise UserError(f"data.root: credentials in the URL would be saved with the run's config.yaml; give "
                        f"the URL without them and set {USER_ENV} and {PASSWORD_ENV} (or {TOKEN_ENV}) in the "
                        "environment")  # fmt: skip
    if parts.query or parts.fragment:
        raise UserError(f"data.root {url}: give the URL of the shard folder, without a query (?...) or "
                        f"fragment (#...); a token goes in {TOKEN_ENV}")  # fmt: skip
    if not parts.hostname:
        raise UserError(f"data.root {url}: the URL names no host")
    return url.rstrip("/")


def default_cache(url: str) -> Path:
    """``$TMPDIR/aesplat-shards/<hash of the URL>`` (``/tmp`` without ``TMPDIR``): node-local on a cluster."""
    digest = hashlib.sha256(url.encode()).hexdigest()[:16]
    return Path(os.environ.get("TMPDIR") or "/tmp") / "aesplat-shards" / digest


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v  # not NaN


# The download settings' ranges: setting -> (test, what it must be); refused in one line when a DataModule is
# built, and by ``aesplat.config_checks`` before a command writes anything.
DOWNLOAD_RANGES = {
    "download_retries": (lambda v: _number(v) and isinstance(v, int) and v >= 0, "0 or more tries"),
    "download_timeout": (lambda v: _number(v) and v > 0, "more than 0 seconds"),
    "download_backoff": (lambda v: _number(v) and v >= 0, "0 or more seconds"),
}


@dataclass(frozen=True)
class DownloadSettings:
    """How hard a download tries: ``retries`` more tries after a failure that may pass (a cut connection, a
    timeout, HTTP 5xx or 429), the first ``backoff`` seconds after the first failure and doubling, and
    ``timeout`` seconds to connect and at most between two pieces of data."""

    retries: int = 5
    timeout: float = 60.0
    backoff: float = 1.0

    def check(self) -> None:
        """One line for a value out of range (:data:`DOWNLOAD_RANGES`)."""
        values = {"download_retries": self.retries, "download_timeout": self.timeout,
                  "download_backoff": self.backoff}  # fmt: skip
        for name, (test, must) in DOWNLOAD_RANGES.items():
            if not test(values[name]):
                raise UserError(f"invalid configuration: data.{name} = {values[name]!r}: it must be {must}")


class _Retry(Exception):
    """A failure another try may mend; ``why`` says it in a few words."""

    def __init__(self, why: str) -> None:
        super().__init__(why)
        self.why = why


class RemoteShards:
    """The shard folder at ``url``, mirrored on demand in ``cache`` (:func:`default_cache` when None).

    :meth:`open` fetches the manifest into the cache and returns the cache folder, which the data code reads
    as a shard folder whose shards are fetched when read; :meth:`fetch` makes one shard of it present and
    verified. An instance travels to the DataLoader workers (pickled), each of which opens its own HTTP
    session."""

    def __init__(self, url: str, cache: str | Path | None = None, settings: DownloadSettings | None = None):
        self.url = check_url(url)
        self.cache = Path(cache) if cache else default_cache(self.url)
        self.settings = settings or DownloadSettings()
        self.settings.check()
        self.expected: dict[str, str | None] = {}  # "split/shard" -> its SHA-256, from the manifest
        self._session: Any = None
        self._session_pid = -1

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_session": None, "_session_pid": -1}

    # ------------------------------------------------------------------------------------------- HTTP

    def session(self) -> Any:
        """This process's HTTP session, with the credentials of the environment (read when it is made)."""
        if self._session is None or self._session_pid != os.getpid():
            import requests

            session = requests.Session()
            token = os.environ.get(TOKEN_ENV)
            if token:
                session.headers["Authorization"] = f"Bearer {token}"
            elif os.environ.get(USER_ENV):
                session.auth = (os.environ[USER_ENV], os.environ.get(PASSWORD_ENV, ""))
            self._session, self._session_pid = session, os.getpid()
        return self._session

    def _final(self, status: int, what: str, url: str) -> FetchError:
        """The one line for an answer no retry mends."""
        if status in (401, 403):
            if os.environ.get(TOKEN_ENV):
                given = f"the token in {TOKEN_ENV} was refused: set it to a token this server accepts"
            elif os.environ.get(USER_ENV):
                given = (f"the user and password in {USER_ENV} and {PASSWORD_ENV} were refused: set ones this "
                         "server accepts")  # fmt: skip
            else:
                given = (f"no credentials were given: set {TOKEN_ENV} (a bearer token), or {USER_ENV} and "
                         f"{PASSWORD_ENV}")  # fmt: skip
            return FetchError(f"{what} {url}: HTTP {status}, {given}")
        if status == 404 and what == MANIFEST:
            return FetchError(f"{what} {url}: not found on the server (HTTP 404); data.root must be the URL of "
                              "the shard folder, the one holding manifest.json")  # fmt: skip
        if status == 404:
            return FetchError(f"{what} {url}: not found on the server (HTTP 404); check data.root, or upload "
                              "the file the manifest lists")  # fmt: skip
        return FetchError(f"{what} {url}: the server answered HTTP {status}")

    def _tries(self, what: str, url: str, attempt) -> Any:
        """``attempt()`` until it returns, a :class:`_Retry` failure given ``retries`` more tries with doubling
        waits; then one line naming ``what`` and its URL."""
        for n in range(self.settings.retries + 1):
            try:
                return attempt()
            except _Retry as err:
                if n == self.settings.retries:
                    raise FetchError(
                        f"could not fetch {what} {url} in {n + 1} tries: {err.why}; check the server, or raise "
                        "data.download_retries / data.download_timeout"
                    ) from None
                wait = self.settings.backoff * 2**n
                log.warning("fetching %s %s failed (%s); trying again in %.1f s", what, url, err.why, wait)
                time.sleep(wait)

    def _get(self, url: str, what: str, headers: dict[str, str] | None = None) -> Any:
        """A streaming GET; a failure another try may mend raises :class:`_Retry`, a final answer the one-line
        error."""
        import requests

        timeout = self.settings.timeout
        try:
            response = self.session().get(url, headers=headers, stream=True, timeout=(timeout, timeout))
        except requests.RequestException as err:
            raise _Retry(_why(err, timeout)) from None
        if response.status_code in RETRY_STATUS:
            response.close()
            raise _Retry(f"HTTP {response.status_code}")
        if response.status_code >= 400 and response.status_code != 416:
            response.close()
            raise self._final(response.status_code, what, url)
        return response

    # ------------------------------------------------------------------------------------------- manifest

    def open(self) -> Path:
        """Fetch the manifest into the cache (whole, then renamed into place) and return the cache folder."""
        url = f"{self.url}/manifest.json"

        def attempt() -> bytes:
            import requests

            with self._get(url, MANIFEST) as response:
                try:
                    return response.content
                except requests.RequestException as err:
                    raise _Retry(_why(err, self.settings.timeout)) from None

        data = self._tries(MANIFEST, url, attempt)
        self.cache.mkdir(parents=True, exist_ok=True)
        atomic_write(self.cache / "manifest.json", lambda f: f.write(data))
        manifest = read_manifest(self.cache)
        self.expected = {f"{name}/{s.shard}": s.sha256 for name, split in manifest.splits.items()
                         for s in split.shards}  # fmt: skip
        _MANIFESTS[self.url] = self.cache
        return self.cache

    # ------------------------------------------------------------------------------------------- shards

    def fetch(self, path: str | Path) -> str:
        """The local path of shard ``path`` (a path in the cache folder), downloaded and verified first unless
        a verified copy is there already."""
        path = Path(path)
        name = path.relative_to(self.cache).as_posix()
        if name not in self.expected:
            raise FetchError(f"{name} is not listed in {self.url}/manifest.json")
        want = self.expected[name]
        if not want:
            raise FetchError(f"{self.url}/manifest.json lists {name} without a sha256, which a shard fetched "
                             "from a server is checked against: convert the shards again with "
                             "data_prep/to_shards.py")  # fmt: skip
        if _verified(path, want):
            return str(path)
        try:
            with _locked(path.with_name(path.name + ".lock")):
                if not _verified(path, want):  # another process may have fetched it meanwhile
                    self._download(name, path, want)
        except OSError as err:  # the cache's disk (full, read-only, ...): one line from a worker too
            raise FetchError(f"shard {name} from {self.url}: {os_error_line(err)}") from None
        return str(path)

    def _download(self, name: str, path: Path, want: str) -> None:
        """Download shard ``name`` to ``path`` through ``path.part``, verified; a copy that does not match the
        manifest is downloaded once more from the start, then refused."""
        url = f"{self.url}/{name}"
        part = path.with_name(path.name + ".part")
        marker = path.with_name(path.name + ".sha256")
        marker.unlink(missing_ok=True)
        if path.exists():  # a copy without a marker that matches: check its bytes once
            if sha256(path) == want:
                atomic_write(marker, lambda f: f.write(f"{want} {path.stat().st_size}\n".encode()))
                return
            path.unlink()
        for attempt in (1, 2):
            start = time.monotonic()
            size = self._tries(f"shard {name}", url, lambda: self._resume(url, f"shard {name}", part))
            got = sha256(part)
            if got == want:
                break
            part.unlink()
            if attempt == 2:
                raise FetchError(
                    f"shard {name} fetched from {url} does not match the manifest (SHA-256 {got[:12]}…, the "
                    f"manifest says {want[:12]}…), twice: the server holds other bytes than its manifest.json "
                    "lists; upload the shards and the manifest of one conversion"
                )
            log.warning("shard %s from %s does not match the manifest's SHA-256: fetching it again", name, url)
        os.replace(part, path)
        atomic_write(marker, lambda f: f.write(f"{want} {size}\n".encode()))
        seconds = max(time.monotonic() - start, 1e-6)
        log.info("fetched shard %s (%.1f MB, %.1f MB/s) into %s", name, size / 1e6, size / 1e6 / seconds,
                 self.cache)  # fmt: skip

    def _resume(self, url: str, what: str, part: Path) -> int:
        """One try: append to ``part`` from its current size (a Range request) to the end of the file; the
        file's size. A cut connection or a short body raises :class:`_Retry` (the bytes so far are kept)."""
        import requests
        import urllib3

        offset = part.stat().st_size if part.exists() else 0
        headers = {"Accept-Encoding": "identity"}  # the file's own bytes: what Range and the SHA-256 count
        if offset:
            headers["Range"] = f"bytes={offset}-"
        with self._get(url, what, headers) as response:
            if response.status_code == 416:  # the part is as long as the file or longer: start again
                part.unlink()
                raise _Retry("the partial download was not shorter than the file (HTTP 416)")
            if response.status_code == 206:
                total = int(response.headers.get("Content-Range", "*/-1").rsplit("/", 1)[-1] or -1)
                mode = "ab"
            else:  # 200: the whole file (a server that ignores Range included)
                total, offset, mode = int(response.headers.get("Content-Length", -1)), 0, "wb"
            written = offset
            with open(part, mode) as f:
                try:  # each read returns what has come (up to CHUNK): a cut loses nothing that arrived
                    while block := response.raw.read1(CHUNK):
                        f.write(block)
                        written += len(block)
                except (requests.RequestException, urllib3.exceptions.HTTPError) as err:
                    raise _Retry(_why(err, self.settings.timeout)) from None
        if total >= 0 and written != total:
            raise _Retry(f"the connection ended after {written} of {total} bytes")
        return written


def manifest_folder(url: str) -> Path:
    """The folder holding the manifest at ``url`` as this process fetched it: the cache of the last
    :class:`RemoteShards` of that URL opened here, else (the checks before a run) a temporary folder holding
    only the manifest, removed when the process ends."""
    url = check_url(url)
    if url not in _MANIFESTS:
        folder = Path(tempfile.mkdtemp(prefix="aesplat-manifest-"))
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        RemoteShards(url, folder).open()
    return _MANIFESTS[url]


def _why(err: Exception, timeout: float) -> str:
    """A request's failure in a few words (never its headers)."""
    text = str(err)
    if "timed out" in text.lower() or "timeout" in type(err).__name__.lower():
        return f"no answer or data for {timeout:g} s (data.download_timeout)"
    if "Connection refused" in text:
        return "the connection was refused"
    if "IncompleteRead" in text or "prematurely" in text or "Connection broken" in text:
        return "the connection was cut"
    return f"the connection failed ({type(err).__name__})"


def _verified(path: Path, want: str) -> bool:
    """Whether ``path`` was verified against SHA-256 ``want`` (its marker says so) and still has that size."""
    marker = path.with_name(path.name + ".sha256")
    try:
        digest, size = marker.read_text().split()
        return digest == want and path.stat().st_size == int(size)
    except (OSError, ValueError):
        return False


@contextmanager
def _locked(lock: Path):
    """Hold an exclusive ``flock`` on ``lock`` (created if missing) while the block runs."""
    lock.parent.mkdir(parents=True, exist_ok=True)
    with open(lock, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
