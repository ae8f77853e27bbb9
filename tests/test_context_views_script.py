"""benchmarks/context_views.py: its k-view evaluation index and its statistics (the runs themselves are the
demo's training and `aesplat bench`'s measurements, tested where they live)."""

import importlib.util
import math
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _script():
    spec = importlib.util.spec_from_file_location("context_views", BENCHMARKS / "context_views.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


def test_k_view_index_adds_context_frames_between_the_pair_and_never_a_target():
    script = _script()
    index = {
        "a": {"context": [4, 16], "target": [7, 10, 13], "overlap": 0.5},
        "b": {"context": [0, 5], "target": [1, 2, 3], "overlap": 0.4},  # one free frame: too few for 4 views
        "c": None,
    }
    wide = script.k_view_index(index, {"a": 32, "b": 32, "c": 32}, views=4)
    assert set(wide) == {"a"}
    entry = wide["a"]
    assert entry["context"][:2] == [4, 16] and entry["target"] == [7, 10, 13] and entry["overlap"] == 0.5
    extra = entry["context"][2:]
    assert extra == [8, 12]  # nearest free frames to 8 and 12 (neither a target)
    assert not set(extra) & set(entry["target"]) and len(set(entry["context"])) == 4
    assert script.k_view_index(index, {"a": 32, "b": 32, "c": 32}, views=3)["b"]["context"] == [0, 5, 4]


def test_summary_pairs_pool_and_concat_by_seed():
    script = _script()
    settings = script.Settings(config="c", scene_args="", size=42, steps=1, train_views=(2, 4),
                               eval_views=(2, 3), test_scenes=4, repeats=1, extra=())  # fmt: skip

    def saved(rows):
        rows = [{"context_views": k, "scenes": 4, "psnr": p, "rot_err_deg": 1.0, "forward_ms": 10.0,
                 "render_ms": 5.0} for k, p in rows]  # fmt: skip
        return {"fit_seconds": 1.0, "rows": rows}

    results = {
        script.Run("pool", 0): saved([(2, 20.0), (3, 21.0)]),
        script.Run("pool", 1): saved([(2, 22.0), (3, 23.0)]),
        script.Run("concat", 0): saved([(2, 21.0)]),
        script.Run("concat", 1): saved([(2, 22.0)]),
        script.Run("concat", 2): saved([(2, 40.0)]),  # no pool run of seed 2: left out of the pairs
    }
    lines = {(x["model"], x["context_views"]): x for x in script.summary_rows(results, settings)}
    assert lines[("pool", 3)]["n"] == 2 and lines[("pool", 3)]["psnr"] == 22.0
    assert lines[("concat", 2)]["n"] == 3
    diff = lines[("pool - concat", 2)]
    assert diff["n"] == 2 and diff["psnr"] == pytest.approx(-0.5)  # (20 - 21 + 22 - 22) / 2
    assert math.isfinite(diff["psnr_ci"]) and diff["forward_ms"] == 0.0
