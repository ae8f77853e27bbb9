"""Scene keys of any characters in an evaluation's outputs: per_scene.csv gives back each key as it was, and
each scene's render grid gets a file of its own, whatever the key holds and wherever the folder is."""

import csv

from aesplat.train.evaluation import write_results
from aesplat.train.module import render_name
from tests.helpers import ODD_KEYS

KEYS = [*ODD_KEYS, "room.one", "room_one", "Room_One", "ü" * 200, ".hidden", "", "a~1", "a_1"]


def test_every_key_gets_a_render_file_of_its_own():
    names = [render_name(key) for key in KEYS]
    assert len({name.lower() for name in names}) == len(KEYS)  # distinct on case-insensitive file systems too
    for name in names:
        assert name.endswith(".png") and "/" not in name and "\n" not in name and not name.startswith(".")
        assert len(name.encode()) <= 255  # one path component on every common file system
    assert render_name("room_one") == "room_one.png" and render_name("0a1b2c3d") == "0a1b2c3d.png"


def test_per_scene_csv_gives_back_every_key_intact(tmp_path):
    rows = [{"scene": key, "dataset": "d", "overlap": 0.5, "bucket": "medium", "psnr": 20.0} for key in KEYS]
    write_results(rows, tmp_path)
    with open(tmp_path / "per_scene.csv", newline="") as f:
        assert sorted(row["scene"] for row in csv.DictReader(f)) == sorted(KEYS)


def test_the_documented_example_is_what_the_code_writes():
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "docs" / "evaluation.md").read_text()
    assert f"`Room 1` →\n  `{render_name('Room 1')}`" in page
