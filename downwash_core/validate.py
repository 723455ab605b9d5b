"""Argument checks at the boundary: each raises `ConfigError` naming the argument,
what was given and what is allowed, before any work starts."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError

__all__ = [
    "choice",
    "number",
    "pair",
    "positive_float",
    "ordered_range",
    "count",
    "vec3",
    "scalar_or_world",
    "check_trailing_shapes",
]


def choice(name: str, value: Any, allowed: Sequence[Any]) -> Any:
    """`value` if it is one of `allowed`, else ConfigError listing them."""
    if isinstance(value, bool) or value not in allowed:
        raise ConfigError(f"{name}: got {value!r}; allowed: {', '.join(map(str, allowed))}")
    return value


def number(name: str, value: Any, unit: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
    """A finite float in [lo, hi] (or (lo, hi] with lo_open)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected a number ({unit}), got {value!r}") from None
    ok = (v > lo if lo_open else v >= lo) and v <= hi and math.isfinite(v)
    if not ok:
        rng = f"({lo}, {hi}]" if lo_open else f"[{lo}, {hi}]"
        raise ConfigError(f"{name}: got {value!r}; allowed {rng} {unit}")
    return v


def pair(name: str, value: Any, unit: str, lo: float, hi: float) -> tuple[float, float]:
    """(low, high) with lo <= low <= high <= hi."""
    try:
        a, b = (float(x) for x in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected (low, high) within {lo}-{hi} {unit}, got {value!r}") from None
    if not (math.isfinite(a) and math.isfinite(b) and lo <= a <= b <= hi):
        raise ConfigError(f"{name}: got {value!r}; allowed (low, high) with {lo} <= low <= high <= {hi} {unit}")
    return a, b


def positive_float(name: str, x: Any, unit: str, *, allow_zero: bool = False) -> float:
    """A finite float > 0 (>= 0 with allow_zero)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected a number ({unit}), got {x!r}") from None
    if not np.isfinite(v) or (v < 0.0 if allow_zero else v <= 0.0):
        bound = ">= 0" if allow_zero else "> 0"
        raise ConfigError(f"{name}: must be finite and {bound} {unit}, got {x!r}")
    return v


def ordered_range(name: str, r: Sequence[float], unit: str, lo: float, hi: float) -> tuple[float, float]:
    """(low, high) with lo <= low <= high <= hi (low > 0 when lo is 0)."""
    if lo > 0:
        allowed = f"allowed {lo}-{hi} {unit}"
    elif np.isfinite(hi):
        allowed = f"allowed > 0 and <= {hi} {unit}"
    else:
        allowed = f"allowed > 0 {unit}"
    try:
        a, b = (float(v) for v in r)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected (low, high), got {r!r}; {allowed}, with low <= high") from None
    ok_lo = a > 0.0 if lo == 0 else a >= lo - 1e-12
    if not (np.isfinite(a) and np.isfinite(b) and ok_lo and b <= hi + 1e-12 and a <= b):
        raise ConfigError(f"{name}: got {r!r}; {allowed}, with low <= high")
    return a, b


def count(name: str, value: Any, lo: int = 1, hi: int | None = None) -> int:
    """An integer (not a bool) in [lo, hi]."""
    ok = not isinstance(value, bool) and isinstance(value, (int, np.integer)) and value >= lo
    ok = ok and (hi is None or value <= hi)
    if not ok:
        allowed = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ConfigError(f"{name}: expected an integer {allowed}, got {value!r}")
    return int(value)


def vec3(name: str, x: ArrayLike) -> np.ndarray:
    """Finite (3,) or (W, 3) float array."""
    a = np.array(x, dtype=float)
    if not (a.shape == (3,) or (a.ndim == 2 and a.shape[1] == 3 and a.shape[0] >= 1)):
        raise ConfigError(f"{name}: expected shape (W, 3) or (3,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: must be finite")
    return a


def scalar_or_world(name: str, x: ArrayLike, unit: str, *, allow_zero: bool = False) -> np.ndarray:
    """Finite positive (or non-negative) float or (W,) array."""
    a = np.array(x, dtype=float)
    if a.ndim > 1 or (a.ndim == 1 and a.shape[0] < 1):
        raise ConfigError(f"{name}: expected a float or shape (W,), got {a.shape}")
    bad = ~np.isfinite(a) | ((a < 0.0) if allow_zero else (a <= 0.0))
    if np.any(bad):
        bound = ">= 0" if allow_zero else "> 0"
        raise ConfigError(f"{name}: must be finite and {bound} {unit}, got {x!r}")
    return a


def check_trailing_shapes(shapes: dict[str, tuple[int, ...]], tail: dict[str, tuple[int, ...]]) -> None:
    """Raise ConfigError naming the first array whose trailing dims differ from `tail`,
    or all of them when their batch shapes do not broadcast against each other."""
    batches = []
    for name, shape in shapes.items():
        want = tail[name]
        if len(shape) < len(want) or tuple(shape[len(shape) - len(want):]) != want:
            pretty = "(..., " + ", ".join(str(d) for d in want) + ")"
            raise ConfigError(f"{name}: expected {pretty} but found {tuple(shape)}")
        batches.append((name, tuple(shape[: len(shape) - len(want)])))
    try:
        np.broadcast_shapes(*(b for _, b in batches))
    except ValueError:
        found = ", ".join(f"{name} {b}" for name, b in batches)
        raise ConfigError(f"batch shapes do not broadcast: {found}") from None
