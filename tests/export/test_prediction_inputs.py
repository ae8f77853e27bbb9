"""A prediction folder is untrusted input to ``aesplat export``: names and links that leave the folder,
cameras and Gaussians holding NaN or Inf, malformed ``cameras.json`` entries, and photo names of every kind a
file system allows. Each refusal is one line naming the entry and writes nothing; each name that is accepted
reaches every format intact and distinct (COLMAP: a safe name, with the mapping recorded)."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from aesplat.data.sources.colmap import read_colmap
from aesplat.data.sources.nerfstudio import read_nerfstudio
from aesplat.errors import UserError
from aesplat.export.command import main as export_main
from aesplat.export.prediction import read_prediction
from tests.export.helpers import (
    edit_cameras,
    random_gaussians,
    view_colour,
    write_ply_with,
    write_prediction,
)

ALL = "colmap,nerfstudio,splat"


def refusal(argv: list[str], capsys) -> str:
    """The one line ``aesplat export argv`` stops with (exit status 1, no traceback)."""
    with pytest.raises(SystemExit) as stop:
        export_main(argv)
    message = str(stop.value.code)
    assert message.startswith("aesplat export: ") and "\n" not in message
    assert "Traceback" not in capsys.readouterr().err
    return message


def exports_in(folder: Path) -> list[str]:
    """What an export wrote into the prediction folder (finished or staged)."""
    return sorted(p.name for p in folder.iterdir() if p.name not in ("cameras.json", "gaussians.ply", "inputs"))


def colour_of(path: Path) -> tuple[int, ...]:
    """The colour of an image's first pixel: which view's image it is (``view_colour``)."""
    with Image.open(path) as image:
        return tuple(int(c) for c in np.asarray(image.convert("RGB"))[0, 0])


# ---------------------------------------------------------------------------------------- names and links


def test_a_name_that_climbs_out_of_the_folder_is_refused(tmp_path, capsys):
    secret = tmp_path / "secret.png"
    secret.write_bytes(b"not the user's to export")
    pred = write_prediction(tmp_path / "pred")
    (pred / "inputs" / "01_x").mkdir()  # inputs/01_x/../../../secret.png is tmp_path/secret.png
    edit_cameras(pred, lambda c: c["views"][1].update(image="x/../../../secret"))
    message = refusal([str(pred), "--formats", ALL], capsys)
    assert "view 1 'x/../../../secret'" in message and "outside the prediction folder" in message
    assert exports_in(pred) == []


def test_a_name_with_a_folder_is_refused(tmp_path, capsys):
    """``sub/x`` stays inside the folder, but the copies would drop its view number (two views, one file)."""
    pred = write_prediction(tmp_path / "pred")
    (pred / "inputs" / "01_sub").mkdir()
    (pred / "inputs" / "01_right.png").rename(pred / "inputs" / "01_sub" / "x.png")
    edit_cameras(pred, lambda c: c["views"][1].update(image="sub/x"))
    message = refusal([str(pred), "--formats", ALL], capsys)
    assert "view 1 'sub/x'" in message and "not a file name" in message
    assert exports_in(pred) == []


def test_a_link_out_of_the_folder_is_refused(tmp_path, capsys):
    secret = tmp_path / "secret.png"
    secret.write_bytes(b"not the user's to export")
    pred = write_prediction(tmp_path / "pred")
    (pred / "inputs" / "01_right.png").unlink()
    (pred / "inputs" / "01_right.png").symlink_to(secret)
    message = refusal([str(pred), "--formats", ALL], capsys)
    assert "view 1 'right'" in message and "links outside the prediction folder" in message
    assert exports_in(pred) == []


def test_a_missing_image_whose_name_holds_a_line_break_is_one_line(tmp_path, capsys):
    pred = write_prediction(tmp_path / "pred", ["left", "new\nline"])
    (pred / "inputs" / "01_new\nline.png").unlink()
    message = refusal([str(pred), "--formats", ALL], capsys)
    assert "input image '01_new\\nline.png' named in cameras.json is missing" in message


def test_a_link_inside_the_folder_is_followed(tmp_path):
    pred = write_prediction(tmp_path / "pred")
    (pred / "renders").mkdir()
    (pred / "inputs" / "01_right.png").rename(pred / "renders" / "01_right.png")
    (pred / "inputs" / "01_right.png").symlink_to(Path("..", "renders", "01_right.png"))
    assert export_main([str(pred), "--formats", "colmap"]) == 0
    assert colour_of(pred / "colmap" / "images" / "01_right.png") == view_colour(1)


# ------------------------------------------------------------------------------------------- NaN and Inf


@pytest.mark.parametrize(
    ("view", "key", "where", "value"),
    [
        (1, "camera_to_world", (0, 3), float("nan")),
        (0, "intrinsics_normalized", (0, 0), float("inf")),
    ],
)
def test_a_non_finite_camera_is_refused(tmp_path, capsys, view, key, where, value):
    pred = write_prediction(tmp_path / "pred")
    edit_cameras(pred, lambda c: c["views"][view][key][where[0]].__setitem__(where[1], value))
    message = refusal([str(pred), "--formats", ALL], capsys)
    name = ("left", "right")[view]
    assert f"view {view} '{name}'" in message and "NaN or Inf" in message
    assert exports_in(pred) == []


def test_a_non_finite_novel_camera_is_refused(tmp_path):
    pred = write_prediction(tmp_path / "pred")
    edit_cameras(pred, lambda c: c["novel"][0]["camera_to_world"][2].__setitem__(2, float("nan")))
    with pytest.raises(UserError, match="novel view 0 has a camera holding NaN or Inf"):
        read_prediction(pred)


# Stored values that are not finite, or that loading turns into Inf (exp of a log-scale of 200): one per
# parameter of a Gaussian.
NON_FINITE = {
    (3, "x"): float("nan"),
    (7, "scale_1"): float("inf"),
    (11, "rot_2"): float("nan"),
    (15, "opacity"): float("inf"),
    (19, "f_rest_4"): float("-inf"),
    (23, "f_dc_0"): float("nan"),
    (27, "scale_0"): 200.0,
}


def strict_json(text: str):
    def refuse(constant):
        raise AssertionError(f"{constant} is not JSON")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_gaussians_are_dropped_from_every_format_in_one_warning(tmp_path, capsys):
    gaussians = random_gaussians(n=40)
    pred = write_prediction(tmp_path / "pred", gaussians=gaussians)
    write_ply_with(pred / "gaussians.ply", gaussians, NON_FINITE)
    assert export_main([str(pred), "--formats", ALL]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dropped 7 of 40 Gaussians" in err[0], err
    kept = [i for i in range(40) if i not in {row for row, _ in NON_FINITE}]
    model = pred / "colmap" / "sparse" / "0"
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        text = (model / name).read_text().lower()
        assert "nan" not in text and "inf" not in text, name
    points = np.loadtxt(model / "points3D.txt", comments="#")
    np.testing.assert_allclose(points[:, 1:4], gaussians.means[0, kept].numpy(), rtol=1e-6)
    strict_json((pred / "nerfstudio" / "transforms.json").read_text())
    cloud = (pred / "nerfstudio" / "sparse_pc.ply").read_bytes()
    body = cloud[cloud.index(b"end_header\n") + 11 :]
    table = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    np.testing.assert_array_equal(table["xyz"], gaussians.means[0, kept].numpy())
    splat = np.frombuffer((pred / "gaussians.splat").read_bytes(), dtype=np.uint8).reshape(-1, 32)
    floats = splat[:, :24].copy().view("<f4")  # centre and scale
    assert len(splat) == len(kept) and np.isfinite(floats).all()
    np.testing.assert_array_equal(floats[:, :3], gaussians.means[0, kept].numpy())


# ----------------------------------------------------------------------------------- malformed cameras.json


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda c: [v.update(camera_to_world=v["intrinsics_pixels"]) for v in c["views"]], "camera_to_world"),
        (lambda c: [v.update(width=0) for v in c["views"]], "width"),
        (lambda c: c.update(render={"background": "white"}), "background"),
        (lambda c: c.update(render=[0.0]), "render"),
    ],
    ids=["pose-3x3", "width-0", "background-word", "render-list"],
)
def test_a_malformed_cameras_file_is_one_line(tmp_path, capsys, edit, message):
    pred = write_prediction(tmp_path / "pred")
    edit_cameras(pred, edit)
    line = refusal([str(pred), "--formats", ALL], capsys)
    assert "is not the cameras file of `aesplat predict`" in line and message in line
    assert exports_in(pred) == []


# ------------------------------------------------------------------------------------------------- names

# Photo names a file system allows (``aesplat predict`` names each view by its photo's stem).
NAMES = [
    "my photo",
    "caf\u00e9 \u2615",
    "#1",
    "100%",
    'it\'s "quoted"',
    "-dash",
    "new\nline",
    "tab\there",
    "A",
    "a",
    " lead",
    "trail ",
    "back\\slash",
    "x" * 248,  # inputs/NN_NAME.png is then 255 bytes, the longest file name most file systems allow
]


def non_utf8_name() -> str:
    """A name holding a byte that is not UTF-8, as Python names such a file (or skip where none can exist)."""
    name = os.fsdecode(b"bad\xff byte")
    try:
        os.fsencode(name)
    except UnicodeError:
        pytest.skip("this file system encoding has no name for a non-UTF-8 byte")
    return name


@pytest.fixture
def named(tmp_path):
    """A prediction folder with one view per name of ``NAMES`` and a non-UTF-8 one, exported in every format."""
    names = [*NAMES, non_utf8_name()]
    try:
        pred = write_prediction(tmp_path / "pred", names)
    except OSError as err:  # a file system that refuses such names cannot hold such a prediction either
        pytest.skip(f"this file system refuses a test name: {err}")
    assert export_main([str(pred), "--formats", ALL]) == 0
    return pred, names


def test_every_name_reaches_the_colmap_export_distinct_with_its_mapping(named):
    pred, names = named
    model = pred / "colmap" / "sparse" / "0"
    header = [line for line in (model / "images.txt").read_text(encoding="utf-8").split("\n")
              if line and not line.startswith("#")]  # fmt: skip
    # COLMAP's readers (pycolmap, nerfstudio's, gsplat's) split a line on whitespace: NAME is the 10th field
    fields = [line.split() for line in header]
    assert [len(f) for f in fields] == [10] * len(names)
    files = [f[9] for f in fields]
    assert len(set(files)) == len(names) and len({f.lower() for f in files}) == len(names)
    assert [f.split("_", 1)[0] for f in files] == [f"{i:02d}" for i in range(len(names))]
    for i, file in enumerate(files):
        assert colour_of(pred / "colmap" / "images" / file) == view_colour(i), file
    mapping = json.loads((pred / "colmap" / "image_names.json").read_text())
    assert mapping == dict(zip(files, names))
    capture = read_colmap(pred / "colmap")
    assert sorted(capture.names) == sorted(files)
    # a name COLMAP can carry (no whitespace, every character printable) is kept as it is
    kept = [name for i, name in enumerate(names) if files[i] == f"{i:02d}_{name}.png"]
    assert kept == ["#1", "100%", "-dash", "A", "a", "back\\slash", "x" * 248]
    assert files[0] == "00_my_photo.png" and files[6] == "06_new_line.png" and files[-1] == "14_bad__byte.png"


def test_every_name_reaches_the_nerfstudio_export_intact(named):
    pred, names = named
    meta = json.loads((pred / "nerfstudio" / "transforms.json").read_text())
    paths = [frame["file_path"] for frame in meta["frames"]]
    assert paths == [f"images/{i:02d}_{name}.png" for i, name in enumerate(names)]
    for i, path in enumerate(paths):
        assert colour_of(pred / "nerfstudio" / path) == view_colour(i)
    capture = read_nerfstudio(pred / "nerfstudio")
    assert sorted(capture.names) == sorted(paths)
    assert capture.intrinsics.shape == (len(names), 3, 3)


def test_predict_writes_and_exports_names_of_every_kind(tmp_path):
    """End to end: ``aesplat predict --export`` on photos named with a space, a newline and a non-UTF-8 byte."""
    from aesplat.predict import main
    from tests.prediction_helpers import split_image, write_view_dependent_checkpoint

    names = [f"{non_utf8_name()} #1", "new\nline 100%"]
    photos = []
    for i, name in enumerate(names):
        (tmp_path / str(i)).mkdir()
        try:
            photos.append(split_image(tmp_path / str(i) / f"{name}.png", 12 + 4 * i))
        except OSError as err:
            pytest.skip(f"this file system refuses a test name: {err}")
    ckpt = write_view_dependent_checkpoint(tmp_path / "run")
    out = tmp_path / "pred"
    argv = ["--ckpt", str(ckpt), "--out", str(out), "--novel-frames", "2", "--no-progress", "--threads", "2"]
    assert main([*argv, "--export", ALL, *map(str, photos)]) == 0
    assert read_prediction(out).names == names
    mapping = json.loads((out / "colmap" / "image_names.json").read_text())
    assert sorted(mapping.values()) == sorted(names)
    lines = (out / "colmap" / "sparse" / "0" / "images.txt").read_text().split("\n")
    assert [len(line.split()) for line in lines if line and not line.startswith("#")] == [10, 10]
