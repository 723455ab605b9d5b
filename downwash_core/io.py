"""Atomic writes and JSON: nothing already written is ever half-overwritten.

Every file the project writes goes through `atomic_write_bytes` (or, for a writer
that needs a path, `atomic_path`): a temporary file in the same folder, flushed to
disk, then renamed over the target. The file ends with the mode a plain `open()`
would give it: the target's own mode when it exists, else 0666 less the umask, so
lab-mates read what the umask lets them (a bare `mkstemp` file would stay 0600).

A process killed while writing (SIGKILL, a lost node) leaves its temporary file, named
``.<target>.<random>.tmp``; `remove_temporaries` clears them from a folder whose lock the
caller holds (so no live writer's file is taken), as each resumable run does when it starts.
"""

from __future__ import annotations

import dataclasses
import json
import os
import contextlib
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_json", "json_default", "plain_open_mode", "to_json",
           "remove_temporaries"]

_TEMPORARY_SUFFIX = ".tmp"  # what `atomic_path` names its temporary files with by default

_UMASK_LOCK = threading.Lock()


def _umask() -> int:
    try:  # Linux: read it without changing it
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    with _UMASK_LOCK:  # elsewhere the only way to read it is to set it (threads in this module wait)
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def plain_open_mode(path: str | os.PathLike) -> int:
    """The permission bits `open(path, "w")` would leave: the file's own if it exists, else 0666 less the umask."""
    try:
        return os.stat(path).st_mode & 0o7777
    except FileNotFoundError:
        return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = _TEMPORARY_SUFFIX) -> Iterator[Path]:
    """A temporary path beside `path` for a writer to fill; renamed over `path` when the block
    ends without an exception (with `plain_open_mode`), removed when it raises. A symlink is written
    through, as `open(path, "w")` would: its target is replaced and the link stays."""
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, plain_open_mode(path))
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write to a temporary file in the same folder, then rename: never a half file."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def json_default(o: Any) -> Any:
    """`json.dumps(default=...)` for NumPy scalars and arrays, paths, dataclasses and
    array-likes with `.tolist()` (torch tensors); anything else raises TypeError naming its type."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return dataclasses.asdict(o)
    if hasattr(o, "tolist"):  # np.ndarray, torch.Tensor
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def to_json(obj: Any, **kwargs: Any) -> str:
    """`json.dumps` with `json_default` and sorted keys."""
    return json.dumps(obj, sort_keys=True, default=json_default, **kwargs)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """Atomically write `obj` as indented JSON."""
    atomic_write_bytes(path, (to_json(obj, indent=2) + "\n").encode())


def remove_temporaries(folder: str | os.PathLike, recursive: bool = True) -> list[Path]:
    """Remove the temporary files that killed writers left in `folder` (and, with `recursive`, its
    subfolders): ``.*.tmp``, as `atomic_path` names them; returns them. Only under the lock of every
    folder searched (`downwash_core.locks.folder_lock`): a live writer there would lose its file."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = folder.rglob if recursive else folder.glob
    stale = [p for p in found(f".*{_TEMPORARY_SUFFIX}") if p.is_file() and not p.is_symlink()]
    for p in stale:
        p.unlink(missing_ok=True)
    return stale
