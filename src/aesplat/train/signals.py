"""Signals during training, acted on at a step boundary: a stop signal saves where training stopped, the
SLURM requeue signal checkpoints and requeues.

**Stop** (SIGTERM, SIGINT, SIGHUP: ``kill``, Ctrl-C, a closed terminal, ``scancel``, a time limit): the step
under way finishes, every rank agrees to stop at the same step, ``last.ckpt`` is saved there
(``aesplat.train.callbacks.RunCheckpoint``) and the fit ends; ``aesplat fit`` then exits with 128 + the
signal's number, so ``aesplat fit … && aesplat test …`` never takes a stopped run for a finished one. A second
stop signal stops at once, without saving. (Lightning's own SIGTERM handling stops without a checkpoint and
exits 0; it is replaced while training runs.) A signal sent to the whole process group or job reaches the
data-loader workers too: they ignore it (``aesplat.errors.ignore_stop_signals_in_worker``), so the step under
way can finish.

**Requeue** (SIGUSR1 under SLURM, ``#SBATCH --signal=SIGUSR1@90``): Lightning's SLURM handler (write
``hpc_ckpt_N.ckpt``, ``scontrol requeue``) would run wherever the signal lands: in the middle of a step the
checkpoint holds half a step, and under DDP each rank stops at a different point, so one rank's checkpoint
barrier meets another's gradient all-reduce. Here the signal is blocked from process start
(``aesplat.cli.hold_requeue_signal``, before any thread or DataLoader worker exists, so none of them takes it;
importing torch already starts one); after every training step the ranks agree whether any of them has it
pending, and if so all of them let it through at the same point. Lightning's handler then writes the HPC
checkpoint where ``ModelCheckpoint`` writes ``last.ckpt`` (a state that resumes exactly) and requeues the job,
and the ranks wait there for SLURM's SIGTERM instead of training steps that the requeued job would repeat.

**Agreement off the device**: under DDP the ranks agree on these flags with one all-reduce per step over a
CPU process group (gloo; the training group itself when training runs on the CPU), so that the check never
waits for a GPU: no device tensor is made or read.

**A lost rank** (its node died, its process was killed, or it stopped answering for ``timeout`` seconds, the
process groups' timeout, set by ``aesplat fit --distributed.timeout``): the collective under way fails on
the other ranks. Every rank counts up a key of the rendezvous store (served by rank 0's process) every
second from a thread of its own (:class:`Heartbeat`); a rank whose collective failed reads the counts twice,
a few seconds apart, and ``lost`` says in one line which ranks, on which nodes, stopped counting (rank 0
when the store itself is gone); ``aesplat fit`` ends with that line, exit status 1. Nothing is saved then:
the last checkpoint written before stays as it was.

**A slow rank** (alive, its count goes on, but it reached the collective more than ``timeout`` seconds after
the others: a first batch from a cold cache, a long checkpoint save): each rank also keeps in the store where
it is (the step, and the phase of it), and ``slow`` says in one line which ranks had not arrived and where they
were, where the rank that gave up waited, and that ``--distributed.timeout`` must be raised. A timeout before
training (the ranks joining the process group, setting up) is one line too.

**The ranks a fit started end with it**: ``aesplat fit --trainer.devices N`` on one machine starts the other
ranks itself (Lightning's subprocess launcher), which ends them only on Ctrl-C. After any other failure they
would run on, still starting or waiting on a collective, and write into the run folder after the failed fit
took its run markers back. :func:`end_started_ranks` ends them, and the fit cleans up once they are gone.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from datetime import timedelta

import torch
import torch.distributed as dist
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.fabric.strategies.launchers.subprocess_script import _ChildProcessObserver
from lightning.pytorch import Callback, LightningModule, Trainer
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn

from aesplat.errors import Stopped, heeded_signals, in_this_process_only, signal_name

REQUEUE_SIGNAL = signal.SIGUSR1  # Lightning's SLURMEnvironment default; slurm/train.sbatch asks for it
BEAT_SECONDS = 1.0  # how often each rank counts up its key of the store
# What a collective that lost a peer raises: torch's distributed errors, and gloo's and NCCL's own words.
_LOST_PEER = re.compile(r"gloo|nccl|connection (closed|reset|refused)|broken pipe|timed out|timeout", re.I)
_BACKEND = re.compile(r"gloo|nccl|c10d", re.I)
_TIMED_OUT = re.compile(r"timed out|timeout", re.I)
# --distributed.timeout, in seconds. It also bounds the process group's start, where the first rank waits for
# the others to join: on one machine, the ranks Lightning starts join after importing torch and building the
# model, 3.5 s after the first on a 2-core machine (4.7 s with both cores busy); 10 s leaves twice that. At most
# 7 days: Python's timedelta ends at 999999999 days, torch's C++ deadlines count nanoseconds in 64 bits and wrap
# after 292 years (a 1e10 s timeout fails at once), and 7 days also stays within a 32-bit count of
# milliseconds (24.8 days).
MIN_TIMEOUT = 10.0
MAX_TIMEOUT = 7 * 24 * 3600.0


def node_name() -> str:
    """The node this process runs on: SLURM's name for it when a SLURM task, else the host name."""
    return os.environ.get("SLURMD_NODENAME") or socket.gethostname()


class Heartbeat:
    """Under DDP, this rank counts up ``aesplat/beat/<rank>`` in the rendezvous store every ``BEAT_SECONDS``
    from a daemon thread, whatever the training thread is waiting for; :meth:`silent` names the ranks that
    stopped counting. The store is a client of the one ``torch.distributed`` made (``MASTER_ADDR``,
    ``MASTER_PORT``), which lives in rank 0's process."""

    def __init__(self, rank: int, world_size: int, where: tuple[int, str] = (0, "setting up")) -> None:
        self.rank, self.world_size = rank, world_size
        address, port = os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"])
        self.store = dist.TCPStore(address, port, is_master=False, timeout=timedelta(seconds=30))
        # (order, what): where this rank is, set by the training thread, in the store at the next beat; a rank
        # with a lower order had not come as far (:meth:`positions`)
        self.where = where
        self.store.set(f"aesplat/at/{rank}", f"{where[0]} {where[1]}")
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="aesplat-heartbeat", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        store = dist.TCPStore(self.store.host, self.store.port, is_master=False, timeout=timedelta(seconds=30))
        told = None
        while not self._done.is_set():
            try:
                store.add(f"aesplat/beat/{self.rank}", 1)
                where = self.where
                if where != told:
                    store.set(f"aesplat/at/{self.rank}", f"{where[0]} {where[1]}")
                    told = where
            except (RuntimeError, dist.DistError):  # the store is gone with rank 0: nothing to tell
                return
            self._done.wait(BEAT_SECONDS)

    def stop(self) -> None:
        """Stop counting, and say so in the store (``aesplat/left/<rank>``): a rank that stopped on purpose
        (its fit ended, or it has named the lost ranks and exits) is not lost."""
        self._done.set()
        try:
            self.store.set(f"aesplat/left/{self.rank}", "1")
        except (RuntimeError, dist.DistError):
            pass

    def silent(self) -> list[int]:
        """The ranks whose count did not move in three beats and that did not stop on purpose (all but this
        one checked); [0] when the store, in rank 0's process, does not answer."""
        others = [r for r in range(self.world_size) if r != self.rank]
        try:
            before = [self.store.add(f"aesplat/beat/{r}", 0) for r in others]
            time.sleep(3 * BEAT_SECONDS)
            after = [self.store.add(f"aesplat/beat/{r}", 0) for r in others]
            still = [r for r, b, a in zip(others, before, after, strict=True) if a == b]
            return [r for r in still if not self.store.check([f"aesplat/left/{r}"])]
        except (RuntimeError, dist.DistError):
            return [0]

    def positions(self) -> dict[int, tuple[int, str]]:
        """Where each rank was at its last beat, this one now: rank -> (order, what); a rank missing had no
        heartbeat yet."""
        found = {self.rank: self.where}
        for r in range(self.world_size):
            key = f"aesplat/at/{r}"
            if r != self.rank and self.store.check([key]):
                order, _, what = self.store.get(key).decode().partition(" ")
                found[r] = (int(order), what)
        return found


def _first_line(exception: BaseException) -> str:
    return (str(exception).strip().splitlines() or [type(exception).__name__])[0][:120]


def lost_peer(exception: BaseException) -> bool:
    """Whether an exception is what a collective raises when another rank is gone or does not answer."""
    if isinstance(exception, dist.DistError):
        return True
    return isinstance(exception, RuntimeError) and bool(_LOST_PEER.search(str(exception)))


def timed_out(exception: BaseException) -> bool:
    """Whether torch.distributed's error says that a collective, or the rendezvous, waited for the others
    longer than the process group's timeout."""
    text = str(exception)
    distributed = isinstance(exception, dist.DistError) or _BACKEND.search(text)
    return isinstance(exception, RuntimeError) and bool(distributed and _TIMED_OUT.search(text))


def stop_watching_started_ranks() -> None:
    """Stop Lightning's observer of the ranks this process started: when one of them ends with an error it
    SIGKILLs them all and this process too, whose cleanup would then never run. Once this process fails, it
    ends them itself (:func:`end_started_ranks`)."""
    for thread in threading.enumerate():
        if isinstance(thread, _ChildProcessObserver):
            thread._child_processes = []  # nothing left to watch: it ends at its next look


def end_started_ranks(launcher: object, wait: float = 30.0) -> None:
    """End the ranks ``launcher`` (Lightning's, of the fit that failed or stopped) started in this machine and
    wait until they are gone, at most ``wait`` seconds each. SIGKILL, as Lightning does on Ctrl-C: such a rank
    is still starting or waits on a collective with this one, where no stop signal is heard, and it has
    nothing to save (rank 0, this process, writes the checkpoints)."""
    procs = list(getattr(launcher, "procs", None) or [])
    if not procs:
        return
    stop_watching_started_ranks()
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
    for proc in procs:
        try:
            proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:  # in uninterruptible sleep (a hung file system): it dies on waking
            pass


def _held() -> bool:
    return REQUEUE_SIGNAL in signal.pthread_sigmask(signal.SIG_BLOCK, set())


class SignalsAtStepBoundary(Callback):
    """Act on stop signals and on a held requeue signal at the end of a training step, on all ranks alike.

    After the fit, ``stop_signal`` is the stop signal that ended it (None if none) and ``stopped_at`` the
    global step it stopped at.

    Under DDP, after a fit that failed because a rank was lost, ``lost`` is the line saying which (None
    otherwise); after one that failed because a collective waited ``timeout`` seconds for ranks that were
    alive, ``slow`` is the line saying which had not arrived, and where (None otherwise).

    Args:
        wait_for_kill: seconds to wait for SLURM's SIGTERM after the requeue before training on (a requeue
            that failed: Lightning has logged why).
        timeout: seconds the CPU process group's collectives wait for every rank (the training group's
            timeout is the same setting, ``--distributed.timeout``).
    """

    def __init__(self, wait_for_kill: float = 120.0, timeout: float = 300.0) -> None:
        self.wait_for_kill = wait_for_kill
        self.timeout = timeout
        self.lost: str | None = None
        self.slow: str | None = None
        self.nodes: list[str] = []  # of every rank, under DDP
        self._batches = 0  # training batches this fit has started: the order of the heartbeat's positions
        self._group: dist.ProcessGroup | None = None  # the CPU group of the flags (None: the default one)
        self._distributed = False
        self._heartbeat: Heartbeat | None = None
        self.requeue_active = False
        self.requeued = False
        self.stop_signal: int | None = None
        self.stopped_at: int | None = None
        self._previous: dict[int, object] = {}
        self._forward = None  # passes a stop signal on to the ranks Lightning started from this process

    # ----------------------------------------------------------------------------------------- set-up
    def setup(self, trainer: Trainer, pl_module: LightningModule, stage: str) -> None:
        if sys.platform == "win32" or not _held():
            return
        # The environment Lightning's signal connector looks at when it installs the requeue handler.
        env = trainer._accelerator_connector.cluster_environment
        self.requeue_active = (
            stage == "fit"
            and isinstance(env, SLURMEnvironment)
            and env.auto_requeue
            and env.requeue_signal == REQUEUE_SIGNAL
        )
        if not self.requeue_active:  # nothing here requeues: the signal acts as Lightning (or the OS) would
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {REQUEUE_SIGNAL})

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.world_size > 1 and dist.is_available() and dist.is_initialized():
            self._distributed = True
            if dist.get_backend() != "gloo":  # every rank makes it, in the same order
                self._group = dist.new_group(backend="gloo", timeout=timedelta(seconds=self.timeout))
            self.nodes = [""] * dist.get_world_size()
            dist.all_gather_object(self.nodes, node_name(), group=self._group)
            if self._heartbeat is None and "MASTER_ADDR" in os.environ and "MASTER_PORT" in os.environ:
                self._heartbeat = Heartbeat(dist.get_rank(), dist.get_world_size(), self._loading(trainer))
        if threading.current_thread() is not threading.main_thread():
            return
        launcher = trainer.strategy.launcher
        self._forward = getattr(launcher, "kill", None) if launcher is not None else None
        handler = in_this_process_only(self._on_stop_signal)
        self._previous = {s: signal.signal(s, handler) for s in heeded_signals()}

    def on_train_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self._restore()
        if self._heartbeat is not None:
            self._heartbeat.stop()

    def on_exception(self, trainer: Trainer, pl_module: LightningModule, exception: BaseException) -> None:
        self._restore()
        stop_watching_started_ranks()  # from here this process ends them itself (aesplat.lightning_cli)
        if self._distributed and lost_peer(exception):
            self._find_lost(trainer, exception)
        elif trainer.world_size > 1 and trainer.state.fn == TrainerFn.FITTING and timed_out(exception):
            self.slow = self._timed_out_setting_up(trainer, exception)  # before training: no heartbeat yet

    def _find_lost(self, trainer: Trainer, exception: BaseException) -> None:
        """Say which ranks were lost (``lost``): those whose heartbeat stopped; or, when every rank is alive
        and the collective timed out, which ranks had not arrived (``slow``). Neither when there is no
        heartbeat to read, or every rank is alive and the collective failed otherwise."""
        if self._heartbeat is None:
            return
        lost = self._heartbeat.silent()  # this rank beats on meanwhile: another may be asking too
        positions = self._heartbeat.positions() if not lost and timed_out(exception) else {}
        self._heartbeat.stop()
        rank, size = dist.get_rank(), dist.get_world_size()
        if positions:
            self.slow = self._slow_line(positions, rank, size)
        if not lost:  # everyone is alive: the failure was not a lost rank
            return
        what = "rank" if len(lost) == 1 else "ranks"
        folders = sorted({str(c.dirpath) for c in trainer.checkpoint_callbacks if getattr(c, "dirpath", None)})
        where = f"the checkpoints in {', '.join(folders)}" if folders else "the checkpoints"
        ranks, seen = self._named(lost), _first_line(exception)
        self.lost = (f"{what} {ranks} of {size} lost at step {trainer.global_step} (rank {rank} saw: {seen}); "
                     f"nothing was saved after it, {where} are as the last save left them: resume with "
                     "--ckpt_path last")  # fmt: skip

    def _named(self, ranks: list[int]) -> str:
        return ", ".join(f"{r} (node {self.nodes[r]})" if r < len(self.nodes) else str(r) for r in ranks)

    def _slow_line(self, positions: dict[int, tuple[int, str]], rank: int, size: int) -> str:
        """Every rank alive, this one's collective timed out: the ranks that had not come as far (where their
        heartbeats last said they were), where this one waited, and the fix."""
        order, here = positions[rank]
        behind = sorted(r for r, (o, _) in positions.items() if o < order)
        behind += [r for r in range(size) if r not in positions]  # no heartbeat yet: still setting up
        fix = ("raise --distributed.timeout above the longest one rank can lag behind the others (a first "
               "batch from a cold cache, a checkpoint save) and resume with --ckpt_path last")  # fmt: skip
        waited = f"after {self.timeout:g} s (--distributed.timeout) {here}"
        if not behind:
            return f"every rank of {size} was alive, but rank {rank} gave up waiting for them {waited}; {fix}"
        doing = [positions[r][1] if r in positions else "setting up" for r in behind]
        if len(set(doing)) == 1:
            still = f"still {doing[0]}"
        else:
            still = "; ".join(f"rank {r} still {d}" for r, d in zip(behind, doing, strict=True))
        what, was, them = ("rank", "was", "it") if len(behind) == 1 else ("ranks", "were", "them")
        return (f"{what} {self._named(behind)} of {size} {was} alive but slow, {still}, when rank {rank} gave "
                f"up waiting for {them} {waited}; {fix}")  # fmt: skip

    def _timed_out_setting_up(self, trainer: Trainer, exception: BaseException) -> str:
        """A timeout before training: the ranks joining the process group (how many had not joined, in the
        store's words), or a collective of the set-up."""
        rank, size = trainer.global_rank, trainer.world_size
        waited = f"after {self.timeout:g} s (--distributed.timeout)"
        fix = "raise --distributed.timeout above the time the slowest rank takes to start"
        joined = re.search(r"(\d+)/(\d+) clients joined", str(exception))
        if joined:
            missing = int(joined.group(2)) - int(joined.group(1))
            them = "it" if missing == 1 else "them"
            return (f"{missing} of the {size} ranks had not joined the process group when rank {rank} gave up "
                    f"waiting for {them} {waited}: still starting; {fix}")  # fmt: skip
        return (f"rank {rank} gave up waiting for the other ranks {waited} while setting up, before training "
                f"(it saw: {_first_line(exception)}); {fix}")  # fmt: skip

    # ----------------------------------------------------------------------------------------- positions
    def _at(self, phase: int, what: str) -> None:
        """Where this rank is now, for the heartbeat to publish: ``phase`` orders the points of one batch."""
        if self._heartbeat is not None:
            self._heartbeat.where = (10 * self._batches + phase, what)

    def _loading(self, trainer: Trainer) -> tuple[int, str]:
        return 10 * self._batches + 5, f"loading its batch for step {trainer.global_step + 1}"

    def on_train_batch_start(self, trainer: Trainer, pl_module: LightningModule, batch, batch_idx: int) -> None:
        self._batches += 1
        self._at(1, f"in the forward pass of step {trainer.global_step + 1}")

    def on_before_backward(self, trainer: Trainer, pl_module: LightningModule, loss) -> None:
        self._at(2, f"in the backward pass of step {trainer.global_step + 1}")

    def on_after_backward(self, trainer: Trainer, pl_module: LightningModule) -> None:
        self._at(3, f"in the optimizer step of step {trainer.global_step + 1}")

    def on_validation_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.state.fn == TrainerFn.FITTING and not trainer.sanity_checking:
            self._at(6, f"validating after step {trainer.global_step}")

    def _restore(self) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}

    def _on_stop_signal(self, signum: int, frame: object) -> None:
        if self.stop_signal is not None:
            raise Stopped(signum, f"stopped by a second {signal_name(signum)}, without saving")
        self.stop_signal = signum
        if self._forward is not None:
            self._forward(signum)

    # ----------------------------------------------------------------------------------------- step boundary
    def _agree(self, trainer: Trainer, pl_module: LightningModule, requeue: bool) -> tuple[bool, int]:
        """(any rank has the requeue signal pending, the stop signal any rank received or 0). Under DDP one
        all-reduce of host tensors over the CPU group, which waits for no device; nothing otherwise."""
        pending = requeue and REQUEUE_SIGNAL in signal.sigpending()
        stop = self.stop_signal or 0
        if self._distributed:
            flags = torch.tensor([int(pending), stop], dtype=torch.int64)
            dist.all_reduce(flags, op=dist.ReduceOp.MAX, group=self._group)
            return bool(flags[0]), int(flags[1])
        return pending, stop

    def on_train_batch_end(self, trainer: Trainer, pl_module: LightningModule, outputs, batch, batch_idx: int):
        step = trainer.global_step
        self._at(4, f"at the end of step {step}")
        requeue, stop = self._agree(trainer, pl_module, self.requeue_active and not self.requeued)
        self._at(5, f"after step {step} (saving a checkpoint, validating or loading its next batch)")
        if requeue:
            self._requeue(trainer)
        elif stop:
            self._stop(trainer, stop)

    def on_validation_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        if trainer.state.fn != TrainerFn.FITTING or trainer.sanity_checking:
            return
        step = trainer.global_step
        self._at(7, f"at the end of the validation after step {step}")
        _, stop = self._agree(trainer, pl_module, requeue=False)
        self._at(8, f"after the validation after step {step} (saving a checkpoint or loading its next batch)")
        if stop:
            self._stop(trainer, stop)

    def _stop(self, trainer: Trainer, signum: int) -> None:
        if self.stopped_at is not None:
            return
        self.stop_signal = self.stop_signal or signum
        self.stopped_at = trainer.global_step
        trainer.should_stop = True  # RunCheckpoint saves last.ckpt at this step; the fit then ends
        rank_zero_info(f"{signal_name(signum)} after step {trainer.global_step}: saving and stopping")

    def _requeue(self, trainer: Trainer) -> None:
        self.requeued = True
        rank_zero_info(f"requeue signal after step {trainer.global_step}: checkpoint and requeue")
        if REQUEUE_SIGNAL not in signal.sigpending():  # another rank got it: take the same path
            signal.raise_signal(REQUEUE_SIGNAL)
        # Unblocking delivers the pending signal, and Python runs Lightning's handler before this call returns
        # (hpc_ckpt_N.ckpt, collective on every rank; `scontrol requeue` on rank 0). Later signals stay held.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {REQUEUE_SIGNAL})
        signal.pthread_sigmask(signal.SIG_BLOCK, {REQUEUE_SIGNAL})
        deadline = time.monotonic() + self.wait_for_kill
        while self.stop_signal is None and time.monotonic() < deadline:
            time.sleep(0.2)
        if self.stop_signal is not None:  # SLURM ends this job; the requeued one resumes from hpc_ckpt_N
            raise Stopped(self.stop_signal, f"requeued after step {trainer.global_step}: the job resumes "
                          "from its hpc_ckpt file")  # fmt: skip
        rank_zero_warn(f"no SIGTERM {self.wait_for_kill:g} s after the requeue: training on")
