#!/usr/bin/env python
"""Data benchmark: storage per scene, conversion time and training-loader throughput, pre-drawn samples (the
pipeline at ``--baseline``) against scene shards (this checkout), side by side in one run.

    python benchmarks/bench_data.py [--baseline c5c0f51] [--work outputs/bench_data] [--out docs/results/data]
        [--size 224 --re10k-size 256 --batch-size 10 --workers 2 --batches 100 --repeats 5]

Two sources, made once into ``--work`` (kept for the next call): the synthetic set as the earlier figures
measured it (16 training and 4 test scenes of 32 frames at 180x320), and a RealEstate10K-layout chunk source
(8 training and 2 test scenes of 125 frames at 360x640 JPEGs, about RealEstate10K's 10 million frames over
80,000 clips; rendered by the synthetic generator, so its images are simpler than photos). Each pipeline runs
in a subprocess of its own: the baseline's ``src/`` is extracted with ``git archive`` (the last commit whose
training shards held pre-drawn samples: 8 per scene with 2 context and 3 target views), this checkout's with
its own. Each converts both sources (2 processes; synthetic at ``--size``, RealEstate10K-layout at
``--re10k-size`` as conf/re10k.yaml's comment converts it), then times the training stream of its
DataModule: ``--workers`` DataLoader workers, ``--size`` images, batch ``--batch-size``, flip augmentation on,
2 context and 1 target views, in the first curriculum phase (the smallest gap only: the paper's 25 frames
for the RealEstate10K layout) and with every gap allowed; scene shards also with ``examples_per_scene`` 4.
Conversions run ``--repeats`` times and loader runs ``--repeats`` times per case, alternating between the
pipelines, so a change in the machine's load hits both; the tables give the median and the range (on a shared
machine other processes only ever slow a run down). The load average is recorded around every measurement.

Writes ``--out``/bench_data.json (every figure, the date, commit, machine and load) and
``--out``/bench_data.md (the table the docs page includes).

    python benchmarks/bench_data.py --sources url [--repeats 3 --batches 100]

compares the same loader on the scene shards of the synthetic source read from their folder and from an
http URL (``data.root``; docs/data.md, "Data on a server"): served by nginx on 127.0.0.1
(``scripts/local_nginx.py``, which installs it when missing), with a cold cache (emptied before each run: every
shard is downloaded and verified while the loader runs) and a warm one (the shards of the run before, reused
without a download). These runs time every batch from the DataLoader's start, worker start-up and downloads
included, since a cold cache pays its cost in the first batches. Writes ``--out``/bench_data_url.json and
``--out``/bench_data_url.md; the other figures stay as they are.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
URL_CASES = {"local": "local folder", "cold": "URL, cold cache", "warm": "URL, warm cache"}
BASELINE = "c5c0f51"  # main before training drew its views at run time: pre-drawn samples, manifest version 1
SOURCES = {  # name: (generate_dataset arguments, the gap range of its curriculum: first phase = lo only)
    "synthetic": (
        {"scenes": 16, "test_scenes": 4, "val_scenes": 0, "frames": 32, "height": 180, "width": 320, "seed": 1},
        (5, 21),
    ),  # fmt: skip
    "re10k-layout": (
        {"scenes": 8, "test_scenes": 2, "val_scenes": 0, "frames": 125, "height": 360, "width": 640, "seed": 2},
        (25, 90),
    ),  # fmt: skip
}


def load() -> float:
    return round(os.getloadavg()[0], 2)


def machine() -> dict:
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())  # fmt: skip
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "system": platform.platform(),
    }


def git(*args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(ROOT), *args], check=True, capture_output=True, text=True
    ).stdout.strip()


# ----------------------------------------------------------------------------------------------- one pipeline


def run_pipeline(name: str, work: Path, size: int, re10k_size: int, source: str) -> dict:
    """In the subprocess: convert ``source`` with whichever ``aesplat`` is importable, return its figures."""
    from aesplat.data import convert_dataset

    out = work / name / source
    shutil.rmtree(out, ignore_errors=True)  # timed from scratch, never resumed
    shard_size = re10k_size if source == "re10k-layout" else size
    before, start = load(), time.perf_counter()
    manifest = convert_dataset(work / "src" / source, out, size=shard_size, workers=2, progress=False)
    seconds = time.perf_counter() - start
    splits = manifest["splits"]
    return {
        "size": shard_size,
        "seconds": seconds,
        "scenes": sum(e["scenes"] for e in splits.values()),
        "train_scenes": splits["train"]["scenes"],
        "train_bytes": sum(s["bytes"] for s in splits["train"]["shards"]),
        "test_scenes": splits["test"]["scenes"],
        "test_bytes": sum(s["bytes"] for s in splits["test"]["shards"]),
        "load": [before, load()],
    }


def loader_rate(name: str, work: Path, source: str, gap: tuple[int, int], size: int, batch_size: int,
                workers: int, batches: int, examples_per_scene: int, root: str | None = None,
                cache_dir: str | None = None, warmup: int = 3) -> dict:  # fmt: skip
    """In the subprocess: training samples per second of the DataModule's stream, after ``warmup`` batches
    (worker start-up and the shuffle buffers). ``root``: another data.root than the converted folder (a URL,
    its shards kept in ``cache_dir``)."""
    from aesplat.data import DataModule

    extra = {"examples_per_scene": examples_per_scene} if examples_per_scene > 1 else {}
    if cache_dir is not None:
        extra["cache_dir"] = cache_dir
    dm = DataModule(root=root or str(work / name / source), image_size=size, batch_size=batch_size,
                    num_workers=workers, gap_initial=gap, gap_final=gap, gap_warmup_steps=0, flip_augment=True,
                    train_batches_per_epoch=batches + warmup, **extra)  # fmt: skip
    before = load()
    it = iter(dm.train_dataloader())
    for _ in range(warmup):
        next(it)
    start, n = time.perf_counter(), 0
    for batch in it:
        n += batch.batch_size
    return {"samples_per_second": n / (time.perf_counter() - start), "load": [before, load()]}


def in_subprocess(pythonpath: Path, task: str, payload: dict) -> dict:
    """Run ``task`` of this file with ``pythonpath`` first on the path; its figures come back as JSON."""
    env = {**os.environ, "PYTHONPATH": str(pythonpath), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, __file__, "--task", task, "--payload", json.dumps(payload)]
    done = subprocess.run(command, env=env, check=True, capture_output=True, text=True, cwd=ROOT)
    return json.loads(done.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------------------------- the run


def make_sources(work: Path, names: tuple[str, ...] = tuple(SOURCES)) -> None:
    """The sources ``names`` (both by default), generated once. The RealEstate10K-layout one loses its
    ``dataset.json`` (kept as ``generated.json``): RealEstate10K has none, so both pipelines take their default
    gap range, 25..90."""
    from aesplat.data import generate_dataset

    for name in names:
        options = SOURCES[name][0]
        src = work / "src" / name
        if not (src / "train" / "index.json").is_file():
            print(f"bench_data: generating the {name} source", flush=True)
            generate_dataset(src, scenes_per_chunk=4, progress=True, **options)
            if name == "re10k-layout":
                (src / "dataset.json").rename(src / "generated.json")


def baseline_source(ref: str, work: Path) -> Path:
    """``src/`` of commit ``ref``, extracted into ``work/baseline-REF``."""
    folder = work / f"baseline-{ref}"
    if not (folder / "src" / "aesplat" / "__init__.py").is_file():
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile() as archive:
            subprocess.run(["git", "-C", str(ROOT), "archive", ref, "src"], check=True, stdout=archive)
            archive.seek(0)
            with tarfile.open(fileobj=archive) as tar:
                tar.extractall(folder, filter="data")
    return folder / "src"


def spread(values: list[float], pattern: str) -> str:
    """Median (lowest–highest) of repeated measurements."""
    low, high = pattern.format(min(values)), pattern.format(max(values))
    return f"{pattern.format(statistics.median(values))} ({low}–{high})"


def table(result: dict) -> list[str]:
    names = {"today": f"pre-drawn samples ({result['baseline']})", "scenes": "scene shards"}
    lines = [
        "| source | figure | " + " | ".join(names.values()) + " | ratio of medians |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    for source in SOURCES:
        runs = {p: result["conversion"][source][p] for p in names}
        size = runs["scenes"][0]["size"]
        rows = (
            ("training shard per scene (MB)", lambda c: c["train_bytes"] / c["train_scenes"] / 1e6, "{:.2f}"),
            ("test shard per scene (MB)", lambda c: c["test_bytes"] / c["test_scenes"] / 1e6, "{:.3f}"),
        )
        for label, value, pattern in rows:  # the same bytes every repeat
            a, b = value(runs["today"][0]), value(runs["scenes"][0])
            lines.append(f"| {source} ({size} px) | {label} | {pattern.format(a)} | {pattern.format(b)} | "
                         f"{b / a:.2f}× |")  # fmt: skip
        seconds = {p: [c["seconds"] / c["scenes"] for c in runs[p]] for p in names}
        ratio = statistics.median(seconds["scenes"]) / statistics.median(seconds["today"])
        lines.append(
            f"| {source} ({size} px) | conversion, 2 processes (s per scene) | "
            f"{spread(seconds['today'], '{:.2f}')} | {spread(seconds['scenes'], '{:.2f}')} | {ratio:.2f}× |"
        )
    for case in result["loader"]:
        rates = {p: [r["samples_per_second"] for r in case["runs"][p]] for p in names if p in case["runs"]}
        cells = [spread(rates[p], "{:.0f}") if p in rates else "—" for p in names]
        ratio = ""
        if "today" in rates:
            ratio = f"{statistics.median(rates['scenes']) / statistics.median(rates['today']):.2f}×"
        lines.append(f"| {case['source']} ({case['size']} px) | loader samples/s, {case['label']} | "
                     f"{' | '.join(cells)} | {ratio} |")  # fmt: skip
    batch = result["settings"]["batch_size"]
    lines.append(
        f"| | loader samples/s needed by one GPU at 4 steps/s × batch {batch} | {4 * batch} | {4 * batch} | |"
    )
    return lines


def url_comparison(a: argparse.Namespace, work: Path) -> dict:
    """The loader on the synthetic source's scene shards from their folder and from a URL (cold and warm
    cache), ``a.repeats`` rounds alternating between the three; every batch timed from the loader's start."""
    from common import provenance
    from local_nginx import Nginx

    source, (_, (lo, hi)) = "synthetic", SOURCES["synthetic"]
    shards = work / "scenes" / source
    if not (shards / "manifest.json").is_file():
        print(f"bench_data: converting {source} with this checkout", flush=True)
        payload = {"name": "scenes", "work": str(work), "size": a.size, "re10k_size": a.re10k_size,
                   "source": source}  # fmt: skip
        in_subprocess(ROOT / "src", "convert", payload)
    load_start = [round(v, 2) for v in os.getloadavg()]
    cache = work / "url-cache"
    runs: dict[str, list[dict]] = {case: [] for case in URL_CASES}
    shutil.rmtree(work / "nginx", ignore_errors=True)  # its access log counts this run's downloads only
    with Nginx(shards, work / "nginx") as server:
        for _ in range(a.repeats):
            for case in URL_CASES:
                print(f"bench_data: loader, {URL_CASES[case]}, {source} (gap {lo}–{hi})", flush=True)
                payload = {"name": "scenes", "work": str(work), "source": source, "gap": [lo, hi],
                           "size": a.size, "batch_size": a.batch_size, "workers": a.workers,
                           "batches": a.batches, "examples_per_scene": 1, "warmup": 0}  # fmt: skip
                if case != "local":
                    payload |= {"root": server.url, "cache_dir": str(cache)}
                if case == "cold":
                    shutil.rmtree(cache, ignore_errors=True)
                runs[case].append(in_subprocess(ROOT / "src", "loader", payload))
        downloaded = [r for r in server.requests() if r[1].endswith(".tar")]
    rates = {case: [r["samples_per_second"] for r in runs[case]] for case in URL_CASES}
    medians = {case: statistics.median(v) for case, v in rates.items()}
    shard_bytes = sum(p.stat().st_size for p in (shards / "train").glob("*.tar"))
    return {
        **provenance(load_start),
        "command": "python benchmarks/bench_data.py " + " ".join(a.argv),
        "settings": {
            "source": source,
            "gap": [lo, hi],
            "size": a.size,
            "batch_size": a.batch_size,
            "workers": a.workers,
            "batches": a.batches,
            "repeats": a.repeats,
            "train_shard_bytes": shard_bytes,
        },  # fmt: skip
        "runs": runs,
        "samples_per_second": {
            case: {"median": medians[case], "lowest": min(v), "highest": max(v)} for case, v in rates.items()
        },  # fmt: skip
        "ratio_to_local": {case: medians[case] / medians["local"] for case in ("cold", "warm")},
        "shard_downloads": len(downloaded),
        "shard_downloads_expected": a.repeats * len(list((shards / "train").glob("*.tar"))),
    }


def url_table(result: dict) -> list[str]:
    s, m = result["settings"], result["machine"]
    modified = " (with uncommitted changes)" if result["modified"] else ""
    lines = [
        f"Measured {result['date'][:10]} at commit {result['commit']}{modified} "
        f"on {m['cores']} cores ({m['cpu']}), load average {result['load']['start'][0]} at the start and "
        f"{result['load']['end'][0]} at the end; `{result['command'].strip()}`. Median (lowest–highest) of "
        f"{s['repeats']} runs; loader: {s['workers']} workers, batch {s['batch_size']}, {s['size']} px, "
        f"{s['batches']} batches timed from the loader's start; {s['train_shard_bytes'] / 1e6:.0f} MB of "
        "training shards; nginx on 127.0.0.1.",
        "",
        "| data.root | loader samples/s | ratio to the local folder |",
        "| --- | ---: | ---: |",
    ]
    for case, label in URL_CASES.items():
        rate = result["samples_per_second"][case]
        ratio = "" if case == "local" else f"{result['ratio_to_local'][case]:.2f}×"
        cell = f"{rate['median']:.0f} ({rate['lowest']:.0f}–{rate['highest']:.0f})"
        lines.append(f"| {label} | {cell} | {ratio} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--baseline", default=BASELINE, help=f"the commit of the pre-drawn pipeline ({BASELINE})")
    p.add_argument("--work", type=Path, default=ROOT / "outputs" / "bench_data", help="sources and shards")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "data", help="bench_data.json/.md")
    p.add_argument("--size", type=int, default=224, help="image side of the synthetic shards and of the loader")
    p.add_argument("--re10k-size", type=int, default=256, help="image side of the RealEstate10K-layout shards")
    p.add_argument("--batch-size", type=int, default=10)
    p.add_argument("--workers", type=int, default=2, help="DataLoader workers")
    p.add_argument("--batches", type=int, default=100, help="timed batches per loader run")
    p.add_argument("--repeats", type=int, default=5, help="conversions and loader runs per case and pipeline")
    p.add_argument("--sources", choices=("folders", "url"), default="folders",
                   help="folders: the pre-drawn and scene pipelines (default); url: the scene shards from "
                   "their folder and from an http URL, cold and warm cache")  # fmt: skip
    p.add_argument("--task", help=argparse.SUPPRESS)
    p.add_argument("--payload", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.task:  # inside a pipeline's subprocess
        payload = json.loads(a.payload)
        payload["work"] = Path(payload["work"])
        task = {"convert": run_pipeline, "loader": loader_rate}[a.task]
        print(json.dumps(task(**payload)))
        return 0

    work = a.work.resolve()
    make_sources(work, ("synthetic",) if a.sources == "url" else tuple(SOURCES))
    if a.sources == "url":
        a.argv = argv if argv is not None else sys.argv[1:]
        result = url_comparison(a, work)
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "bench_data_url.json").write_text(json.dumps(result, indent=1) + "\n")
        report = "\n".join(url_table(result))
        (a.out / "bench_data_url.md").write_text(report + "\n")
        print(report)
        return 0
    paths = {"today": baseline_source(a.baseline, work), "scenes": ROOT / "src"}
    dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    result: dict = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": git("rev-parse", "--short", "HEAD") + ("+changes" if dirty else ""),
        "baseline": a.baseline,
        "machine": machine(),
        "command": "python benchmarks/bench_data.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "settings": {
            k: v
            for k, v in vars(a).items()
            if k in ("size", "re10k_size", "batch_size", "workers", "batches", "repeats")
        },  # fmt: skip
        "load_start": load(),
        "conversion": {},
        "loader": [],
    }
    for source in SOURCES:
        result["conversion"][source] = {name: [] for name in paths}
        for _ in range(a.repeats):
            for name, path in paths.items():
                print(f"bench_data: converting {source} with {name} ({path})", flush=True)
                payload = {"name": name, "work": str(work), "size": a.size, "re10k_size": a.re10k_size,
                           "source": source}  # fmt: skip
                result["conversion"][source][name].append(in_subprocess(path, "convert", payload))
    cases = []
    for source, (_, (lo, hi)) in SOURCES.items():
        cases.append((source, "first curriculum phase", (lo, lo), 1, ("today", "scenes")))
        cases.append((source, "every gap", (lo, hi), 1, ("today", "scenes")))
        cases.append((source, "every gap, 4 examples per scene read", (lo, hi), 4, ("scenes",)))
    for source, label, gap, per_scene, pipelines in cases:
        case = {
            "source": source,
            "label": f"{label} (gap {gap[0]}–{gap[1]})",
            "gap": list(gap),
            "size": a.size,
            "examples_per_scene": per_scene,
            "runs": {p: [] for p in pipelines},
        }
        for _ in range(a.repeats):
            for name in pipelines:
                print(f"bench_data: loader, {name}, {source}, {case['label']}", flush=True)
                payload = {"name": name, "work": str(work), "source": source, "gap": list(gap), "size": a.size,
                           "batch_size": a.batch_size, "workers": a.workers, "batches": a.batches,
                           "examples_per_scene": per_scene}  # fmt: skip
                case["runs"][name].append(in_subprocess(paths[name], "loader", payload))
        result["loader"].append(case)
    result["load_end"] = load()
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "bench_data.json").write_text(json.dumps(result, indent=1) + "\n")
    m = result["machine"]
    header = [
        f"Measured {result['date'][:10]} at commit {result['commit']} against {a.baseline} on {m['cores']} "
        f"cores ({m['cpu']}), load average {result['load_start']} at the start and {result['load_end']} at the "
        f"end; `{result['command'].strip()}`. Median (lowest–highest) of {a.repeats} runs; loader: "
        f"{a.workers} workers, batch {a.batch_size}, {a.batches} timed batches.",
        "",
    ]
    report = "\n".join(header + table(result))
    (a.out / "bench_data.md").write_text(report + "\n")
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
