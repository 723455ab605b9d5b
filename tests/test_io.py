"""Atomic writes leave the mode a plain `open()` would: the umask decides, as for any file."""

import os
import stat

import pytest

from downwash_core.io import atomic_path, atomic_write_bytes, atomic_write_json, plain_open_mode, remove_temporaries


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(old)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077, 0o002])
def test_new_files_get_0666_less_the_umask(tmp_path, umask, mask):
    umask(mask)
    atomic_write_bytes(tmp_path / "a.bin", b"x")
    atomic_write_json(tmp_path / "b.json", {"a": 1})
    with open(tmp_path / "plain.txt", "w") as f:
        f.write("x")
    assert _mode(tmp_path / "a.bin") == _mode(tmp_path / "b.json") == _mode(tmp_path / "plain.txt") == 0o666 & ~mask
    assert plain_open_mode(tmp_path / "missing") == 0o666 & ~mask


def test_an_existing_file_keeps_its_mode(tmp_path, umask):
    umask(0o022)
    path = tmp_path / "r.json"
    atomic_write_json(path, {"a": 1})
    os.chmod(path, 0o640)
    atomic_write_json(path, {"a": 2})
    assert _mode(path) == 0o640 and path.read_text().strip().endswith("}")


def test_a_failed_write_leaves_neither_the_file_nor_a_temporary(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "v.mp4", suffix=".mp4") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("writer died")
    assert list(tmp_path.iterdir()) == []


def test_a_symlink_is_written_through_and_stays_a_link(tmp_path, umask):
    """As `open(path, "w")`: the target gets the data and keeps its mode; the link keeps pointing at it."""
    umask(0o022)
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    atomic_write_json(target, {"a": 1})
    os.chmod(target, 0o600)
    link.symlink_to(target)
    atomic_write_json(link, {"a": 2})
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert _mode(target) == 0o600 and '"a": 2' in target.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.json", "target.json"]


def test_temporaries_that_killed_writers_left_are_removed(tmp_path):
    """What a SIGKILL during `atomic_path` leaves (``.<name>.<random>.tmp``), in the folder and below it,
    goes; finished files, hidden files of other kinds and the lock file stay."""
    stage = tmp_path / "stage0" / "train"
    stage.mkdir(parents=True)
    (stage / "flight_000.npz").write_bytes(b"log")
    (tmp_path / ".lock").write_text("")
    (tmp_path / ".notes").write_text("mine")
    stale = [stage / ".flight_001.npz.k2j4_x.tmp", tmp_path / ".manifest.json.a8b3c.tmp"]
    for p in stale:
        p.write_bytes(b"half")
    assert sorted(remove_temporaries(tmp_path)) == sorted(stale)
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == [
        ".lock", ".notes", "stage0", "stage0/train", "stage0/train/flight_000.npz"]
    assert remove_temporaries(tmp_path / "missing") == []
