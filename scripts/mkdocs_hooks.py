"""MkDocs hooks (mkdocs.yml: ``hooks``): fill the configuration reference from the code at build time.

``docs/configuration.md`` holds the line ``<!-- config-reference -->``; the build replaces it with the tables
``scripts/config_reference.py`` makes from the config dataclasses, so the page cannot drift from the code. A
page that lost the marker, or a reference that cannot be made, fails the build.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

MARKER = "<!-- config-reference -->"
_SCRIPT = Path(__file__).resolve().parent / "config_reference.py"


def _reference() -> str:
    spec = importlib.util.spec_from_file_location("config_reference", _SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.markdown()


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri != "configuration.md":
        return markdown
    if MARKER not in markdown:
        raise ValueError(f"docs/configuration.md lost its {MARKER} line: put it back where the tables go")
    return markdown.replace(MARKER, _reference())
