"""The picture of the "View and export" docs page: `aesplat view` on the demo's prediction in headless Chromium.

    make demo                           # outputs/demo: the trained checkpoint and the synthetic test scenes
    python scripts/view_screenshot.py   # -> docs/images/view.png (and outputs/view-demo/pred, with its exports)

Takes the context views of the first test scene of the evaluation index (as ``aesplat test`` does), predicts
from them with ``aesplat predict --export colmap,nerfstudio,splat``, serves the prediction with ``aesplat view``
in the exact mode (this project's rasterizer, view-dependent SH) and screenshots the page once the server's
render is shown. Needs the viewer extra and Debian's chromium (scripts/install_chromium.sh).
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import time
from pathlib import Path

from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from headless_chromium import Chromium  # noqa: E402  (a file beside this one, not a package)


def demo_views(demo: Path, out: Path) -> list[Path]:
    """The two context frames of the evaluation index's first test scene, as PNG files under ``out``."""
    from aesplat.data.chunks import jpeg_bytes, load_chunk

    index = json.loads((demo / "src" / "evaluation_index.json").read_text())
    key, entry = next((k, v) for k, v in index.items() if v)
    chunks = json.loads((demo / "src" / "test" / "index.json").read_text())
    scene = next(s for s in load_chunk(demo / "src" / "test" / chunks[key]) if s["key"] == key)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for frame in entry["context"]:
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--demo", type=Path, default=Path("outputs/demo"), help="the folder `make demo` wrote")
    parser.add_argument("--work", type=Path, default=Path("outputs/view-demo"), help="images and prediction")
    parser.add_argument("--out", type=Path, default=Path("docs/images/view.png"), help="the screenshot")
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    args = parser.parse_args(argv)

    from aesplat.predict import main as predict
    from aesplat.view import scene_from_path
    from aesplat.view.app import Viewer, ViewerOptions

    ckpt = args.demo / "run" / "checkpoints" / "last.ckpt"
    images = demo_views(args.demo, args.work / "images")
    pred = args.work / "pred"
    predict(["--ckpt", str(ckpt), "--out", str(pred), "--overwrite", "--export", "colmap,nerfstudio,splat",
             "--no-progress", *map(str, images)])  # fmt: skip
    viewer = Viewer(scene_from_path(pred), ViewerOptions(port=0, mode="exact", exact_height=args.height))
    try:
        with Chromium(width=args.width, height=args.height) as page:
            page.open(viewer.url)
            session = wait(lambda: next(iter(viewer.clients.values()), None), "the page to connect")
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
            time.sleep(2.0)  # the image decoded and drawn
            # the notice that WebGL runs in software (SwiftShader here) is not part of the viewer
            page.evaluate("document.querySelectorAll('.mantine-Notification-root').forEach(e => e.remove())")
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_bytes(page.screenshot())
    finally:
        viewer.stop()
    print(f"view_screenshot: wrote {args.out} ({args.width}x{args.height}) of {pred}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
