"""Where a training step's time goes: real optimizer steps of a config on synthetic shards, stage by stage.

    python benchmarks/bench_train_step.py --config conf/demo.yaml                      # the CPU demo
    python benchmarks/bench_train_step.py --config conf/demo.yaml --image-size 224     # tiny model at 224^2
    python benchmarks/bench_train_step.py --config conf/re10k.yaml --device cuda       # the paper's setting
    python benchmarks/bench_train_step.py -c conf/re10k.yaml --device cuda --set model.net.compile=none \
        --steps 200 --losses eager.csv                                                 # record a loss curve
    python benchmarks/bench_train_step.py -c conf/re10k.yaml --device cuda --steps 200 --compare eager.csv

Builds the module and DataModule from the config's ``model`` / ``data`` sections, writes a few synthetic
scenes as shards at the config's image size (the curriculum is widened to the gaps they hold), and runs
``warmup + steps`` steps of a Lightning fit of that module (``trainer.precision`` as configured on CUDA,
32-true on the CPU; no logger, checkpoints, validation or progress bar; ``trainer.log_every_n_steps`` as
configured, since the steps that log read values back to the host). So it times the product's own training
step, ``AESplatModule.training_step`` as ``aesplat fit`` runs it: forward (model + render with the predicted
target cameras, the context views too when the loss wants them), loss, backward, clipping and the device-side
finiteness check, AdamW, schedule, the skip guard. ``benchmarks/gpu_throughput.sh fit`` times ``aesplat fit``
itself. Prints the seconds per step (median after ``--warmup`` steps; one step = from the end of the previous
step to the end of this one), samples/s, peak memory and the median time of each stage:

    data wait + loop  between steps: the DataLoader (workers run ahead, so this is what they fail to hide),
                      Lightning's loop, callbacks and logging
    host to device    moving the batch, uint8 -> float images
    encoder, transformer, heads (camera, depth, Gaussian), appearance, model (other: unprojection, glue)
    render            the rasterizer (the module's forward minus the model)
    loss              the photometric loss (and the pose loss of the posed warm start)
    backward          autograd through everything
    optimizer         clipping + finiteness check, AdamW step, schedule, skip guard; on logging steps the
                      training PSNR and the one read-back of the logged values

Stages are timed with forward hooks and Lightning's hooks; on CUDA every boundary synchronises, which costs a
little overlap (the step times are those of a run that waits at every boundary).

``--set KEY=VALUE`` changes one setting of the layered config (dotted path, YAML value), e.g.
``--set model.net.compile=none``, ``--set model.optim.impl=foreach``,
``--set model.net.options.head_precision=bf16``.
``--seed`` fixes the initial weights and the order of the data, so two runs that differ only in a speed
setting see the same batches: ``--losses FILE`` writes every step's loss and time (warm-up included) as CSV and
``--compare FILE`` prints how far this run's losses are from such a file, step by step and as means over
windows of ``--window`` steps (bf16 and atomics make single steps differ a little; the windowed means show a
drift). ``--json FILE`` also writes the figures (seconds per step, samples/s, peak memory and, on the CPU, the
process's resident memory before the fit, stages, settings) for a script to read.
"""

from __future__ import annotations

import argparse
import csv
import importlib.metadata
import json
import math
import resource
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import lightning as L
import torch
import yaml
from common import synthetic_shards
from lightning.pytorch import Callback

from aesplat.data import DataModule
from aesplat.files import atomic_write
from aesplat.threads import apply_thread_policy
from aesplat.train import AESplatModule
from aesplat.train.loss import LpipsWeightsMissing

STAGES = ("data wait + loop", "host to device", "encoder", "transformer", "heads", "appearance",
          "model (other)", "render", "loss", "backward", "optimizer")  # fmt: skip
MODEL_PARTS = {
    "encoder": ("encoder",),  # the patch encoder (aggregator.patch_embed), timed inside the transformer's
    "transformer": ("aggregator",),
    "heads": ("camera_head", "depth_head", "gaussian_head"),
    "appearance": ("appearance",),
}


class StageClock:
    """Accumulates wall time per stage within one step; synchronises CUDA at every boundary."""

    def __init__(self, device: torch.device) -> None:
        self.cuda = device.type == "cuda"
        self.step: dict[str, float] = defaultdict(float)
        self._open: dict[str, float] = {}

    def now(self) -> float:
        if self.cuda:
            torch.cuda.synchronize()
        return time.perf_counter()

    def start(self, stage: str) -> None:
        self._open[stage] = self.now()

    def stop(self, stage: str) -> None:
        self.step[stage] += self.now() - self._open.pop(stage)

    def hook(self, module: torch.nn.Module, stage: str) -> None:
        module.register_forward_pre_hook(lambda *_: self.start(stage))
        module.register_forward_hook(lambda *_: self.stop(stage))


class StepTimer(Callback):
    """Times every training step of a fit stage by stage, and keeps its loss (read once, at the end).

    The stage boundaries inside the step are Lightning's own hooks (batch transfer, the module's forward,
    ``on_before_backward``, ``on_after_backward``, the return of ``training_step``), so the step itself is the
    module's, untouched; one step runs from the end of the previous one to the end of this one.
    """

    def __init__(self, device: torch.device) -> None:
        self.clock = StageClock(device)
        self.stages: list[dict[str, float]] = []  # per step, seconds per stage
        self.seconds: list[float] = []  # per step
        self.losses: list[torch.Tensor] = []
        self._mark = 0.0

    def setup(self, trainer, pl_module, stage: str) -> None:
        clock, model = self.clock, pl_module.model
        for part, names in MODEL_PARTS.items():
            for name in names:
                clock.hook(getattr(model, name), part)
        clock.hook(model, "model")
        clock.hook(pl_module, "forward")
        for name, before, after in (("transfer_batch_to_device", "data wait + loop", "host to device"),
                                    ("on_after_batch_transfer", None, "host to device"),
                                    ("training_step", None, "optimizer")):  # fmt: skip
            setattr(pl_module, name, self._timed(getattr(pl_module, name), before, after))

    def _timed(self, method, before: str | None, after: str):
        """``method`` with the time up to its call charged to ``before`` and its own time to ``after``."""

        def timed(*args, **kwargs):
            if before is not None and pl_trainer_training(method):
                self._lap(before)
            out = method(*args, **kwargs)
            if pl_trainer_training(method):
                self._lap(after)
            return out

        return timed

    def _lap(self, stage: str) -> None:
        """Charge the time since the last mark to ``stage`` (the stages of the model are charged by hooks)."""
        now = self.clock.now()
        self.clock.step[stage] += now - self._mark
        self._mark = now

    def on_train_start(self, trainer, pl_module) -> None:
        self._mark = self._step_start = self.clock.now()

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        self.clock.step["data wait + loop"] += self.clock.now() - self._mark  # the loop's own hooks
        self._mark = self.clock.now()

    def on_before_backward(self, trainer, pl_module, loss) -> None:
        s = self.clock.step
        now = self.clock.now()
        forward = s.pop("forward", 0.0)
        parts = sum(s.get(k, 0.0) for k in MODEL_PARTS)
        s["model (other)"] = s.pop("model", 0.0) - parts
        s["render"] = forward - s["model (other)"] - parts
        s["loss"] = now - self._mark - forward
        self._mark = now

    def on_after_backward(self, trainer, pl_module) -> None:
        self._lap("backward")

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx: int) -> None:
        self._lap("optimizer")  # anything after training_step returned, before this hook
        loss = outputs["loss"] if isinstance(outputs, dict) else outputs
        self.losses.append(loss.detach())
        self.stages.append(dict(self.clock.step))
        self.seconds.append(self._mark - self._step_start)
        self._step_start = self._mark
        self.clock.step = defaultdict(float)


def pl_trainer_training(method) -> bool:
    """Whether the bound method's module is training (validation and the anomaly re-run are not timed)."""
    module = getattr(method, "__self__", None)
    return module is None or module.training


def load_config(paths: list[str]) -> dict:
    """The ``-c`` files layered left to right (plain YAML; top-level sections merged key by key)."""
    merged: dict = {}
    for path in paths:
        for key, value in (yaml.safe_load(Path(path).read_text()) or {}).items():
            if isinstance(value, dict) and isinstance(merged.get(key), dict):
                merged[key] = _deep_merge(merged[key], value)
            else:
                merged[key] = value
    return merged


def apply_overrides(cfg: dict, assignments: list[str]) -> dict:
    """``KEY=VALUE`` assignments (dotted key, YAML value) applied to a copy of ``cfg``."""
    out = _deep_merge(cfg, {})
    for assignment in assignments:
        key, sep, raw = assignment.partition("=")
        if not sep or not key or any(not part for part in key.split(".")):
            raise SystemExit(f"--set {assignment!r}: expected KEY=VALUE, e.g. model.net.compile=none")
        *parents, leaf = key.split(".")
        node = out
        for i, part in enumerate(parents):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise SystemExit(f"--set {assignment!r}: {'.'.join(parents[: i + 1])} is not a section")
            child = dict(child)  # copied, so the caller's dict stays as it was
            node[part] = child
            node = child
        node[leaf] = _yaml_value(raw)
    return out


def _yaml_value(raw: str):
    """A YAML scalar or list; numbers YAML 1.1 reads as strings (``1e-2``, no dot) become floats."""
    value = yaml.safe_load(raw)
    if isinstance(value, str):
        try:
            return float(value) if value.strip().lower() not in ("nan", "inf", "-inf", "infinity") else value
        except ValueError:
            return value
    return value


def _deep_merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for key, value in b.items():
        out[key] = (
            _deep_merge(out[key], value)
            if isinstance(value, dict) and isinstance(out.get(key), dict)
            else value
        )
    return out


def build(cfg: dict, args: argparse.Namespace, shards: Path, gaps: list[int]):
    model_cfg = dict(cfg.get("model", {}))
    loss = dict(model_cfg.get("loss") or {})
    try:
        module = AESplatModule(net=model_cfg.get("net"), loss=loss, optim=model_cfg.get("optim"),
                               render=model_cfg.get("render"), eval={"metrics_lpips": False})  # fmt: skip
    except LpipsWeightsMissing as err:
        print(f"note: LPIPS weights missing ({err}); timing with lpips_weight 0", file=sys.stderr)
        module = AESplatModule(net=model_cfg.get("net"), loss={**loss, "lpips_weight": 0.0},
                               optim=model_cfg.get("optim"), render=model_cfg.get("render"),
                               eval={"metrics_lpips": False})  # fmt: skip
    data_cfg = {k: v for k, v in (cfg.get("data") or {}).items() if k not in ("root",)}
    data_cfg.update(root=str(shards), gap_initial=gaps, gap_final=gaps, gap_warmup_steps=1,
                    train_batches_per_epoch=args.warmup + args.steps)  # fmt: skip
    if args.image_size:
        data_cfg["image_size"] = args.image_size
    if args.batch_size:
        data_cfg["batch_size"] = args.batch_size
    if args.num_workers is not None:
        data_cfg["num_workers"] = args.num_workers
    data_cfg["seed"] = args.seed
    return module, DataModule(**data_cfg)


def run(module: AESplatModule, datamodule: DataModule, device: torch.device, steps: int, warmup: int,
        precision: str, trainer_cfg: dict) -> tuple[list[dict], list[float], list[dict]]:  # fmt: skip
    """Fit ``warmup + steps`` steps and time them.

    Returns per-step stage times and step times (after warm-up), and one record per step (warm-up included)
    with its loss and seconds.
    """
    timer = StepTimer(device)
    log_every = trainer_cfg.get("log_every_n_steps", 50)
    trainer = L.Trainer(
        accelerator=device.type, devices=[device.index or 0] if device.type == "cuda" else 1,
        precision=precision, max_steps=warmup + steps, log_every_n_steps=log_every,
        benchmark=trainer_cfg.get("benchmark"), logger=False, callbacks=[timer], enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0, limit_val_batches=0,
    )  # fmt: skip
    module.step_tracker = datamodule.step_tracker
    trainer.fit(module, datamodule)
    records = [
        {"step": i, "warmup": int(i < warmup), "seconds": took, "loss": loss}
        for i, (took, loss) in enumerate(zip(timer.seconds, torch.stack(timer.losses).float().tolist()))
    ]  # one device read for all the losses, after the run
    return timer.stages[warmup:], timer.seconds[warmup:], records


def write_losses(path: Path, records: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["step", "warmup", "loss", "seconds"])
        writer.writeheader()
        for r in records:
            writer.writerow({**r, "loss": repr(r["loss"]), "seconds": f"{r['seconds']:.6f}"})


def read_losses(path: Path) -> dict[int, float]:
    with path.open(newline="") as f:
        return {int(row["step"]): float(row["loss"]) for row in csv.DictReader(f)}


def compare_losses(ours: dict[int, float], reference: dict[int, float], window: int) -> dict[str, float]:
    """How far ``ours`` is from ``reference`` over their common steps.

    Per step: the largest and the median relative difference |a - b| / |b|. Over consecutive windows of
    ``window`` steps: the largest relative difference of the windows' mean losses, and the mean loss of the
    last window of each run.
    """
    steps = sorted(set(ours) & set(reference))
    if not steps:
        raise SystemExit("--compare: the two runs share no step")
    finite = [s for s in steps if math.isfinite(ours[s]) and math.isfinite(reference[s])]
    rel = [abs(ours[s] - reference[s]) / max(abs(reference[s]), 1e-12) for s in finite]
    windows = [steps[i : i + window] for i in range(0, len(steps) - window + 1, window)] or [steps]
    mean_a = [statistics.fmean(ours[s] for s in w) for w in windows]
    mean_b = [statistics.fmean(reference[s] for s in w) for w in windows]
    return {
        "steps": len(steps),
        "non-finite steps": len(steps) - len(finite),
        "max relative difference, per step": max(rel, default=math.nan),
        "median relative difference, per step": statistics.median(rel) if rel else math.nan,
        "windows": len(windows),
        f"max relative difference, {len(windows[0])}-step means": max(
            abs(a - b) / max(abs(b), 1e-12) for a, b in zip(mean_a, mean_b)
        ),
        "last window mean loss, this run": mean_a[-1],
        "last window mean loss, reference": mean_b[-1],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", "-c", action="append", required=True, help="config file(s), layered")
    p.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N")
    p.add_argument("--steps", type=int, default=20, help="timed steps")
    p.add_argument("--warmup", type=int, default=5, help="untimed steps first")
    p.add_argument("--image-size", type=int, default=None, help="override data.image_size")
    p.add_argument("--batch-size", type=int, default=None, help="override data.batch_size")
    p.add_argument("--num-workers", type=int, default=None, help="override data.num_workers")
    p.add_argument("--scenes", type=int, default=4, help="synthetic training scenes")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: aesplat.threads)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="change one setting, e.g. model.net.compile=none (repeatable)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="initial weights and data order")
    p.add_argument("--losses", type=Path, default=None, help="write every step's loss and time here (CSV)")
    p.add_argument("--compare", type=Path, default=None, help="compare the losses with such a CSV")
    p.add_argument("--window", type=int, default=20, help="steps per window of --compare's means")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here (JSON)")
    args = p.parse_args()
    if args.compare is not None and not args.compare.is_file():
        raise SystemExit(f"--compare {args.compare}: no such file (write one first with --losses)")
    if args.steps < 1 or args.warmup < 0 or args.window < 1:
        raise SystemExit("--steps and --window must be at least 1, --warmup at least 0")

    cfg = apply_overrides(load_config(args.config), args.overrides)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: CUDA is not available here")
    workers = (
        args.num_workers if args.num_workers is not None else (cfg.get("data") or {}).get("num_workers", 4)
    )
    threads = apply_thread_policy(workers, args.threads)
    trainer_cfg = cfg.get("trainer") or {}
    precision = str(trainer_cfg.get("precision", "32-true")) if device.type == "cuda" else "32-true"

    with tempfile.TemporaryDirectory() as tmp:
        size = args.image_size or (cfg.get("data") or {}).get("image_size", 224)
        shards, gaps = synthetic_shards(Path(tmp), size, args.scenes)
        torch.manual_seed(args.seed)
        module, datamodule = build(cfg, args, shards, gaps)
        start_rss = start_peak_window()  # the process before the fit: imports, the model, the data module
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        per_step, times, records = run(module, datamodule, device, args.steps, args.warmup, precision,
                                       trainer_cfg)  # fmt: skip
    if args.losses is not None:
        write_losses(args.losses, records)

    batch = datamodule.batch_size
    step = statistics.median(times)
    if device.type == "cuda":
        peak_gib = torch.cuda.max_memory_allocated(device) / 2**30
        peak = f"{peak_gib:.2f} GiB (CUDA, allocated)"
    else:
        peak_gib = fit_peak_gib()
        peak = f"{peak_gib:.2f} GiB (process RSS during the fit; {start_rss:.2f} GiB before it)"
    net = module.model.cfg
    settings = "".join(f" --set {o}" for o in args.overrides)
    print(f"## {' + '.join(args.config)}{settings}: {precision}, {device}, {threads} torch threads\n")
    print(f"torch {torch.__version__}{gsplat_version()}, seed {args.seed}\n")
    name = (cfg.get("model") or {}).get("net", {}).get("size")
    print(f"model {name}, SH {net.sh_degree}, {size}^2, batch {batch}, {datamodule.num_workers} workers, "
          f"{args.steps} timed steps after {args.warmup}\n")  # fmt: skip
    print("| measure | value |\n| --- | ---: |")
    print(f"| seconds per step (median) | {step:.3f} |")
    print(f"| samples / s | {batch / step:.1f} |")
    print(f"| peak memory | {peak} |\n")
    print("| stage | median ms | share of the step |\n| --- | ---: | ---: |")
    stages = {s: statistics.median(x.get(s, 0.0) for x in per_step) * 1e3 for s in STAGES}
    for stage, ms in stages.items():
        print(f"| {stage} | {ms:.1f} | {ms / (step * 1e3):.0%} |")
    total = statistics.median(sum(s.values()) for s in per_step) * 1e3
    print(f"| (sum of stages) | {total:.1f} | {total / (step * 1e3):.0%} |")
    skipped = module.skipped_steps
    first, last = records[0]["loss"], records[-1]["loss"]
    print(f"\nloss: step 0 {first:.5f}, step {len(records) - 1} {last:.5f}; {skipped} skipped steps")
    if args.json is not None:
        kind = "cuda allocated" if device.type == "cuda" else "process RSS during the fit"
        figures = {"config": args.config, "overrides": args.overrides, "device": str(device),
                   "threads": threads, "precision": precision, "image_size": size, "batch_size": batch,
                   "steps": args.steps, "warmup": args.warmup, "seconds_per_step": step,
                   "samples_per_s": batch / step, "peak_memory_gib": peak_gib, "peak_memory_kind": kind,
                   "rss_before_fit_gib": start_rss, "skipped_steps": skipped, "stages_ms": stages}  # fmt: skip
        atomic_write(args.json, lambda f: f.write((json.dumps(figures, indent=1) + "\n").encode()))
    if args.compare is not None:
        ours = {r["step"]: r["loss"] for r in records}
        print(f"\n| against {args.compare} | value |\n| --- | ---: |")
        for key, value in compare_losses(ours, read_losses(args.compare), args.window).items():
            print(f"| {key} | {value:.3g} |" if isinstance(value, float) else f"| {key} | {value} |")


def start_peak_window() -> float:
    """This process's resident memory now (GiB), after returning freed heap memory to the system, and the
    start of a new peak (Linux: the kernel's high-water mark is reset), so that ``fit_peak_gib`` reads the
    peak of what follows rather than of the scene generation before it. NaN where /proc is missing."""
    import ctypes
    import ctypes.util
    import gc

    gc.collect()
    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
        return _status_gib("VmRSS")
    except (OSError, AttributeError):
        return math.nan


def fit_peak_gib() -> float:
    """The peak resident memory since ``start_peak_window`` (GiB); the process's whole peak (``ru_maxrss``)
    where the high-water mark cannot be read."""
    peak = _status_gib("VmHWM")
    return peak if math.isfinite(peak) else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _status_gib(field: str) -> float:
    """A memory line of /proc/self/status (kB) in GiB; NaN where it is missing."""
    try:
        line = next(x for x in Path("/proc/self/status").read_text().splitlines() if x.startswith(field + ":"))
    except (OSError, StopIteration):
        return math.nan
    return int(line.split()[1]) / 2**20


def gsplat_version() -> str:
    """The installed gsplat's version for the header, read from its metadata (importing it may compile it)."""
    try:
        return f", gsplat {importlib.metadata.version('gsplat')}"
    except importlib.metadata.PackageNotFoundError:
        return ""


if __name__ == "__main__":
    main()
