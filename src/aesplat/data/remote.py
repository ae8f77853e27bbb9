"""Shards behind an http(s) URL, read through a node-local cache (docs/data.md, "Data on a server").

``data.root`` may be the URL of a shard folder (the one holding ``manifest.json``). Everything the server sends
is untrusted: the manifest is held to the converter's names, digests and sizes when it is read
(:func:`aesplat.data.manifest.parse_manifest`), a download to the size the manifest lists, every transfer to
a deadline, and a shard is used only once its bytes match the manifest's SHA-256.

The cache (``data.cache_dir``) is one user's: created 0700, its owner checked before use, never entered
through a symbolic link it did not name itself, its files 0600::

    CACHE/sets/<URL and manifest digest>/manifest.json   the listing of one data set, as the server sent it
    CACHE/shards/<SHA-256>.tar                            a verified shard, named by its content
    CACHE/shards/<SHA-256>.tar.part                       a download under way (resumed with a Range request)
    CACHE/shards/<SHA-256>.tar.lock                       held (``flock``) by the process downloading it

A shard is renamed into ``shards/`` only after its SHA-256 matched, so in a cache only this user can write its
presence proves it; where others can write the cache, each process hashes a shard before it uses it. Two data
sets, or two versions of one, never share a listing, and share the shards they have in common. Nothing is
ever evicted.

Credentials come from the environment only (never from the configuration, so they are never saved with a
run): a bearer token in ``AESPLAT_DATA_TOKEN``, or ``AESPLAT_DATA_USER`` and ``AESPLAT_DATA_PASSWORD`` for basic
authentication. They are not sent over plain http to another machine unless ``AESPLAT_DATA_INSECURE_HTTP=1``
says to. Every failure is one line (:class:`FetchError`) naming the file and its URL, never the credentials.
"""

from __future__ import annotations

import atexit
import errno
import fcntl
import functools
import hashlib
import ipaddress
import logging
import os
import re
import shutil
import socket
import stat
import tempfile
import threading
import time
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ..errors import UserError, os_error_line
from ..files import atomic_write
from .manifest import Manifest, ShardRecord, parse_manifest, sha256

log = logging.getLogger("aesplat.data")

SCHEMES = ("http", "https")
TOKEN_ENV = "AESPLAT_DATA_TOKEN"
USER_ENV = "AESPLAT_DATA_USER"
PASSWORD_ENV = "AESPLAT_DATA_PASSWORD"
INSECURE_ENV = "AESPLAT_DATA_INSECURE_HTTP"
RETRY_STATUS = {408, 425, 429, 500, 502, 503, 504}  # answers worth asking again; other errors are final
CHUNK = 1 << 20
MANIFEST_MAX_BYTES = 64 << 20  # a manifest of RealEstate10K's 67k scenes is about 5 MB
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
    query in the URL (they would be saved with the run's configuration), no host, a port outside 1-65535."""
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
    try:
        port = parts.port
    except ValueError:  # not a number, or above 65535
        port = 0
    if port == 0:
        raise UserError(f"data.root {url}: the port must be a number from 1 to 65535")
    return url.rstrip("/")


def loopback(host: str) -> bool:
    """Whether ``host`` is this machine (``localhost``, 127.0.0.0/8, ``::1``): nothing sent there crosses a
    network."""
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def credentials(url: str) -> str | None:
    """What would authenticate a request to ``url`` (named, never shown): the environment's token, user and
    password, or a ``~/.netrc`` entry for its host; None without any."""
    if os.environ.get(TOKEN_ENV):
        return f"the token in {TOKEN_ENV}"
    if os.environ.get(USER_ENV):
        return f"the password in {PASSWORD_ENV}"
    from requests.utils import get_netrc_auth

    return "a password from ~/.netrc" if get_netrc_auth(url) else None


def check_transport(url: str) -> None:
    """Refuse to send credentials over plain http to another machine, where anyone on the path reads them,
    unless ``AESPLAT_DATA_INSECURE_HTTP=1`` asks for it."""
    parts = urlsplit(url)
    if parts.scheme != "http" or loopback(parts.hostname or "") or os.environ.get(INSECURE_ENV) == "1":
        return
    given = credentials(url)
    if given:
        raise UserError(
            f"data.root {url}: {given} would go over plain http to {parts.hostname}, readable by anyone on the "
            f"network path: give the https:// URL, or set {INSECURE_ENV}=1 to send it over http knowingly"
        )


def default_cache() -> Path:
    """``$TMPDIR/aesplat-shards-<user id>`` (``/tmp`` without ``TMPDIR``): node-local on a cluster, and one per
    user, since a cache is checked to be its user's own."""
    return Path(os.environ.get("TMPDIR") or "/tmp") / f"aesplat-shards-{os.geteuid()}"


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v  # not NaN


# The download settings' ranges: setting -> (test, what it must be); refused in one line when a DataModule is
# built, and by ``aesplat.config_checks`` before a command writes anything.
DOWNLOAD_RANGES = {
    "download_retries": (lambda v: _number(v) and isinstance(v, int) and 0 <= v <= 100, "0 to 100 tries"),
    "download_timeout": (lambda v: _number(v) and 0 < v <= 86400, "more than 0 and at most 86400 seconds"),
    "download_backoff": (lambda v: _number(v) and 0 <= v <= 3600, "0 to 3600 seconds"),
}


@dataclass(frozen=True)
class DownloadSettings:
    """How hard a download tries: ``retries`` more tries after a failure that may pass (a cut or refused
    connection, a timeout, HTTP 5xx or 429), the first ``backoff`` seconds after the first failure and
    doubling; ``timeout`` seconds to connect, at most between two pieces of data, and for each try as a whole
    ``timeout`` seconds plus ``timeout`` for each megabyte received (so a file must come at 1 MB per
    ``timeout`` on average: a server that trickles bytes cannot hold a run)."""

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

    def longest(self, size: int) -> float:
        """The longest a download of ``size`` bytes takes with these settings: every try to its deadline (an
        answer within twice ``timeout``, then the body's), every wait between tries, and all of it twice (a copy
        that does not match is fetched once more)."""
        tries = self.retries + 1
        return 2 * (tries * self.timeout * (3 + size / 1e6) + self.backoff * (2**tries - 1))

    def overdue(self, start: float, received: int) -> bool:
        """Whether a try that began at ``start`` (``time.monotonic``) and has received ``received`` bytes has
        run past its deadline."""
        return time.monotonic() - start > self.timeout * (1 + received / 1e6)


class _Retry(Exception):
    """A failure another try may mend; ``why`` says it in a few words."""

    def __init__(self, why: str) -> None:
        super().__init__(why)
        self.why = why


class RemoteShards:
    """The shard folder at ``url``, mirrored on demand in the cache folder ``cache`` (:func:`default_cache`
    when None).

    :meth:`open` takes the manifest (:meth:`fetch_manifest`, or bytes another rank fetched) and returns the
    folder of its listing, which the data code reads as a shard folder whose shards are fetched when read;
    :meth:`fetch` makes one shard of it present and verified and returns its path. An instance travels to the
    DataLoader workers (pickled), each of which opens its own HTTP session."""

    def __init__(self, url: str, cache: str | Path | None = None, settings: DownloadSettings | None = None):
        self.url = check_url(url)
        check_transport(self.url)
        self.cache = Path(cache) if cache else default_cache()
        self.named_cache = cache is not None  # a folder the user named: links to it are the user's own
        self.settings = settings or DownloadSettings()
        self.settings.check()
        self.listed: dict[str, ShardRecord] = {}  # "split/shard" -> its record, from the manifest
        self.folder: Path | None = None  # the listing's folder, once opened
        self.shards: Path | None = None  # the cache's folder of verified shards
        self.private = True  # only this user can write the cache: a shard there is as it was verified
        self._hashed: set[str] = set()  # shards this process hashed in a cache others can write
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
            adapter = _watched_adapter()
            session.mount("http://", adapter)
            session.mount("https://", adapter)
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
        """A streaming GET answered 200, 206 or 416; a failure another try may mend raises :class:`_Retry`,
        any other the one-line error."""
        import requests

        timeout = self.settings.timeout
        no_answer = f"no answer within {2 * timeout:g} s (twice data.download_timeout)"
        with _answer_within(2 * timeout) as late:
            try:
                response = self.session().get(url, headers=headers, stream=True, timeout=(timeout, timeout))
            except requests.RequestException as err:
                final = _final_failure(err)
                if final:
                    raise FetchError(f"{what} {url}: {final}") from None
                if late:
                    raise _Retry(no_answer) from None
                raise _Retry(_why(err, timeout)) from None
        if late:  # cut in its headers: what came is not the answer
            response.close()
            raise _Retry(no_answer)
        if response.status_code in RETRY_STATUS:
            response.close()
            raise _Retry(f"HTTP {response.status_code}")
        if response.status_code not in (200, 206, 416):
            response.close()
            raise self._final(response.status_code, what, url)
        return response

    def _read(self, response: Any, start: float, received: int, out, limit: int, too_long) -> int:
        """Pass ``response``'s body to ``out`` as it comes, ``received`` bytes counted already: at most
        ``limit`` of them (past it, ``too_long()`` is raised), within the deadline; the count at the end."""
        import requests
        import urllib3

        while True:
            try:  # each read returns what has come (up to CHUNK): a cut loses nothing that arrived
                block = response.raw.read1(CHUNK)
            except (requests.RequestException, urllib3.exceptions.HTTPError, OSError) as err:
                raise _Retry(_why(err, self.settings.timeout)) from None
            if not block:
                return received
            if received + len(block) > limit:
                raise too_long()
            out(block)  # an error of the cache's disk is not the server's: not retried
            received += len(block)
            if self.settings.overdue(start, received):
                raise _Retry(f"the transfer was slower than 1 MB per {self.settings.timeout:g} s "
                             "(data.download_timeout)")  # fmt: skip

    # ------------------------------------------------------------------------------------------- manifest

    def fetch_manifest(self) -> bytes:
        """The manifest's bytes, as the server sends them (at most :data:`MANIFEST_MAX_BYTES`)."""
        url = f"{self.url}/manifest.json"

        def too_long() -> FetchError:
            return FetchError(f"{MANIFEST} {url} is larger than {MANIFEST_MAX_BYTES >> 20} MiB, far more than "
                              "a manifest of data_prep/to_shards.py holds: check data.root")  # fmt: skip

        def attempt() -> bytes:
            start, body = time.monotonic(), bytearray()
            with self._get(url, MANIFEST) as response:
                if response.status_code != 200:
                    raise self._final(response.status_code, MANIFEST, url)
                expected = _length(response.headers.get("Content-Length"))
                if expected > MANIFEST_MAX_BYTES:
                    raise too_long()
                size = self._read(response, start, 0, body.extend, MANIFEST_MAX_BYTES, too_long)
                if 0 <= expected != size:
                    raise _Retry(f"the connection ended after {size} of {expected} bytes")
            return bytes(body)

        return self._tries(MANIFEST, url, attempt)

    def parse(self, data: bytes) -> Manifest:
        """The manifest ``data`` (:meth:`fetch_manifest`'s), checked: names, digests and sizes as the
        converter writes them, and a SHA-256 and a size for every shard, which its download is held to."""
        url = f"{self.url}/manifest.json"

        def damaged(why: str) -> FetchError:
            return FetchError(f"{MANIFEST} {url} is damaged ({why}): the server must hold the manifest.json "
                              "data_prep/to_shards.py wrote beside its shards")  # fmt: skip

        manifest = parse_manifest(data, url, damaged)
        for name, split in manifest.splits.items():
            for s in split.shards:
                if not s.sha256 or s.size is None:
                    raise FetchError(
                        f"{url} lists {name}/{s.shard} without its sha256 and size (bytes), which a shard "
                        "fetched from a server is held to: convert the shards again with "
                        "data_prep/to_shards.py (finished shards are kept) and upload its manifest.json"
                    )
        return manifest

    def open(self, data: bytes | None = None) -> Path:
        """Take the manifest ``data`` (None: fetch it now), check it, keep it in the cache under its URL and
        digest, and return that folder (a shard folder whose shards :meth:`fetch` brings)."""
        data = self.fetch_manifest() if data is None else data
        manifest = self.parse(data)
        digest = hashlib.sha256(data).hexdigest()
        key = hashlib.sha256(f"{self.url}\n{digest}".encode()).hexdigest()[:32]
        try:
            self._prepare_cache()
            folder = self.cache / "sets" / key
            _own_folder(folder, "the cache")
            if not (folder / "manifest.json").is_file():
                atomic_write(folder / "manifest.json", lambda f: f.write(data), mode=0o600)
        except OSError as err:
            raise FetchError(f"{MANIFEST} of {self.url}: {os_error_line(err)}") from None
        self.listed = {f"{name}/{s.shard}": s for name, split in manifest.splits.items() for s in split.shards}
        self.folder = folder
        _MANIFESTS[self.url] = folder
        return folder

    # ------------------------------------------------------------------------------------------- cache

    def _prepare_cache(self) -> None:
        """Make or check the cache folder and its ``sets/`` and ``shards/`` (one line for one that is not this
        user's own); warn once where other users can write it, whose shards are then hashed before use."""
        if self.named_cache:  # the user's own links (a scratch folder, say) lead where they meant
            self.cache = Path(os.path.realpath(self.cache))
        base = self.cache
        base.parent.mkdir(parents=True, exist_ok=True)
        self.private = _own_folder(base, "data.cache_dir" if self.named_cache else "the default cache")
        self.shards = base / "shards"
        for folder in (base / "sets", self.shards):
            self.private = _own_folder(folder, "the cache") and self.private
        if not self.private:
            mode = stat.S_IMODE(os.lstat(base).st_mode)
            log.warning("the cache %s can be written by other users (mode %o): each process hashes every shard "
                        "before it uses it; give data.cache_dir a folder only you can write to skip that", base,
                        mode)  # fmt: skip

    # ------------------------------------------------------------------------------------------- shards

    def fetch(self, path: str | Path) -> str:
        """The local path of shard ``path`` (a path in the listing's folder), downloaded and verified first
        unless a verified copy is in the cache already."""
        path = Path(path)
        name = path.relative_to(self.folder).as_posix() if self.folder in path.parents else str(path)
        record = self.listed.get(name)
        if record is None:
            raise FetchError(f"{name} is not listed in {self.url}/manifest.json")
        target = self.shards / f"{record.sha256}.tar"
        try:
            if self._ready(target, record):
                return str(target)
            with _locked(target.with_name(target.name + ".lock"), self.settings.longest(record.size)):
                if not self._ready(target, record):  # another process may have fetched it meanwhile
                    self._download(name, record, target)
        except OSError as err:  # the cache's disk (full, read-only, ...): one line from a worker too
            raise FetchError(f"shard {name} from {self.url}: {os_error_line(err)}") from None
        return str(target)

    def _ready(self, target: Path, record: ShardRecord) -> bool:
        """Whether ``target`` holds the shard ``record`` lists: a plain file of its size which, in a cache
        others can write, this process has hashed."""
        try:
            st = os.lstat(target)
        except FileNotFoundError:
            return False
        if not stat.S_ISREG(st.st_mode) or st.st_size != record.size:
            return False
        if self.private or record.sha256 in self._hashed:
            return True
        if sha256(target, follow_links=False) != record.sha256:
            return False
        self._hashed.add(record.sha256)
        return True

    def _download(self, name: str, record: ShardRecord, target: Path) -> None:
        """Download shard ``name`` to ``target`` through ``target.part``, verified; a copy that does not match
        the manifest is downloaded once more from the start, then refused."""
        url = f"{self.url}/{name}"
        part = target.with_name(target.name + ".part")
        if os.path.lexists(target):  # not what the manifest lists (another size, a link): replaced
            target.unlink()
        for attempt in (1, 2):
            start = time.monotonic()
            try:
                self._tries(f"shard {name}", url, lambda: self._resume(url, name, part, record.size))
            except FetchError:  # final: what it holds is of no use to a later try
                part.unlink(missing_ok=True)
                raise
            got = sha256(part, follow_links=False)
            if got == record.sha256:
                break
            part.unlink()
            if attempt == 2:
                raise FetchError(
                    f"shard {name} fetched from {url} does not match the manifest (SHA-256 {got[:12]}…, the "
                    f"manifest says {record.sha256[:12]}…), twice: the server holds other bytes than its "
                    "manifest.json lists; upload the shards and the manifest of one conversion"
                )
            log.warning("shard %s from %s does not match the manifest's SHA-256: fetching it again", name, url)
        os.replace(part, target)
        seconds = max(time.monotonic() - start, 1e-6)
        log.info("fetched shard %s (%.1f MB, %.1f MB/s) into %s", name, record.size / 1e6,
                 record.size / 1e6 / seconds, self.cache)  # fmt: skip

    def _resume(self, url: str, name: str, part: Path, size: int) -> None:
        """One try: append to ``part`` from its current size (a Range request) up to the ``size`` bytes the
        manifest lists. A cut connection, a short body or a missed deadline raises :class:`_Retry` (the bytes
        so far are kept); a server that sends another size than the manifest lists, the one-line error."""
        what = f"shard {name}"
        if os.path.islink(part):  # planted where others can write the cache: removed, never followed
            part.unlink()
        fd = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
        with os.fdopen(fd, "wb") as f:
            offset = os.fstat(fd).st_size
            if offset > size:
                offset = 0
            if offset == size and size:  # a previous try wrote it whole, then stopped before its check
                return
            headers = {"Accept-Encoding": "identity"}  # the file's own bytes: what Range and the SHA-256 count
            if offset:
                headers["Range"] = f"bytes={offset}-"
            start = time.monotonic()
            with self._get(url, what, headers) as response:
                total = -1
                if response.status_code == 416:  # the part is not shorter than the file: start again
                    os.ftruncate(fd, 0)
                    raise _Retry("the partial download was not shorter than the file (HTTP 416)")
                if response.status_code == 206:
                    first, total = _content_range(response.headers.get("Content-Range"))
                    if first != offset:  # another range than asked for (or none that can be read)
                        os.ftruncate(fd, 0)
                        raise _Retry("the server answered the Range request with other bytes; starting again")
                else:  # 200: the whole file (a server that ignores Range included)
                    offset, total = 0, _length(response.headers.get("Content-Length"))
                if total >= 0 and total != size:
                    raise FetchError(
                        f"{what} {url}: the server holds {total} bytes, the manifest lists {size}: upload the "
                        "shards and the manifest of one conversion"
                    )
                os.ftruncate(fd, offset)
                f.seek(offset)

                def too_long() -> FetchError:
                    return FetchError(f"{what} {url}: the server sent more than the {size} bytes the "
                                      "manifest lists: upload the shards and the manifest of one "
                                      "conversion")  # fmt: skip

                try:
                    written = self._read(response, start, offset, f.write, size, too_long)
                finally:
                    f.flush()
            if written != size:
                raise _Retry(f"the connection ended after {written} of {size} bytes")


_ANSWERING = threading.local()  # .sockets: those of the request this thread waits on for an answer


@contextmanager
def _answer_within(seconds: float):
    """Shut down the connection of the request made in the block if its answer (status and headers) has not
    come within ``seconds``: a server that sends its headers a byte at a time cannot hold a try, which the
    timeout of each read alone would let it. Yields a list that holds True once that happened."""
    sockets: list = []
    late: list[bool] = []

    def expire() -> None:
        late.append(True)
        for sock in sockets:
            with suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    _ANSWERING.sockets = sockets
    timer = threading.Timer(seconds, expire)
    timer.daemon = True
    timer.start()
    try:
        yield late
    finally:
        timer.cancel()
        _ANSWERING.sockets = None


@functools.cache
def _watched_pools() -> dict[str, type]:
    """urllib3's connection pools, their connections telling :func:`_answer_within` the socket a request waits
    on for its answer."""
    from urllib3.connectionpool import HTTPConnectionPool, HTTPSConnectionPool

    def watched(pool: type) -> type:
        class Connection(pool.ConnectionCls):
            def getresponse(self, *args, **kwargs):
                sockets = getattr(_ANSWERING, "sockets", None)
                if sockets is not None and self.sock is not None:
                    sockets.append(self.sock)
                return super().getresponse(*args, **kwargs)

        return type(pool.__name__, (pool,), {"ConnectionCls": Connection})

    return {"http": watched(HTTPConnectionPool), "https": watched(HTTPSConnectionPool)}


def _watched_adapter() -> Any:
    """A requests adapter whose connections :func:`_answer_within` watches."""
    from requests.adapters import HTTPAdapter

    adapter = HTTPAdapter()
    adapter.poolmanager.pool_classes_by_scheme = _watched_pools()
    return adapter


def manifest_folder(url: str) -> Path:
    """The folder holding the manifest at ``url`` as this process fetched it: the listing of the last
    :class:`RemoteShards` of that URL opened here, else (the checks before a run) a temporary folder holding
    only the manifest, removed when the process ends."""
    url = check_url(url)
    if url not in _MANIFESTS:
        folder = Path(tempfile.mkdtemp(prefix="aesplat-manifest-"))
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        RemoteShards(url, folder).open()
    return _MANIFESTS[url]


def _length(value: str | None) -> int:
    """A ``Content-Length`` header's number, or -1 when there is none or it is not one."""
    value = (value or "").strip()
    return int(value) if value.isascii() and value.isdigit() and len(value) < 19 else -1


def _content_range(value: str | None) -> tuple[int, int]:
    """A ``Content-Range: bytes FIRST-LAST/TOTAL`` header's first byte and total (-1 for ``*``); (-1, -1)
    when there is none or it is not one."""
    match = re.fullmatch(r"bytes (\d+)-(\d+)/(\d+|\*)", (value or "").strip())
    if not match:
        return -1, -1
    return int(match[1]), -1 if match[3] == "*" else int(match[3])


def _final_failure(err: Exception) -> str | None:
    """What makes a failed request one that no retry mends, in a few words (a refused certificate, a name no
    DNS server knows, a redirect to a URL that is not http(s)); None for the others."""
    import requests

    text = str(err)
    if isinstance(err, requests.exceptions.SSLError):
        found = re.search(r"certificate verify failed: ([^()'\"]+)", text)
        reason = found[1].strip() if found else "the TLS handshake failed"
        return (f"the server's certificate was refused ({reason}); if a private certificate authority signed "
                "it, name that authority's certificate file in REQUESTS_CA_BUNDLE")  # fmt: skip
    if isinstance(err, (requests.exceptions.InvalidSchema, requests.exceptions.MissingSchema)):
        return "the server redirected to a URL that is not http(s), which is not followed"
    if isinstance(err, (requests.exceptions.InvalidURL, requests.exceptions.TooManyRedirects)):
        return f"the server's redirects cannot be followed ({type(err).__name__})"
    if "Name or service not known" in text or "No address associated with hostname" in text:
        return "the host name is not known to the DNS (check data.root)"
    return None


def _why(err: Exception, timeout: float) -> str:
    """A request's failure that another try may mend, in a few words (never its headers)."""
    text = str(err)
    if "timed out" in text.lower() or "timeout" in type(err).__name__.lower():
        return f"no answer or data for {timeout:g} s (data.download_timeout)"
    if "Connection refused" in text:
        return "the connection was refused"
    if "IncompleteRead" in text or "prematurely" in text or "Connection broken" in text:
        return "the connection was cut"
    if "Temporary failure in name resolution" in text:
        return "the DNS did not answer"
    return f"the connection failed ({type(err).__name__})"


def _owner(uid: int) -> str:
    import pwd

    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


def _own_folder(folder: Path, named: str) -> bool:
    """Make ``folder`` (0700) when missing, or check the one there: one line (:class:`UserError`) when it is a
    link, not a folder, or another user's (shards planted there would be read as verified). Whether only this
    user can write it."""
    try:
        os.mkdir(folder, 0o700)
    except FileExistsError:
        pass
    st = os.lstat(folder)
    if stat.S_ISLNK(st.st_mode):
        raise UserError(f"{named} {folder} is a symbolic link, which this cache never follows (another user "
                        "can plant one): remove it, or set data.cache_dir to a folder of yours")  # fmt: skip
    if not stat.S_ISDIR(st.st_mode):
        raise UserError(
            f"{named} {folder} is not a folder: remove it, or set data.cache_dir to a folder of yours"
        )
    if st.st_uid != os.geteuid():
        raise UserError(
            f"{named} {folder} belongs to {_owner(st.st_uid)}, not to you: shards another user put there would "
            "be read as yours; set data.cache_dir to a folder of your own"
        )
    return not stat.S_IMODE(st.st_mode) & 0o022


@contextmanager
def _locked(lock: Path, seconds: float):
    """Hold an exclusive ``flock`` on ``lock`` (created 0600 if missing, never through a link) while the block
    runs; waiting for it at most ``seconds`` (longer than the download its holder makes may take: a holder
    that is frozen, or another user's, cannot hold a run)."""
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise FetchError(f"{lock} is a symbolic link, which this cache never follows: remove it") from None
        raise
    try:
        deadline = time.monotonic() + seconds
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise FetchError(
                        f"another process has held {lock} for {seconds:.1f} s, longer than its download can "
                        "take: end it (a frozen aesplat, say), or give data.cache_dir a folder of your own"
                    ) from None
                time.sleep(min(0.2, seconds / 10))
        yield
    finally:
        os.close(fd)
