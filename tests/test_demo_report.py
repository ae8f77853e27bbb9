"""scripts/demo_report.py: the posed diagnostic section (`model.cameras: dataset`) of the demo report."""

import json
import math
from pathlib import Path

import torch

from .script_loader import load_script


def _report_module():
    return load_script("demo_report")


def _summary(folder: Path, psnr: float, rot: float | None, trans: float | None) -> dict:
    folder.mkdir(parents=True)
    summary = {"num_scenes": 3, "metrics": {"psnr": psnr, "ssim": 0.5, "lpips": None, "rot_err_deg": rot,
                                            "trans_err_deg": trans}}  # fmt: skip
    (folder / "summary.json").write_text(json.dumps(summary))
    return summary


def test_posed_section_compares_both_runs(tmp_path):
    report = _report_module()
    initial, trained = _summary(tmp_path / "a", 16.0, 8.0, 70.0), _summary(tmp_path / "b", 17.0, 8.0, 15.0)
    _summary(tmp_path / "posed0", 15.0, None, None)  # no pose predicted, none scored
    _summary(tmp_path / "posed1", 21.5, None, None)
    lines = report.posed_section(initial, trained, tmp_path / "posed0", tmp_path / "posed1")
    text = "\n".join(lines)
    assert "| predicted cameras (the method) | 16.00 | 17.00 | +1.00 | 8.00 | 15.0 |" in text
    assert "| the data set's cameras (`model.cameras: dataset`) | 15.00 | 21.50 | +6.50 | n/a | n/a |" in text
    assert "the pose head is what limits this run" in text


def test_posed_section_is_empty_or_says_what_is_missing(tmp_path):
    report = _report_module()
    initial, trained = _summary(tmp_path / "a", 16.0, 8.0, 70.0), _summary(tmp_path / "b", 19.0, 2.0, 5.0)
    assert report.posed_section(initial, trained, None, None) == []
    missing = report.posed_section(initial, trained, tmp_path / "x", tmp_path / "y")
    assert "did not finish" in missing[0]
    _summary(tmp_path / "posed0", 15.0, None, None)
    _summary(
        tmp_path / "posed1", 17.5, None, None
    )  # a gain no larger than the method's: no verdict on the poses
    lines = report.posed_section(initial, trained, tmp_path / "posed0", tmp_path / "posed1")
    assert not any("limits this run" in line for line in lines)


def test_context_baselines_average_like_aesplat_test():
    report = _report_module()
    target = torch.full((1, 2, 3, 4, 4), 0.5)
    same = torch.full((1, 1, 3, 4, 4), 0.5)
    off = torch.full((1, 1, 3, 4, 4), 0.6)  # MSE 0.01 -> 20 dB
    scenes = [
        (torch.cat([off, off], 1), target),  # both views 20 dB, their mean too
        (torch.cat([same + 0.2, off], 1), target),  # views 0.7 (14 dB) and 0.6 (20 dB), mean 0.65 (16.48 dB)
    ]
    values = report.context_baselines(scenes)
    assert abs(values["the better context view of each scene"] - 20.0) < 1e-4
    mean = (20.0 + 10 * math.log10(1 / 0.15**2)) / 2
    assert abs(values["mean of the context views"] - mean) < 1e-4
