"""The one place that configures compiled kernels (numba).

The per-autopilot-tick work (field, autopilot, attitude set-points) runs at 100 Hz
on every world; as NumPy on small arrays its cost is dominated by per-call
overhead (about 1 us per operation), which made a single flight run at only a few
tens of times real time. These few kernels are compiled with numba instead:
explicit loops over the flattened batch, the same code for one world or many.
`cache=True` keeps the machine code on disk, so only the first import compiles.
Strict IEEE arithmetic (no fastmath) keeps results bit-identical run to run.

A cached kernel is stamped with the source of the whole compiled stack (`source_stamp`:
every module of the packages in `KERNEL_PACKAGES`), not of its own file alone as numba
stamps it: a kernel compiles in the functions and constants of other modules (the fused
tick calls the autopilot's mixer, the guard's pass, the field), and numba's own stamp
would load the stale machine code after one of those was edited. Editing any module of
those packages therefore recompiles every kernel on its next use (a minute or so, once).
The stamp is installed as a cache locator (`install_locator`, at import); with a numba
whose caching internals differ it is left out, numba's own stamp applies, and the caches
must be deleted by hand after such an edit (``find . -name '*.nbi' -delete``).
"""

from __future__ import annotations

import hashlib
from functools import lru_cache
from pathlib import Path

import numba

__all__ = ["njit", "source_stamp", "install_locator", "KERNEL_PACKAGES"]

KERNEL_PACKAGES = ("downwash_core", "sim", "controllers", "downwash", "downwash_envs", "downwash_trajectories")
_ROOT = Path(__file__).resolve().parents[1]


def njit(fn):
    """Compile `fn` in nopython mode, cached on disk, without fast-math reassociation."""
    return numba.njit(cache=True, fastmath=False, nogil=True)(fn)


@lru_cache(maxsize=1)
def source_stamp() -> str:
    """SHA-256 over the path and bytes of every module of `KERNEL_PACKAGES`, in path order."""
    h = hashlib.sha256()
    for package in KERNEL_PACKAGES:
        for path in sorted((_ROOT / package).rglob("*.py")):
            h.update(path.relative_to(_ROOT).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def _ours(py_file: str) -> bool:
    try:
        first = Path(py_file).resolve().relative_to(_ROOT).parts[0]
    except (ValueError, IndexError):
        return False
    return first in KERNEL_PACKAGES


def install_locator() -> bool:
    """Stamp this project's cached kernels with `source_stamp` (module doc); True when installed.
    Idempotent; kernels of other projects keep numba's own locators."""
    try:
        from numba.core import caching

        impl = caching.CacheImpl
        bases = (caching.UserProvidedCacheLocator, caching.InTreeCacheLocator, caching.UserWideCacheLocator)
        if not (isinstance(impl._locator_classes, list) and all(hasattr(b, "get_source_stamp") for b in bases)):
            return False
    except (ImportError, AttributeError):
        return False
    if any(getattr(c, "_downwash_stamp", False) for c in impl._locator_classes):
        return True
    stamped = []
    for base in bases:
        def from_function(cls, py_func, py_file, _base=base):
            return _base.from_function.__func__(cls, py_func, py_file) if _ours(py_file) else None

        stamped.append(type(f"Stamped{base.__name__}", (base,), {
            "_downwash_stamp": True,
            "get_source_stamp": lambda self: source_stamp(),
            "from_function": classmethod(from_function),
        }))
    impl._locator_classes[:0] = stamped  # (tried first, in numba's order: a user's cache dir, in-tree, user-wide)
    return True


install_locator()
