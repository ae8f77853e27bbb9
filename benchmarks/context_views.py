#!/usr/bin/env python
"""What one ``pool`` appearance head buys and costs per number of context views, against the paper's
two-view ``concat`` head: synthetic scenes, the demo's model and training, on the CPU.

    python benchmarks/context_views.py [--seeds 3] [--steps 600] [--train-views 2 4] [--eval-views 2 3 4]
        [--work outputs/context_views] [--out docs/results/context_views] [-- extra `aesplat fit` overrides]

1. Data, under --work: the demo's synthetic scenes and 42-pixel shards, made as ``make demo`` makes them
   (``data_prep/synthetic.py --val-scenes 12``, ``data_prep/to_shards.py --size 42``). Their test samples
   carry the contexts of 2 to 6 views on the same targets (``to_shards.py --eval-context-views``, default 6):
   the evaluation index's context pair plus frames evenly between its two frames.
2. Runs, for each seed (``seed_everything`` and ``data.seed``), all from conf/demo.yaml and its warm start,
   with the same data and steps:
   - ``pool``: ``model.net.view_aggregation pool``, trained with a count of context views drawn per batch
     from --train-views (``data.num_context_views [LOW, HIGH]``); the warm start's appearance head is the
     paper's, so this head starts from its initialisation (everything else loads);
   - ``concat``: the paper's head, trained with two views, its appearance head from the warm start;
   - ``concat_fresh``: the same with the appearance head from its initialisation (the warm start without
     its appearance tensors, written under --work);
   - ``pool_2``: the ``pool`` head trained with two views only.
   So ``pool`` minus ``concat`` is what a user switching heads sees, ``pool_2`` minus ``concat_fresh`` the
   head alone (same start, same views), ``pool`` minus ``pool_2`` what training with a range changes.
3. Evaluation of each run's last checkpoint, the ``pool`` runs at every --eval-views count, the ``concat``
   runs at two:
   accuracy with ``aesplat test --data.num_context_views k`` (the shards' k-view contexts; PSNR, SSIM,
   rotation and translation-direction errors of the predicted cameras), time with ``aesplat bench --knobs
   context_views --threads 1`` on the same samples (milliseconds per scene of the model forward and of
   rendering the targets, the median of --repeats interleaved rounds). The script checks that every run and
   count rendered the same target frames of the same scenes (``per_scene.csv``'s ``target_frames``), else
   stops.
4. Report, under --out: ``runs.csv`` (one line per run and count), ``results.json`` (per model and count the
   mean and 95 % t-interval over seeds, and the paired per-seed differences of ``summary_rows``; the
   settings, the scenes and their targets; date, commit, machine and load), ``table.md`` and
   ``context_views.png``.

Run it again to resume: a run whose RUN/context_views.json exists under the same settings is not redone, an
interrupted fit continues from its last checkpoint, a finished evaluation is kept. Heavy: run it under
``flock /work/heavy.lock`` where the machine is shared. ``--report-only`` rebuilds the report from the
finished runs.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import os
import shlex
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

# On a shared machine, spinning OpenMP workers make timed runs several times slower; yield instead.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO = Path(__file__).resolve().parents[1]
from common import DEMO_VAL_SCENES, demo_shards, provenance, t_interval, write_whole  # noqa: E402

from aesplat.files import atomic_write  # noqa: E402

MODELS = ("pool", "concat", "concat_fresh", "pool_2")
NAMES = {"pool": "`pool`", "concat": "`concat`", "concat_fresh": "`concat`, fresh head",
         "pool_2": "`pool`, trained with 2"}  # fmt: skip
# What `aesplat test` gives per count. The pose errors of the target views alone are those of the same views
# at every count; rot_err_deg / trans_err_deg average over the other context views too, more of them (and
# nearer view 0) the more context views there are.
TESTED = ("psnr", "ssim", "rot_err_target_deg", "trans_err_target_deg", "rot_err_deg", "trans_err_deg")
# Every metric kept per run and count; the table shows the first four.
METRICS = ("psnr", "rot_err_target_deg", "forward_ms", "render_ms", "ssim", "trans_err_target_deg",
           "rot_err_deg", "trans_err_deg")  # fmt: skip
LABELS = {"psnr": "PSNR (dB)", "rot_err_target_deg": "rotation error, targets (°)", "forward_ms": "forward ms",
          "render_ms": "render ms", "ssim": "SSIM", "trans_err_target_deg": "translation error, targets (°)",
          "rot_err_deg": "rotation error, all views (°)",
          "trans_err_deg": "translation error, all views (°)"}  # fmt: skip
DIGITS = {"psnr": 2, "rot_err_target_deg": 2, "forward_ms": 1, "render_ms": 1, "ssim": 3,
          "trans_err_target_deg": 1, "rot_err_deg": 2, "trans_err_deg": 1}  # fmt: skip
# Threads of the timed forwards and renders: one, as each fit of `make demo` has, and less disturbed by the
# other work of a 2-core machine than two.
THREADS = 1


@dataclass(frozen=True)
class Settings:
    """What every run shares; recorded beside each run, whose results are reused only under the same."""

    config: str
    scene_args: str
    size: int
    steps: int
    train_views: tuple[int, int]
    eval_views: tuple[int, ...]
    repeats: int
    extra: tuple[str, ...]


@dataclass(frozen=True)
class Run:
    model: str  # one of MODELS
    seed: int

    def directory(self, work: Path) -> Path:
        return work / "runs" / self.model / f"seed{self.seed}"

    @property
    def aggregation(self) -> str:
        """``model.net.view_aggregation`` of the run."""
        return "pool" if self.model.startswith("pool") else "concat"

    def counts(self, settings: Settings) -> tuple[int, ...]:
        """The context-view counts this run is evaluated at: the concat head takes its own two only."""
        return settings.eval_views if self.aggregation == "pool" else (2,)

    def train_views(self, settings: Settings) -> str:
        """``data.num_context_views`` of its fit: the range for ``pool``, 2 for the paper's head."""
        low, high = settings.train_views if self.model == "pool" else (2, 2)
        return str(low) if low == high else f"[{low},{high}]"


# ----------------------------------------------------------------------------------------------- data


def prepare_data(work: Path, settings: Settings) -> Path:
    """The demo's scenes and shards (made once, as `make demo` makes them, with ``scene_args``); a one-line
    exit when their test samples carry fewer context views than --eval-views asks for."""
    shards = work / "shards"
    demo_shards(work / "src", [(settings.size, shards)], ["--val-scenes", str(DEMO_VAL_SCENES),
                                                          *shlex.split(settings.scene_args)])  # fmt: skip
    from aesplat.data.manifest import read_manifest

    record = read_manifest(shards).splits["test"]
    if record.context_views < max(settings.eval_views):
        raise SystemExit(f"{shards}: test samples carry contexts of up to {record.context_views} views, not "
                         f"{max(settings.eval_views)}: delete it, or lower --eval-views")  # fmt: skip
    return shards


def fresh_head_weights(work: Path, settings: Settings) -> Path:
    """The config's warm start (``model.net.weights``) without its appearance tensors, written once under
    ``work``: a ``concat`` network loads everything else and starts its appearance head from initialisation,
    as ``pool`` does from the same file."""
    import torch
    import yaml

    weights = (yaml.safe_load((REPO / settings.config).read_text())["model"]["net"] or {}).get("weights")
    if not weights:
        raise SystemExit(f"{settings.config} starts from no weights: concat_fresh would be concat itself")
    out = work / f"{Path(weights).stem}-no-appearance.pt"
    if not out.exists():
        raw = torch.load(REPO / weights, map_location="cpu", weights_only=True)
        kept = {k: v for k, v in raw["state_dict"].items() if not k.startswith("model.appearance.")}
        if len(kept) == len(raw["state_dict"]):
            raise SystemExit(f"{weights} holds no appearance tensors (model.appearance.*)")
        note = f"{raw.get('note', '')}; appearance tensors removed by benchmarks/context_views.py"
        atomic_write(out, lambda f: torch.save({**raw, "state_dict": kept, "note": note}, f))
    return out


# ----------------------------------------------------------------------------------------------- runs


def train(run: Run, shards: Path, work: Path, settings: Settings) -> float:
    """``aesplat fit`` of one run (continuing an interrupted one); returns its seconds."""
    from aesplat.lightning_cli import run_lightning

    weights = []
    if run.model == "concat_fresh":
        weights = ["--model.net.weights", str(fresh_head_weights(work, settings))]
    start = time.perf_counter()
    run_lightning(["fit", "-c", str(REPO / settings.config), "--model.net.view_aggregation", run.aggregation,
                   *weights, "--data.num_context_views", run.train_views(settings), "--seed_everything",
                   str(run.seed), "--data.seed", str(run.seed), "--data.root", str(shards), "--data.image_size",
                   str(settings.size), "--trainer.max_steps", str(settings.steps), "--trainer.default_root_dir",
                   str(run.directory(work)), "--trainer.logger", "false", "--trainer.enable_progress_bar",
                   "false", *settings.extra, "--ckpt_path", "last"])  # fmt: skip
    return time.perf_counter() - start


def test_at(run: Run, count: int, work: Path) -> dict:
    """``aesplat test --data.num_context_views COUNT`` of the run's last checkpoint (kept when it is newer
    than the checkpoint and has every metric of ``TESTED``): its summary and, per scene, the frames it
    rendered."""
    from aesplat.lightning_cli import run_lightning

    folder = run.directory(work)
    ckpt = folder / "checkpoints" / "last.ckpt"
    out = folder / f"test-{count}-views"
    latest = out / "test-latest"
    summary = latest / "summary.json"
    fresh = summary.exists() and summary.stat().st_mtime >= ckpt.stat().st_mtime
    if not fresh or not set(TESTED) <= set(json.loads(summary.read_text())["metrics"]):
        run_lightning(["test", "-c", str(folder / "config.yaml"), "--data.num_context_views", str(count),
                       "--model.eval.output_dir", str(out), "--trainer.logger", "false",
                       "--trainer.enable_progress_bar", "false", "--ckpt_path", str(ckpt)])  # fmt: skip
    with open(latest / "per_scene.csv", newline="") as f:
        scenes = {r["scene"]: {"context": r["context_frames"], "target": r["target_frames"]}
                  for r in csv.DictReader(f)}  # fmt: skip
    return {"summary": json.loads(summary.read_text()), "scenes": scenes}


def bench(run: Run, work: Path, settings: Settings) -> dict[int, dict]:
    """``aesplat bench --knobs context_views`` of the run's last checkpoint at its counts, on every test scene
    (kept when it is newer than the checkpoint): the bench's row per count, with the machine's 1-minute load
    average when it ran (``load_1min``)."""
    from aesplat.bench.command import main as bench_main

    folder = run.directory(work)
    out = folder / "bench"
    counts = run.counts(settings)
    ckpt = folder / "checkpoints" / "last.ckpt"
    done = out / "load.json"  # written after bench.json: the bench finished
    if done.exists() and done.stat().st_mtime >= ckpt.stat().st_mtime:
        return _bench_rows(run, out, counts, json.loads(done.read_text())["load_1min"])
    bench_main(["--ckpt", str(folder / "checkpoints" / "last.ckpt"), "--knobs", "context_views",
                "--context-views", ",".join(map(str, counts)), "--scenes", "100000", "--repeats",
                str(settings.repeats), "--warmup", "1", "--process-warmup", "3", "--threads", str(THREADS),
                "--no-progress", "--out", str(out)])  # fmt: skip
    load = round(os.getloadavg()[0], 2)
    write_whole(done, json.dumps({"load_1min": load}).encode())
    return _bench_rows(run, out, counts, load)


def _bench_rows(run: Run, out: Path, counts: tuple[int, ...], load: float) -> dict[int, dict]:
    rows = json.loads((out / "bench.json").read_text())["rows"]
    by_label = {r["label"]: r for r in rows if r["knob"] == "context_views"}
    measured = {}
    for k in counts:
        row = by_label[f"{k} views"]
        if row["skipped"]:
            raise RuntimeError(f"{run}: {k} views not measured: {row['skipped']}")
        measured[k] = {**row, "load_1min": load}
    return measured


def evaluate(run: Run, work: Path, settings: Settings) -> list[dict]:
    """The run's last checkpoint at each of its counts: one row per count."""
    rows = []
    timed = bench(run, work, settings)
    for k in run.counts(settings):
        tested = test_at(run, k, work)
        metrics = tested["summary"]["metrics"]
        row = {"context_views": k, "scenes": tested["summary"]["num_scenes"],
               "load_1min": timed[k]["load_1min"], "bench_psnr": timed[k]["psnr"],
               "frames": tested["scenes"]}  # fmt: skip
        row.update({m: metrics[m] for m in TESTED})
        row.update(forward_ms=timed[k]["forward_ms"], render_ms=timed[k]["render_ms"])
        if abs(row["bench_psnr"] - row["psnr"]) > 0.05:  # the two commands share the metric code
            print(f"note: {run} at {k} views: aesplat bench {row['bench_psnr']:.3f} dB, aesplat test "
                  f"{row['psnr']:.3f} dB", flush=True)  # fmt: skip
        rows.append(row)
    return rows


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


def complete(saved: dict) -> bool:
    """Whether a run's saved evaluation has every metric (one made before a metric was added has not)."""
    return all(m in row for row in saved["rows"] for m in METRICS)


def run_one(run: Run, shards: Path, work: Path, settings: Settings, previous: dict | None = None) -> dict:
    """Fit (unless ``previous``, the run's incomplete evaluation, says the fit finished) and evaluate."""
    folder = run.directory(work)
    folder.mkdir(parents=True, exist_ok=True)
    marker = folder / "settings.json"
    if marker.exists() and json.loads(marker.read_text()) != json.loads(json.dumps(asdict(settings))):
        raise SystemExit(f"{folder} was trained with other settings; delete it or use another --work")
    write_whole(marker, json.dumps(asdict(settings), indent=1).encode())
    seconds = previous["fit_seconds"] if previous else train(run, shards, work, settings)
    saved = {"settings": asdict(settings), "fit_seconds": seconds, "rows": evaluate(run, work, settings)}
    # Whole or not at all: its presence marks a finished run.
    write_whole(folder / "context_views.json", json.dumps(saved, indent=1).encode())
    return saved


# ----------------------------------------------------------------------------------------------- report


def same_targets(results: dict[Run, dict]) -> dict[str, str]:
    """The target frames of every test scene, the same in every run and count (scene -> frames); stops with
    the first difference."""
    reference: dict[str, str] | None = None
    for run, saved in sorted(results.items(), key=lambda x: (x[0].model, x[0].seed)):
        for row in saved["rows"]:
            targets = {scene: frames["target"] for scene, frames in row["frames"].items()}
            if reference is None:
                reference, first = targets, (run, row["context_views"])
            elif targets != reference:
                raise SystemExit(f"{run} at {row['context_views']} views evaluated other scenes or targets "
                                 f"than {first[0]} at {first[1]}: the counts are not comparable")  # fmt: skip
    return reference or {}


def summary_rows(results: dict[Run, dict], settings: Settings) -> list[dict]:
    """Per model and count: n seeds, mean and 95 % half-width of every metric. Then the paired per-seed
    differences: at two views pool - concat, pool - concat_fresh and pool_2 - concat_fresh; at every count
    pool - pool_2; pool at k - pool at two. Each row's ``id`` names it for the pages' figures: ``pool@3``,
    ``concat@2``, ``pool-concat_fresh@2``, ``pool-pool_2@3``, ``pool@3-2``."""
    seeds = sorted({run.seed for run in results})

    def row(model: str, seed: int, k: int) -> dict | None:
        saved = results.get(Run(model, seed))
        return None if saved is None else next((r for r in saved["rows"] if r["context_views"] == k), None)

    def line(key: str, name: str, views: str, pairs: list[tuple[dict, dict | None]]) -> dict:
        out: dict = {"id": f"{key}@{views.replace(' − ', '-')}", "model": name, "context_views": views,
                     "n": len(pairs)}  # fmt: skip
        for m in METRICS:
            out[m], out[f"{m}_ci"], _ = t_interval([a[m] - (b[m] if b else 0.0) for a, b in pairs])
        return out

    def paired(first: str, second: str, k: int, other_k: int | None = None) -> list[tuple[dict, dict]]:
        return [(a, b) for s in seeds if (a := row(first, s, k)) and (b := row(second, s, other_k or k))]

    lines = []
    for model in MODELS:
        for k in Run(model, 0).counts(settings):
            found = [r for s in seeds if (r := row(model, s, k)) is not None]
            lines.append(line(model, NAMES[model], str(k), [(r, None) for r in found]))
    # What generality costs at two views: the whole switch, then the head alone (the same start, two views).
    for first, second in (("pool", "concat"), ("pool", "concat_fresh"), ("pool_2", "concat_fresh")):
        lines.append(
            line(f"{first}-{second}", f"{NAMES[first]} − {NAMES[second]}", "2", paired(first, second, 2))
        )
    for k in settings.eval_views:  # what training with a range of counts changes, at each count
        lines.append(
            line("pool-pool_2", f"{NAMES['pool']} − {NAMES['pool_2']}", str(k), paired("pool", "pool_2", k))
        )
    for k in settings.eval_views[1:]:  # what each further view buys
        lines.append(line("pool", NAMES["pool"], f"{k} − 2", paired("pool", "pool", k, 2)))
    return lines


def _fmt(mean: float, half: float, digits: int) -> str:
    if not math.isfinite(mean):
        return "–"
    return f"{mean:.{digits}f}" + (f" ± {half:.{digits}f}" if math.isfinite(half) else "")


def markdown(lines: list[dict], results: dict[Run, dict], runs: list[Run], settings: Settings, meta: dict,
             scenes: int) -> str:  # fmt: skip
    low, high = settings.train_views
    fit = {m: [r["fit_seconds"] for run, r in results.items() if run.model == m] for m in MODELS}
    minutes = ", ".join(f"{NAMES[m]} {sum(v) / len(v) / 60:.1f}" for m, v in fit.items() if v)
    machine = meta["machine"]
    load = meta["load"]  # the report's
    seeds = len({r.seed for r in runs})
    evaluated = [row["load_1min"] for r in results.values() for row in r["rows"]]
    out = [
        f"`python benchmarks/context_views.py --seeds {seeds}`: runs finished {meta['runs_finished']}, "
        f"report {meta['date'][:16].replace('T', ' ')} UTC at commit {meta['commit']}"
        f"{' (modified)' if meta['modified'] else ''}; {machine['cpu']}, {machine['cores']} cores, torch "
        f"{machine.get('torch', '?')}; 1-minute load average {min(evaluated):.1f}–{max(evaluated):.1f} at the "
        f"evaluations, {load['end'][0]} at the report. {len(results)} of {len(runs)} runs, {settings.steps} "
        f"steps each from `{settings.config}` at {settings.size}×{settings.size}; mean fit minutes: {minutes}.",
        "",
        f"`pool` trained with {low} to {high} context views per batch, the other rows with 2; each "
        f"evaluated on the same {scenes} test scenes and target frames at every count. Mean ± half-width of "
        f"the 95 % t-interval over seeds. The rotation error is that of the target views, the same views at "
        f"every count. Milliseconds per scene on the CPU, {meta['bench_threads']} thread (median of "
        f"{settings.repeats} runs).",
        "",
    ]
    header = " | seeds | " + " | ".join(LABELS[m] for m in METRICS[:4]) + " |"
    paired = [x for x in lines if "−" in x["model"] + x["context_views"]]
    for title, mine in (
        ("model", [x for x in lines if x not in paired]),
        ("difference, paired by seed", paired),
    ):
        out += [f"| {title} | context views{header}", "| --- | ---: | ---: |" + " ---: |" * 4]
        for x in mine:
            cells = [_fmt(x[m], x[f"{m}_ci"], DIGITS[m]) for m in METRICS[:4]]
            out.append(f"| {x['model']} | {x['context_views']} | {x['n']} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def plot(lines: list[dict], path: Path) -> None:
    """PSNR, rotation error and forward + render ms against the number of context views: the pool models as
    lines, the concat models as points at two (set a little apart), each with its 95 % interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    styles = (
        (NAMES["pool"], "o-"),
        (NAMES["pool_2"], "o--"),
        (NAMES["concat"], "s"),
        (NAMES["concat_fresh"], "^"),
    )
    for i, (model, style) in enumerate(styles):
        mine = [x for x in lines if x["model"] == model and x["context_views"].isdigit()]
        ks = [int(x["context_views"]) + 0.06 * i for x in mine]
        label = model.replace("`", "")
        for ax, metric in zip(axes[:2], ("psnr", "rot_err_target_deg")):
            ax.errorbar(ks, [x[metric] for x in mine], yerr=[_zero(x[f"{metric}_ci"]) for x in mine], fmt=style,
                        capsize=3, label=label)  # fmt: skip
            ax.set_ylabel(LABELS[metric])
        total = [x["forward_ms"] + x["render_ms"] for x in mine]
        axes[2].errorbar(ks, total, yerr=[_zero(x["forward_ms_ci"]) + _zero(x["render_ms_ci"]) for x in mine],
                         fmt=style, capsize=3, label=label)  # fmt: skip
    axes[2].set_ylabel("forward + render ms per scene")
    counts = sorted({int(x["context_views"]) for x in lines if x["context_views"].isdigit()})
    for ax in axes:
        ax.set_xticks(counts)
        ax.set_xlabel("context views")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)


def finished(results: dict[Run, dict], work: Path) -> str:
    """When the runs finished (their context_views.json written): 'YYYY-MM-DD HH:MM–HH:MM UTC'."""
    times = sorted(
        datetime.datetime.fromtimestamp(
            (run.directory(work) / "context_views.json").stat().st_mtime, datetime.timezone.utc
        )
        for run in results
    )
    first, last = times[0], times[-1]
    end = f"{last:%H:%M}" if last.date() == first.date() else f"{last:%Y-%m-%d %H:%M}"
    return f"{first:%Y-%m-%d %H:%M}–{end} UTC"


def _zero(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def write_report(out: Path, results: dict[Run, dict], runs: list[Run], settings: Settings,
                 load_start: list[float], work: Path) -> None:  # fmt: skip
    import torch  # noqa: F401 - provenance() names the torch version of a process that imported it

    meta = {**provenance(load_start), "bench_threads": THREADS, "runs_finished": finished(results, work)}
    targets = same_targets(results)
    columns = ["model", "seed", "context_views", "scenes", *METRICS, "bench_psnr", "load_1min", "fit_seconds"]
    table = [",".join(columns)]
    for run in runs:
        for row in (results.get(run) or {}).get("rows", []):
            values = {"model": run.model, "seed": run.seed, **row, "fit_seconds": results[run]["fit_seconds"]}
            table.append(",".join(str(values[c]) for c in columns))
    write_whole(out / "runs.csv", ("\n".join(table) + "\n").encode())
    lines = summary_rows(results, settings)
    clean = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in x.items()}
             for x in lines]  # fmt: skip
    record = {**meta, "settings": asdict(settings), "runs": len(results), "scenes": len(targets),
              "targets": targets, "rows": clean}  # fmt: skip
    write_whole(out / "results.json", (json.dumps(record, indent=1) + "\n").encode())
    write_whole(out / "table.md", markdown(lines, results, runs, settings, meta, len(targets)).encode())
    plot(lines, out / "context_views.png")


# ----------------------------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO / "docs" / "results" / "context_views"), help="report folder")
    p.add_argument("--work", default=str(REPO / "outputs" / "context_views"), help="data and checkpoints")
    p.add_argument("--config", default="conf/demo.yaml", help="base config of every run (repository-relative)")
    p.add_argument("--seeds", type=int, default=3, help="seeds per model (default 3)")
    p.add_argument("--steps", type=int, default=600, help="training steps per run (default 600: the demo's)")
    p.add_argument("--size", type=int, default=42, help="image side (default 42, the demo's)")
    p.add_argument("--scene-args", default="", help="more data_prep/synthetic.py options (default: the demo's)")
    p.add_argument("--train-views", type=int, nargs=2, default=[2, 4], metavar=("LOW", "HIGH"),
                   help="range of context views the pool model trains with (default 2 4)")  # fmt: skip
    p.add_argument("--eval-views", type=int, nargs="+", default=[2, 3, 4],
                   help="counts of context views the pool model is evaluated at (default 2 3 4)")  # fmt: skip
    p.add_argument("--repeats", type=int, default=5, help="aesplat bench's timing rounds (median; default 5)")
    p.add_argument("--report-only", action="store_true", help="only rebuild the report from finished runs")
    p.add_argument("extra", nargs="*", help="after `--`: more `aesplat fit` overrides for every run")
    a = p.parse_args(argv)
    if a.seeds < 1 or not 2 <= a.train_views[0] <= a.train_views[1] or min(a.eval_views) < 2:
        p.error("--seeds must be >= 1, --train-views LOW HIGH with 2 <= LOW <= HIGH, --eval-views >= 2")
    if 2 not in a.eval_views:
        p.error("--eval-views must include 2: the counts are compared with the two-view concat models")
    settings = Settings(config=a.config, scene_args=a.scene_args, size=a.size, steps=a.steps,
                        train_views=tuple(a.train_views), eval_views=tuple(sorted(set(a.eval_views))),
                        repeats=a.repeats, extra=tuple(a.extra))  # fmt: skip
    work, out = Path(a.work).resolve(), Path(a.out).resolve()
    load_start = [round(v, 2) for v in os.getloadavg()]
    os.chdir(REPO)  # the configs name files (the warm start) relative to the repository
    runs = [Run(model, seed) for seed in range(a.seeds) for model in MODELS]
    saved = {run: r for run in runs if (r := result(run, work, settings)) is not None}
    results = {run: r for run, r in saved.items() if complete(r)}
    if not a.report_only:
        shards = prepare_data(work, settings)
        for i, run in enumerate(runs, 1):
            if run in results:
                continue
            print(f"[run {i}/{len(runs)}] {run.model}, seed {run.seed}", flush=True)
            results[run] = run_one(run, shards, work, settings, saved.get(run))
    if not results:
        raise SystemExit("no finished run to report")
    write_report(out, results, runs, settings, load_start, work)
    print(f"wrote {out / 'table.md'}, results.json, runs.csv and context_views.png ({len(results)} of "
          f"{len(runs)} runs)")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
