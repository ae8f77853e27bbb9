"""scripts/code_map.py: the layering rules hold on this tree, and the checker sees a break of each."""

import json
import textwrap
from pathlib import Path

import pytest

from tests.script_loader import load_script


@pytest.fixture(scope="module")
def code_map():
    return load_script("code_map")


def test_no_room_imports_in_a_circle_and_no_test_module_imports_another(code_map):
    now = code_map.measure(code_map.REPO)
    assert now["room_circles"] == []
    assert now["tests_importing_tests"] == []


def write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))


def test_an_import_back_up_a_floor_is_a_circle_of_rooms(code_map, tmp_path):
    write(tmp_path, {
        "src/aesplat/__init__.py": "",
        "src/aesplat/errors.py": "",
        "src/aesplat/checkpoint.py": "from aesplat.train import loop\nfrom . import errors\n",
        "src/aesplat/train/__init__.py": "",
        "src/aesplat/train/loop.py": "def f():\n    from ..checkpoint import RECORD\n",
        "src/aesplat/cli.py": "from aesplat import checkpoint, train\n",
    })  # fmt: skip
    assert code_map.room_circles(tmp_path) == [["checkpoint", "train"]]
    write(tmp_path, {"src/aesplat/train/loop.py": "from ..errors import UserError\n"})
    assert code_map.room_circles(tmp_path) == []


def test_a_test_module_importing_a_test_module_is_found_and_a_helpers_module_is_not(code_map, tmp_path):
    write(tmp_path, {
        "tests/__init__.py": "",
        "tests/helpers.py": "",
        "tests/test_a.py": "from tests.helpers import build\n",
        "tests/train/__init__.py": "",
        "tests/train/test_b.py": "from tests.test_a import make\nfrom ..helpers import build\n",
        "tests/test_c.py": "CONFIG = 'callbacks:\\n  - class_path: tests.train.test_b.Stop\\n'\n",
    })  # fmt: skip
    assert code_map.tests_importing_tests(tmp_path) == [
        "tests/test_c.py -> tests.train.test_b",
        "tests/train/test_b.py -> tests.test_a",
    ]


def test_the_page_figures_come_from_the_json_it_writes(code_map, tmp_path):
    out = tmp_path / "code_map.json"
    assert code_map.main(["--out", str(out)]) == 0
    record = json.loads(out.read_text())
    src = sorted((code_map.REPO / "src" / "aesplat").rglob("*.py"))
    assert record["now"]["files"]["src"] == len(src)
    assert record["now"]["lines"]["src"] == sum(len(p.read_text().splitlines()) for p in src)
    assert "commit" in record["provenance"]
