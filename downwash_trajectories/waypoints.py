"""Waypoint patterns: piecewise minimum-jerk moves between waypoints, with a dwell at each.

`Waypoints` pads the patterns so that every world flies its own, and is evaluated without
Python loops (one search over every world's segments); the staged collection's passes
(`downwash_trajectories.patterns`) are made of it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError
from downwash_trajectories.base import RefSample, resolve_n_worlds, sample_times, zero_yaw

__all__ = ["Waypoints", "MIN_JERK_PEAK"]

MIN_JERK_PEAK = 1.875  # -, peak speed of a min-jerk move over its mean speed (distance / duration)


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
            raise ConfigError(f"points: expected shape (W, K, 3) or (K, 3) with K >= 1, got {p.shape}")
        k = p.shape[-2]
        d = np.array(durations, dtype=float)
        if d.shape == () and k == 2:
            d = d.reshape(1)
        if not (d.ndim in (1, 2) and d.shape[-1] == k - 1):
            raise ConfigError(f"durations: expected shape (W, {k - 1}) or ({k - 1},) for K = {k} points, got {d.shape}")
        dw = np.array(dwell, dtype=float)
        if not (dw.ndim == 0 or (dw.ndim in (1, 2) and dw.shape[-1] == k)):
            raise ConfigError(f"dwell: expected a float or shape (W, {k}) or ({k},) for K = {k} points, got {dw.shape}")
        tags = None
        if move_tags is not None:
            tags = np.array(move_tags, dtype=str)
            if tags.size == 0 and k == 1:
                tags = tags.reshape(k - 1)
            if not (tags.ndim in (1, 2) and tags.shape[-1] == k - 1):
                raise ConfigError(f"move_tags: expected shape (W, {k - 1}) or ({k - 1},), got {tags.shape}")
        batched = {"points": p.shape[0]} if p.ndim == 3 else {}
        if d.ndim == 2:
            batched["durations"] = d.shape[0]
        if dw.ndim == 2:
            batched["dwell"] = dw.shape[0]
        if tags is not None and tags.ndim == 2:
            batched["move_tags"] = tags.shape[0]
        w = self.n_worlds = resolve_n_worlds(n_worlds, batched)

        p = np.broadcast_to(p, (w, k, 3)).copy()
        d = np.broadcast_to(d, (w, k - 1)).copy()
        dw = np.broadcast_to(dw, (w, k)).copy()
        tags = np.full((w, k - 1), "", dtype="<U16") if tags is None else np.broadcast_to(tags, (w, k - 1)).copy()

        finite = np.isfinite(p)
        valid = finite.all(axis=-1)  # (W, K) real waypoints
        if np.any(finite.any(axis=-1) & ~valid):
            raise ConfigError("points: a waypoint has some but not all coordinates NaN")
        if np.any(valid[:, 1:] & ~valid[:, :-1]) or not np.all(valid[:, 0]):
            raise ConfigError("points: NaN padding must be trailing, and every world needs at least one waypoint")
        n_pts = valid.sum(axis=1)
        move_ok = valid[:, 1:]  # (W, K - 1) real moves
        if np.any(move_ok & ~(np.isfinite(d) & (d > 0.0))):
            raise ConfigError("durations: every move needs a finite duration > 0 s")
        if np.any(valid & ~(np.isfinite(dw) & (dw >= 0.0))):
            raise ConfigError("dwell: every dwell must be finite and >= 0 s")
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
    def concatenate(cls, parts: "list[Waypoints]") -> "Waypoints":
        """The worlds of several `Waypoints` as one batch, in order (padded to the longest pattern)."""
        points, durations, dwell, tags = [], [], [], []
        for wp in parts:
            for w in range(wp.n_worlds):
                k = int(wp.n_points[w])
                points.append(wp.points[w, :k])
                durations.append(wp.durations[w, : k - 1])
                dwell.append(wp.dwell[w, :k])
                tags.append(list(wp.move_tags[w, : k - 1]))
        return cls.from_patterns(points, durations, dwell, move_tags=tags)

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
            raise ConfigError("points: expected at least one world's pattern")
        if len(durations) != n:
            raise ConfigError(f"durations: expected {n} per-world arrays, got {len(durations)}")
        pts = []
        for i, pw in enumerate(points):
            a = np.array(pw, dtype=float)
            if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
                raise ConfigError(f"points[{i}]: expected shape (K, 3) with K >= 1, got {a.shape}")
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
                raise ConfigError(f"dwell: expected a float or {n} per-world values, got {len(dwells)}")
        for i, a in enumerate(pts):
            kw = a.shape[0]
            dd = np.array(durations[i], dtype=float).reshape(-1)
            if dd.shape != (kw - 1,):
                raise ConfigError(f"durations[{i}]: expected shape ({kw - 1},) for {kw} points, got {dd.shape}")
            ddw = np.array(dwells[i], dtype=float)
            if ddw.shape not in ((), (kw,)):
                raise ConfigError(f"dwell[{i}]: expected a float or shape ({kw},) for {kw} points, got {ddw.shape}")
            p[i, :kw] = a
            d[i, : kw - 1] = dd
            dw[i, :kw] = ddw
            if move_tags is not None:
                tg[i, : kw - 1] = np.array(list(move_tags[i]), dtype=str).reshape(kw - 1)
        return cls(p, d, dw, n, move_tags=tg)

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)); arrays (W, 3) and (W,)."""
        t = sample_times(t, self.n_worlds)
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
        yaw, yaw_rate = zero_yaw(self.n_worlds)
        return RefSample(pos, ds[:, None] * dp, dds[:, None] * dp, yaw, yaw_rate)
