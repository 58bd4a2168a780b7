"""ocv2.atomic: whole-file writes are all or nothing, and leave nothing behind on failure."""

import pytest

from ocv2.atomic import atomic_path, atomic_write, is_temporary, remove_stale_temporaries


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
