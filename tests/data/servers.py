"""What the tests of shards behind a URL (aesplat.data.remote) share: their download settings, where a cache
keeps a shard, and :class:`FaultServer`, an HTTP(S) server on 127.0.0.1 that answers as a broken or hostile
data server would. It serves a folder as a plain server does (200 with Content-Length, 206 for a Range
request), except on the paths given a fault (:class:`FaultServer.faults`): each fault writes its own answer.
Every request is recorded as (path, Range header or "")."""

from __future__ import annotations

import json
import ssl
import subprocess
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from aesplat.data.manifest import read_manifest
from aesplat.data.remote import DownloadSettings

TOKEN = "tok-3f9c1d7e"  # what /auth/ accepts; a test looks for it in everything a run writes
FAST = DownloadSettings(retries=2, timeout=5.0, backoff=0.05)
LOADER = {"image_size": 28, "batch_size": 2, "gap_initial": (2, 4), "gap_final": (2, 4), "gap_warmup_steps": 0,
          "train_batches_per_epoch": 4, "shuffle_buffer": 4, "validate_on_test": True}  # fmt: skip


def record(root: Path, name: str):
    """The manifest's record of shard ``name`` ("split/shard") of the folder ``root``."""
    split, shard = name.split("/")
    return next(s for s in read_manifest(root).splits[split].shards if s.shard == shard)


def cached(cache: Path, root: Path, name: str) -> Path:
    """Where the cache ``cache`` keeps shard ``name`` of ``root``: under its SHA-256."""
    return cache / "shards" / f"{record(root, name).sha256}.tar"


def manifest_of(root: Path) -> dict:
    """``root/manifest.json`` as JSON."""
    return json.loads((root / "manifest.json").read_text())


def write_manifest(root: Path, manifest: dict) -> None:
    (root / "manifest.json").write_text(json.dumps(manifest))


def edit_manifest(root: Path, name: str, **fields) -> None:
    """Set ``fields`` of shard ``name``'s entry in ``root/manifest.json`` (as a new conversion would)."""
    manifest = manifest_of(root)
    split, shard = name.split("/")
    next(e for e in manifest["splits"][split]["shards"] if e["shard"] == shard).update(fields)
    write_manifest(root, manifest)


def logged(nginx, suffix: str, at_least: int = 1) -> list[str]:
    """The paths ending in ``suffix`` that ``nginx`` has logged, once at least ``at_least`` are there (it logs a
    request when it ends, which for one the client left may be a moment after the client saw its error)."""
    deadline = time.monotonic() + 5
    while True:
        paths = [uri for _, uri, _, _ in nginx.requests() if uri.endswith(suffix)]
        if len(paths) >= at_least or time.monotonic() > deadline:
            return paths
        time.sleep(0.05)


Fault = Callable[[BaseHTTPRequestHandler, bytes], None]  # (the request, the file's bytes) -> writes an answer


class FaultServer:
    """Serves ``root`` on 127.0.0.1 (over TLS with ``tls=(cert, key)``); ``faults[path]`` answers ``path``."""

    def __init__(self, root: Path, tls: tuple[Path, Path] | None = None) -> None:
        self.root = Path(root)
        self.faults: dict[str, Fault] = {}
        self.requests: list[tuple[str, str]] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                server.requests.append((path, self.headers.get("Range", "")))
                file = server.root / path.lstrip("/")
                data = file.read_bytes() if file.is_file() else None
                try:
                    if path in server.faults:
                        server.faults[path](self, data or b"")
                    elif data is None:
                        self.send_error(404)
                    else:
                        plain(self, data)
                except (BrokenPipeError, ConnectionResetError):
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        if tls is not None:
            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            context.load_cert_chain(*map(str, tls))
            self.httpd.socket = context.wrap_socket(self.httpd.socket, server_side=True)
        scheme = "https" if tls else "http"
        self.url = f"{scheme}://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def gets(self, path: str) -> list[str]:
        """The Range header of every GET of ``path`` so far."""
        return [ranged for p, ranged in self.requests if p == path]

    def __enter__(self) -> FaultServer:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def plain(handler: BaseHTTPRequestHandler, data: bytes) -> None:
    """What a correct server answers: the file, or the range a ``Range: bytes=N-`` header asks for."""
    ranged = handler.headers.get("Range", "")
    if ranged.startswith("bytes="):
        first = int(ranged[6:].split("-")[0])
        handler.send_response(206)
        handler.send_header("Content-Range", f"bytes {first}-{len(data) - 1}/{len(data)}")
        data = data[first:]
    else:
        handler.send_response(200)
    handler.send_header("Content-Length", str(len(data)))
    handler.end_headers()
    handler.wfile.write(data)


def headers(status: int, pairs: dict[str, str], body: bytes | None = None) -> Fault:
    """Answer ``status`` with the headers ``pairs`` and ``body`` (None: the file's bytes); the connection ends
    after it (HTTP/1.0)."""

    def answer(handler: BaseHTTPRequestHandler, data: bytes) -> None:
        handler.send_response(status)
        for key, value in pairs.items():
            handler.send_header(key, value)
        handler.end_headers()
        handler.wfile.write(data if body is None else body)

    return answer


def once(fault: Fault) -> Fault:
    """``fault`` for the first request, a correct answer after it."""
    used: list[bool] = []

    def answer(handler: BaseHTTPRequestHandler, data: bytes) -> None:
        if used:
            return plain(handler, data)
        used.append(True)
        fault(handler, data)

    return answer


def trickle(every: float) -> Fault:
    """The file with its true Content-Length, one byte each ``every`` seconds."""

    def answer(handler: BaseHTTPRequestHandler, data: bytes) -> None:
        handler.send_response(200)
        handler.send_header("Content-Length", str(len(data)))
        handler.end_headers()
        for i in range(len(data)):
            handler.wfile.write(data[i : i + 1])
            handler.wfile.flush()
            time.sleep(every)

    return answer


def endless(handler: BaseHTTPRequestHandler, data: bytes) -> None:
    """The file's bytes and then more, without end and without a Content-Length (until the client leaves)."""
    handler.send_response(200)
    handler.end_headers()
    handler.wfile.write(data)
    block = b"\0" * (1 << 20)
    while True:
        handler.wfile.write(block)


def self_signed(folder: Path) -> tuple[Path, Path]:
    """A certificate for 127.0.0.1 signed by itself, and its key (openssl)."""
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key),
                    "-out", str(cert), "-days", "2", "-subj", "/CN=127.0.0.1",
                    "-addext", "subjectAltName=IP:127.0.0.1"], check=True, capture_output=True)  # fmt: skip
    return cert, key
