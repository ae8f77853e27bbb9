"""benchmarks/pose_probe.py: the supervised relative-pose probe, on the smoke shards."""

import csv
import math

from ..script_loader import load_benchmark


def _probe():
    return load_benchmark("pose_probe")


def test_probe_trains_each_variant_and_scores_the_test_views(smoke_shards, tmp_path):
    out = tmp_path / "probe"
    _probe().main(["--data", str(smoke_shards.parent), "--size", "28", "--steps", "3", "--every", "2",
                   "--batch", "2", "--out", str(out)])  # fmt: skip
    for variant in ("head", "head-correlation", "stacked-cnn"):
        with open(out / f"{variant}.csv") as f:
            rows = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
        assert [r["step"] for r in rows] == [0, 2, 3]
        assert all(math.isfinite(r["test_rot_deg"]) for r in rows)
        assert math.isnan(rows[0]["train_rot_deg"]) and all(math.isfinite(r["train_rot_deg"]) for r in rows[1:])
        assert rows[0]["seconds"] == 0 < rows[1]["seconds"] < rows[2]["seconds"]
        assert rows[0]["no_rotation_deg"] > 0
    with open(out / "stacked-cnn.csv") as f:
        cnn = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
    # Its pose layers start at zero weights and the identity bias: it predicts no rotation, which scores the
    # true angles themselves; training moves it off that.
    assert math.isclose(cnn[0]["test_rot_deg"], cnn[0]["no_rotation_deg"], rel_tol=1e-5)
    assert cnn[-1]["test_rot_deg"] != cnn[0]["test_rot_deg"]
    table = (out / "PROBE.md").read_text()
    assert all(f"| {v} |" in table for v in ("head", "head-correlation", "stacked-cnn"))
