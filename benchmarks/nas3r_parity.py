"""NAS3R's network and this project's on the same weights and images: every output compared, in fp32.

    python benchmarks/nas3r_parity.py --out docs/results/nas3r/parity.json            # full size, all cases
    python benchmarks/nas3r_parity.py --fixture tests/model/fixtures/nas3r_parity.pt  # the CI fixture
    python benchmarks/nas3r_parity.py --predict-check outputs/nas3r --record docs/results/nas3r/parity.json

NAS3R's public code (github.com/ranrhuang/NAS3R) is not part of this repository: ``--source`` names a plain
copy of it (default ``.peer/nas3r``, git-ignored), mounted as ``benchmarks/peer_step.py`` mounts it; its
imports that this project does not depend on (einops, jaxtyping, huggingface_hub) are looked up in ``--site``
too (default ``.peer/site``: ``pip install --target .peer/site einops jaxtyping huggingface_hub``).

For each case, NAS3R's encoder is built from its own classes and YAML files with random weights (``pretrained``
forced off; the ``pretrained`` experiment's settings: one camera-head iteration, sigmoid depth in [1, 100],
the camera head's FoV initialised at 2·atan(0.5)); this project's ``large`` network (``appearance:
baseline``: NAS3R's own SH) is built and given NAS3R's tensors through the loader every command uses
(``aesplat.model.nas3r``). Both run on the same random images (context views, then target views, which enter
the masked attention and get their poses from the camera head) and the same normalised intrinsics. Compared:
the cameras of all views (camera-to-world relative to view 0, normalised intrinsics), the context depth maps
and every Gaussian parameter (means, scales, rotations, opacities, SH); each figure is the largest absolute
difference over the largest absolute value of NAS3R's tensor. Both sets of Gaussians are then rendered by
this project's rasterizer into NAS3R's target cameras; the PSNR of one render against the other is reported.

NAS3R's camera head attends across all views' camera tokens, so its target views change its context cameras
(and through them the Gaussians' centres). This project's default (``model.net.options.camera_mask: true``)
masks that attention as the trunk's global attention is masked; the comparison above is made with
``camera_mask: false`` (NAS3R's head exactly), and a second one checks the default: with the same weights and
the target views given, its context cameras, depth and Gaussians against NAS3R's run on the context views alone.

Cases (full size: 224 x 224): 2 context + 1 target (NAS3R's training setting), 3 and 10 context + 1 target
(its multiview checkpoints), and 2 + 1 of the ``-I`` network, which reads every view's intrinsics.

``--fixture`` writes the file the CI test ``tests/model/test_nas3r_parity.py`` checks: the same three kinds of
case from NAS3R's code at a reduced size (its DINOv2 encoder replaced by one of its own ViT blocks at width 32,
4 alternating block pairs, a one-block camera head, DPT heads at width 16, images of 28 x 42), with NAS3R's
weights (VGGT's unused point head left out), inputs and outputs, so parity is checked on every commit without
NAS3R's source.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib
import json
import math
import sys
import time
from pathlib import Path

import torch
from common import provenance, write_whole
from peer_step import PKG, build_encoder, mount, read_config
from torch import Tensor, nn

from aesplat.model.encoder import EncoderConfig
from aesplat.model.model import AESplatModel, ModelConfig, build_model
from aesplat.model.nas3r import load_nas3r_state
from aesplat.model.transformer import TransformerConfig
from aesplat.render import render
from aesplat.types import Gaussians

ROOT = Path(__file__).resolve().parents[1]
FULL_CASES = {"2+1": (2, 1, False), "3+1": (3, 1, False), "10+1": (10, 1, False), "2+1-I": (2, 1, True)}
SMALL_CASES = {"2+1": (2, 1, False), "3+1": (3, 1, False), "2+1-I": (2, 1, True)}
SMALL_SIZE = (28, 42)
# The reduced network of the fixture, as this project's settings (NAS3R's side is built to match: small_nas3r).
SMALL = ModelConfig(
    encoder=EncoderConfig(dim=32, depth=1, num_heads=2, num_registers=4, pos_grid=16),
    transformer=TransformerConfig(dim=32, depth=4, num_heads=2, num_register_tokens=4, layers=(0, 1, 2, 3)),
    head_features=16,
    head_channels=(8, 16, 32, 32),
    camera_depth=1,
    appearance="baseline",
    view_aggregation="pool",
    sh_degree=4,
    near=1.0,
    far=100.0,
)


def small_nas3r(encoder_module) -> None:
    """Make NAS3R's constructors build the reduced network of the fixture (module globals they look up)."""
    vggt = importlib.import_module(f"{PKG}.model.encoder.backbone.vggt.models.vggt")
    aggregator = importlib.import_module(f"{PKG}.model.encoder.backbone.vggt.models.aggregator")
    backbone = importlib.import_module(f"{PKG}.model.encoder.backbone.backbone_masked_vggt")
    vit = importlib.import_module(f"{PKG}.model.encoder.backbone.vggt.layers.vision_transformer")
    dpt_gs = importlib.import_module(f"{PKG}.model.encoder.backbone.vggt.heads.dpt_gs_head")
    e, t = SMALL.encoder, SMALL.transformer
    block = functools.partial(vit.Block, attn_class=vit.MemEffAttention)
    aggregator.vit_large = lambda **kw: vit.DinoVisionTransformer(
        embed_dim=e.dim, depth=e.depth, num_heads=e.num_heads, mlp_ratio=4, block_fn=block, **kw
    )
    vggt.Aggregator = functools.partial(vggt.Aggregator, depth=t.depth, num_heads=t.num_heads)
    backbone.VGGT = functools.partial(backbone.VGGT, img_size=e.pos_grid * e.patch_size, embed_dim=t.dim)
    vggt.CameraHead = functools.partial(vggt.CameraHead, trunk_depth=SMALL.camera_depth, num_heads=t.num_heads)
    heads = {"features": SMALL.head_features, "out_channels": list(SMALL.head_channels),
             "intermediate_layer_idx": list(t.layers)}  # fmt: skip
    vggt.DPTHead = functools.partial(vggt.DPTHead, **heads)
    encoder_module.DPTGSHead = lambda dim_in, output_dim: dpt_gs.DPTGSHead(
        2 * t.dim, output_dim=output_dim, **heads
    )


def build_nas3r(source: Path, intrinsics: bool, small: bool, seed: int) -> nn.Module:
    """NAS3R's encoder as its RE10K ``pretrained`` experiment builds it (``-I``: re10k-I), random weights."""
    encoder_cfg, _ = read_config(source, "pretrained", "re10k-I" if intrinsics else "re10k")
    if small:
        small_nas3r(importlib.import_module(f"{PKG}.model.encoder.encoder_nas3r"))
    torch.manual_seed(seed)
    encoder = build_encoder(encoder_cfg, [])
    if small:  # the two widths NAS3R's code fixes at VGGT-1B's, set to the reduced network's
        agg = encoder.backbone.model.aggregator
        if agg.intrinsics_embed_loc != "none":
            agg.intrinsic_encoder = nn.Linear(9, SMALL.transformer.dim)
        encoder.gaussian_param_head.input_merger[0] = nn.Conv2d(3, SMALL.head_features // 2, 7, 1, 3)
    with torch.no_grad():  # the fixed, small initialisations (tokens, layer scales) would hide differences
        for p in encoder.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return encoder.eval()


def make_inputs(vc: int, vt: int, size: tuple[int, int], seed: int) -> dict[str, Tensor]:
    gen = torch.Generator().manual_seed(seed)
    v = vc + vt
    k = torch.tensor([[0.86, 0.0, 0.5], [0.0, 0.86 * size[1] / size[0], 0.5], [0.0, 0.0, 1.0]])
    k = k.expand(1, v, 3, 3).clone()
    k[..., :2, :2] *= 1 + 0.05 * torch.rand(1, v, 1, 1, generator=gen)  # views' focals differ a little
    return {"images": torch.rand(1, v, 3, *size, generator=gen), "intrinsics": k, "vc": torch.tensor(vc)}


@torch.no_grad()
def run_nas3r(encoder: nn.Module, inputs: dict[str, Tensor], targets: bool = True) -> dict[str, Tensor]:
    """NAS3R's outputs; ``targets=False``: its run on the context views alone."""
    vc = int(inputs["vc"])
    images, k = inputs["images"], inputs["intrinsics"]
    context = {"image": images[:, :vc], "intrinsics": k[:, :vc]}
    target = {"image": images[:, vc:], "intrinsics": k[:, vc:]} if targets else None
    dump: dict = {}
    out = encoder(context, 0, visualization_dump=dump, target=target)
    g = out["gaussians"]
    which = "cwt" if targets else "c"
    intrinsics = out["intrinsics"][which] if "intrinsics" in out else k[:, : vc if not targets else None]
    return {
        "extrinsics": out["extrinsics"][which], "intrinsics": intrinsics, "depth": dump["depth"],
        "means": g.means, "scales": g.scales, "quats": g.rotations, "opacities": g.opacities,
        "sh": g.harmonics.transpose(-1, -2),  # [B, N, 3, K] -> [B, N, K, 3]
    }  # fmt: skip


def build_ours(nas3r: nn.Module, intrinsics: bool, small: bool, camera_mask: bool) -> AESplatModel:
    """This project's network with NAS3R's weights; ``camera_mask=False`` is NAS3R's camera head exactly (its
    context cameras see the targets), True this project's default (they do not)."""
    if small:
        cfg = SMALL
        model = AESplatModel(
            ModelConfig(**{**cfg.__dict__, "camera_mask": camera_mask, "transformer": TransformerConfig(
                **{**cfg.transformer.__dict__, "intrinsics_tokens": intrinsics})})
        )  # fmt: skip
    else:
        model = build_model("large", "baseline", 4, view_aggregation="pool", near=1.0, far=100.0,
                            intrinsics_tokens=intrinsics, camera_mask=camera_mask)  # fmt: skip
    load_nas3r_state(model, {"encoder." + k: v for k, v in nas3r.state_dict().items()}, "NAS3R (random)")
    return model.eval()


@torch.no_grad()
def run_ours(model: AESplatModel, inputs: dict[str, Tensor], targets: bool = True) -> dict[str, Tensor]:
    vc = int(inputs["vc"])
    images = inputs["images"] if targets else inputs["images"][:, :vc]
    k = inputs["intrinsics"][:, : images.shape[1]] if model.takes_intrinsics else None
    out = model(images[:, :vc], images[:, vc:] if targets else None, intrinsics=k)
    g = out.gaussians
    return {
        "extrinsics": out.extrinsics, "intrinsics": out.intrinsics, "depth": out.depth, "means": g.means,
        "scales": g.scales, "quats": g.quats, "opacities": g.opacities, "sh": g.sh,
    }  # fmt: skip


def compare(ours: dict[str, Tensor], theirs: dict[str, Tensor]) -> dict[str, dict[str, float]]:
    """Per output: the largest absolute difference, NAS3R's largest absolute value, and their ratio."""
    rows = {}
    for name, ref in theirs.items():
        diff = float((ours[name].double() - ref.double()).abs().max())
        scale = float(ref.double().abs().max())
        rows[name] = {"max_abs_diff": diff, "max_abs": scale, "relative": diff / scale if scale else diff}
    return rows


@torch.no_grad()
def render_psnr(ours: dict[str, Tensor], theirs: dict[str, Tensor], vc: int, size: tuple[int, int]) -> float:
    """PSNR (dB) of this project's rasterizer's render of our Gaussians against its render of NAS3R's, in
    NAS3R's target cameras."""

    def gaussians(o: dict[str, Tensor]) -> Gaussians:
        return Gaussians(means=o["means"], quats=o["quats"], scales=o["scales"], opacities=o["opacities"],
                         sh=o["sh"])  # fmt: skip

    cams = theirs["extrinsics"][:, vc:], theirs["intrinsics"][:, vc:]
    a = render(gaussians(ours), *cams, *size, backend="torch").color.clamp(0, 1)
    b = render(gaussians(theirs), *cams, *size, backend="torch").color.clamp(0, 1)
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


def run_case(source: Path, name: str, vc: int, vt: int, intrinsics: bool, small: bool, seed: int) -> dict:
    size = SMALL_SIZE if small else (224, 224)
    start = time.perf_counter()
    nas3r = build_nas3r(source, intrinsics, small, seed)
    inputs = make_inputs(vc, vt, size, seed)
    theirs = run_nas3r(nas3r, inputs)
    theirs_context = run_nas3r(nas3r, inputs, targets=False)
    ours_model = build_ours(nas3r, intrinsics, small, camera_mask=False)
    masked_model = build_ours(nas3r, intrinsics, small, camera_mask=True)
    state = {k: v.clone() for k, v in nas3r.state_dict().items() if ".point_head." not in k}  # unused
    del nas3r
    ours = run_ours(ours_model, inputs)
    rows = compare(ours, theirs)
    # the default (masked camera head) with targets: its context outputs are NAS3R's on the context alone
    masked = run_ours(masked_model, inputs)
    masked_rows = compare(context_part(masked, vc), theirs_context)
    case = {
        "case": name, "context_views": vc, "target_views": vt, "intrinsics_input": intrinsics,
        "size": list(size), "outputs": rows, "max_relative": max(r["relative"] for r in rows.values()),
        "render_psnr_db": render_psnr(ours, theirs, vc, size),
        "masked_context": masked_rows,
        "masked_context_max_relative": max(r["relative"] for r in masked_rows.values()),
        "seconds": time.perf_counter() - start,
    }  # fmt: skip
    print(f"{name}: max relative difference {case['max_relative']:.2e} "
          f"({max(rows, key=lambda k: rows[k]['relative'])}), render {case['render_psnr_db']:.1f} dB; "
          f"masked camera head, context outputs vs NAS3R on the context alone: "
          f"{case['masked_context_max_relative']:.2e}; {case['seconds']:.0f} s", flush=True)  # fmt: skip
    if small:
        case["fixture"] = {"network": "nas3r-I" if intrinsics else "nas3r", "state": state, "inputs": inputs,
                           "outputs": theirs, "context_outputs": theirs_context}  # fmt: skip
    return case


def context_part(out: dict[str, Tensor], vc: int) -> dict[str, Tensor]:
    """The context views' cameras of a run with targets (the Gaussians and depth are the context's anyway)."""
    return {**out, "extrinsics": out["extrinsics"][:, :vc], "intrinsics": out["intrinsics"][:, :vc]}


PANORAMA = "viser/_assets/hdri/st_fagans_interior_1k.jpg"  # a photo of a room, in the viewer extra's package


def real_photos(out: Path) -> list[Path]:
    """Two overlapping views of a real room: square crops, 40° of yaw apart, of an equirectangular photo that
    viser ships (no download), saved as PNG."""
    import viser
    from PIL import Image

    pano = Image.open(Path(viser.__file__).parent.parent / PANORAMA).convert("RGB")
    w, h = pano.size
    side = h // 2
    paths = []
    for i, left in enumerate((w // 4, w // 4 + w // 9)):
        path = out / f"photo_{i}.png"
        pano.crop((left, h // 4, left + side, h // 4 + side)).save(path)
        paths.append(path)
    return paths


def predict_check(source: Path, out: Path, seed: int) -> dict:
    """As a new user: a NAS3R checkpoint (random weights from NAS3R's code, in its Lightning checkpoint layout)
    given to `aesplat predict` with two real photos; the cameras it writes against NAS3R's own forward on the
    same images as predict feeds them, and the PLY's header and size read back."""
    import subprocess

    import lightning

    from aesplat.images import load_image

    out.mkdir(parents=True, exist_ok=True)
    nas3r = build_nas3r(source, False, False, seed)
    ckpt = out / "nas3r_random.ckpt"
    state = {"encoder." + k: v for k, v in nas3r.state_dict().items()}
    torch.save({"state_dict": state, "pytorch-lightning_version": lightning.__version__, "epoch": 0,
                "global_step": 0, "loops": {}, "callbacks": {}, "optimizer_states": [], "lr_schedulers": []},
               ckpt)  # fmt: skip
    photos = real_photos(out)
    pred = out / "pred"
    command = [sys.executable, "-m", "aesplat.cli", "predict", "--ckpt", str(ckpt), *map(str, photos), "--out",
               str(pred), "--overwrite", "--no-progress", "--device", "cpu", "--novel-frames", "2"]  # fmt: skip
    start = time.perf_counter()
    run = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if run.returncode:
        raise SystemExit(f"aesplat predict failed ({run.returncode}): {run.stderr[-2000:]}")
    cameras = json.loads((pred / "cameras.json").read_text())["views"]
    ours_e = torch.tensor([v["camera_to_world"] for v in cameras])[None]
    ours_k = torch.tensor([v["intrinsics_normalized"] for v in cameras])[None]
    images = torch.stack([load_image(p, 224, (0.0, 0.0, 0.0), patch=14).image for p in photos])[None]
    inputs = {"images": images, "intrinsics": torch.eye(3).expand(1, 2, 3, 3), "vc": torch.tensor(2)}
    theirs = run_nas3r(nas3r, inputs, targets=False)
    rows = compare({"extrinsics": ours_e, "intrinsics": ours_k},
                   {"extrinsics": theirs["extrinsics"], "intrinsics": theirs["intrinsics"]})  # fmt: skip
    ply = pred / "gaussians.ply"
    header = ply.read_bytes()[:4096].split(b"end_header\n")[0].decode().splitlines()
    vertices = int(next(line.split()[-1] for line in header if line.startswith("element vertex")))
    properties = [line.split()[-1] for line in header if line.startswith("property")]
    ckpt.unlink()  # 4.8 GB
    return {
        "photos": f"two 40°-apart crops of site-packages/{PANORAMA}", "predict_seconds": seconds,
        "cameras": rows, "max_relative": max(r["relative"] for r in rows.values()),
        "ply": {"format": header[1], "vertices": vertices, "properties": len(properties),
                "first_properties": properties[:14], "bytes": ply.stat().st_size},
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=ROOT / ".peer" / "nas3r", help="plain copy of NAS3R")
    parser.add_argument(
        "--site", type=Path, default=ROOT / ".peer" / "site", help="extra packages NAS3R imports"
    )
    parser.add_argument(
        "--cases", nargs="+", default=None, help=f"full-size cases (default all: {list(FULL_CASES)})"
    )
    parser.add_argument("--seed", type=int, default=0)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--out", type=Path, help="full size: write the figures here as JSON")
    group.add_argument("--fixture", type=Path, help="reduced size: write the CI fixture here")
    group.add_argument("--predict-check", type=Path, metavar="DIR",
                       help="full size: `aesplat predict` on a NAS3R checkpoint (written into DIR, then "
                       "removed) and two real photos; the figures go into --record")  # fmt: skip
    parser.add_argument(
        "--record", type=Path, default=None, help="with --predict-check: the JSON to add them to"
    )
    args = parser.parse_args()
    if not (args.source / "src").is_dir():
        raise SystemExit(f"nas3r_parity.py: no NAS3R source at {args.source} (a plain copy of its repository)")
    if args.site.is_dir():
        sys.path.append(str(args.site))
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    notes = mount(args.source.resolve())
    if args.predict_check is not None:
        check = {**predict_check(args.source.resolve(), args.predict_check, args.seed), **provenance()}
        print(
            f"aesplat predict on a NAS3R checkpoint: cameras within {check['max_relative']:.1e} of NAS3R's "
            f"forward; PLY {check['ply']['format']}, {check['ply']['vertices']:,} Gaussians",
            flush=True,
        )
        if args.record is not None:
            record = json.loads(args.record.read_text()) if args.record.is_file() else {}
            write_whole(args.record, (json.dumps({**record, "predict_check": check}, indent=2) + "\n").encode())
        return
    small = args.fixture is not None
    cases = SMALL_CASES if small else {k: FULL_CASES[k] for k in (args.cases or FULL_CASES)}
    record = {"precision": "fp32", "torch": torch.__version__, "notes": notes, "cases": [], **provenance()}
    commit_file = args.source / "COMMIT"
    record["nas3r_commit"] = commit_file.read_text().strip() if commit_file.is_file() else None
    for name, (vc, vt, intrinsics) in cases.items():
        record["cases"].append(run_case(args.source.resolve(), name, vc, vt, intrinsics, small, args.seed))
        if args.out is not None:  # what is measured so far, in case a later case fails
            write_whole(args.out, (json.dumps(record, indent=2) + "\n").encode())
    if small:
        states = {
            c["fixture"]["network"]: c["fixture"].pop("state") for c in record["cases"]
        }  # one per network
        fixture = {"net": dataclasses.asdict(SMALL), "states": states, "cases": record["cases"],
                   "nas3r_commit": record["nas3r_commit"]}  # fmt: skip
        args.fixture.parent.mkdir(parents=True, exist_ok=True)
        torch.save(fixture, args.fixture)
        print(f"wrote {args.fixture} ({args.fixture.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
