"""MkDocs hooks (mkdocs.yml: ``hooks``): pages built from the code and from the files benchmarks wrote.

- ``docs/configuration.md`` holds the line ``<!-- config-reference -->``; the build replaces it with the tables
  ``scripts/config_reference.py`` makes from the config dataclasses, so the page cannot drift from the code. A
  page that lost the marker, or a reference that cannot be made, fails the build.
- Every page's figures (``<!-- fig SOURCE:KEY -->20.05<!-- /fig -->``, ``scripts/figures.py``) are checked
  against their sources: a figure that disagrees with the file its command wrote fails the build, with the
  value to write. The comments are removed from what the site shows.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

MARKER = "<!-- config-reference -->"
_SCRIPTS = Path(__file__).resolve().parent


def _script(name: str):
    spec = importlib.util.spec_from_file_location(f"aesplat_docs_{name}", _SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


_figures = _script("figures")


def on_pre_build(config) -> None:
    _figures.load.cache_clear()  # `mkdocs serve` rebuilds after a benchmark rewrote a source


def _reference() -> str:
    return _script("config_reference").markdown()


def on_page_markdown(markdown: str, page, config, files) -> str:
    uri = page.file.src_uri
    disagreements = _figures.problems(markdown, f"docs/{uri}")
    if disagreements:
        raise ValueError("figures that disagree with their sources:\n" + "\n".join(disagreements))
    markdown = _figures.strip(markdown)
    if uri != "configuration.md":
        return markdown
    if MARKER not in markdown:
        raise ValueError(f"docs/configuration.md lost its {MARKER} line: put it back where the tables go")
    return markdown.replace(MARKER, _reference())
