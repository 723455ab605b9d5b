"""The shed wake's elements and its centreline: where a point lies in each vehicle's wake.

`WakeState` holds the elements of W worlds x V vehicles, a ring buffer of N per vehicle
(`sim.fields.shed.ShedWake` sheds, carries and ages them). A vehicle's valid elements, in
shedding order, are the vertices of a polyline that starts at its rotor plane: `nearest`
finds the nearest point of each polyline to each point (`nearest_segments`, compiled, beside
its NumPy reference `nearest_segments_numpy`) and interpolates the travelled depth, thrust and
axis there (`Local`); `air` is the jet's air velocity about it (the model: `sim.fields.shed`'s
docstring, 3). `sim.fields.shed` re-exports `WakeState`. Units: m, m/s, s, N.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from downwash_core.geometry import dot as _dot
from downwash_core.jit import njit

__all__ = ["WakeState", "Local", "nearest", "air", "nearest_segments", "nearest_segments_numpy", "dot_first", "TINY"]

TINY = 1e-300  # m^2, a zero-length segment projects onto its start


@dataclass
class WakeState:
    """The shed elements of W worlds x V vehicles, N per vehicle (a ring buffer), mutated by `ShedWake.step`.

    pos (W, V, N, 3) m, world frame: element centres; axis (W, V, N, 3) -, unit, downstream
    (the shedding vehicle's -n at shedding); depth (W, V, N) m: travelled depth s; thrust
    (W, V, N) N: the shedding thrust; age (W, V, N) s; valid (W, V, N) bool; cursor (W,) int:
    the slot the next element goes to; clock (W,) s: time since the last shedding.
    """

    pos: np.ndarray
    axis: np.ndarray
    depth: np.ndarray
    thrust: np.ndarray
    age: np.ndarray
    valid: np.ndarray
    cursor: np.ndarray
    clock: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        """(W, V, N)."""
        return self.valid.shape


class Local(NamedTuple):
    """The wake of each source at each point, from the nearest point c of its centreline; (W, Vs, P, ...)."""

    s: np.ndarray  # m, travelled depth at c
    thrust: np.ndarray  # N
    axis: np.ndarray  # (..., 3) -, unit, downstream
    tangent: np.ndarray  # (..., 3) -, unit: the centreline's direction at c
    offset: np.ndarray  # (..., 3) m, p - c
    active: np.ndarray  # bool: the source has a wake and p is below its rotor plane


def nearest(state: WakeState, pos, rot, points, compiled: bool = True) -> Local:
    """The nearest point of each source's centreline polyline to each point (W, P, 3) m, with the wake there.

    pos (W, V, 3) m and rot (W, V, 3, 3): the vehicles now (their rotor planes start the wakes).

    Segment 0 runs from the rotor plane to the newest element, segment 1 + i from the element in
    ring slot i to the next older one, in slot i - 1 (the newest follows the oldest: no segment)."""
    W, V, N = state.shape
    newest = (state.cursor - 1) % N  # (W,)
    find = nearest_segments if compiled else nearest_segments_numpy
    seg, tj = find(points, pos, state.pos, state.valid, state.age, newest)  # (W, V, P)
    ring = seg > 0
    w_i, v_i = np.arange(W)[:, None, None], np.arange(V)[None, :, None]
    first = np.where(ring, seg - 1, newest[:, None, None])  # the slot at each end (where a ring segment)
    second = np.where(ring, (seg - 2) % N, newest[:, None, None])
    n = rot[..., :, 2]
    T_newest = state.thrust[np.arange(W), :, newest]  # (W, V) N

    def lerp(x, at_plane):  # x (W, V, N[, 3]) per element, at_plane (W, V[, 3]): the value at the nearest point
        vec = x.ndim == 4
        x0 = np.where(ring[..., None] if vec else ring, x[w_i, v_i, first], at_plane[:, :, None])
        return x0 + (tj[..., None] if vec else tj) * (x[w_i, v_i, second] - x0)

    start = np.where(ring[..., None], state.pos[w_i, v_i, first], pos[:, :, None])
    seg_vec = state.pos[w_i, v_i, second] - start  # (W, V, P, 3) m
    offset = points[:, None] - (start + tj[..., None] * seg_vec)  # m, p - c
    axis = lerp(state.axis, -n)
    axis = axis / np.sqrt(_dot(axis, axis))[..., None]
    seg_len = np.sqrt(_dot(seg_vec, seg_vec))[..., None]
    tangent = np.where(seg_len > 0.0, seg_vec / np.maximum(seg_len, TINY), axis)
    above = _dot(points[:, None] - pos[:, :, None], n[:, :, None]) > 0.0  # above the source's rotor plane
    active = state.valid[np.arange(W), :, newest][..., None] & ~above  # the newest is valid iff any is
    return Local(lerp(state.depth, np.zeros((W, V))), lerp(state.thrust, T_newest), axis, tangent, offset,
                 active)


def air(axial: np.ndarray, radial_over_r: np.ndarray, loc: Local, offset: np.ndarray) -> np.ndarray:
    """u = U d + (V / r) r_perp (m/s), r_perp the offset less its part along the centreline; 0 where inactive."""
    perp = offset - _dot(offset, loc.tangent)[..., None] * loc.tangent
    u = axial[..., None] * loc.axis + radial_over_r[..., None] * perp
    return np.where(loc.active[..., None], u, 0.0)


@njit
def nearest_segments(points, origin, elem, valid, age, newest):  # pragma: no cover - compiled
    """The nearest segment of each source's polyline to each point, compiled: (W, V, P) index and parameter t.

    points (W, P, 3) m; origin (W, V, 3) m, the rotor planes; elem (W, V, N, 3) m, valid (W, V, N),
    age (W, V, N) s, the ring; newest (W,) its newest slot. Segments as `nearest`; the
    first of equally near ones; (0, 0) where a source has none. `nearest_segments_numpy` is the reference."""
    W, P = points.shape[0], points.shape[1]
    V, N = valid.shape[1], valid.shape[2]
    seg_out = np.zeros((W, V, P), np.int64)
    t_out = np.zeros((W, V, P))
    for w in range(W):
        k = newest[w]
        for v in range(V):
            for p in range(P):
                best, best_j, best_t = np.inf, 0, 0.0
                for j in range(N + 1):
                    if j == 0:
                        if not valid[w, v, k]:
                            continue
                        a, b = origin[w, v], elem[w, v, k]
                    else:
                        i = j - 1
                        i1 = i - 1 if i > 0 else N - 1
                        if not (valid[w, v, i] and valid[w, v, i1] and age[w, v, i1] > age[w, v, i]):
                            continue
                        a, b = elem[w, v, i], elem[w, v, i1]
                    sx, sy, sz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
                    rx, ry, rz = points[w, p, 0] - a[0], points[w, p, 1] - a[1], points[w, p, 2] - a[2]
                    t = (rx * sx + ry * sy + rz * sz) / max(sx * sx + sy * sy + sz * sz, TINY)
                    t = min(max(t, 0.0), 1.0)
                    ox, oy, oz = rx - t * sx, ry - t * sy, rz - t * sz
                    d2 = ox * ox + oy * oy + oz * oz
                    if d2 < best:
                        best, best_j, best_t = d2, j, t
                seg_out[w, v, p] = best_j
                t_out[w, v, p] = best_t
    return seg_out, t_out


def nearest_segments_numpy(points, origin, elem, valid, age, newest):
    """The readable reference of `nearest_segments`: every segment at once, (3, W, V, P, N + 1)."""
    W, V, N = valid.shape
    older = lambda a: np.roll(a, 1, axis=2)  # slot i - 1 at i
    pick = lambda a: a[np.arange(W), :, newest][:, :, None]  # (W, V, 1, ...)
    ok = np.concatenate([pick(valid), valid & older(valid) & (older(age) > age)], axis=2)  # (W, V, N + 1)
    a = np.concatenate([origin[:, :, None], elem], axis=2)  # (W, V, N + 1, 3)
    b = np.concatenate([pick(elem), older(elem)], axis=2)
    seg = np.moveaxis(b - a, -1, 0)[:, :, :, None, :]  # (3, W, V, 1, N + 1)
    rel = np.moveaxis(points, -1, 0)[:, :, None, :, None] - np.moveaxis(a, -1, 0)[:, :, :, None, :]
    t = np.clip(dot_first(rel, seg) / np.maximum(dot_first(seg, seg), TINY), 0.0, 1.0)
    off = rel - t * seg
    j = np.argmin(np.where(ok[:, :, None, :], dot_first(off, off), np.inf), axis=-1)
    tj = np.where(ok.any(axis=-1)[..., None], np.take_along_axis(t, j[..., None], axis=3)[..., 0], 0.0)
    return j, tj


def dot_first(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the first axis (3, ...), summed in index order as `downwash_core.geometry.dot`."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
