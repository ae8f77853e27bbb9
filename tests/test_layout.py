"""The layout of the test suite: test modules share helpers through conftest.py and helper modules, never by
importing one another (a test module imported elsewhere runs its tests twice and hides what depends on it)."""

import ast
import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent
# A Lightning callback named by its class path in a config the test writes: imported by the command it runs.
CLASS_PATH = re.compile(r"class_path:\s*([\w.]+)")


def is_test_module(dotted: str) -> bool:
    return dotted.rsplit(".", 1)[-1].startswith("test_")


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, dotted module) of every module ``path`` imports, relative imports resolved, ``from a import b``
    counted as ``a.b`` too (``b`` may be a module), and class paths in the strings it holds."""
    package = ".".join(path.relative_to(TESTS.parent).parent.parts)
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, *([base] if base else [])])
            found += [(node.lineno, base)] + [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            found += [(node.lineno, name.rsplit(".", 1)[0]) for name in CLASS_PATH.findall(node.value)]
    return found


def test_no_test_module_imports_another_test_module():
    offenders = [
        f"{path.relative_to(TESTS.parent)}:{line}: {module}"
        for path in sorted(TESTS.rglob("*.py"))
        for line, module in imported_modules(path)
        if module.startswith("tests.") and is_test_module(module)
    ]
    assert not offenders, "move what they share to conftest.py or a helper module:\n" + "\n".join(offenders)
