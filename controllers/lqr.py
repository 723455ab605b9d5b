"""Feedback-linearised LQR outer loop (paper eq. 2; DESIGN section 4).

State x = [p (3), v (3), psi], input u = [a (3), psi_dot], world frame z up.
The gain comes from python-control; the command is

    u_f = a_ref - K (x - x_ref) - f_hat

and feedback linearisation turns the acceleration part into a collective thrust
and a desired attitude for the autopilot. The controller holds gains, not history.
"""

from __future__ import annotations

from typing import NamedTuple

import control
import numpy as np

from sim.jit import njit
from sim.params import GRAVITY

__all__ = [
    "DEFAULT_Q",
    "DEFAULT_R",
    "double_integrator",
    "lqr_gain",
    "LQRCommand",
    "FeedbackLinearisedLQR",
    "attitude_setpoint",
    "wrap_angle",
]

# Weights like the Freyja LQG controller of the paper (DESIGN section 4).
DEFAULT_Q = np.diag([1.0, 1.0, 8.0, 0.01, 0.01, 0.1, 1.0])
DEFAULT_R = np.diag([0.8, 0.8, 0.8, 1.0])


def double_integrator() -> tuple[np.ndarray, np.ndarray]:
    """A (7, 7), B (7, 4) of the paper's eq. 2 (three double integrators and a yaw integrator)."""
    A = np.zeros((7, 7))
    A[0:3, 3:6] = np.eye(3)
    B = np.zeros((7, 4))
    B[3:6, 0:3] = np.eye(3)
    B[6, 3] = 1.0
    return A, B


def _check_weight(M: np.ndarray, n: int, name: str, definite: bool) -> np.ndarray:
    M = np.asarray(M, dtype=float)
    if M.shape != (n, n):
        raise ValueError(f"{name}: expected ({n}, {n}) but found {M.shape}")
    if not np.allclose(M, M.T):
        raise ValueError(f"{name}: must be symmetric")
    eig = np.linalg.eigvalsh(M)
    if definite and eig.min() <= 0:
        raise ValueError(f"{name}: must be positive definite (smallest eigenvalue {eig.min():.3g})")
    if not definite and eig.min() < -1e-12:
        raise ValueError(f"{name}: must be positive semi-definite (smallest eigenvalue {eig.min():.3g})")
    return M


def lqr_gain(Q: np.ndarray = DEFAULT_Q, R: np.ndarray = DEFAULT_R) -> np.ndarray:
    """Continuous-time LQR gain K (4, 7) of the double integrator from `control.lqr`."""
    Q = _check_weight(Q, 7, "Q", definite=False)
    R = _check_weight(R, 4, "R", definite=True)
    A, B = double_integrator()
    K, _, _ = control.lqr(A, B, Q, R)
    return np.asarray(K)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles (rad) to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


class LQRCommand(NamedTuple):
    """Outer-loop output, batched (...).

    acc: (..., 3) m/s^2, commanded acceleration u_f (gravity excluded, compensation included).
    yaw_rate: (...,) rad/s.
    """

    acc: np.ndarray
    yaw_rate: np.ndarray


class FeedbackLinearisedLQR:
    """u_f = a_ref - K (x - x_ref) - f_hat, batched over any leading shape."""

    def __init__(self, Q: np.ndarray = DEFAULT_Q, R: np.ndarray = DEFAULT_R):
        self.K = lqr_gain(Q, R)
        # The gain is block diagonal for diagonal weights; keep the full matrix anyway so
        # that any Q, R the user passes is honoured.
        self._Kt = self.K.T.copy()

    def __call__(
        self,
        pos: np.ndarray,
        vel: np.ndarray,
        yaw: np.ndarray,
        ref_pos: np.ndarray,
        ref_vel: np.ndarray,
        ref_acc: np.ndarray,
        ref_yaw: np.ndarray,
        ref_yaw_rate: np.ndarray,
        f_hat: np.ndarray | None = None,
    ) -> LQRCommand:
        """All (..., 3) in m, m/s, m/s^2 (world), yaw terms (...,) in rad, rad/s; f_hat (..., 3) m/s^2."""
        err = np.concatenate([pos - ref_pos, vel - ref_vel, wrap_angle(yaw - ref_yaw)[..., None]], axis=-1)
        fb = err @ self._Kt  # (..., 4) = K (x - x_ref)
        acc = ref_acc - fb[..., :3]
        if f_hat is not None:
            acc = acc - f_hat
        return LQRCommand(acc, ref_yaw_rate - fb[..., 3])


def attitude_setpoint(
    acc: np.ndarray, yaw: np.ndarray, max_tilt: float = np.deg2rad(35.0), min_vertical: float = 0.25 * GRAVITY
) -> tuple[np.ndarray, np.ndarray]:
    """Feedback linearisation: acceleration command -> (specific thrust, desired attitude).

    acc: (..., 3) m/s^2 desired acceleration (gravity excluded); yaw: (...,) rad desired heading.
    Returns thrust_acc (...,) m/s^2 (collective thrust / mass) and R_d (..., 3, 3) body-to-world,
    whose third column is the desired thrust direction. The tilt is limited to `max_tilt`
    and the vertical specific force kept above `min_vertical` (no commanded free fall).
    """
    batch = yaw.shape
    thrust, rot = _attitude_setpoint_kernel(
        acc.reshape(-1, 3).astype(float, copy=False), yaw.reshape(-1).astype(float, copy=False),
        np.tan(max_tilt), min_vertical,
    )
    return thrust.reshape(batch), rot.reshape(batch + (3, 3))


@njit
def _attitude_setpoint_kernel(acc, yaw, tan_tilt, min_vertical):
    n = acc.shape[0]
    thrust = np.empty(n)
    rot = np.empty((n, 3, 3))
    for i in range(n):
        fx, fy, fz = acc[i, 0], acc[i, 1], max(acc[i, 2] + GRAVITY, min_vertical)
        nxy = np.sqrt(fx * fx + fy * fy)
        limit = tan_tilt * fz
        if nxy > limit:  # keep the heading of the lateral command, shorten it to the tilt limit
            fx, fy = fx * limit / nxy, fy * limit / nxy
        t = np.sqrt(fx * fx + fy * fy + fz * fz)
        thrust[i] = t
        b3x, b3y, b3z = fx / t, fy / t, fz / t
        # b2 = b3 x c1 / |.| with c1 = (cos yaw, sin yaw, 0) the heading; b1 = b2 x b3
        c, s = np.cos(yaw[i]), np.sin(yaw[i])
        b2x, b2y, b2z = -b3z * s, b3z * c, b3x * s - b3y * c
        norm = np.sqrt(b2x * b2x + b2y * b2y + b2z * b2z)
        b2x, b2y, b2z = b2x / norm, b2y / norm, b2z / norm
        rot[i, 0, 0], rot[i, 1, 0], rot[i, 2, 0] = b2y * b3z - b2z * b3y, b2z * b3x - b2x * b3z, b2x * b3y - b2y * b3x
        rot[i, 0, 1], rot[i, 1, 1], rot[i, 2, 1] = b2x, b2y, b2z
        rot[i, 0, 2], rot[i, 1, 2], rot[i, 2, 2] = b3x, b3y, b3z
    return thrust, rot
