"""benchmarks/bench_check.py: which pairs of bench points it holds against each other, and how it reads them."""

import math

from .script_loader import load_benchmark

check = load_benchmark("bench_check")


def row(knob: str, label: str, setting: dict, total: tuple[float, float], speedup: tuple[float, float, float],
        baseline: bool = False) -> dict:  # fmt: skip
    base = {"sh_degree": None, "render_size": None, "keep_fraction": 1.0, "min_opacity": 0.0}
    return {"knob": knob, "label": label, "setting": {**base, **setting}, "total_ms_lo": total[0],
            "total_ms_hi": total[1], "speedup": speedup[0], "speedup_lo": speedup[1], "speedup_hi": speedup[2],
            "baseline": baseline}  # fmt: skip


def rows(sh0_total=(40.0, 50.0), sh0_speedup=(1.0, 0.9, 1.1)) -> dict:
    out = [
        row("sh_degree", "SH 0", {"sh_degree": 0}, sh0_total, sh0_speedup),
        row("sh_degree", "SH 1", {"sh_degree": 1}, (41.0, 52.0), (1.0, 0.95, 1.05)),
        row("sh_degree", "SH 2", {}, (42.0, 55.0), (1.0, 1.0, 1.0), baseline=True),
        row("render_size", "10 px", {"render_size": 10}, (30.0, 40.0), (1.3, 1.2, 1.4)),
        row("render_size", "42 px", {}, (42.0, 55.0), (1.0, 1.0, 1.0), baseline=True),
        row("keep_fraction", "10 %", {"keep_fraction": 0.1}, (20.0, 25.0), (2.0, 1.8, 2.2)),
        row("keep_fraction", "50 %", {"keep_fraction": 0.5}, (30.0, 35.0), (1.5, 1.4, 1.6)),
        row("keep_fraction", "100 %", {}, (42.0, 55.0), (1.0, 1.0, 1.0), baseline=True),
        row("min_opacity", "≥ 0", {}, (42.0, 55.0), (1.0, 1.0, 1.0), baseline=True),
        row("min_opacity", "≥ 0.8", {"min_opacity": 0.8}, (30.0, 40.0), (1.3, 1.2, 1.4)),
    ]
    return {(r["knob"], r["label"]): r for r in out}


def test_subset_pairs_put_the_lesser_work_first():
    pairs = [(a[1], b[1]) for a, b in check.subset_pairs(rows())]
    assert pairs == [("SH 0", "SH 1"), ("SH 0", "SH 2"), ("SH 1", "SH 2"), ("10 px", "42 px"), ("10 %", "50 %"),
                     ("50 %", "100 %"), ("≥ 0.8", "≥ 0")]  # fmt: skip


def test_a_subset_reported_slower_is_caught_either_way():
    assert not any(c["significantly_slower"] for c in check.subset_check(rows()))
    # Its interval wholly above the superset's (SH 0 against SH 1 and SH 2):
    above = check.subset_check(rows(sh0_total=(56.0, 60.0)))
    assert [(c["subset"][1], c["of"][1]) for c in above if c["significantly_slower"]] == [
        ("SH 0", "SH 1"),
        ("SH 0", "SH 2"),
    ]
    # "slower" than the baseline by its paired speed-up, the totals' intervals overlapping:
    paired = check.subset_check(rows(sh0_speedup=(0.9, 0.85, 0.95)))
    assert [(c["subset"][1], c["of"][1]) for c in paired if c["significantly_slower"]] == [("SH 0", "SH 2")]


def test_agreement_of_two_runs():
    first, second = rows(), rows()
    second["render_size", "10 px"] = {**second["render_size", "10 px"], "speedup": 1.45}  # outside 1.2-1.4
    second["keep_fraction", "50 %"] = {**second["keep_fraction", "50 %"], "speedup": 1.55}  # inside
    verdicts = {tuple(a["point"]): a["agree"] for a in check.agreement(first, second)}
    assert verdicts[("render_size", "10 px")] is False and verdicts[("keep_fraction", "50 %")] is True
    assert verdicts[("sh_degree", "SH 0")] is True  # both "no measurable difference"
    assert ("sh_degree", "SH 2") not in verdicts  # the baseline is not a speed-up
    assert check.verdict(rows()["sh_degree", "SH 0"]) == "no measurable difference"
    assert check.verdict({"speedup": 1.1, "speedup_lo": math.nan, "speedup_hi": math.nan}) == "untested"
