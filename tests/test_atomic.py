"""ocv2.atomic: whole-file writes are all or nothing, and leave nothing behind on failure."""

import os

import pytest

from ocv2.atomic import atomic_path, atomic_write, is_temporary, remove_stale_temporaries, staged_folder


def test_atomic_write_replaces_whole_file(tmp_path):
    target = tmp_path / "sub" / "data.csv"
    atomic_write(target, "a,b\r\n1,2\r\n")
    assert target.read_bytes() == b"a,b\r\n1,2\r\n"  # no newline translation, parents created
    atomic_write(target, b"new")
    assert target.read_bytes() == b"new"
    assert [p.name for p in target.parent.iterdir()] == ["data.csv"]


def test_failed_write_keeps_old_file_and_removes_temporary(tmp_path):
    target = tmp_path / "plot.png"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            assert tmp.suffix == ".png" and is_temporary(tmp)  # writers that choose a format by suffix
            tmp.write_bytes(b"half")
            raise RuntimeError("disk full")
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["plot.png"]


def test_remove_stale_temporaries(tmp_path):
    (tmp_path / "ck").mkdir()
    stale = tmp_path / "ck" / ".update_0000004.tmp-123-abcd.msgpack"
    stale.write_bytes(b"x")
    keep = tmp_path / "ck" / "update_0000004.msgpack"
    keep.write_bytes(b"y")
    assert remove_stale_temporaries(tmp_path) == [stale]
    assert keep.exists() and not stale.exists()


def test_staged_folder_replaces_whole_or_leaves_everything_as_it_was(tmp_path):
    out = tmp_path / "out"
    with staged_folder(out) as staging:
        (staging / "a.txt").write_text("first")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]
    with pytest.raises(RuntimeError):
        with staged_folder(out) as staging:
            (staging / "b.txt").write_text("half")
            raise RuntimeError("stopped part-way")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]  # the earlier folder as it was
    with staged_folder(out) as staging:
        (staging / "b.txt").write_text("second")
    assert sorted(p.name for p in out.iterdir()) == ["b.txt"]  # replaced whole: nothing of the earlier left
    (tmp_path / ".out.keep").mkdir()  # a folder of the user's with a staging-like name is never touched
    with staged_folder(out):
        pass
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.keep", "out"]


def test_staged_folder_fills_an_empty_folder_in_place_even_the_current_directory(tmp_path, monkeypatch):
    """`ocv2 xp --out .` in an empty directory: '.' cannot be renamed, so it is filled in place, whole or not at all;
    a new folder gets mkdir's permissions, not mkdtemp's 0700."""
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    with pytest.raises(OSError), staged_folder(".") as staging:
        (staging / "matrix.csv").write_text("half")
        raise OSError(28, "No space left on device")
    assert list(here.iterdir()) == []
    with staged_folder(".") as staging:
        (staging / "matrix.csv").write_text("whole")
        (staging / "plots").mkdir()
    assert sorted(p.name for p in here.iterdir()) == ["matrix.csv", "plots"]
    old = os.umask(0o022)
    try:
        with staged_folder(tmp_path / "new") as staging:
            (staging / "a").write_text("x")
    finally:
        os.umask(old)
    assert (tmp_path / "new").stat().st_mode & 0o777 == 0o755
