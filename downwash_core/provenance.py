"""Provenance: what made an artifact, recorded with it and checked before it is reused.

Every log, collection manifest, checkpoint and results file records a provenance
record: the field, the scene, the configuration, the seed base and the code version.
`describe` turns the objects involved into stable JSON (no memory addresses),
`fingerprint` hashes a record into a short key, and `differences` says, field by
field, how two records differ, for errors that tell the user what changed.

The code version is recorded but kept out of the key (`KEY_EXCLUDES`): most commits
do not change what a collection means, and `tests/test_golden.py` guards the numbers;
a reuse across code versions is logged as a warning instead.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.io import to_json

__all__ = ["KEY_EXCLUDES", "describe", "fingerprint", "differences", "code_version"]

KEY_EXCLUDES = ("code",)  # provenance entries recorded but not part of the key
_ROOT = Path(__file__).resolve().parent.parent


def describe(obj: Any) -> Any:
    """A stable, JSON-serialisable description of `obj` for provenance.

    Objects with a `describe()` method give their own; dataclasses give their class and
    fields; plain values, arrays and containers give themselves; functions their import
    path; other objects their class and attributes, when those are describable. An
    object that cannot be described stably raises ConfigError: give it a `describe()`
    method that returns its parameters.
    """
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (list, tuple)):
        return [describe(x) for x in obj]
    if isinstance(obj, dict):
        return {str(k): describe(v) for k, v in obj.items()}
    if isinstance(obj, Path):
        return str(obj)
    if callable(getattr(obj, "describe", None)) and not isinstance(obj, type):
        return describe(obj.describe())
    name = f"{type(obj).__module__}.{type(obj).__qualname__}"
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"type": name, **{f.name: describe(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, (type, functools.partial)) or callable(obj) and hasattr(obj, "__qualname__"):
        if isinstance(obj, functools.partial):
            return {"type": "partial", "func": describe(obj.func), "args": describe(obj.args),
                    "keywords": describe(obj.keywords)}
        return {"type": "callable", "name": f"{obj.__module__}.{obj.__qualname__}"}
    attributes = {k: v for k, v in vars(obj).items() if not k.startswith("_")} if hasattr(obj, "__dict__") else {}
    try:
        return {"type": name, **{k: describe(v) for k, v in sorted(attributes.items())}}
    except ConfigError:
        raise ConfigError(
            f"cannot describe a {name} for provenance (its attributes are not plain values); give it a "
            "describe() method that returns its parameters as a dict"
        ) from None


def fingerprint(record: dict[str, Any], length: int = 12) -> str:
    """A short hex key of a provenance record, without the KEY_EXCLUDES entries."""
    keyed = {k: v for k, v in record.items() if k not in KEY_EXCLUDES}
    return hashlib.sha256(to_json(keyed).encode()).hexdigest()[:length]


def differences(have: Any, want: Any, path: str = "", limit: int = 12) -> list[str]:
    """Leaf-by-leaf differences between two descriptions: ["field.strength: 10.6 here, 5.0 asked for", ...]."""
    out: list[str] = []
    have, want = json.loads(to_json(have)), json.loads(to_json(want))  # tuples vs lists, numpy vs float

    def walk(a: Any, b: Any, where: str) -> None:
        if len(out) >= limit:
            return
        if isinstance(a, dict) and isinstance(b, dict):
            for k in sorted(set(a) | set(b)):
                if k in KEY_EXCLUDES and not where:
                    continue
                walk(a.get(k, "<missing>"), b.get(k, "<missing>"), f"{where}.{k}" if where else k)
        elif a != b:
            out.append(f"{where or '<record>'}: {_short(a)} here, {_short(b)} asked for")

    walk(have, want, path)
    return out


def _short(x: Any, n: int = 80) -> str:
    text = json.dumps(x, sort_keys=True)
    return text if len(text) <= n else text[: n - 3] + "..."


@functools.lru_cache(maxsize=1)
def code_version() -> dict[str, Any]:
    """The package version and, in a git checkout, the commit and whether the tree has changes."""
    try:
        version = metadata.version("downwash-testbed")
    except metadata.PackageNotFoundError:
        version = None
    commit, dirty = None, None
    # --no-optional-locks: `git status` would otherwise refresh the index under .git/index.lock, and the
    # user's own git command at that moment would fail on the lock
    git = ["git", "--no-optional-locks"]
    try:
        commit = subprocess.run([*git, "rev-parse", "HEAD"], cwd=_ROOT, capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip() or None
        status = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], cwd=_ROOT,
                                capture_output=True, text=True, timeout=5, check=True).stdout
        dirty = bool(status.strip())
    except (OSError, subprocess.SubprocessError):
        pass  # not a git checkout (an installed copy): the package version is all there is
    return {"version": version, "commit": commit, "dirty": dirty}
