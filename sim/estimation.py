"""The Kalman filter that turns a sensor's positions into position/velocity estimates.

The sensor (`sim.sensors`: motion capture, `SimConfig.mocap`) measures every vehicle's
position and attitude at the autopilot rate (100 Hz). The
controller's heading, the learned models and the labels use the measured attitude; the
true one is for the field, the oracle and diagnostics only (the autopilot flies on its
own onboard attitude, which we take as exact).

Each axis is an independent double integrator driven by the commanded acceleration,
with the unmodelled part (downwash, lag) as white process noise, and the sensor's
`measurement_noise` as white measurement noise (a sensor's per-episode offset is no
noise the filter can average away). All axes and vehicles share the same noise model,
so the filter's covariance converges to one steady state: we compute that gain once
(discrete algebraic Riccati equation, scipy) and apply it to the whole batch.
`kalman_gain_sequence` runs the time-varying filter for the test that the steady-state
gain is its limit. `MocapConfig` (the default sensor) is defined in `sim.sensors` and
still imported from here.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg

from downwash_core.jit import njit
from downwash_core.numerics import cpu_independent
from sim.sensors import MocapConfig

__all__ = ["MocapConfig", "steady_state_gain", "kalman_gain_sequence", "MocapKalmanFilter", "kf_predict", "kf_update"]


def _model(dt: float, q_acc: float, r_pos: float):
    F = np.array([[1.0, dt], [0.0, 1.0]])
    G = np.array([[0.5 * dt * dt], [dt]])
    Qn = G @ G.T * q_acc**2
    H = np.array([[1.0, 0.0]])
    Rn = np.array([[max(r_pos, 1e-9) ** 2]])
    return F, G, Qn, H, Rn


def steady_state_gain(dt: float, cfg: Any = MocapConfig()) -> np.ndarray:
    """Steady-state Kalman gain (2,) [position, velocity] per axis for measurements every dt s by
    the sensor `cfg` (its `measurement_noise` and `process_accel_noise`).

    Rounded to float32 precision (`downwash_core.numerics.cpu_independent`): the Riccati solve's
    last bits differ between CPUs, and flights must not."""
    F, _, Qn, H, Rn = _model(dt, cfg.process_accel_noise, cfg.measurement_noise)
    P = scipy.linalg.solve_discrete_are(F.T, H.T, Qn, Rn)  # prior covariance
    return cpu_independent((P @ H.T @ np.linalg.inv(H @ P @ H.T + Rn)).ravel())


def kalman_gain_sequence(dt: float, n: int, cfg: Any = MocapConfig(), p0: float = 1.0) -> np.ndarray:
    """Gains (n, 2) of the time-varying filter from prior covariance p0 * I (slow reference)."""
    F, _, Qn, H, Rn = _model(dt, cfg.process_accel_noise, cfg.measurement_noise)
    P = np.eye(2) * p0
    gains = np.empty((n, 2))
    for k in range(n):
        S = H @ P @ H.T + Rn
        L = P @ H.T / S
        gains[k] = L.ravel()
        P = (np.eye(2) - L @ H) @ P
        P = F @ P @ F.T + Qn
    return gains


class MocapKalmanFilter:
    """Batched predict/update on arrays (..., 3); the state lives with the caller.

    Call `update` at each motion-capture sample and `predict` between samples with
    the commanded acceleration. The filter holds gains, not history; its measurement
    noise is the sensor's (`cfg`, a `sim.sensors` sensor).
    """

    def __init__(self, dt: float, cfg: Any = MocapConfig()):
        self.dt = dt
        self.cfg = cfg
        self.gain = steady_state_gain(dt, cfg)

    def predict(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Propagate (..., 3) estimates one sample period with acceleration acc (m/s^2)."""
        dt = self.dt
        return pos + dt * vel + (0.5 * dt * dt) * acc, vel + dt * acc

    def update(self, pos: np.ndarray, vel: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Correct (..., 3) prior estimates with a position measurement (m)."""
        innov = measured - pos
        return pos + self.gain[0] * innov, vel + self.gain[1] * innov


# Scalar forms of predict/update for compiled loops (the simulator's per-tick kernels);
# the same arithmetic in the same order, so they agree with the class bit for bit (tested).


@njit
def kf_predict(pos: float, vel: float, acc: float, dt: float) -> tuple[float, float]:
    """One axis: propagate position (m) and velocity (m/s) by dt (s) with acceleration acc (m/s^2)."""
    return pos + dt * vel + (0.5 * dt * dt) * acc, vel + dt * acc


@njit
def kf_update(pos: float, vel: float, measured: float, gain_pos: float, gain_vel: float) -> tuple[float, float]:
    """One axis: correct the prior position (m) and velocity (m/s) with a position measurement (m)."""
    innov = measured - pos
    return pos + gain_pos * innov, vel + gain_vel * innov
