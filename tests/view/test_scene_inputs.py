"""What ``aesplat view`` loads is untrusted input: a PLY that cannot be shown (no Gaussians, a malformed header,
truncated data) is one line before any server starts; Gaussians holding NaN or Inf are dropped with one
warning line; a prediction folder's names and links are checked as ``aesplat export`` checks them; every camera
name is text the browser can be sent."""

import importlib.util
import os

import numpy as np
import pytest
import torch
from PIL import Image

from aesplat.errors import UserError
from aesplat.export import ply_property_names, write_ply
from aesplat.view.command import main as view_main
from aesplat.view.scene import scene_from_path
from tests.export.helpers import edit_cameras, ply_bytes, random_gaussians, write_ply_with, write_prediction

NAMES = ply_property_names(0)
ROW = np.arange(len(NAMES), dtype=np.float32) * 0.1  # one Gaussian's stored values, all finite


def one_line_refusal(path, match: str) -> str:
    with pytest.raises(UserError, match=match) as err:
        scene_from_path(path)
    assert "\n" not in str(err.value)
    return str(err.value)


def header_with(lines: list[str]) -> bytes:
    """A binary 3DGS PLY with ``lines`` between its format line and ``end_header``, and one Gaussian's data."""
    head = ["ply", "format binary_little_endian 1.0", *lines, "end_header"]
    return ("\n".join(head) + "\n").encode() + ROW.astype("<f4").tobytes()


PROPERTIES = [f"property float {name}" for name in NAMES]


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (ply_bytes(NAMES, ROW[None], count="-1"), "'element vertex -1' .*count"),
        (ply_bytes(NAMES, ROW[None], count="many"), "'element vertex many' .*count"),
        (ply_bytes(NAMES, ROW[None], count="1.5"), "'element vertex 1.5' .*count"),
        (header_with(["element vertex", *PROPERTIES]), "'element vertex' .*count"),
        (header_with(["element", *PROPERTIES]), "'element' .*count"),
        (header_with(["element vertex 1", *PROPERTIES[:-1], "property float"]), "'property float'"),
        (header_with(["element vertex 1", *PROPERTIES, "property float x"]), "property x twice"),
        (ply_bytes(NAMES, ROW[None], count="2"), "truncated"),
    ],
    ids=["negative", "word", "fraction", "no-count", "no-kind", "no-name", "twice", "more-than-data"],
)
def test_a_malformed_ply_is_one_line(tmp_path, data, match):
    path = tmp_path / "g.ply"
    path.write_bytes(data)
    assert str(path) in one_line_refusal(path, match)


def test_a_ply_without_gaussians_is_one_line(tmp_path):
    path = tmp_path / "g.ply"
    path.write_bytes(ply_bytes(NAMES, ROW[:0].reshape(0, len(NAMES))))
    one_line_refusal(path, "no Gaussians to show")


def test_a_ply_whose_gaussians_are_all_non_finite_is_one_line(tmp_path, capsys):
    gaussians = random_gaussians(n=3, degree=0)
    path = write_ply_with(tmp_path / "g.ply", gaussians, {(i, "x"): float("nan") for i in range(3)})
    one_line_refusal(path, "no Gaussians to show")
    assert "dropped 3 of 3 Gaussians" in capsys.readouterr().err


def test_non_finite_gaussians_are_dropped_with_one_warning(tmp_path, capsys):
    gaussians = random_gaussians(n=12, degree=2)
    bad = {(1, "y"): float("nan"), (4, "scale_2"): float("inf"), (6, "rot_0"): float("nan"),
           (8, "opacity"): float("-inf"), (10, "f_rest_20"): float("nan")}  # fmt: skip
    scene = scene_from_path(write_ply_with(tmp_path / "g.ply", gaussians, bad))
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dropped 5 of 12 Gaussians" in err[0] and str(tmp_path / "g.ply") in err[0]
    kept = [0, 2, 3, 5, 7, 9, 11]
    assert scene.gaussians.num_gaussians == len(kept)
    torch.testing.assert_close(scene.gaussians.means[0], gaussians.means[0, kept])
    for t in (scene.gaussians.quats, scene.gaussians.scales, scene.gaussians.opacities, scene.gaussians.sh):
        assert torch.isfinite(t).all()


def test_a_finite_ply_loads_without_a_warning(tmp_path, capsys):
    scene = scene_from_path(write_ply(tmp_path / "g.ply", random_gaussians(n=5)))
    assert scene.gaussians.num_gaussians == 5 and capsys.readouterr().err == ""


def test_the_command_stops_in_one_line_before_serving(tmp_path, capsys):
    if importlib.util.find_spec("viser") is None:
        pytest.skip('viser (pip install -e ".[viewer]") is not installed')
    path = tmp_path / "g.ply"
    path.write_bytes(ply_bytes(NAMES, ROW[None], count="-1"))
    with pytest.raises(SystemExit) as stop:
        view_main([str(path), "--port", "0"])
    message = str(stop.value.code)
    assert message.startswith("aesplat view: ") and "element vertex -1" in message and "\n" not in message
    out, err = capsys.readouterr()
    assert "http" not in out and "Traceback" not in err


def test_a_prediction_folder_that_links_out_is_refused(tmp_path):
    secret = tmp_path / "secret.png"
    Image.new("RGB", (4, 4), (1, 2, 3)).save(secret)  # an image of the user's, not the prediction's
    pred = write_prediction(tmp_path / "pred")
    (pred / "inputs" / "00_left.png").unlink()
    (pred / "inputs" / "00_left.png").symlink_to(secret)
    one_line_refusal(pred, "view 0 'left'.* links outside the prediction folder")


def test_a_prediction_folder_whose_name_climbs_out_is_refused(tmp_path):
    pred = write_prediction(tmp_path / "pred")
    (pred / "inputs" / "00_x").mkdir()
    (pred / "inputs" / "00_left.png").rename(tmp_path / "outside.png")
    edit_cameras(pred, lambda c: c["views"][0].update(image="x/../../../outside"))
    one_line_refusal(pred, "view 0 'x/../../../outside'.* outside the prediction folder")


def test_camera_names_of_every_kind_can_be_sent_to_the_browser(tmp_path):
    """The browser gets names as UTF-8 (viser's messages): a name holding a byte that is not UTF-8 is shown with
    that byte escaped; every name stays distinct and the others are shown as they are."""
    odd = os.fsdecode(b"bad\xff byte")
    names = [odd, "new\nline", "caf\u00e9 #1 100%", "A", "a"]
    try:
        pred = write_prediction(tmp_path / "pred", names)
    except (OSError, UnicodeError) as err:
        pytest.skip(f"this file system refuses a test name: {err}")
    shown = [camera.name for camera in scene_from_path(pred).cameras]
    for name in shown:
        name.encode("utf-8")  # what viser's msgpack encoder needs
    assert len(set(shown)) == len(names) and shown[1:] == names[1:]
    assert shown[0] == "bad\\xff byte"
