"""ocv2.atomic: whole-file writes are all or nothing, and leave nothing behind on failure."""

import os
from pathlib import Path

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


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError])
def test_a_stop_between_the_two_renames_puts_the_earlier_folder_back(tmp_path, monkeypatch, stop):
    """Replacing an earlier output is two renames (it aside, the new one in); Ctrl-C between them used to leave the
    earlier folder hidden beside --out and nothing at --out."""
    out = tmp_path / "out"
    with staged_folder(out) as staging:
        (staging / "a.txt").write_text("first")
    rename = Path.rename

    def stopped_moving_in(self, target):
        if Path(target) == out and self.name != out.name:  # the new folder moving in, not the earlier one back
            raise stop()
        return rename(self, target)

    monkeypatch.setattr(Path, "rename", stopped_moving_in)
    with pytest.raises(stop), staged_folder(out) as staging:
        (staging / "b.txt").write_text("second")
    monkeypatch.undo()
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]  # the earlier folder as it was
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging or aside folder left


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


def _moves_then_interrupts(monkeypatch, allowed: int) -> list[str]:
    """Path.rename moves ``allowed`` items, then raises KeyboardInterrupt (a SIGTERM between two moves); returns
    the names it was asked to move, in order."""
    rename, asked = Path.rename, []

    def interrupted(self, target):
        asked.append(self.name)
        if len(asked) > allowed:
            raise KeyboardInterrupt
        return rename(self, target)

    monkeypatch.setattr(Path, "rename", interrupted)
    return asked


@pytest.mark.parametrize("allowed", [0, 1, 2, 3])
def test_an_empty_folder_filled_in_place_is_empty_again_after_an_interruption(tmp_path, monkeypatch, allowed):
    """A pack into an empty --out was moved up in sorted order: pack.json (the marker read_pack takes as "finished")
    went first, and a stop on the next move left a folder holding only pack.json, which a rerun refused as not
    empty. Now the named markers move last, and what was moved is taken back."""
    dest = tmp_path / "pack"
    dest.mkdir()
    asked = []
    with pytest.raises(KeyboardInterrupt), staged_folder(dest, ".packing", markers=["pack.json"]) as staging:
        for name in ("study.tar.gz.000", "study.tar.gz.001", "pack.json"):
            (staging / name).write_text(name)
        (staging / "plots").mkdir()
        (staging / "plots" / "a.png").write_text("png")
        asked = _moves_then_interrupts(monkeypatch, allowed)
    monkeypatch.undo()
    assert list(dest.iterdir()) == []
    assert asked == ["plots", "study.tar.gz.000", "study.tar.gz.001", "pack.json"][: allowed + 1]


def test_markers_are_moved_in_last_in_the_order_named(tmp_path, monkeypatch):
    dest = tmp_path / "report"
    dest.mkdir()
    with staged_folder(dest, ".report", markers=["summary.json", "report.md", "absent.txt"]) as staging:
        for name in ("report.md", "summary.json", "a.csv", "z.png"):
            (staging / name).write_text(name)
        asked = _moves_then_interrupts(monkeypatch, allowed=99)
    assert asked == ["a.csv", "z.png", "summary.json", "report.md"]
    assert sorted(p.name for p in dest.iterdir()) == ["a.csv", "report.md", "summary.json", "z.png"]
