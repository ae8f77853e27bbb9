"""What the viewer tests share: the headless Chromium driver, the viewer extra's check, waiting on a page."""

import importlib.util
import time

from tests.helpers import need
from tests.script_loader import load_script

browser = load_script("headless_chromium")


def need_viser() -> None:
    need(importlib.util.find_spec("viser") is not None, 'viser (pip install -e ".[viewer]")')


def wait_for(condition, timeout: float, what: str):
    """Poll ``condition`` until it returns something (not None, False or an empty dict); that value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value is not None and value is not False and not (isinstance(value, dict) and not value):
            return value
        time.sleep(0.25)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")
