"""From one vehicle's measured signals to the arrays of a real flight's log: what every reader shares.

A reader brings each vehicle's samples in SI units on its own time stamps; `vehicle_arrays`
resamples them onto the flight's uniform grid and derives what the log holds besides
(`sim.logs.ARRAY_SPECS` less the truth): the heading, and ``u_cmd``, the acceleration of the
measured thrust less gravity, ``R e3 T / m - g e3``, so that the labels ``a - u`` are the
residual force per mass. `real_flight` stacks the vehicles into one `sim.logs.FlightLog`.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from downwash_core.geometry import quat_to_mat
from downwash_core.params import GRAVITY
from downwash_core.status import Status
from sim.logs import FlightLog

__all__ = ["resample", "vehicle_arrays", "real_flight"]


def resample(t: np.ndarray, grid: np.ndarray, values: np.ndarray) -> np.ndarray:
    """values (N, C) at increasing times t (N,) s, linear at grid (G,) s."""
    return np.stack([np.interp(grid, t, values[:, c]) for c in range(values.shape[1])], axis=1)


def _one_hemisphere(quat: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) with the sign of each chosen so that neighbours agree (q and -q are one
    rotation), so that their components interpolate."""
    flips = np.cumsum(np.r_[0, np.sum(quat[1:] * quat[:-1], axis=1) < 0]) % 2 == 1
    return np.where(flips[:, None], -quat, quat)


def vehicle_arrays(t: np.ndarray, grid: np.ndarray, *, pos: np.ndarray, vel: np.ndarray, quat: np.ndarray,
                   ref_pos: np.ndarray, ref_vel: np.ndarray, thrust: np.ndarray, mass: float) -> dict[str, np.ndarray]:
    """One vehicle's log arrays on `grid` (G,) s from its samples at times t (N,) s: pos (N, 3) m and
    vel (N, 3) m/s (the lab's estimate, fused with its motion capture), quat (N, 4) (w, x, y, z)
    body to world, ref_pos (N, 3) m and ref_vel (N, 3) m/s (the setpoint), thrust (G,) N on the
    grid already (a thrust model may need the grid's step), mass kg."""
    q = resample(t, grid, _one_hemisphere(np.asarray(quat, np.float64)))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    p = resample(t, grid, pos)
    return {
        "pos_est": p, "mocap_pos": p, "vel_est": resample(t, grid, vel), "quat_est": q,
        "yaw_est": np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
        "ref_pos": resample(t, grid, ref_pos), "ref_vel": resample(t, grid, ref_vel), "ref_acc": np.zeros((grid.size, 3)),
        "u_cmd": quat_to_mat(q)[..., 2] * (np.asarray(thrust) / mass)[:, None] - np.array([0.0, 0.0, GRAVITY]),
        "f_hat": np.full((grid.size, 3), np.nan),  # what flew is not in the logs
    }  # fmt: skip


def real_flight(grid: np.ndarray, vehicles: Sequence[dict[str, np.ndarray]], meta: dict[str, Any]) -> FlightLog:
    """The flight log of `vehicle_arrays` per vehicle on `grid`, with `meta` (which must hold the
    ``source``) and the status of a flight that ended as logged."""
    if "source" not in meta:
        raise ValueError("meta: a real flight's log must say its source (the files, their format and digests)")
    arrays = {"t": np.asarray(grid, np.float64), **{n: np.stack([v[n] for v in vehicles], axis=1) for n in vehicles[0]}}
    return FlightLog(arrays, {"leader": -1, "status": Status.OK, "status_name": Status.OK.label, "message": "",
                              "seed": None, **meta})
