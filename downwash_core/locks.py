"""Cross-process locks on folders and files, so that concurrent runs share work instead of doing it twice.

    with folder_lock("runs/pipeline/so2-abc/collection", label="collection"):
        ...   # one process at a time in this folder; a second one waits here, then reuses the result

    with file_lock(cache / "cell.lock", wait=False, remove=True) as held:
        if held:
            ...   # this process computes it; another that tries now gets held == False and skips it

A lock is `fcntl.flock` on a lock file (`.lock` inside a folder), not a file that says
"taken": the kernel lets go when the holder's last descriptor closes, so a holder that
is killed (SIGKILL, a crash, a lost node's process) never leaves a stale lock behind.
The lock file also records who holds it (pid, host, time, label), for the one message
a waiter logs ("waiting for pid 123 on host h ... which holds ...").

Rules that keep it simple:
- Re-entrant within a process: taking a lock this process already holds nests (a
  pipeline that locks its folder may call another function that locks it too).
  Threads of one process share the locks; do not use them to exclude threads.
- A forked child does not keep its parent's locks (`os.register_at_fork`): the
  trainings the staged collection forks would otherwise hold the collection's lock
  after their parent died.
- `remove=True` deletes the lock file on release (one file per cache entry would
  pile up); a waiter that then gets the lock of a deleted file notices (the path no
  longer names the file it locked) and tries again on the new one, making its folder
  again if the holder removed that too (a folder it made and left empty).
- flock works on local file systems and NFSv4; a folder on a file system without
  locks, or one this process may not write (a read-only copy of a finished
  collection), is used without the lock, with a warning.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["LOCK_NAME", "folder_lock", "file_lock", "holder", "describe_holder"]

LOCK_NAME = ".lock"  # the lock file inside a locked folder
_POLL_S = 0.05  # how often a waiter with a timeout tries again

log = logging.getLogger(__name__)

_held: dict[str, list[int]] = {}  # absolute lock-file path -> [descriptor, depth]: this process's locks
_guard = threading.Lock()


def _forget_in_child() -> None:
    """In a forked child: close the inherited lock descriptors, so that only the parent holds the locks."""
    global _guard
    _guard = threading.Lock()  # another thread may have held it at the fork
    for fd, _ in _held.values():
        try:
            os.close(fd)
        except OSError:
            pass
    _held.clear()


os.register_at_fork(after_in_child=_forget_in_child)


def holder(path: str | os.PathLike) -> dict[str, Any] | None:
    """Who holds (or last held) the lock file at `path`: pid, host, since, label; None if unknown."""
    try:
        text = Path(path).read_text()
        info = json.loads(text) if text.strip() else None
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def describe_holder(path: str | os.PathLike) -> str:
    """"pid 123 on host h (collection, since 2026-01-01T00:00:00Z)", or "another process" if unknown."""
    info = holder(path)
    if not info:
        return "another process"
    since = f"since {info['since']}" if info.get("since") else None
    detail = ", ".join(str(x) for x in (info.get("label"), since) if x)
    return f"pid {info.get('pid')} on host {info.get('host')}" + (f" ({detail})" if detail else "")


def _same_file(fd: int, path: str) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (a.st_ino, a.st_dev) == (b.st_ino, b.st_dev)


def _acquire(path: str, wait: bool, timeout: float | None, label: str, target: str, quiet: bool) -> int | None:
    """A descriptor of `path` holding its exclusive flock, or None when not acquired (wait False or timed out)."""
    deadline = None if timeout is None else time.monotonic() + timeout
    announced = False
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except FileNotFoundError:  # a holder removed the folder of the lock file (it left it empty): make it again
            os.makedirs(os.path.dirname(path), exist_ok=True)
            continue
        acquired = poll = False
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not wait or (deadline is not None and time.monotonic() >= deadline):
                    return None
                if not announced:
                    (log.debug if quiet else log.info)("waiting for %s which holds %s", describe_holder(path), target)
                    announced = True
                poll = deadline is not None  # with a timeout: close, sleep a little, try again
                if not poll:
                    fcntl.flock(fd, fcntl.LOCK_EX)  # blocks; the kernel wakes it when the holder lets go
            # a holder that removes its file does so before letting go: then lock the new file
            if not poll and _same_file(fd, path):
                info = {"pid": os.getpid(), "host": socket.gethostname(), "label": label,
                        "since": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
                os.ftruncate(fd, 0)
                os.pwrite(fd, (json.dumps(info) + "\n").encode(), 0)
                acquired = True
                return fd
        finally:
            if not acquired:
                os.close(fd)  # not held (or no longer the file at `path`)
        if poll:
            time.sleep(min(_POLL_S, max(0.0, deadline - time.monotonic())))


@contextlib.contextmanager
def file_lock(
    path: str | os.PathLike,
    *,
    wait: bool = True,
    timeout: float | None = None,
    label: str = "",
    remove: bool = False,
    quiet: bool = False,
    target: str | os.PathLike | None = None,
) -> Iterator[bool]:
    """Hold the exclusive lock of the file at `path` (created, with its folder) for the block.

    Yields True while held. wait=False: yields False at once when another process
    holds it; timeout (s): yields False if it is not free by then. While waiting it
    logs once "waiting for <holder> which holds <target>" (INFO, DEBUG when quiet).
    remove: delete the lock file on release (see the module docstring). label and
    target (default `path`) are for the messages.
    """
    path = os.path.abspath(path)
    target = str(target if target is not None else path)
    with _guard:
        mine = _held.get(path)
        if mine is not None:
            mine[1] += 1
    if mine is not None:  # re-entered in this process
        try:
            yield True
        finally:
            with _guard:
                mine[1] -= 1
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = _acquire(path, wait, timeout, label, target, quiet)
    except OSError as e:
        if e.errno not in (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOLCK, errno.EOPNOTSUPP):
            raise
        log.warning("cannot lock %s (%s): going on without the lock; do not let two runs write there at once",
                    target, e.strerror)
        yield True
        return
    if fd is None:
        yield False
        return
    with _guard:
        _held[path] = entry = [fd, 1]
    try:
        yield True
    finally:
        with _guard:
            entry[1] -= 1
            last = entry[1] == 0 and _held.get(path) is entry
            if last:
                del _held[path]
        if last:
            if remove:  # while still holding it, so no one locks a file that is about to vanish unseen
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(path)
            os.close(fd)  # lets go


@contextlib.contextmanager
def folder_lock(
    folder: str | os.PathLike,
    *,
    wait: bool = True,
    timeout: float | None = None,
    label: str = "",
    quiet: bool = False,
) -> Iterator[bool]:
    """Hold the lock of `folder` (created if missing) for the block: `file_lock` on `folder/.lock`.

    Yields True while held, False when wait=False and another process holds it (or the
    timeout passed). A second process on the folder logs once "waiting for pid ... which
    holds <folder>" and goes on when the first lets go (or dies).
    """
    folder = Path(folder)
    with file_lock(folder / LOCK_NAME, wait=wait, timeout=timeout, label=label, quiet=quiet, target=folder) as held:
        yield held
