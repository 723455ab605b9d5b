"""Which vehicles a vehicle's downwash model sees: its neighbour set, one definition for the
data, the predictor in the loop and the swarm env's observation.

A target's neighbours are the other vehicles at a finite distance (a diverged vehicle's
NaN or infinite state is never a neighbour), within ``radius`` if one is given, nearest
first by squared distance of the estimated positions (ties by vehicle index), padded to
``max_neighbours`` slots with a mask. `select_neighbours` is the readable selection and
`select_into` its compiled twin (one target at a time), which the swarm env's compiled
observation and the compiled predictor passes (`downwash.set_fused`) call; tests tie the
two together.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.geometry import dot
from downwash_core.jit import njit
from downwash_core.roles import MAX_VEHICLES
from downwash_core.validate import count, positive_float

__all__ = ["MAX_NEIGHBOURS", "NeighbourSet", "select_neighbours", "select_into", "gather_neighbours"]

MAX_NEIGHBOURS = 64  # the largest neighbour set a data set or model may ask for


@dataclass(frozen=True)
class NeighbourSet:
    """Which vehicles a target's sample holds: the nearest others, padded to a fixed count.

    max_neighbours: K, the number of slots (1-64); a target with fewer neighbours is padded.
    radius: m, drop neighbours farther than this (centre to centre, estimated positions);
      None keeps every other vehicle (up to K).
    """

    max_neighbours: int = MAX_VEHICLES - 1  # every other vehicle of the largest scene
    radius: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_neighbours", count("max_neighbours", self.max_neighbours, 1, MAX_NEIGHBOURS))
        if self.radius is not None:
            object.__setattr__(self, "radius", positive_float("radius", self.radius, "m"))

    def describe(self) -> dict[str, Any]:
        """The definition, stored with data sets and checkpoints (compared on load)."""
        return {
            "candidates": "every other vehicle",
            "max_neighbours": self.max_neighbours,
            "radius": self.radius,
            "selection": "nearest first (estimated positions), ties by vehicle index",
        }

    @classmethod
    def from_record(cls, record: Any) -> "NeighbourSet":
        """The neighbour set of a stored `describe()` record; ConfigError when it is not one."""
        if not isinstance(record, dict) or "max_neighbours" not in record:
            raise ConfigError(f"neighbour set: expected a record with 'max_neighbours' and 'radius', got {record!r}")
        ns = cls(record["max_neighbours"], record.get("radius"))
        if ns.describe() != record:
            raise ConfigError(f"neighbour set: unknown definition {record!r} (this code writes {ns.describe()!r})")
        return ns


def select_neighbours(pos: np.ndarray, neighbours: NeighbourSet) -> tuple[np.ndarray, np.ndarray]:
    """Each vehicle's neighbour set: (index (..., V, K) int, -1 in padding; mask (..., V, K) bool).

    pos: (..., V, 3) m, the estimated positions. Candidates are the other vehicles with a
    finite distance within ``neighbours.radius``; the nearest K are kept (a stable sort:
    ties go to the lower vehicle index).
    """
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim < 2 or pos.shape[-1] != 3:
        raise ConfigError(f"pos: expected (..., V, 3), got {pos.shape}")
    V, K = pos.shape[-2], neighbours.max_neighbours
    with np.errstate(invalid="ignore"):  # inf - inf: a diverged vehicle, dropped below
        diff = pos[..., :, None, :] - pos[..., None, :, :]
        d2 = dot(diff, diff)  # (..., V target, V candidate), summed as the env's compiled observation sums it
    d2[..., np.arange(V), np.arange(V)] = np.inf
    bad = ~np.isfinite(d2)
    if neighbours.radius is not None:
        bad |= d2 > neighbours.radius**2
    d2 = np.where(bad, np.inf, d2)
    n = min(K, V - 1)
    order = np.argsort(d2, axis=-1, kind="stable")[..., :n]
    mask = np.isfinite(np.take_along_axis(d2, order, -1))
    index = np.where(mask, order, -1)
    if n < K:
        pad = [(0, 0)] * (index.ndim - 1) + [(0, K - n)]
        index = np.pad(index, pad, constant_values=-1)
        mask = np.pad(mask, pad, constant_values=False)
    return index.astype(np.int64), mask


def gather_neighbours(
    pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, index: np.ndarray, mask: np.ndarray
) -> dict[str, np.ndarray]:
    """The model inputs of every vehicle's neighbour set, float64.

    pos, vel (..., V, 3) m, m/s; rot (..., V, 3, 3); index, mask (..., V, K) from
    `select_neighbours`. Returns dp, v_a (..., V, K, 3), v_b (..., V, 3), R_a (..., V, K, 3, 3)
    (see the module doc; padding: dp = v_a = 0, R_a = I).
    """
    pos, vel, rot = (np.asarray(a, dtype=np.float64) for a in (pos, vel, rot))
    V, K = pos.shape[-2], index.shape[-1]
    flat = np.where(mask, index, 0).reshape(*index.shape[:-2], V * K)
    p_n = np.take_along_axis(pos, flat[..., None], -2).reshape(*index.shape, 3)
    v_n = np.take_along_axis(vel, flat[..., None], -2).reshape(*index.shape, 3)
    r_n = np.take_along_axis(rot, flat[..., None, None], -3).reshape(*index.shape, 3, 3)
    m = mask[..., None]
    return {
        "dp": np.where(m, pos[..., :, None, :] - p_n, 0.0),
        "v_a": np.where(m, v_n, 0.0),
        "v_b": vel,
        "R_a": np.where(m[..., None], r_n, np.eye(3)),
    }


@njit
def select_into(pos, w, j, radius2, n_slots, key, idx):
    """Vehicle j's neighbour set in world w: its first n entries of idx (nearest first), n returned.

    pos (W, V, 3) m; radius2: m^2, the squared radius (inf: none); n_slots: K; key (>= V - 1,)
    float64 and idx (>= V - 1,) int64 scratch. A stable insertion sort of the other vehicles by
    squared distance, summed as `sim.neighbours.select_neighbours` sums it; a NaN or infinite
    distance, or one beyond the radius, sorts as +inf and fills no slot.
    """
    V = pos.shape[1]
    m = 0
    for b in range(V):
        if b == j:
            continue
        dx, dy, dz = pos[w, j, 0] - pos[w, b, 0], pos[w, j, 1] - pos[w, b, 1], pos[w, j, 2] - pos[w, b, 2]
        d = dx * dx + dy * dy + dz * dz
        if not d < np.inf or d > radius2:  # NaN, infinite or too far: no neighbour
            d = np.inf
        s = m
        while s > 0 and d < key[s - 1]:  # strict: equal keys keep vehicle order
            key[s] = key[s - 1]
            idx[s] = idx[s - 1]
            s -= 1
        key[s] = d
        idx[s] = b
        m += 1
    n = 0
    while n < n_slots and n < m and key[n] < np.inf:
        n += 1
    return n
