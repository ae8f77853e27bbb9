"""Timing that a busy machine cannot turn into a speed-up: the stopwatch (wall clock on the CPU, CUDA events
after a synchronise on a GPU), interleaved rounds over every setting, medians with distribution-free 95 %
intervals, speed-ups as paired per-round ratios, and what else the machine was doing meanwhile.

Why interleaved: timing each setting in its own block (warm-up, then its repeats) lets any change of load
between blocks land on one setting, which then looks slower or faster than it is. In a round every setting
runs once (the baseline too), in an order rotated from round to round, so a slow phase falls on the settings
of the rounds it spans alike, and a setting's ratio to the baseline is taken within each round before the
median is taken over rounds.
"""

from __future__ import annotations

import ctypes
import math
import os
import time
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, TypeVar

import torch

from ..stats import interval_contains, median_interval

K = TypeVar("K", bound=Hashable)

MIN_TIMED_MS = 20.0  # a cheap setting runs back to back until a timing spans about this long ...
MAX_CALLS = 16  # ... but at most this many calls per round
BUSY_CORES = 0.5  # other processes using this many cores on average while timing widen the intervals
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)


class Stopwatch:
    """Milliseconds per call of a function run ``calls`` times back to back.

    CPU: the wall clock (``now``, seconds; a test passes a fake one). CUDA: the device is synchronised, then
    CUDA events recorded on the current stream before the first call and after the last, so the figure is the
    device's time for the calls, comparable to every other CUDA timing of the project.
    """

    def __init__(self, device: torch.device | str = "cpu", now: Callable[[], float] = time.perf_counter):
        self.device = torch.device(device)
        self.now = now

    def __call__(self, fn: Callable[[], Any], calls: int = 1) -> tuple[float, Any]:
        """(ms per call, the last call's result)."""
        calls = max(1, int(calls))
        result = None
        if self.device.type == "cuda":
            with torch.cuda.device(self.device):
                torch.cuda.synchronize()
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                for _ in range(calls):
                    result = fn()
                end.record()
                end.synchronize()
                return start.elapsed_time(end) / calls, result
        begin = self.now()
        for _ in range(calls):
            result = fn()
        return 1000.0 * (self.now() - begin) / calls, result


def calls_per_round(first_ms: float, min_ms: float = MIN_TIMED_MS, cap: int = MAX_CALLS) -> int:
    """Back-to-back calls that make one timing of a setting whose untimed first call took ``first_ms``: more
    where a setting is cheap, so that the clock's and the scheduler's jitter weigh little in its figure."""
    if not math.isfinite(first_ms) or first_ms <= 0:
        return cap
    return max(1, min(cap, math.ceil(min_ms / first_ms)))


def round_order(keys: Sequence[K], round_index: int, rounds: int) -> list[K]:
    """The order of the settings in one round: rotated by an even share of the list each round, so every
    setting takes early and late places in turn (a drift within rounds does not fall on the same ones)."""
    n = len(keys)
    if n == 0:
        return []
    shift = (round_index * n) // max(1, rounds) % n
    return list(keys[shift:]) + list(keys[:shift])


def interleaved(
    tasks: Mapping[K, Callable[[Any], Any]],
    rounds: int,
    stopwatch: Stopwatch,
    calls: Mapping[K, int] | None = None,
    round_input: Callable[[int], Any] = lambda r: r,
    progress: Callable[[int], Any] | None = None,
) -> dict[K, list[float]]:
    """Time every task once per round for ``rounds`` rounds, in ``round_order``; returns each task's
    milliseconds per call, one figure per round. Every task of round r is called with ``round_input(r)``
    (what the round works on: the same for all, so the figures of one round pair up). ``calls``:
    back-to-back calls per timing (default 1); ``progress`` is told the number of timings done after each."""
    keys = list(tasks)
    samples: dict[K, list[float]] = {k: [] for k in keys}
    for r in range(rounds):
        arg = round_input(r)
        for key in round_order(keys, r, rounds):
            ms, _ = stopwatch(partial(tasks[key], arg), (calls or {}).get(key, 1))
            samples[key].append(ms)
            if progress is not None:
                progress(1)
    return samples


@dataclass(frozen=True)
class Estimate:
    """A median with its 95 % interval (NaN bounds: too few rounds for one)."""

    value: float
    lo: float
    hi: float

    @classmethod
    def of(cls, values: Sequence[float]) -> Estimate:
        return cls(*median_interval(values))

    def contains(self, x: float) -> bool | None:
        return interval_contains(self.lo, self.hi, x)


def per_round_totals(*parts: Sequence[float]) -> list[float]:
    """Round by round, the sum of the parts (a forward's and a render's milliseconds of the same round)."""
    return [sum(values) for values in zip(*parts, strict=True)]


def speedup(baseline: Sequence[float], other: Sequence[float]) -> Estimate:
    """The baseline's time over ``other``'s, round by round (paired: both ran in the same round), then the
    median and its interval over rounds. Above 1: ``other`` is faster."""
    return Estimate.of([b / o if o > 0 else math.nan for b, o in zip(baseline, other, strict=True)])


def speed_verdict(estimate: Estimate) -> str:
    """ "faster", "slower", "no measurable difference" (the interval holds 1) or "untested" (no interval)."""
    holds = estimate.contains(1.0)
    if holds is None:
        return "untested"
    if holds:
        return "no measurable difference"
    return "faster" if estimate.value > 1.0 else "slower"


class LoadWatch:
    """What else the machine did while a measurement ran: the load averages before and after, and the cores
    that other processes kept busy on average (Linux: /proc/stat's busy time less this process's own CPU
    time; None elsewhere)."""

    def __init__(self) -> None:
        self.before = _loadavg()
        self._busy0, self._own0, self._wall0 = _busy_seconds(), _own_seconds(), time.monotonic()

    def stop(self) -> dict:
        wall = time.monotonic() - self._wall0
        busy = _busy_seconds()
        other = None
        if busy is not None and self._busy0 is not None and wall > 0:
            other = max(0.0, ((busy - self._busy0) - (_own_seconds() - self._own0)) / wall)
        return {
            "load_before": self.before,
            "load_after": _loadavg(),
            "other_cores": None if other is None else round(other, 2),
            "cpu_count": os.cpu_count(),
            "seconds": round(wall, 1),
        }


def steady_allocator() -> str:
    """Keep freed memory in this process (glibc's malloc: a fixed mmap threshold of 32 MiB instead of the
    adaptive one, and no trimming of the heap), so that a setting's time does not depend on what the allocator
    happened to hand back to the system before it: with the adaptive defaults, the time of a forward against
    another differed by several per cent from one process to the next. Returns what was set, in words (the
    allocator as it was where there is no glibc)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return "the platform's default"
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    if mallopt(M_MMAP_THRESHOLD, 32 << 20) == 1 and mallopt(M_TRIM_THRESHOLD, 1 << 30) == 1:
        return "glibc malloc with a fixed 32 MiB mmap threshold and no trimming"
    return "the platform's default"


def other_cores_busy(seconds: float = 0.5) -> float | None:
    """The cores other processes keep busy, watched for ``seconds`` while this one sleeps (None off Linux)."""
    watch = LoadWatch()
    time.sleep(seconds)
    return watch.stop()["other_cores"]


def busy_warning(load: Mapping[str, Any], threads: int) -> str | None:
    """One line when other work was heavy enough to widen the intervals, else None."""
    other = load.get("other_cores")
    before, after = (load.get(k) or [math.nan] for k in ("load_before", "load_after"))
    loads = f"load average {before[0]:.1f} before, {after[0]:.1f} after"
    if other is not None:
        if other < BUSY_CORES:
            return None
        cores = load.get("cpu_count")
        figure = f"other processes kept {other:.1f} of {cores} cores busy while it timed ({loads})"
    elif before[0] >= BUSY_CORES:  # no /proc/stat: the load average before the run is what is known
        figure = f"the machine was busy when it started ({loads})"
    else:
        return None
    return (
        f"aesplat bench: warning: {figure}, beside its {threads} thread(s): the intervals are wider and the "
        "milliseconds higher than on a quiet machine (the speed-ups stay paired within each round)"
    )


def _loadavg() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return [math.nan] * 3


def _own_seconds() -> float:
    t = os.times()
    return t.user + t.system


def _busy_seconds() -> float | None:
    """CPU seconds every core spent busy since boot (all processes), from /proc/stat; None without it."""
    try:
        with open("/proc/stat") as f:
            fields = [float(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 5:
        return None
    idle = fields[3] + fields[4]  # idle, iowait
    return (sum(fields[:7]) - idle) / os.sysconf("SC_CLK_TCK")  # user .. softirq (guest time is inside user)
