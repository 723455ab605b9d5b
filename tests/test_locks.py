"""Cross-process locks (`downwash_core.locks`): exclusion, waiting, a killed holder, re-entry, fork, removal.

Holders run in subprocesses (a flock is per open file, so only another process shows the
exclusion); every wait has a timeout, so a broken lock fails the test instead of hanging it.
"""

import logging
import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from downwash_core.locks import LOCK_NAME, file_lock, folder_lock, holder

ROOT = Path(__file__).resolve().parent.parent


def _holder(path: Path, seconds: float, remove: bool = False, folder: bool = True) -> subprocess.Popen:
    """A process that takes the lock of `path`, prints "held", holds it `seconds`, then exits."""
    take = (f"folder_lock({str(path)!r}, label='test holder')" if folder
            else f"file_lock({str(path)!r}, label='test holder', remove={remove})")
    code = textwrap.dedent(f"""
        import sys, time
        from downwash_core.locks import file_lock, folder_lock
        with {take}:
            print("held", flush=True)
            time.sleep({seconds})
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert proc.stdout.readline().strip() == "held"  # a hang here is caught by pytest's timeout of the caller
    return proc


def _try_elsewhere(path: Path) -> bool:
    """Whether another process gets the lock of the folder `path` at once (wait=False)."""
    code = f"from downwash_core.locks import folder_lock\nwith folder_lock({str(path)!r}, wait=False) as h: print(h)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0, out.stderr
    return out.stdout.strip() == "True"


def test_a_second_process_waits_for_the_holder_and_says_so(tmp_path, caplog):
    proc = _holder(tmp_path / "pipeline", seconds=1.5)
    try:
        assert holder(tmp_path / "pipeline" / LOCK_NAME)["pid"] == proc.pid
        with folder_lock(tmp_path / "pipeline", wait=False) as held:
            assert held is False  # held elsewhere: not taken, no wait
        t0 = time.monotonic()
        with caplog.at_level(logging.INFO, logger="downwash_core.locks"):
            with folder_lock(tmp_path / "pipeline", timeout=60, label="test") as held:
                waited = time.monotonic() - t0
                assert held is True
                assert proc.wait(timeout=30) == 0  # the holder let go as its block ended
                assert holder(tmp_path / "pipeline" / LOCK_NAME)["pid"] == os.getpid()
        waits = [r.getMessage() for r in caplog.records if "waiting for" in r.getMessage()]
        assert len(waits) == 1, waits  # said once, not per poll
        assert f"waiting for pid {proc.pid} on host" in waits[0] and str(tmp_path / "pipeline") in waits[0]
        assert "test holder" in waits[0]
        assert waited > 1.0  # it held the lock 1.5 s after saying so
    finally:
        proc.kill()
        proc.wait(timeout=30)


def test_a_killed_holder_does_not_block(tmp_path):
    """SIGKILL leaves no chance to clean up: the kernel drops the flock, so the lock is free at once."""
    proc = _holder(tmp_path / "f", seconds=600)
    assert not _try_elsewhere(tmp_path / "f")
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    t0 = time.monotonic()
    with folder_lock(tmp_path / "f", wait=False) as held:
        assert held is True
    assert time.monotonic() - t0 < 1.0
    assert holder(tmp_path / "f" / LOCK_NAME)["pid"] == os.getpid()


def test_the_lock_is_reentrant_within_a_process(tmp_path):
    with folder_lock(tmp_path / "f") as outer:
        with folder_lock(tmp_path / "f", wait=False) as inner:  # would deadlock if it took a second flock
            assert outer and inner
        assert not _try_elsewhere(tmp_path / "f")  # the inner release kept the outer hold
    assert _try_elsewhere(tmp_path / "f")


def _sleep(seconds: float) -> None:
    time.sleep(seconds)


def test_a_forked_child_does_not_keep_its_parents_lock(tmp_path):
    """The staged collection forks its trainings while it holds the folders' locks: a child
    that outlives the lock (or its parent) must not hold it."""
    ctx = multiprocessing.get_context("fork")
    with folder_lock(tmp_path / "f"):
        child = ctx.Process(target=_sleep, args=(60,), daemon=True)
        child.start()
    try:
        assert child.is_alive()
        assert _try_elsewhere(tmp_path / "f")
    finally:
        child.kill()
        child.join(timeout=30)


def test_a_removed_lock_file_is_taken_again_on_its_new_file(tmp_path):
    """remove=True: the holder deletes the file as it lets go; a waiter that had opened the old
    file notices and locks the new one (else two processes could hold "the" lock at once)."""
    path = tmp_path / "cells" / "abc.lock"
    proc = _holder(path, seconds=1.0, remove=True, folder=False)
    try:
        with file_lock(path, remove=True, timeout=60) as held:
            assert held and path.is_file() and holder(path)["pid"] == os.getpid()
            assert proc.wait(timeout=60) == 0
        assert not path.exists()
    finally:
        proc.kill()
        proc.wait(timeout=30)


def test_a_timeout_gives_up_and_reports_not_held(tmp_path):
    proc = _holder(tmp_path / "f", seconds=600)
    try:
        t0 = time.monotonic()
        with folder_lock(tmp_path / "f", timeout=0.3) as held:
            assert held is False
        assert 0.25 < time.monotonic() - t0 < 5
    finally:
        proc.kill()
        proc.wait(timeout=30)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only folder")
def test_a_read_only_folder_is_used_without_the_lock(tmp_path, caplog):
    folder = tmp_path / "shared"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with caplog.at_level(logging.WARNING, logger="downwash_core.locks"):
            with folder_lock(folder) as held:
                assert held
        assert "going on without the lock" in caplog.text
    finally:
        folder.chmod(0o755)


def test_a_waiter_makes_the_folder_again_when_the_holder_removed_it(tmp_path):
    """An experiment removes the --out folder its lock made when the run left it empty (a refused run
    leaves nothing): a run waiting on that folder makes it again instead of failing to open its lock file."""
    folder = tmp_path / "out"
    code = textwrap.dedent(f"""
        import os, time
        from downwash_core.locks import file_lock
        with file_lock({str(folder / LOCK_NAME)!r}, remove=True):
            print("held", flush=True)
            time.sleep(1.0)
            os.unlink({str(folder / LOCK_NAME)!r})
            os.rmdir({str(folder)!r})
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        assert proc.stdout.readline().strip() == "held"
        with folder_lock(folder, timeout=60) as held:
            assert held and holder(folder / LOCK_NAME)["pid"] == os.getpid()
            assert proc.wait(timeout=60) == 0
    finally:
        proc.kill()
        proc.wait(timeout=30)


# ----------------------------------------------------------------------------- an experiment's --out folder

# every experiment of experiments/common.py's dataclasses: the module whose `run` it calls, and that call's arguments
RUNS = {"lemniscate": "tracking", "transect": "tracking", "outdoor": "outdoor", "swarm": "swarm",
        "sample_efficiency": "sample_efficiency", "staged_collection": "staged_collection",
        "force_maps": "force_maps", "train": "train", "fields": "fields", "vehicles": "vehicles",
        "benchmark": "benchmark", "sweep": "sweep"}


def _held_here(lock: Path) -> bool:
    """Whether some open file of this process holds the flock of `lock` (a second open cannot take it)."""
    import fcntl

    fd = os.open(lock, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


@pytest.mark.parametrize("name", sorted(RUNS))
def test_every_experiment_holds_its_out_folder_for_the_whole_run(tmp_path, monkeypatch, name):
    """Two runs on one --out would mix their files (results.json of one, figures of the other): each run
    holds the folder's lock from before its work to after its last file, and leaves no lock file behind."""
    import importlib

    out = tmp_path / "a" / "out"
    seen = []

    def run(*args):
        lock = out / LOCK_NAME
        seen.append((lock.is_file() and _held_here(lock), (holder(lock) or {}).get("pid"),
                     (holder(lock) or {}).get("label")))
        return {}

    monkeypatch.setattr(importlib.import_module(f"experiments.{RUNS[name]}"), "run", run)
    importlib.import_module(f"experiments.{name}").main(["--out", str(out)])
    assert seen == [(True, os.getpid(), f"python -m experiments.{name}")]
    assert not (out / LOCK_NAME).exists()
    if name != "benchmark":  # its main writes results.json itself
        assert not (tmp_path / "a").exists()  # the folders the lock made, left empty, are gone again


def test_a_run_removes_what_a_killed_run_left_half_written_in_its_out_folder(tmp_path, monkeypatch):
    """A run killed while writing results.json leaves its temporary file; the next run on the folder
    removes it under the lock, and leaves the subfolders (other runs' folders, their own locks) alone."""
    import experiments.vehicles as vehicles

    out = tmp_path / "out"
    (out / "nested").mkdir(parents=True)
    stale, other = out / ".results.json.x1y2z3.tmp", out / "nested" / ".log.npz.a1b2.tmp"
    stale.write_text("{half")
    other.write_text("another run's")
    monkeypatch.setattr(vehicles, "run", lambda args: {})
    vehicles.main(["--out", str(out)])
    assert not stale.exists() and other.exists()


def test_a_second_run_on_one_out_folder_waits_for_the_first(tmp_path):
    """folder_lock's behaviour, as for a pipeline folder: the second run says who holds the folder, waits,
    and runs once it is free (a killed holder frees it at once)."""
    import select

    out = tmp_path / "out"
    proc = _holder(out, seconds=600)
    run = subprocess.Popen([sys.executable, "-m", "experiments.vehicles", "--out", str(out)], cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        deadline, said = time.monotonic() + 60, ""
        while "waiting for" not in said and time.monotonic() < deadline:
            if select.select([run.stderr], [], [], 1.0)[0]:
                said += run.stderr.readline()
        assert f"waiting for pid {proc.pid} on host" in said and str(out) in said, said
        time.sleep(0.5)
        assert run.poll() is None and not (out / "results.json").exists()
        proc.kill()
        proc.wait(timeout=30)
        assert run.wait(timeout=60) == 0, run.stderr.read()
        assert (out / "results.json").is_file()
    finally:
        for p in (proc, run):
            p.kill()
            p.wait(timeout=30)


# ----------------------------------------------------------------------------- the user's git


@pytest.mark.skipif(__import__("shutil").which("git") is None, reason="needs git")
def test_recording_the_code_version_takes_no_lock_of_the_users_git(tmp_path, monkeypatch):
    """Every run records the commit and whether the tree has changes. Plain `git status` refreshes the
    index under .git/index.lock (a user's git command at that moment fails on it) and rewrites it;
    with --no-optional-locks it leaves .git alone."""
    from downwash_core import provenance

    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(tmp_path)]
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "f.py").write_text("x = 1\n")
    subprocess.run([*git, "add", "f.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "one"], check=True)
    stamp = (tmp_path / "f.py").stat().st_mtime_ns + 5_000_000_000
    os.utime(tmp_path / "f.py", ns=(stamp, stamp))  # same content, new times: the index is stale
    index = tmp_path / ".git" / "index"
    before = (index.stat().st_ino, index.stat().st_mtime_ns, index.read_bytes())
    monkeypatch.setattr(provenance, "_ROOT", tmp_path)
    version = provenance.code_version.__wrapped__()
    assert version["commit"] and version["dirty"] is False
    assert (index.stat().st_ino, index.stat().st_mtime_ns, index.read_bytes()) == before
