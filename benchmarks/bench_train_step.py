"""Where a training step's time goes: real optimizer steps of a config on synthetic shards, stage by stage.

    python benchmarks/bench_train_step.py --config conf/demo.yaml                      # the CPU demo
    python benchmarks/bench_train_step.py --config conf/demo.yaml --image-size 224     # tiny model at 224^2
    python benchmarks/bench_train_step.py --config conf/re10k.yaml --device cuda       # the paper's setting

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
"""

from __future__ import annotations

import argparse
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
    datamodule = DataModule(**data_cfg)
    pretrained = bool(getattr(module.model, "pretrained_backbone", False))
    total = max(args.warmup + args.steps, module.optim_cfg.warmup_steps + 1)
    groups = module.model.named_parameter_groups()
    optimizer, scheduler = build_optimizer(groups, module.optim_cfg, pretrained, total_steps=total)
    return module, datamodule, optimizer, scheduler


def run(module: AESplatModule, datamodule: DataModule, optimizer, scheduler, device: torch.device,
        steps: int, warmup: int, autocast) -> tuple[list[dict[str, float]], list[float]]:  # fmt: skip
    """Time ``warmup + steps`` training steps; returns per-step stage times and step times (after warm-up)."""
    clock = StageClock(device)
    model = module.model
    for stage, names in MODEL_PARTS.items():
        for name in names:
            clock.hook(getattr(model, name), stage)
    clock.hook(model, "model")
    loader = iter(datamodule.train_dataloader())
    per_step, step_times = [], []
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
        if i >= warmup:
            s = dict(clock.step)
            parts = sum(s.get(k, 0.0) for k in MODEL_PARTS)
            s["model (other)"] = s.pop("model") - parts
            s["render"] = s.pop("forward") - s["model (other)"] - parts
            per_step.append(s)
            step_times.append(took)
    return per_step, step_times


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
    args = p.parse_args()

    cfg = load_config(args.config)
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

    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        size = args.image_size or (cfg.get("data") or {}).get("image_size", 224)
        shards, gaps = synthetic_shards(Path(tmp), size, args.scenes)
        module, datamodule, optimizer, scheduler = build(cfg, args, shards, gaps, device)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        per_step, times = run(
            module, datamodule, optimizer, scheduler, device, args.steps, args.warmup, autocast
        )

    batch = datamodule.batch_size
    step = statistics.median(times)
    if device.type == "cuda":
        peak = f"{torch.cuda.max_memory_allocated(device) / 2**30:.2f} GiB (CUDA, allocated)"
    else:
        peak = f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB (process RSS)"
    net = module.model.cfg
    print(f"## {' + '.join(args.config)}: {precision}, {device}, {threads} torch threads\n")
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


if __name__ == "__main__":
    main()
