"""`aesplat bench`'s timing on a fake clock: interleaved rounds, medians with intervals, paired speed-ups, and a
slow phase of the machine that must not turn into a setting being "slower"."""

import math
import subprocess
import sys
import time
from dataclasses import replace

import pytest
import torch

import aesplat.bench.run as bench_run
from aesplat.bench.run import Bench
from aesplat.bench.sweep import Point, Setting
from aesplat.bench.timing import (
    Estimate,
    LoadWatch,
    Stopwatch,
    busy_warning,
    calls_per_round,
    interleaved,
    round_order,
    speed_verdict,
    speedup,
)
from aesplat.model import build_model
from aesplat.types import BatchedExample, BatchedViews
from tests.helpers import SH_DEGREE, identity_views

pytestmark = pytest.mark.filterwarnings("ignore:LPIPS metric unavailable")

SIZE = 28


def views(v: int, size: int = SIZE) -> BatchedViews:
    return identity_views(v, size)


class FakeClock:
    """Seconds that pass only when a task says it worked; the calls numbered in ``slow`` take ``factor`` times
    as long (another process taking the cores for a while)."""

    def __init__(self, slow: range = range(0), factor: float = 3.0) -> None:
        self.t, self.calls, self.slow, self.factor = 0.0, 0, slow, factor

    def now(self) -> float:
        return self.t

    def work(self, ms: float) -> None:
        self.t += ms / 1000.0 * (self.factor if self.calls in self.slow else 1.0)
        self.calls += 1


def costing(clock: FakeClock, ms: float):
    return lambda _round_input=None: clock.work(ms)


def blockwise(tasks: dict, rounds: int, stopwatch: Stopwatch) -> dict:
    """The former scheme, for contrast: each task timed in its own block of repeats."""
    return {key: [stopwatch(fn)[0] for _ in range(rounds)] for key, fn in tasks.items()}


ROUNDS = 9
SLOW = range(9, 18)  # nine calls in a row: the whole second block of the blockwise scheme


def test_a_slow_phase_makes_one_block_slower_but_no_interleaved_setting():
    clock = FakeClock(SLOW)
    tasks = {name: costing(clock, 10.0) for name in "ABCD"}  # four settings of the same cost; A the baseline
    old = blockwise(tasks, ROUNDS, Stopwatch(now=clock.now))
    assert speed_verdict(speedup(old["A"], old["B"])) == "slower"  # what the former bench reported
    assert speedup(old["A"], old["B"]).value == pytest.approx(1 / 3)

    clock.t, clock.calls = 0.0, 0  # the same slow phase, now over interleaved rounds
    new = interleaved(tasks, ROUNDS, Stopwatch(now=clock.now))
    assert all(len(samples) == ROUNDS for samples in new.values())
    for name in "BCD":
        ratio = speedup(new["A"], new[name])
        assert ratio.value == pytest.approx(1.0) and ratio.contains(1.0), (name, ratio)
        assert speed_verdict(ratio) == "no measurable difference"
        est = Estimate.of(new[name])  # the slow phase widens the interval, the median stays
        assert est.value == pytest.approx(10.0) and est.lo == pytest.approx(10.0) and est.hi > 10.0


def test_real_differences_survive_the_slow_phase():
    clock = FakeClock(SLOW)
    tasks = {"base": costing(clock, 10.0), "cheap": costing(clock, 5.0), "dear": costing(clock, 20.0)}
    samples = interleaved(tasks, ROUNDS, Stopwatch(now=clock.now))
    cheap, dear = speedup(samples["base"], samples["cheap"]), speedup(samples["base"], samples["dear"])
    assert speed_verdict(cheap) == "faster" and cheap.value == pytest.approx(2.0) and cheap.lo > 1.0
    assert speed_verdict(dear) == "slower" and dear.value == pytest.approx(0.5) and dear.hi < 1.0
    # Too few rounds for a 95 % interval: no verdict either way.
    few = interleaved(tasks, 5, Stopwatch(now=FakeClock().now))
    assert speed_verdict(speedup(few["base"], few["dear"])) == "untested"


def test_rounds_rotate_the_order_and_share_their_input():
    keys = ["a", "b", "c", "d"]
    orders = [round_order(keys, r, 4) for r in range(4)]
    assert all(sorted(o) == keys for o in orders)
    for position in range(4):  # each key takes each place once over four rounds
        assert sorted(o[position] for o in orders) == keys
    assert round_order(keys, 1, 2) == ["c", "d", "a", "b"]
    seen = []
    interleaved({k: (lambda arg, k=k: seen.append((k, arg))) for k in "xy"}, 3, Stopwatch(now=lambda: 0.0),
                round_input=lambda r: f"scenes of round {r}")  # fmt: skip
    assert [arg for _, arg in seen] == [f"scenes of round {r}" for r in range(3) for _ in "xy"]


def test_stopwatch_and_calls_per_round():
    clock = FakeClock()
    ms, result = Stopwatch(now=clock.now)(lambda: clock.work(2.0) or "done", calls=3)
    assert ms == pytest.approx(2.0) and result == "done" and clock.calls == 3
    assert calls_per_round(30.0) == 1 and calls_per_round(5.0) == 4 and calls_per_round(0.5) == 16
    assert calls_per_round(math.nan) == 16


def test_the_bench_times_interleaved_and_reports_paired_intervals(monkeypatch):
    """The whole ``Bench.run`` on the fake clock: a render costs 10 ms whatever the SH degree, 5 ms with half
    the Gaussians; a slow phase falls in the middle of the timing."""
    clock = FakeClock(range(60, 78))
    real_render = bench_run.render

    def render(gaussians, *args, **kwargs):
        clock.work(10.0 * gaussians.num_gaussians / (2 * SIZE * SIZE))
        return real_render(gaussians, *args, **kwargs)

    monkeypatch.setattr(bench_run, "render", render)
    torch.manual_seed(0)
    model = build_model(size="tiny", sh_degree=SH_DEGREE, near=0.1, far=20.0).eval()
    scenes = [BatchedExample(context=views(2), target=views(1), scene=[f"s{i}"]) for i in range(3)]
    base = Setting()
    points = [Point("sh_degree", "SH 0", replace(base, sh_degree=0)), Point("sh_degree", "SH 2", base),
              Point("keep_fraction", "50 %", replace(base, keep_fraction=0.5))]  # fmt: skip
    bench = Bench(model, scenes, torch.device("cpu"), repeats=ROUNDS, round_scenes=2, progress=False,
                  stopwatch=Stopwatch(now=clock.now))  # fmt: skip
    rows = {r.label: r for r in bench.run(points, base, warmup_runs=0)}
    sh0, half = rows["SH 0"], rows["50 %"]
    assert sh0.speedup == pytest.approx(1.0) and sh0.speedup_lo <= 1.0 <= sh0.speedup_hi
    assert half.speedup == pytest.approx(2.0) and half.speedup_lo > 1.0
    assert rows["SH 2"].baseline and rows["SH 2"].render_ms == pytest.approx(10.0)
    assert rows["SH 2"].render_ms_hi > 10.0  # the slow phase shows in the interval, not in the median
    assert half.render_ms == pytest.approx(5.0) and half.render_calls == 2  # a cheap render runs twice a timing
    # Quality: per-scene changes with a t-interval over the three scenes.
    assert len(sh0.scene_psnr) == 3 and sh0.psnr_delta == pytest.approx(
        sum(a - b for a, b in zip(sh0.scene_psnr, rows["SH 2"].scene_psnr)) / 3
    )
    assert sh0.psnr_delta_lo < sh0.psnr_delta < sh0.psnr_delta_hi
    # Every round timed two scenes, taking turns: 0 1, 2 0, 1 2, ...
    assert [bench.round_indices(r) for r in range(3)] == [[0, 1], [2, 0], [1, 2]]


def test_load_watch_sees_another_busy_process_and_the_bench_warns():
    quiet = {"load_before": [0.1, 0, 0], "load_after": [0.4, 0, 0], "other_cores": 0.02, "cpu_count": 2}
    assert busy_warning(quiet, 2) is None
    watch = LoadWatch()
    spinner = subprocess.Popen(
        [sys.executable, "-c", "import time\nend = time.time() + 1.5\nwhile time.time() < end: pass"]
    )
    spinner.wait()
    time.sleep(0.1)
    load = watch.stop()
    assert load["other_cores"] >= 0.5 and load["cpu_count"] >= 1 and len(load["load_before"]) == 3
    line = busy_warning(load, 2)
    assert (
        line.startswith("aesplat bench: warning: other processes kept") and f"{load['other_cores']:.1f}" in line
    )
    assert "\n" not in line


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_steady_allocator_sets_glibc_malloc_in_its_process():
    """In a process of its own (the setting stays for the process's life): mallopt accepts both settings."""
    code = "from aesplat.bench.timing import steady_allocator; print(steady_allocator())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "glibc malloc with a fixed 32 MiB mmap threshold and no trimming"
