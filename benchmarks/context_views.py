#!/usr/bin/env python
"""What one ``pool`` appearance head buys and costs per number of context views, against the paper's
two-view ``concat`` head: synthetic scenes, the demo's model and training, on the CPU.

    python benchmarks/context_views.py [--seeds 3] [--steps 600] [--train-views 2 4] [--eval-views 2 3 4]
        [--work outputs/context_views] [--out docs/results/context_views] [-- extra `aesplat fit` overrides]

1. Data, under --work: the demo's synthetic scenes (``data_prep/synthetic.py`` with 12 validation scenes,
   42-pixel shards, as ``make demo`` makes them), and test shards whose samples hold max(--eval-views) context
   views (``k_view_index``): each test scene keeps its two context frames (views 0 and 1) and its targets
   and gains context frames spread evenly between the two, none of them a target.
2. Runs, for each seed: ``pool`` trained with a count of context views drawn per batch from --train-views
   (``model.net.view_aggregation pool``, ``data.num_context_views [LOW, HIGH]``) and ``concat``, the paper's
   head, trained with two; both from conf/demo.yaml (its warm start: a ``pool`` run loads all of it but the
   appearance head), same data, steps and seed.
3. Evaluation of each run's last checkpoint with ``aesplat bench``'s machinery (its ``context_views`` knob)
   on the same test targets: ``pool`` at every --eval-views count (which context views:
   ``aesplat.bench.context_subset``), ``concat`` at two: PSNR, rotation error of the predicted cameras,
   milliseconds of the model forward and of rendering the targets (median of --repeats runs per scene).
4. Report, under --out: ``runs.csv`` (one line per run and count), ``results.json`` (per model and count the
   mean and 95 % t-interval over seeds, the paired per-seed difference of ``pool`` to ``concat`` at two views,
   the settings, date, commit, machine and its load), ``table.md`` and ``context_views.png``.

Run it again to resume: a run whose evaluation (RUN/context_views.json) exists under the same settings is not
redone, an interrupted fit continues from its last checkpoint. Heavy: run it under ``flock /work/heavy.lock``
where the machine is shared. ``--report-only`` rebuilds the report from the finished runs.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from aesplat.stats import t_interval

REPO = Path(__file__).resolve().parents[1]
MODELS = ("pool", "concat")
METRICS = ("psnr", "rot_err_deg", "forward_ms", "render_ms")
LABELS = {"psnr": "PSNR (dB)", "rot_err_deg": "rotation error (°)", "forward_ms": "forward ms",
          "render_ms": "render ms"}  # fmt: skip
VAL_SCENES = 12  # as `make demo`


@dataclass(frozen=True)
class Settings:
    """What every run shares; recorded beside each run, whose results are reused only under the same."""

    config: str
    scene_args: str
    size: int
    steps: int
    train_views: tuple[int, int]
    eval_views: tuple[int, ...]
    test_scenes: int
    repeats: int
    extra: tuple[str, ...]


@dataclass(frozen=True)
class Run:
    model: str  # pool | concat
    seed: int

    def directory(self, work: Path) -> Path:
        return work / "runs" / self.model / f"seed{self.seed}"

    def counts(self, settings: Settings) -> tuple[int, ...]:
        """The context-view counts this run is evaluated at: the concat head takes its own two only."""
        return settings.eval_views if self.model == "pool" else (2,)


# ----------------------------------------------------------------------------------------------- data


def k_view_index(index: dict, frames: dict[str, int], views: int) -> dict:
    """An evaluation index with ``views`` context views per scene from one with two: each entry keeps its
    context pair (views 0 and 1) and its targets and gains ``views - 2`` context frames between the pair, spread
    evenly (the frame nearest each of the evenly spaced positions that is neither a target nor taken; a scene
    without enough such frames is left out). ``frames``: frames per scene."""
    out = {}
    for key, entry in index.items():
        if entry is None:
            continue
        a, b = entry["context"][:2]
        lo, hi = min(a, b), max(a, b)
        free = [f for f in range(lo + 1, hi) if f not in entry["target"]]
        if len(free) < views - 2 or hi >= frames[key]:
            continue
        extra: list[int] = []
        for j in range(1, views - 1):
            want = lo + (hi - lo) * j / (views - 1)
            pick = min((f for f in free if f not in extra), key=lambda f: (abs(f - want), f))
            extra.append(pick)
        out[key] = {**entry, "context": [a, b, *extra]}
    return out


def prepare_data(work: Path, settings: Settings) -> tuple[Path, Path]:
    """The demo's scenes and shards (made once, as `make demo` makes them, with ``scene_args``) and test
    shards whose samples hold max(eval_views) context views (``k_view_index``)."""
    import torch

    views = max(settings.eval_views)
    src, shards, eval_shards = work / "src", work / "shards", work / f"shards-{views}-views"
    python = sys.executable
    if not (src / "dataset.json").exists():
        subprocess.run([python, str(REPO / "data_prep/synthetic.py"), "--out", str(src), "--val-scenes",
                        str(VAL_SCENES), *shlex.split(settings.scene_args)], check=True)  # fmt: skip
    if not (shards / "manifest.json").exists():
        subprocess.run([python, str(REPO / "data_prep/to_shards.py"), "--src", str(src), "--out", str(shards),
                        "--size", str(settings.size)], check=True)  # fmt: skip
    if not (eval_shards / "manifest.json").exists():
        index = json.loads((src / "evaluation_index.json").read_text())
        frames = {}
        for chunk in sorted((src / "test").glob("*.torch")):
            for scene in torch.load(chunk, weights_only=True):
                frames[scene["key"]] = len(scene["images"])
        wide = k_view_index(index, frames, views)
        path = work / f"evaluation_index_{views}_views.json"
        path.write_text(json.dumps(wide, indent=1))
        print(f"[data] {len(wide)} of {len(index)} test scenes with {views} context views", flush=True)
        subprocess.run([python, str(REPO / "data_prep/to_shards.py"), "--src", str(src), "--out",
                        str(eval_shards), "--size", str(settings.size), "--eval-index", str(path)],
                       check=True)  # fmt: skip
    return shards, eval_shards


# ----------------------------------------------------------------------------------------------- runs


def train(run: Run, shards: Path, work: Path, settings: Settings) -> float:
    """``aesplat fit`` of one run (continuing an interrupted one); returns its seconds."""
    from aesplat.cli import run_lightning

    folder = run.directory(work)
    low, high = settings.train_views if run.model == "pool" else (2, 2)
    views = str(low) if low == high else f"[{low},{high}]"
    config = Path(settings.config) if Path(settings.config).is_absolute() else REPO / settings.config
    start = time.perf_counter()
    run_lightning(["fit", "-c", str(config), "--model.net.view_aggregation", run.model,
                   "--data.num_context_views", views, "--seed_everything", str(run.seed), "--data.seed",
                   str(run.seed), "--data.root", str(shards), "--data.image_size", str(settings.size),
                   "--trainer.max_steps", str(settings.steps), "--trainer.default_root_dir", str(folder),
                   "--trainer.logger", "false", "--trainer.enable_progress_bar", "false", *settings.extra,
                   "--ckpt_path", "last"])  # fmt: skip
    return time.perf_counter() - start


def evaluate(run: Run, eval_shards: Path, work: Path, settings: Settings) -> list[dict]:
    """The run's last checkpoint at each of its counts on the same test targets: one row per count."""
    import torch

    from aesplat.bench import Bench, Point, Setting, evaluation_scenes
    from aesplat.checkpoint import load_checkpoint
    from aesplat.threads import apply_thread_policy

    apply_thread_policy(num_workers=0)  # as `aesplat bench`: the fit before left its own thread count
    device = torch.device("cpu")
    loaded = load_checkpoint(run.directory(work) / "checkpoints" / "last.ckpt", device)
    scenes = evaluation_scenes(loaded, str(eval_shards), settings.size, settings.test_scenes, device,
                               max(settings.eval_views))  # fmt: skip
    options = {**loaded.render.get("options", {}), "background": loaded.background}
    bench = Bench(loaded.model, scenes, device, repeats=settings.repeats, warmup=1, render_kwargs=options,
                  progress=False)  # fmt: skip
    points = [Point("context_views", f"{k} views", Setting(context_views=k)) for k in run.counts(settings)]
    rows = bench.run(points, points[0].setting, warmup_runs=2)
    failed = [r for r in rows if r.skipped]
    if failed:
        raise RuntimeError(f"{run}: {failed[0].label} not measured: {failed[0].skipped}")
    return [{"context_views": k, "scenes": len(scenes), **{m: getattr(r, m) for m in METRICS}}
            for k, r in zip(run.counts(settings), rows)]  # fmt: skip


def result(run: Run, work: Path, settings: Settings) -> dict | None:
    """A finished run's evaluation (rows per count, fit seconds), or None. Other settings are an error."""
    path = run.directory(work) / "context_views.json"
    if not path.exists():
        return None
    saved = json.loads(path.read_text())
    if saved["settings"] != json.loads(json.dumps(asdict(settings))):
        raise SystemExit(
            f"{path} was made with other settings; delete {run.directory(work)} or use another --work"
        )
    return saved


def run_one(run: Run, shards: Path, eval_shards: Path, work: Path, settings: Settings) -> dict:
    folder = run.directory(work)
    folder.mkdir(parents=True, exist_ok=True)
    marker = folder / "settings.json"
    if marker.exists() and json.loads(marker.read_text()) != json.loads(json.dumps(asdict(settings))):
        raise SystemExit(f"{folder} was trained with other settings; delete it or use another --work")
    marker.write_text(json.dumps(asdict(settings), indent=1))
    seconds = train(run, shards, work, settings)
    saved = {"settings": asdict(settings), "fit_seconds": seconds,
             "rows": evaluate(run, eval_shards, work, settings)}  # fmt: skip
    tmp = folder / ".context_views.json.tmp"
    tmp.write_text(json.dumps(saved, indent=1))
    os.replace(tmp, folder / "context_views.json")  # whole or not at all: its presence marks a finished run
    return saved


# ----------------------------------------------------------------------------------------------- report


def summary_rows(results: dict[Run, dict], settings: Settings) -> list[dict]:
    """Per model and count: n seeds, mean and 95 % half-width of every metric; then, per count both models
    have, the paired per-seed difference pool - concat."""
    lines = []
    for model in MODELS:
        counts = settings.eval_views if model == "pool" else (2,)
        for k in counts:
            values = [
                _row(r, k) for run, r in sorted(results.items(), key=lambda x: x[0].seed) if run.model == model
            ]
            values = [v for v in values if v is not None]
            line: dict = {"model": model, "context_views": k, "n": len(values)}
            for m in METRICS:
                line[m], line[f"{m}_ci"], _ = t_interval([v[m] for v in values])
            lines.append(line)
    seeds = sorted({run.seed for run in results})
    for k in (2,):
        pairs = [(_row(results.get(Run("pool", s)), k), _row(results.get(Run("concat", s)), k)) for s in seeds]
        pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
        line = {"model": "pool - concat", "context_views": k, "n": len(pairs)}
        for m in METRICS:
            line[m], line[f"{m}_ci"], _ = t_interval([a[m] - b[m] for a, b in pairs])
        lines.append(line)
    return lines


def _row(saved: dict | None, k: int) -> dict | None:
    if saved is None:
        return None
    return next((r for r in saved["rows"] if r["context_views"] == k), None)


def _fmt(mean: float, half: float, digits: int) -> str:
    if not math.isfinite(mean):
        return "–"
    return f"{mean:.{digits}f}" + (f" ± {half:.{digits}f}" if math.isfinite(half) else "")


def machine() -> dict:
    """Where and when: date, commit, CPU, torch and the threads it measures with, the load average now."""
    import torch

    from aesplat.threads import apply_thread_policy

    apply_thread_policy(num_workers=0)  # the count every evaluation ran with

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True)
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                           capture_output=True, text=True).stdout.strip()  # fmt: skip
    cpu = ""
    if Path("/proc/cpuinfo").exists():
        cpu = next(
            (ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), ""
        )
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "commit": commit.stdout.strip() + (" (with uncommitted changes)" if dirty else ""),
        "machine": f"{cpu or platform.processor() or platform.machine()}, {os.cpu_count()} logical cores",
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def markdown(
    lines: list[dict], results: dict[Run, dict], runs: list[Run], settings: Settings, meta: dict
) -> str:
    low, high = settings.train_views
    fit = [r["fit_seconds"] for r in results.values()]
    scenes = next((row["scenes"] for r in results.values() for row in r["rows"]), "?")
    out = [
        "# Context views: one pool head at 2 to N views against the paper's two-view head",
        "",
        f"Written by `python benchmarks/context_views.py` on {meta['date']}, commit {meta['commit']}, "
        f"{meta['machine']}, torch {meta['torch']} with {meta['threads']} threads, load average "
        f"{meta['load_average_1min']} when the report was written ({len(results)} of {len(runs)} runs "
        f"finished; {settings.steps} steps each from `{settings.config}`, {settings.size}x{settings.size} "
        f"images; total fit time {sum(fit) / 60:.1f} min).",
        "",
        f"`pool`: trained with {low} to {high} context views per batch; `concat`: the paper's head, trained "
        f"with 2. Both evaluated on the same {scenes} test scenes' targets; "
        "mean ± half-width of the 95 % t-interval over seeds; milliseconds per scene on the CPU (median of "
        f"{settings.repeats} runs). The last row: `pool` minus `concat` at two views, paired by seed.",
        "",
        "| model | context views | seeds | " + " | ".join(LABELS[m] for m in METRICS) + " |",
        "| --- | ---: | ---: |" + " ---: |" * len(METRICS),
    ]
    for line in lines:
        cells = [_fmt(line[m], line[f"{m}_ci"], 2 if m in ("psnr", "rot_err_deg") else 1) for m in METRICS]
        out.append(f"| `{line['model']}` | {line['context_views']} | {line['n']} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def plot(lines: list[dict], path: Path) -> None:
    """PSNR and rotation error (left, middle) and forward + render ms (right) against the number of context
    views: pool as a line, concat as a point at two, each with its 95 % interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for model, style in (("pool", "o-"), ("concat", "s")):
        mine = [x for x in lines if x["model"] == model]
        ks = [x["context_views"] for x in mine]
        for ax, metric in zip(axes[:2], ("psnr", "rot_err_deg")):
            ax.errorbar(ks, [x[metric] for x in mine], yerr=[_zero(x[f"{metric}_ci"]) for x in mine], fmt=style,
                        capsize=3, label=model)  # fmt: skip
            ax.set_ylabel(LABELS[metric])
        total = [x["forward_ms"] + x["render_ms"] for x in mine]
        axes[2].errorbar(ks, total, yerr=[_zero(x["forward_ms_ci"]) + _zero(x["render_ms_ci"]) for x in mine],
                         fmt=style, capsize=3, label=model)  # fmt: skip
    axes[2].set_ylabel("forward + render ms per scene")
    counts = sorted({x["context_views"] for x in lines})
    for ax in axes:
        ax.set_xticks(counts)
        ax.set_xlabel("context views")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _zero(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def write_report(out: Path, results: dict[Run, dict], runs: list[Run], settings: Settings) -> None:
    out.mkdir(parents=True, exist_ok=True)
    meta = machine()
    with open(out / "runs.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "seed", "context_views", "scenes", *METRICS, "fit_seconds"])
        for run in runs:
            for row in (results.get(run) or {}).get("rows", []):
                writer.writerow([run.model, run.seed, row["context_views"], row["scenes"],
                                 *(row[m] for m in METRICS), results[run]["fit_seconds"]])  # fmt: skip
    lines = summary_rows(results, settings)
    clean = [
        {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in x.items()} for x in lines
    ]
    (out / "results.json").write_text(
        json.dumps({**meta, "settings": asdict(settings), "rows": clean}, indent=1)
    )
    (out / "table.md").write_text(markdown(lines, results, runs, settings, meta))
    plot(lines, out / "context_views.png")


# ----------------------------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO / "docs" / "results" / "context_views"), help="report folder")
    p.add_argument("--work", default=str(REPO / "outputs" / "context_views"), help="data and checkpoints")
    p.add_argument("--config", default="conf/demo.yaml", help="base config of every run")
    p.add_argument("--seeds", type=int, default=3, help="seeds per model (default 3)")
    p.add_argument(
        "--steps", type=int, default=600, help="training steps of every run (default 600, the demo's)"
    )
    p.add_argument("--size", type=int, default=42, help="image side (default 42, the demo's)")
    p.add_argument(
        "--scene-args", default="", help="more data_prep/synthetic.py options (default: none, the demo's)"
    )
    p.add_argument("--train-views", type=int, nargs=2, default=[2, 4], metavar=("LOW", "HIGH"),
                   help="range of context views the pool model trains with (default 2 4)")  # fmt: skip
    p.add_argument("--eval-views", type=int, nargs="+", default=[2, 3, 4],
                   help="context-view counts the pool model is evaluated at (default 2 3 4)")  # fmt: skip
    p.add_argument("--test-scenes", type=int, default=1000, help="test scenes evaluated (default: all)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per scene and count (median)")
    p.add_argument("--report-only", action="store_true", help="only rebuild the report from finished runs")
    p.add_argument("extra", nargs="*", help="after `--`: more `aesplat fit` overrides for every run")
    a = p.parse_args(argv)
    if a.seeds < 1 or not 2 <= a.train_views[0] <= a.train_views[1] or min(a.eval_views) < 2:
        p.error("--seeds must be >= 1, --train-views LOW HIGH with 2 <= LOW <= HIGH, --eval-views >= 2")
    if 2 not in a.eval_views:
        p.error("--eval-views must include 2: the counts are compared with the two-view concat model")
    settings = Settings(config=a.config, scene_args=a.scene_args, size=a.size, steps=a.steps,
                        train_views=tuple(a.train_views), eval_views=tuple(sorted(set(a.eval_views))),
                        test_scenes=a.test_scenes, repeats=a.repeats, extra=tuple(a.extra))  # fmt: skip
    work, out = Path(a.work).resolve(), Path(a.out).resolve()
    os.chdir(REPO)  # the configs name files (the warm start) relative to the repository
    runs = [Run(model, seed) for seed in range(a.seeds) for model in MODELS]
    results = {run: r for run in runs if (r := result(run, work, settings)) is not None}
    if not a.report_only:
        shards, eval_shards = prepare_data(work, settings)
        for i, run in enumerate(runs, 1):
            if run in results:
                continue
            print(f"[run {i}/{len(runs)}] {run.model}, seed {run.seed}", flush=True)
            results[run] = run_one(run, shards, eval_shards, work, settings)
    write_report(out, results, runs, settings)
    print(f"wrote {out / 'table.md'}, results.json, runs.csv and context_views.png ({len(results)} of "
          f"{len(runs)} runs)")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
