#!/usr/bin/env python
"""One source per figure: every figure a page states is checked against the file the command that measured it
wrote, so that two pages cannot give two values for one figure.

A page (README.md or docs/**/*.md) wraps a figure in two HTML comments that name its source and key:

    trained, the demo scores <!-- fig demo:test.trained.psnr -->20.05<!-- /fig --> dB on its test scenes

The comments do not show on the site (the build removes them) nor on GitHub. What lies between them must agree
with the source:

- a number agrees when it equals the source's value rounded to as many decimals as the page writes
  (``20.05``, ``20.1`` and ``20`` all agree with 20.0512; ``1,536`` and ``−0.38`` are numbers);
- with a format after the key, ``<!-- fig demo:test.trained.psnr | +.2f -->``, the text must be exactly the
  value so formatted: a Python format spec, or one of ``FORMATS`` (``duration``: seconds as "4 min 58 s",
  ``date``: an ISO time as its day, ``floor``: the version of a ``>=`` requirement);
- anything else (a commit, a version) must equal the source's text.

SOURCE is a name of ``SOURCES`` below or a file path from the repository root; KEY is a path into the file:
``a.b.c`` walks mappings, ``[2]`` or ``[-1]`` picks an element of a list, ``[step=600]`` the first row whose
``step`` is 600 (``[set=diffuse,row=full]``: all of them hold), ``[torch]`` in a list of requirements the
specifier of ``torch``. Files are read by their suffix: JSON, YAML, TOML, CSV (a list of rows), a Makefile
(its variables) and markdown, whose tables are one list of rows (each row a mapping of its table's header cells
to its cells, markup removed): ``[run=eager again].seconds per step``.

A command that measures writes its source with ``provenance()`` (date, commit, machine, load) beside its
figures, and ``write_whole()`` (whole or not at all), both of ``benchmarks/common.py``, as
``scripts/demo_report.py`` and ``benchmarks/bench_render.py --json`` do.

    python scripts/figures.py                  # check every page; print each disagreement; exit 1 if any
    python scripts/figures.py --write          # rewrite the figures of the pages from their sources
    python scripts/figures.py --list [PAGE …]  # every figure: page, line, source, key, value

The documentation build (scripts/mkdocs_hooks.py) fails on a page whose figure disagrees with its source, and
tests/test_docs.py checks README.md and every page, so a figure cannot drift from its source without a test
failing. Adopting it on a page: write the figure between the comments, add the source to ``SOURCES`` when it
is a file others will quote too, and run ``python scripts/figures.py --write`` after the source changes.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import datetime
from decimal import ROUND_HALF_UP, Decimal
from functools import cache
from pathlib import Path

import yaml

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: a page may not quote a TOML file there
    tomllib = None

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from common import t_interval  # noqa: E402  (benchmarks/common.py, a file beside the packages)


def _seeds(pattern: str, step_column: str = "step") -> Callable[[], dict]:
    """A computed source: the mean and 95 % t-interval over data seeds of the last row of each curve CSV that
    ``benchmarks/learning_curves.py`` wrote (files matching ``pattern``, in name order), per column, and those
    last rows themselves (``runs``), each with its gain over copying the mean of the context views."""

    def compute() -> dict:
        files = sorted(REPO.glob(pattern))
        if not files:
            raise FigureError(f"no file matches {pattern}")
        last = [_csv(path)[-1] for path in files]
        for row in last:  # the gain over copying the mean of the context views, per seed
            if row.get("psnr") and row.get("copy_mean_psnr"):
                row["psnr_over_copy_mean"] = float(row["psnr"]) - float(row["copy_mean_psnr"])
        out: dict = {
            "seeds": len(files),
            "files": [p.relative_to(REPO).as_posix() for p in files],
            "runs": last,
        }
        for column in last[0]:
            if column == step_column:
                out[column] = last[0][column]
                continue
            try:
                values = [float(row[column]) for row in last]
            except (TypeError, ValueError):
                continue
            mean, half, n = t_interval(values)
            out[column] = {"mean": mean, "ci95": half, "n": n}
        return out

    return compute


def _paper_scale() -> dict:
    """A computed source: the hours the paper's runs take at the step time of the last GPU run
    (`aesplat fit -c conf/re10k.yaml` at 2 context views, docs/results/gpu/summary.json), for conf/re10k.yaml's
    steps and the ablation overlays' (conf/ablation/*.yaml, six rows)."""
    step = _number(lookup(_gpu_run(), "by_part.fit.seconds per step (median)"))
    steps = int(lookup(load("re10k-config"), "trainer.max_steps"))
    rows = sorted((REPO / "conf" / "ablation").glob("*.yaml"))
    ablation = {int(lookup(yaml.safe_load(p.read_text()), "trainer.max_steps")) for p in rows}
    if len(ablation) != 1:
        raise FigureError(f"the ablation overlays train for different numbers of steps: {sorted(ablation)}")
    ablation_steps = ablation.pop()
    hours = step / 3600
    return {"step_seconds": step, "steps": steps, "hours": steps * hours, "ablation_steps": ablation_steps,
            "ablation_hours": ablation_steps * hours, "ablation_rows": len(rows),
            "ablation_rows_hours": len(rows) * ablation_steps * hours}  # fmt: skip


GPU_STEP_GOAL = 0.25  # the target seconds per `aesplat fit -c conf/re10k.yaml` step on one H100


def _gpu_run() -> dict:
    """A computed source: docs/results/gpu/summary.json (``scripts/gpu_results.py``, the last GPU run) and what
    the GPU page reads from it: the step at the fewest context views against ``GPU_STEP_GOAL`` (``over_goal``,
    a fraction), per further count of views (``more_views``, in the order of ``fits``) what it adds to the
    step (a fraction) and to the peak memory (GiB), and the peak memory at 6 views on the line through the
    fewest and most views measured (``six_views_gib``)."""
    run = json.loads((REPO / "docs" / "results" / "gpu" / "summary.json").read_text())
    if not run["fits"]:
        return run
    base, step, memory = run["fits"][0], "seconds per step (median)", "peak memory (GiB)"
    run["over_goal"] = base[step] / GPU_STEP_GOAL - 1
    run["goal"] = GPU_STEP_GOAL
    run["more_views"] = [{"context_views": f["context_views"], "time": f[step] / base[step] - 1,
                          "memory": f[memory] - base[memory]} for f in run["fits"][1:]]  # fmt: skip
    last = run["fits"][-1]
    if last["context_views"] != base["context_views"]:
        per_view = (last[memory] - base[memory]) / (last["context_views"] - base["context_views"])
        run["six_views_gib"] = base[memory] + per_view * (6 - base["context_views"])
    return run


# Named sources: the files (or computations over files) that pages quote. A page may also name a path.
SOURCES: dict[str, str | Callable[[], dict]] = {
    # `make demo DEMO_RESULTS=docs/results/demo`: today's demo figures, with date, commit, machine and load
    "demo": "docs/results/demo/demo.json",
    # the demo's pose-free stage over three data seeds (validation split and choices, docs/validation.md)
    "demo-seeds": _seeds("docs/results/curves/validation-choice/ws1536-lr5e-5*.csv"),
    "demo-config": "conf/demo.yaml",
    "re10k-config": "conf/re10k.yaml",
    "pyproject": "pyproject.toml",
    "makefile": "Makefile",  # its variables, and the torch / torchvision its venv pins (torch_pin)
    # python benchmarks/bench_render.py --repeats 7 --compile --sections reference --json (this file)
    "rasterizer": "docs/results/rasterizer/reference.json",
    # python benchmarks/nas3r_parity.py --out (this file): this project's network against NAS3R's own code
    "nas3r-parity": "docs/results/nas3r/parity.json",
    "ablation": "docs/results/ablation/table.csv",
    "gpu-step": "docs/results/gpu-training-step.md",  # the record of the H100 measurement at 4c63102
    "gpu-run": _gpu_run,  # the last GPU run (scripts/gpu_results.py), with its derived figures
    "paper-scale": _paper_scale,
}

MARKER = re.compile(
    r"<!--\s*fig\s+(?P<source>[^\s:]+):(?P<key>[^|]*?)\s*(?:\|\s*(?P<format>\S+)\s*)?-->"
    r"(?P<text>.*?)<!--\s*/fig\s*-->",
    re.DOTALL,
)
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


class FigureError(Exception):
    """A source or key that cannot be read."""


# ---------------------------------------------------------------------------------------------------
# Reading sources


def _csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


_MARKUP = re.compile(r"\*\*|__|`|\[([^\]]*)\]\([^)]*\)")


def _plain(cell: str) -> str:
    """A table cell without emphasis, code marks and links (a link keeps its text)."""
    return _MARKUP.sub(lambda m: m.group(1) or "", cell).strip()


def _markdown_tables(path: Path) -> list[dict]:
    """The rows of every table of a markdown page, each a mapping of its table's header cells to its cells."""
    rows, header, fenced = [], None, False
    for line in path.read_text().splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        stripped = line.strip()
        if fenced or not (stripped.startswith("|") and stripped.endswith("|")):
            header = None
            continue
        cells = [_plain(c) for c in re.split(r"(?<!\\)\|", stripped[1:-1])]
        if header is None:
            header = cells
        elif not all(re.fullmatch(r":?-+:?", c) for c in cells):
            rows.append(dict(zip(header, cells)))
    return rows


def _make_variables(path: Path) -> dict:
    """A Makefile's variables (``NAME ?= value``, ``NAME := value``, ``NAME = value``; comments dropped), and
    ``torch_pin`` / ``torchvision_pin``: the versions its venv recipe pins (``"torch==2.14.1"``)."""
    text = path.read_text()
    assignment = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*[?:]?=\s*(.*)$", re.MULTILINE)
    found = {m.group(1): m.group(2).split("#")[0].strip() for m in assignment.finditer(text)}
    for name, version in re.findall(r'"(torch|torchvision)==([^"]+)"', text):
        found.setdefault(f"{name}_pin", version)
    return found


@cache
def load(source: str) -> object:
    """The data of a named source or a file from the repository root."""
    entry = SOURCES.get(source, source)
    if callable(entry):
        return entry()
    path = REPO / entry
    if not path.is_file():
        if source not in SOURCES and "/" not in source and "." not in source:
            raise FigureError(f"no source named '{source}' in scripts/figures.py SOURCES, and no such file")
        raise FigureError(f"{entry} does not exist (the command that measures it writes it)")
    suffix = path.suffix.lower()
    if suffix == ".json":
        return json.loads(path.read_text())
    if suffix in (".yaml", ".yml"):
        return yaml.safe_load(path.read_text())
    if suffix == ".toml":
        if tomllib is None:
            raise FigureError(f"{entry}: reading TOML needs Python 3.11 or later")
        return tomllib.loads(path.read_text())
    if suffix == ".csv":
        return _csv(path)
    if suffix == ".md":
        return _markdown_tables(path)
    if path.name == "Makefile":
        return _make_variables(path)
    raise FigureError(f"{entry}: no reader for {suffix} files")


_TOKEN = re.compile(r"\[([^\]]*)\]|([^.\[\]]+)")


def _requirement(items: list, name: str) -> str | None:
    for item in items:
        if isinstance(item, str):
            match = re.match(r"\s*([A-Za-z0-9_.-]+)\s*(.*)", item)
            if match and match.group(1).lower() == name.lower():
                return match.group(2).split(";")[0].strip()
    return None


def _same(cell: object, wanted: str) -> bool:
    text = _plain(str(cell))
    if text == wanted or text.split(" (")[0] == wanted:
        return True
    try:
        return float(text) == float(wanted)
    except ValueError:
        return False


def lookup(data: object, key: str) -> object:
    """The value at ``key`` in ``data`` (see the module's docstring for the key syntax)."""
    value = data
    for match in _TOKEN.finditer(key.strip()):
        selector, name = match.group(1), match.group(2)
        if name is not None:
            name = name.strip()
            if not isinstance(value, dict) or name not in value:
                raise FigureError(f"no '{name}' in {_describe(value)}")
            value = value[name]
            continue
        if not isinstance(value, list):
            raise FigureError(f"[{selector}] needs a list, found {_describe(value)}")
        selector = selector.strip()
        if re.fullmatch(r"-?\d+", selector):
            try:
                value = value[int(selector)]
            except IndexError:
                raise FigureError(f"[{selector}]: the list has {len(value)} elements") from None
        elif "=" in selector:
            wanted = [tuple(s.strip() for s in part.split("=", 1)) for part in selector.split(",")]
            rows = [
                r for r in value if isinstance(r, dict) and all(f in r and _same(r[f], v) for f, v in wanted)
            ]
            if not rows:
                raise FigureError(f"no row with {selector}")
            value = rows[0]
        else:
            found = _requirement(value, selector)
            if found is None:
                raise FigureError(f"no requirement '{selector}' in the list")
            value = found
    return value


def _describe(value: object) -> str:
    if isinstance(value, dict):
        keys = list(value)
        return "a mapping with " + ", ".join(map(str, keys[:12])) + (" …" if len(keys) > 12 else "")
    return f"{type(value).__name__} {str(value)[:40]!r}"


# ---------------------------------------------------------------------------------------------------
# Formatting and comparing


def _duration(seconds: object) -> str:
    total = round(float(seconds))
    hours, rest = divmod(total, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours} h {minutes} min" if minutes else f"{hours} h"
    if minutes:
        return f"{minutes} min {secs} s" if secs else f"{minutes} min"
    return f"{secs} s"


def _date(value: object) -> str:
    return datetime.fromisoformat(str(value).replace("Z", "+00:00")).strftime("%Y-%m-%d")


def _floor(value: object) -> str:
    match = re.search(r">=\s*([0-9][0-9A-Za-z.+]*)", str(value))
    if not match:
        raise FigureError(f"{value!r} has no >= bound")
    return match.group(1)


FORMATS: dict[str, Callable[[object], str]] = {"duration": _duration, "date": _date, "floor": _floor}


def formatted(value: object, spec: str) -> str:
    if spec in FORMATS:
        return FORMATS[spec](value)
    try:
        number = _number(value)
        return format(int(number) if spec.endswith("d") and number.is_integer() else number, spec)
    except (TypeError, ValueError) as error:
        raise FigureError(f"cannot format {value!r} with '{spec}': {error}") from None


def _number(value: object) -> float:
    """The value as a number: a number, or text that starts with one ("0.377 (13 % slower)")."""
    if isinstance(value, bool):
        raise TypeError("a boolean is not a figure")
    if isinstance(value, int | float):
        return float(value)
    text = str(value).strip().replace("−", "-").replace(",", "")
    match = NUMBER.match(text)
    rest = text[match.end() :] if match else ""
    if not match or rest[:1].isalnum() or rest[:1] == "_":  # "1976cb4" is a commit, not 1976
        raise ValueError(f"{value!r} is not a number")
    return float(match.group(0))


def _page_number(text: str) -> tuple[float, int] | None:
    """(number, decimals) of a page's figure text, or None when it is not a plain number."""
    plain = text.strip().strip("*").replace("−", "-").replace(",", "").replace("\u202f", "")
    if not NUMBER.fullmatch(plain):
        return None
    decimals = len(plain.split(".")[1]) if "." in plain and "e" not in plain.lower() else 0
    return float(plain), (-1 if "e" in plain.lower() else decimals)


def _rounded(value: float, decimals: int) -> float:
    return float(Decimal(repr(value)).quantize(Decimal(1).scaleb(-decimals), rounding=ROUND_HALF_UP))


def expected_text(value: object, spec: str | None, page_text: str) -> str:
    """What the page should say for ``value``: formatted by ``spec``, else in the page's own precision,
    grouping, sign and emphasis."""
    if spec:
        return formatted(value, spec)
    page = _page_number(page_text)
    try:
        source = _number(value)
    except (TypeError, ValueError):
        source = None
    if page is None or source is None or not math.isfinite(source):
        return str(value)
    decimals = page[1]
    if decimals < 0:  # scientific notation, in the page's style: 5e-5, 2.5e-4
        mantissa = page_text.strip().strip("*").lower().split("e")[0]
        digits = len(mantissa.split(".")[1]) if "." in mantissa else 0
        return re.sub(r"e([-+])0*(\d)", lambda m: f"e{m.group(1).replace('+', '')}{m.group(2)}",
                      f"{source:.{digits}e}")  # fmt: skip
    core = page_text.strip()
    body = f"{_rounded(source, decimals):{',' if ',' in core else ''}.{decimals}f}"
    if body.startswith("-") and "−" in core:
        body = "−" + body[1:]
    if core.strip("*").startswith("+") and not body.startswith("-"):
        body = "+" + body
    return f"**{body}**" if core.startswith("**") else body


def agrees(value: object, spec: str | None, page_text: str) -> bool:
    page_text = " ".join(page_text.split())  # a figure may wrap across lines
    if spec:
        return page_text.strip().replace("−", "-") == formatted(value, spec).replace("−", "-")
    page = _page_number(page_text)
    if page is None:
        return page_text.strip() == str(value).strip()
    number, decimals = page
    try:
        source = _number(value)
    except (TypeError, ValueError):
        return False
    if not math.isfinite(source):
        return False
    if decimals < 0:
        return math.isclose(number, source, rel_tol=1e-9)
    return _rounded(source, decimals) == _rounded(number, decimals)


# ---------------------------------------------------------------------------------------------------
# Pages


@dataclass(frozen=True)
class Figure:
    page: str
    line: int
    source: str
    key: str
    spec: str | None
    text: str
    start: int
    end: int  # span of the text between the comments
    outer: tuple[int, int]  # span of the comments and the text


_CODE = re.compile(r"^\s*```.*?^\s*```|``[^\n]*?``|`[^`\n]*`", re.DOTALL | re.MULTILINE)


def _without_code(text: str) -> str:
    """``text`` with code blocks and spans blanked out (same length): a marker shown as an example is none."""
    return _CODE.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text)


def figures(text: str, page: str = "") -> Iterator[Figure]:
    for m in MARKER.finditer(_without_code(text)):
        yield Figure(page, text.count("\n", 0, m.start()) + 1, m.group("source"), m.group("key").strip(),
                     m.group("format"), text[m.start("text") : m.end("text")], m.start("text"), m.end("text"),
                     m.span())  # fmt: skip


def problems(text: str, page: str = "") -> list[str]:
    """One line per figure of ``text`` that disagrees with its source or whose source cannot be read."""
    out = []
    for fig in figures(text, page):
        where = f"{page}:{fig.line}" if page else f"line {fig.line}"
        try:
            value = lookup(load(fig.source), fig.key)
            if agrees(value, fig.spec, fig.text):
                continue
            want = expected_text(value, fig.spec, fig.text)
            out.append(f"{where}: the page says {fig.text.strip()!r}, {fig.source}:{fig.key} holds {value!r} "
                       f"(write {want!r}, or run `python scripts/figures.py --write`)")  # fmt: skip
        except FigureError as error:
            out.append(f"{where}: {fig.source}:{fig.key}: {error}")
    open_marks = len(re.findall(r"<!--\s*fig\s", _without_code(text)))
    found = sum(1 for _ in figures(text))
    if open_marks != found:
        out.append(f"{page or 'the page'}: {open_marks - found} figure comment(s) without a matching "
                   "<!-- /fig --> or with no SOURCE:KEY")  # fmt: skip
    return out


def strip(text: str) -> str:
    """The page with each figure's comments removed, its text kept (what the site shows)."""
    pieces, last = [], 0
    for fig in figures(text):
        pieces += [text[last : fig.outer[0]], fig.text]
        last = fig.outer[1]
    return "".join(pieces) + text[last:]


def rewrite(text: str) -> str:
    """The page with every figure that disagrees with its source replaced by the source's value, in the
    page's precision, style or format (a figure that agrees is left as the page writes it)."""
    pieces, last = [], 0
    for fig in figures(text):
        value = lookup(load(fig.source), fig.key)
        new = fig.text if agrees(value, fig.spec, fig.text) else expected_text(value, fig.spec, fig.text)
        pieces += [text[last : fig.start], new]
        last = fig.end
    return "".join(pieces) + text[last:]


def pages() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pages", nargs="*", type=Path, help="pages to check (default: README.md and docs/)")
    action = parser.add_mutually_exclusive_group()
    action.add_argument("--write", action="store_true", help="rewrite the pages' figures from their sources")
    action.add_argument("--list", action="store_true", help="list every figure with its source's value")
    args = parser.parse_args(argv)
    found = []
    for path in [p.resolve() for p in args.pages] or pages():
        name = path.relative_to(REPO).as_posix() if path.is_relative_to(REPO) else str(path)
        text = path.read_text()
        if args.write:
            new = rewrite(text)
            if new != text:
                path.write_text(new)
                print(f"rewrote {name}")
        elif args.list:
            for fig in figures(text, name):
                try:
                    value = lookup(load(fig.source), fig.key)
                except FigureError as error:
                    value = f"({error})"
                print(f"{name}:{fig.line}\t{fig.source}:{fig.key}\t{fig.text.strip()}\t{value!r}")
        else:
            found += problems(text, name)
    for line in found:
        print(line, file=sys.stderr)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
