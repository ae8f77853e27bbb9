"""``aesplat view`` in a real browser (headless Chromium), its command line, and its one-line refusals."""

import importlib.util
import io
import json
import select
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from urllib.parse import urlsplit

import numpy as np
import pytest
from PIL import Image

from aesplat.view.command import main as view_main
from tests.helpers import need
from tests.prediction_helpers import BLUE, RED, make_prediction
from tests.view.helpers import browser, need_viser, wait_for

pytestmark = pytest.mark.filterwarnings("ignore:LPIPS metric unavailable")


@pytest.fixture(scope="module")
def prediction(tmp_path_factory):
    return make_prediction(tmp_path_factory.mktemp("view"))[0]


def snapshot(folder) -> dict:
    return {p: p.stat().st_mtime_ns for p in folder.rglob("*")}


def free_port_closed(port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) != 0


# ----------------------------------------------------------------------------------------------- browser


def canvas_pixels(shot: bytes, page: "browser.Chromium") -> np.ndarray:
    """The screenshot's pixels [N, 3] that show the 3D canvas: not under the control panel or a notification."""
    image = np.asarray(Image.open(io.BytesIO(shot)).convert("RGB")).astype(int)
    keep = np.ones(image.shape[:2], bool)
    rects = page.evaluate(
        "JSON.stringify([...document.querySelectorAll('.mantine-Paper-root, .mantine-Notification-root')]"
        ".map(e => e.getBoundingClientRect()).map(r => [r.left, r.top, r.right, r.bottom]))"
    )
    for left, top, right, bottom in json.loads(rects):
        keep[max(0, int(top) - 2) : int(bottom) + 2, max(0, int(left) - 2) : int(right) + 2] = False
    keep[-80:, :80] = False  # the axes widget
    return image[keep], image, keep


def test_viewer_in_headless_chromium(prediction):
    need_viser()
    need(browser.find_chromium() is not None, "Chromium (apt-get install chromium)")
    from aesplat.images import to_uint8
    from aesplat.view.app import Viewer, ViewerOptions, framing_distance
    from aesplat.view.exact import render_viewpoint
    from aesplat.view.scene import scene_from_path

    before = snapshot(prediction)
    scene = scene_from_path(prediction)
    fast = Viewer(scene, ViewerOptions(port=0, show_cameras=False))
    exact = Viewer(scene, ViewerOptions(port=0, mode="exact", show_cameras=False))
    try:
        with browser.Chromium(width=1000, height=500) as page:  # the scene clear of the panel
            # fast mode: the browser draws the splats; the canvas shows the scene's two colours and no other
            page.open(fast.url)
            wait_for(lambda: fast.clients, 60, "the page to connect")

            def scene_drawn():
                pixels, _, _ = canvas_pixels(page.screenshot(), page)
                coloured = pixels[np.ptp(pixels, axis=1) > 40]  # not viser's white-grey background
                # the splats fade in: wait until both of the scene's colours show at full strength
                near = [np.abs(coloured - c).sum(1).min(initial=999) < 40 for c in (RED, BLUE)]
                return coloured if len(coloured) > 0.1 * len(pixels) and all(near) else None

            drawn = wait_for(scene_drawn, 60, "the splats to be drawn")
            # the first view looks along input camera 0, moved back to frame the Gaussians (at least half
            # their median depth, clear of camera 0's frustum); the novel-view path is hidden until asked for
            start = next(iter(fast.clients.values()))
            now, view0 = start.viewpoint(), start.views[0]
            assert abs(float(np.dot(now.wxyz, view0.wxyz))) > 1 - 1e-6
            c2w = view0.extrinsics().double()
            means = scene.gaussians.means[0].double()
            depth = float(((means - c2w[:3, 3]) @ c2w[:3, 2]).median())
            back = max(framing_distance(means, c2w, view0.fov, view0.aspect), 0.5 * depth)
            expected = (c2w[:3, 3] - back * c2w[:3, 2]).numpy()
            assert np.allclose(now.position, expected, atol=1e-4)
            assert start.path_nodes and not any(node.visible for node in start.path_nodes)
            red, green, blue = drawn.T
            assert (red > blue + 60).mean() > 0.2 and (blue > red + 60).mean() > 0.2  # both halves
            # red, blue, and their blends with each other and the background: green never leads
            assert (green <= np.minimum(red, blue) + 12).mean() > 0.98
            # what "Save screenshot" sends in the fast mode: the browser's own render of the view
            client = next(iter(fast.clients.values())).client
            shot = client.get_render(250, 500, transport_format="png", timeout=30)[..., :3].reshape(-1, 3)
            assert shot.shape == (250 * 500, 3) and (np.abs(shot.astype(int) - RED).sum(1) < 60).any()

            # exact mode: the server's render fills the canvas, the browser shows it pixel for pixel
            page.open(exact.url)
            session = wait_for(lambda: next(iter(exact.clients.values()), None), 60, "the page to connect")

            def exact_shown():  # a screenshot taken while one exact image stayed on the page
                wait_for(lambda: session.showing_exact, 60, "an exact render")
                renders = session.exact_renders
                time.sleep(1.0)  # decoded and drawn
                shot = page.screenshot()
                return shot if session.showing_exact and session.exact_renders == renders else None

            pixels, image, keep = canvas_pixels(wait_for(exact_shown, 120, "a steady exact image"), page)
            shown = np.asarray(Image.fromarray(session.last_exact).resize(image.shape[1::-1], Image.BILINEAR))
            diff = np.abs(image - shown.astype(int))[keep]
            assert np.median(diff) <= 3 and (diff.max(1) > 40).mean() < 0.02, (np.median(diff), diff.max())
            assert session.viewpoint().aspect == pytest.approx(1000 / 500, rel=0.02)

            # "Go to camera": the browser takes input camera 1's pose and field of view and reports it back;
            # the exact image of that view (2:1, square pixels) holds predict's render of camera 1 in its middle
            target = session.views[1]

            def at(view) -> bool:
                now = session.viewpoint()
                turned = abs(float(np.dot(now.wxyz, view.wxyz)))
                return np.allclose(now.position, view.position, atol=1e-5) and turned > 1 - 1e-9

            session.go_to(target)
            wait_for(lambda: at(target), 30, "the browser's camera at input camera 1")
            h = scene.cameras[1].height
            image = to_uint8(render_viewpoint(scene, session.viewpoint(), h, sh_degree=scene.sh_degree))
            assert image.shape == (h, 2 * h, 3)
            saved = np.asarray(Image.open(prediction / "renders" / f"01_{scene.cameras[1].name}.png"))
            assert np.abs(image[:, h // 2 : h // 2 + h].astype(int) - saved).max() <= 1
            # "Play path" ends at the path's last frame; "Save screenshot" sends the exact image
            session.play_path()
            wait_for(lambda: at(session.path[-1]), 30, "the browser's camera at the path's end")
            session.send_screenshot()
    finally:
        sessions = [*fast.clients.values(), *exact.clients.values()]
        ports = [fast.server.get_port(), exact.server.get_port()]
        fast.stop()
        exact.stop()
    # shut down cleanly: the render threads ended, the ports are closed, nothing was written
    assert all(not s._worker.is_alive() for s in sessions)
    assert all(free_port_closed(p) for p in ports)
    assert snapshot(prediction) == before


# ----------------------------------------------------------------------------------------------- command line


def test_command_prints_its_url_serves_and_stops_on_sigint(prediction):
    need_viser()
    proc = subprocess.Popen([sys.executable, "-m", "aesplat.cli", "view", str(prediction), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 60)
        line = proc.stdout.readline() if ready else ""
        assert line.startswith("aesplat view: http://127.0.0.1:"), line
        url = urlsplit(line.split()[2])  # http://127.0.0.1:PORT/KEY/: the page needs the key
        assert len(url.path.strip("/")) >= 32 and url.path.endswith("/")
        with urllib.request.urlopen(url.geturl(), timeout=10) as response:
            assert response.status == 200 and b"<html" in response.read().lower()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "aesplat view: stopped" in out
    assert free_port_closed(url.port)


def refusal(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exit_:
        view_main(argv)
    assert exit_.value.code not in (0, None)
    message = str(exit_.value.code)
    assert "\n" not in message.strip() and "Traceback" not in capsys.readouterr().err
    return message


def test_a_port_in_use_is_one_line(prediction, capsys):
    need_viser()
    before = snapshot(prediction)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        message = refusal([str(prediction), "--port", str(port)], capsys)
    assert (
        message
        == f"aesplat view: cannot listen on 127.0.0.1:{port} (Address already in use); give another --port"
    )
    assert snapshot(prediction) == before


def test_bad_inputs_are_one_line_and_write_nothing(tmp_path, capsys):
    need_viser()
    (tmp_path / "empty").mkdir()
    assert "holds no prediction (no cameras.json, gaussians.ply, inputs)" in refusal(
        [str(tmp_path / "empty")], capsys
    )
    other = tmp_path / "mesh.ply"
    other.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
                      b"property float y\nproperty float z\nend_header\n" + bytes(12))  # fmt: skip
    assert "is not a 3DGS PLY of the reference layout (no f_dc_0" in refusal([str(other)], capsys)
    assert "does not exist" in refusal([str(tmp_path / "nowhere")], capsys)
    assert "give one prediction folder" in refusal([], capsys)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["empty", "mesh.ply"]


def test_a_missing_viewer_extra_is_one_line(prediction, capsys, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "viser" else real(name, *a)
    )
    message = refusal([str(prediction)], capsys)
    assert message == 'aesplat view: the viewer extra is not installed: pip install -e ".[viewer]"'
