"""What every reference shares: the protocol, sample times and the in-place sample layout.

A reference serves W worlds at once and is sampled with `ref(t)`, `t` a float (all
worlds share it) or an array (W,) of per-world times; it returns a `RefSample`
(position, velocity, acceleration, yaw, yaw rate; world frame, z up, SI units),
derived analytically so that the outer loop's feed-forward `a_ref` is exact.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError
from downwash_core.state import RefSample
from downwash_core.validate import count

__all__ = ["RefSample", "Reference", "resolve_n_worlds", "leading_sizes", "sample_times", "zero_yaw",
           "duration_of", "empty_sample", "single"]


@runtime_checkable
class Reference(Protocol):
    """A batched reference: `ref(t) -> RefSample` for `n_worlds` worlds.

    `t` is a float (s, shared by all worlds) or an array (W,) of per-world times.
    `duration` (s, float or (W,)) is the natural length: one period, or the whole
    waypoint pattern. Sampling beyond it is allowed: periodic references continue,
    waypoint patterns hold their last point.
    """

    n_worlds: int
    duration: np.ndarray | float

    def __call__(self, t: float | ArrayLike) -> RefSample: ...



def resolve_n_worlds(n_worlds: int | None, batched: dict[str, int]) -> int:
    """World count from the explicit `n_worlds` and the leading sizes of batched args."""
    n_worlds = None if n_worlds is None else count("n_worlds", n_worlds)
    sizes = set(batched.values())
    if len(sizes) > 1:
        detail = ", ".join(f"{k}: {v}" for k, v in batched.items())
        raise ConfigError(f"batched arguments disagree on the number of worlds ({detail})")
    if sizes:
        (size,) = sizes
        if n_worlds is not None and n_worlds != size:
            name = next(iter(batched))
            raise ConfigError(f"n_worlds: got {n_worlds} but {name} is batched over {size} worlds")
        return size
    return 1 if n_worlds is None else n_worlds


def leading_sizes(batched: dict[str, np.ndarray], ndim_unbatched: dict[str, int]) -> dict[str, int]:
    """{name: leading size} of the arrays that carry a world axis."""
    return {k: v.shape[0] for k, v in batched.items() if v.ndim > ndim_unbatched[k]}


def sample_times(t: float | ArrayLike, n_worlds: int) -> np.ndarray:
    """Sample times as (W,) float array."""
    if type(t) is np.ndarray and t.dtype == np.float64 and t.shape == (n_worlds,):
        return t  # the simulator's clock, sampled at 50 Hz: nothing to convert
    a = np.asarray(t, dtype=float)
    if a.ndim == 0:
        return np.full(n_worlds, float(a))
    if a.shape != (n_worlds,):
        raise ConfigError(f"t: expected a float or shape ({n_worlds},), got {a.shape}")
    return a


def zero_yaw(n_worlds: int) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(n_worlds), np.zeros(n_worlds)


def duration_of(period: np.ndarray) -> np.ndarray | float:
    """A reference's `duration` from its period (W,): a float when not batched."""
    return float(period) if period.ndim == 0 else period.copy()


# Stacked samples are filled in place: vec (3, W, V, 3) holds pos, vel, acc and ang (2, W, V)
# yaw, yaw_rate, and a reference with `sample_into(t, vec, ang, v)` writes vehicle v's
# slots directly (the 50 Hz control path; a copy per field cost more than the sample). A class
# with `group_into(refs, shifts)` gives one `into(t, vec, ang, slots)` for all its references
# in a stack (see `combinators.StackedReference`): one call for the group, not one each.


def empty_sample(n_worlds: int, n_vehicles: int) -> tuple[np.ndarray, np.ndarray, RefSample]:
    """Uninitialised (vec, ang) storage and the RefSample of views into it."""
    vec, ang = np.empty((3, n_worlds, n_vehicles, 3)), np.empty((2, n_worlds, n_vehicles))
    return vec, ang, RefSample(vec[0], vec[1], vec[2], ang[0], ang[1])


def single(vec: np.ndarray, ang: np.ndarray) -> RefSample:
    """The (W, 3) / (W,) RefSample of a one-vehicle (vec, ang)."""
    return RefSample(vec[0, :, 0], vec[1, :, 0], vec[2, :, 0], ang[0, :, 0], ang[1, :, 0])
