#!/usr/bin/env python
"""Can `aesplat bench` be believed on a busy machine? Its goals, measured on the demo's checkpoint.

    python benchmarks/bench_check.py [--ckpt outputs/demo/run/checkpoints/last.ckpt] [--reference 289d332]
        [--pairs 3] [--work outputs/bench_check] [--out docs/results/bench]

1. Beside one busy process (``python -c "while True: pass"``, one core), `aesplat bench --ckpt CKPT` with its
   defaults runs twice. Checked on those two runs:
   - no setting that does a subset of another's work is reported significantly slower than it (its total
     time's interval lies wholly above the other's: low end above the other's high end), nor "slower" than
     the baseline when the other is the baseline: SH 0 and SH 1 against SH 2 (and SH 0 against SH 1), each
     smaller render against the full-size one, fewer kept Gaussians against more, a higher opacity threshold
     against a lower one;
   - the two runs agree: every speed-up of the second run lies inside the first run's interval, or both say
     "no measurable difference".
2. On the machine without the busy process, the wall time of the whole command with its defaults, this
   checkout's against ``--reference``'s (the bench before interleaved timing; its ``src/`` extracted with
   ``git archive``), ``--pairs`` runs each, alternating which goes first.

Every run is kept under ``--work`` and not repeated when the script runs again (delete the folder, or a run's
folder, to measure anew). Writes ``--out``/check.json (figures, the date, commit, machine and load of every
run), ``--out``/check.md (the tables the bench page includes) and ``--out``/busy-1 and busy-2 (the two busy
runs' BENCH.md and bench.json) and quiet/ (the last quiet run's, with its plot).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from common import REPO, provenance, write_whole

from aesplat.bench.timing import Estimate, speed_verdict

BUSY = "while True: pass"
REFERENCE = "289d332"  # the last commit whose bench timed each setting in a block of its own


def bench_command(ckpt: Path, out: Path) -> list[str]:
    """`aesplat bench` with its defaults; paths relative to the repository (they show in BENCH.md)."""
    paths = [os.path.relpath(p, REPO) for p in (ckpt, out)]
    return [sys.executable, "-m", "aesplat.cli", "bench", "--ckpt", paths[0], "--out", paths[1],
            "--no-progress"]  # fmt: skip


def run_bench(ckpt: Path, out: Path, src: Path) -> dict:
    """`aesplat bench` with its defaults from the package under ``src`` in a process of its own: its wall
    seconds and the 1-minute load average before and after."""
    env = {**os.environ, "PYTHONPATH": str(src), "WANDB_MODE": "disabled", "PYTHONWARNINGS": "ignore"}
    env.pop("AESPLAT_THREADS", None)
    before = os.getloadavg()[0]
    start = time.perf_counter()
    proc = subprocess.run(bench_command(ckpt, out), cwd=REPO, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"bench_check: `aesplat bench` from {src} failed:\n{proc.stderr[-3000:]}")
    load_after = round(os.getloadavg()[0], 2)
    return {"seconds": round(seconds, 2), "load_before": round(before, 2), "load_after": load_after,
            "provenance": provenance()}  # fmt: skip


def reference_src(work: Path, ref: str) -> Path:
    """``src/`` of commit ``ref``, extracted once under ``work``."""
    folder = work / f"reference-{ref}"
    if not (folder / "src" / "aesplat" / "__init__.py").is_file():
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        archive = subprocess.run(
            ["git", "archive", ref, "src"], cwd=REPO, capture_output=True, check=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    return folder / "src"


# ---------------------------------------------------------------------------------------------------- checks


def rows_of(bench_json: Path) -> dict[tuple[str, str], dict]:
    """The measured rows of a bench.json by (knob, label)."""
    rows = json.loads(bench_json.read_text())["rows"]
    return {(r["knob"], r["label"]): r for r in rows if not r.get("skipped")}


def verdict(row: dict) -> str:
    """The bench's own reading of a row's speed-up (faster, slower, no measurable difference, untested)."""
    return speed_verdict(Estimate(row["speedup"], row["speedup_lo"], row["speedup_hi"]))


def subset_pairs(rows: dict[tuple[str, str], dict]) -> list[tuple[tuple[str, str], tuple[str, str]]]:
    """(smaller, larger) pairs of points where the first does a subset of the second's work: fewer SH bands,
    a smaller render, fewer kept Gaussians, a higher opacity threshold (each knob's points in its order)."""

    def series(knob: str, key) -> list[tuple[str, str]]:
        return sorted((k for k in rows if k[0] == knob), key=lambda k: key(rows[k]))

    pairs = []
    sh = series(
        "sh_degree", lambda r: r["setting"]["sh_degree"] if r["setting"]["sh_degree"] is not None else 99
    )
    pairs += [(a, b) for i, a in enumerate(sh) for b in sh[i + 1 :]]
    size = series("render_size", lambda r: r["setting"]["render_size"] or 10**6)
    pairs += [(a, size[-1]) for a in size[:-1]]
    keep = series("keep_fraction", lambda r: r["setting"]["keep_fraction"])
    pairs += list(zip(keep[:-1], keep[1:]))
    threshold = series("min_opacity", lambda r: -r["setting"]["min_opacity"])
    pairs += list(zip(threshold[:-1], threshold[1:]))
    return pairs


def subset_check(rows: dict[tuple[str, str], dict]) -> list[dict]:
    """Per subset pair: whether the smaller one is reported significantly slower than the larger."""
    out = []
    for small, large in subset_pairs(rows):
        a, b = rows[small], rows[large]
        above = a["total_ms_lo"] > b["total_ms_hi"]  # its interval wholly above the other's
        slower = b["baseline"] and verdict(a) == "slower"
        out.append({"subset": list(small), "of": list(large), "total_ms": [a["total_ms_lo"], a["total_ms_hi"]],
                    "of_total_ms": [b["total_ms_lo"], b["total_ms_hi"]], "verdict": verdict(a),
                    "significantly_slower": bool(above or slower)})  # fmt: skip
    return out


def agreement(first: dict[tuple[str, str], dict], second: dict[tuple[str, str], dict]) -> list[dict]:
    """Per point measured in both runs (the baseline left out): do the two runs agree on its speed-up?"""
    out = []
    for key in (k for k in first if k in second and not first[k]["baseline"]):
        a, b = first[key], second[key]
        both_none = verdict(a) == verdict(b) == "no measurable difference"
        inside = a["speedup_lo"] <= b["speedup"] <= a["speedup_hi"]
        out.append({"point": list(key), "first": [a["speedup"], a["speedup_lo"], a["speedup_hi"], verdict(a)],
                    "second": [b["speedup"], b["speedup_lo"], b["speedup_hi"], verdict(b)],
                    "agree": bool(both_none or inside)})  # fmt: skip
    return out


def baseline_ms(bench_json: Path) -> dict[str, float]:
    """The baseline row's forward and render milliseconds of a bench.json (either bench's)."""
    row = next(r for r in json.loads(bench_json.read_text())["rows"] if r["baseline"] and not r["skipped"])
    return {"forward_ms": row["forward_ms"], "render_ms": row["render_ms"]}


def overlap(first: dict[tuple[str, str], dict], second: dict[tuple[str, str], dict]) -> int:
    """Points (the baseline left out) whose speed-up intervals in the two runs share a value."""
    keys = [k for k in first if k in second and not first[k]["baseline"]]
    return sum(max(first[k]["speedup_lo"], second[k]["speedup_lo"]) <= min(first[k]["speedup_hi"],
               second[k]["speedup_hi"]) for k in keys)  # fmt: skip


def between_runs(runs: dict[str, Path]) -> list[dict]:
    """Every ordered pair of this checkout's runs: how many speed-ups of the second lie in the first's
    interval (or both read "no measurable difference"), and how many intervals overlap."""
    rows = {name: rows_of(path) for name, path in runs.items()}
    out = []
    for a in rows:
        for b in (b for b in rows if b != a):
            agreed = agreement(rows[a], rows[b])
            out.append({"first": a, "second": b, "inside": sum(x["agree"] for x in agreed),
                        "overlap": overlap(rows[a], rows[b]), "points": len(agreed)})  # fmt: skip
    return out


# ---------------------------------------------------------------------------------------------------- report


def markdown(result: dict) -> str:
    busy, quiet = result["busy"], result["quiet"]
    subsets = busy["subsets"]
    agree = busy["agreement"]
    worst = [s for s in subsets if s["significantly_slower"]]
    disagree = [a for a in agree if not a["agree"]]
    ratio = quiet["ratio"]
    runs = [*busy["runs"].values(), *quiet["runs"]]
    dates = sorted(r["provenance"]["date"] for r in runs)
    ours = [*busy["runs"].values(), *(r for r in quiet["runs"] if r["which"] == "this")]
    commits = sorted({r["provenance"]["commit"] + (" (modified)" if r["provenance"]["modified"] else "")
                      for r in ours})  # fmt: skip
    machine = runs[0]["provenance"]["machine"]
    lines = [
        f"Measured {dates[0]} to {dates[-1]} on commit {', '.join(commits)}, {machine['cpu']}, "
        f'{machine["cores"]} cores, by `python benchmarks/bench_check.py` on `{result["ckpt"]}`; "quiet" '
        "means no process of the check's beside the bench (the load averages include the bench's own threads).",
        "",
        "| goal | measured | met |",
        "| --- | --- | --- |",
        f"| beside a busy process, no subset setting significantly slower than its superset | "
        f"{len(worst)} of {len(subsets)} pairs reported slower (runs 1 and 2 together) | "
        f"{'yes' if not worst else 'no'} |",
        f"| two runs agree | {len(agree) - len(disagree)} of {len(agree)} speed-ups of run 2 inside run 1's "
        f'interval, or both "no measurable difference" | {"yes" if not disagree else "no"} |',
        f"| wall time with the defaults, quiet, within 1.5x of the former bench | "
        f"{quiet['new_median_s']:.1f} s against {quiet['reference_median_s']:.1f} s ({quiet['reference']}): "
        f"{ratio:.2f}x (median of {quiet['pairs']} runs each) | {'yes' if ratio <= 1.5 else 'no'} |",
        "",
        "Load while the busy runs measured (the bench's own threads excluded):",
        "",
        "| run | other processes' cores | torch threads of the bench | 1-min load before → after | wall s |",
        "| --- | ---: | ---: | --- | ---: |",
    ]
    for name in ("busy-1", "busy-2"):
        run = busy["runs"][name]
        cells = [name, f"{run['other_cores']:.2f} of {run['cpu_count']}", str(run["threads"]),
                 f"{run['load_before']:.2f} → {run['load_after']:.2f}", f"{run['seconds']:.1f}"]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "Quiet runs (wall seconds; 1-min load average before each): "
        + "; ".join(f"{r['which']} {r['seconds']:.1f} s ({r['load_before']:.2f})" for r in quiet["runs"])
        + ".",
        "",
        "Subset pairs (total ms per scene, 95 % intervals; both runs):",
        "",
        "| run | subset | of | its total ms | the other's | speed-up verdict against the baseline |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for run, checks in (("1", busy["subsets_by_run"]["busy-1"]), ("2", busy["subsets_by_run"]["busy-2"])):
        for s in checks:
            mark = " **(slower)**" if s["significantly_slower"] else ""
            spans = [f"{lo:.1f}–{hi:.1f}" for lo, hi in (s["total_ms"], s["of_total_ms"])]
            lines.append(
                f"| {run} | {s['subset'][1]} | {s['of'][1]} | {spans[0]} | {spans[1]} | {s['verdict']}{mark} |"
            )
    between = result["between_runs"]
    former, ours = quiet["baseline_ms"]["reference"], quiet["baseline_ms"]["this"]
    lines += [
        "",
        "The baseline's milliseconds per scene in the last quiet run of each bench: the former bench's "
        f"back-to-back repeats {former['forward_ms']:.1f} forward + {former['render_ms']:.1f} render, "
        f"interleaved {ours['forward_ms']:.1f} + {ours['render_ms']:.1f}.",
        "",
        "Every pair of this checkout's runs (the busy ones and the quiet ones), the first against the second: "
        "speed-ups of the second inside the first's interval (or both \"no measurable difference\"), and "
        "intervals that overlap:",
        "",
        "| first | second | inside | overlap |",
        "| --- | --- | ---: | ---: |",
        *(f"| {x['first']} | {x['second']} | {x['inside']} of {x['points']} | {x['overlap']} of {x['points']} |"
          for x in between["pairs"]),
        "",
        "The baseline's milliseconds per scene in each run (forward + render): "
        + "; ".join(f"{name} {ms['forward_ms']:.1f} + {ms['render_ms']:.1f}"
                    for name, ms in between["baseline_ms"].items())
        + ".",
    ]  # fmt: skip
    lines += [
        "",
        "Speed-ups of both runs against the baseline (median, 95 % interval):",
        "",
        "| knob | setting | run 1 | run 2 | agree |",
        "| --- | --- | --- | --- | --- |",
    ]
    for a in agree:
        cells = [f"{v[0]:.2f} ({v[1]:.2f}–{v[2]:.2f}) {v[3]}" for v in (a["first"], a["second"])]
        lines.append(
            f"| {a['point'][0]} | {a['point'][1]} | {cells[0]} | {cells[1]} | {'yes' if a['agree'] else 'no'} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", type=Path, default=REPO / "outputs/demo/run/checkpoints/last.ckpt")
    parser.add_argument("--reference", default=REFERENCE, help="commit of the bench to compare wall time with")
    parser.add_argument("--pairs", type=int, default=3, help="quiet runs of each bench for the wall time")
    parser.add_argument("--work", type=Path, default=REPO / "outputs/bench_check")
    parser.add_argument("--out", type=Path, default=REPO / "docs/results/bench")
    args = parser.parse_args()
    if not args.ckpt.is_file():
        raise SystemExit(f"bench_check: no checkpoint at {args.ckpt}: run `make demo` first, or give --ckpt")
    args.work.mkdir(parents=True, exist_ok=True)
    load_start = [round(x, 2) for x in os.getloadavg()]
    src = REPO / "src"

    def fresh(folder: Path) -> bool:  # a finished run newer than the checkpoint
        done = folder / "run.json"
        return done.is_file() and done.stat().st_mtime >= args.ckpt.stat().st_mtime

    # 1. beside a busy process
    busy_runs = {}
    for name in ("busy-1", "busy-2"):
        folder = args.work / name
        if not fresh(folder):
            print(f"bench_check: {name}: aesplat bench beside `python -c '{BUSY}'`", flush=True)
            spinner = subprocess.Popen([sys.executable, "-c", BUSY])
            try:
                time.sleep(2.0)  # the spinner is running before the bench starts
                timing = run_bench(args.ckpt, folder, src)
            finally:
                spinner.kill()
                spinner.wait()
            write_whole(folder / "run.json", json.dumps(timing).encode())
        meta = json.loads((folder / "bench.json").read_text())["meta"]  # the bench's own record
        busy_runs[name] = {**json.loads((folder / "run.json").read_text()), "threads": meta["threads"],
                           "other_cores": meta["load"]["other_cores"],
                           "cpu_count": meta["load"]["cpu_count"]}  # fmt: skip
    first, second = rows_of(args.work / "busy-1" / "bench.json"), rows_of(args.work / "busy-2" / "bench.json")
    by_run = {"busy-1": subset_check(first), "busy-2": subset_check(second)}

    # 2. quiet wall time, alternating which bench goes first
    ref_src = reference_src(args.work, args.reference)
    quiet_runs = []
    for i in range(args.pairs):
        order = [("this", src), ("reference", ref_src)]
        for which, code in order if i % 2 == 0 else order[::-1]:
            folder = args.work / f"quiet-{which}-{i}"
            if not fresh(folder):
                print(f"bench_check: quiet run {i + 1} of {args.pairs}: {which}", flush=True)
                write_whole(folder / "run.json", json.dumps(run_bench(args.ckpt, folder, code)).encode())
            quiet_runs.append({"which": which, **json.loads((folder / "run.json").read_text())})
    new = statistics.median(r["seconds"] for r in quiet_runs if r["which"] == "this")
    old = statistics.median(r["seconds"] for r in quiet_runs if r["which"] == "reference")
    last = {
        which: args.work / f"quiet-{which}-{args.pairs - 1}" / "bench.json" for which in ("this", "reference")
    }
    ours = {name: args.work / name / "bench.json"
            for name in ("busy-1", "busy-2", *(f"quiet-this-{i}" for i in range(args.pairs)))}  # fmt: skip

    result = {
        "provenance": provenance(load_start),  # when the tables were written; each run has its own
        "ckpt": os.path.relpath(args.ckpt, REPO),
        "busy": {
            "runs": busy_runs,
            "subsets": by_run["busy-1"] + by_run["busy-2"],
            "subsets_by_run": by_run,
            "agreement": agreement(first, second),
        },
        "between_runs": {
            "pairs": between_runs(ours),
            "baseline_ms": {name: baseline_ms(path) for name, path in ours.items()},
        },  # fmt: skip
        "quiet": {
            "reference": args.reference,
            "pairs": args.pairs,
            "runs": quiet_runs,
            "new_median_s": new,
            "reference_median_s": old,
            "ratio": round(new / old, 3),
            "baseline_ms": {which: baseline_ms(path) for which, path in last.items()},
        },
    }
    pairs, agreed = result["between_runs"]["pairs"], result["busy"]["agreement"]
    result["summary"] = {  # what the bench page quotes
        "subset_pairs": len(result["busy"]["subsets"]),
        "subset_slower": sum(x["significantly_slower"] for x in result["busy"]["subsets"]),
        "agree": sum(x["agree"] for x in agreed),
        "points": len(agreed),
        "inside_min": min(x["inside"] for x in pairs),
        "inside_max": max(x["inside"] for x in pairs),
        "overlap_min": min(x["overlap"] for x in pairs),
        "overlap_max": max(x["overlap"] for x in pairs),
        "wall_ratio": result["quiet"]["ratio"],
        "busy_threads": sorted({r["threads"] for r in busy_runs.values()}),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_whole(args.out / "check.json", json.dumps(result, indent=1).encode())
    write_whole(args.out / "check.md", markdown(result).encode())
    last_quiet = args.work / f"quiet-this-{args.pairs - 1}"
    tables = ("BENCH.md", "bench.json")
    copies = [("busy-1", args.work / "busy-1", tables), ("busy-2", args.work / "busy-2", tables),
              ("quiet", last_quiet, (*tables, "accuracy_vs_time.png"))]  # fmt: skip
    for name, folder, files in copies:
        (args.out / name).mkdir(exist_ok=True)
        for file in files:
            write_whole(args.out / name / file, (folder / file).read_bytes())
    print(markdown(result))
    print(f"bench_check: wrote {args.out / 'check.json'} and {args.out / 'check.md'}")


if __name__ == "__main__":
    main()
