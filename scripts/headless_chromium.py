"""Headless Chromium driven over the Chrome DevTools protocol: open a page, run JavaScript, take screenshots.

Used by the browser test of ``aesplat view`` and by ``scripts/view_screenshot.py`` (the docs page's picture).
It needs Debian's ``chromium`` (``apt-get install chromium``) and the ``websockets`` package (a dependency of
viser, the viewer extra); it never downloads a browser. The browser runs with a fresh profile, no network
services of its own and WebGL on SwiftShader (software rendering: no GPU needed).

    with Chromium(width=960, height=640) as browser:
        browser.open("http://127.0.0.1:8080")
        png = browser.screenshot()          # PNG bytes of the whole page
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

FLAGS = [
    "--headless=new",
    "--no-sandbox",  # as root (CI) Chromium refuses to start without it
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
    "--disable-default-apps",
    "--disable-extensions",
    "--no-first-run",
    "--no-default-browser-check",
    "--use-angle=swiftshader",  # WebGL without a GPU
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--hide-scrollbars",
    "--remote-debugging-port=0",  # any free port; Chromium writes it to DevToolsActivePort
]


def find_chromium() -> str | None:
    """The Chromium executable on PATH (Debian's ``chromium``), or None."""
    for name in ("chromium", "chromium-browser"):
        if path := shutil.which(name):
            return path
    return None


class Chromium:
    """A headless Chromium with one page, controlled over the DevTools protocol; stopped on exit."""

    def __init__(self, width: int = 960, height: int = 640, executable: str | None = None) -> None:
        self.width, self.height = width, height
        self.executable = executable or find_chromium()
        if self.executable is None:
            raise RuntimeError("Chromium is not installed (Debian: apt-get install chromium)")
        self._next_id = 0

    def __enter__(self) -> Chromium:
        from websockets.sync.client import connect

        self.profile = tempfile.mkdtemp(prefix="aesplat-chromium-")
        args = [self.executable, *FLAGS, f"--user-data-dir={self.profile}",
                f"--window-size={self.width},{self.height}", "about:blank"]  # fmt: skip
        self.process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                        start_new_session=True)  # fmt: skip
        try:
            port = self._devtools_port(timeout=30.0)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as response:
                pages = [t for t in json.load(response) if t["type"] == "page"]
            self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
            self.call("Page.enable")
            self.call("Emulation.setDeviceMetricsOverride", width=self.width, height=self.height,
                      deviceScaleFactor=1, mobile=False)  # fmt: skip
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _devtools_port(self, timeout: float) -> int:
        active = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"Chromium exited with status {self.process.returncode} at start")
            if active.is_file() and (lines := active.read_text().splitlines()):
                return int(lines[0])
            time.sleep(0.1)
        raise TimeoutError(f"Chromium did not open its DevTools port within {timeout:.0f} s")

    def call(self, method: str, timeout: float = 60.0, **params) -> dict:
        """Send one DevTools command and return its result (events that arrive meanwhile are dropped)."""
        self._next_id += 1
        self.ws.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            message = json.loads(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))
            if message.get("id") == self._next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (JSON-able values only)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return result.get("result", {}).get("value")

    def screenshot(self) -> bytes:
        """PNG bytes of the page as shown (``width`` x ``height``)."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def __exit__(self, *exc) -> None:
        ws = getattr(self, "ws", None)
        if ws is not None:
            ws.close()
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, 9)
                self.process.wait()
        shutil.rmtree(self.profile, ignore_errors=True)
