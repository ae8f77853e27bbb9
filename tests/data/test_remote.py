"""Shards behind an http URL (aesplat.data.remote), against a real nginx on 127.0.0.1 (scripts/local_nginx.py,
which installs Debian's nginx when missing): the data read equal the local folder's, only the shards read are
fetched, a verified shard is reused, and each fault ends in a successful retry or one line, never in a step on
bad bytes."""

from __future__ import annotations

import multiprocessing
import os
import re
import shutil
import threading
import time
from pathlib import Path

import pytest

from aesplat import cli
from aesplat.data import DataModule
from aesplat.data.manifest import sha256
from aesplat.data.remote import DownloadSettings, FetchError, RemoteShards
from aesplat.errors import UserError
from tests.data.servers import FAST, LOADER, TOKEN, cached, edit_manifest
from tests.helpers import aesplat, common, one_line, sample_keys


def shard_gets(server) -> list[tuple[str, int, str]]:
    """(path, status, Range) of every GET of a shard the server answered."""
    return [(uri, status, ranged) for method, uri, status, ranged in server.requests()
            if method == "GET" and uri.endswith(".tar")]  # fmt: skip


def test_a_url_gives_the_folder_s_batches_and_a_verified_shard_is_reused(server, tmp_path):
    local = DataModule(root=str(server.root), num_workers=2, **LOADER)
    remote = DataModule(root=server.url + "/", cache_dir=str(tmp_path / "cache"), num_workers=2, **LOADER)
    want = [sample_keys(b) for b in local.train_dataloader()]
    assert [sample_keys(b) for b in remote.train_dataloader()] == want
    assert len(list(remote.val_dataloader())) == len(list(local.val_dataloader())) == 2
    assert len(list(remote.test_dataloader())) == 2
    fetched = sorted(uri for uri, _, _ in shard_gets(server))
    assert fetched == sorted(f"/{p.relative_to(server.root)}" for p in server.root.glob("*/*.tar"))
    cache = tmp_path / "cache"
    for uri in fetched:
        assert cached(cache, server.root, uri[1:]).read_bytes() == (server.root / uri[1:]).read_bytes()
    assert sorted(p.name for p in (cache / "shards").glob("*.tar")) == sorted(
        cached(cache, server.root, uri[1:]).name for uri in fetched
    )
    assert not list(cache.rglob("*.part"))
    # The cache is its user's alone: folders 0700, files 0600.
    assert {oct(p.stat().st_mode & 0o777) for p in [cache, *cache.rglob("*")] if p.is_dir()} == {"0o700"}
    assert {oct(p.stat().st_mode & 0o777) for p in cache.rglob("*") if p.is_file()} == {"0o600"}

    again = DataModule(root=server.url, cache_dir=str(cache), num_workers=2, **LOADER)
    assert [sample_keys(b) for b in again.train_dataloader()] == want
    assert sorted(uri for uri, _, _ in shard_gets(server)) == fetched  # no second GET of any shard
    assert [u for m, u, _, _ in server.requests() if u == "/manifest.json"] == ["/manifest.json"] * 2


def test_a_rank_fetches_only_the_shards_it_reads(server, tmp_path):
    dm = DataModule(root=server.url, cache_dir=str(tmp_path / "cache"), num_workers=0, **LOADER)
    dm.set_distributed(1, 2)
    list(dm.train_dataloader())
    mine = sorted({Path(s.shard).name for s in dm.train_dataset().scenes})
    assert len(mine) == 2
    assert sorted(uri for uri, _, _ in shard_gets(server)) == [f"/train/{name}" for name in mine]


def test_a_changed_shard_in_a_new_manifest_is_fetched_again(server, tmp_path):
    first = RemoteShards(server.url, tmp_path / "cache", FAST)
    listing = first.open()
    shard = listing / "test" / "test-000000.tar"
    old = Path(first.fetch(shard)).read_bytes()
    first.fetch(listing / "test" / "test-000001.tar")
    # A new conversion on the server: other bytes, another SHA-256 in its manifest.
    served = server.root / "test" / "test-000000.tar"
    served.write_bytes(served.read_bytes() + b"\0" * 10240)
    edit_manifest(server.root, "test/test-000000.tar", sha256=sha256(served), bytes=served.stat().st_size)
    second = RemoteShards(server.url, tmp_path / "cache", FAST)
    listing2 = second.open()
    assert listing2 != listing  # a listing of its own; the first one's is unchanged
    assert Path(second.fetch(listing2 / "test" / "test-000000.tar")).read_bytes() == served.read_bytes()
    assert Path(first.fetch(shard)).read_bytes() == old
    second.fetch(listing2 / "test" / "test-000001.tar")  # the same bytes in both: the copy there is used
    gets = [uri for uri, _, _ in shard_gets(server)]
    assert gets == ["/test/test-000000.tar", "/test/test-000001.tar", "/test/test-000000.tar"]


def test_a_cut_download_resumes_with_a_range_request(server, tmp_path):
    remote = RemoteShards(server.url, tmp_path / "cache", FAST)
    shard = remote.open() / "train" / "train-000001.tar"
    whole = (server.root / "train" / "train-000001.tar").read_bytes()
    part = cached(tmp_path / "cache", server.root, "train/train-000001.tar").with_suffix(".tar.part")
    part.write_bytes(whole[:10_000])
    assert Path(remote.fetch(shard)).read_bytes() == whole
    assert shard_gets(server) == [("/train/train-000001.tar", 206, "bytes=10000-")]


def test_a_server_stopped_in_the_middle_of_a_shard_is_resumed_when_it_is_back(local_nginx, served, tmp_path):
    # 30 kB at 12 kB/s: the server stops after the first bytes have come, and is back during the backoff.
    with local_nginx.Nginx(served, tmp_path / "nginx", slow_rate="12k") as server:
        remote = RemoteShards(server.url + "/slow", tmp_path / "cache", DownloadSettings(6, 5.0, 0.2))
        shard = remote.open() / "train" / "train-000002.tar"
        target = cached(tmp_path / "cache", served, "train/train-000002.tar")
        part = target.with_suffix(".tar.part")
        done: list = []
        fetching = threading.Thread(target=lambda: done.append(remote.fetch(shard)))
        fetching.start()
        deadline = time.monotonic() + 10
        while not (part.exists() and part.stat().st_size > 0) and time.monotonic() < deadline:
            time.sleep(0.01)
        server.stop()
        cut = part.stat().st_size
        time.sleep(0.3)
        server.start()
        fetching.join(30)
        assert done == [str(target)]
    assert target.read_bytes() == (served / "train" / "train-000002.tar").read_bytes()
    # nginx logs a request when it ends: the one cut by the stop is not there; the next resumed it.
    (uri, status, ranged), *later = shard_gets(server)
    resumed_from = int(ranged.removeprefix("bytes=").removesuffix("-"))
    assert (uri, status) == ("/slow/train/train-000002.tar", 206) and later == []
    assert 0 < cut <= resumed_from < target.stat().st_size


def _fetch_in_process(remote: RemoteShards, shard: Path, out) -> None:
    out.put(remote.fetch(shard))


def test_two_processes_wanting_one_shard_download_it_once(local_nginx, served, tmp_path):
    with local_nginx.Nginx(served, tmp_path / "nginx", slow_rate="60k") as server:
        remote = RemoteShards(server.url + "/slow", tmp_path / "cache", FAST)
        shard = remote.open() / "train" / "train-000000.tar"
        context = multiprocessing.get_context("fork")
        out = context.Queue()
        workers = [context.Process(target=_fetch_in_process, args=(remote, shard, out)) for _ in range(2)]
        for w in workers:
            w.start()
        results = [out.get(timeout=30) for _ in workers]
        for w in workers:
            w.join(10)
    target = cached(tmp_path / "cache", served, "train/train-000000.tar")
    assert results == [str(target)] * 2 and [w.exitcode for w in workers] == [0, 0]
    assert target.read_bytes() == (served / "train" / "train-000000.tar").read_bytes()
    assert [uri for uri, _, _ in shard_gets(server)] == ["/slow/train/train-000000.tar"]


def test_a_missing_shard_fails_the_run_in_one_line(server, tmp_path):
    (server.root / "train" / "train-000003.tar").unlink()
    dm = DataModule(root=server.url, cache_dir=str(tmp_path / "cache"), num_workers=0, **LOADER)
    with pytest.raises(FetchError) as err:
        list(dm.train_dataloader())
    line = one_line(str(err.value))
    url = f"{server.url}/train/train-000003.tar"
    assert line == (f"shard train/train-000003.tar {url}: not found on the server (HTTP 404); check data.root, "
                    "or upload the file the manifest lists")  # fmt: skip


def test_a_url_without_a_manifest_stops_the_command_in_one_line(server, capsys, tmp_path):
    run_dir = tmp_path / "run"
    code, err = aesplat(capsys, "fit", *common(f"{server.url}/nowhere", run_dir))
    assert code == 1 and one_line(err) == (
        f"aesplat fit: the manifest {server.url}/nowhere/manifest.json: not found on the server (HTTP 404); "
        "data.root must be the URL of the shard folder, the one holding manifest.json"
    )
    assert not run_dir.exists()


def test_a_fetch_error_raised_in_a_data_loader_worker_is_still_one_line():
    """torch rebuilds a worker's exception in the main process from a message that holds the worker's
    traceback; the line comes back out of it."""
    from torch._utils import ExceptionWrapper

    line = "shard train/a.tar http://host/train/a.tar: not found on the server (HTTP 404)"
    try:
        raise FetchError(line)
    except FetchError:
        wrapped = ExceptionWrapper(where="in DataLoader worker process 1")
    with pytest.raises(FetchError) as err:
        wrapped.reraise()
    assert str(err.value) == line


def test_a_shard_with_other_bytes_than_the_manifest_is_fetched_twice_then_refused(server, tmp_path):
    served = server.root / "train" / "train-000000.tar"
    data = bytearray(served.read_bytes())
    data[5000] ^= 0xFF
    served.write_bytes(bytes(data))
    dm = DataModule(root=server.url, cache_dir=str(tmp_path / "cache"), num_workers=0, **LOADER)
    with pytest.raises(FetchError) as err:
        list(dm.train_dataloader())
    line = one_line(str(err.value))
    url = f"{server.url}/train/train-000000.tar"
    assert line.startswith(
        f"shard train/train-000000.tar fetched from {url} does not match the manifest (SHA-256 "
    )
    assert [u for u, _, _ in shard_gets(server) if u.endswith("-000000.tar")] == ["/train/train-000000.tar"] * 2
    assert not list((tmp_path / "cache" / "shards").glob("*.tar*[!k]"))  # no copy, no part


def test_a_throttled_server_completes_and_a_stalled_one_times_out_in_one_line(server, tmp_path):
    remote = RemoteShards(server.url + "/slow", tmp_path / "slow", FAST)
    shard = remote.open() / "test" / "test-000001.tar"
    assert Path(remote.fetch(shard)).read_bytes() == (server.root / "test" / "test-000001.tar").read_bytes()

    crawl = RemoteShards(server.url + "/crawl", tmp_path / "crawl", DownloadSettings(1, 0.5, 0.0))
    shard = crawl.open() / "test" / "test-000001.tar"
    with pytest.raises(FetchError) as err:
        crawl.fetch(shard)
    assert one_line(str(err.value)) == (
        f"could not fetch shard test/test-000001.tar {server.url}/crawl/test/test-000001.tar in 2 tries: no "
        "answer or data for 0.5 s (data.download_timeout); check the server, or raise data.download_retries / "
        "data.download_timeout"
    )
    assert not cached(tmp_path / "crawl", server.root, "test/test-000001.tar").exists()


def test_a_server_that_stays_down_fails_in_one_line_after_the_retries(server, tmp_path):
    remote = RemoteShards(server.url, tmp_path / "cache", FAST)
    shard = remote.open() / "train" / "train-000000.tar"
    server.stop()
    with pytest.raises(FetchError) as err:
        remote.fetch(shard)
    assert one_line(str(err.value)) == (
        f"could not fetch shard train/train-000000.tar {server.url}/train/train-000000.tar in 3 tries: the "
        "connection was refused; check the server, or raise data.download_retries / data.download_timeout"
    )


def test_a_cache_that_cannot_be_written_is_one_line(server, tmp_path):
    remote = RemoteShards(server.url, tmp_path / "cache", FAST)
    shard = remote.open() / "train" / "train-000000.tar"
    shutil.rmtree(tmp_path / "cache" / "shards")
    (tmp_path / "cache" / "shards").write_text("a file where the shards' folder goes")
    target = cached(tmp_path / "cache", server.root, "train/train-000000.tar")
    with pytest.raises(FetchError) as err:
        remote.fetch(shard)
    assert (
        one_line(str(err.value)) == f"shard train/train-000000.tar from {server.url}: {target}: Not a directory"
    )


def test_credentials_come_from_the_environment_and_a_refusal_names_the_variable(server, tmp_path, monkeypatch):
    url = server.url + "/auth"
    monkeypatch.delenv("AESPLAT_DATA_TOKEN", raising=False)
    monkeypatch.delenv("AESPLAT_DATA_USER", raising=False)
    with pytest.raises(FetchError, match="HTTP 401, no credentials were given: set AESPLAT_DATA_TOKEN"):
        RemoteShards(url, tmp_path / "cache", FAST).open()
    monkeypatch.setenv("AESPLAT_DATA_TOKEN", "not-the-token")
    with pytest.raises(FetchError) as err:
        RemoteShards(url, tmp_path / "cache", FAST).open()
    assert one_line(str(err.value)) == (
        f"the manifest {url}/manifest.json: HTTP 401, the token in AESPLAT_DATA_TOKEN was refused: set it to a "
        "token this server accepts"
    )
    monkeypatch.setenv("AESPLAT_DATA_TOKEN", TOKEN)
    remote = RemoteShards(url, tmp_path / "cache", FAST)
    shard = remote.open() / "test" / "test-000000.tar"
    assert Path(remote.fetch(shard)).read_bytes() == (server.root / "test" / "test-000000.tar").read_bytes()


@pytest.mark.parametrize(
    "root, words",
    [
        ("http://me:pw@127.0.0.1:9/shards", "credentials in the URL would be saved with the run's config.yaml"),
        ("s3://bucket/shards", "only http:// and https:// URLs are read"),
        ("https://host/shards?sig=abc", "without a query (?...) or fragment"),
    ],
)
def test_a_url_that_cannot_be_used_is_refused_in_one_line(root, words, capsys, tmp_path):
    with pytest.raises(UserError, match=words.replace("?", r"\?").replace("(", r"\(").replace(")", r"\)")):
        DataModule(root=root)
    code, err = aesplat(capsys, "fit", *common(root, tmp_path / "run"))
    assert code == 1 and words in one_line(err) and "me:pw" not in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "option, value, must",
    [
        ("download_timeout", "0", "more than 0 and at most 86400 seconds"),
        ("download_timeout", "1e18", "more than 0 and at most 86400 seconds"),  # beyond a socket's timeout
        ("download_retries", "-1", "0 to 100 tries"),
        ("download_retries", "5000", "0 to 100 tries"),  # its doubling wait would overflow
        ("download_backoff", "-1", "0 to 3600 seconds"),
        ("download_backoff", "1e300", "0 to 3600 seconds"),
    ],
)
def test_download_settings_out_of_range_are_refused_before_anything_is_fetched(option, value, must, capsys,
                                                                               tmp_path):  # fmt: skip
    number = float(value) if option != "download_retries" else int(value)
    with pytest.raises(UserError, match=re.escape(f"data.{option} = {number!r}: it must be {must}")):
        DataModule(root="http://127.0.0.1/x", **{option: number})
    run_dir = tmp_path / "run"
    code, err = aesplat(capsys, "fit", *common("http://127.0.0.1:9/x", run_dir), f"--data.{option}={value}")
    assert code == 1 and one_line(err) == (
        f"aesplat fit: invalid configuration: data.{option} = {number!r}: it must be {must}"
    )
    assert not run_dir.exists()


def test_a_fit_from_a_url_trains_and_saves_no_credential(server, tmp_path, monkeypatch, capsys):
    """A real `aesplat fit` from an http URL that needs a token: it trains, and the token is in no file the run
    wrote nor in its output."""
    monkeypatch.setenv("AESPLAT_DATA_TOKEN", TOKEN)
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))  # the default cache
    run_dir = tmp_path / "run"
    url = server.url + "/auth"
    args = ["-c", "conf/smoke.yaml", "--data.root", url, "--trainer.default_root_dir", str(run_dir)]
    cli.main(["fit", *args])
    out, err = capsys.readouterr()
    assert (run_dir / "checkpoints" / "last.ckpt").is_file()
    assert f"root: {url}" in (run_dir / "config.yaml").read_text()
    written = [p for p in run_dir.rglob("*") if p.is_file()]
    assert written and not [p for p in written if TOKEN.encode() in p.read_bytes()]
    assert TOKEN not in err + out
    cache = tmp_path / "tmp" / f"aesplat-shards-{os.geteuid()}"
    names = [f"train/train-00000{i}.tar" for i in range(4)]
    assert {p.name for p in (cache / "shards").glob("*.tar")} >= {
        cached(cache, server.root, n).name for n in names
    }
