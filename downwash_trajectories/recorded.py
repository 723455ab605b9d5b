"""A reference that plays back recorded setpoints: a lab's logged trajectory flown again.

`Recorded(t, pos, vel=None, acc=None)` holds samples at times t (N,) s, shared by every world,
and plays them back linearly between samples. Velocity and acceleration are the recorded ones
when given, else derived: the velocity from the positions and the acceleration from the
velocity, each by central differences (`numpy.gradient`, second order on an uneven grid too,
so the derived velocity of a straight line at constant speed is its slope exactly; one-sided
at the two ends). Outside [t[0], t[-1]] the end positions are held, at rest (velocity and
acceleration 0: a held point does not move, and a controller fed the last sample's velocity
would fly on past it). Yaw is 0, like every other built-in reference.

A flight of several vehicles is one `Recorded` per vehicle, stacked with
`downwash_trajectories.combinators.stack`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError
from downwash_trajectories.base import RefSample, empty_sample, resolve_n_worlds, sample_times, single

__all__ = ["Recorded"]


def _times(t: ArrayLike) -> np.ndarray:
    """Sample times (N,) s; ConfigError unless finite, at least two and strictly increasing."""
    a = np.array(t, dtype=float)
    if a.ndim != 1 or a.size < 2:
        raise ConfigError(f"t: expected a 1-D array of at least 2 sample times (s), got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a))
    if bad.size:
        raise ConfigError(f"t: sample {bad[0]} is {a[bad[0]]}; allowed: finite times in s")
    steps = np.diff(a)
    if np.any(steps <= 0.0):
        k = int(np.argmax(steps <= 0.0)) + 1
        raise ConfigError(f"t: sample {k} ({float(a[k])!r} s) does not follow sample {k - 1} "
                          f"({float(a[k - 1])!r} s); allowed: strictly increasing times")
    return a


def _samples(name: str, x: ArrayLike, n: int, unit: str) -> np.ndarray:
    """x as (N, 3) or (W, N, 3) float; ConfigError naming a wrong shape or the first non-finite sample."""
    a = np.array(x, dtype=float)
    if a.ndim not in (2, 3) or a.shape[-2:] != (n, 3):
        raise ConfigError(f"{name}: expected shape ({n}, 3) or (W, {n}, 3) in {unit}, one row per sample time "
                          f"of t ({n}), got {a.shape}")
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        where = f"sample {bad[0][-2]}" + (f" of world {bad[0][0]}" if a.ndim == 3 else "")
        raise ConfigError(f"{name}: {where} is not finite; allowed: finite values in {unit}")
    return a


class Recorded:
    """Recorded setpoints played back: linear between samples, the ends held at rest outside, yaw 0.

    t: (N,) s, strictly increasing, N >= 2, shared by every world (the simulator's clock starts at
      0, so samples before t[0] hold the first one).
    pos: (W, N, 3) or (N, 3) m, world frame (z up); (N, 3) is shared by `n_worlds` worlds.
    vel: (W, N, 3) or (N, 3) m/s, or None: the central differences of `pos`.
    acc: (W, N, 3) or (N, 3) m/s^2, or None: the central differences of the velocity.
    n_worlds: number of worlds (inferred from batched arguments when given).
    `duration` is t[-1] (s): the time at which the recording ends on the simulator's clock.
    """

    def __init__(self, t: ArrayLike, pos: ArrayLike, vel: ArrayLike | None = None, acc: ArrayLike | None = None,
                 n_worlds: int | None = None) -> None:
        self.t = _times(t)  # (N,) s
        n = self.t.size
        p = _samples("pos", pos, n, "m")
        v = None if vel is None else _samples("vel", vel, n, "m/s")
        a = None if acc is None else _samples("acc", acc, n, "m/s^2")
        given = {"pos": p, "vel": v, "acc": a}
        self.n_worlds = w = resolve_n_worlds(n_worlds, {k: x.shape[0] for k, x in given.items()
                                                        if x is not None and x.ndim == 3})
        if v is None:
            v = np.gradient(p, self.t, axis=-2)
        if a is None:
            a = np.gradient(v, self.t, axis=-2)
        # (W, N, 3): pos, vel, acc, stacked so one gather serves all three
        self._values = np.stack([np.broadcast_to(x, (w, n, 3)) for x in (p, v, a)], axis=0).copy()
        self.duration: float = float(self.t[-1])

    @property
    def pos(self) -> np.ndarray:
        """(W, N, 3) m, the recorded positions."""
        return self._values[0]

    @property
    def vel(self) -> np.ndarray:
        """(W, N, 3) m/s, recorded or derived."""
        return self._values[1]

    @property
    def acc(self) -> np.ndarray:
        """(W, N, 3) m/s^2, recorded or derived."""
        return self._values[2]

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        vec, ang, _ = empty_sample(self.n_worlds, 1)
        self.sample_into(sample_times(t, self.n_worlds), vec, ang, 0)
        return single(vec, ang)

    def sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
        """Samples at t (W,) s into vehicle slot v of vec (3, W, V, 3), ang (2, W, V)."""
        knots = self.t
        # segment i holds t in [t_i, t_{i+1}); times outside are clamped to an end segment's end
        i = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, knots.size - 2)
        frac = np.clip((t - knots[i]) / (knots[i + 1] - knots[i]), 0.0, 1.0)[None, :, None]
        worlds = np.arange(self.n_worlds)
        lo, hi = self._values[:, worlds, i], self._values[:, worlds, i + 1]  # (3, W, 3)
        out = (1.0 - frac) * lo + frac * hi  # each end exactly at frac 0 and 1
        outside = (t < knots[0]) | (t > knots[-1])
        out[1:, outside] = 0.0  # held at rest
        vec[:, :, v] = out
        ang[:, :, v] = 0.0
