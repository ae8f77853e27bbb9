"""Who may use a running ``aesplat view``, and what a client can make it render.

The page and its websocket need the key in the URL the viewer prints, and a websocket must come from the
viewer's own page (its ``Origin`` names the address the request went to): a Python client with another
``Origin``, one without the key, and a page from another port on this machine (in headless Chromium) get an
HTTP 403 and no scene. The sizes a client reports are capped before the server renders them.
"""

import http.server
import json
import socket
import struct
import threading
import urllib.error
import urllib.request
from types import SimpleNamespace
from unittest.mock import MagicMock
from urllib.parse import urlsplit

import numpy as np
import pytest
import torch

from aesplat.errors import UserError
from tests.helpers import need
from tests.prediction_helpers import make_prediction
from tests.view.helpers import browser, need_viser, wait_for

pytestmark = pytest.mark.filterwarnings("ignore:LPIPS metric unavailable")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    need_viser()
    from aesplat.view.scene import scene_from_path

    return scene_from_path(make_prediction(tmp_path_factory.mktemp("view"))[0])


def start(scene, **options):
    from aesplat.view.app import Viewer, ViewerOptions

    return Viewer(scene, ViewerOptions(port=0, show_cameras=False, **options))


@pytest.fixture
def viewer(scene):
    running = start(scene)
    yield running
    running.stop()


def origin_of(viewer) -> str:
    """The viewer's own origin as a browser names it: the scheme, host and port of its page."""
    return f"http://127.0.0.1:{viewer.server.get_port()}"


def socket_url(viewer) -> str:
    """The websocket address the viewer's page connects to: its URL as ws://, without the trailing slash."""
    return viewer.url.replace("http://", "ws://", 1).rstrip("/")


def connect(url: str, origin: str | None):
    import viser
    from websockets.sync.client import connect as ws_connect

    return ws_connect(url, origin=origin, subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10,
                      max_size=None)  # fmt: skip


def look(ws) -> None:
    """Send what a browser sends first, its camera: viser then counts the client as connected and the viewer
    sends it the scene."""
    import msgspec
    from viser import _messages

    camera = _messages.ViewerCameraMessage(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -1.0), fov=1.0,
                                           near=0.01, far=100.0, image_height=100, image_width=100,
                                           look_at=(0.0, 0.0, 0.0), up_direction=(0.0, -1.0, 0.0))  # fmt: skip
    ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))


def message_types(frame: bytes) -> list[str]:
    """The types of the messages in one frame viser sends: a zstd-compressed msgpack window of messages after
    two little-endian uint64 sizes (unpacked, packed), then the raw arrays."""
    import msgspec
    import zstandard

    size, packed = struct.unpack_from("<QQ", frame)
    window = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(frame[16 : 16 + packed], size))
    return [message["type"] for message in window["messages"]]


def receive_gaussians(ws) -> None:
    """Wait for the Gaussians (viser's splats message); TimeoutError if the socket stays quiet 30 s first."""
    while "GaussianSplatsMessage" not in message_types(ws.recv(timeout=30)):
        pass


def refused(url: str, origin: str | None) -> int:
    """The HTTP status that refuses a websocket handshake (the test fails if the connection opens instead)."""
    from websockets.exceptions import InvalidStatus

    with pytest.raises(InvalidStatus) as err, connect(url, origin) as ws:
        look(ws)
        receive_gaussians(ws)
    return err.value.response.status_code


def page_status(url: str) -> int:
    try:
        with urllib.request.urlopen(url, timeout=10) as response:
            return response.status
    except urllib.error.HTTPError as err:
        return err.code


# ----------------------------------------------------------------------------------------------- who connects


def test_the_printed_url_from_its_own_origin_gets_the_page_and_the_scene(viewer):
    with urllib.request.urlopen(viewer.url, timeout=10) as response:
        assert response.status == 200 and b"<html" in response.read().lower()
    with connect(socket_url(viewer), origin_of(viewer)) as ws:
        look(ws)
        receive_gaussians(ws)
        wait_for(lambda: len(viewer.clients) == 1, 30, "the client's session")


@pytest.mark.parametrize(
    "origin",
    [
        "https://evil.example",
        "http://127.0.0.1:1",  # another port of this machine
        "http://localhost.evil.example",
        "null",  # a sandboxed frame or a file:// page
        "http://[::1",  # not a URL
        None,  # no Origin at all
    ],
)
def test_a_websocket_from_another_origin_is_refused(viewer, origin):
    assert refused(socket_url(viewer), origin) == 403
    assert not viewer.clients


@pytest.mark.parametrize("path", ["", "/not-the-key", "/not-the-key/"])
def test_the_websocket_and_the_page_without_the_key_are_refused(viewer, path):
    port = viewer.server.get_port()
    assert refused(f"ws://127.0.0.1:{port}{path}", origin_of(viewer)) == 403
    assert page_status(f"http://127.0.0.1:{port}{path}") == 403
    assert not viewer.clients


def test_each_start_has_its_own_key_and_the_url_holds_it(scene, viewer):
    other = start(scene)
    try:
        urls = [urlsplit(v.url) for v in (viewer, other)]
    finally:
        other.stop()
    keys = [url.path.strip("/") for url in urls]
    assert keys[0] != keys[1] and all(len(key) >= 32 for key in keys)
    assert [url.path for url in urls] == [f"/{key}/" for key in keys]


def test_host_0000_prints_the_machines_name_and_still_needs_the_key(scene):
    shared = start(scene, host="0.0.0.0")
    try:
        port = shared.server.get_port()
        url = urlsplit(shared.url)
        assert (url.hostname, url.port) == (socket.gethostname().lower(), port)
        assert page_status(f"http://127.0.0.1:{port}/") == 403
        assert refused(f"ws://127.0.0.1:{port}", f"http://127.0.0.1:{port}") == 403
        assert refused(f"ws://127.0.0.1:{port}{url.path.rstrip('/')}", "https://evil.example") == 403
        with connect(f"ws://127.0.0.1:{port}{url.path.rstrip('/')}", f"http://127.0.0.1:{port}") as ws:
            look(ws)
            receive_gaussians(ws)
    finally:
        shared.stop()


def test_the_viewer_refuses_to_start_unguarded(scene, monkeypatch):
    """Should viser start its server some other way, the viewer stops it rather than serve without a check."""
    from aesplat.view import app

    monkeypatch.setattr(app, "guarding_handshakes", lambda gate: app.contextlib.nullcontext())
    with pytest.raises(UserError, match="cannot guard"):
        start(scene)


class OtherSite:
    """A page served from another port of this machine that opens websockets to the given addresses and
    records, per address, whether it opened, how many messages came, and its close code."""

    def __init__(self, targets: list[str], protocol: str) -> None:
        script = (
            f"window.report = {json.dumps(targets)}.map((url) => {{"
            "const r = {url: url, opened: false, messages: 0, closed: null};"
            f"const ws = new WebSocket(url, [{json.dumps(protocol)}]); ws.binaryType = 'arraybuffer';"
            "ws.onopen = () => { r.opened = true; }; ws.onmessage = () => { r.messages += 1; };"
            "ws.onclose = (e) => { r.closed = e.code; }; return r; });"
        )
        body = f"<!doctype html><html><body><script>{script}</script></body></html>".encode()

        class Page(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def test_a_page_from_another_port_gets_nothing_in_chromium(viewer):
    need(browser.find_chromium() is not None, "Chromium (apt-get install chromium)")
    import viser

    port = viewer.server.get_port()
    # the viewer's own websocket address (key included: the Origin alone refuses it), and the bare port
    targets = [socket_url(viewer), f"ws://127.0.0.1:{port}"]
    other = OtherSite(targets, f"viser-v{viser.__version__}")
    try:
        with browser.Chromium(width=400, height=300) as page:
            page.open(other.url)

            def settled():  # every socket closed, or one got a message
                sockets = json.loads(page.evaluate("JSON.stringify(window.report || [])") or "[]")
                done = len(sockets) == len(targets)
                done = done and all(s["closed"] is not None or s["messages"] for s in sockets)
                return sockets if done else None

            report = wait_for(settled, 60, "the other page's websockets to settle")
    finally:
        other.close()
    assert all(not s["opened"] and s["messages"] == 0 for s in report), report
    assert not viewer.clients


# ----------------------------------------------------------------------------------------------- render caps


class Camera(SimpleNamespace):
    """A browser's camera as viser reports it: its pose, field of view and canvas size in pixels."""

    @property
    def aspect(self) -> float:
        return self.image_width / self.image_height  # as viser's CameraHandle.aspect

    def on_update(self, callback) -> None:
        pass


def session_for(scene, mode: str, image_height: float, image_width: float) -> tuple:
    """A client session on a stand-in client (a mock: its scene and controls accept anything) whose canvas
    reports ``image_height`` x ``image_width`` pixels."""
    from aesplat.view.app import ClientSession, ViewerOptions

    client = MagicMock()
    client.camera = Camera(image_height=image_height, image_width=image_width)
    client.get_render.return_value = np.zeros((1, 1, 4), np.uint8)
    session = ClientSession(SimpleNamespace(options=ViewerOptions(mode=mode, exact_height=480), scene=scene),
                            client)  # fmt: skip
    client.camera.wxyz, client.camera.position = np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3)
    return session, client


@pytest.fixture
def recorded(monkeypatch):
    """The sizes the exact renders were asked for; each render returns one black pixel."""
    from aesplat.view import app

    sizes = []

    def render_viewpoint(scene, view, height, **_):
        sizes.append(view.size(height))
        return torch.zeros(3, 1, 1)

    monkeypatch.setattr(app, "render_viewpoint", render_viewpoint)
    return sizes


@pytest.mark.parametrize(
    ("height", "width", "expected"),
    [
        (20000, 20000, (480, 480)),  # the canvas height: at most --exact-height
        (300, 300 * 20000, (300, 1200)),  # the width: at most 4 times the height
        (20000, 1, (480, 120)),  # a tall view: at least a quarter as wide as tall
        (0, 5, (1, 1)),  # sizes that are not positive: one pixel of a square view
        (-5, -7, (1, 1)),
    ],
)
def test_a_clients_exact_render_size_is_capped(scene, recorded, height, width, expected):
    session, _ = session_for(scene, "exact", image_height=height, image_width=width)
    try:
        session.render_exact()
    finally:
        session.close()
    assert recorded == [expected]


def test_a_screenshot_is_capped(scene, recorded):
    session, client = session_for(scene, "exact", image_height=20000, image_width=20000 * 20000)
    try:
        session.send_screenshot()  # exact: the server renders it, at most 1080 pixels tall
        session.mode = "fast"
        session.send_screenshot()  # fast: the browser renders it, at most 2160 pixels tall
    finally:
        session.close()
    assert recorded == [(1080, 4 * 1080)]  # the view at most 4 times as wide as tall
    (height, width), _ = client.get_render.call_args
    assert (height, width) == (2160, 4 * 2160)
    assert client.send_file_download.call_count == 2


def test_a_burst_of_screenshot_clicks_renders_once(scene, monkeypatch):
    """A click while a screenshot is being made is dropped: the one under way answers it."""
    from aesplat.view import app

    entered, release, renders = threading.Event(), threading.Event(), []

    def render_viewpoint(scene, view, height, **_):
        renders.append(height)
        entered.set()
        release.wait(timeout=60)
        return torch.zeros(3, 1, 1)

    monkeypatch.setattr(app, "render_viewpoint", render_viewpoint)
    session, client = session_for(scene, "exact", image_height=100, image_width=100)
    first = threading.Thread(target=session.send_screenshot)
    try:
        first.start()
        assert entered.wait(timeout=60)
        second = threading.Thread(target=session.send_screenshot)
        second.start()
        second.join(timeout=10)  # returns at once: nothing to wait for
    finally:
        release.set()
        first.join(timeout=60)
        session.close()
    assert renders == [100] and client.send_file_download.call_count == 1
