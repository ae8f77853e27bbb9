"""`aesplat predict`: unposed images in; Gaussians (PLY), cameras, re-renders, depth and a novel-view path out.

    aesplat predict --ckpt CKPT --out DIR IMAGE IMAGE [IMAGE ...]

The first image is the reference frame (the world of the outputs), the others follow in the order given.

writes

    DIR/gaussians.ply     one Gaussian per input pixel, reference 3DGS layout (see aesplat.export.ply)
    DIR/cameras.json      predicted camera of every input view (and of every novel frame)
    DIR/inputs/           the images as the model saw them (resized at their aspect ratio, or cropped: see
                          cameras.json, views[].source)
    DIR/renders/          the input views re-rendered from the Gaussians with the predicted cameras
    DIR/depth/            predicted depth per input view: colour-mapped PNG and raw float32 .npy
    DIR/novel/            frames along a path through the predicted input cameras, and trajectory.gif
    DIR/colmap/, DIR/nerfstudio/, DIR/gaussians.splat
                          with ``--export colmap,nerfstudio,splat`` (see aesplat.export; ``aesplat export``
                          writes them from a prediction folder later)

DIR is written whole: into a hidden folder beside it, renamed into place once everything is written (a
failure leaves DIR as it was). A non-empty DIR is refused unless ``--overwrite``, which replaces it as a whole.
A checkpoint trained with ``model.cameras: dataset`` is refused: its camera head never trained, and images
come without poses here. Every refusal is one line (see docs/troubleshooting.md).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor
from tqdm import tqdm

from .camera_path import camera_record, interpolate_cameras
from .commands import HelpFormatter, OneLineParser, resolve_device
from .errors import UserError, nearest_existing, run_reporting_user_errors
from .export import EXPORTS, VIEWER_MAX_SH_DEGREE, drop_transparent, export_prediction, parse_formats, write_ply
from .files import check_output_dir, written_whole
from .images import CROPS, colorize_depth, save_image
from .inference import Prediction, predict_photos, render_views
from .render import BACKENDS
from .threads import ENV_OVERRIDE, apply_thread_policy


def compact_json(obj: object) -> str:
    """JSON with two-space indents but each innermost list of numbers (a matrix row) on one line."""
    text = json.dumps(obj, indent=2)
    numbers = re.compile(r"\[([-0-9.eE+,\s]+)\]")
    return numbers.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)


def write_outputs(
    out_dir: Path,
    names: list[str],
    images: Tensor,  # [V, 3, H, W]
    pred: Prediction,
    *,
    novel_frames: int,
    ply_sh_degree: int | None,
    min_opacity: float,
    render_options: dict | None = None,
    progress: bool = True,
    sources: list[dict] | None = None,
) -> dict:
    """Render and write every output of ``aesplat predict`` under ``out_dir``; returns the cameras record.
    ``sources``: per view, what part of which photo the model saw (``InputImage.crop_record``)."""
    v, _, height, width = images.shape
    steps = 2 * v + novel_frames + 2  # inputs+depth, re-renders, novel frames, PLY, cameras
    bar = tqdm(total=steps, desc="aesplat predict", unit="step", disable=not progress)
    for i in range(v):
        save_image(images[i], out_dir / "inputs" / f"{i:02d}_{names[i]}.png")
        (out_dir / "depth").mkdir(parents=True, exist_ok=True)
        np.save(out_dir / "depth" / f"{i:02d}_{names[i]}.npy", pred.depth[i].cpu().numpy().astype(np.float32))
        Image.fromarray(colorize_depth(pred.depth[i])).save(out_dir / "depth" / f"{i:02d}_{names[i]}.png")
        bar.update(1)
    renders = render_views(pred.gaussians, pred.extrinsics, pred.intrinsics, height, width, render_options,
                           progress=bar)  # fmt: skip
    for i in range(v):
        save_image(renders[i], out_dir / "renders" / f"{i:02d}_{names[i]}.png")
    novel_ext, novel_int = interpolate_cameras(pred.extrinsics, pred.intrinsics, novel_frames)
    novel = render_views(pred.gaussians, novel_ext, novel_int, height, width, render_options, progress=bar)
    for f in range(novel_frames):
        save_image(novel[f], out_dir / "novel" / f"{f:03d}.png")
    frames = [Image.open(out_dir / "novel" / f"{f:03d}.png") for f in range(novel_frames)]
    frames += frames[-2:0:-1]  # there and back again
    frames[0].save(
        out_dir / "novel" / "trajectory.gif", save_all=True, append_images=frames[1:], duration=80, loop=0
    )

    gaussians = drop_transparent(pred.gaussians, min_opacity)
    degree = min(gaussians.sh_degree, VIEWER_MAX_SH_DEGREE) if ply_sh_degree is None else ply_sh_degree
    write_ply(out_dir / "gaussians.ply", gaussians, sh_degree=degree)
    bar.update(1)
    cameras = {
        "convention": "OpenCV axes (x right, y down, z forward); world = the first input view's camera frame; "
        "intrinsics_normalized has fx, cx divided by width and fy, cy by height",
        "views": [
            {
                "image": names[i],
                **camera_record(pred.extrinsics[i].cpu(), pred.intrinsics[i].cpu(), height, width),
                **({"source": sources[i]} if sources else {}),
            }
            for i in range(v)
        ],
        "novel": [
            camera_record(novel_ext[f].cpu(), novel_int[f].cpu(), height, width) for f in range(novel_frames)
        ],
        "gaussians": {"count": gaussians.num_gaussians, "ply_sh_degree": degree, "min_opacity": min_opacity},
        # what the renders were made with, so that a viewer renders the same images from these files
        "render": _render_record(render_options),
    }
    (out_dir / "cameras.json").write_text(compact_json(cameras))
    bar.update(1)
    bar.close()
    return cameras


def _render_record(render_options: dict | None) -> dict:
    """The background and renderer options of ``render_options`` as JSON (the backend is the machine's)."""
    options = dict(render_options or {})
    background = options.pop("background", None)
    options.pop("backend", None)
    background = [0.0, 0.0, 0.0] if background is None else torch.as_tensor(background).tolist()
    return {"background": background, "options": options}


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="aesplat predict",
        description="Predict cameras and 3D Gaussians from unposed images with a trained checkpoint; write a "
        "3DGS PLY, the cameras, re-renders of the inputs, depth maps and a short novel-view path.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("images", nargs="+", metavar="IMAGE",
                        help="2 or more images of one scene; the first is the reference frame, the others "
                        "follow in the order given (a model with the paper's appearance head, "
                        "view_aggregation concat, takes exactly the count it was built for, 2; a pool model "
                        "any); photos keep their aspect ratio (that of the first; others are centre-cropped "
                        "to it); any size down to half the model's input; 16-bit images keep their range, "
                        "transparent pixels are composited over the model's background colour, EXIF "
                        "orientation is applied")  # fmt: skip
    parser.add_argument("--ckpt", required=True, help="checkpoint written by `aesplat fit` (last.ckpt / best)")
    parser.add_argument("--out", required=True,
                        help="output folder: created whole (written beside it, then renamed into place); an "
                        "existing non-empty folder is refused unless --overwrite")  # fmt: skip
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a non-empty --out folder as a whole (its old contents are removed)",
    )
    parser.add_argument("--size", type=int, default=None,
                        help="the shorter side of the model's input, a multiple of the model's patch size; the "
                        "longer side follows the photo's aspect ratio (default: the image size the checkpoint "
                        "was trained at)")  # fmt: skip
    parser.add_argument("--crop", choices=CROPS, default="none",
                        help="none: the photo's own aspect ratio; square: a centre square, the shape the "
                        "models are trained on (cameras.json says what was cropped)")  # fmt: skip
    parser.add_argument("--intrinsics", default=None, metavar="FX,FY,CX,CY",
                        help="every photo's focal lengths and principal point, normalised by its width and "
                        "height (e.g. 0.86,0.86,0.5,0.5); for the checkpoints that read intrinsics (NAS3R's "
                        "-I), which need them; the others predict them")  # fmt: skip
    parser.add_argument("--novel-frames", type=int, default=30, help="frames of the novel-view path")
    parser.add_argument("--ply-sh-degree", type=int, default=None,
                        help="SH bands written to the PLY (default: min(model degree, 3), what common 3DGS "
                        "viewers read)")  # fmt: skip
    parser.add_argument("--min-opacity", type=float, default=0.0,
                        help="leave Gaussians below this opacity out of the PLY")  # fmt: skip
    parser.add_argument("--export", default=None, metavar="FORMATS",
                        help="also write these exports, comma-separated: colmap (DIR/colmap/), "
                        "nerfstudio (DIR/nerfstudio/), splat (DIR/gaussians.splat); see `aesplat export "
                        "--help`")  # fmt: skip
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:1, ... (auto: cuda if available)")
    parser.add_argument("--backend", default="auto", help="renderer backend: auto, torch or gsplat")
    parser.add_argument("--threads", type=int, default=None,
                        help=f"torch CPU threads (default: the usable cores, or ${ENV_OVERRIDE})")  # fmt: skip
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``aesplat predict`` (see ``--help``)."""
    args = build_parser().parse_args(argv)
    return run_reporting_user_errors("predict", lambda: _predict(args))


def check_options(args: argparse.Namespace) -> None:
    """Every option's value, checked before anything is loaded or written (one line each)."""
    if len(args.images) < 2:
        raise UserError("give at least two images of the same scene")
    if args.novel_frames < 2:
        raise UserError("--novel-frames must be at least 2")
    if args.size is not None and args.size < 1:
        raise UserError(f"--size must be a positive number of pixels, got {args.size}")
    if args.ply_sh_degree is not None and args.ply_sh_degree < 0:
        raise UserError(f"--ply-sh-degree must be 0 or more, got {args.ply_sh_degree}")
    if not 0.0 <= args.min_opacity < 1.0:
        raise UserError(f"--min-opacity must be in [0, 1), got {args.min_opacity}")
    if args.backend != "auto" and args.backend not in BACKENDS:
        raise UserError(f"--backend {args.backend} is not a renderer: give auto, {', '.join(BACKENDS)}")
    if args.intrinsics is not None:
        args.intrinsics = parse_intrinsics(args.intrinsics)


def parse_intrinsics(text: str) -> tuple[float, float, float, float]:
    """``--intrinsics FX,FY,CX,CY`` -> four floats: positive focal lengths, a principal point inside the photo
    (all normalised by the photo's width and height); UserError (one line) otherwise."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise UserError(f"--intrinsics {text!r} is not four numbers FX,FY,CX,CY (e.g. 0.86,0.86,0.5,0.5)")
    fx, fy, cx, cy = values
    if fx <= 0 or fy <= 0 or not (0 < cx < 1 and 0 < cy < 1):
        raise UserError(f"--intrinsics {text}: focal lengths must be > 0 and the principal point inside the "
                        "photo (0 < CX, CY < 1), all normalised by its width and height")  # fmt: skip
    return values


def check_name_lengths(out: Path, photos: list[str], names: list[str]) -> None:
    """Refuse, before the model loads, a photo whose outputs' file name (``inputs/NN_NAME.png``, the longest)
    is longer than the file system under ``out`` allows."""
    try:
        limit = os.pathconf(nearest_existing(out.resolve().parent), "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for i, (photo, name) in enumerate(zip(photos, names)):
        length = len(os.fsencode(f"{i:02d}_{name}.png"))
        if length > limit:
            raise UserError(f"the input image {photo!r} makes a {length}-byte file name under --out (this file "
                            f"system allows {limit}); rename the photo")  # fmt: skip


def _predict(args: argparse.Namespace) -> int:
    apply_thread_policy(num_workers=0, override=args.threads)
    check_options(args)
    out_dir = Path(args.out)
    inputs = [("--ckpt", args.ckpt), *(("the input image", image) for image in args.images)]
    check_output_dir(out_dir, args.overwrite, inputs)
    names = [Path(p).stem for p in args.images]
    check_name_lengths(out_dir, args.images, names)
    exports = parse_formats(args.export) if args.export is not None else []
    device = resolve_device(args.device)
    photos = predict_photos(args.ckpt, args.images, size=args.size, crop=args.crop, device=device,
                            intrinsics=args.intrinsics)  # fmt: skip
    loaded, inputs, images, pred, shape = photos.loaded, photos.inputs, photos.images, photos.pred, photos.shape
    model_degree = loaded.sh_degree
    if args.ply_sh_degree is not None and not 0 <= args.ply_sh_degree <= model_degree:
        raise UserError(f"--ply-sh-degree must be in 0..{model_degree} for this checkpoint")
    options = {**loaded.render_options(device), "backend": args.backend}
    with written_whole(out_dir, args.overwrite, "aesplat predict", "--out") as staging:
        write_outputs(
            staging, names, images, pred, novel_frames=args.novel_frames, ply_sh_degree=args.ply_sh_degree,
            min_opacity=args.min_opacity, render_options=options, progress=not args.no_progress,
            sources=[i.crop_record() for i in inputs],
        )  # fmt: skip
        export_prediction(staging, exports)
    written = "".join(", " + EXPORTS[name].dest for name in exports)
    print(f"aesplat predict: {len(inputs)} views of {shape[1]}x{shape[0]} pixels; wrote "
          f"{out_dir / 'gaussians.ply'} ({pred.gaussians.num_gaussians:,} Gaussians), cameras.json, inputs/, "
          f"renders/, depth/, novel/{written} under {out_dir}")  # fmt: skip
    for name, i in zip(names, inputs):
        if i.cropped:
            left, top, right, bottom = (round(c) for c in i.crop)
            print(f"aesplat predict: {name!r} ({i.source[0]}x{i.source[1]}) was centre-cropped to its pixels "
                  f"x {left}..{right}, y {top}..{bottom} (cameras.json: views[].source)")  # fmt: skip
    return 0
