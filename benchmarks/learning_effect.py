#!/usr/bin/env python
"""What drawing fresh views at every step buys over a fixed pool of pre-drawn examples, at the demo's size.

    python benchmarks/learning_effect.py [--seeds 0 1 … 7] [--pool 6] [--steps 600] [--every 300]
        [--data outputs/learning_effect/data] [--out outputs/learning_effect] [--results docs/results/data]

Two arms of ``benchmarks/learning_curves.py`` on the demo's data (synthetic.py with 12 validation scenes,
42 px shards, made if missing), both ``conf/demo.yaml`` (the tiny model from the same warm start, the same
steps, batch, learning rate and curriculum), once per data seed (``--data.seed``):

    fresh        every example drawn at run time (the paper's recipe; the default)
    fixed-pool   ``--data.fixed_pool POOL``: POOL examples per scene drawn once (seeded by the data seed and the
                 scene) with gaps stratified over the curriculum's range, each used with one of its 3 targets,
                 as pre-drawn samples of a conversion were

The pool is sized so training passes over it at least as often as the paper's run passes over its pool of
8 samples per RealEstate10K scene (400k steps x batch 10 / (67k scenes x 8) = 7.5 passes): passes = steps x
batch / (training scenes x POOL). Resumable: finished runs are kept, an interrupted one continues.

Writes RESULTS/learning_effect.json (per seed: validation PSNR and rotation error of both arms at the last
point, and their paired differences; the date, commit, machine and load) and RESULTS/learning_effect.md (mean
and 95 % t-interval over the seeds).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

from common import t_interval
from curves import read_curve

ROOT = Path(__file__).resolve().parents[1]
PAPER_PASSES = 400_000 * 10 / (67_000 * 8)  # the paper's steps x batch over RealEstate10K's scenes x 8 samples


def demo_settings(config: Path) -> dict:
    import yaml

    data = yaml.safe_load(config.read_text())["data"]
    return {"batch_size": int(data["batch_size"]), "image_size": int(data["image_size"])}


def git(*args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(ROOT), *args], check=True, capture_output=True, text=True
    ).stdout.strip()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(8)), help="data seeds (default 0..7)")
    p.add_argument("--pool", type=int, default=6, help="examples per scene of the fixed pool (default 6)")
    p.add_argument(
        "--steps", type=int, default=600, help="training steps of every run (default 600, the demo's)"
    )
    p.add_argument("--every", type=int, default=300, help="evaluate every N steps (default 300)")
    p.add_argument("--config", type=Path, default=ROOT / "conf" / "demo.yaml")
    p.add_argument("--data", type=Path, default=ROOT / "outputs" / "learning_effect" / "data")
    p.add_argument("--out", type=Path, default=ROOT / "outputs" / "learning_effect")
    p.add_argument("--results", type=Path, default=ROOT / "docs" / "results" / "data")
    a = p.parse_args(argv)

    settings = demo_settings(a.config)
    load_start = round(os.getloadavg()[0], 2)
    import learning_curves  # beside this script (its folder is on sys.path)

    learning_curves.main([
        "--config", str(a.config), "--data", str(a.data), "--size", str(settings["image_size"]),
        "--steps", str(a.steps), "--every", str(a.every), "--runs", "fresh", "fixed-pool",
        "--define", "fresh=", "--define", f"fixed-pool=--data.fixed_pool {a.pool}",
        "--data-seeds", *map(str, a.seeds), "--out", str(a.out),
    ])  # fmt: skip

    manifest = json.loads((a.data / "shards" / "manifest.json").read_text())
    scenes = manifest["splits"]["train"]["scenes"]
    passes = a.steps * settings["batch_size"] / (scenes * a.pool)
    per_seed = []
    for seed in a.seeds:
        row = {"seed": seed}
        for arm in ("fresh", "fixed-pool"):
            last = read_curve(a.out / f"{arm}{learning_curves.SEED_TAG}{seed}" / "curve.csv")[-1]
            if int(last["step"]) != a.steps:
                raise SystemExit(
                    f"learning_effect: {arm}, seed {seed} stopped at step {last['step']}; run again"
                )
            row[arm] = {
                "val_psnr": last["val_psnr"],
                "val_rot_err_deg": last["val_rot_err_deg"],
                "val_num_scenes": int(last["val_num_scenes"]),
            }
        row["difference"] = {k: row["fresh"][k] - row["fixed-pool"][k] for k in ("val_psnr", "val_rot_err_deg")}
        per_seed.append(row)

    def interval(values: list[float]) -> dict:
        mean, half, n = t_interval(values)
        return {"mean": mean, "half_width_95": half, "n": n}

    summary = {arm: {k: interval([r[arm][k] for r in per_seed]) for k in ("val_psnr", "val_rot_err_deg")}
               for arm in ("fresh", "fixed-pool", "difference")}  # fmt: skip
    dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    result = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": git("rev-parse", "--short", "HEAD") + ("+changes" if dirty else ""),
        "machine": {"cores": os.cpu_count()},
        "load": [load_start, round(os.getloadavg()[0], 2)],
        "command": "python benchmarks/learning_effect.py "
        + " ".join(argv if argv is not None else sys.argv[1:]),
        "config": str(a.config.relative_to(ROOT)) if a.config.is_relative_to(ROOT) else str(a.config),
        "steps": a.steps,
        "batch_size": settings["batch_size"],
        "train_scenes": scenes,
        "pool": a.pool,
        "passes_over_pool": passes,
        "paper_passes_over_pool": PAPER_PASSES,
        "seeds": per_seed,
        "summary": summary,
    }
    a.results.mkdir(parents=True, exist_ok=True)
    (a.results / "learning_effect.json").write_text(json.dumps(result, indent=1) + "\n")

    def cell(s: dict, pattern: str) -> str:
        return f"{pattern.format(s['mean'])} ± {abs(s['half_width_95']):.2f}"

    val_scenes = per_seed[0]["fresh"]["val_num_scenes"]
    lines = [
        f"Measured {result['date'][:10]} at commit {result['commit']} on {result['machine']['cores']} cores, "
        f"load average {result['load'][0]} at the start and {result['load'][1]} at the end; "
        f"`{result['command'].strip()}`.",
        f"`{result['config']}` ({a.steps} steps of batch {settings['batch_size']} from the warm start), "
        f"{scenes} training scenes, a fixed pool of {a.pool} examples per scene: {passes:.1f} passes over the "
        f"pool (the paper's run: {PAPER_PASSES:.1f}). Validation figures on {val_scenes} validation scenes at "
        f"step {a.steps}; mean ± half-width of the 95 % t-interval over {len(a.seeds)} data seeds; the "
        "difference is paired by seed (fresh minus fixed pool).",
        "",
        "| arm | validation PSNR (dB) | validation rotation error (°) |",
        "| --- | ---: | ---: |",
        f"| fresh views at every step | {cell(summary['fresh']['val_psnr'], '{:.2f}')} | "
        f"{cell(summary['fresh']['val_rot_err_deg'], '{:.2f}')} |",
        f"| fixed pool of {a.pool} per scene | {cell(summary['fixed-pool']['val_psnr'], '{:.2f}')} | "
        f"{cell(summary['fixed-pool']['val_rot_err_deg'], '{:.2f}')} |",
        f"| difference, fresh − fixed | {cell(summary['difference']['val_psnr'], '{:+.2f}')} | "
        f"{cell(summary['difference']['val_rot_err_deg'], '{:+.2f}')} |",
        "",
        "| data seed | fresh PSNR | fixed PSNR | fresh rotation | fixed rotation |",
        "| ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [
        f"| {r['seed']} | {r['fresh']['val_psnr']:.2f} | {r['fixed-pool']['val_psnr']:.2f} | "
        f"{r['fresh']['val_rot_err_deg']:.2f} | {r['fixed-pool']['val_rot_err_deg']:.2f} |"
        for r in per_seed
    ]
    (a.results / "learning_effect.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
