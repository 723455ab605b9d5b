"""The one place that configures compiled kernels (numba).

The per-autopilot-tick work (field, autopilot, attitude set-points) runs at 100 Hz
on every world; as NumPy on small arrays its cost is dominated by per-call
overhead (about 1 us per operation), which made a single flight run at only a few
tens of times real time. These few kernels are compiled with numba instead:
explicit loops over the flattened batch, the same code for one world or many.
`cache=True` keeps the machine code on disk, so only the first import compiles.
numba checks a cached kernel against its own file only: after editing a module whose
compiled functions or constants a kernel elsewhere uses (`sim/fork_join.py`,
`sim/passes.py` and `sim/predictor.py`, used by `sim/fused.py`'s fused kernel), delete the caches
(`find . -name '*.nbi' -delete`) or touch that file, or the stale kernel runs. An install
writes every file afresh.
Strict IEEE arithmetic (no fastmath) keeps results bit-identical run to run.
"""

from __future__ import annotations

import numba

__all__ = ["njit"]


def njit(fn):
    """Compile `fn` in nopython mode, cached on disk, without fast-math reassociation."""
    return numba.njit(cache=True, fastmath=False, nogil=True)(fn)
