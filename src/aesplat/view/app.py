"""The browser viewer: a viser server showing one :class:`ViewScene` to every client that connects.

Each client gets its own copy of the scene and controls (viser's per-client scene and GUI), so one client's
render mode or camera never changes another's:

- the Gaussians as client-side splats (base colour, sorted and drawn by the browser: fast while moving);
- the input cameras as frustums textured with their images (click one to look through it) and the
  novel-view path as a curve with a small frustum per frame;
- controls: render mode, SH degree, opacity threshold, showing the cameras, jumping to any camera, playing the
  path, saving a screenshot (sent to the browser as a PNG download; nothing is written on the server).

In the exact mode the splats are shown while the camera moves; once it rests for ``REST_S`` seconds the server
renders the viewpoint with this project's rasterizer (view-dependent SH up to the chosen degree) and shows that
image in place of the splats until the camera moves again.

Only the viewer's own page may connect (:class:`Gate`): each start draws a random key that the printed URL
holds (``http://HOST:PORT/KEY/``); the page and its websocket are refused (HTTP 403) without it, and a websocket
is refused unless its ``Origin`` is the address it connects to, so a page of another site, or of another port
on this machine, gets nothing even where it knows the key. What a client can make the server render is capped
(:func:`~aesplat.view.camera.capped_height`, :func:`~aesplat.view.camera.capped_aspect`): exact renders at most
``--exact-height`` pixels tall, screenshots at most ``EXACT_SCREENSHOT_HEIGHT`` (server-rendered) or
``SCREENSHOT_HEIGHT`` (browser-rendered), each at most ``MAX_ASPECT`` times as wide as tall, one screenshot at
a time per tab.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
import secrets
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from http import HTTPStatus
from urllib.parse import urlsplit

import numpy as np
import torch
from PIL import Image

from ..errors import UserError
from ..export import drop_transparent
from ..geometry import covariance_from_scale_rot, sh_dc_to_rgb
from ..images import to_uint8
from .camera import Viewpoint, capped_aspect, capped_height, viewpoint_of
from .exact import render_viewpoint
from .scene import ViewScene

MODES = ("fast", "exact")
REST_S = 0.25  # the camera has rested this long: render the exact image
PATH_FPS = 10.0
EXACT_SCREENSHOT_HEIGHT = 1080  # the tallest screenshot the server renders (the exact mode)
SCREENSHOT_HEIGHT = 2160  # the tallest screenshot the server asks the browser for (the fast mode)
KEY_BYTES = 24  # the key in the URL: 192 random bits, 32 URL-safe characters
WILDCARD_HOSTS = ("0.0.0.0", "::", "")  # listening on every address: the URL names this machine instead
NO_KEY = "Forbidden: open the URL that `aesplat view` printed; it holds this viewer's key.\n"
OTHER_ORIGIN = "Forbidden: only the viewer's own page may open its websocket.\n"


def check_port_free(host: str, port: int) -> None:
    """Refuse a port another program listens on, before the server starts (viser would quietly take the next
    free port, and the printed URL would not be the one asked for)."""
    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as err:
            raise UserError(f"cannot listen on {host}:{port} ({err.strerror}); give another --port") from None


def path_after_key(path: str, key: str) -> str | None:
    """The rest of a request path that starts with the viewer's key: ``/KEY`` or ``/KEY/REST`` (a query
    dropped) -> ``/REST``; None when it does not start with the key. Compared in constant time, so that the
    time of a refusal tells nothing about the key."""
    first, _, rest = path.partition("?")[0].lstrip("/").partition("/")
    given = first.encode("utf-8", "surrogateescape")
    return "/" + rest if secrets.compare_digest(given, key.encode()) else None


def same_origin(origin: str | None, host: str | None) -> bool:
    """Whether a websocket handshake's ``Origin`` (the page that opens it, as the browser names it) is the
    address the request went to (its ``Host``): true for the viewer's own page, however it was reached (by
    name, address or a forwarded port), false for a page of another site or of another port on this machine,
    and for a client that names no origin."""
    if not origin or not host:
        return False
    try:
        parts = urlsplit(origin)
    except ValueError:  # not a URL (an unclosed IPv6 bracket)
        return False
    return parts.scheme in ("http", "https") and parts.netloc.lower() == host.strip().lower()


def single_header(request, name: str) -> str | None:
    """The value of a header a request holds exactly once, else None."""
    values = request.headers.get_all(name)
    return values[0] if len(values) == 1 else None


class Gate:
    """What the server answers to before viser does: every request must start with the viewer's key
    (:func:`path_after_key`), and a websocket handshake must also come from the viewer's own page
    (:func:`same_origin`); anything else gets an HTTP 403 and nothing of the scene. The page itself is viser's,
    served for the path after the key."""

    def __init__(self, key: str) -> None:
        self.key = key
        self.installed = False  # wrap() was called: the server viser started answers to this gate

    def wrap(self, serve_page: Callable | None) -> Callable:
        """The ``process_request`` of websockets' ``serve`` for the server viser starts, given viser's own
        (which serves the page and lets websocket handshakes through)."""
        self.installed = True

        def process_request(connection, request):
            rest = path_after_key(request.path, self.key)
            if rest is None:
                return connection.respond(HTTPStatus.FORBIDDEN, NO_KEY)
            if (single_header(request, "Upgrade") or "").lower() == "websocket":
                if not same_origin(single_header(request, "Origin"), single_header(request, "Host")):
                    return connection.respond(HTTPStatus.FORBIDDEN, OTHER_ORIGIN)
                return None  # the handshake goes on
            if serve_page is None:
                return None
            return serve_page(connection, dataclasses.replace(request, path=rest))

        return process_request


_SERVE_LOCK = threading.Lock()


@contextlib.contextmanager
def guarding_handshakes(gate: Gate) -> Iterator[None]:
    """While the block starts a viser server: the server it starts answers to ``gate`` first.

    viser offers no hook of its own on the opening handshake; it starts its server with websockets' ``serve``,
    giving it a ``process_request`` (the page). For the block, ``serve`` puts the gate in front of that; the
    lock keeps two viewers that start at once from taking each other's gate. The caller checks
    ``gate.installed`` after the block: a viser that starts its server some other way is refused, not served
    unguarded.
    """
    import websockets.asyncio.server as ws_server

    real = ws_server.serve

    def serve(handler, *args, process_request=None, **kwargs):
        return real(handler, *args, process_request=gate.wrap(process_request), **kwargs)

    with _SERVE_LOCK:
        ws_server.serve = serve
        try:
            yield
        finally:
            ws_server.serve = real


def framing_distance(
    means: torch.Tensor, c2w: torch.Tensor, fov: float, aspect: float, keep: float = 0.95
) -> float:
    """How far back along a camera's axis the eye must move for ``keep`` of the points to be in its view.

    means [N, 3] world points, c2w [4, 4] the camera (OpenCV axes), fov its vertical field of view (radians),
    aspect width / height. A point (x, y, z) in the camera's frame is in view from ``t`` behind it when
    |x| <= (z + t) tan(fov_x / 2) and |y| <= (z + t) tan(fov / 2); the answer is the ``keep`` quantile of the
    smallest such t over the points, never negative.
    """
    local = (means - c2w[:3, 3]) @ c2w[:3, :3]  # [N, 3] in the camera's frame
    tan_y = math.tan(fov / 2)
    need = torch.maximum(local[:, 0].abs() / (tan_y * aspect), local[:, 1].abs() / tan_y) - local[:, 2]
    return max(float(torch.quantile(need, keep)), 0.0)


def png_bytes(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return buf.getvalue()


@dataclass(frozen=True)
class ViewerOptions:
    """How the viewer starts: host and port it listens on (0: any free port), the render mode, whether the
    input cameras and the novel-view path show, the height of exact renders (their width follows the browser's
    aspect), and where and how the exact renders run."""

    host: str = "127.0.0.1"
    port: int = 8080
    mode: str = "fast"
    show_cameras: bool = True
    show_path: bool = False
    exact_height: int = 480
    device: str = "cpu"
    backend: str = "auto"


class Viewer:
    """A running viewer: ``url``, ``clients`` (connected client sessions by id) and ``stop()``."""

    def __init__(self, scene: ViewScene, options: ViewerOptions) -> None:
        import viser  # the optional `viewer` extra; aesplat.view.command turns its absence into one line

        if options.mode not in MODES:
            raise UserError(f"unknown render mode {options.mode!r}; choose from {', '.join(MODES)}")
        check_port_free(options.host, options.port)
        self.scene = scene
        self.options = options
        self.key = secrets.token_urlsafe(KEY_BYTES)  # a new one each start: a URL seen before opens nothing
        gate = Gate(self.key)
        # viser's own banner is dropped: the command prints the URL, key included
        with guarding_handshakes(gate), contextlib.redirect_stdout(io.StringIO()):
            self.server = viser.ViserServer(host=options.host, port=options.port, label="aesplat view",
                                            verbose=False)  # fmt: skip
        if not gate.installed:
            self._stop_server()
            raise UserError(
                f"viser {viser.__version__} starts its server in a way aesplat view cannot guard (it would "
                "serve anyone); install the tested one: pip install viser==1.1.1"
            )
        if options.port not in (0, self.server.get_port()):  # taken between the check and the start
            self._stop_server()
            raise UserError(f"cannot listen on {options.host}:{options.port} (in use); give another --port")
        self.server.scene.set_up_direction("-y")  # the world is view 0's camera frame: y points down
        self.clients: dict[int, ClientSession] = {}
        self._lock = threading.Lock()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        """The address to open, key included; listening on every address (0.0.0.0), under this machine's name,
        for another machine to open."""
        host = self.options.host
        if host in WILDCARD_HOSTS:
            host = socket.gethostname()
        return f"http://{f'[{host}]' if ':' in host else host}:{self.server.get_port()}/{self.key}/"

    def _connect(self, client) -> None:
        session = ClientSession(self, client)
        with self._lock:
            self.clients[client.client_id] = session

    def _disconnect(self, client) -> None:
        with self._lock:
            session = self.clients.pop(client.client_id, None)
        if session is not None:
            session.close()

    def stop(self) -> None:
        """Close every client session and stop the server (its threads end; the port is released)."""
        with self._lock:
            sessions = list(self.clients.values())
            self.clients.clear()
        for session in sessions:
            session.close()
        self._stop_server()

    def _stop_server(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # viser's "server stopped"
            self.server.stop()


class ClientSession:
    """One browser tab: its scene nodes, controls, and the thread that renders its exact images."""

    def __init__(self, viewer: Viewer, client) -> None:
        self.viewer, self.client, self.scene = viewer, client, viewer.scene
        self.mode = viewer.options.mode
        self.sh_degree = self.scene.sh_degree
        self.min_opacity = 0.0
        self.showing_exact = False
        self.last_exact: np.ndarray | None = None  # the exact image shown now (uint8 [H, W, 3])
        self.exact_renders = 0  # exact images shown so far
        self._moved = threading.Event()
        self._last_move = 0.0
        self._closed = threading.Event()
        self._playing = threading.Event()
        self._screenshot_busy = threading.Lock()
        self.views = [viewpoint_of(c.extrinsics, c.intrinsics, c.width, c.height) for c in self.scene.cameras]
        self.path = [
            viewpoint_of(e, k, 1, 1) for e, k in zip(self.scene.path_extrinsics, self.scene.path_intrinsics)
        ]
        self._add_scene()
        self._add_controls()
        self._set_initial_camera()
        client.camera.on_update(self._camera_moved)
        self._worker = threading.Thread(target=self._render_loop, daemon=True, name=f"exact-{client.client_id}")
        self._worker.start()

    # ------------------------------------------------------------------------------------------- scene

    def _extent(self) -> float:
        """A length for sizing frustums: the spread of the Gaussian centres (robust to outliers)."""
        means = self.scene.gaussians.means[0]
        lo, hi = torch.quantile(means, torch.tensor([0.05, 0.95]), dim=0)
        return max(float((hi - lo).norm()), 1e-3)

    def _add_splats(self) -> None:
        g = drop_transparent(self.scene.gaussians, self.min_opacity)
        rgb = sh_dc_to_rgb(g.sh[0, :, 0]).clamp(0, 1)  # base colour: what the fast mode shows
        cov = covariance_from_scale_rot(g.scales[0], g.quats[0])  # [N, 3, 3]
        self.splats = self.client.scene.add_gaussian_splats(
            "/gaussians", centers=g.means[0].numpy(), covariances=cov.numpy(), rgbs=rgb.numpy(),
            opacities=g.opacities[0, :, None].numpy(), visible=not self.showing_exact,
        )  # fmt: skip

    def _add_scene(self) -> None:
        self._add_splats()
        scale = 0.1 * self._extent()
        self.frustums = []
        for i, (cam, view) in enumerate(zip(self.scene.cameras, self.views)):
            frustum = self.client.scene.add_camera_frustum(
                f"/cameras/{i:02d}_{cam.name}", fov=view.fov, aspect=view.aspect, scale=scale, image=cam.image,
                wxyz=view.wxyz, position=view.position, color=(230, 120, 20), thickness=2.0,
                thickness_units="screen", visible=self.viewer.options.show_cameras,
            )  # fmt: skip
            frustum.on_click(lambda _event, view=view: self.go_to(view))
            self.frustums.append(frustum)
        self.path_nodes = []  # the novel-view path: hidden unless asked for (it stands between eye and scene)
        if self.path:
            positions = np.array([v.position for v in self.path])
            self.path_nodes.append(self.client.scene.add_spline_catmull_rom(
                "/path/curve", points=positions, color=(40, 160, 240), thickness=2.0, thickness_units="screen",
                visible=self.viewer.options.show_path,
            ))  # fmt: skip
            for f, view in enumerate(self.path):
                self.path_nodes.append(self.client.scene.add_camera_frustum(
                    f"/path/{f:03d}", fov=view.fov, aspect=view.aspect, scale=0.4 * scale, wxyz=view.wxyz,
                    position=view.position, color=(40, 160, 240), thickness=1.5, thickness_units="screen",
                    visible=self.viewer.options.show_path,
                ))  # fmt: skip

    def _set_initial_camera(self) -> None:
        """Input view 0's direction and field of view, moved back along its axis far enough that the Gaussians
        (all but the farthest-out 5 %) are in view (:func:`framing_distance`), and at least half their median
        depth, so that view 0's own frustum (its photo on it) stands in the scene instead of filling the
        screen; without cameras, in front of the Gaussians."""
        means = self.scene.gaussians.means[0].double()
        camera = self.client.camera
        if self.views:
            view = self.views[0]
            c2w = view.extrinsics().double()
            forward, centre = c2w[:3, 2], c2w[:3, 3]
            depth = float(((means - centre) @ forward).median().clamp_min(1e-3))
            back = max(framing_distance(means, c2w, view.fov, view.aspect), 0.5 * depth)
            camera.fov = view.fov
            camera.up_direction = (-c2w[:3, 1]).numpy()
            camera.position = (centre - back * forward).numpy()
            camera.look_at = (centre + depth * forward).numpy()
        else:
            target = means.median(dim=0).values
            camera.up_direction = (0.0, -1.0, 0.0)
            camera.position = (
                target - torch.tensor([0.0, 0.0, 1.5 * self._extent()], dtype=torch.float64)
            ).numpy()
            camera.look_at = target.numpy()

    # ------------------------------------------------------------------------------------------- controls

    def _add_controls(self) -> None:
        gui = self.client.gui
        g = self.scene.gaussians
        gui.add_markdown(f"**{self.scene.source}**  \n{g.num_gaussians:,} Gaussians, SH degree {g.sh_degree}, "
                         f"{len(self.scene.cameras)} cameras")  # fmt: skip
        with gui.add_folder("Render"):
            mode = gui.add_dropdown("Mode", MODES, initial_value=self.mode,
                                    hint="fast: splats drawn by the browser, base colour; exact: this "
                                    "project's rasterizer on the server, view-dependent SH")  # fmt: skip
            degrees = [str(d) for d in range(self.scene.sh_degree + 1)]
            degree = gui.add_dropdown("SH degree", degrees, initial_value=degrees[-1],
                                      hint="bands the exact mode evaluates (fast: degree 0)")  # fmt: skip
            opacity = gui.add_slider("Min opacity", min=0.0, max=1.0, step=0.01, initial_value=0.0,
                                     hint="hide Gaussians less opaque than this")  # fmt: skip
            screenshot = gui.add_button("Save screenshot", hint="the current view as a PNG download")
        with gui.add_folder("Cameras"):
            show = gui.add_checkbox("Show cameras", initial_value=self.viewer.options.show_cameras,
                                    hint="the input cameras' frustums, textured with their images")  # fmt: skip
            show_path = gui.add_checkbox("Show path", initial_value=self.viewer.options.show_path,
                                         hint="the novel-view path and its frames")  # fmt: skip
            names = [f"{i:02d} {c.name}" for i, c in enumerate(self.scene.cameras)]
            names += [f"path {f:03d}" for f in range(len(self.path))]
            if names:
                target = gui.add_dropdown("Camera", names, initial_value=names[0])
                go = gui.add_button("Go to camera")
                go.on_click(lambda _: self.go_to((self.views + self.path)[names.index(target.value)]))
            if self.path:
                play = gui.add_button("Play path")
                play.on_click(lambda _: self.play_path())

        @mode.on_update
        def _(_) -> None:
            self.mode = mode.value
            self._show_splats()
            self._request_exact()

        @degree.on_update
        def _(_) -> None:
            self.sh_degree = int(degree.value)
            self._request_exact()

        @opacity.on_update
        def _(_) -> None:
            self.min_opacity = float(opacity.value)
            self._add_splats()  # replaces the node of the same name
            self._request_exact()

        @show.on_update
        def _(_) -> None:
            for node in self.frustums:
                node.visible = show.value

        @show_path.on_update
        def _(_) -> None:
            for node in self.path_nodes:
                node.visible = show_path.value

        screenshot.on_click(lambda _: self.send_screenshot())

    def go_to(self, view: Viewpoint) -> None:
        """Put the browser's camera at ``view`` (its pose and vertical field of view)."""
        rot = view.extrinsics()[:3, :3].double()
        with self.client.atomic():
            self.client.camera.fov = view.fov
            self.client.camera.up_direction = (-rot[:, 1]).numpy()
            self.client.camera.position = view.position
            self.client.camera.wxyz = view.wxyz

    def play_path(self) -> None:
        """Fly along the novel-view path (one frame every 1 / PATH_FPS s); a second click stops it."""
        if self._playing.is_set():
            self._playing.clear()
            return
        self._playing.set()
        for view in self.path:
            if not self._playing.is_set() or self._closed.is_set():
                break
            self.go_to(view)
            time.sleep(1.0 / PATH_FPS)
        self._playing.clear()

    def send_screenshot(self) -> None:
        """The current view as a PNG download: the exact image in the exact mode (at most
        EXACT_SCREENSHOT_HEIGHT pixels tall), else the browser's render (at most SCREENSHOT_HEIGHT). A click
        while one is being made is dropped: the one under way answers it, and a burst of clicks cannot queue
        renders."""
        if not self._screenshot_busy.acquire(blocking=False):
            return
        try:
            if self.mode == "exact":
                image = to_uint8(self.render_exact(EXACT_SCREENSHOT_HEIGHT))
            else:
                height = capped_height(self.client.camera.image_height, SCREENSHOT_HEIGHT)
                h, w = self.viewpoint().size(height)
                image = self.client.get_render(h, w, transport_format="png")[..., :3]
            self.client.send_file_download("aesplat-view.png", png_bytes(image))
        finally:
            self._screenshot_busy.release()

    # ------------------------------------------------------------------------------------------- exact mode

    def viewpoint(self) -> Viewpoint:
        """The browser's current viewpoint; its aspect ratio the canvas's, within :func:`capped_aspect`'s
        bounds."""
        camera = self.client.camera
        aspect = capped_aspect(camera.image_width, camera.image_height)
        return Viewpoint(tuple(camera.wxyz.tolist()), tuple(camera.position.tolist()), float(camera.fov),
                         aspect)  # fmt: skip

    def render_exact(self, most: int | None = None) -> torch.Tensor:
        """The current viewpoint by this project's rasterizer -> colour [3, H, W]: H the browser's canvas
        height, at most ``most`` (default: the ``exact_height`` option), W = H times the capped aspect ratio."""
        options = self.viewer.options
        height = capped_height(self.client.camera.image_height, most or options.exact_height)
        return render_viewpoint(self.scene, self.viewpoint(), height, sh_degree=self.sh_degree,
                                min_opacity=self.min_opacity, backend=options.backend,
                                device=options.device)  # fmt: skip

    def _show_splats(self) -> None:
        """Back to the client's splats (the camera moves, or the fast mode)."""
        if self.showing_exact:
            self.showing_exact = False
            self.client.scene.set_background_image(None)
            self.splats.visible = True

    def _camera_moved(self, _camera) -> None:
        self._show_splats()
        self._request_exact()

    def _request_exact(self) -> None:
        self._last_move = time.monotonic()
        self._moved.set()

    def _render_loop(self) -> None:
        """Render the exact image once the camera has rested; drop it if the camera moved meanwhile."""
        while not self._closed.is_set():
            if not self._moved.wait(timeout=0.5):
                continue
            rest = REST_S - (time.monotonic() - self._last_move)
            if rest > 0:
                time.sleep(rest)
                continue
            self._moved.clear()
            if self.mode != "exact" or self._closed.is_set():
                continue
            started = self._last_move
            try:
                image = to_uint8(self.render_exact())
            except Exception:  # noqa: BLE001 - a disconnect mid-render; the session closes
                if self._closed.is_set():
                    return
                raise
            if self._closed.is_set():
                return  # the tab closed while rendering
            if self._last_move != started or self.mode != "exact":
                continue  # stale: the camera moved while rendering
            with self.client.atomic():
                self.client.scene.set_background_image(image, format="png")
                self.splats.visible = False
            self.showing_exact = True
            self.last_exact = image
            self.exact_renders += 1

    def close(self) -> None:
        self._closed.set()
        self._playing.clear()
        self._moved.set()
        if threading.current_thread() is not self._worker:
            self._worker.join(timeout=10.0)
