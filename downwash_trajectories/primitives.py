"""The closed-form references: hover points, the paper's lemniscate and transect, lines, circles.

- `Hover`: fixed points.
- `Lemniscate`: the paper's figure-eight (lemniscate of Gerono) beneath the leader.
- `Transect`: the paper's back-and-forth pass along world y, offset in x.
- `Line`, `Circle`: a leader that translates at constant speed (the outdoor regime of
  the paper's future work), in a straight line or around a horizontal circle.

Each serves W worlds (each world may have its own parameters) and has analytic derivatives;
all but `Line` have a compiled `sample_into` for stacking, and `Circle` a `group_into` that
fills all the circles of a stack in one call (see `downwash_trajectories.base`); the tests
check every derivative against finite differences. Waypoint patterns (`Waypoints`,
`MIN_JERK_PEAK`) live in `downwash_trajectories.waypoints`, importable from here too.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.validate import positive_float, scalar_or_world, vec3
from downwash_trajectories.base import (
    RefSample,
    duration_of,
    empty_sample,
    leading_sizes,
    resolve_n_worlds,
    sample_times,
    single,
    zero_yaw,
)
from downwash_trajectories.waypoints import MIN_JERK_PEAK, Waypoints  # noqa: F401  (importable from here, as before)

__all__ = ["Hover", "Lemniscate", "Transect", "Waypoints", "Line", "Circle", "MIN_JERK_PEAK"]


@njit
def _hover_into(points, vec, ang, v):
    """Hover samples (points (W, 3) m) into vehicle slot v of vec (3, W, V, 3), ang (2, W, V)."""
    for w in range(points.shape[0]):
        for k in range(3):
            vec[0, w, v, k] = points[w, k]
            vec[1, w, v, k] = 0.0
            vec[2, w, v, k] = 0.0
        ang[0, w, v] = 0.0
        ang[1, w, v] = 0.0


@njit
def _lemniscate_into(t, omega, center, a, b, vec, ang, v):
    """Lemniscate samples at t (W,) s into vehicle slot v of vec (3, W, V, 3), ang (2, W, V)."""
    for w in range(t.shape[0]):
        om = omega[w]
        th = om * t[w]
        c1, s1 = np.cos(th), np.sin(th)
        c2, s2 = np.cos(2.0 * th), np.sin(2.0 * th)
        vec[0, w, v, 0] = center[w, 0] + a[w] * c1
        vec[0, w, v, 1] = center[w, 1] + b[w] * s2
        vec[0, w, v, 2] = center[w, 2]
        vec[1, w, v, 0] = -a[w] * om * s1
        vec[1, w, v, 1] = 2.0 * b[w] * om * c2
        vec[1, w, v, 2] = 0.0
        vec[2, w, v, 0] = -a[w] * om * om * c1
        vec[2, w, v, 1] = -4.0 * b[w] * om * om * s2
        vec[2, w, v, 2] = 0.0
        ang[0, w, v] = 0.0
        ang[1, w, v] = 0.0


@njit
def _transect_into(t, omega, base, half_length, vec, ang, v):
    """Transect samples at t (W,) s into vehicle slot v of vec (3, W, V, 3), ang (2, W, V)."""
    for w in range(t.shape[0]):
        om = omega[w]
        th = om * t[w]
        c, s = np.cos(th), np.sin(th)
        hl = half_length[w]
        vec[0, w, v, 0] = base[w, 0]
        vec[0, w, v, 1] = base[w, 1] - hl * c
        vec[0, w, v, 2] = base[w, 2]
        vec[1, w, v, 0] = 0.0
        vec[1, w, v, 1] = hl * om * s
        vec[1, w, v, 2] = 0.0
        vec[2, w, v, 0] = 0.0
        vec[2, w, v, 1] = hl * om * om * c
        vec[2, w, v, 2] = 0.0
        ang[0, w, v] = 0.0
        ang[1, w, v] = 0.0


@njit
def _circles_into(t, vec, ang, slots, shift, phase, omega, center, radius):
    """Circle g at t (W,) + shift (W, G) s into vehicle slot slots[g] of vec (3, W, V, 3), ang (2, W, V).

    phase, omega, radius: (W, G); center: (W, G, 3). Element by element, so a circle's sample
    is the same bits whichever group (or none) it is sampled in.
    """
    for w in range(t.shape[0]):
        for g in range(slots.shape[0]):
            v = slots[g]
            r, om = radius[w, g], omega[w, g]
            th = phase[w, g] + om * (t[w] + shift[w, g])
            c, s = np.cos(th), np.sin(th)
            vec[0, w, v, 0] = center[w, g, 0] + r * c
            vec[0, w, v, 1] = center[w, g, 1] + r * s
            vec[0, w, v, 2] = center[w, g, 2] + 0.0  # as NumPy's center + [.., .., 0]: -0.0 becomes 0.0
            vec[1, w, v, 0] = -r * om * s
            vec[1, w, v, 1] = r * om * c
            vec[1, w, v, 2] = 0.0
            vec[2, w, v, 0] = -r * om * om * c
            vec[2, w, v, 1] = -r * om * om * s
            vec[2, w, v, 2] = 0.0
            ang[0, w, v] = 0.0
            ang[1, w, v] = 0.0


# ----------------------------------------------------------------------------- simple references


class Hover:
    """Hold fixed points: zero velocity and acceleration, yaw 0.

    points: (W, 3) or (3,) m, world frame (z up); (3,) is shared by `n_worlds` worlds.
    n_worlds: number of worlds (inferred from `points` when batched).
    duration: s, the length a caller should fly it for (a hover has no natural
        end; default 0.0). Sampling at any time returns the points.
    """

    def __init__(self, points: ArrayLike, n_worlds: int | None = None, duration: float = 0.0) -> None:
        p = vec3("points", points)
        self.n_worlds = resolve_n_worlds(n_worlds, {"points": p.shape[0]} if p.ndim == 2 else {})
        self.points = np.broadcast_to(p, (self.n_worlds, 3)).copy()  # (W, 3) m
        self.duration: float = positive_float("duration", duration, "s", allow_zero=True)

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)): the points, zeros elsewhere."""
        sample_times(t, self.n_worlds)
        w = self.n_worlds
        yaw, yaw_rate = zero_yaw(w)
        return RefSample(self.points.copy(), np.zeros((w, 3)), np.zeros((w, 3)), yaw, yaw_rate)

    def sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
        _hover_into(self.points, vec, ang, v)


class Lemniscate:
    """Horizontal figure-eight (lemniscate of Gerono) around `center`, constant z.

    With theta = 2 pi t / period::

        x = cx + half_length * cos(theta)
        y = cy + half_width  * sin(2 theta)
        z = cz

    t = 0 is at a tip (x = cx + half_length, y = cy); the crossing point
    (cx, cy) -- which the experiments put directly beneath the leader -- is passed
    at t = period / 4 and 3 period / 4 (mod period). `half_width` is the largest
    |y - cy| (the classic Gerono curve is half_width = half_length / 2).
    Velocity and acceleration are analytic; yaw is 0.

    center: (W, 3) or (3,) m, world frame (z up).
    half_length: m, float or (W,), > 0; half the extent along world x.
    half_width: m, float or (W,), > 0; half the extent along world y.
    period: s, float or (W,), > 0.
    n_worlds: number of worlds (inferred from batched arguments when given).
    """

    def __init__(
        self,
        center: ArrayLike,
        half_length: float | ArrayLike = 1.0,
        half_width: float | ArrayLike = 0.5,
        period: float | ArrayLike = 20.0,
        n_worlds: int | None = None,
    ) -> None:
        c = vec3("center", center)
        a = scalar_or_world("half_length", half_length, "m")
        b = scalar_or_world("half_width", half_width, "m")
        per = scalar_or_world("period", period, "s")
        args = {"center": c, "half_length": a, "half_width": b, "period": per}
        self.n_worlds = resolve_n_worlds(
            n_worlds, leading_sizes(args, {"center": 1, "half_length": 0, "half_width": 0, "period": 0})
        )
        w = self.n_worlds
        self.center = np.broadcast_to(c, (w, 3)).copy()  # (W, 3) m
        self.half_length = np.broadcast_to(a, (w,)).copy()  # (W,) m
        self.half_width = np.broadcast_to(b, (w,)).copy()  # (W,) m
        self.period = np.broadcast_to(per, (w,)).copy()  # (W,) s
        self.duration: np.ndarray | float = duration_of(per)
        self._omega = 2.0 * np.pi / self.period  # (W,) rad/s

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        vec, ang, _ = empty_sample(self.n_worlds, 1)
        self.sample_into(sample_times(t, self.n_worlds), vec, ang, 0)
        return single(vec, ang)

    def sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
        _lemniscate_into(t, self._omega, self.center, self.half_length, self.half_width, vec, ang, v)


class Transect:
    """Back and forth along world y at a fixed x offset, constant z (paper 5.D).

    With theta = 2 pi t / period::

        x = cx + x_offset
        y = cy - half_length * cos(theta)
        z = cz

    so t = 0 is at the y = cy - half_length end, the centre is crossed at peak
    speed (2 pi half_length / period) at period / 4 and 3 period / 4, and the
    far end is reached at period / 2. The paper's transect: `center` the point
    0.6 m directly below the leader, x_offset 0.2 m. Yaw is 0.

    center: (W, 3) or (3,) m, world frame (z up).
    x_offset: m, float or (W,) (any sign).
    half_length: m, float or (W,), > 0.
    period: s, float or (W,), > 0.
    n_worlds: number of worlds (inferred from batched arguments when given).
    """

    def __init__(
        self,
        center: ArrayLike,
        x_offset: float | ArrayLike = 0.2,
        half_length: float | ArrayLike = 1.2,
        period: float | ArrayLike = 12.0,
        n_worlds: int | None = None,
    ) -> None:
        c = vec3("center", center)
        xo = np.array(x_offset, dtype=float)
        if xo.ndim > 1 or (xo.ndim == 1 and xo.shape[0] < 1) or not np.all(np.isfinite(xo)):
            raise ConfigError(f"x_offset: expected a finite float or shape (W,) in m, got {x_offset!r}")
        hl = scalar_or_world("half_length", half_length, "m")
        per = scalar_or_world("period", period, "s")
        args = {"center": c, "x_offset": xo, "half_length": hl, "period": per}
        self.n_worlds = resolve_n_worlds(
            n_worlds, leading_sizes(args, {"center": 1, "x_offset": 0, "half_length": 0, "period": 0})
        )
        w = self.n_worlds
        self.center = np.broadcast_to(c, (w, 3)).copy()  # (W, 3) m
        self.x_offset = np.broadcast_to(xo, (w,)).copy()  # (W,) m
        self.half_length = np.broadcast_to(hl, (w,)).copy()  # (W,) m
        self.period = np.broadcast_to(per, (w,)).copy()  # (W,) s
        self.duration: np.ndarray | float = duration_of(per)
        self._omega = 2.0 * np.pi / self.period  # (W,) rad/s
        self._base = self.center.copy()
        self._base[:, 0] += self.x_offset

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        vec, ang, _ = empty_sample(self.n_worlds, 1)
        self.sample_into(sample_times(t, self.n_worlds), vec, ang, 0)
        return single(vec, ang)

    def sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
        _transect_into(t, self._omega, self._base, self.half_length, vec, ang, v)


class Line:
    """Constant velocity in a straight line: pos = start + velocity t, acceleration 0, yaw 0.

    start: (W, 3) or (3,) m, world frame (z up): the position at t = 0.
    velocity: (W, 3) or (3,) m/s, world frame.
    duration: s, the length a caller should fly it for (default 10 s).
    n_worlds: number of worlds (inferred from batched arguments when given).
    """

    def __init__(self, start: ArrayLike, velocity: ArrayLike, duration: float = 10.0, n_worlds: int | None = None) -> None:
        p0, v = vec3("start", start), vec3("velocity", velocity)
        batched = {k: a.shape[0] for k, a in (("start", p0), ("velocity", v)) if a.ndim == 2}
        self.n_worlds = w = resolve_n_worlds(n_worlds, batched)
        self.start = np.broadcast_to(p0, (w, 3)).copy()  # (W, 3) m
        self.velocity = np.broadcast_to(v, (w, 3)).copy()  # (W, 3) m/s
        self.duration: float = positive_float("duration", duration, "s")

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        t = sample_times(t, self.n_worlds)
        yaw, yaw_rate = zero_yaw(self.n_worlds)
        return RefSample(self.start + t[:, None] * self.velocity, self.velocity.copy(), np.zeros((self.n_worlds, 3)),
                         yaw, yaw_rate)


class Circle:
    """A horizontal circle at constant speed around `center`, constant z, yaw 0.

    With theta = phase + (speed / radius) t::

        pos = center + radius [cos theta, sin theta, 0]

    so the speed is `speed` (m/s) and the acceleration `speed^2 / radius`, centripetal;
    a negative speed turns clockwise (seen from above).

    center: (W, 3) or (3,) m, world frame (z up).
    radius: m, float or (W,), > 0.
    speed: m/s, float or (W,), any sign, |speed| > 0.
    phase: rad, float or (W,): the angle at t = 0.
    n_worlds: number of worlds (inferred from batched arguments when given).
    `duration` is one lap (s).
    """

    def __init__(
        self,
        center: ArrayLike,
        radius: float | ArrayLike = 2.0,
        speed: float | ArrayLike = 1.0,
        phase: float | ArrayLike = 0.0,
        n_worlds: int | None = None,
    ) -> None:
        c = vec3("center", center)
        r = scalar_or_world("radius", radius, "m")
        v = np.array(speed, dtype=float)
        ph = np.array(phase, dtype=float)
        for name, a, unit in (("speed", v, "m/s"), ("phase", ph, "rad")):
            if a.ndim > 1 or not np.all(np.isfinite(a)):
                raise ConfigError(f"{name}: expected a finite float or shape (W,) in {unit}, got {a!r}")
        if np.any(v == 0.0):
            raise ConfigError(f"speed: must be non-zero (m/s; its sign sets the direction), got {speed!r}")
        args = {"center": c, "radius": r, "speed": v, "phase": ph}
        self.n_worlds = w = resolve_n_worlds(
            n_worlds, leading_sizes(args, {"center": 1, "radius": 0, "speed": 0, "phase": 0})
        )
        self.center = np.broadcast_to(c, (w, 3)).copy()  # (W, 3) m
        self.radius = np.broadcast_to(r, (w,)).copy()  # (W,) m
        self.speed = np.broadcast_to(v, (w,)).copy()  # (W,) m/s
        self.phase = np.broadcast_to(ph, (w,)).copy()  # (W,) rad
        self._omega = self.speed / self.radius  # (W,) rad/s
        # _circles_into's arguments as a group of one (shift -0.0: t + -0.0 is t bit for bit, even t = -0.0)
        self._alone = (np.full((w, 1), -0.0), self.phase[:, None], self._omega[:, None], self.center[:, None],
                       self.radius[:, None])
        lap = 2.0 * np.pi * self.radius / np.abs(self.speed)
        self.duration: np.ndarray | float = float(lap[0]) if np.ndim(r) == 0 and v.ndim == 0 else lap

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        vec, ang, _ = empty_sample(self.n_worlds, 1)
        self.sample_into(sample_times(t, self.n_worlds), vec, ang, 0)
        return single(vec, ang)

    def sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
        _circles_into(t, vec, ang, np.array([v]), *self._alone)

    @classmethod
    def group_into(cls, circles: list["Circle"], shifts: list[np.ndarray | None]):
        """`into(t, vec, ang, slots)` that fills vehicle slots (G,) of a stacked sample with several
        circles, circle g at t + shifts[g] (s, (W,) float; None: at t): one compiled call for them
        all, not one each (a stack is sampled at every control tick). Reads the circles now."""
        w = circles[0].n_worlds
        shift = np.stack([np.full(w, -0.0) if s is None else s for s in shifts], axis=1)  # (W, G) s

        def col(name: str) -> np.ndarray:  # (W, G) or (W, G, 3)
            return np.stack([getattr(c, name) for c in circles], axis=1)

        args = (shift, col("phase"), col("_omega"), col("center"), col("radius"))
        return lambda t, vec, ang, slots: _circles_into(t, vec, ang, slots, *args)
