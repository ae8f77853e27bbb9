"""benchmarks/context_views.py: its statistics, its check that every count rendered the same targets and the
warm start without an appearance head (the runs themselves are `aesplat fit`, `aesplat test` and `aesplat
bench`, tested where they live); benchmarks/context_view_cost.py: its count of the paper network's work per
count of context views, its table and its resumption."""

import json
import math

import pytest
import torch
import yaml

from tests.script_loader import load_benchmark


def _script():
    return load_benchmark("context_views")


def _settings(script, **changes):
    fields = {"config": "c", "scene_args": "", "size": 42, "steps": 1, "train_views": (2, 4),
              "eval_views": (2, 3), "repeats": 1, "extra": ()}  # fmt: skip
    return script.Settings(**{**fields, **changes})


def _saved(rows, targets=None):
    frames = {"a": {"context": "0 9", "target": targets or "3 6"}}
    rows = [{"context_views": k, "scenes": 1, "psnr": p, "rot_err_deg": 1.0, "forward_ms": 10.0 * k,
             "render_ms": 5.0, "ssim": 0.5, "trans_err_deg": 2.0, "rot_err_target_deg": 1.5,
             "trans_err_target_deg": 2.5, "frames": frames} for k, p in rows]  # fmt: skip
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
        run("pool_2", 1): _saved([(2, 20.0), (3, 23.0)]),
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
    assert more["n"] == 2 and more["psnr"] == 1.25 and more["forward_ms"] == 10.0 and more["id"] == "pool@3-2"
    head = lines[("`pool`, trained with 2 − `concat`, fresh head", "2")]  # the head alone: 20 - 21
    assert head["n"] == 1 and head["psnr"] == -1.0 and head["id"] == "pool_2-concat_fresh@2"
    ranged = lines[("`pool` − `pool`, trained with 2", "3")]  # seed 1: 23.5 - 23
    assert ranged["n"] == 1 and ranged["psnr"] == 0.5 and lines[("`pool`, trained with 2", "3")]["n"] == 1


def test_a_run_evaluated_before_a_metric_was_added_is_evaluated_again():
    script = _script()
    saved = _saved([(2, 20.0)])
    assert script.complete(saved)
    del saved["rows"][0]["rot_err_target_deg"]
    assert not script.complete(saved)


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


# ----------------------------------------------------------------------------------------------- cost per count


def test_cost_counts_the_paper_network_per_count_and_resumes_its_measurements(tmp_path, monkeypatch):
    from tests.script_loader import load_benchmark

    cost = load_benchmark("context_view_cost")
    calls = []

    def measure(size, count, steps, warmup):  # a stand-in for one bench_train_step process
        calls.append((size, count))
        return {"size": size, "context_views": count, "seconds_per_step": 0.1 * count, "peak_gib": 1.0 + count,
                "before_fit_gib": 1.0, "threads": 1, "batch_size": 2, "steps": steps, "warmup": warmup,
                "load_1min": 0.0}  # fmt: skip

    monkeypatch.setattr(cost, "measure", measure)
    argv = ["--counts", "2", "3", "--sizes", "42", "--steps", "2", "--warmup", "0", "--out", str(tmp_path)]
    cost.main(argv)
    record = json.loads((tmp_path / "cost.json").read_text())
    assert calls == [(42, 2), (42, 3)] and record["meta"]["commit"]
    two, three = record["computed"]
    # The paper's network at 224²: 16 x 16 patches + a camera token + 4 registers per view; one target view.
    assert two["tokens_per_view"] == 261 and three["global_tokens"] == 4 * 261
    assert three["gaussians"] == 3 * 224 * 224 and three["pool_pairs"] == 9 * 224 * 224
    # The pool head's per-pair MLPs (relation: 5 -> 32 -> 32, colour: 10 -> 32 -> 32) at batch 10: 2 views
    # give 4 relation and 2 colour pairs per pixel, 3 views 9 and 6.
    assert two["pool_saved_gib"] == pytest.approx(4 * 10 * 224**2 * (4 * 69 + 2 * 74) / 2**30)
    assert three["pool_saved_gib"] == pytest.approx(4 * 10 * 224**2 * (9 * 69 + 6 * 74) / 2**30)
    # One more view: the encoder grows with the views (3 -> 4), attention faster than the tokens.
    assert three["encoder_gflops"] / two["encoder_gflops"] == pytest.approx(4 / 3, rel=0.01)
    assert three["attention_gflops"] / two["attention_gflops"] > 1.5
    parts = ("encoder", "attention", "transformer_other", "heads", "appearance")
    assert sum(three[f"{p}_gflops"] for p in parts) == pytest.approx(three["gflops"], rel=0.01)
    table = (tmp_path / "cost.md").read_text()
    assert "| 42 | 3 | 0.300 | 1.50 | 4.00 | 3.000 |" in table and "| 3 | 1,044 | 150,528 |" in table
    calls.clear()
    cost.main(argv)  # everything measured already: nothing runs again
    assert calls == []
