"""The command line of ``aesplat view`` (see ``--help``)."""

from __future__ import annotations

import argparse
import importlib.util
import signal
import threading

from ..errors import UserError, run_reporting_user_errors
from ..images import CROPS
from .scene import scene_from_checkpoint, scene_from_path

VIEWER_EXTRA = 'pip install -e ".[viewer]"'


def build_parser() -> argparse.ArgumentParser:
    from .app import MODES, ViewerOptions

    defaults = ViewerOptions()
    parser = argparse.ArgumentParser(
        prog="aesplat view",
        description="Look at a prediction in the browser: the Gaussians, the input cameras with their images "
        "and the novel-view path, rendered by the browser (fast) or by this project's rasterizer with "
        "view-dependent colour (exact).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("inputs", nargs="*", metavar="PATH",
                        help="a prediction folder of `aesplat predict`, or a 3DGS .ply file; with --ckpt: the "
                        "images to predict from")  # fmt: skip
    parser.add_argument("--ckpt", default=None, help="predict from the images with this checkpoint, then view")
    parser.add_argument("--size", type=int, default=None,
                        help="with --ckpt: the model's square input side (default: its own)")  # fmt: skip
    parser.add_argument("--crop", choices=CROPS, default="none",
                        help="with --ckpt: as `aesplat predict --crop`")  # fmt: skip
    parser.add_argument("--intrinsics", default=None, metavar="FX,FY,CX,CY",
                        help="with --ckpt: as `aesplat predict --intrinsics` (NAS3R -I)")  # fmt: skip
    parser.add_argument("--host", default=defaults.host,
                        help="address to listen on; 0.0.0.0 shares the viewer with the network (the printed "
                        "URL, its key included, then opens it from another machine)")  # fmt: skip
    parser.add_argument("--port", type=int, default=defaults.port, help="port (0: any free port)")
    parser.add_argument("--mode", choices=MODES, default=defaults.mode, help="render mode to start in")
    parser.add_argument("--hide-cameras", action="store_true", help="start with the input cameras hidden")
    parser.add_argument("--show-path", action="store_true", help="start with the novel-view path shown")
    parser.add_argument("--exact-height", type=int, default=defaults.exact_height,
                        help="pixel height of the exact mode's renders (at most the browser's; the width at "
                        "most 4 times the height)")  # fmt: skip
    parser.add_argument(
        "--device", default="auto", help="where predictions and exact renders run: cpu, cuda, …"
    )
    parser.add_argument("--backend", default=defaults.backend, help="renderer backend: auto, torch or gsplat")
    return parser


def require_viewer_extra() -> None:
    """One line naming the install command when viser (the `viewer` extra) is missing."""
    if importlib.util.find_spec("viser") is None:
        raise UserError(f"the viewer extra is not installed: {VIEWER_EXTRA}")


def start_viewer(args: argparse.Namespace):
    """Load what ``args`` name and start the viewer on it (returns the running Viewer)."""
    from ..commands import resolve_device
    from ..predict import parse_intrinsics
    from .app import Viewer, ViewerOptions

    require_viewer_extra()
    if args.exact_height < 8:
        raise UserError("--exact-height must be at least 8 pixels")
    if not 0 <= args.port < 65536:
        raise UserError(f"--port {args.port} is not a port number (0..65535)")
    device = resolve_device(args.device)
    if args.ckpt:
        intrinsics = parse_intrinsics(args.intrinsics) if args.intrinsics is not None else None
        scene = scene_from_checkpoint(
            args.ckpt, args.inputs, size=args.size, crop=args.crop, device=str(device), intrinsics=intrinsics
        )
    elif len(args.inputs) == 1:
        scene = scene_from_path(args.inputs[0])
    else:
        raise UserError(
            "give one prediction folder or .ply file, or --ckpt CKPT and the images to predict from"
        )
    options = ViewerOptions(host=args.host, port=args.port, mode=args.mode, show_cameras=not args.hide_cameras,
                            show_path=args.show_path, exact_height=args.exact_height, device=str(device),
                            backend=args.backend)  # fmt: skip
    return Viewer(scene, options)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``aesplat view``: serve until Ctrl-C (or SIGTERM), then stop cleanly."""
    args = build_parser().parse_args(argv)

    def run() -> int:
        viewer = start_viewer(args)
        done = threading.Event()
        # Both signals set the event, SIGINT included: a shell starts a background job with SIGINT ignored,
        # and Python then installs no KeyboardInterrupt handler of its own.
        previous = {sig: signal.signal(sig, lambda *_: done.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:  # from here on, Ctrl-C (or SIGTERM) stops the viewer cleanly
            print(f"aesplat view: {viewer.url}  ({viewer.scene.source}; Ctrl-C to stop)", flush=True)
            done.wait()
        except KeyboardInterrupt:  # a Ctrl-C that came before the handlers were installed
            pass
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            viewer.stop()
        print("aesplat view: stopped", flush=True)
        return 0

    return run_reporting_user_errors("view", run)
