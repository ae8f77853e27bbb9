"""The command line of ``aesplat bench`` (see ``--help``): its options, the evaluation scenes of the run's data
set, and ``main``."""

from __future__ import annotations

import argparse
import inspect
import math
import shlex
import sys
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import torch

from ..commands import HelpFormatter, OneLineParser, resolve_device
from ..errors import UserError
from ..render import BACKENDS
from ..threads import ENV_OVERRIDE, apply_thread_policy
from ..types import BatchedExample, BatchedViews
from .report import machine_meta, write_report
from .run import Bench, contexts_of, each_scene, single_scenes
from .sweep import KNOB_TITLES, PRECISIONS, default_sweep
from .timing import LoadWatch, busy_warning, other_cores_busy, steady_allocator

T = TypeVar("T")


def _listed(parse: Callable[[str], T], what: str) -> Callable[[str], list[T]]:
    """An argparse ``type``: comma-separated values, each read by ``parse`` (empty ones skipped); text it cannot
    read is a command-line error saying the option takes a list of ``what``."""

    def listed(text: str) -> list[T]:
        try:
            return [parse(x.strip()) for x in text.split(",") if x.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of {what}") from None

    return listed


_floats = _listed(float, "numbers")
_ints = _listed(int, "whole numbers")
_names = _listed(str, "names")


def _finite_positive(x: float) -> bool:
    return math.isfinite(x) and x > 0


# What each count, size and list of `aesplat bench` must hold: option -> (the test of one value, what a value
# must be). A list is tested value by value, and must hold at least one value, each once.
RANGES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "--image-size": (lambda n: n >= 1, "1 or more pixels"),
    "--scenes": (lambda n: n >= 1, "1 or more"),
    "--repeats": (lambda n: n >= 1, "1 or more"),
    "--round-scenes": (lambda n: n >= 1, "1 or more"),
    "--warmup": (lambda n: n >= 0, "0 or more"),
    "--process-warmup": (lambda n: n >= 0, "0 or more"),
    "--context-views": (lambda n: n >= 2, "a count of 2 or more"),
    "--data-context-views": (lambda n: n >= 2, "2 or more"),
    "--knobs": (lambda k: k in KNOB_TITLES, f"one of {', '.join(KNOB_TITLES)}"),
    "--input-scales": (_finite_positive, "a finite number more than 0"),
    "--render-scales": (_finite_positive, "a finite number more than 0"),
    "--keep-fractions": (lambda f: 0 < f <= 1, "a fraction in (0, 1]"),
    "--min-opacities": (lambda o: 0 <= o < 1, "an opacity in [0, 1)"),
    "--precisions": (lambda p: p in PRECISIONS, f"one of {', '.join(PRECISIONS)}"),
    "--backends": (lambda b: b in BACKENDS, f"one of {', '.join(BACKENDS)}"),
    "--tile-sizes": (lambda t: float(t).is_integer() and t >= 1, "a whole number of pixels, 1 or more"),
    "--threads": (lambda n: n >= 1, "1 or more"),
}


def check_arguments(args: argparse.Namespace) -> None:
    """A UserError naming the first option of ``RANGES`` whose value is outside its range, the value given and
    what it must be; nothing when every value is in range (an option left unset is not checked)."""

    def shown(value: Any) -> str:
        return f"{value:g}" if isinstance(value, float) else str(value)

    for flag, (ok, what) in RANGES.items():
        value = getattr(args, flag.removeprefix("--").replace("-", "_"))
        if value is None:
            continue
        if not isinstance(value, list):
            if not ok(value):
                raise UserError(f"{flag} {shown(value)}: it must be {what}")
            continue
        given = shlex.quote(",".join(shown(v) for v in value))
        if not value:
            raise UserError(f"{flag} {given}: it must list one or more values, each {what}")
        if not all(ok(v) for v in value):
            raise UserError(f"{flag} {given}: each must be {what}")
        repeated = [v for i, v in enumerate(value) if v in value[:i]]
        if repeated:
            raise UserError(f"{flag} {given}: it gives {shown(repeated[0])} twice")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="aesplat bench",
        description="Accuracy versus time: sweep every quality knob of a trained model on evaluation scenes "
        "and write tables (markdown, CSV) and a plot of PSNR/SSIM against milliseconds.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--ckpt", required=True, help="checkpoint written by `aesplat fit`")
    parser.add_argument("--out", default=None, help="output directory (default: RUN_DIR/bench next to the "
                        "checkpoint's run, else outputs/bench)")  # fmt: skip
    parser.add_argument("--data-root", default=None, help="shard folder with test/*.tar (default: the run's "
                        "data.root from its config.yaml)")  # fmt: skip
    parser.add_argument("--image-size", type=int, default=None, help="evaluation image side (default: the "
                        "run's data.image_size)")  # fmt: skip
    parser.add_argument("--scenes", type=int, default=8, help="evaluation scenes measured")
    parser.add_argument("--repeats", type=int, default=9, help="timing rounds: each times every setting once, "
                        "interleaved (the median and, from 6 rounds on, its 95 %% interval)")  # fmt: skip
    parser.add_argument("--round-scenes", type=int, default=2, help="scenes each round times every setting "
                        "on, the next ones in turn each round")  # fmt: skip
    parser.add_argument("--warmup", type=int, default=0, help="untimed runs of each setting before the rounds, "
                        "after the untimed first pass that measures its quality")  # fmt: skip
    parser.add_argument("--process-warmup", type=int, default=5,
                        help="untimed baseline passes before the first measurement")  # fmt: skip
    parser.add_argument("--context-views", type=_ints, default=[2, 3, 4, 6],
                        help="context-view counts fed to the model: each evaluation sample's k-view context, "
                        "the same targets (a count some scene carries no context of, or one the model cannot "
                        "take, is listed as not measured)")  # fmt: skip
    parser.add_argument("--data-context-views", type=int, default=None,
                        help="context views of every other knob's settings (default: the run's "
                        "data.num_context_views, the lower end of a range)")  # fmt: skip
    parser.add_argument("--knobs", type=_names, default=None,
                        help=f"comma-separated subset of {', '.join(KNOB_TITLES)} (default: all)")  # fmt: skip
    parser.add_argument("--input-scales", type=_floats, default=[0.5, 0.75, 1.0], help="model input sides as "
                        "fractions of the data's (rounded to multiples of 14)")  # fmt: skip
    parser.add_argument("--render-scales", type=_floats, default=[0.25, 0.5, 0.75, 1.0],
                        help="render sides as fractions of the data's")  # fmt: skip
    parser.add_argument("--keep-fractions", type=_floats, default=[1.0, 0.5, 0.25, 0.1],
                        help="fractions of the most opaque Gaussians kept")  # fmt: skip
    parser.add_argument("--min-opacities", type=_floats, default=[0.0, 0.05, 0.2, 0.5, 0.8],
                        help="opacity thresholds below which Gaussians are dropped")  # fmt: skip
    parser.add_argument("--precisions", type=_names, default=["fp32", "bf16"], help="model precisions")
    parser.add_argument("--backends", type=_names, default=None,
                        help="renderer backends (default: torch, plus gsplat when CUDA and gsplat are here; "
                        "the first is the baseline's)")  # fmt: skip
    parser.add_argument("--tile-sizes", type=_floats, default=[8, 16], help="renderer tile sides")
    parser.add_argument("--compile", action="store_true", help="also measure the torch backend with "
                        "torch.compile (cold compiles take minutes)")  # fmt: skip
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:1, ... (auto: cuda if available)")
    parser.add_argument("--threads", type=int, default=None,
                        help=f"torch CPU threads (default: ${ENV_OVERRIDE}, else the usable cores less those "
                        "other processes keep busy, watched for half a second at the start)")  # fmt: skip
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def evaluation_scenes(loaded, data_root: str | None, image_size: int | None, limit: int, device: torch.device,
                      context_views: int | None = None) -> list[BatchedExample]:  # fmt: skip
    """The first ``limit`` test scenes of the run's data set, one per example, on ``device``;
    ``context_views``: the count of context views (default: the run's; see ``evaluation_stream``)."""
    return single_scenes(evaluation_stream(loaded, data_root, image_size, context_views), limit, device)


def evaluation_stream(loaded, data_root: str | None, image_size: int | None, context_views: int | None = None):
    """The test stream of the run's data set (``aesplat.data.EvalStream``) with the k-view contexts of its
    evaluation samples for k = ``context_views`` (default: the run's ``data.num_context_views``, the lower
    end of a range), as ``aesplat test --data.num_context_views k`` reads them. A UserError when the shards
    carry no contexts of that count."""
    from ..data import DataModule

    data = dict(loaded.data or {})
    if data_root is not None:
        data["root"] = data_root
    if "root" not in data:
        why = loaded.config_problem or "there is no config.yaml beside the checkpoint's run"
        raise SystemExit(f"aesplat bench: the data set is not known ({why}); give --data-root DIR")
    if image_size is not None:
        data["image_size"] = image_size
    elif loaded.trained_size is not None:
        data["image_size"] = loaded.trained_size
    else:
        raise UserError(f"{loaded.path} does not say which image size it was trained at: give --image-size")
    if context_views is not None:
        data["num_context_views"] = context_views
    data.update(num_workers=0, eval_batch_size=1)
    known = set(inspect.signature(DataModule).parameters)
    datamodule = DataModule(**{k: v for k, v in data.items() if k in known})
    try:
        return datamodule.eval_dataset("test")
    except FileNotFoundError as err:
        raise SystemExit(f"aesplat bench: {err}") from err


def context_views_of(
    loaded,
    data_root: str | None,
    image_size: int | None,
    scenes: Sequence[BatchedExample],
    counts: Iterable[int],
    device: torch.device,
) -> dict[int, list[BatchedViews | None]]:
    """Per count k, the k-view context the evaluation sample of each of ``scenes`` carries (None where it
    carries none; every entry None when the shards were converted for fewer views)."""
    keys = [s.scene[0] for s in scenes]
    contexts = {}
    for k in sorted(set(counts) - {s.context.num_views for s in scenes}):
        try:
            stream = evaluation_stream(loaded, data_root, image_size, k)
        except UserError:
            contexts[k] = [None] * len(keys)
            continue
        contexts[k] = contexts_of(each_scene(stream, device), keys)
    return contexts


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``aesplat bench`` (see ``--help``)."""
    from ..checkpoint import load_checkpoint
    from ..render import RenderSettings, get_backend

    args = build_parser().parse_args(argv)
    check_arguments(args)  # before anything is read or written
    # The scenes are read in this process. Cores other processes keep busy are left to them: a parallel region
    # whose threads wait for a core times the other work, not the setting.
    allocator = steady_allocator()  # before the model and the scenes take their memory
    busy_at_start = other_cores_busy() if args.threads is None else None
    apply_thread_policy(num_workers=0, override=args.threads, busy_cores=busy_at_start or 0.0)
    device = resolve_device(args.device)
    loaded = load_checkpoint(args.ckpt, device)  # a UserError is one line (aesplat.cli reports it)
    scenes = evaluation_scenes(loaded, args.data_root, args.image_size, args.scenes, device,
                               args.data_context_views)  # fmt: skip
    if not scenes:
        raise SystemExit("aesplat bench: the test split holds no scenes")
    contexts = {}
    if args.knobs is None or "context_views" in args.knobs:
        contexts = context_views_of(loaded, args.data_root, args.image_size, scenes, args.context_views, device)
    native = scenes[0].target.images.shape[-1]
    # The scenes' tensors are float32 on `device`: "auto" picks what a render of them would use.
    auto = get_backend("auto", device)[0]
    backends = args.backends or (["gsplat", "torch"] if auto == "gsplat" else ["torch"])
    render_kwargs = loaded.render_options(device)
    render_kwargs.pop("compile", None)  # compiling is a knob of its own here
    baseline, points = default_sweep(
        loaded.sh_degree, native, patch=loaded.patch_size, context_views=args.context_views,
        base_context_views=scenes[0].context.num_views, backends=backends, input_scales=args.input_scales,
        render_scales=args.render_scales, keep_fractions=args.keep_fractions, min_opacities=args.min_opacities,
        precisions=args.precisions, tile_sizes=[int(t) for t in args.tile_sizes],
        base_tile_size=render_kwargs.get("tile_size", RenderSettings.tile_size), compiled=args.compile,
        knobs=args.knobs,
    )  # fmt: skip
    bench = Bench(loaded.model, scenes, device, repeats=args.repeats, round_scenes=args.round_scenes,
                  warmup=args.warmup,
                  render_kwargs=render_kwargs, progress=not args.no_progress,
                  cameras=loaded.cameras, contexts=contexts)  # fmt: skip
    watch = LoadWatch()
    try:
        rows = bench.run(points, baseline, warmup_runs=args.process_warmup)
    except ValueError as err:  # the baseline itself cannot run here
        raise UserError(str(err)) from err
    load = watch.stop()
    if args.out is not None:
        out = Path(args.out)
    elif loaded.data is not None:
        out = loaded.path.parent.parent / "bench"
    else:
        out = Path("outputs/bench")
    meta = {
        **machine_meta(device), "ckpt": str(loaded.path), "scenes": len(scenes), "native_size": native,
        "context_views": scenes[0].context.num_views,
        "view_aggregation": loaded.net.get("view_aggregation", "concat"),
        "repeats": args.repeats, "round_scenes": bench.round_scenes, "warmup": args.warmup,
        "process_warmup": args.process_warmup,
        "sh_degree": loaded.sh_degree,
        "model_size": loaded.net.get("size"), "appearance": loaded.net.get("appearance"),
        "cameras": loaded.cameras, "load": {**load, "other_cores_at_start": busy_at_start},
        "allocator": allocator,
    }  # fmt: skip
    meta["warning"] = busy_warning(load, meta["threads"])
    paths = write_report(rows, out, meta)
    print(paths["BENCH.md"].read_text())
    if meta["warning"]:
        print(meta["warning"], file=sys.stderr)
    print(f"aesplat bench: wrote {', '.join(str(p) for p in paths.values())}")
    return 0
