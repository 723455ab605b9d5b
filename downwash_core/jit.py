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

Compiling takes about half a minute to a few minutes on two cores. So that a first flight or a
first env `reset()` does not look hung, the simulator calls `announce_first_compile` when it is
built: where no flight has run yet with this source, numba and CPU (`first_use_marker`), it logs
one warning saying so, once per process; `mark_compiled` (after the first tick) records that
one has. ``python -m experiments.warmup`` (``downwash-warmup``) compiles every kernel ahead.
"""

from __future__ import annotations

import hashlib
import logging
import os
from functools import lru_cache
from pathlib import Path

import numba

__all__ = ["njit", "njit_inline", "source_stamp", "install_locator", "KERNEL_PACKAGES", "first_use_marker", "announce_first_compile",
           "mark_compiled"]

log = logging.getLogger(__name__)

KERNEL_PACKAGES = ("downwash_core", "sim", "controllers", "downwash", "downwash_envs", "downwash_trajectories")
_ROOT = Path(__file__).resolve().parents[1]


def njit(fn):
    """Compile `fn` in nopython mode, cached on disk, without fast-math reassociation."""
    return numba.njit(cache=True, fastmath=False, nogil=True)(fn)


def njit_inline(fn):
    """`njit`, and inlined into every compiled caller (numba's IR inlining): a stage of the fused tick
    costs no call, and its bundles of arrays are not passed by value (a single world's tick is short)."""
    return numba.njit(cache=True, fastmath=False, nogil=True, inline="always")(fn)


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
    if any(getattr(c, "downwash_stamp", False) for c in impl._locator_classes):
        return True
    stamped = []
    for base in bases:
        def from_function(cls, py_func, py_file, _base=base):
            return _base.from_function.__func__(cls, py_func, py_file) if _ours(py_file) else None

        stamped.append(type(f"Stamped{base.__name__}", (base,), {
            "downwash_stamp": True,
            "get_source_stamp": lambda self: source_stamp(),
            "from_function": classmethod(from_function),
        }))
    impl._locator_classes[:0] = stamped  # (tried first, in numba's order: a user's cache dir, in-tree, user-wide)
    return True


def first_use_marker() -> Path:
    """The file whose presence says kernels of this source, numba and CPU have compiled here:
    under ``$XDG_CACHE_HOME`` (default ``~/.cache``), ``downwash-testbed/``."""
    from llvmlite import binding

    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "downwash-testbed"
    return root / f"kernels-{source_stamp()[:16]}-numba{numba.__version__}-{binding.get_host_cpu_name()}.compiled"


_pending: bool | None = None  # None: not asked yet in this process


def announce_first_compile() -> None:
    """Log one warning, once per process, when no flight has compiled the kernels here (module doc)."""
    global _pending
    if _pending is None:
        _pending = not first_use_marker().exists()
        if _pending:
            log.warning("compiling the simulator's kernels: the first flight after an install or an update takes "
                        "about half a minute to a few minutes, once (python -m experiments.warmup compiles them ahead)")


def mark_compiled() -> None:
    """Record that a flight ran (its kernels are compiled and cached); no-op when already recorded."""
    global _pending
    if _pending is False:
        return
    _pending = False
    marker = first_use_marker()
    try:  # a read-only home only means the notice shows again next time
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()
    except OSError:
        pass


install_locator()
