"""Import a file of ``scripts/``, ``benchmarks/`` or ``data_prep/`` (not packages) as a module, for the tests
of those files."""

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from tests.helpers import REPO

SCRIPTS = REPO / "scripts"
BENCHMARKS = REPO / "benchmarks"
DATA_PREP = REPO / "data_prep"


def load_script(name: str, folder: Path = SCRIPTS) -> ModuleType:
    """``<folder>/<name>.py`` (default ``scripts/``) as a fresh module, its folder on ``sys.path`` as when it
    runs as a script (the files beside it import each other by name)."""
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


def load_benchmark(name: str) -> ModuleType:
    """``benchmarks/<name>.py`` as a fresh module."""
    return load_script(name, BENCHMARKS)
