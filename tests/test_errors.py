"""aesplat.errors: how every command ends. A user's mistake or an OSError is one line and exit 1; a signal
exits with 128 + its number, after the cleanups ran."""

import errno
import functools
import itertools
import multiprocessing
import os
import signal
import time

import pytest
import torch
from lightning.fabric.utilities.seed import pl_worker_init_function
from torch.utils.data import DataLoader, IterableDataset

from aesplat.data.datamodule import DataModule
from aesplat.errors import (
    STOP_SIGNALS,
    UserError,
    os_error_line,
    run_reporting_user_errors,
    stopping_on_signals,
)


def ends(fn, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as info:
        run_reporting_user_errors("fit", fn)
    code = info.value.code
    err = capsys.readouterr().err
    if isinstance(code, str):  # Python prints it and exits with 1
        return 1, code
    return code, err.strip()


def test_a_full_disk_is_one_line_naming_the_file(capsys):
    def full():
        raise OSError(errno.ENOSPC, "No space left on device", "/runs/r/checkpoints/last.ckpt")

    code, line = ends(full, capsys)
    assert code == 1 and line == (
        "aesplat fit: /runs/r/checkpoints/last.ckpt: No space left on device (the disk is full: free some "
        "space and run the command again)"
    )


@pytest.mark.parametrize("number, words", [(errno.EROFS, "read-only"), (errno.EACCES, "no permission"),
                                           (errno.ENOENT, None)])  # fmt: skip
def test_os_errors_name_the_file_and_what_to_do(number, words):
    line = os_error_line(OSError(number, os.strerror(number), "f.txt"))
    assert line.startswith(f"f.txt: {os.strerror(number)}") and "\n" not in line
    assert (words in line) if words else line == f"f.txt: {os.strerror(number)}"


def test_a_user_error_is_one_line(capsys):
    def bad():
        raise UserError("--data.root D holds no shards")

    assert ends(bad, capsys) == (1, "aesplat fit: --data.root D holds no shards")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_a_signal_runs_the_cleanups_and_exits_128_plus_its_number(signum, capsys, stop_signals_heeded):
    cleaned = []

    def stopped():
        try:
            os.kill(os.getpid(), signum)
            raise AssertionError("the signal must interrupt here")
        finally:
            cleaned.append(True)

    code, line = ends(stopped, capsys)
    assert (code, line, cleaned) == (
        128 + signum,
        f"aesplat fit: stopped by {signal.Signals(signum).name}",
        [True],
    )
    assert signal.getsignal(signum) in (signal.SIG_DFL, signal.default_int_handler)  # handlers restored


def test_a_forked_worker_ignores_a_stop_signal_the_main_process_acts_on():
    """A forked worker (of a process pool) inherits the handlers: a signal sent to the whole process group
    (Ctrl-C, SLURM) must leave it running, for the main process to stop it when its work is over."""
    context = multiprocessing.get_context("fork")

    def worker(conn) -> None:
        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            os.kill(os.getpid(), signum)
        conn.send("still running")

    def main() -> None:
        here, there = context.Pipe()
        child = context.Process(target=worker, args=(there,))
        child.start()
        assert here.poll(30) and here.recv() == "still running"
        child.join(timeout=30)
        assert child.exitcode == 0

    with stopping_on_signals():
        main()


class SignalsItself(IterableDataset):
    """In each data-loader worker: send itself the stop signals (from another process than the main one, as a
    signal to the whole process group comes), wait until they are taken, and yield its pid."""

    def __iter__(self):
        for signum in STOP_SIGNALS:
            os.kill(os.getpid(), signum)
        deadline = time.monotonic() + 60
        while set(STOP_SIGNALS) & signal.sigpending() and time.monotonic() < deadline:
            time.sleep(0.01)
        yield os.getpid()


class Counts(IterableDataset):
    def __iter__(self):
        yield from itertools.count()


class InitialSeed(IterableDataset):
    def __iter__(self):
        yield torch.initial_seed()


def test_a_data_loader_worker_outlives_a_stop_signal_sent_to_the_process_group(stop_signals_heeded):
    """torch sets a SIGTERM handler of its own in each data-loader worker, over the one it inherited, which
    ends the worker on a SIGTERM from any process but the main one: the main process, which finishes its step
    and saves, would fail on the lost worker ("DataLoader worker ... killed by signal")."""
    loader = DataModule(num_workers=2)._loader(SignalsItself())
    with stopping_on_signals():
        pids = list(loader)
    assert len(set(pids)) == 2 and os.getpid() not in pids


def test_the_main_process_still_ends_a_data_loader_worker_with_sigterm():
    """How the main process ends a worker that does not stop when asked, and at exit every worker still
    running: a SIGTERM of its own, and it waits for the worker to end (an ignored one would hang the exit)."""
    loader = DataModule(num_workers=2)._loader(Counts())
    batches = iter(loader)
    next(batches)
    for worker in batches._workers:
        worker.terminate()
        worker.join(timeout=60)
    assert [worker.exitcode for worker in batches._workers] == [0, 0]


def test_data_loader_workers_are_seeded_as_lightning_seeds_them(monkeypatch):
    """The workers' ``worker_init_fn`` also seeds them as Lightning's own would after
    ``seed_everything(workers=True)`` (which ``aesplat fit`` calls): Lightning adds its own only to a DataLoader
    that has none."""
    monkeypatch.setenv("PL_SEED_WORKERS", "1")
    data = DataModule(num_workers=2)
    data.set_distributed(1, 2)
    seeds = {}
    for name, loader in (
        ("ours", data._loader(InitialSeed())),
        ("lightning", DataLoader(InitialSeed(), batch_size=None, num_workers=2,
                                 worker_init_fn=functools.partial(pl_worker_init_function, rank=1))),
        ("torch", DataLoader(InitialSeed(), batch_size=None, num_workers=2)),
    ):  # fmt: skip
        torch.manual_seed(7)  # the workers' base seed comes from here
        seeds[name] = sorted(loader)
    assert seeds["ours"] == seeds["lightning"] != seeds["torch"]


def test_a_signal_the_process_was_started_to_ignore_stays_ignored():
    """`nohup` ignores SIGHUP, a shell's background job SIGINT: the command must not start heeding them."""
    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with stopping_on_signals():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGHUP)  # nothing happens
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_IGN, signal.SIG_DFL)
    finally:
        signal.signal(signal.SIGHUP, before)
