"""aesplat.files: the guard every --overwrite goes through, and whole-or-nothing writes."""

from pathlib import Path

import pytest

from aesplat.errors import UserError
from aesplat.files import PARTIAL_SUFFIX, check_deletable, delete_folder, remove_partials


def test_never_the_current_folder_the_home_or_a_folder_holding_them(tmp_path, monkeypatch):
    work = tmp_path / "home" / "work"
    work.mkdir(parents=True)
    monkeypatch.chdir(work)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for folder in (work, tmp_path, Path("."), tmp_path / "home", Path("/")):
        with pytest.raises(UserError, match="--overwrite will not delete .*: it holds the current folder"):
            check_deletable(folder, "--overwrite")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match="it holds your home folder"):
        check_deletable(tmp_path / "home", "--overwrite")
    check_deletable(tmp_path / "home" / "work", "--overwrite")  # a folder of its own: fine


def test_never_a_folder_holding_an_input_even_through_a_link(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    (out / "photos").mkdir(parents=True)
    photo = out / "photos" / "a.png"
    photo.write_bytes(b"png")
    link = tmp_path / "link"
    link.symlink_to(out)
    for target in (out, link):
        with pytest.raises(UserError, match=r"it holds the input image .*a\.png, an input of this command"):
            check_deletable(target, "--overwrite", [("--ckpt", None), ("the input image", photo)])
    with pytest.raises(UserError, match="it holds --data.root"):
        delete_folder(out, "--overwrite", [("--data.root", out / "photos")])
    assert photo.read_bytes() == b"png"


def test_delete_folder_keeps_what_it_is_told_to(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / ".lock").write_text("held")
    (run / "config.yaml").write_text("x")
    delete_folder(run, "--overwrite", keep=(".lock",))
    assert [p.name for p in run.iterdir()] == [".lock"]


def test_remove_partials_removes_only_temporary_files(tmp_path):
    (tmp_path / f".last.ckpt.1a2b{PARTIAL_SUFFIX}").write_bytes(b"half")
    (tmp_path / "last.ckpt").write_bytes(b"whole")
    assert [p.name for p in remove_partials(tmp_path)] == [f".last.ckpt.1a2b{PARTIAL_SUFFIX}"]
    assert [p.name for p in tmp_path.iterdir()] == ["last.ckpt"]
