#!/usr/bin/env python
"""The figures of the architecture page (docs/architecture.md), measured from the code of a checkout.

For the tree of this checkout and, with ``--before REV``, for the tree of an earlier commit (read with
``git archive``, nothing checked out):

- lines and files of Python in src/aesplat, benchmarks/, scripts/ and tests/;
- the rooms of the package (each sub-package of ``aesplat`` and each of its top-level modules) that import
  each other in a circle: an import that runs back up a floor makes one;
- the test modules that import another test module (``test_*.py``), which the suite's shared modules
  (``tests/helpers.py`` and the like) are there to prevent;
- the rooms by floor (``map.md``): a room is one floor above the highest room it imports.

    python scripts/code_map.py --before 21adc7c   # docs/results/architecture/code_map.json and map.md
    python scripts/code_map.py --check                       # exit 1 on a circle or a test importing a test

tests/test_code_map.py holds the rules of ``--check`` on the current tree.
"""

from __future__ import annotations

import argparse
import ast
import io
import json
import re
import subprocess
import sys
import tarfile
import tempfile
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
AREAS = {"src": "src/aesplat", "benchmarks": "benchmarks", "scripts": "scripts", "tests": "tests"}
OUT = REPO / "docs" / "results" / "architecture" / "code_map.json"
# A class named by its path in a config a file writes (a Lightning callback): the command it runs imports it.
CLASS_PATH = re.compile(r"class_path:\s*([\w.]+)\.\w+")


def python_files(root: Path, area: str) -> list[Path]:
    return sorted(p for p in (root / area).rglob("*.py") if "__pycache__" not in p.parts)


def lines(files: list[Path]) -> int:
    return sum(len(p.read_text(encoding="utf-8").splitlines()) for p in files)


def module_name(path: Path, package_root: Path) -> str:
    parts = list(path.relative_to(package_root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(path: Path, name: str) -> set[str]:
    """Every module an ``import`` or ``from … import`` of the file names (inside functions too), absolute, and
    the modules of the class paths in its strings."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            found.update(CLASS_PATH.findall(node.value))
    return found


def room_of(module: str) -> str | None:
    """``aesplat.data.stream`` -> ``data``; ``aesplat.cli`` -> ``cli``; anything outside aesplat -> None."""
    parts = module.split(".")
    return parts[1] if parts[0] == "aesplat" and len(parts) > 1 else None


def is_room(root: Path, room: str | None) -> bool:
    package = root / AREAS["src"]
    return bool(room) and ((package / room).is_dir() or (package / f"{room}.py").is_file())


def room_imports(root: Path) -> dict[str, set[str]]:
    """Room -> the other rooms its files import."""
    package_root = root / "src"
    edges: dict[str, set[str]] = defaultdict(set)
    for path in python_files(root, AREAS["src"]):
        name = module_name(path, package_root)
        here = room_of(name)
        if not here:
            continue
        edges[here] |= {room_of(m) for m in imported_modules(path, name) if is_room(root, room_of(m))} - {here}
    return edges


def room_circles(root: Path) -> list[list[str]]:
    """The groups of rooms that import each other in a circle (strongly connected, more than one room)."""
    edges = room_imports(root)
    # Tarjan's strongly connected components over the room graph.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(room: str) -> None:
        index[room] = low[room] = len(index)
        stack.append(room)
        for other in sorted(edges[room]):
            if other not in index:
                visit(other)
                low[room] = min(low[room], low[other])
            elif other in stack:
                low[room] = min(low[room], index[other])
        if low[room] == index[room]:
            group = []
            while True:
                member = stack.pop()
                group.append(member)
                if member == room:
                    break
            if len(group) > 1:
                circles.append(sorted(group))

    for room in sorted(edges):
        if room not in index:
            visit(room)
    return sorted(circles)


def floors(root: Path) -> dict[str, int]:
    """Each room's floor: 1 for a room that imports no other, else one above the highest room it imports
    (only defined without circles)."""
    edges = room_imports(root)
    floor: dict[str, int] = {}

    def of(room: str) -> int:
        if room not in floor:
            floor[room] = 1 + max((of(other) for other in edges[room]), default=0)
        return floor[room]

    for room in edges:
        of(room)
    return dict(sorted(floor.items(), key=lambda item: (-item[1], item[0])))


def room_lines(root: Path) -> dict[str, int]:
    counts: dict[str, int] = defaultdict(int)
    package = root / AREAS["src"]
    for path in python_files(root, AREAS["src"]):
        parts = path.relative_to(package).parts
        if len(parts) > 1 or parts[0] != "__init__.py":
            counts[parts[0].removesuffix(".py")] += len(path.read_text(encoding="utf-8").splitlines())
    return counts


def map_table(root: Path) -> str:
    """The rooms by floor, top down, as a markdown table (the architecture page includes it)."""
    lines, by_floor = room_lines(root), defaultdict(list)
    for room, floor in floors(root).items():
        folder = (root / AREAS["src"] / room).is_dir()
        by_floor[floor].append(f"`{room}/` ({lines[room]})" if folder else f"`{room}.py` ({lines[room]})")
    rows = [f"| {floor} | {', '.join(rooms)} |" for floor, rooms in sorted(by_floor.items(), reverse=True)]
    return "\n".join(["| floor | rooms (lines) |", "| ---: | --- |", *rows]) + "\n"


def tests_importing_tests(root: Path) -> list[str]:
    """``tests/a.py -> test_b`` for every test module that imports another test module."""
    found = []
    for path in python_files(root, AREAS["tests"]):
        name = module_name(path, root)
        for module in sorted(imported_modules(path, name)):
            last = module.rpartition(".")[2]
            if last.startswith("test_") and (root / Path(*module.split("."))).with_suffix(".py").is_file():
                found.append(f"{path.relative_to(root)} -> {module}")
    return found


def measure(root: Path) -> dict:
    areas = {area: python_files(root, folder) for area, folder in AREAS.items()}
    circles, test_imports = room_circles(root), tests_importing_tests(root)
    return {
        "lines": {area: lines(files) for area, files in areas.items()},
        "files": {area: len(files) for area, files in areas.items()},
        "room_circles": circles,
        "rooms_in_circles": sum(len(circle) for circle in circles),
        "tests_importing_tests": test_imports,
        "test_imports_of_tests": len(test_imports),
    }


def measure_commit(rev: str) -> dict:
    command = ["git", "archive", rev, *AREAS.values()]
    archive = subprocess.run(command, cwd=REPO, capture_output=True, check=True)
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
            tar.extractall(tmp, filter="data")
        return measure(Path(tmp))


def commit_of(rev: str) -> str:
    return subprocess.run(["git", "rev-parse", "--short", rev], cwd=REPO, capture_output=True, text=True,
                          check=True).stdout.strip()  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", metavar="REV", help="also measure this commit, for the before/after table")
    parser.add_argument("--out", type=Path, default=OUT, help="where the JSON goes")
    parser.add_argument("--check", action="store_true", help="only check the rules; write nothing")
    args = parser.parse_args(argv)
    now = measure(REPO)
    if args.check:
        problems = [f"rooms in a circle: {' <-> '.join(c)}" for c in now["room_circles"]]
        problems += [f"a test module imports a test module: {t}" for t in now["tests_importing_tests"]]
        print("\n".join(problems) or "code_map: no circle between rooms, no test module importing another")
        return 1 if problems else 0
    sys.path.insert(0, str(REPO / "benchmarks"))
    from common import provenance, write_whole

    record = {"provenance": provenance(), "now": now}
    if args.before:
        record["before"] = {"commit": commit_of(args.before), **measure_commit(args.before)}
    write_whole(args.out, (json.dumps(record, indent=1) + "\n").encode())
    table = args.out.with_name("map.md")
    write_whole(table, map_table(REPO).encode())
    print(f"code_map: wrote {args.out}, {table}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
