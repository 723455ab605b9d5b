"""Tracking metrics of a flight (DESIGN section 10), in SI units."""

from __future__ import annotations

import numpy as np

from sim.logs import FlightLog

__all__ = ["TRACKING_METRICS", "IMPROVEMENT_METRICS", "tracking_errors", "tracking_metrics", "improvement"]

TRACKING_METRICS = (
    "pos_err_3d_mean", "pos_err_xy_mean", "pos_err_z_mean", "pos_err_3d_peak",
    "vel_err_3d_mean", "vel_err_xy_mean", "vel_err_z_mean",
)
# improvement_<name>: fraction by which a condition's metric is smaller than the baseline's
IMPROVEMENT_METRICS = {"improvement_pos_3d": "pos_err_3d_mean", "improvement_pos_z": "pos_err_z_mean", "improvement_vel_3d": "vel_err_3d_mean"}


def tracking_errors(log: FlightLog, vehicle: int | None = None) -> dict[str, np.ndarray]:
    """Per-tick errors of one vehicle (default: the log's follower): true state minus reference.

    Returns pos_3d, pos_xy, pos_z (m) and vel_3d, vel_xy, vel_z (m/s), each (T,).
    """
    v = log.meta.get("follower", 1) if vehicle is None else vehicle
    dp = log["pos"][:, v] - log["ref_pos"][:, v]
    dv = log["vel"][:, v] - log["ref_vel"][:, v]
    return {
        "pos_3d": np.linalg.norm(dp, axis=1), "pos_xy": np.linalg.norm(dp[:, :2], axis=1), "pos_z": np.abs(dp[:, 2]),
        "vel_3d": np.linalg.norm(dv, axis=1), "vel_xy": np.linalg.norm(dv[:, :2], axis=1), "vel_z": np.abs(dv[:, 2]),
    }


def tracking_metrics(log: FlightLog, vehicle: int | None = None) -> dict[str, float]:
    """The scalar metrics of TRACKING_METRICS for one flight."""
    if len(log) == 0:
        raise ValueError("tracking_metrics: the log has no rows")
    e = tracking_errors(log, vehicle)
    out = {}
    for key, x in e.items():  # "pos_3d" -> "pos_err_3d_mean"
        quantity, axes = key.split("_")
        out[f"{quantity}_err_{axes}_mean"] = float(x.mean())
    out["pos_err_3d_peak"] = float(e["pos_3d"].max())
    return {k: out[k] for k in TRACKING_METRICS}


def improvement(metrics: dict[str, float], baseline: dict[str, float]) -> dict[str, float]:
    """Fractions by which `metrics` improve on `baseline` (0.36: 36 % smaller error)."""
    return {name: 1.0 - metrics[m] / baseline[m] for name, m in IMPROVEMENT_METRICS.items()}
