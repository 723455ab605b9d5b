"""Deprecated: the compiled-kernel helper moved to `core.jit`."""

import warnings

from core.jit import njit  # noqa: F401

__all__ = ["njit"]

warnings.warn("sim.jit is deprecated; import from core.jit instead", DeprecationWarning, stacklevel=2)
