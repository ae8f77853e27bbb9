#!/usr/bin/env python
"""Open a prediction's exports in an independent web 3DGS viewer and compare its picture with predict's own.

    aesplat predict --ckpt CKPT --out PRED --export splat IMAGE IMAGE
    python scripts/splat_viewer_check.py --pred PRED      # -> PRED/splat-viewer-check/

Loads ``gaussians.splat`` and ``gaussians.ply`` of the prediction folder, one at a time, into GaussianSplats3D
(npm ``@mkkellogg/gaussian-splats-3d``, on ``three``) in headless Chromium, renders input camera 0 there (its
pose, intrinsics, image size, background and 2D filter as ``cameras.json`` records them) and compares each
picture with ``renders/00_*.png`` (predict's render, every SH band) and with this project's render of the PLY
at SH degree 0 (what the viewer shows: ``.splat`` holds no SH, and the viewer is set to degree 0), and
scores each picture and predict's render against camera 0's photo as the model saw it (``inputs/00_*.png``).
Writes into --out (default PRED/splat-viewer-check), whole or not at all:

    splat.png, ply.png        the viewer's pictures of camera 0 (the render's size, one canvas pixel each)
    sh0.png                   this project's render of the PLY at SH degree 0
    predict.png               predict's render of camera 0 (a copy of renders/00_*.png)
    splat_viewer_check.json   PSNR (dB) of each picture against both renders and the photo, the Gaussians
                              each file holds and the viewer loaded, image size, package versions, date and
                              commit

The viewer draws at the render's own size, one canvas pixel per pixel: both renderers then evaluate every
Gaussian at the same pixel centres with the same 2D low-pass (eps2d px^2). A supersampled canvas, its low-pass
scaled to match and averaged down, would agree a little better on Gaussians of a pixel or more, but would hide
the viewer's size floor, which a user meets at any size: it skips a Gaussian whose low-passed footprint is
round and under 0.316 px^2 (sigma under 0.13 px before a 0.3 low-pass); the JSON counts those in camera 0.
The viewer also drops Gaussians whose 8-bit opacity is 0, so it may load fewer than a file holds.

Needs Node.js's ``npm`` (the pinned packages are installed once into --cache, default outputs/splat-viewer),
Debian's chromium (scripts/install_chromium.sh) and the ``websockets`` package (the viewer extra).
"""

from __future__ import annotations

import argparse
import functools
import http.server
import importlib.util
import io
import json
import shutil
import string
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from common import provenance  # noqa: E402  (benchmarks/common.py and a file beside this one, not packages)
from headless_chromium import Chromium, find_chromium  # noqa: E402

from aesplat.errors import UserError  # noqa: E402
from aesplat.export.prediction import PredictedScene, read_prediction  # noqa: E402
from aesplat.export.splat import SPLAT_DTYPE  # noqa: E402
from aesplat.files import check_output_dir, written_whole  # noqa: E402
from aesplat.images import to_uint8  # noqa: E402
from aesplat.render import render  # noqa: E402
from aesplat.render.projection import project_gaussians  # noqa: E402
from aesplat.train.metrics import psnr  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NAME = "splat_viewer_check"
PACKAGES = {"@mkkellogg/gaussian-splats-3d": "0.4.7", "three": "0.187.0"}
FILES = {"splat": "gaussians.splat", "ply": "gaussians.ply"}  # screenshot name -> file of the prediction

# The page: three.js's camera set to input camera 0, GaussianSplats3D drawing one file with no progressive
# loading, fade-in or orbit controls; ``window.splatCheck`` says when the sorted scene has been drawn.
PAGE = string.Template("""<!doctype html>
<html><head><meta charset="utf-8">
<style>html, body { margin: 0; overflow: hidden; background: $background; }
#view { position: absolute; left: 0; top: 0; width: ${width}px; height: ${height}px; }</style>
<script type="importmap">$importmap</script>
<script type="application/json" id="config">$config</script>
</head><body><div id="view"></div>
<script type="module">
import * as THREE from "three";
import * as GS from "@mkkellogg/gaussian-splats-3d";

const report = (fields) => { window.splatCheck = { ...window.splatCheck, ...fields }; };
addEventListener("error", (e) => report({ error: String(e.message) }));
addEventListener("unhandledrejection", (e) => report({ error: String(e.reason?.message || e.reason) }));
const consoleError = console.error;  // three.js reports a shader that does not compile here, and draws nothing
console.error = (...args) => { report({ error: args.map(String).join(" ") }); consoleError(...args); };

const c = JSON.parse(document.getElementById("config").textContent);
const [[fx, , cx], [, fy, cy]] = c.intrinsics;  // normalised: fx, cx / width; fy, cy / height
const fovY = 2 * Math.atan(0.5 / fy) * 180 / Math.PI;  // degrees; the viewer culls its splat tree with it
const camera = new THREE.PerspectiveCamera(fovY, c.width / c.height, c.near, c.far);
// OpenCV intrinsics as an OpenGL projection (any principal point, fx != fy); kept if anything recomputes it
camera.updateProjectionMatrix = function () {
  this.projectionMatrix.set(
    2 * fx, 0, 1 - 2 * cx, 0,
    0, 2 * fy, 2 * cy - 1, 0,
    0, 0, -(c.far + c.near) / (c.far - c.near), -2 * c.far * c.near / (c.far - c.near),
    0, 0, -1, 0);
  this.projectionMatrixInverse.copy(this.projectionMatrix).invert();
};
camera.updateProjectionMatrix();
// camera-to-world in OpenCV axes (x right, y down, z forward) -> three.js's camera (y up, looking down -z)
const flipYZ = new THREE.Matrix4().makeScale(1, -1, -1);
const pose = new THREE.Matrix4().set(...c.camera_to_world.flat()).multiply(flipYZ);
pose.decompose(camera.position, camera.quaternion, camera.scale);
camera.updateMatrixWorld(true);

const viewer = new GS.Viewer({
  ...c.viewer, rootElement: document.getElementById("view"), camera, useBuiltInControls: false,
  sceneRevealMode: GS.SceneRevealMode.Instant, renderMode: GS.RenderMode.Always, logLevel: GS.LogLevel.None,
});
await viewer.addSplatScene(c.file, { progressiveLoad: false, showLoadingUI: false });
viewer.start();
let frames = 0;  // frames drawn since the full sort finished
const settle = () => {
  frames = viewer.sortRunning || !viewer.splatRenderReady ? 0 : frames + 1;
  if (frames < 5) return requestAnimationFrame(settle);
  report({ done: true, loaded: viewer.splatMesh.getSplatCount(), drawn: viewer.splatRenderCount,
           cross_origin_isolated: self.crossOriginIsolated });  // drawn: in the sorted draw list
};
requestAnimationFrame(settle);
</script></body></html>
""")


# ---------------------------------------------------------------------------------------------------
# Inputs


def check_inputs(pred: Path) -> tuple[PredictedScene, Path]:
    """The prediction folder read back, and predict's render of camera 0; a folder that lacks something is one
    line naming it."""
    try:
        scene = read_prediction(pred)
    except UserError as err:
        raise SystemExit(f"{NAME}: {err}") from None
    if not (pred / FILES["splat"]).is_file():
        raise SystemExit(
            f"{NAME}: {pred} holds no {FILES['splat']}; predict with `--export splat`, or run "
            f"`aesplat export {pred} splat`"
        )
    reference = pred / "renders" / f"00_{scene.names[0]}.png"
    if not reference.is_file():
        raise SystemExit(f"{NAME}: {reference} (predict's render of camera 0) is missing; predict again")
    return scene, reference


def check_tools() -> None:
    if find_chromium() is None:
        raise SystemExit(f"{NAME}: Chromium is not installed; run scripts/install_chromium.sh (apt-get)")
    if importlib.util.find_spec("websockets") is None:
        raise SystemExit(f'{NAME}: the websockets package is missing; pip install -e ".[viewer]"')
    if shutil.which("npm") is None:
        raise SystemExit(f"{NAME}: npm is not installed; install Node.js (Debian: apt-get install npm)")


def installed_versions(cache: Path) -> dict[str, str | None]:
    versions = {}
    for name in PACKAGES:
        manifest = cache / "node_modules" / name / "package.json"
        versions[name] = json.loads(manifest.read_text())["version"] if manifest.is_file() else None
    return versions


def install_viewer(cache: Path) -> dict[str, str]:
    """The pinned viewer packages under ``cache/node_modules`` (``npm install`` when any is missing or of
    another version); returns their versions."""
    if installed_versions(cache) == PACKAGES:
        print(f"{NAME}: viewer packages in {cache}: {_versions_line()}", flush=True)
        return dict(PACKAGES)
    print(f"{NAME}: installing {_versions_line()} into {cache} (npm)", flush=True)
    cache.mkdir(parents=True, exist_ok=True)
    (cache / "package.json").write_text(json.dumps({"private": True, "dependencies": PACKAGES}, indent=2))
    npm = [shutil.which("npm"), "install", "--no-audit", "--no-fund", "--ignore-scripts", "--loglevel=error"]
    proc = subprocess.run(npm, cwd=cache, capture_output=True, text=True)
    if proc.returncode != 0 or installed_versions(cache) != PACKAGES:
        lines = [line.removeprefix("npm error").strip() for line in proc.stderr.splitlines()]
        routine = ("code ", "syscall ", "errno ", "at ", "A complete log", "Log files")
        reason = next(
            (line for line in lines if line and not line.startswith(routine)), "no packages installed"
        )
        raise SystemExit(
            f"{NAME}: npm install in {cache} failed ({reason}); check the network and npm's registry"
        )
    return dict(PACKAGES)


def _versions_line() -> str:
    return ", ".join(f"{name} {version}" for name, version in PACKAGES.items())


# ---------------------------------------------------------------------------------------------------
# This project's renders and the comparison


def sh0_render(scene: PredictedScene) -> np.ndarray:
    """This project's render of input camera 0 from the PLY at SH degree 0, uint8 [H, W, 3]."""
    options = {k: v for k, v in scene.render_options.items() if k != "compile"}
    with torch.no_grad():
        out = render(scene.gaussians, scene.extrinsics[None, :1], scene.intrinsics[None, :1], scene.height,
                     scene.width, background=scene.background, sh_degree=0, **options)  # fmt: skip
    return to_uint8(out.color[0, 0])


def psnr_db(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB of two uint8 images [H, W, 3] (inf when equal)."""
    as_tensor = lambda a: torch.tensor(a).permute(2, 0, 1)[None].float() / 255  # noqa: E731
    return round(float(psnr(as_tensor(image), as_tensor(reference))[0]), 2)


def below_viewer_size_floor(scene: PredictedScene) -> tuple[int, int]:
    """(Gaussians this project's renderer draws in camera 0, how many of them GaussianSplats3D leaves out).

    The viewer takes the smaller eigenvalue of the low-passed 2D covariance as trace/2 - sqrt(max(0.1,
    (a - c)^2 / 4 + b^2)) and skips the Gaussian where it is not positive: a round footprint of variance under
    0.316 px^2 with the low-pass (sigma under 0.13 px before it, with eps2d 0.3) is not drawn at all.
    """
    options = scene.render_options
    with torch.no_grad():
        projected, _ = project_gaussians(
            scene.gaussians, scene.extrinsics[None, :1], scene.intrinsics[None, :1], scene.height, scene.width,
            sh_degree=0, near=options.get("near", 0.01), far=options.get("far", 1e10),
            eps2d=options.get("eps2d", 0.3), antialiased=options.get("rasterize_mode") == "antialiased",
        )  # fmt: skip
    a, b, c = projected.conics.unbind(-1)  # the inverse of the low-passed 2D covariance
    det = a * c - b * b
    var_x, cov_xy, var_y = c / det, -b / det, a / det
    smaller = (var_x + var_y) / 2 - torch.sqrt(((var_x - var_y) ** 2 / 4 + cov_xy**2).clamp_min(0.1))
    return projected.gaussian.numel(), int((smaller <= 0).sum())


def alpha_zero_count(path: Path, scene: PredictedScene) -> int:
    """Gaussians of ``path`` whose 8-bit opacity, as the viewer reads it, is 0 (the viewer drops them)."""
    if path.suffix == ".splat":
        return int((np.fromfile(path, dtype=SPLAT_DTYPE)["rgba"][:, 3] == 0).sum())
    return int((scene.gaussians.opacities[0] * 255).floor().eq(0).sum())  # the PLY reader floors


# ---------------------------------------------------------------------------------------------------
# The page, its server and the browser


def viewer_settings(scene: PredictedScene) -> dict:
    """GaussianSplats3D's ``Viewer`` options that make it draw as predict's renders did: the same 2D low-pass
    (classic: it widens a Gaussian; antialiased: it also scales its opacity, as the viewer's ``antialiased``),
    SH degree 0, one canvas pixel per CSS pixel, no shared memory (no cross-origin isolation needed) and
    sorting by float depth (its integer sort rounds positions to 1/1000 of a scene unit)."""
    eps2d = float(scene.render_options.get("eps2d", 0.3))
    return {
        "antialiased": scene.render_options.get("rasterize_mode", "classic") == "antialiased",
        # written into the shader as JavaScript prints it: a whole number would be a GLSL int and not compile
        "kernel2DSize": eps2d + 1e-7 if eps2d.is_integer() else eps2d,
        "sphericalHarmonicsDegree": 0,
        "ignoreDevicePixelRatio": True,
        "sharedMemoryForWorkers": False,
        "gpuAcceleratedSort": False,
        "integerBasedSort": False,
        "halfPrecisionCovariancesOnGPU": False,
        "inMemoryCompressionLevel": 0,
        "dynamicScene": False,
    }


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".js": "text/javascript",
                      ".ply": "application/octet-stream", ".splat": "application/octet-stream"}  # fmt: skip

    def log_message(self, *args) -> None:
        pass


def serve(folder: Path) -> http.server.ThreadingHTTPServer:
    """An HTTP server of ``folder`` on 127.0.0.1 (a free port), running in a daemon thread."""
    handler = functools.partial(_QuietHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def write_page(site: Path, scene: PredictedScene, file: str) -> str:
    """The page that draws ``/scene/<file>`` from camera 0 into ``site``; returns its path on the server."""
    config = {
        "file": f"/scene/{file}",
        "width": scene.width,
        "height": scene.height,
        "camera_to_world": scene.extrinsics[0].tolist(),
        "intrinsics": scene.intrinsics[0].tolist(),
        "near": float(scene.render_options.get("near", 0.01)),
        "far": float(scene.render_options.get("far", 1e10)),
        "viewer": viewer_settings(scene),
    }
    builds = {
        "three": "build/three.module.js",
        "@mkkellogg/gaussian-splats-3d": "build/gaussian-splats-3d.module.js",
    }
    importmap = {"imports": {name: f"/node_modules/{name}/{path}" for name, path in builds.items()}}
    r, g, b = (round(255 * float(v)) for v in scene.background.clamp(0, 1))
    page = PAGE.substitute(background=f"rgb({r}, {g}, {b})", width=scene.width, height=scene.height,
                       importmap=json.dumps(importmap), config=json.dumps(config))  # fmt: skip
    name = f"{Path(file).suffix[1:]}.html"
    (site / name).write_text(page)
    return name


def viewer_picture(
    browser: Chromium, url: str, width: int, height: int, timeout: float
) -> tuple[np.ndarray, dict]:
    """Open ``url``, wait until the page has drawn its sorted scene, and return the canvas's pixels
    uint8 [height, width, 3] with the page's report (Gaussians loaded and drawn)."""
    browser.open(url)
    deadline = time.monotonic() + timeout
    while not (state := browser.evaluate("window.splatCheck") or {}).get("done") or state.get("error"):
        if state.get("error"):
            lines = state["error"].splitlines()
            detail = next((line.strip() for line in lines if line.strip().startswith("ERROR")), "")
            raise SystemExit(f"{NAME}: the viewer failed on {url}: {lines[0]} {detail}".rstrip())
        if time.monotonic() > deadline:
            raise SystemExit(f"{NAME}: the viewer drew nothing within {timeout:.0f} s on {url}")
        time.sleep(0.2)
    shot = Image.open(io.BytesIO(browser.screenshot())).convert("RGB")
    return np.asarray(shot)[:height, :width].copy(), state


def viewer_pictures(
    scene: PredictedScene, pred: Path, cache: Path, timeout: float
) -> tuple[str, dict[str, tuple[np.ndarray, dict]]]:
    """Serve the page, the viewer's packages and the two files of ``pred``; draw each file in Chromium.
    Returns the browser's version and, per key of ``FILES``, the picture and the page's report."""
    shown = {}
    with tempfile.TemporaryDirectory(prefix="splat-viewer-check-") as tmp:
        site = Path(tmp)
        (site / "node_modules").symlink_to(cache.resolve() / "node_modules")
        (site / "scene").mkdir()
        for file in FILES.values():
            (site / "scene" / file).symlink_to((pred / file).resolve())
        server = serve(site)
        try:
            size = (max(scene.width, 256), max(scene.height, 256))  # a window smaller than that may be refused
            with Chromium(width=size[0], height=size[1]) as browser:
                chromium = browser.call("Browser.getVersion").get("product")
                print(f"{NAME}: {chromium} started, serving on port {server.server_port}", flush=True)
                for key, file in FILES.items():
                    started = time.monotonic()
                    url = f"http://127.0.0.1:{server.server_port}/{write_page(site, scene, file)}"
                    shown[key] = viewer_picture(browser, url, scene.width, scene.height, timeout)
                    print(f"{NAME}: drew {file} ({time.monotonic() - started:.1f} s)", flush=True)
        finally:
            server.shutdown()
            server.server_close()
    return chromium, shown


# ---------------------------------------------------------------------------------------------------
# Command line


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pred", type=Path, required=True, help="a folder of `aesplat predict --export splat`")
    parser.add_argument("--out", type=Path, default=None, help="default: PRED/splat-viewer-check")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --out as a whole")
    parser.add_argument("--cache", type=Path, default=ROOT / "outputs" / "splat-viewer",
                        help="where npm installs the viewer's packages (node_modules/)")  # fmt: skip
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for each picture")
    args = parser.parse_args(argv)
    out = args.out or args.pred / "splat-viewer-check"
    started = time.monotonic()

    scene, reference_path = check_inputs(args.pred)
    check_tools()
    try:
        check_output_dir(out, args.overwrite, [("--pred", args.pred)])
    except UserError as err:
        raise SystemExit(f"{NAME}: {err}") from None
    versions = install_viewer(args.cache)

    predict_render = np.asarray(Image.open(reference_path).convert("RGB"))
    if predict_render.shape != (scene.height, scene.width, 3):
        raise SystemExit(f"{NAME}: {reference_path} is not {scene.width}x{scene.height} as cameras.json says")
    sh0 = sh0_render(scene)
    # camera 0's photo as the model saw it (inputs/): what both pictures are scored against as well
    photo_path = args.pred / "inputs" / f"00_{scene.names[0]}.png"
    photo = np.asarray(Image.open(photo_path).convert("RGB")) if photo_path.is_file() else None
    if photo is not None and photo.shape != predict_render.shape:
        photo = None
    drawn, too_small = below_viewer_size_floor(scene)
    print(f"{NAME}: rendered camera 0 ({scene.width}x{scene.height}) at SH degree 0 with aesplat", flush=True)
    if too_small:
        print(f"{NAME}: {too_small:,} of the {drawn:,} Gaussians aesplat draws in camera 0 are under the "
              "viewer's size floor (round, under 0.316 px^2 with the low-pass): it leaves them out",
              flush=True)  # fmt: skip

    chromium, shown = viewer_pictures(scene, args.pred, args.cache, args.timeout)
    files = {}
    for key, file in FILES.items():
        picture, state = shown[key]
        held = scene.gaussians.num_gaussians if key == "ply" else (args.pred / file).stat().st_size // 32
        files[key] = {
            "file": file,
            "gaussians_in_file": held,
            "gaussians_loaded": state["loaded"],
            "gaussians_in_draw_list": state["drawn"],
            "opacity_8bit_zero_in_file": alpha_zero_count(args.pred / file, scene),
            "psnr_db": {
                "vs_predict_render": psnr_db(picture, predict_render),
                "vs_sh0_render": psnr_db(picture, sh0),
                "vs_input_photo": None if photo is None else psnr_db(picture, photo),
            },
            "screenshot": f"{key}.png",
        }
        print(f"{NAME}: {file}: {state['loaded']:,} of {held:,} Gaussians loaded; PSNR "
              f"{files[key]['psnr_db']['vs_predict_render']:.2f} dB vs predict's render, "
              f"{files[key]['psnr_db']['vs_sh0_render']:.2f} dB vs the SH-0 render", flush=True)  # fmt: skip

    options = scene.render_options
    record = {
        **provenance(),
        "command": "python scripts/splat_viewer_check.py "
        + " ".join(argv if argv is not None else sys.argv[1:]),
        "prediction": str(args.pred),
        "packages": versions,
        "chromium": chromium,
        "cross_origin_isolated": shown["splat"][1]["cross_origin_isolated"],
        "image_size": [scene.width, scene.height],
        "canvas_scale": 1,
        "camera": 0,
        "background": scene.background.tolist(),
        "render_options": {k: options.get(k) for k in ("rasterize_mode", "eps2d", "near", "far")},
        "viewer_settings": viewer_settings(scene),
        "ply_sh_degree": scene.gaussians.sh_degree,
        "sh0_render_vs_predict_render_psnr_db": psnr_db(sh0, predict_render),
        # camera 0's input photo against predict's render: the viewer's pictures are scored against it too
        "predict_render_vs_input_photo_psnr_db": None if photo is None else psnr_db(predict_render, photo),
        "camera0_gaussians": {"drawn_by_aesplat": drawn, "below_viewer_size_floor": too_small},
        "files": files,
        "seconds": round(time.monotonic() - started, 1),
    }
    with written_whole(out, args.overwrite, "aesplat predict", "--out") as staging:
        staging.mkdir()
        for key, (picture, _) in shown.items():
            Image.fromarray(picture).save(staging / f"{key}.png")
        Image.fromarray(sh0).save(staging / "sh0.png")
        Image.fromarray(predict_render).save(staging / "predict.png")  # beside them, for the pages
        (staging / f"{NAME}.json").write_text(json.dumps(record, indent=2) + "\n")
    print(f"{NAME}: wrote {out / (NAME + '.json')}, splat.png, ply.png, sh0.png, predict.png "
          f"({record['seconds']:.0f} s)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
