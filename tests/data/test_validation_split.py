"""The validation split: synthetic validation scenes from their own seed stream, training scenes held out by
`to_shards.py --val-scenes`, the DataModule validating on it, and choices made on its figures only."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import pytest
import torch

from aesplat.data import DataModule, convert_dataset, generate_dataset
from aesplat.data.convert import held_out_keys
from aesplat.data.pixelsplat_chunks import list_chunks, load_chunk
from aesplat.errors import UserError

from ..script_loader import load_benchmark, load_script

CURVE_COLUMNS = load_benchmark("curves").CURVE_COLUMNS

ROOT = Path(__file__).resolve().parents[2]
TINY = {"frames": 8, "height": 16, "width": 24, "seed": 3, "scenes_per_chunk": 2}


def _files(root: Path, split: str) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((root / split).iterdir())}


def test_validation_scenes_come_from_their_own_seeds_and_change_no_train_or_test_scene(tmp_path):
    without = generate_dataset(tmp_path / "a", scenes=3, test_scenes=3, val_scenes=0, **TINY)
    default = generate_dataset(tmp_path / "b", scenes=3, test_scenes=3, **TINY)
    more = generate_dataset(tmp_path / "c", scenes=3, test_scenes=3, val_scenes=2, **TINY)
    assert (without["validation_scenes"], default["validation_scenes"], more["validation_scenes"]) == (0, 1, 2)
    assert not (tmp_path / "a" / "validation").exists()
    assert not (tmp_path / "a" / "validation_index.json").exists()
    for other in ("b", "c"):  # train and test chunks and the test evaluation index: byte for byte the same
        for split in ("train", "test"):
            assert _files(tmp_path / other, split) == _files(tmp_path / "a", split)
        assert (tmp_path / other / "evaluation_index.json").read_bytes() == (
            tmp_path / "a" / "evaluation_index.json"
        ).read_bytes()
    val = [s for c in list_chunks(tmp_path / "c" / "validation") for s in load_chunk(c)]
    rest = [s for sp in ("train", "test") for c in list_chunks(tmp_path / "c" / sp) for s in load_chunk(c)]
    assert [s["key"] for s in val] == ["validation003_00000", "validation003_00001"]
    for scene in val:  # other scenes, not copies of a train or test scene
        assert not any(torch.equal(scene["cameras"], s["cameras"]) for s in rest)
    index = json.loads((tmp_path / "c" / "validation_index.json").read_text())
    assert sorted(index) == [s["key"] for s in val]
    assert all(index[k]["context"][0] < t < index[k]["context"][1] for k in index for t in index[k]["target"])
    with pytest.raises(ValueError, match="val_scenes"):
        generate_dataset(tmp_path / "d", scenes=1, val_scenes=-1, **TINY)


def test_synthetic_validation_split_converts_with_its_index_and_the_datamodule_validates_on_it(tmp_path):
    generate_dataset(tmp_path / "src", scenes=2, test_scenes=2, val_scenes=2, **TINY)
    manifest = convert_dataset(tmp_path / "src", tmp_path / "out", size=16, progress=False)
    entry = manifest["splits"]["validation"]
    assert entry["scenes"] == 2 and entry["samples"] == 2 and entry["evaluation_index_missing"] == 0
    assert manifest["validation_index"].endswith("validation_index.json")
    dm = DataModule(root=str(tmp_path / "out"), image_size=16, num_workers=0)
    assert dm.validation_split() == "validation"
    val_scenes = [s for b in dm.eval_dataset("val") for s in b.scene]
    test_scenes = [s for b in dm.eval_dataset("test") for s in b.scene]
    assert sorted(val_scenes) == ["validation003_00000", "validation003_00001"]
    assert sorted(test_scenes) == ["test003_00000", "test003_00001"]
    index = json.loads((tmp_path / "src" / "validation_index.json").read_text())
    batch = next(iter(dm.eval_dataset("val")))
    assert batch.target.index[0].tolist() == index[batch.scene[0]]["target"]


def test_without_a_validation_split_validation_is_refused_unless_the_test_split_is_asked_for(tmp_path, caplog):
    generate_dataset(tmp_path / "src", scenes=2, test_scenes=1, val_scenes=0, **TINY)
    convert_dataset(tmp_path / "src", tmp_path / "out", size=16, progress=False)
    dm = DataModule(root=str(tmp_path / "out"), image_size=16, num_workers=0)
    with pytest.raises(UserError) as err:
        dm.eval_dataset("val")
    message = str(err.value)
    assert "has no validation split" in message and "--val-scenes N" in message and "\n" not in message
    assert "--data.validate_on_test true" in message
    asked = DataModule(root=str(tmp_path / "out"), image_size=16, num_workers=0, validate_on_test=True)
    with caplog.at_level(logging.WARNING, logger="aesplat.data"):
        assert [s for b in asked.eval_dataset("val") for s in b.scene] == ["test003_00000"]
    assert "data.validate_on_test: validating on the TEST split" in caplog.text  # the logs name it


def test_aesplat_fit_without_a_validation_split_is_refused_before_anything_is_written(tmp_path):
    from aesplat import cli

    generate_dataset(tmp_path / "src", scenes=2, test_scenes=1, val_scenes=0, **TINY)
    convert_dataset(tmp_path / "src", tmp_path / "out", size=28, progress=False)
    run = tmp_path / "run"
    argv = [
        "fit",
        "-c",
        str(ROOT / "conf" / "smoke.yaml"),
        "--data.root",
        str(tmp_path / "out"),
        "--data.image_size",
        "28",
        "--data.validate_on_test",
        "false",
        "--trainer.default_root_dir",
        str(run),
    ]
    with pytest.raises(SystemExit) as verdict:  # SystemExit(message): printed on stderr, exit status 1
        cli.main(argv)
    err = str(verdict.value)
    assert err.startswith("aesplat fit: ") and "has no validation split" in err and "\n" not in err
    assert not run.exists()


def test_aesplat_validate_checks_the_split_it_validates_on(tmp_path):
    from aesplat import cli

    def validate(root, *more):
        argv = ["validate", "-c", str(ROOT / "conf" / "smoke.yaml"), "--data.root", str(root),
                "--trainer.default_root_dir", str(tmp_path / "run"), "--trainer.logger", "false",
                "--trainer.enable_progress_bar", "false", *more]  # fmt: skip
        return cli.main(argv)

    generate_dataset(tmp_path / "src", scenes=2, test_scenes=1, val_scenes=0, **TINY)
    convert_dataset(tmp_path / "src", tmp_path / "no_val", size=28, progress=False)
    with pytest.raises(SystemExit) as verdict:
        validate(tmp_path / "no_val", "--data.validate_on_test", "false")  # smoke.yaml asks for the test split
    err = str(verdict.value)
    assert err.startswith("aesplat validate: ") and "has no validation split" in err and "\n" not in err
    assert not (tmp_path / "run").exists()
    # validation scenes without test scenes: it validates (the test split is not its input)
    generate_dataset(tmp_path / "src2", scenes=2, test_scenes=0, val_scenes=1, **TINY)
    convert_dataset(tmp_path / "src2", tmp_path / "val_only", size=28, progress=False)
    assert not (tmp_path / "val_only" / "test").exists() and (tmp_path / "val_only" / "validation").is_dir()
    validate(tmp_path / "val_only")


def test_to_shards_val_scenes_holds_out_training_scenes_deterministically(tmp_path):
    generate_dataset(tmp_path / "src", scenes=5, test_scenes=1, val_scenes=0, **TINY)
    whole = convert_dataset(tmp_path / "src", tmp_path / "whole", size=16, progress=False)
    a = convert_dataset(tmp_path / "src", tmp_path / "a", size=16, val_scenes=2, progress=False)
    b = convert_dataset(tmp_path / "src", tmp_path / "b", size=16, val_scenes=2, workers=2, progress=False)
    keys = a["splits"]["validation"]["held_out_from_train"]["scene_keys"]
    assert len(keys) == 2 and keys == b["splits"]["validation"]["held_out_from_train"]["scene_keys"]
    assert [s["sha256"] for s in a["splits"]["train"]["shards"]] == [
        s["sha256"] for s in b["splits"]["train"]["shards"]
    ]
    assert a["splits"]["train"]["scenes"] == 3 and a["splits"]["validation"]["scenes"] == 2
    assert a["splits"]["train"]["samples"] + 2 == whole["splits"]["train"]["samples"]
    dm = DataModule(root=str(tmp_path / "a"), image_size=16, num_workers=0)
    assert sorted(s for batch in dm.eval_dataset("val") for s in batch.scene) == keys
    trained = {r for shard in (tmp_path / "a" / "train").glob("*.json") for r in json.loads(shard.read_text())
               ["scene_keys"]}  # fmt: skip
    assert not trained & set(keys) and len(trained) == 3
    # The test split is untouched by the hold-out.
    assert a["splits"]["test"]["shards"] == whole["splits"]["test"]["shards"]
    # The choice depends on the keys and the seed only, not on their order.
    all_keys = sorted(json.loads((tmp_path / "src" / "train" / "index.json").read_text()))
    assert held_out_keys(all_keys[::-1], 2, 0) == keys
    assert held_out_keys(all_keys, 2, 1) != keys or held_out_keys(all_keys, 2, 2) != keys


def test_to_shards_val_scenes_refuses_what_does_not_fit(tmp_path, capsys):
    generate_dataset(tmp_path / "src", scenes=2, test_scenes=1, val_scenes=1, **TINY)
    to_shards = load_script("to_shards", ROOT / "data_prep")
    with pytest.raises(SystemExit, match="already has a validation/ split"):
        to_shards.main(["--src", str(tmp_path / "src"), "--out", str(tmp_path / "o"), "--val-scenes", "1"])
    with pytest.raises(UserError, match="leave some to train on"):
        held_out_keys(["a", "b"], 2, 0)


def test_learning_curves_choose_on_validation_figures_and_report_test_for_the_chosen_run_only():
    driver = load_benchmark("learning_curves")

    def row(step, val, test):
        base = {k: math.nan for k in CURVE_COLUMNS}
        base.update(step=step, train_seconds=float(step), psnr=test, val_psnr=val, rot_err_deg=1.0,
                    val_rot_err_deg=1.0, trans_err_deg=2.0, val_trans_err_deg=2.0, num_scenes=3,
                    val_num_scenes=3, copy_mean_psnr=10.0, copy_best_psnr=9.0, val_copy_mean_psnr=11.0,
                    val_copy_best_psnr=9.5)  # fmt: skip
        return base

    curves = {  # "a" is better on the test scenes, "b" on the validation scenes
        "a": [row(0, 15.0, 15.0), row(10, 16.0, 19.5)],
        "b@data-seed-0": [row(0, 15.0, 15.0), row(10, 17.0, 18.25)],
        "b@data-seed-1": [row(0, 15.0, 15.0), row(10, 16.5, 18.75)],
    }
    assert driver.choose(curves) == "b"
    table = "\n".join(driver.summary_table(curves))
    assert "validation PSNR start → end" in table and "**b**" in table
    assert "18.25" in table and "18.75" in table and "19.50" not in table  # a's test figure is not reported
    assert "mean of the context views 11.00 dB" in table and "mean of the context views 10.00 dB" in table


def test_learning_curves_keep_the_baseline_unless_a_run_beats_it_by_the_margin():
    driver = load_benchmark("learning_curves")

    def curve(val, rotation, test):
        base = {k: math.nan for k in CURVE_COLUMNS}
        base.update(step=10, train_seconds=10.0, psnr=test, val_psnr=val, rot_err_deg=1.0,
                    val_rot_err_deg=rotation, trans_err_deg=2.0, val_trans_err_deg=2.0, num_scenes=3,
                    val_num_scenes=3, copy_mean_psnr=10.0, copy_best_psnr=9.0, val_copy_mean_psnr=11.0,
                    val_copy_best_psnr=9.5)  # fmt: skip
        return [base]

    curves = {"demo": curve(19.50, 2.0, 20.00), "blur": curve(19.70, 2.0, 20.10)}
    assert driver.choose(curves) == "blur"  # no baseline: the highest validation PSNR
    assert driver.choose(curves, "demo", 0.25) == "demo"  # +0.20 dB is within the margin
    assert driver.choose(curves, "demo", 0.1) == "blur"
    curves["views"] = curve(19.90, 2.5, 20.30)  # beats the margin, but with a higher rotation error
    assert driver.choose(curves, "demo", 0.25) == "demo"
    curves["views"] = curve(19.90, 1.9, 20.30)
    assert driver.choose(curves, "demo", 0.25) == "views"
    table = "\n".join(driver.summary_table({"demo": curves["demo"], "blur": curves["blur"]}, "demo", 0.25))
    assert "only over **demo**, if its validation PSNR exceeds demo's by more than 0.25 dB" in table
    assert "**demo**. Its test figures" in table and "20.10" not in table  # blur's test figure is not reported
