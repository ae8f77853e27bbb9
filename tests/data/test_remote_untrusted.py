"""Shards behind a URL, tried as an attacker or a broken server would (aesplat.data.remote): what a server sends
(names, digests, sizes, headers, time), the cache another user of the node can reach, credentials on the wire,
and the ranks of one run reading one data set. Each case ends in the right data or one line, never in a file
written outside the cache, a traceback, a hang or a run on other data than it says."""

from __future__ import annotations

import logging
import os
import shutil
import socket
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from aesplat import cli
from aesplat.data import DataModule
from aesplat.data.manifest import sha256
from aesplat.data.remote import DownloadSettings, FetchError, RemoteShards
from aesplat.errors import UserError
from tests.data.servers import (
    FAST,
    LOADER,
    FaultServer,
    cached,
    edit_manifest,
    endless,
    headers,
    logged,
    manifest_of,
    once,
    record,
    self_signed,
    trickle,
    write_manifest,
)
from tests.helpers import aesplat, common, need, one_line, tree

ONE_TRY = DownloadSettings(retries=0, timeout=5.0, backoff=0.0)


def refusal(server, tmp_path: Path) -> str:
    """The one line that opening ``server``'s data stops with."""
    with pytest.raises(FetchError) as err:
        RemoteShards(server.url, tmp_path / "cache", FAST).open()
    return one_line(str(err.value))


@pytest.fixture
def folder(served, tmp_path):
    """A copy of ``served`` that a test may change, for a :class:`FaultServer`."""
    return shutil.copytree(served, tmp_path / "root")


# ----------------------------------------------------------------------------------------------- names


@pytest.mark.parametrize(
    "split, shard",
    [
        ("test", "../../../victim/notes.txt"),
        ("test", "/tmp/elsewhere.tar"),
        ("test", "sub/test-000000.tar"),
        ("test", ".hidden.tar"),
        ("test", "test-000000.tar\naesplat fit: done"),
        ("..", "test-000000.tar"),
        ("a/b", "test-000000.tar"),
    ],
)
def test_a_manifest_naming_a_file_outside_the_cache_is_refused_when_read(
    split, shard, server, tmp_path, capsys
):
    manifest = manifest_of(server.root)
    entry = manifest["splits"].pop("test")
    entry["shards"][0]["shard"] = shard
    manifest["splits"][split] = entry
    write_manifest(server.root, manifest)
    (server.root / "victim").mkdir()  # what the URL of "../../../victim/notes.txt" comes to, normalised
    (server.root / "victim" / "notes.txt").write_text("the server's")
    victim = tmp_path / "victim" / "notes.txt"
    victim.parent.mkdir()
    victim.write_text("mine")
    cache, run_dir = tmp_path / "c" / "cache", tmp_path / "run"
    args = [*common(server.url, run_dir), "--data.cache_dir", str(cache), "--data.validate_on_test", "true"]
    code, err = aesplat(capsys, "fit", *args)
    line = one_line(err)
    assert code == 1 and line.startswith(f"aesplat fit: the manifest {server.url}/manifest.json is damaged (")
    assert line.endswith(
        "the server must hold the manifest.json data_prep/to_shards.py wrote beside its shards"
    )
    assert "\naesplat fit: done" not in err
    assert victim.read_text() == "mine" and sorted(os.listdir(victim.parent)) == ["notes.txt"]
    assert not run_dir.exists() and not (tmp_path / "elsewhere.tar").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nginx", "root", "victim"]


def test_a_digest_is_checked_when_read_and_compared_in_any_case(server, tmp_path):
    real = record(server.root, "test/test-000000.tar").sha256
    edit_manifest(server.root, "test/test-000000.tar", sha256="12345")
    assert refusal(server, tmp_path) == (
        f"the manifest {server.url}/manifest.json is damaged (split 'test': shard test-000000.tar has the "
        "sha256 '12345', not 64 hexadecimal digits): the server must hold the manifest.json "
        "data_prep/to_shards.py wrote beside its shards"
    )
    edit_manifest(server.root, "test/test-000000.tar", sha256=real)
    edit_manifest(
        server.root, "test/test-000001.tar", sha256=record(server.root, "test/test-000001.tar").sha256.upper()
    )
    remote = RemoteShards(server.url, tmp_path / "cache", FAST)
    shard = remote.open() / "test" / "test-000001.tar"
    assert Path(remote.fetch(shard)).read_bytes() == (server.root / "test" / "test-000001.tar").read_bytes()


def test_a_manifest_without_a_size_for_a_shard_is_refused_when_read(server, tmp_path):
    manifest = manifest_of(server.root)
    del manifest["splits"]["train"]["shards"][2]["bytes"]
    write_manifest(server.root, manifest)
    assert refusal(server, tmp_path) == (
        f"{server.url}/manifest.json lists train/train-000002.tar without its sha256 and size (bytes), which a "
        "shard fetched from a server is held to: convert the shards again with data_prep/to_shards.py "
        "(finished shards are kept) and upload its manifest.json"
    )


@pytest.mark.parametrize(
    "field, value, why",
    [
        ("bytes", -5, "the size '-5', not a number of bytes"),
        ("bytes", "30720", "the size '30720', not a number of bytes"),
        ("samples", "many", "a malformed count of samples"),
        ("scene_frames", {"a": "12"}, "malformed scene_frames"),
    ],
)
def test_a_malformed_count_in_a_manifest_is_one_line(field, value, why, server, tmp_path):
    edit_manifest(server.root, "train/train-000001.tar", **{field: value})
    assert f"is damaged (split 'train': shard train-000001.tar has {why})" in refusal(server, tmp_path)


# ----------------------------------------------------------------------------------------------- sizes


def test_a_shard_the_server_holds_at_another_size_is_refused_at_once(server, tmp_path):
    served = server.root / "train" / "train-000001.tar"
    listed = served.stat().st_size
    served.write_bytes(served.read_bytes() + b"\0" * 10 * listed)
    remote = RemoteShards(server.url, tmp_path / "cache", FAST)
    shard = remote.open() / "train" / "train-000001.tar"
    with pytest.raises(FetchError) as err:
        remote.fetch(shard)
    url = f"{server.url}/train/train-000001.tar"
    assert one_line(str(err.value)) == (
        f"shard train/train-000001.tar {url}: the server holds {11 * listed} bytes, the manifest lists "
        f"{listed}: upload the shards and the manifest of one conversion"
    )
    assert logged(server, ".tar") == ["/train/train-000001.tar"]  # not retried
    assert not list((tmp_path / "cache" / "shards").glob("*.tar*[!k]"))


def test_a_server_that_sends_more_than_the_listed_size_is_cut_there(folder, tmp_path):
    with FaultServer(folder) as server:
        server.faults["/train/train-000000.tar"] = endless
        remote = RemoteShards(server.url, tmp_path / "cache", FAST)
        shard = remote.open() / "train" / "train-000000.tar"
        with pytest.raises(FetchError) as err:
            remote.fetch(shard)
    listed = record(folder, "train/train-000000.tar").size
    assert one_line(str(err.value)) == (
        f"shard train/train-000000.tar {server.url}/train/train-000000.tar: the server sent more than the "
        f"{listed} bytes the manifest lists: upload the shards and the manifest of one conversion"
    )
    assert not list((tmp_path / "cache" / "shards").glob("*.tar*[!k]"))


def test_a_manifest_larger_than_any_manifest_is_refused(folder, tmp_path):
    with FaultServer(folder) as server:
        server.faults["/manifest.json"] = endless
        with pytest.raises(FetchError) as err:
            RemoteShards(server.url, tmp_path / "cache", FAST).open()
        server.faults["/manifest.json"] = headers(200, {"Content-Length": str(400 << 20)}, body=b"{}")
        with pytest.raises(FetchError) as announced:
            RemoteShards(server.url, tmp_path / "cache", FAST).open()
    line = (f"the manifest {server.url}/manifest.json is larger than 64 MiB, far more than a manifest of "
            "data_prep/to_shards.py holds: check data.root")  # fmt: skip
    assert one_line(str(err.value)) == one_line(str(announced.value)) == line
    assert server.gets("/manifest.json") == ["", ""]  # neither retried


# ----------------------------------------------------------------------------------------------- time


def _fetch_in_thread(fn) -> list:
    """Run ``fn`` in a thread, waiting at most 60 s: [result] or [exception]; [] if it is still running."""
    out: list = []

    def run() -> None:
        try:
            out.append(fn())
        except Exception as err:  # noqa: BLE001 - handed to the test
            out.append(err)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(60)
    return out


@pytest.mark.parametrize("path", ["/manifest.json", "/test/test-000000.tar"])
def test_a_server_that_trickles_bytes_cannot_hold_a_download(path, folder, tmp_path):
    """A byte every 0.05 s never leaves 0.5 s without data, so only the deadline of a whole try ends it."""
    settings = DownloadSettings(retries=1, timeout=0.5, backoff=0.0)
    with FaultServer(folder) as server:
        server.faults[path] = trickle(0.05)
        remote = RemoteShards(server.url, tmp_path / "cache", settings)
        if path == "/manifest.json":
            out = _fetch_in_thread(remote.open)
        else:
            shard = remote.open() / "test" / "test-000000.tar"
            out = _fetch_in_thread(lambda: remote.fetch(shard))
    assert len(out) == 1 and isinstance(out[0], FetchError), out
    what = "the manifest" if path == "/manifest.json" else "shard test/test-000000.tar"
    assert one_line(str(out[0])) == (
        f"could not fetch {what} {server.url}{path} in 2 tries: the transfer was slower than 1 MB per 0.5 s "
        "(data.download_timeout); check the server, or raise data.download_retries / data.download_timeout"
    )


def slow_headers(handler, data: bytes) -> None:
    """A status line, then header bytes one every 0.05 s, without end: every read gets data in time."""
    handler.wfile.write(b"HTTP/1.1 200 OK\r\n")
    while True:
        handler.wfile.write(b"X")
        handler.wfile.flush()
        time.sleep(0.05)


def test_a_server_that_sends_its_headers_a_byte_at_a_time_cannot_hold_a_try(folder, tmp_path):
    with FaultServer(folder) as server:
        server.faults["/manifest.json"] = slow_headers
        remote = RemoteShards(
            server.url, tmp_path / "cache", DownloadSettings(retries=1, timeout=0.5, backoff=0)
        )
        out = _fetch_in_thread(remote.open)
    assert len(out) == 1 and isinstance(out[0], FetchError), out
    assert one_line(str(out[0])) == (
        f"could not fetch the manifest {server.url}/manifest.json in 2 tries: no answer within 1 s (twice "
        "data.download_timeout); check the server, or raise data.download_retries / data.download_timeout"
    )


def test_a_download_lock_held_longer_than_any_download_takes_is_one_line(server, tmp_path):
    """A frozen process (or another user, in a cache others can write) holding a shard's lock."""
    import fcntl

    settings = DownloadSettings(retries=0, timeout=0.2, backoff=0.0)
    remote = RemoteShards(server.url, tmp_path / "cache", settings)
    shard = remote.open() / "test" / "test-000000.tar"
    lock = cached(tmp_path / "cache", server.root, "test/test-000000.tar").with_suffix(".tar.lock")
    with open(lock, "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        out = _fetch_in_thread(lambda: remote.fetch(shard))
    longest = settings.longest(record(server.root, "test/test-000000.tar").size)
    assert len(out) == 1 and isinstance(out[0], FetchError), out
    assert one_line(str(out[0])) == (
        f"another process has held {lock} for {longest:.1f} s, longer than its download can take: end it (a "
        "frozen aesplat, say), or give data.cache_dir a folder of your own"
    )
    assert Path(remote.fetch(shard)).read_bytes() == (server.root / "test" / "test-000000.tar").read_bytes()


# ----------------------------------------------------------------------------------------------- headers


@pytest.mark.parametrize(
    "fault",
    [
        headers(206, {"Content-Range": "bytes 0-9/*", "Content-Length": "10"}, body=b"0123456789"),
        headers(206, {"Content-Length": "5"}, body=b"01234"),  # no Content-Range
        headers(206, {"Content-Range": "bytes=100-x", "Content-Length": "5"}, body=b"01234"),
        headers(206, {"Content-Range": "bytes 5-9/40960"}, body=b"56789"),  # another range than asked for
        headers(200, {"Content-Length": "many"}),  # the whole file, its length unreadable
        headers(200, {"Content-Length": "9" * 5000}),
    ],
    ids=[
        "range-of-unknown-total",
        "range-missing",
        "range-malformed",
        "range-elsewhere",
        "length-malformed",
        "length-overlong",
    ],  # fmt: skip
)
def test_malformed_range_and_length_headers_end_in_the_right_bytes(fault, folder, tmp_path):
    path = "/train/train-000001.tar"
    whole = (folder / path[1:]).read_bytes()
    with FaultServer(folder) as server:
        server.faults[path] = once(fault)
        remote = RemoteShards(server.url, tmp_path / "cache", FAST)
        shard = remote.open() / "train" / "train-000001.tar"
        cached(tmp_path / "cache", folder, path[1:]).with_suffix(".tar.part").write_bytes(whole[:10_000])
        assert Path(remote.fetch(shard)).read_bytes() == whole


# ----------------------------------------------------------------------------------------------- failures


def test_a_refused_certificate_is_one_line_at_once_and_a_named_authority_is_trusted(folder, tmp_path, caplog,
                                                                                     monkeypatch):  # fmt: skip
    need(shutil.which("openssl") is not None, "openssl")
    cert, key = self_signed(tmp_path)
    monkeypatch.delenv("REQUESTS_CA_BUNDLE", raising=False)
    with FaultServer(folder, tls=(cert, key)) as server, caplog.at_level(logging.WARNING, "aesplat.data"):
        with pytest.raises(FetchError) as err:
            RemoteShards(server.url, tmp_path / "cache", DownloadSettings(5, 5.0, 1.0)).open()
        assert one_line(str(err.value)) == (
            f"the manifest {server.url}/manifest.json: the server's certificate was refused (self-signed "
            "certificate); if a private certificate authority signed it, name that authority's certificate "
            "file in REQUESTS_CA_BUNDLE"
        )
        assert not caplog.records  # no "trying again"
        monkeypatch.setenv("REQUESTS_CA_BUNDLE", str(cert))
        remote = RemoteShards(server.url, tmp_path / "cache", FAST)
        shard = remote.open() / "test" / "test-000000.tar"
        assert Path(remote.fetch(shard)).read_bytes() == (folder / "test" / "test-000000.tar").read_bytes()


@pytest.mark.parametrize("location", ["file:///etc/passwd", "gopher://127.0.0.1/x"])
def test_a_redirect_to_another_scheme_is_one_line_at_once(location, folder, tmp_path):
    with FaultServer(folder) as server:
        server.faults["/manifest.json"] = headers(302, {"Location": location, "Content-Length": "0"}, b"")
        with pytest.raises(FetchError) as err:
            RemoteShards(server.url, tmp_path / "cache", DownloadSettings(5, 5.0, 1.0)).open()
    assert one_line(str(err.value)) == (
        f"the manifest {server.url}/manifest.json: the server redirected to a URL that is not http(s), which "
        "is not followed"
    )
    assert server.gets("/manifest.json") == [""]


def test_a_host_the_dns_does_not_know_is_one_line_at_once(tmp_path, caplog):
    host = "no-such-host.invalid"  # a name no DNS server holds (RFC 2606)
    try:
        socket.getaddrinfo(host, 80)
    except socket.gaierror as err:
        if err.errno != socket.EAI_NONAME:
            pytest.skip(f"this machine's DNS does not answer ({err})")
    with caplog.at_level(logging.WARNING, "aesplat.data"), pytest.raises(FetchError) as err:
        RemoteShards(f"https://{host}/shards", tmp_path / "cache", DownloadSettings(5, 5.0, 1.0)).open()
    assert one_line(str(err.value)) == (
        f"the manifest https://{host}/shards/manifest.json: the host name is not known to the DNS (check "
        "data.root)"
    )
    assert not caplog.records  # no "trying again"


@pytest.mark.parametrize("root", ["http://127.0.0.1:99999/shards", "http://127.0.0.1:0/shards",
                                  "http://127.0.0.1:http/shards"])  # fmt: skip
def test_a_port_that_cannot_be_reached_is_refused_before_anything(root, capsys, tmp_path):
    with pytest.raises(UserError, match="the port must be a number from 1 to 65535"):
        DataModule(root=root)
    code, err = aesplat(capsys, "fit", *common(root, tmp_path / "run"))
    assert code == 1 and one_line(err) == (
        f"aesplat fit: data.root {root}: the port must be a number from 1 to 65535"
    )


# ----------------------------------------------------------------------------------------------- credentials


@pytest.mark.parametrize("given", ["token", "user", "netrc"])
def test_credentials_never_go_over_plain_http_to_another_machine_unasked(given, monkeypatch, capsys, tmp_path):
    for name in (
        "AESPLAT_DATA_TOKEN",
        "AESPLAT_DATA_USER",
        "AESPLAT_DATA_PASSWORD",
        "AESPLAT_DATA_INSECURE_HTTP",
    ):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.delenv("NETRC", raising=False)
    url = "http://data.example.org/shards"
    words = {"token": "the token in AESPLAT_DATA_TOKEN", "user": "the password in AESPLAT_DATA_PASSWORD",
             "netrc": "a password from ~/.netrc"}[given]  # fmt: skip
    if given == "token":
        monkeypatch.setenv("AESPLAT_DATA_TOKEN", "s3cret-token")
    elif given == "user":
        monkeypatch.setenv("AESPLAT_DATA_USER", "me")
        monkeypatch.setenv("AESPLAT_DATA_PASSWORD", "s3cret-token")
    else:
        (tmp_path / ".netrc").write_text("machine data.example.org login me password s3cret-token\n")
        (tmp_path / ".netrc").chmod(0o600)
    line = (f"data.root {url}: {words} would go over plain http to data.example.org, readable by anyone on the "
            "network path: give the https:// URL, or set AESPLAT_DATA_INSECURE_HTTP=1 to send it over http "
            "knowingly")  # fmt: skip
    with pytest.raises(UserError) as err:
        DataModule(root=url)
    assert str(err.value) == line
    code, out = aesplat(capsys, "fit", *common(url, tmp_path / "run"))
    assert code == 1 and one_line(out) == f"aesplat fit: {line}" and "s3cret" not in out
    assert not (tmp_path / "run").exists()
    # Over https, to this machine, or when asked for: built (nothing is fetched until the data is read).
    for ok in ("https://data.example.org/shards", "http://127.0.0.1:8000/shards", "http://localhost/shards",
               "http://[::1]:8000/shards"):  # fmt: skip
        DataModule(root=ok)
    monkeypatch.setenv("AESPLAT_DATA_INSECURE_HTTP", "1")
    DataModule(root=url)


# ----------------------------------------------------------------------------------------------- the cache


def test_the_default_cache_is_refused_when_another_user_made_it_or_planted_a_link(
    server, tmp_path, monkeypatch
):
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    default = tmp_path / "tmp" / f"aesplat-shards-{os.geteuid()}"
    default.parent.mkdir()
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    default.symlink_to(theirs)
    with pytest.raises(UserError) as err:
        RemoteShards(server.url, settings=FAST).open()
    assert one_line(str(err.value)) == (
        f"the default cache {default} is a symbolic link, which this cache never follows (another user can "
        "plant one): remove it, or set data.cache_dir to a folder of yours"
    )
    assert list(theirs.iterdir()) == []
    if os.geteuid() != 0:
        return  # giving a folder to another user takes root
    default.unlink()
    default.mkdir(mode=0o777)
    os.chown(default, 65534, 65534)
    with pytest.raises(UserError) as err:
        RemoteShards(server.url, settings=FAST).open()
    assert one_line(str(err.value)).startswith(f"the default cache {default} belongs to ")
    assert one_line(str(err.value)).endswith(
        "(uid 65534), not to you: shards another user put there would be read as yours; set data.cache_dir to "
        "a folder of your own"
    )
    assert list(default.iterdir()) == []


def test_a_cache_others_can_write_is_verified_and_its_links_are_never_followed(server, tmp_path, caplog):
    """A shard planted with the right name and size, and a ``.part`` planted as a link to a file of the
    victim's: the run reads the server's bytes and the victim's file is untouched."""
    cache = tmp_path / "shared"
    cache.mkdir()
    cache.chmod(0o777)
    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    names = ["train/train-000000.tar", "train/train-000001.tar"]
    for folder in ("sets", "shards"):
        (cache / folder).mkdir(mode=0o700)
    planted = cached(cache, server.root, names[0])
    planted.write_bytes(b"x" * record(server.root, names[0]).size)
    cached(cache, server.root, names[1]).with_suffix(".tar.part").symlink_to(victim)
    with caplog.at_level(logging.WARNING, "aesplat.data"):
        remote = RemoteShards(server.url, cache, FAST)
        listing = remote.open()
    assert f"the cache {cache} can be written by other users (mode 777)" in caplog.text
    for name in names:
        got = Path(remote.fetch(listing / name)).read_bytes()
        assert got == (server.root / name).read_bytes()
    assert victim.read_text() == "mine"
    assert sorted(logged(server, ".tar", 2)) == [f"/{n}" for n in names]


def test_a_folder_of_the_cache_that_is_not_the_user_s_is_refused(server, tmp_path):
    cache = tmp_path / "cache"
    (cache / "sets").mkdir(parents=True)
    (cache / "shards").symlink_to(tmp_path)
    with pytest.raises(UserError) as err:
        RemoteShards(server.url, cache, FAST).open()
    assert one_line(str(err.value)) == (
        f"the cache {cache / 'shards'} is a symbolic link, which this cache never follows (another user can "
        "plant one): remove it, or set data.cache_dir to a folder of yours"
    )


def test_two_data_sets_sharing_a_cache_each_read_their_own_listing(local_nginx, served, tmp_path):
    both = tmp_path / "both"
    shutil.copytree(served, both / "a")
    shutil.copytree(served, both / "b")
    manifest = manifest_of(both / "b")
    manifest["splits"]["train"]["shards"] = manifest["splits"]["train"]["shards"][2:]
    write_manifest(both / "b", manifest)
    cache = str(tmp_path / "cache")
    with local_nginx.Nginx(both, tmp_path / "nginx") as server:
        a = DataModule(root=f"{server.url}/a", cache_dir=cache, num_workers=0, **LOADER)
        b = DataModule(root=f"{server.url}/b", cache_dir=cache, num_workers=0, **LOADER)
        a.shard_folder(), b.shard_folder()  # b's manifest fetched last
        for dm, root in ((a, both / "a"), (b, both / "b")):
            local = DataModule(root=str(root), num_workers=0, **LOADER)
            want = sorted((Path(s.shard).name, s.key) for s in local.train_dataset().scenes)
            assert sorted((Path(s.shard).name, s.key) for s in dm.train_dataset().scenes) == want
    assert len(want) == 2


# ----------------------------------------------------------------------------------------------- ranks


def _rank(rank: int, root: str, node: str, store: str, reupload: tuple[str, str] | None, out) -> None:
    """One rank of a gloo group of two, on its own "node" (the folder ``node``, its working folder): its data
    module's set-up, as Lightning calls it; what it saw."""
    import torch.distributed as dist

    os.chdir(node)
    dist.init_process_group("gloo", init_method=f"file://{store}", rank=rank, world_size=2)
    try:
        dm = DataModule(root=root, cache_dir="cache", num_workers=0, **LOADER)
        if reupload and rank == 0:  # the server's manifest changes right after rank 0 fetched it
            fetch = dm.remote.fetch_manifest

            def fetch_then_reupload() -> bytes:
                data = fetch()
                shutil.copy(*reupload)
                return data

            dm.remote.fetch_manifest = fetch_then_reupload
        dm.trainer = SimpleNamespace(global_rank=rank, world_size=2, global_step=0)
        try:
            dm.setup("fit")
        except UserError as err:
            out.put((rank, "error", str(err)))
            return
        scenes = sorted((Path(s.shard).name, s.key) for s in dm.train_dataset().scenes)
        out.put((rank, dm.data_sha256, scenes))
    finally:
        dist.destroy_process_group()


def _two_ranks(root: str, tmp_path: Path, reupload: tuple[str, str] | None = None) -> dict:
    """What each of two ranks on the nodes ``tmp_path/node0`` and ``node1`` saw (:func:`_rank`) of the data at
    ``root``; ``reupload``: (new manifest, the served one it replaces)."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    out = context.Queue()
    for r in (0, 1):
        (tmp_path / f"node{r}").mkdir(exist_ok=True)
    args = [(r, root, str(tmp_path / f"node{r}"), str(tmp_path / "store"), reupload, out) for r in (0, 1)]
    procs = [context.Process(target=_rank, args=a) for a in args]
    for p in procs:
        p.start()
    seen = [out.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(30)
    assert [p.exitcode for p in procs] == [0, 0]
    return {rank: rest for rank, *rest in seen}


def test_ranks_read_rank_0_s_manifest_even_across_a_reupload(server, tmp_path):
    every = sorted((Path(s.shard).name, s.key)
                   for s in DataModule(root=str(server.root), **LOADER).train_dataset().scenes)  # fmt: skip
    manifest = manifest_of(server.root)  # the re-upload: a conversion with one shard fewer
    manifest["splits"]["train"]["shards"] = manifest["splits"]["train"]["shards"][1:]
    (tmp_path / "new").mkdir()
    write_manifest(tmp_path / "new", manifest)
    reupload = (str(tmp_path / "new" / "manifest.json"), str(server.root / "manifest.json"))
    seen = _two_ranks(server.url, tmp_path, reupload)
    assert seen[0][0] == seen[1][0] is not None  # one data digest
    assert sorted(seen[0][1] + seen[1][1]) == every  # every scene of rank 0's listing, each read by one rank
    assert logged(server, "/manifest.json") == ["/manifest.json"]


def test_ranks_whose_copies_of_the_data_differ_stop_with_one_line(served, tmp_path):
    shutil.copytree(served, tmp_path / "node0" / "shards")
    other = shutil.copytree(served, tmp_path / "node1" / "shards")
    edit_manifest(other, "train/train-000003.tar", sha256="0" * 64)
    seen = _two_ranks("shards", tmp_path)
    line = ("ranks 1 read other data than rank 0: the manifest.json of shards lists other shards on their "
            "nodes; give every node the same copy of the shards")  # fmt: skip
    assert seen == {0: ["error", line], 1: ["error", line]}


def test_a_manifest_rank_0_cannot_fetch_stops_every_rank_with_its_line(server, tmp_path):
    (server.root / "manifest.json").unlink()
    seen = _two_ranks(server.url, tmp_path)
    line = (f"the manifest {server.url}/manifest.json: not found on the server (HTTP 404); data.root must be "
            "the URL of the shard folder, the one holding manifest.json")  # fmt: skip
    assert seen == {0: ["error", line], 1: ["error", line]}
    assert logged(server, "/manifest.json") == ["/manifest.json"]


# ----------------------------------------------------------------------------------------------- resume


def test_a_resume_on_other_data_is_refused_unless_asked_for(served, tmp_path, capsys):
    run_dir = tmp_path / "run"
    cli.main(["fit", *common(served, run_dir), "--trainer.max_steps", "2"])
    other = shutil.copytree(served, tmp_path / "other")
    served = other / "train" / "train-000000.tar"
    served.write_bytes(served.read_bytes() + b"\0" * 10240)  # end-of-archive blocks: the same samples
    edit_manifest(other, "train/train-000000.tar", sha256=sha256(served), bytes=served.stat().st_size)
    before = tree(run_dir / "checkpoints")
    code, err = aesplat(
        capsys, "fit", *common(other, run_dir), "--trainer.max_steps", "3", "--ckpt_path", "last"
    )
    line = one_line(err, after_start=True)
    assert code == 1 and line.startswith(
        f"aesplat fit: the checkpoint was trained on other data than {other} holds now (its manifest lists "
        "other shards: "
    )
    assert line.endswith("resume on the data it was trained on, or pass --data.allow_other_data true to go on "
                         "with these")  # fmt: skip
    assert tree(run_dir / "checkpoints") == before
    cli.main(["fit", *common(other, run_dir), "--trainer.max_steps", "3", "--ckpt_path", "last",
              "--data.allow_other_data", "true"])  # fmt: skip
    assert torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 3
