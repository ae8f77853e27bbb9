"""aesplat.errors: how every command ends. A user's mistake or an OSError is one line and exit 1; a signal
exits with 128 + its number, after the cleanups ran."""

import errno
import multiprocessing
import os
import signal

import pytest

from aesplat.errors import UserError, os_error_line, run_reporting_user_errors, stopping_on_signals


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
    """A data-loader worker inherits the handlers: a signal sent to the whole process group (Ctrl-C, SLURM)
    must leave it running, for the main process to stop it when the step is over."""
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
