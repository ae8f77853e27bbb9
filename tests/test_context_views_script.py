"""benchmarks/context_views.py: its statistics, its check that every count rendered the same targets and the
warm start without an appearance head (the runs themselves are `aesplat fit`, `aesplat test` and `aesplat
bench`, tested where they live)."""

import importlib.util
import math
import sys
from pathlib import Path

import pytest
import torch
import yaml

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _script():
    spec = importlib.util.spec_from_file_location("context_views", BENCHMARKS / "context_views.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


def _settings(script, **changes):
    fields = {"config": "c", "scene_args": "", "size": 42, "steps": 1, "train_views": (2, 4),
              "eval_views": (2, 3), "repeats": 1, "extra": ()}  # fmt: skip
    return script.Settings(**{**fields, **changes})


def _saved(rows, targets=None):
    frames = {"a": {"context": "0 9", "target": targets or "3 6"}}
    rows = [{"context_views": k, "scenes": 1, "psnr": p, "rot_err_deg": 1.0, "forward_ms": 10.0 * k,
             "render_ms": 5.0, "ssim": 0.5, "trans_err_deg": 2.0, "frames": frames}
            for k, p in rows]  # fmt: skip
    return {"fit_seconds": 1.0, "rows": rows}


def test_summary_pairs_the_models_and_the_counts_by_seed():
    script = _script()
    run = script.Run
    results = {
        run("pool", 0): _saved([(2, 20.0), (3, 21.0)]),
        run("pool", 1): _saved([(2, 22.0), (3, 23.5)]),
        run("concat", 0): _saved([(2, 21.0)]),
        run("concat", 1): _saved([(2, 22.0)]),
        run("concat", 2): _saved([(2, 40.0)]),  # no pool run of seed 2: left out of the pairs
        run("concat_fresh", 1): _saved([(2, 21.0)]),
    }
    lines = {(x["model"], x["context_views"]): x for x in script.summary_rows(results, _settings(script))}
    assert lines[("`pool`", "3")]["n"] == 2 and lines[("`pool`", "3")]["psnr"] == 22.25
    assert lines[("`concat`", "2")]["n"] == 3
    diff = lines[("`pool` − `concat`", "2")]
    assert diff["n"] == 2 and diff["psnr"] == pytest.approx(-0.5)  # (20 - 21 + 22 - 22) / 2
    assert math.isfinite(diff["psnr_ci"]) and diff["forward_ms"] == 0.0
    fresh = lines[("`pool` − `concat`, fresh head", "2")]
    assert fresh["n"] == 1 and fresh["psnr"] == 1.0 and math.isnan(fresh["psnr_ci"])
    more = lines[("`pool`", "3 − 2")]  # what the third view buys: 1.0 and 1.5 dB
    assert more["n"] == 2 and more["psnr"] == 1.25 and more["forward_ms"] == 10.0


def test_counts_that_rendered_other_targets_stop_the_report():
    script = _script()
    same = {script.Run("pool", 0): _saved([(2, 20.0), (3, 21.0)]), script.Run("concat", 0): _saved([(2, 21.0)])}
    assert script.same_targets(same) == {"a": "3 6"}
    other = {**same, script.Run("concat", 1): _saved([(2, 21.0)], targets="3 7")}
    with pytest.raises(SystemExit, match="not comparable"):
        script.same_targets(other)


def test_fresh_head_weights_drop_the_appearance_tensors_only(tmp_path):
    script = _script()
    state = {"model.appearance.gvsre.mlp.0.weight": torch.ones(2), "model.encoder.w": torch.zeros(3)}
    torch.save({"state_dict": state, "hyper_parameters": {"net": {}}, "note": "n"}, tmp_path / "warm.pt")
    config = tmp_path / "c.yaml"
    config.write_text(yaml.safe_dump({"model": {"net": {"weights": str(tmp_path / "warm.pt")}}}))
    out = script.fresh_head_weights(tmp_path / "work", _settings(script, config=str(config)))
    saved = torch.load(out, weights_only=True)
    assert list(saved["state_dict"]) == ["model.encoder.w"] and saved["hyper_parameters"] == {"net": {}}
