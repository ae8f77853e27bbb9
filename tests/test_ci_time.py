"""scripts/ci_time.py: what it reads from the log of `.ci/run` (running CI itself is the command's job)."""

import pytest

from tests.script_loader import load_script

LOG = """\
.venv/bin/python -m pytest -q -m "not slow"
........................................................................ [ 93%]
=========================== short test summary info ============================
SKIPPED [1] tests/test_bench.py:268: needs CUDA
840 passed, 5 skipped, 4 deselected, 221 warnings in 327.07s (0:05:27)
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict
INFO    -  Documentation built in 4.99 seconds
.venv-torch-floor/bin/python -m pytest -q -m "not slow and not slurm" tests/geometry
354 passed, 3 skipped, 7 deselected, 194 warnings in 82.64s (0:01:22)
"""


@pytest.fixture(scope="module")
def ci_time():
    return load_script("ci_time")


def test_each_leg_is_the_summary_pytest_printed_in_order(ci_time):
    legs = ci_time.pytest_legs(LOG)
    assert legs == {
        "make test": {"passed": 840, "skipped": 5, "seconds": 327.07},
        "make test-torch-floor": {"passed": 354, "skipped": 3, "seconds": 82.64},
    }


def test_a_failed_test_or_a_missing_leg_is_an_error(ci_time):
    failed = LOG.replace("840 passed, 5 skipped", "1 failed, 839 passed, 5 skipped")
    with pytest.raises(ci_time.CIError, match="tests failed: 1 failed, 839 passed"):
        ci_time.pytest_legs(failed)
    one_leg = "\n".join(line for line in LOG.splitlines() if not line.startswith("354 passed"))
    with pytest.raises(ci_time.CIError, match="expected 2 pytest summaries .* found 1"):
        ci_time.pytest_legs(one_leg)
