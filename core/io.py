"""Atomic writes and JSON: nothing already written is ever half-overwritten.

Every file the project writes goes through `atomic_write_bytes`: a temporary file
in the same folder, flushed to disk, then renamed over the target.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write_bytes", "atomic_write_json", "json_default", "to_json"]


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write to a temporary file in the same folder, then rename: never a half file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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
