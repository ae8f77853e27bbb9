#!/usr/bin/env python
"""Does decoupled appearance help? The paper's ablation (Tab. 4), scaled down to synthetic scenes on the CPU.

    python benchmarks/appearance_ablation.py [--seeds 3 --free-seeds 2 --steps 500 --size 56 ...]

1. Data: the ``specular`` preset of ``data_prep/synthetic.py`` (every scene and surface glossy) and its
   ``diffuse`` control (the same scenes, highlights off), converted to shards whose test targets carry
   highlight masks (pixels whose specular term exceeds 0.05).
2. Runs: every appearance row (``full``, ``no_gvsre``, ``no_wcm``, ``baseline_i2dc``, ``baseline``,
   ``i2dc_only``) trained with the data set's poses (``model.cameras: dataset``) on both sets with ``--seeds``
   seeds, and pose-free (``model.cameras: predicted``) on the specular set with ``--free-seeds`` seeds; each
   with ``aesplat fit`` then ``aesplat test`` (run in this process) from ``conf/appearance_ablation.yaml``.
   Same data, steps and settings for every run; the seed sets the initialisation and the data order.
3. Report, under ``--out`` (default docs/results/ablation/): ``runs.csv`` (one line per run), ``table.csv`` and
   ``table.md`` (per set, camera source and row: mean and 95 % t-interval over seeds of PSNR on all, highlight
   and non-highlight pixels and SSIM, and the paired per-seed difference to ``full`` with its interval; and
   what the view-dependent part learned: the energy of the predicted higher-order SH coefficients on the test
   scenes, measured once per finished run from its checkpoint and kept in RUN/sh_energy.json), and
   ``ablation.png`` (one panel per set and camera source), and ``headline.md``, the results page's two
   headline tables (PSNR and its difference to ``full`` per set and camera source).
4. The primary comparisons, fixed here for every run of the grid (``PRIMARY``): every row against ``full``,
   posed, on PSNR over the highlight pixels of the specular set and on overall PSNR of the diffuse set. For
   that family of ten, ``primary.csv`` and the table give the paired t-test's p-value per comparison and its
   Holm adjustment; every other difference in the table is exploratory. ``--from-runs RUNS.csv`` rebuilds the
   report from a ``runs.csv`` (e.g. the committed one) without the runs' folders.

Data and checkpoints go under ``--work`` (default outputs/ablation/). The runner resumes: a run whose
``test-latest/summary.json`` exists is not retrained, an interrupted fit continues from its last checkpoint, and
the report is rebuilt from every run's results. A run made with other settings is an error, never silently
reused.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from common import holm, paired_t_p, t_interval

REPO = Path(__file__).resolve().parents[1]
ROWS = ("full", "no_gvsre", "no_wcm", "baseline_i2dc", "baseline", "i2dc_only")  # the paper's table order
SETS = ("specular", "diffuse")
METRICS = ("psnr", "psnr_highlight", "psnr_rest", "ssim")
LABELS = {"psnr": "PSNR", "psnr_highlight": "PSNR highlight", "psnr_rest": "PSNR rest", "ssim": "SSIM"}
# What the view-dependent part learned, per run: mean over the test scenes' Gaussians of the squared SH
# coefficients of degree >= 1 (summed over coefficients and colour channels), and that over the DC term's.
SH_METRICS = ("sh_high", "sh_high_ratio")
# The primary family: (set, cameras, metric), each row against `full`; the rest of the table is exploratory.
PRIMARY = (("specular", "dataset", "psnr_highlight"), ("diffuse", "dataset", "psnr"))
FRAMES = 32  # per scene; the config's curriculum (gaps 5..21) is the generator's suggestion for 32 frames


@dataclass(frozen=True)
class Settings:
    """What every run shares; recorded next to each run's results, which are reused only under the same."""

    config: str
    size: int
    steps: int
    scenes: int
    test_scenes: int
    data_seed: int
    extra: tuple[str, ...]


@dataclass(frozen=True)
class Run:
    dataset: str  # specular | diffuse
    cameras: str  # dataset (posed) | predicted (pose-free)
    row: str
    seed: int

    def directory(self, work: Path) -> Path:
        return work / "runs" / f"{self.dataset}_{self.cameras}" / self.row / f"seed{self.seed}"


# ----------------------------------------------------------------------------------------------- statistics


def paired_differences(results: dict[Run, dict], dataset: str, cameras: str, row: str, seeds: list[int],
                       metric: str) -> list[float]:  # fmt: skip
    """Per seed: ``row`` minus ``full`` (same set, cameras and seed), where both have the metric."""
    out = []
    for seed in seeds:
        a = (results.get(Run(dataset, cameras, row, seed)) or {}).get(metric)
        b = (results.get(Run(dataset, cameras, "full", seed)) or {}).get(metric)
        if a is not None and b is not None and math.isfinite(a) and math.isfinite(b):
            out.append(a - b)
    return out


def primary_family(results: dict[Run, dict], runs: list[Run], rows: list[str]) -> list[dict]:
    """The ``PRIMARY`` comparisons (each row but ``full``) present in ``runs``: n, the paired mean difference
    to ``full`` with its 95 % half-width, the paired t-test's p-value and its Holm adjustment (the family)."""
    family = []
    for dataset, cameras, metric in PRIMARY:
        seeds = sorted({r.seed for r in runs if (r.dataset, r.cameras) == (dataset, cameras)})
        if not seeds:
            continue
        for row in rows:
            if row == "full":
                continue
            diff = paired_differences(results, dataset, cameras, row, seeds, metric)
            mean, half, n = t_interval(diff)
            p, _ = paired_t_p(diff)
            family.append({"set": dataset, "cameras": cameras, "metric": metric, "row": row, "n": n,
                           "diff": mean, "diff_ci": half, "p": p})  # fmt: skip
    for line, adjusted in zip(family, holm([line["p"] for line in family])):
        line["p_holm"] = adjusted
    return family


def results_from_csv(path: Path) -> dict[Run, dict]:
    """Results as ``runs.csv`` records them (one line per finished run)."""
    with open(path) as f:
        lines = list(csv.DictReader(f))
    return {
        Run(r["set"], r["cameras"], r["row"], int(r["seed"])): {
            k: (float(r[k]) if r.get(k) not in (None, "") else None)
            for k in (*METRICS, *SH_METRICS, "fit_seconds")
        }
        for r in lines
    }


# ----------------------------------------------------------------------------------------------- data and runs


def prepare_data(preset: str, work: Path, settings: Settings) -> Path:
    """Generate (once) the preset's chunks and convert them to shards (resumable); returns the shard folder."""
    from aesplat.data import convert_dataset
    from aesplat.data.synthetic_scenes import generate_dataset

    src, shards = work / "src" / preset, work / "shards" / preset
    want = {"preset": preset, "height": settings.size, "train_scenes": settings.scenes,
            "test_scenes": settings.test_scenes, "seed": settings.data_seed, "frames": FRAMES}  # fmt: skip
    info_file = src / "dataset.json"
    if info_file.exists():
        info = json.loads(info_file.read_text())
        if {k: info.get(k) for k in want} != want:
            raise SystemExit(f"{src} holds another data set ({info_file}); delete it or choose another --work")
    else:
        print(f"[data] generating the {preset} set in {src}", flush=True)
        generate_dataset(src, scenes=settings.scenes, test_scenes=settings.test_scenes, frames=FRAMES,
                         height=settings.size, width=round(settings.size * 4 / 3), seed=settings.data_seed,
                         supersample=2, preset=preset)  # fmt: skip
    manifest = convert_dataset(src, shards, size=settings.size, progress=False)
    share = manifest["splits"]["test"].get("highlight_share", 0.0)
    print(
        f"[data] {preset}: {share:.1%} of test-target pixels are highlights (specular term > 0.05)", flush=True
    )
    return shards


def plan(rows: list[str], seeds: int, free_seeds: int, sets: list[str]) -> list[Run]:
    """Posed runs on every set, then pose-free runs on the specular set (if it is among ``sets``)."""
    runs = [Run(s, "dataset", row, seed) for s in sets for seed in range(seeds) for row in rows]
    if "specular" in sets:
        runs += [Run("specular", "predicted", row, seed) for seed in range(free_seeds) for row in rows]
    return runs


def train_and_test(run: Run, shards: Path, work: Path, settings: Settings) -> None:
    """``aesplat fit`` (continuing an interrupted fit) then ``aesplat test`` of its last checkpoint."""
    from aesplat.lightning_cli import run_lightning

    folder = run.directory(work)
    folder.mkdir(parents=True, exist_ok=True)
    _check_settings(folder, settings)  # an interrupted fit continues only under the same settings
    (folder / "settings.json").write_text(json.dumps(asdict(settings), indent=1))
    config = Path(settings.config) if Path(settings.config).is_absolute() else REPO / settings.config
    common = ["-c", str(config), "--model.net.appearance", run.row, "--model.cameras", run.cameras,
              "--seed_everything", str(run.seed), "--data.seed", str(run.seed), "--data.root", str(shards),
              "--data.image_size", str(settings.size), "--trainer.max_steps", str(settings.steps),
              "--trainer.default_root_dir", str(folder), *settings.extra]  # fmt: skip
    start = time.perf_counter()
    run_lightning(["fit", *common, "--ckpt_path", "last"])
    fit_seconds = time.perf_counter() - start
    run_lightning(["test", *common, "--ckpt_path", str(folder / "checkpoints" / "last.ckpt")])
    timing = {"fit_seconds": fit_seconds, "test_seconds": time.perf_counter() - start - fit_seconds}
    (folder / "timing.json").write_text(json.dumps(timing))


def result(run: Run, work: Path, settings: Settings) -> dict | None:
    """A finished run's metrics and timing, or None if it has not finished. Another setting is an error."""
    folder = run.directory(work)
    summary = folder / "test-latest" / "summary.json"  # the newest `aesplat test` of the run
    if not summary.exists():
        return None
    _check_settings(folder, settings)
    metrics = json.loads(summary.read_text())["metrics"]
    timing_file = folder / "timing.json"
    timing = json.loads(timing_file.read_text()) if timing_file.exists() else {}
    energy_file = folder / "sh_energy.json"
    energy = json.loads(energy_file.read_text()) if energy_file.exists() else {}
    return {**{m: metrics.get(m) for m in METRICS}, **{m: energy.get(m) for m in SH_METRICS},
            "fit_seconds": timing.get("fit_seconds")}  # fmt: skip


def measure_sh_energy(run: Run, work: Path) -> None:
    """Write RUN/sh_energy.json (``SH_METRICS``) from the run's last checkpoint on its set's test scenes, with
    the run's own config and camera source. Rows without higher orders (``i2dc_only``) get nulls."""
    import torch
    from omegaconf import OmegaConf

    from aesplat.data import DataModule
    from aesplat.model import forward_batch
    from aesplat.train import AESplatModule

    folder = run.directory(work)
    module = AESplatModule.load_from_checkpoint(folder / "checkpoints" / "last.ckpt", map_location="cpu").eval()
    data_cfg = OmegaConf.to_container(OmegaConf.load(folder / "config.yaml"), resolve=True)["data"]
    data = DataModule(**{**data_cfg, "num_workers": 0})
    data.setup("test")
    high, dc = [], []
    with torch.no_grad():
        for batch in data.test_dataloader():
            sh = forward_batch(module.model, batch.float_images(), module.cameras).gaussians.sh  # [B, N, K, 3]
            dc.append(sh[:, :, 0].square().sum(-1).mean().item())
            if sh.shape[2] > 1:
                high.append(sh[:, :, 1:].square().sum((-1, -2)).mean().item())
    energy = {"sh_high": None, "sh_high_ratio": None}
    if high:
        energy = {"sh_high": sum(high) / len(high), "sh_high_ratio": sum(high) / max(sum(dc), 1e-12)}
    (folder / "sh_energy.json").write_text(json.dumps(energy))


def _check_settings(folder: Path, settings: Settings) -> None:
    path = folder / "settings.json"
    if path.exists() and json.loads(path.read_text()) != json.loads(json.dumps(asdict(settings))):
        raise SystemExit(f"{folder} was run with other settings ({path}); delete it or choose another --work")


# ----------------------------------------------------------------------------------------------- report


def groups(runs: list[Run]) -> list[tuple[str, str]]:
    return list(dict.fromkeys((r.dataset, r.cameras) for r in runs))


def group_title(dataset: str, cameras: str) -> str:
    return f"{dataset} set, {'posed (data set cameras)' if cameras == 'dataset' else 'pose-free (predicted)'}"


def table_rows(runs: list[Run], results: dict[Run, dict], rows: list[str]) -> list[dict]:
    """One line per (set, cameras, row): n, and per metric the mean, its half-width, and the paired
    difference to ``full`` with its half-width."""
    lines = []
    for dataset, cameras in groups(runs):
        seeds = sorted({r.seed for r in runs if (r.dataset, r.cameras) == (dataset, cameras)})
        for row in rows:
            line: dict = {"set": dataset, "cameras": cameras, "row": row}
            mine = [results.get(Run(dataset, cameras, row, s)) for s in seeds]
            line["n"] = sum(m is not None for m in mine)
            for metric in (*METRICS, *SH_METRICS):
                mean, half, _ = t_interval([m.get(metric) for m in mine if m is not None])
                line[metric], line[f"{metric}_ci"] = mean, half
                if row != "full" and metric in METRICS:
                    diff = paired_differences(results, dataset, cameras, row, seeds, metric)
                    line[f"{metric}_vs_full"], line[f"{metric}_vs_full_ci"], _ = t_interval(diff)
            lines.append(line)
    return lines


def _fmt(mean: float | None, half: float | None, digits: int, signed: bool = False) -> str:
    if mean is None or not math.isfinite(mean):
        return "–"
    text = f"{mean:+.{digits}f}" if signed else f"{mean:.{digits}f}"
    return text + (f" ± {half:.{digits}f}" if half is not None and math.isfinite(half) else "")


def _p(value: float) -> str:
    if not math.isfinite(value):
        return "–"
    return f"{value:.4f}" if value >= 1e-4 else f"{value:.1e}"


def primary_markdown(family: list[dict]) -> list[str]:
    """The primary family's table: named before the figures, Holm-adjusted."""
    if not family:
        return []
    out = ["", "## Primary comparisons (Holm-adjusted)", "",
           "The primary family, fixed in the code (`PRIMARY`): each row against `full`, posed, on PSNR "
           "over the highlight pixels of the specular set and on overall PSNR of the diffuse set. Δ: the "
           "paired per-seed "
           "difference to `full`, mean ± half-width of its 95 % t-interval; p: two-sided paired t-test; "
           f"Holm p: adjusted over the family of {sum(math.isfinite(x['p']) for x in family)} comparisons "
           "(a difference is significant at 5 % for the family where Holm p ≤ 0.05). Every other difference "
           "in the tables below is exploratory: no correction, no claim.", "",
           "| set | metric | row | n | Δ (dB) | p | Holm p |",
           "| --- | --- | --- | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for x in family:
        diff = _fmt(x["diff"], x["diff_ci"], 2, signed=True)
        out.append(f"| {x['set']} | {LABELS[x['metric']]} | `{x['row']}` | {x['n']} | {diff} | {_p(x['p'])} | "
                   f"{_p(x['p_holm'])} |")  # fmt: skip
    return out


def markdown(lines: list[dict], runs: list[Run], results: dict[Run, dict], settings: Settings) -> str:
    done = [results[r] for r in runs if r in results]
    fit = [d["fit_seconds"] for d in done if d.get("fit_seconds") is not None]
    out = [
        "# Appearance ablation on synthetic scenes",
        "",
        f"Written by `python benchmarks/appearance_ablation.py` ({len(done)} of {len(runs)} runs finished; "
        f"{settings.steps} steps, {settings.size}x{settings.size} images, {settings.scenes} training and "
        f"{settings.test_scenes} test scenes, config `{settings.config}`"
        + (f", extra overrides `{' '.join(settings.extra)}`" if settings.extra else "")
        + f"; total fit time {sum(fit) / 60:.1f} min).",
        "",
        "Mean ± half-width of the 95 % t-interval over seeds. Δ: the paired per-seed difference to `full` "
        "(same set, cameras and seed), mean ± half-width. PSNR highlight / rest: PSNR on the test-target "
        "pixels whose specular term exceeds 0.05 and on the others (the diffuse set has no highlight pixels).",
        *primary_markdown(primary_family(results, runs, list(dict.fromkeys(r.row for r in runs)))),
    ]
    digits = {m: 4 if m == "ssim" else 2 for m in METRICS}
    for dataset, cameras in groups(runs):
        mine = [line for line in lines if (line["set"], line["cameras"]) == (dataset, cameras)]
        # Two narrow tables, the values and their differences to `full`: one wide one would hide its last
        # columns on the documentation site.
        head = ["row", "n", *(LABELS[m] for m in METRICS)]
        out += ["", f"## {group_title(dataset, cameras)}", "", "| " + " | ".join(head) + " |",
                "| " + " | ".join(["---"] + ["---:"] * (len(head) - 1)) + " |"]  # fmt: skip
        for line in mine:
            cells = [
                f"`{line['row']}`",
                str(line["n"]),
                *(_fmt(line[m], line[f"{m}_ci"], digits[m]) for m in METRICS),
            ]
            out.append("| " + " | ".join(cells) + " |")
        out += ["", "| row | " + " | ".join(f"Δ {LABELS[m]}" for m in METRICS) + " |",
                "| --- |" + " ---: |" * len(METRICS)]  # fmt: skip
        for line in mine:
            if line["row"] != "full":
                cells = [
                    _fmt(line[f"{m}_vs_full"], line[f"{m}_vs_full_ci"], digits[m], signed=True) for m in METRICS
                ]
                out.append(f"| `{line['row']}` | " + " | ".join(cells) + " |")
    rows = list(dict.fromkeys(line["row"] for line in lines))
    out += ["", "## What the view-dependent part learned", "",
            "Mean over the test scenes' Gaussians of the squared SH coefficients of degree ≥ 1 (summed over "
            "coefficients and colour channels), and its ratio to the DC term's; mean ± half-width of the "
            "95 % t-interval over seeds (`i2dc_only` has no higher orders).", "",
            "| set, cameras | " + " | ".join(f"`{r}`" for r in rows) + " |",
            "| --- |" + " ---: |" * len(rows)]  # fmt: skip
    for dataset, cameras in groups(runs):
        mine = [line for line in lines if (line["set"], line["cameras"]) == (dataset, cameras)]
        cells = [
            f"{_fmt(x['sh_high'], x['sh_high_ci'], 4)} ({_fmt(x['sh_high_ratio'], None, 3)})" for x in mine
        ]
        kind = "posed" if cameras == "dataset" else "pose-free"
        out.append(f"| {dataset}, {kind} | " + " | ".join(cells) + " |")
    out += ["", "Cells: energy of degree ≥ 1 (its ratio to the DC energy)."]
    return "\n".join(out) + "\n"


def _cell(line: dict, metric: str, difference: bool) -> str:
    """A table cell; a difference to `full` whose 95 % interval excludes 0 is bold."""
    key = f"{metric}_vs_full" if difference else metric
    mean, half = line.get(key), line.get(f"{key}_ci")
    if difference and line["row"] == "full":
        return ""
    text = _fmt(mean, half, 2, signed=difference)
    excludes_zero = difference and half is not None and math.isfinite(half) and abs(mean) > half
    return f"**{text}**" if excludes_zero else text


def headline_markdown(lines: list[dict]) -> str:
    """The results page's headline (headline.md): PSNR and its difference to `full` for the posed specular set
    (all pixels and the highlight pixels), the posed diffuse set and the pose-free specular set."""
    by = {(x["set"], x["cameras"], x["row"]): x for x in lines}
    rows = list(dict.fromkeys(x["row"] for x in lines))
    out = ["| row | specular: PSNR | Δ | highlight PSNR | Δ |", "| --- | ---: | ---: | ---: | ---: |"]
    for row in rows:
        x = by.get(("specular", "dataset", row))
        if x is not None:
            cells = [_cell(x, "psnr", False), _cell(x, "psnr", True), _cell(x, "psnr_highlight", False),
                     _cell(x, "psnr_highlight", True)]  # fmt: skip
            out.append(f"| `{row}` | " + " | ".join(cells) + " |")
    out += [
        "",
        "| row | diffuse: PSNR | Δ | pose-free specular: PSNR | Δ |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for row in rows:
        d, f = by.get(("diffuse", "dataset", row)), by.get(("specular", "predicted", row))
        cells = [_cell(d, "psnr", False), _cell(d, "psnr", True)] if d else ["", ""]
        cells += [_cell(f, "psnr", False), _cell(f, "psnr", True)] if f else ["", ""]
        out.append(f"| `{row}` | " + " | ".join(cells) + " |")
    out += ["", "Test PSNR (dB), mean ± half-width of the 95 % t-interval over seeds; Δ: the row minus `full`, "
            "paired by seed; bold: a Δ whose interval excludes 0 (unadjusted)."]  # fmt: skip
    return "\n".join(out) + "\n"


def plot(lines: list[dict], runs: list[Run], path: Path) -> None:
    """One column per (set, cameras): PSNR on all / highlight / non-highlight pixels per row (top) and the
    paired per-seed difference to ``full`` (bottom), each with its 95 % interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = groups(runs)
    fig, axes = plt.subplots(2, len(panels), figsize=(5.5 * len(panels), 8.0), squeeze=False)
    for col, (dataset, cameras) in enumerate(panels):
        mine = [line for line in lines if (line["set"], line["cameras"]) == (dataset, cameras)]
        for row, suffix in enumerate(("", "_vs_full")):
            ax = axes[row, col]
            for k, (metric, colour) in enumerate(zip(METRICS[:3], ("black", "tab:orange", "tab:blue"))):
                xs = [i + (k - 1) * 0.22 for i in range(len(mine))]
                ys = [line.get(metric + suffix, math.nan) for line in mine]
                half = [line.get(f"{metric}{suffix}_ci", math.nan) for line in mine]
                err = [h if math.isfinite(h) else 0.0 for h in half]
                if any(math.isfinite(y) for y in ys):
                    ax.errorbar(xs, ys, yerr=err, fmt="o", color=colour, capsize=3, label=LABELS[metric])
            ax.set_xticks(range(len(mine)), [line["row"] for line in mine], rotation=30, ha="right")
            ax.grid(axis="y", alpha=0.3)
            if row == 0:
                ax.set_title(group_title(dataset, cameras))
                ax.set_ylabel("test PSNR (dB), mean and 95 % interval over seeds")
            else:
                ax.axhline(0.0, color="grey", lw=1)
                ax.set_ylabel("row − full, paired by seed (dB), 95 % interval")
            if ax.lines:
                ax.legend(fontsize="small")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(
    out: Path, runs: list[Run], results: dict[Run, dict], rows: list[str], settings: Settings
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "runs.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["set", "cameras", "row", "seed", *METRICS, *SH_METRICS, "fit_seconds"])
        for run in runs:
            if run in results:
                r = results[run]
                values = ["" if r.get(k) is None else r[k] for k in (*METRICS, *SH_METRICS, "fit_seconds")]
                writer.writerow([run.dataset, run.cameras, run.row, run.seed, *values])
    lines = table_rows(runs, results, rows)
    with open(out / "table.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for line in lines for k in line)))
        writer.writeheader()
        writer.writerows([{k: ("" if isinstance(v, float) and math.isnan(v) else v) for k, v in line.items()}
                          for line in lines])  # fmt: skip
    family = primary_family(results, runs, rows)
    with open(out / "primary.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["set", "cameras", "metric", "row", "n", "diff", "diff_ci", "p",
                                               "p_holm"])  # fmt: skip
        writer.writeheader()
        writer.writerows([{k: ("" if isinstance(v, float) and math.isnan(v) else v) for k, v in x.items()}
                          for x in family])  # fmt: skip
    (out / "table.md").write_text(markdown(lines, runs, results, settings))
    (out / "headline.md").write_text(headline_markdown(lines))
    plot(lines, runs, out / "ablation.png")


# ----------------------------------------------------------------------------------------------- command line


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(REPO / "docs" / "results" / "ablation"), help="report folder")
    p.add_argument("--work", default=str(REPO / "outputs" / "ablation"), help="data and checkpoints")
    p.add_argument("--config", default="conf/appearance_ablation.yaml", help="base config of every run")
    p.add_argument("--rows", nargs="+", default=list(ROWS), choices=ROWS, help="appearance rows (first: full)")
    p.add_argument("--sets", nargs="+", default=list(SETS), choices=SETS, help="data sets")
    p.add_argument("--seeds", type=int, default=3, help="seeds of the posed runs (default 3)")
    p.add_argument("--free-seeds", type=int, default=2, help="seeds of the pose-free runs (default 2; 0: none)")
    p.add_argument("--steps", type=int, default=500, help="training steps of every run (default 500)")
    p.add_argument("--size", type=int, default=56, help="image side, a multiple of 14 (default 56)")
    p.add_argument("--scenes", type=int, default=48, help="training scenes per set (default 48)")
    p.add_argument("--test-scenes", type=int, default=16, help="test scenes per set (default 16)")
    p.add_argument("--data-seed", type=int, default=0, help="seed of the synthetic scenes (default 0)")
    p.add_argument("--report-only", action="store_true", help="only rebuild the report from finished runs")
    p.add_argument("--from-runs", default=None, metavar="RUNS_CSV",
                   help="rebuild the report from this runs.csv (e.g. docs/results/ablation/runs.csv) instead "
                   "of the runs' folders; implies --report-only")  # fmt: skip
    p.add_argument("--shard", default="0/1", metavar="K/N",
                   help="train only the runs whose place in the plan is K modulo N (default 0/1: all); start N "
                        "processes, 0/N .. N-1/N, to use N cores (one thread each)")  # fmt: skip
    p.add_argument("extra", nargs="*", help="after `--`: more overrides for every fit and test (same for all)")
    a = p.parse_args(argv)
    if a.rows[0] != "full":
        p.error("--rows must start with full: the paired differences are taken against it")
    if a.seeds < 1 or a.free_seeds < 0:
        p.error("--seeds must be >= 1 and --free-seeds >= 0")
    try:
        shard, shards_total = (int(x) for x in a.shard.split("/"))
        if not 0 <= shard < shards_total:
            raise ValueError
    except ValueError:
        p.error(f"--shard must be K/N with 0 <= K < N, got {a.shard!r}")
    settings = Settings(config=a.config, size=a.size, steps=a.steps, scenes=a.scenes, test_scenes=a.test_scenes,
                        data_seed=a.data_seed, extra=tuple(a.extra))  # fmt: skip
    work, out = Path(a.work), Path(a.out)
    runs = plan(a.rows, a.seeds, a.free_seeds, a.sets)
    if a.from_runs is not None:
        recorded = results_from_csv(Path(a.from_runs))
        write_report(out, runs, {run: recorded[run] for run in runs if run in recorded}, a.rows, settings)
        print(
            f"wrote {out / 'table.md'}, headline.md, table.csv, primary.csv, runs.csv and ablation.png from "
            f"{a.from_runs}"
        )
        return
    results = {run: r for run in runs if (r := result(run, work, settings)) is not None}
    if not a.report_only:
        shards = {s: prepare_data(s, work, settings) for s in a.sets}
        for i, run in enumerate(runs, 1):
            if run in results or (i - 1) % shards_total != shard:
                continue
            print(f"[run {i}/{len(runs)}] {run.dataset} set, cameras {run.cameras}, {run.row}, seed {run.seed}",
                  flush=True)  # fmt: skip
            train_and_test(run, shards[run.dataset], work, settings)
            results[run] = result(run, work, settings)
            if results[run] is None:
                summary = run.directory(work) / "test-latest" / "summary.json"
                raise RuntimeError(f"{run} finished without {summary}")
        # other shards may have finished runs meanwhile: report everything on disk
        results = {run: r for run in runs if (r := result(run, work, settings)) is not None}
    missing = [run for run in results if not (run.directory(work) / "sh_energy.json").exists()]
    for i, run in enumerate(missing, 1):
        print(
            f"[sh energy {i}/{len(missing)}] {run.dataset}, {run.cameras}, {run.row}, seed {run.seed}",
            flush=True,
        )
        measure_sh_energy(run, work)
        results[run] = result(run, work, settings)
    write_report(out, runs, results, a.rows, settings)
    print(
        f"wrote {out / 'table.md'}, table.csv, runs.csv and ablation.png ({len(results)} of {len(runs)} runs)"
    )


if __name__ == "__main__":
    sys.exit(main())
