"""Where a training step's time goes: real optimizer steps of a config on synthetic shards, stage by stage.

    python benchmarks/bench_train_step.py --config conf/demo.yaml                      # the CPU demo
    python benchmarks/bench_train_step.py --config conf/demo.yaml --image-size 224     # tiny model at 224^2
    python benchmarks/bench_train_step.py --config conf/re10k.yaml --device cuda       # the paper's setting
    python benchmarks/bench_train_step.py -c conf/re10k.yaml --device cuda --set model.net.compile=none \
        --steps 200 --losses eager.csv                                                 # record a loss curve
    python benchmarks/bench_train_step.py -c conf/re10k.yaml --device cuda --steps 200 --compare eager.csv

Builds the module, optimizer and DataModule from the config's ``model`` / ``data`` sections
(``trainer.precision`` bf16-mixed -> bf16 autocast on CUDA), writes a few synthetic scenes as shards at the
config's image size (the curriculum is widened to the gaps they hold), and runs the same step as
``AESplatModule.training_step``: forward (model + render with the predicted target cameras), loss, backward,
gradient clipping, AdamW, schedule.
Lightning's own loop (logging, callbacks) is not included. Prints the seconds per step (median after
``--warmup`` steps), samples/s, peak memory and the median time of each stage:

    data wait        blocking on the DataLoader (workers run ahead, so this is what they fail to hide)
    host to device   moving the batch, uint8 -> float images
    encoder, transformer, heads (camera, depth, Gaussian), appearance, model (other: unprojection, glue)
    render           the rasterizer (forward minus the model)
    loss             photometric loss and the logged training PSNR
    backward         autograd through everything
    optimizer        gradient clipping + finiteness check, AdamW step, schedule, zero_grad

Stages are timed with forward hooks; on CUDA every boundary synchronises, which costs a little overlap.

``--set KEY=VALUE`` changes one setting of the layered config (dotted path, YAML value), e.g.
``--set model.net.compile=none``, ``--set model.optim.impl=foreach``,
``--set model.net.options.head_precision=bf16``.
``--seed`` fixes the initial weights and the order of the data, so two runs that differ only in a speed
setting see the same batches: ``--losses FILE`` writes every step's loss (warm-up included) as CSV and
``--compare FILE`` prints how far this run's losses are from such a file, step by step and as means over
windows of ``--window`` steps (bf16 and atomics make single steps differ a little; the windowed means show a
drift).
"""

from __future__ import annotations

import argparse
import csv
import importlib.metadata
import math
import resource
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import nullcontext
from pathlib import Path

import torch
import yaml

from aesplat.data import DataModule, convert_dataset, generate_dataset
from aesplat.threads import apply_thread_policy
from aesplat.train import AESplatModule
from aesplat.train.loss import LpipsWeightsMissing
from aesplat.train.metrics import psnr
from aesplat.train.optim import build_optimizer, clip_and_check, discard_gradients

STAGES = ("data wait", "host to device", "encoder", "transformer", "heads", "appearance", "model (other)",
          "render", "loss", "backward", "optimizer")  # fmt: skip
MODEL_PARTS = {
    "encoder": ("encoder",),
    "transformer": ("transformer",),
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


def synthetic_shards(root: Path, size: int, scenes: int) -> tuple[Path, list[int]]:
    """Synthetic scenes (32 frames) as shards of ``size``; returns the folder and the gap range they hold."""
    info = generate_dataset(root / "src", scenes=scenes, test_scenes=1, frames=32, seed=0, progress=False)
    convert_dataset(root / "src", root / "shards", size=size, progress=False)
    return root / "shards", list(info["gap_range"])


def build(cfg: dict, args: argparse.Namespace, shards: Path, gaps: list[int], device: torch.device):
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
    module.to(device).train()
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
    datamodule = DataModule(**data_cfg)
    pretrained = bool(getattr(module.model, "pretrained_backbone", False))
    total = max(args.warmup + args.steps, module.optim_cfg.warmup_steps + 1)
    groups = module.model.named_parameter_groups()
    optimizer, scheduler = build_optimizer(groups, module.optim_cfg, pretrained, total_steps=total)
    return module, datamodule, optimizer, scheduler


def run(module: AESplatModule, datamodule: DataModule, optimizer, scheduler, device: torch.device,
        steps: int, warmup: int, autocast) -> tuple[list[dict], list[float], list[dict]]:  # fmt: skip
    """Time ``warmup + steps`` training steps.

    Returns per-step stage times and step times (after warm-up), and one record per step (warm-up included)
    with its loss and seconds.
    """
    clock = StageClock(device)
    model = module.model
    for stage, names in MODEL_PARTS.items():
        for name in names:
            clock.hook(getattr(model, name), stage)
    clock.hook(model, "model")
    loader = iter(datamodule.train_dataloader())
    per_step, step_times, losses, records = [], [], [], []
    for i in range(warmup + steps):
        clock.step = defaultdict(float)
        t0 = clock.now()
        clock.start("data wait")
        batch = next(loader)
        clock.stop("data wait")
        clock.start("host to device")
        batch = module.on_after_batch_transfer(module.transfer_batch_to_device(batch, device, 0), 0)
        clock.stop("host to device")
        clock.start("forward")
        with autocast():
            _, rendered = module(batch)
        clock.stop("forward")
        clock.start("loss")
        terms = module.loss_fn(rendered.color, batch.target.images)
        with torch.no_grad():
            psnr(rendered.color.flatten(0, 1), batch.target.images.flatten(0, 1)).mean()
        clock.stop("loss")
        clock.start("backward")
        optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        clock.stop("backward")
        clock.start("optimizer")
        _, finite = clip_and_check(model.parameters(), module.optim_cfg.grad_clip, terms["total"])
        if not finite:
            discard_gradients(optimizer)
        optimizer.step()
        scheduler.step()
        clock.stop("optimizer")
        took = clock.now() - t0
        losses.append(terms["total"].detach())
        records.append({"step": i, "warmup": int(i < warmup), "seconds": took, "skipped": int(not finite)})
        if i >= warmup:
            s = dict(clock.step)
            parts = sum(s.get(k, 0.0) for k in MODEL_PARTS)
            s["model (other)"] = s.pop("model") - parts
            s["render"] = s.pop("forward") - s["model (other)"] - parts
            per_step.append(s)
            step_times.append(took)
    for record, loss in zip(records, torch.stack(losses).float().tolist()):  # one device sync, at the end
        record["loss"] = loss
    return per_step, step_times, records


def write_losses(path: Path, records: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["step", "warmup", "loss", "seconds", "skipped"])
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
    precision = str((cfg.get("trainer") or {}).get("precision", "32-true"))
    bf16 = precision.startswith("bf16") and device.type == "cuda"

    def autocast():
        return torch.autocast("cuda", dtype=torch.bfloat16) if bf16 else nullcontext()

    with tempfile.TemporaryDirectory() as tmp:
        size = args.image_size or (cfg.get("data") or {}).get("image_size", 224)
        shards, gaps = synthetic_shards(Path(tmp), size, args.scenes)
        torch.manual_seed(args.seed)
        module, datamodule, optimizer, scheduler = build(cfg, args, shards, gaps, device)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        per_step, times, records = run(
            module, datamodule, optimizer, scheduler, device, args.steps, args.warmup, autocast
        )
    if args.losses is not None:
        write_losses(args.losses, records)

    batch = datamodule.batch_size
    step = statistics.median(times)
    if device.type == "cuda":
        peak = f"{torch.cuda.max_memory_allocated(device) / 2**30:.2f} GiB (CUDA, allocated)"
    else:
        peak = f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB (process RSS)"
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
    for stage in STAGES:
        ms = statistics.median(s.get(stage, 0.0) for s in per_step) * 1e3
        print(f"| {stage} | {ms:.1f} | {ms / (step * 1e3):.0%} |")
    total = statistics.median(sum(s.values()) for s in per_step) * 1e3
    print(f"| (sum of stages) | {total:.1f} | {total / (step * 1e3):.0%} |")
    skipped = sum(r["skipped"] for r in records)
    first, last = records[0]["loss"], records[-1]["loss"]
    print(f"\nloss: step 0 {first:.5f}, step {len(records) - 1} {last:.5f}; {skipped} skipped steps")
    if args.compare is not None:
        ours = {r["step"]: r["loss"] for r in records}
        print(f"\n| against {args.compare} | value |\n| --- | ---: |")
        for key, value in compare_losses(ours, read_losses(args.compare), args.window).items():
            print(f"| {key} | {value:.3g} |" if isinstance(value, float) else f"| {key} | {value} |")


def gsplat_version() -> str:
    """The installed gsplat's version for the header, read from its metadata (importing it may compile it)."""
    try:
        return f", gsplat {importlib.metadata.version('gsplat')}"
    except importlib.metadata.PackageNotFoundError:
        return ""


if __name__ == "__main__":
    main()
