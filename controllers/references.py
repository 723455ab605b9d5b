"""Batched reference trajectories with analytic derivatives.

Every reference serves W worlds at once (each world may have its own parameters)
and is sampled with `ref(t)`, where `t` is a float (all worlds share it) or an
array (W,) of per-world times (a vector env whose worlds reset at different
times). A sample is a `RefSample` of position, velocity and acceleration (world
frame, z up, SI units) plus yaw and yaw rate, all derived analytically so the
outer loop's feed-forward `a_ref` is exact.

- `Hover`: fixed points.
- `Lemniscate`: the paper's figure-eight (lemniscate of Gerono) beneath the leader.
- `Transect`: the paper's back-and-forth pass along world y, offset in x.
- `Waypoints`: piecewise minimum-jerk moves between waypoints with dwells, padded
  so that every world can fly its own pattern; evaluated without Python loops.
- `random_passes`: the randomised passes and hovers of the staged data
  collection (DESIGN section 8), built as `Waypoints`.
- `stack`: one reference per vehicle, sampled as (W, V, ...) arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from sim.jit import njit

__all__ = [
    "SPEED_RANGE",
    "RefSample",
    "Reference",
    "Hover",
    "Lemniscate",
    "Transect",
    "Waypoints",
    "StackedReference",
    "Mixed",
    "random_passes",
    "stack",
]

SPEED_RANGE = (0.1, 1.0)  # m/s, allowed peak speeds of data-collection moves (DESIGN section 8)
_MIN_JERK_PEAK = 1.875  # -, peak speed of a min-jerk move over its mean speed (distance / duration)


class RefSample(NamedTuple):
    """One sample of a batched reference; world frame (z up), SI units.

    pos: (W, 3) m; vel: (W, 3) m/s; acc: (W, 3) m/s^2; yaw: (W,) rad;
    yaw_rate: (W,) rad/s. `stack` gives the same fields with a vehicle axis:
    (W, V, 3) and (W, V).
    """

    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    yaw: np.ndarray
    yaw_rate: np.ndarray


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


# ----------------------------------------------------------------------------- checks


def _check_n_worlds(n_worlds: int | None) -> int | None:
    if n_worlds is None:
        return None
    if isinstance(n_worlds, bool) or not isinstance(n_worlds, (int, np.integer)) or n_worlds < 1:
        raise ValueError(f"n_worlds: expected an integer >= 1, got {n_worlds!r}")
    return int(n_worlds)


def _resolve_n_worlds(n_worlds: int | None, batched: dict[str, int]) -> int:
    """World count from the explicit `n_worlds` and the leading sizes of batched args."""
    n_worlds = _check_n_worlds(n_worlds)
    sizes = set(batched.values())
    if len(sizes) > 1:
        detail = ", ".join(f"{k}: {v}" for k, v in batched.items())
        raise ValueError(f"batched arguments disagree on the number of worlds ({detail})")
    if sizes:
        (size,) = sizes
        if n_worlds is not None and n_worlds != size:
            name = next(iter(batched))
            raise ValueError(f"n_worlds: got {n_worlds} but {name} is batched over {size} worlds")
        return size
    return 1 if n_worlds is None else n_worlds


def _vec3(name: str, x: ArrayLike) -> np.ndarray:
    """Finite (3,) or (W, 3) float array."""
    a = np.array(x, dtype=float)
    if not (a.shape == (3,) or (a.ndim == 2 and a.shape[1] == 3 and a.shape[0] >= 1)):
        raise ValueError(f"{name}: expected shape (W, 3) or (3,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: must be finite")
    return a


def _scalar_or_world(name: str, x: ArrayLike, unit: str, *, allow_zero: bool = False) -> np.ndarray:
    """Finite positive (or non-negative) float or (W,) array."""
    a = np.array(x, dtype=float)
    if a.ndim > 1 or (a.ndim == 1 and a.shape[0] < 1):
        raise ValueError(f"{name}: expected a float or shape (W,), got {a.shape}")
    bad = ~np.isfinite(a) | ((a < 0.0) if allow_zero else (a <= 0.0))
    if np.any(bad):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name}: must be finite and {bound} {unit}, got {x!r}")
    return a


def _leading(batched: dict[str, np.ndarray], ndim_unbatched: dict[str, int]) -> dict[str, int]:
    return {k: v.shape[0] for k, v in batched.items() if v.ndim > ndim_unbatched[k]}


def _positive_float(name: str, x: float, unit: str, *, allow_zero: bool = False) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number ({unit}), got {x!r}") from None
    if not np.isfinite(v) or (v < 0.0 if allow_zero else v <= 0.0):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name}: must be finite and {bound} {unit}, got {x!r}")
    return v


def _ordered_range(name: str, r: Sequence[float], unit: str, lo: float, hi: float) -> tuple[float, float]:
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
        raise ValueError(f"{name}: expected (low, high), got {r!r}; {allowed}, with low <= high") from None
    ok_lo = a > 0.0 if lo == 0 else a >= lo - 1e-12
    if not (np.isfinite(a) and np.isfinite(b) and ok_lo and b <= hi + 1e-12 and a <= b):
        raise ValueError(f"{name}: got {r!r}; {allowed}, with low <= high")
    return a, b


def _times(t: float | ArrayLike, n_worlds: int) -> np.ndarray:
    """Sample times as (W,) float array."""
    if type(t) is np.ndarray and t.dtype == np.float64 and t.shape == (n_worlds,):
        return t  # the simulator's clock, sampled at 50 Hz: nothing to convert
    a = np.asarray(t, dtype=float)
    if a.ndim == 0:
        return np.full(n_worlds, float(a))
    if a.shape != (n_worlds,):
        raise ValueError(f"t: expected a float or shape ({n_worlds},), got {a.shape}")
    return a


def _zero_yaw(n_worlds: int) -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(n_worlds), np.zeros(n_worlds)


def _duration_out(period: np.ndarray) -> np.ndarray | float:
    return float(period) if period.ndim == 0 else period.copy()


# Stacked samples are filled in place: vec (3, W, V, 3) holds pos, vel, acc and ang (2, W, V)
# yaw, yaw_rate, and a reference with `_sample_into(t, vec, ang, v)` writes vehicle v's
# slots directly (the 50 Hz control path; a copy per field cost more than the sample).


def _empty_sample(n_worlds: int, n_vehicles: int) -> tuple[np.ndarray, np.ndarray, RefSample]:
    """Uninitialised (vec, ang) storage and the RefSample of views into it."""
    vec, ang = np.empty((3, n_worlds, n_vehicles, 3)), np.empty((2, n_worlds, n_vehicles))
    return vec, ang, RefSample(vec[0], vec[1], vec[2], ang[0], ang[1])


def _single(vec: np.ndarray, ang: np.ndarray) -> RefSample:
    """The (W, 3) / (W,) RefSample of a one-vehicle (vec, ang)."""
    return RefSample(vec[0, :, 0], vec[1, :, 0], vec[2, :, 0], ang[0, :, 0], ang[1, :, 0])


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


# ----------------------------------------------------------------------------- simple references


class Hover:
    """Hold fixed points: zero velocity and acceleration, yaw 0.

    points: (W, 3) or (3,) m, world frame (z up); (3,) is shared by `n_worlds` worlds.
    n_worlds: number of worlds (inferred from `points` when batched).
    duration: s, the length a caller should fly it for (a hover has no natural
        end; default 0.0). Sampling at any time returns the points.
    """

    def __init__(self, points: ArrayLike, n_worlds: int | None = None, duration: float = 0.0) -> None:
        p = _vec3("points", points)
        self.n_worlds = _resolve_n_worlds(n_worlds, {"points": p.shape[0]} if p.ndim == 2 else {})
        self.points = np.broadcast_to(p, (self.n_worlds, 3)).copy()  # (W, 3) m
        self.duration: float = _positive_float("duration", duration, "s", allow_zero=True)

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)): the points, zeros elsewhere."""
        _times(t, self.n_worlds)
        w = self.n_worlds
        yaw, yaw_rate = _zero_yaw(w)
        return RefSample(self.points.copy(), np.zeros((w, 3)), np.zeros((w, 3)), yaw, yaw_rate)

    def _sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
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
        c = _vec3("center", center)
        a = _scalar_or_world("half_length", half_length, "m")
        b = _scalar_or_world("half_width", half_width, "m")
        per = _scalar_or_world("period", period, "s")
        args = {"center": c, "half_length": a, "half_width": b, "period": per}
        self.n_worlds = _resolve_n_worlds(
            n_worlds, _leading(args, {"center": 1, "half_length": 0, "half_width": 0, "period": 0})
        )
        w = self.n_worlds
        self.center = np.broadcast_to(c, (w, 3)).copy()  # (W, 3) m
        self.half_length = np.broadcast_to(a, (w,)).copy()  # (W,) m
        self.half_width = np.broadcast_to(b, (w,)).copy()  # (W,) m
        self.period = np.broadcast_to(per, (w,)).copy()  # (W,) s
        self.duration: np.ndarray | float = _duration_out(per)
        self._omega = 2.0 * np.pi / self.period  # (W,) rad/s

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        vec, ang, _ = _empty_sample(self.n_worlds, 1)
        self._sample_into(_times(t, self.n_worlds), vec, ang, 0)
        return _single(vec, ang)

    def _sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
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
        c = _vec3("center", center)
        xo = np.array(x_offset, dtype=float)
        if xo.ndim > 1 or (xo.ndim == 1 and xo.shape[0] < 1) or not np.all(np.isfinite(xo)):
            raise ValueError(f"x_offset: expected a finite float or shape (W,) in m, got {x_offset!r}")
        hl = _scalar_or_world("half_length", half_length, "m")
        per = _scalar_or_world("period", period, "s")
        args = {"center": c, "x_offset": xo, "half_length": hl, "period": per}
        self.n_worlds = _resolve_n_worlds(
            n_worlds, _leading(args, {"center": 1, "x_offset": 0, "half_length": 0, "period": 0})
        )
        w = self.n_worlds
        self.center = np.broadcast_to(c, (w, 3)).copy()  # (W, 3) m
        self.x_offset = np.broadcast_to(xo, (w,)).copy()  # (W,) m
        self.half_length = np.broadcast_to(hl, (w,)).copy()  # (W,) m
        self.period = np.broadcast_to(per, (w,)).copy()  # (W,) s
        self.duration: np.ndarray | float = _duration_out(per)
        self._omega = 2.0 * np.pi / self.period  # (W,) rad/s
        self._base = self.center.copy()
        self._base[:, 0] += self.x_offset

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        vec, ang, _ = _empty_sample(self.n_worlds, 1)
        self._sample_into(_times(t, self.n_worlds), vec, ang, 0)
        return _single(vec, ang)

    def _sample_into(self, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
        _transect_into(t, self._omega, self._base, self.half_length, vec, ang, v)


# ----------------------------------------------------------------------------- waypoints


class Waypoints:
    """Piecewise minimum-jerk moves between waypoints, with a dwell at each.

    World w starts at its waypoint 0, dwells `dwell[w, 0]` there, moves to
    waypoint 1 in `durations[w, 0]` along a straight line with the quintic
    minimum-jerk profile s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 (zero velocity and
    acceleration at both ends, so the reference is C2 everywhere), dwells
    `dwell[w, 1]`, and so on; after the last dwell it holds the last waypoint
    (and before t = 0 it holds the first). A move's peak speed is
    1.875 * distance / duration. Yaw is 0.

    Worlds may fly different patterns: arrays are padded to K waypoints, and a
    world with fewer fills its trailing rows of `points` with NaN (its padded
    `durations` / `dwell` entries are ignored and may be NaN).
    `Waypoints.from_patterns` does the padding from per-world lists.

    points: (W, K, 3) or (K, 3) m, world frame (z up); (K, 3) is shared by
        `n_worlds` worlds.
    durations: (W, K - 1) or (K - 1,) s, > 0, the duration of each move.
    dwell: float, (K,) or (W, K) s, >= 0, the hover time at each waypoint.
    n_worlds: number of worlds (inferred when any argument is batched).
    move_tags: optional (W, K - 1) or (K - 1,) strings naming each move (for
        example "pass" / "reposition"; padded entries are "").

    Attributes: `points` (W, K, 3) m NaN-padded, `n_points` (W,), `durations`
    (W, K - 1) s and `dwell` (W, K) s (NaN where padded), `arrival_times`
    (W, K) s (when each waypoint is reached, NaN where padded), `move_tags`
    (W, K - 1) str, `duration` (W,) s (end of the last dwell).
    """

    def __init__(
        self,
        points: ArrayLike,
        durations: ArrayLike,
        dwell: float | ArrayLike = 0.0,
        n_worlds: int | None = None,
        *,
        move_tags: ArrayLike | None = None,
    ) -> None:
        p = np.array(points, dtype=float)
        if not (p.ndim in (2, 3) and p.shape[-1] == 3 and p.shape[-2] >= 1 and (p.ndim == 2 or p.shape[0] >= 1)):
            raise ValueError(f"points: expected shape (W, K, 3) or (K, 3) with K >= 1, got {p.shape}")
        k = p.shape[-2]
        d = np.array(durations, dtype=float)
        if d.shape == () and k == 2:
            d = d.reshape(1)
        if not (d.ndim in (1, 2) and d.shape[-1] == k - 1):
            raise ValueError(f"durations: expected shape (W, {k - 1}) or ({k - 1},) for K = {k} points, got {d.shape}")
        dw = np.array(dwell, dtype=float)
        if not (dw.ndim == 0 or (dw.ndim in (1, 2) and dw.shape[-1] == k)):
            raise ValueError(f"dwell: expected a float or shape (W, {k}) or ({k},) for K = {k} points, got {dw.shape}")
        tags = None
        if move_tags is not None:
            tags = np.array(move_tags, dtype=str)
            if tags.size == 0 and k == 1:
                tags = tags.reshape(k - 1)
            if not (tags.ndim in (1, 2) and tags.shape[-1] == k - 1):
                raise ValueError(f"move_tags: expected shape (W, {k - 1}) or ({k - 1},), got {tags.shape}")
        batched = {"points": p.shape[0]} if p.ndim == 3 else {}
        if d.ndim == 2:
            batched["durations"] = d.shape[0]
        if dw.ndim == 2:
            batched["dwell"] = dw.shape[0]
        if tags is not None and tags.ndim == 2:
            batched["move_tags"] = tags.shape[0]
        w = self.n_worlds = _resolve_n_worlds(n_worlds, batched)

        p = np.broadcast_to(p, (w, k, 3)).copy()
        d = np.broadcast_to(d, (w, k - 1)).copy()
        dw = np.broadcast_to(dw, (w, k)).copy()
        tags = np.full((w, k - 1), "", dtype="<U16") if tags is None else np.broadcast_to(tags, (w, k - 1)).copy()

        finite = np.isfinite(p)
        valid = finite.all(axis=-1)  # (W, K) real waypoints
        if np.any(finite.any(axis=-1) & ~valid):
            raise ValueError("points: a waypoint has some but not all coordinates NaN")
        if np.any(valid[:, 1:] & ~valid[:, :-1]) or not np.all(valid[:, 0]):
            raise ValueError("points: NaN padding must be trailing, and every world needs at least one waypoint")
        n_pts = valid.sum(axis=1)
        move_ok = valid[:, 1:]  # (W, K - 1) real moves
        if np.any(move_ok & ~(np.isfinite(d) & (d > 0.0))):
            raise ValueError("durations: every move needs a finite duration > 0 s")
        if np.any(valid & ~(np.isfinite(dw) & (dw >= 0.0))):
            raise ValueError("dwell: every dwell must be finite and >= 0 s")
        d[~move_ok] = np.nan
        dw[~valid] = np.nan
        tags[~move_ok] = ""

        # Segment slots: 2k = dwell at point k, 2k + 1 = move k -> k + 1.
        n_slots = 2 * k - 1
        last = p[np.arange(w), n_pts - 1]  # (W, 3)
        pp = np.where(valid[..., None], p, last[:, None, :])  # padded rows hold the last point
        p0 = np.repeat(pp, 2, axis=1)[:, :n_slots]
        p1 = np.repeat(pp, 2, axis=1)[:, 1 : n_slots + 1]
        seg_dur = np.empty((w, n_slots))
        seg_dur[:, 0::2] = np.where(valid, dw, 0.0)
        seg_dur[:, 1::2] = np.where(move_ok, d, 0.0)
        seg_ok = np.empty((w, n_slots), dtype=bool)
        seg_ok[:, 0::2] = valid
        seg_ok[:, 1::2] = move_ok
        ends = np.cumsum(seg_dur, axis=1)
        starts = ends - seg_dur
        starts[~seg_ok] = np.inf  # never selected
        safe_dur = np.where(seg_dur > 0.0, seg_dur, 1.0)  # zero-length dwells have p1 == p0

        self.points = np.where(valid[..., None], p, np.nan)  # (W, K, 3) m
        self.n_points = n_pts  # (W,)
        self.durations = d  # (W, K - 1) s
        self.dwell = dw  # (W, K) s
        self.move_tags = tags  # (W, K - 1)
        self.arrival_times = np.where(valid, starts[:, 0::2], np.nan)  # (W, K) s
        self.duration: np.ndarray = ends[:, -1].copy()  # (W,) s

        # Segment search: one searchsorted over every world's slot start times,
        # made globally increasing by giving world i the offset i * span (and
        # padded slots a start just after their world's end).
        span = float(self.duration.max()) + 2.0
        self._row_offset = np.arange(w) * span  # (W,) s
        keys = np.where(seg_ok, starts, self.duration[:, None] + 1.0) + self._row_offset[:, None]
        self._keys = keys.ravel()  # (W * S,) s, increasing
        self._start_flat = starts.ravel()
        self._inv_dur = (1.0 / safe_dur).ravel()
        self._p0 = p0.reshape(-1, 3)
        self._dp = (p1 - p0).reshape(-1, 3)

    @classmethod
    def from_patterns(
        cls,
        points: Sequence[ArrayLike],
        durations: Sequence[ArrayLike],
        dwell: float | Sequence[float | ArrayLike] = 0.0,
        *,
        move_tags: Sequence[Sequence[str]] | None = None,
    ) -> "Waypoints":
        """Pad one pattern per world into a batched `Waypoints`.

        points: W arrays (K_w, 3) m; durations: W arrays (K_w - 1,) s;
        dwell: a float, or W floats / arrays (K_w,) s; move_tags: W sequences of
        K_w - 1 strings.
        """
        n = len(points)
        if n < 1:
            raise ValueError("points: expected at least one world's pattern")
        if len(durations) != n:
            raise ValueError(f"durations: expected {n} per-world arrays, got {len(durations)}")
        pts = []
        for i, pw in enumerate(points):
            a = np.array(pw, dtype=float)
            if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
                raise ValueError(f"points[{i}]: expected shape (K, 3) with K >= 1, got {a.shape}")
            pts.append(a)
        k = max(a.shape[0] for a in pts)
        p = np.full((n, k, 3), np.nan)
        d = np.full((n, max(k - 1, 0)), np.nan)
        dw = np.full((n, k), np.nan)
        tg = np.full((n, max(k - 1, 0)), "", dtype="<U16")
        if np.isscalar(dwell) or (isinstance(dwell, np.ndarray) and dwell.ndim == 0):
            dwells = [dwell] * n
        else:
            dwells = list(dwell)  # type: ignore[arg-type]
            if len(dwells) != n:
                raise ValueError(f"dwell: expected a float or {n} per-world values, got {len(dwells)}")
        for i, a in enumerate(pts):
            kw = a.shape[0]
            dd = np.array(durations[i], dtype=float).reshape(-1)
            if dd.shape != (kw - 1,):
                raise ValueError(f"durations[{i}]: expected shape ({kw - 1},) for {kw} points, got {dd.shape}")
            ddw = np.array(dwells[i], dtype=float)
            if ddw.shape not in ((), (kw,)):
                raise ValueError(f"dwell[{i}]: expected a float or shape ({kw},) for {kw} points, got {ddw.shape}")
            p[i, :kw] = a
            d[i, : kw - 1] = dd
            dw[i, :kw] = ddw
            if move_tags is not None:
                tg[i, : kw - 1] = np.array(list(move_tags[i]), dtype=str).reshape(kw - 1)
        return cls(p, d, dw, n, move_tags=tg)

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        t = _times(t, self.n_worlds)
        # Last slot starting at or before t (t clipped to [0, end]: outside it the
        # first / last slot is selected and tau saturates at 0 / 1).
        key = np.minimum(np.maximum(t, 0.0), self.duration) + self._row_offset
        flat = np.searchsorted(self._keys, key, side="right") - 1
        inv = self._inv_dur[flat]
        tau = np.minimum(np.maximum((t - self._start_flat[flat]) * inv, 0.0), 1.0)
        # s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 and its time derivatives.
        tau2 = tau * tau
        s = tau2 * tau * (10.0 + tau * (-15.0 + 6.0 * tau))
        ds = tau2 * (30.0 + tau * (-60.0 + 30.0 * tau)) * inv
        dds = tau * (60.0 + tau * (-180.0 + 120.0 * tau)) * (inv * inv)
        dp = self._dp.take(flat, axis=0)
        pos = self._p0.take(flat, axis=0) + s[:, None] * dp
        yaw, yaw_rate = _zero_yaw(self.n_worlds)
        return RefSample(pos, ds[:, None] * dp, dds[:, None] * dp, yaw, yaw_rate)


# ----------------------------------------------------------------------------- data-collection patterns


def random_passes(
    rng: np.random.Generator,
    n_worlds: int,
    center: ArrayLike,
    *,
    depth_range: tuple[float, float] = (1.35, 1.75),
    speed_range: tuple[float, float] = (0.1, 1.0),
    max_offset: float = 0.6,
    pass_half_length: float = 1.0,
    duration: float = 60.0,
    n_segments: int | None = None,
    hover_prob: float = 0.2,
    hover_radius: float = 0.8,
    hover_time_range: tuple[float, float] = (2.0, 5.0),
    reposition_speed: float = 0.5,
    min_move_time: float = 1.0,
    start: ArrayLike | None = None,
) -> Waypoints:
    """Randomised passes through and beside the leader's wake (DESIGN section 8).

    Each world flies a sequence of items, each a straight pass (probability
    1 - hover_prob) or a hover (probability hover_prob), joined by
    repositioning moves; every move is minimum-jerk and every waypoint lies
    `depth` below the leader, depth uniform in `depth_range` per waypoint.

    - A pass has a heading uniform in [0, 2 pi), a lateral offset from the wake
      axis (the vertical line through `center`) uniform in [0, max_offset] m,
      and runs from -pass_half_length to +pass_half_length m along its heading
      about its closest point to the axis; its peak speed v is uniform in
      `speed_range` and its duration 1.875 * distance / v (tag "pass").
    - A hover sits at a horizontal offset of radius uniform in
      [0, hover_radius] m (uniform angle) for a time uniform in
      `hover_time_range` s (the dwell at that waypoint).
    - A repositioning move (tag "reposition") goes from where the last item
      ended to where the next begins, with peak speed `reposition_speed` m/s
      and at least `min_move_time` s.

    Items are added until a world's pattern lasts at least `duration` s, or,
    when `n_segments` is given, exactly `n_segments` items per world. The
    pattern begins at `start` when given, else at the first item's start point.
    Randomness only through `rng`: the same generator state gives the same
    patterns.

    rng: numpy Generator.
    n_worlds: number of worlds, >= 1.
    center: (W, 3) or (3,) m, the leader's position, world frame (z up).
    depth_range: (low, high) m, 0 < low <= high, vertical separation below `center`.
    speed_range: (low, high) m/s, within 0.1-1.0 m/s.
    start: optional (W, 3) or (3,) m, the first waypoint of every world.
    Returns a `Waypoints` over `n_worlds` worlds with move tags "pass" and
    "reposition".
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    w = _check_n_worlds(n_worlds)
    if w is None:
        raise ValueError("n_worlds: expected an integer >= 1, got None")
    c = _vec3("center", center)
    if c.ndim == 2 and c.shape[0] != w:
        raise ValueError(f"center: expected shape ({w}, 3) or (3,), got {c.shape}")
    c = np.broadcast_to(c, (w, 3))
    d_lo, d_hi = _ordered_range("depth_range", depth_range, "m", 0.0, np.inf)
    s_lo, s_hi = _ordered_range("speed_range", speed_range, "m/s", *SPEED_RANGE)
    max_offset = _positive_float("max_offset", max_offset, "m", allow_zero=True)
    pass_half_length = _positive_float("pass_half_length", pass_half_length, "m")
    duration = _positive_float("duration", duration, "s")
    if n_segments is not None and (
        isinstance(n_segments, bool) or not isinstance(n_segments, (int, np.integer)) or n_segments < 1
    ):
        raise ValueError(f"n_segments: expected None or an integer >= 1, got {n_segments!r}")
    hover_prob = float(hover_prob)
    if not 0.0 <= hover_prob <= 1.0:
        raise ValueError(f"hover_prob: got {hover_prob!r}; allowed 0-1")
    hover_radius = _positive_float("hover_radius", hover_radius, "m", allow_zero=True)
    h_lo, h_hi = _ordered_range("hover_time_range", hover_time_range, "s", 0.0, np.inf)
    reposition_speed = float(reposition_speed)
    if not SPEED_RANGE[0] <= reposition_speed <= SPEED_RANGE[1]:
        raise ValueError(
            f"reposition_speed: got {reposition_speed!r}; allowed {SPEED_RANGE[0]}-{SPEED_RANGE[1]} m/s"
        )
    min_move_time = _positive_float("min_move_time", min_move_time, "s")
    st = None
    if start is not None:
        st = _vec3("start", start)
        if st.ndim == 2 and st.shape[0] != w:
            raise ValueError(f"start: expected shape ({w}, 3) or (3,), got {st.shape}")
        st = np.broadcast_to(st, (w, 3))

    def below(cw: np.ndarray, xy: np.ndarray) -> np.ndarray:
        return np.array([cw[0] + xy[0], cw[1] + xy[1], cw[2] - rng.uniform(d_lo, d_hi)])

    all_pts, all_durs, all_dwell, all_tags = [], [], [], []
    for wi in range(w):
        cw = c[wi]
        pts: list[np.ndarray] = []
        durs: list[float] = []
        dwl: list[float] = []
        tags: list[str] = []
        total = 0.0
        n_items = 0

        def move_to(p: np.ndarray, dur: float, tag: str) -> float:
            pts.append(p)
            durs.append(dur)
            dwl.append(0.0)
            tags.append(tag)
            return dur

        def reposition(p: np.ndarray) -> float:
            dist = float(np.linalg.norm(p - pts[-1]))
            return move_to(p, max(_MIN_JERK_PEAK * dist / reposition_speed, min_move_time), "reposition")

        if st is not None:
            pts.append(st[wi].copy())
            dwl.append(0.0)
        while (n_items < n_segments) if n_segments is not None else (total < duration):
            if rng.uniform() < hover_prob:
                r = rng.uniform(0.0, hover_radius)
                ang = rng.uniform(0.0, 2.0 * np.pi)
                p = below(cw, r * np.array([np.cos(ang), np.sin(ang)]))
                hold = rng.uniform(h_lo, h_hi)
                if pts:
                    total += reposition(p)
                else:
                    pts.append(p)
                    dwl.append(0.0)
                dwl[-1] = hold
                total += hold
            else:
                heading = rng.uniform(0.0, 2.0 * np.pi)
                offset = rng.uniform(0.0, max_offset)
                speed = rng.uniform(s_lo, s_hi)
                u = np.array([np.cos(heading), np.sin(heading)])
                n = np.array([-u[1], u[0]])
                p_a = below(cw, offset * n - pass_half_length * u)
                p_b = below(cw, offset * n + pass_half_length * u)
                if pts:
                    total += reposition(p_a)
                else:
                    pts.append(p_a)
                    dwl.append(0.0)
                dist = float(np.linalg.norm(p_b - p_a))
                total += move_to(p_b, _MIN_JERK_PEAK * dist / speed, "pass")
            n_items += 1
        all_pts.append(np.array(pts))
        all_durs.append(np.array(durs))
        all_dwell.append(np.array(dwl))
        all_tags.append(tags)
    return Waypoints.from_patterns(all_pts, all_durs, all_dwell, move_tags=all_tags)


# ----------------------------------------------------------------------------- mixing


class Mixed:
    """Different references for different worlds of one batch.

    parts: (reference, worlds) pairs; `worlds` (index array) are the batch worlds that
    `reference` (built with n_worlds = len(worlds)) serves. Every world must be served
    exactly once. Sampling calls each part once on its worlds' times.
    """

    def __init__(self, parts: Sequence[tuple[Reference, ArrayLike]]) -> None:
        parts = [(ref, np.asarray(worlds, dtype=np.int64).reshape(-1)) for ref, worlds in parts]
        if not parts:
            raise ValueError("parts: expected at least one (reference, worlds) pair")
        for ref, worlds in parts:
            if int(ref.n_worlds) != worlds.size:
                raise ValueError(f"parts: a reference with n_worlds={ref.n_worlds} was given {worlds.size} worlds")
        all_worlds = np.sort(np.concatenate([w for _, w in parts]))
        if not np.array_equal(all_worlds, np.arange(all_worlds.size)):
            raise ValueError("parts: the worlds must be 0..W-1, each served by exactly one reference")
        self.parts = parts
        self.n_worlds = int(all_worlds.size)
        self.duration = np.zeros(self.n_worlds)
        for ref, worlds in parts:
            self.duration[worlds] = np.broadcast_to(np.asarray(ref.duration, dtype=float), (worlds.size,))

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)): the fields of RefSample, (W, 3) and (W,)."""
        t = _times(t, self.n_worlds)
        W = self.n_worlds
        out = RefSample(np.empty((W, 3)), np.empty((W, 3)), np.empty((W, 3)), np.empty(W), np.empty(W))
        for ref, worlds in self.parts:
            for dst, src in zip(out, ref(t[worlds])):
                dst[worlds] = src
        return out


# ----------------------------------------------------------------------------- stacking


class StackedReference:
    """One reference per vehicle, sampled together: `(W, V, ...)` arrays.

    refs: V references with the same `n_worlds`. `duration` (s, (W,)) is the
    longest natural length over the vehicles.
    """

    def __init__(self, refs: Sequence[Reference]) -> None:
        refs = list(refs)
        if not refs:
            raise ValueError("refs: expected at least one reference")
        counts = [int(r.n_worlds) for r in refs]
        if len(set(counts)) != 1:
            raise ValueError(f"refs: all references must have the same n_worlds, got {counts}")
        self.refs = refs
        self._into = [getattr(r, "_sample_into", None) for r in refs]
        self.n_worlds = counts[0]
        self.n_vehicles = len(refs)
        self.duration: np.ndarray = np.max(
            [np.broadcast_to(np.asarray(r.duration, dtype=float), (self.n_worlds,)) for r in refs], axis=0
        )

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)): pos/vel/acc (W, V, 3), yaw/yaw_rate (W, V)."""
        t = _times(t, self.n_worlds)
        vec, ang, out = _empty_sample(self.n_worlds, self.n_vehicles)
        for v, (ref, into) in enumerate(zip(self.refs, self._into)):
            if into is not None:  # our references write their slots directly
                into(t, vec, ang, v)
            else:  # any other Reference: sample, then copy
                for dst, src in zip(out, ref(t)):
                    dst[:, v] = src
        return out


def stack(refs: Sequence[Reference]) -> StackedReference:
    """Stack one reference per vehicle: `stack([Hover(leader), Lemniscate(c)])(t)`
    gives pos (W, 2, 3) etc. All refs must have the same `n_worlds` (ValueError)."""
    return StackedReference(refs)
