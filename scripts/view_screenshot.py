"""The pictures of the "View and export" docs page: `aesplat view` on the demo's prediction, headless Chromium.

    make demo                           # outputs/demo: the trained checkpoint and the synthetic test scenes
    python scripts/view_screenshot.py   # -> docs/images/view-*.png (and outputs/view-demo/pred-*, with exports)

Takes the first test scene of the evaluation index: its context pair, and for ``--views 4`` two more frames
evenly between them (as ``aesplat test --data.num_context_views 4`` does), predicts from them with ``aesplat
predict --export colmap,nerfstudio,splat`` into ``--work/pred-{N}views``, serves each prediction with ``aesplat
view`` at its defaults (the first view, the exact renders' height) and screenshots the page:

    view-fast.png      the fast mode (the browser draws the splats) at the viewer's first view
    view-exact.png     the exact mode (this project's rasterizer, view-dependent SH) at the same view
    view-oblique.png   the exact mode from above, right of and behind input camera 0

each for the 2-view prediction, and ``view-exact-4views.png`` for the 4-view one; ``view.json`` says when, at
which commit, on what machine and under what load. Needs the viewer extra and Debian's chromium
(scripts/install_chromium.sh).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import time
from pathlib import Path

from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import provenance, write_whole  # noqa: E402
from headless_chromium import Chromium  # noqa: E402  (a file beside this one, not a package)


def demo_views(demo: Path, out: Path, count: int = 2) -> list[Path]:
    """``count`` frames of the evaluation index's first test scene as PNG files under ``out``: its context pair
    (first and last) and ``count - 2`` frames evenly between them."""
    from aesplat.data.pixelsplat_chunks import jpeg_bytes, load_chunk

    index = json.loads((demo / "src" / "evaluation_index.json").read_text())
    key, entry = next((k, v) for k, v in index.items() if v)
    chunks = json.loads((demo / "src" / "test" / "index.json").read_text())
    scene = next(s for s in load_chunk(demo / "src" / "test" / chunks[key]) if s["key"] == key)
    first, last = entry["context"]
    frames = [first, *(round(first + (last - first) * i / (count - 1)) for i in range(1, count - 1)), last]
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for frame in frames:
        path = out / f"{key}_{frame:03d}.png"
        Image.open(io.BytesIO(jpeg_bytes(scene["images"][frame]))).convert("RGB").save(path)
        paths.append(path)
    return paths


def wait(condition, what: str, timeout: float = 120.0):
    deadline = time.monotonic() + timeout
    while not (value := condition()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {what} within {timeout:.0f} s")
        time.sleep(0.25)
    return value


def shoot(page: Chromium, path: Path) -> None:
    # the notice that WebGL runs in software (SwiftShader here) is not part of the viewer
    page.evaluate("document.querySelectorAll('.mantine-Notification-root').forEach(e => e.remove())")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(page.screenshot())
    print(f"view_screenshot: wrote {path}", flush=True)


def screenshots(pred: Path, out: Path, suffix: str, width: int, height: int, oblique: bool) -> None:
    """The fast and exact modes at the viewer's first view (and the oblique exact view) of one prediction."""
    from aesplat.view.scene import scene_from_path

    scene = scene_from_path(pred)
    for mode in ("fast", "exact") if suffix == "" else ("exact",):
        screenshot_mode(scene, mode, out, suffix, width, height, oblique)


def screenshot_mode(scene, mode: str, out: Path, suffix: str, width: int, height: int, oblique: bool) -> None:
    from aesplat.view.app import Viewer, ViewerOptions

    viewer = Viewer(scene, ViewerOptions(port=0, mode=mode))  # every other option at its default
    try:
        with Chromium(width=width, height=height) as page:
            page.open(viewer.url)
            session = wait(lambda: next(iter(viewer.clients.values()), None), "the page to connect")
            if mode == "fast":
                time.sleep(5.0)  # the splats sorted, faded in and drawn
                shoot(page, out / "view-fast.png")
                return
            wait(lambda: session.showing_exact and session.exact_renders > 0, "the exact render")
            time.sleep(2.0)  # the image decoded and drawn
            shoot(page, out / f"view-exact{suffix}.png")
            if not oblique:
                return
            # an oblique view: above, right of and behind input camera 0, at the scene's median depth
            means = session.scene.gaussians.means[0]
            target = means.median(dim=0).values.double().numpy()
            depth = float(target[2])
            rendered = session.exact_renders
            with session.client.atomic():
                session.client.camera.up_direction = (0.0, -1.0, 0.0)
                session.client.camera.position = (0.9 * depth, -0.7 * depth, -0.6 * depth)
                session.client.camera.look_at = target
            wait(lambda: session.exact_renders > rendered and session.showing_exact, "the exact render")
            time.sleep(2.0)
            shoot(page, out / "view-oblique.png")
    finally:
        viewer.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--demo", type=Path, default=Path("outputs/demo"), help="the folder `make demo` wrote")
    parser.add_argument("--work", type=Path, default=Path("outputs/view-demo"), help="images and predictions")
    parser.add_argument("--out", type=Path, default=Path("docs/images"), help="where the screenshots go")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    args = parser.parse_args(argv)

    from aesplat.predict import main as predict

    load_start = list(os.getloadavg())
    ckpt = args.demo / "run" / "checkpoints" / "last.ckpt"
    for count in (2, 4):
        images = demo_views(args.demo, args.work / f"images-{count}views", count)
        pred = args.work / f"pred-{count}views"
        predict(["--ckpt", str(ckpt), "--out", str(pred), "--overwrite", "--export", "colmap,nerfstudio,splat",
                 "--no-progress", *map(str, images)])  # fmt: skip
        screenshots(pred, args.out, "" if count == 2 else f"-{count}views", args.width, args.height, count == 2)
    predictions = [str(args.work / f"pred-{n}views") for n in (2, 4)]
    record = {**provenance(load_start), "checkpoint": str(ckpt), "predictions": predictions,
              "window": [args.width, args.height]}  # fmt: skip
    write_whole(args.out / "view.json", (json.dumps(record, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
