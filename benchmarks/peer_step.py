"""The training step of NAS3R's network beside this project's, without the render, in one process on one device.

    python benchmarks/peer_step.py --device cuda --out peer.json                    # RE10K setting, bf16 trunk
    python benchmarks/peer_step.py --device cuda --precision fp32 --out peer_fp32.json
    python benchmarks/peer_step.py --device cpu --batch 1 --size 56 --steps 2 --warmup 1 --precision fp32

Three runs, one after the other, each timed the same way on the same random inputs: ``nas3r`` (below),
``aesplat`` (this project's network as ``--config`` builds it, default conf/re10k.yaml, eager) and
``aesplat-compiled`` (the same with the config's ``model.net.compile``, as `aesplat fit` runs it; left out
when the config compiles nothing). Ours: the forward on the context and target views under bf16 autocast
(``--precision bf16``, as ``trainer.precision: bf16-mixed`` runs it: the model keeps its heads, geometry and
appearance in fp32 itself), a scalar loss from the Gaussians, depth and cameras, backward, clipping at the
config's ``model.optim.grad_clip`` and AdamW with the config's settings and kernel (fused on CUDA). The ratio
NAS3R / aesplat of the median seconds per step is reported for each of ours.

NAS3R's public code (github.com/ranrhuang/NAS3R) is not part of this repository: ``--source`` names a plain
copy of it (default ``.peer/nas3r``, git-ignored), which this script imports at run time. Its ``src`` folder is
mounted under the private package name ``_nas3r`` (so it cannot clash with ours), and the package
``__init__`` files of ``src``, ``src.dataset``, ``src.model`` and ``src.model.encoder`` are skipped: they only
gather registries (data sets, loaders, the NAS3R-M variant) whose imports the network does not need.

The encoder is built as NAS3R's RE10K experiment builds it: the settings are read from its own YAML files
(``config/model/encoder/<encoder>.yaml``, its backbone's file, then ``config/experiment/nas3r/<variant>/
re10k.yaml`` on top), and the classes are constructed directly (no Hydra): ``EncoderNAS3R`` with the
``masked_vggt`` backbone (VGGT-1B: a DINOv2 ViT-L/14 patch embed, then 24 frame + 24 global attention
blocks of width 1024, 16 heads), VGGT's camera head, depth DPT head (and its point head, which is built but
unused), and NAS3R's DPT Gaussian head. ``pretrained`` is forced off: no weights are loaded or downloaded.

One step, as NAS3R's ``ModelWrapper.training_step`` drives it minus the render: the encoder forward on
``--context`` context and ``--targets`` target views (the targets enter the trunk's masked global
attention and get poses from the camera head), a scalar loss from its outputs (means of the Gaussians'
means, covariances, harmonics and opacities, of the depth, and of the predicted extrinsics and intrinsics),
backward, gradient-norm clipping at the config's ``trainer.gradient_clip_val`` and AdamW as NAS3R configures
it (weight decay 0.05, betas 0.9/0.95). The rasterizer is left out (NAS3R's is a CUDA extension that is not
built here), so ``"render": false``. Inputs are random images in [0, 1] at ``--size``^2 with normalised
pinhole intrinsics.

``--precision fp32`` is what NAS3R's own Trainer runs (it sets no precision, so 32-true; importing its
backbones turns TF32 matmuls on). ``--precision bf16`` (the default on CUDA) runs the trunk (patch embed +
alternating attention) under bf16 autocast and the heads, geometry and Gaussian adapter in fp32, as VGGT's
own forward and our RE10K config do.

Each of ``--warmup`` + ``--steps`` steps is timed between two ``torch.cuda.synchronize()`` calls; the
median and the 2.5/97.5 percentiles of the timed steps are reported, with the peak allocated memory of the
timed steps, the parameter count and one markdown line. ``--out`` writes the JSON atomically.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import importlib.util
import json
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch
import yaml
from common import provenance, write_whole

ROOT = Path(__file__).resolve().parents[1]
PKG = "_nas3r"  # where NAS3R's `src` folder is mounted
SKIPPED_INITS = ("", ".dataset", ".model", ".model.encoder")  # registries only: data, loaders, NAS3R-M


def mount(source: Path) -> list[str]:
    """Make NAS3R's ``src`` importable as ``_nas3r``; returns notes on what was stubbed or skipped."""
    src = source / "src"
    if not (src / "model" / "encoder" / "encoder_nas3r.py").is_file():
        raise SystemExit(f"no NAS3R source at {source} (expected src/model/encoder/encoder_nas3r.py)")
    for suffix in SKIPPED_INITS:
        name = PKG + suffix
        module = types.ModuleType(name)
        module.__path__ = [str(src.joinpath(*suffix.split(".")[1:]))]
        module.__package__ = name
        sys.modules[name] = module
    skipped = ", ".join("src" + suffix for suffix in SKIPPED_INITS)
    notes = [f"package __init__ of {skipped} not run (registries the network does not use)"]
    if importlib.util.find_spec("e3nn") is None:
        # misc/sh_rotation.py imports e3nn at module level for rotate_sh, whose only call (in the Gaussian
        # adapter) is commented out; a stub that fails loudly if it is ever called stands in for it.
        def unused(*args, **kwargs):
            raise RuntimeError("e3nn stub called: this benchmark assumed NAS3R never calls it")

        e3nn, o3 = types.ModuleType("e3nn"), types.ModuleType("e3nn.o3")
        o3.matrix_to_angles = o3.wigner_D = unused
        e3nn.o3 = o3
        sys.modules.update({"e3nn": e3nn, "e3nn.o3": o3})
        notes.append("e3nn not installed: stubbed (only rotate_sh uses it, and NAS3R never calls that)")
    return notes


def merge(base: dict, over: dict) -> dict:
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            merge(base[key], value)
        else:
            base[key] = value
    return base


def read_config(source: Path, variant: str, experiment: str = "re10k") -> tuple[dict, dict]:
    """NAS3R's encoder settings and the rest of the experiment's config, read from its YAML files
    (``config/experiment/nas3r/<variant>/<experiment>.yaml``: re10k, or re10k-I for the intrinsics variant)."""
    conf = source / "config"

    def load(path: Path) -> dict:
        return yaml.safe_load(path.read_text()) or {}

    experiment = load(conf / "experiment" / "nas3r" / variant / f"{experiment}.yaml")
    choices = {k: v for d in experiment.get("defaults", []) if isinstance(d, dict) for k, v in d.items()}
    encoder_name = choices.get("override /model/encoder", "nas3r")
    encoder = load(conf / "model" / "encoder" / f"{encoder_name}.yaml")
    backbone = next(
        d["backbone"] for d in encoder.pop("defaults", []) if isinstance(d, dict) and "backbone" in d
    )
    backbone = choices.get("override /model/encoder/backbone", backbone)
    encoder["backbone"] = load(conf / "model" / "encoder" / "backbone" / f"{backbone}.yaml")
    merge(encoder, experiment.get("model", {}).get("encoder", {}))
    main = load(conf / "main.yaml")
    main.pop("defaults", None)
    merge(main, {k: v for k, v in experiment.items() if k != "defaults"})
    return encoder, main


def make(cls, values: dict, ignored: list[str]):
    """``cls(**values)`` over the dataclass's fields; keys it has no field for (as dacite drops them) go to
    ``ignored``."""
    names = {f.name for f in dataclasses.fields(cls)}
    ignored += [f"{cls.__name__}.{k}" for k in values if k not in names]
    return cls(**{k: v for k, v in values.items() if k in names})


def build_encoder(encoder_cfg: dict, ignored: list[str]) -> torch.nn.Module:
    nas3r = importlib.import_module(f"{PKG}.model.encoder.encoder_nas3r")
    backbone = importlib.import_module(f"{PKG}.model.encoder.backbone.backbone_masked_vggt")
    adapter = importlib.import_module(f"{PKG}.model.encoder.common.gaussian_adapter")
    visual = importlib.import_module(f"{PKG}.model.encoder.visualization.encoder_visualizer_epipolar_cfg")
    if encoder_cfg["name"] != "nas3r" or encoder_cfg["backbone"]["name"] != "masked_vggt":
        raise SystemExit(f"unexpected config: {encoder_cfg['name']} / {encoder_cfg['backbone']['name']}")
    cfg = make(
        nas3r.EncoderNAS3RCfg,
        {
            **encoder_cfg,
            "backbone": make(
                backbone.BackboneMaskedVGGTCfg, {**encoder_cfg["backbone"], "pretrained": False}, ignored
            ),
            "gaussian_adapter": make(adapter.GaussianAdapterCfg, encoder_cfg["gaussian_adapter"], ignored),
            "opacity_mapping": make(nas3r.OpacityMappingCfg, encoder_cfg["opacity_mapping"], ignored),
            "visualizer": make(visual.EncoderVisualizerEpipolarCfg, encoder_cfg["visualizer"], ignored),
        },
        ignored,
    )
    return nas3r.EncoderNAS3R(cfg)


class Fp32Tokens(list):
    """The trunk's bf16 token list as a head reads it: each layer cast to fp32 only when it is read."""

    def __getitem__(self, index):
        item = super().__getitem__(index)
        return [t.float() for t in item] if isinstance(index, slice) else item.float()

    def __iter__(self):
        return (self[i] for i in range(len(self)))


def bf16_trunk(encoder: torch.nn.Module, device_type: str) -> None:
    """bf16 autocast over the backbone (patch embed + alternating attention); heads read fp32 tokens."""
    trunk_forward = encoder.backbone.forward

    def forward(*args, **kwargs):
        with torch.autocast(device_type, dtype=torch.bfloat16):
            return trunk_forward(*args, **kwargs)

    encoder.backbone.forward = forward
    model = encoder.backbone.model
    for head in (model.camera_head, model.depth_head, encoder.gaussian_param_head):
        head.forward = (lambda f: lambda tokens, *a, **k: f(Fp32Tokens(tokens), *a, **k))(head.forward)


def make_views(batch: int, views: int, size: int, device: torch.device, gen: torch.Generator) -> dict:
    intrinsics = torch.tensor([[0.86, 0.0, 0.5], [0.0, 0.86, 0.5], [0.0, 0.0, 1.0]])  # normalised, RE10K-like
    return {
        "image": torch.rand(batch, views, 3, size, size, generator=gen).to(device),
        "intrinsics": intrinsics.expand(batch, views, 3, 3).contiguous().to(device),
    }


def count(module: torch.nn.Module | None) -> int:
    return 0 if module is None else sum(p.numel() for p in module.parameters())


def describe(encoder: torch.nn.Module) -> dict:
    model = encoder.backbone.model
    agg = model.aggregator
    return {
        "trunk": {
            "patch_embed": f"DINOv2 ViT-L/{agg.patch_size} ({len(agg.patch_embed.blocks)} blocks, "
            f"width {agg.patch_embed.embed_dim}, {agg.patch_embed.num_heads} heads, "
            f"{agg.patch_embed.num_register_tokens} registers)",
            "alternating_blocks": f"{agg.depth} frame + {agg.depth} global",
            "embed_dim": int(agg.camera_token.shape[-1]),
            "num_heads": agg.frame_blocks[0].attn.num_heads,
            "patch_size": agg.patch_size,
            "aa_order": list(agg.aa_order),
        },
        "camera_head": f"{model.camera_head.trunk_depth} blocks, width {2 * agg.camera_token.shape[-1]}",
        "params": {
            "patch_embed": count(agg.patch_embed),
            "aggregator_blocks": count(agg) - count(agg.patch_embed),
            "camera_head": count(model.camera_head),
            "depth_head": count(model.depth_head),
            "point_head_unused": count(getattr(model, "point_head", None)),
            "gaussian_head": count(encoder.gaussian_param_head),
            "total": count(encoder),
        },
    }


def time_steps(step, device: torch.device, warmup: int, steps: int) -> dict:
    """Run ``step`` ``warmup`` + ``steps`` times, each between two device synchronisations; the timed steps'
    median, 2.5 and 97.5 percentiles, mean and peak allocated memory (CUDA)."""

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    times, loss = [], None
    if device.type == "cuda":
        torch.cuda.empty_cache()
    for i in range(warmup + steps):
        if i == warmup and device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        sync()
        start = time.perf_counter()
        loss = step()
        sync()
        if i >= warmup:
            times.append(time.perf_counter() - start)
    t = np.asarray(times)
    median, lo, hi = (float(np.percentile(t, q)) for q in (50, 2.5, 97.5))
    return {
        "median_s": median,
        "p2_5_s": lo,
        "p97_5_s": hi,
        "mean_s": float(t.mean()),
        "peak_mem_gib": torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None,
        "loss_finite": bool(torch.isfinite(loss)),
    }


def nas3r(args, device: torch.device, precision: str, context: dict, target: dict) -> tuple[dict, object]:
    """NAS3R's encoder step (module docstring): its description and the step function."""
    source = args.source.resolve()
    commit_file = source / "COMMIT"
    notes = mount(source)
    encoder_cfg, run_cfg = read_config(source, args.variant)
    torch.manual_seed(args.seed)
    ignored: list[str] = []
    encoder = build_encoder(encoder_cfg, ignored).to(device).train()
    if ignored:
        notes.append(f"config keys without a field in NAS3R's dataclasses, unused: {', '.join(ignored)}")
    if precision == "bf16":
        bf16_trunk(encoder, device.type)
    info = describe(encoder)
    opt_cfg = run_cfg.get("optimizer", {})
    clip = run_cfg.get("trainer", {}).get("gradient_clip_val")
    params = [p for p in encoder.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(
        params, lr=float(opt_cfg.get("lr", 1e-4)), weight_decay=0.05, betas=(0.9, 0.95)
    )

    def step() -> torch.Tensor:
        dump: dict = {}
        out = encoder(context, 0, visualization_dump=dump, target=target)
        g = out["gaussians"]
        loss = g.means.mean() + g.covariances.mean() + g.harmonics.mean() + g.opacities.mean()
        loss = loss + dump["depth"].mean() + out["extrinsics"]["cwt"].mean() + out["intrinsics"]["cwt"].mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if clip:
            torch.nn.utils.clip_grad_norm_(params, float(clip))
        optimizer.step()
        return loss.detach()

    described = {
        "source": str(source),
        "commit": commit_file.read_text().strip() if commit_file.is_file() else None,
        "variant": args.variant,
        "tf32_matmul": torch.backends.cuda.matmul.allow_tf32,
        "params": info["params"]["total"],
        "network": info,
        "optimizer": "torch AdamW, default kernel (foreach on CUDA)",
        "config": {
            "backbone": encoder_cfg["backbone"],
            "gs_params_head_type": encoder_cfg["gs_params_head_type"],
            "gaussian_adapter": encoder_cfg["gaussian_adapter"],
            "estimating_pose": encoder_cfg.get("estimating_pose"),
            "estimating_focal": encoder_cfg.get("estimating_focal"),
            "input_image_shape": run_cfg.get("dataset", {}).get("re10k", {}).get("input_image_shape"),
            "batch_size": run_cfg.get("data_loader", {}).get("train", {}).get("batch_size"),
            "gradient_clip_val": clip,
            "lr": opt_cfg.get("lr"),
            "trainer_precision": run_cfg.get("trainer", {}).get("precision", "unset (32-true)"),
        },
        "note": "; ".join(
            [
                "encoder forward + backward + grad clipping + AdamW; the render (NAS3R's CUDA rasterizer) "
                "is not included, nor are the MSE/LPIPS losses on rendered images",
                "random weights (config's pretrained flag forced off, no checkpoint, no download)",
                "bf16 = trunk under bf16 autocast, heads/geometry fp32; NAS3R's own Trainer runs 32-true"
                if precision == "bf16"
                else "fp32 as NAS3R's own Trainer (32-true)",
                "the VGGT point head is built (as NAS3R builds it) but unused, so gets no gradient",
                *notes,
            ]
        ),
    }
    return described, step


def aesplat(args, device: torch.device, precision: str, compiled: bool, context: dict, target: dict):
    """This project's network step (module docstring), built as ``--config`` builds it: description, step."""
    from aesplat.model import NetConfig
    from aesplat.train.optim import OptimConfig, build_optimizer, resolve_impl

    config = yaml.safe_load(args.config.read_text())
    net = dict(config["model"]["net"])
    net["compile"] = net.get("compile", "none") if compiled else "none"
    torch.manual_seed(args.seed)
    model = NetConfig(**net).build().to(device).train()
    optim = OptimConfig(**{k: tuple(v) if k == "betas" else v for k, v in config["model"]["optim"].items()})
    optimizer, _ = build_optimizer(model.named_parameter_groups(), optim, False, total_steps=1000)
    params = [p for p in model.parameters() if p.requires_grad]
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")

    def step() -> torch.Tensor:
        with autocast:
            out = model(context["image"], target["image"])
        g = out.gaussians
        loss = g.means.mean() + g.quats.mean() + g.scales.mean() + g.opacities.mean() + g.sh.mean()
        loss = loss + out.depth.mean() + out.extrinsics.mean() + out.intrinsics.mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, optim.grad_clip)
        optimizer.step()
        return loss.detach()

    described = {
        "config": str(args.config),
        "net": {k: v for k, v in net.items() if k != "weights"},
        "params": sum(p.numel() for p in model.parameters()),
        "optimizer": f"this project's AdamW groups, kernel {resolve_impl(optim.impl, params)}",
        "note": "forward + backward + grad clipping + AdamW; the render and the image losses are not included",
    }
    return described, step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=ROOT / ".peer" / "nas3r", help="plain copy of NAS3R")
    parser.add_argument("--config", type=Path, default=ROOT / "conf" / "re10k.yaml", help="this project's run")
    parser.add_argument(
        "--variant",
        choices=("random", "pretrained"),
        default="random",
        help="which of NAS3R's RE10K experiment files to read (the weights are random either way)",
    )
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    parser.add_argument("--batch", type=int, default=10)
    parser.add_argument("--size", type=int, default=224, help="image side, a multiple of the patch size 14")
    parser.add_argument("--context", type=int, default=2)
    parser.add_argument("--targets", type=int, default=1)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument(
        "--precision",
        choices=("bf16", "fp32"),
        default=None,
        help="bf16: the trunks under bf16 autocast (default on cuda); fp32: as NAS3R trains (default on cpu)",
    )
    parser.add_argument("--runs", nargs="+", choices=RUNS, default=list(RUNS), help="which steps to time")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="write the results here as JSON (whole)")
    args = parser.parse_args()

    if args.size % 14:
        parser.error("--size must be a multiple of the patch size 14")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("peer_step.py: --device cuda but no CUDA device is available")
    if "nas3r" in args.runs and not (args.source / "src").is_dir():
        raise SystemExit(f"peer_step.py: no NAS3R source at {args.source} (a plain copy of its repository)")
    device = torch.device(args.device)
    precision = args.precision or ("bf16" if device.type == "cuda" else "fp32")
    gen = torch.Generator().manual_seed(args.seed)
    context = make_views(args.batch, args.context, args.size, device, gen)
    target = make_views(args.batch, args.targets, args.size, device, gen)
    compiles = (yaml.safe_load(args.config.read_text())["model"]["net"].get("compile") or "none") != "none"

    record = {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
        "precision": precision,
        "batch": args.batch,
        "size": args.size,
        "context_views": args.context,
        "target_views": args.targets,
        "warmup": args.warmup,
        "steps": args.steps,
        "render": False,
        "runs": {},
        **provenance(),
    }
    for name in args.runs:
        if name == "aesplat-compiled" and not compiles:
            continue
        if name == "nas3r":
            described, step = nas3r(args, device, precision, context, target)
        else:
            described, step = aesplat(args, device, precision, name == "aesplat-compiled", context, target)
        figures = time_steps(step, device, args.warmup, args.steps)
        run = record["runs"][name] = {**described, **figures, "samples_per_s": args.batch / figures["median_s"]}
        del step
        if device.type == "cuda":
            torch.cuda.empty_cache()
        peak = f", peak {run['peak_mem_gib']:.1f} GiB" if run["peak_mem_gib"] is not None else ""
        print(f"| {name} (no render) | {record['device']} | {precision} | {args.batch} x ({args.context}+"
              f"{args.targets}) views @ {args.size}^2 | {run['median_s']:.4f} s/step (95%: {run['p2_5_s']:.4f}-"
              f"{run['p97_5_s']:.4f}){peak} | {run['params'] / 1e6:.1f} M params |", flush=True)  # fmt: skip
        if args.out is not None:  # what is measured so far, in case a later run fails
            record["ratios"] = ratios(record["runs"])
            write_whole(args.out, (json.dumps(record, indent=2) + "\n").encode())
    for name, ratio in ratios(record["runs"]).items():
        print(f"NAS3R / {name}: {ratio:.2f} (median seconds per step, no render)")


RUNS = ("nas3r", "aesplat", "aesplat-compiled")


def ratios(runs: dict) -> dict[str, float]:
    """NAS3R's median seconds per step over each of ours."""
    if "nas3r" not in runs:
        return {}
    return {name: runs["nas3r"]["median_s"] / run["median_s"] for name, run in runs.items() if name != "nas3r"}


if __name__ == "__main__":
    main()
