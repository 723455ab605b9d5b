"""Feedback-linearised LQR outer loop (paper eq. 2).

State x = [p (3), v (3), psi], input u = [a (3), psi_dot], world frame z up.
The gain comes from python-control; the command is

    u_f = a_ref - K (x - x_ref) - f_hat

and feedback linearisation turns the acceleration part into a collective thrust
and a desired attitude for the autopilot. The controller holds gains, not history.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import control
import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.geometry import wrap_angle
from downwash_core.jit import njit
from downwash_core.numerics import cpu_independent, matmul_rows
from downwash_core.params import GRAVITY
from downwash_core.state import RefSample

__all__ = [
    "DEFAULT_Q",
    "DEFAULT_R",
    "MAX_TILT_DEG",
    "MIN_THRUST_G",
    "LQRConfig",
    "ControllerState",
    "Setpoint",
    "LQRCommand",
    "double_integrator",
    "lqr_gain",
    "check_weight",
    "FeedbackLinearisedLQR",
    "attitude_setpoint",
    "wrap_angle",
]

# Weights like the Freyja LQG controller of the paper.
DEFAULT_Q = np.diag([1.0, 1.0, 8.0, 0.01, 0.01, 0.1, 1.0])
DEFAULT_R = np.diag([0.8, 0.8, 0.8, 1.0])
MAX_TILT_DEG = 35.0  # deg, tilt limit of feedback linearisation
MIN_THRUST_G = 0.25  # g, floor of the commanded vertical specific force (no commanded free fall)


@dataclass(frozen=True)
class LQRConfig:
    """The outer loop's settings: LQR weights and the feedback-linearisation limits."""

    q: tuple[float, ...] = tuple(np.diag(DEFAULT_Q))  # diagonal of Q: [p (m), v (m/s), psi (rad)] weights
    r: tuple[float, ...] = tuple(np.diag(DEFAULT_R))  # diagonal of R: [a (m/s^2), psi_dot (rad/s)] weights
    max_tilt_deg: float = MAX_TILT_DEG  # deg
    min_thrust_g: float = MIN_THRUST_G  # g

    def __post_init__(self) -> None:
        if len(self.q) != 7 or len(self.r) != 4:
            raise ConfigError(f"LQRConfig.q/r: expected 7 and 4 diagonal entries, got {len(self.q)} and {len(self.r)}")
        if not 0.0 < self.max_tilt_deg < 90.0:
            raise ConfigError(f"LQRConfig.max_tilt_deg: allowed (0, 90) deg, got {self.max_tilt_deg}")
        if not 0.0 <= self.min_thrust_g < 1.0:
            raise ConfigError(f"LQRConfig.min_thrust_g: allowed [0, 1) g, got {self.min_thrust_g}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_pd(cls, kp: tuple[float, float, float], kd: tuple[float, float, float], r: float = 0.8,
                **limits: Any) -> "LQRConfig":
        """The weights whose gain on each axis of the double integrator is the PD law (kp s^-2, kd s^-1):
        with R = r, the LQR gain is K_p = sqrt(q_p / r) and K_v = sqrt(q_v / r + 2 K_p), so
        q_p = kp^2 r and q_v = (kd^2 - 2 kp) r, which needs kd^2 >= 2 kp (an LQR gain on a double
        integrator is at least that damped). The yaw weights are the default's. For comparing with a lab's PD controller."""
        kp, kd = tuple(float(x) for x in kp), tuple(float(x) for x in kd)
        if len(kp) != 3 or len(kd) != 3 or not all(math.isfinite(x) and x > 0 for x in (*kp, *kd, r)):
            raise ConfigError(f"LQRConfig.from_pd: expected 3 finite kp > 0 and 3 kd > 0 and r > 0, got {kp}, {kd}, {r}")
        if any(d * d < 2.0 * p * (1.0 - 1e-12) for p, d in zip(kp, kd)):  # (the boundary within rounding)
            raise ConfigError(f"LQRConfig.from_pd: kd^2 >= 2 kp on every axis for an LQR gain, got kp {kp}, kd {kd}")
        q = (*(p * p * r for p in kp), *(max(d * d - 2.0 * p, 0.0) * r for p, d in zip(kp, kd)), float(DEFAULT_Q[6, 6]))
        return cls(q=q, r=(r, r, r, float(DEFAULT_R[3, 3])), **limits)


class ControllerState(NamedTuple):
    """What the outer loop knows of each vehicle, batched (...): the estimator's output.

    pos: (..., 3) m and vel: (..., 3) m/s, world frame; yaw: (...,) rad (motion capture).
    """

    pos: np.ndarray
    vel: np.ndarray
    yaw: np.ndarray


class Setpoint(NamedTuple):
    """The outer loop's output for the autopilot, batched (W, V, ...); buffers the fast path fills.

    acc: (W, V, 3) m/s^2, the command u applied (gravity excluded, compensation included);
    yaw_rate: (W, V) rad/s; thrust: (W, V) m/s^2, collective thrust / mass;
    rot: (W, V, 3, 3) desired attitude R_d, body to world.
    """

    acc: np.ndarray
    yaw_rate: np.ndarray
    thrust: np.ndarray
    rot: np.ndarray

    @classmethod
    def empty(cls, n_worlds: int, n_vehicles: int) -> "Setpoint":
        W, V = n_worlds, n_vehicles
        return cls(np.empty((W, V, 3)), np.empty((W, V)), np.empty((W, V)), np.empty((W, V, 3, 3)))


def double_integrator() -> tuple[np.ndarray, np.ndarray]:
    """A (7, 7), B (7, 4) of the paper's eq. 2 (three double integrators and a yaw integrator)."""
    A = np.zeros((7, 7))
    A[0:3, 3:6] = np.eye(3)
    B = np.zeros((7, 4))
    B[3:6, 0:3] = np.eye(3)
    B[6, 3] = 1.0
    return A, B


def check_weight(M: np.ndarray, n: int, name: str, definite: bool) -> np.ndarray:
    """M as a symmetric (n, n) weight, positive (semi-)definite; ConfigError naming `name` otherwise."""
    M = np.asarray(M, dtype=float)
    if M.shape != (n, n):
        raise ConfigError(f"{name}: expected ({n}, {n}) but found {M.shape}")
    if not np.allclose(M, M.T):
        raise ConfigError(f"{name}: must be symmetric")
    eig = np.linalg.eigvalsh(M)
    if definite and eig.min() <= 0:
        raise ConfigError(f"{name}: must be positive definite (smallest eigenvalue {eig.min():.3g})")
    if not definite and eig.min() < -1e-12:
        raise ConfigError(f"{name}: must be positive semi-definite (smallest eigenvalue {eig.min():.3g})")
    return M


def lqr_gain(Q: np.ndarray = DEFAULT_Q, R: np.ndarray = DEFAULT_R) -> np.ndarray:
    """Continuous-time LQR gain K (4, 7) of the double integrator from `control.lqr`.

    Rounded to float32 precision (`downwash_core.numerics.cpu_independent`): LAPACK's last bits
    differ between CPUs, and flights must not."""
    Q = check_weight(Q, 7, "Q", definite=False)
    R = check_weight(R, 4, "R", definite=True)
    A, B = double_integrator()
    K, _, _ = control.lqr(A, B, Q, R)
    return cpu_independent(K)


class LQRCommand(NamedTuple):
    """Outer-loop output, batched (...).

    acc: (..., 3) m/s^2, commanded acceleration u_f (gravity excluded, compensation included).
    yaw_rate: (...,) rad/s.
    """

    acc: np.ndarray
    yaw_rate: np.ndarray


class FeedbackLinearisedLQR:
    """u_f = a_ref - K (x - x_ref) - f_hat, then feedback linearisation; batched over any leading shape.

    Holds gains, not history. `__call__` and `setpoint` are the readable steps;
    `command_setpoint` is both in one compiled pass over (W, V) arrays (the
    simulator's 50 Hz path), tested against them.
    """

    # rad/s: the disturbance observer's bandwidth under this controller, chosen on the training flights
    # (`python -m experiments.observer_bandwidth`, results/observer_bandwidth.json; sim.observer.bandwidth_for)
    observer_bandwidth = 8.0

    def __init__(self, config: LQRConfig | None = None, gain: np.ndarray | None = None):
        """gain: (4, 7) K in place of the LQR gain of `config`'s weights (e.g. the state part of an
        augmented system's gain, `controllers.integral`); the limits are still `config`'s."""
        self.config = config if config is not None else LQRConfig()
        self.K = lqr_gain(np.diag(self.config.q), np.diag(self.config.r)) if gain is None else np.array(gain, float)
        if self.K.shape != (4, 7):
            raise ConfigError(f"gain: expected a (4, 7) matrix, got {self.K.shape}")
        # The gain is block diagonal for diagonal weights; keep the full matrix anyway.
        self._Kt = self.K.T.copy()
        self.max_tilt = float(np.deg2rad(self.config.max_tilt_deg))  # rad
        self.min_vertical = self.config.min_thrust_g * GRAVITY  # m/s^2

    def describe(self) -> dict[str, Any]:
        """Class and settings (JSON-serialisable), for logs and provenance."""
        return {"type": type(self).__name__, **self.config.to_dict()}

    def __call__(self, state: ControllerState, ref: RefSample, f_hat: np.ndarray | None = None) -> LQRCommand:
        """The LQR command for estimated `state` and reference `ref` (same batch shapes);
        f_hat (..., 3) m/s^2 is the predicted downwash, subtracted."""
        err = np.concatenate(
            [state.pos - ref.pos, state.vel - ref.vel, wrap_angle(state.yaw - ref.yaw)[..., None]], axis=-1
        )
        fb = matmul_rows(err, self._Kt)  # (..., 4) = K (x - x_ref)
        acc = ref.acc - fb[..., :3]
        if f_hat is not None:
            acc = acc - f_hat
        return LQRCommand(acc, ref.yaw_rate - fb[..., 3])

    def setpoint(self, acc: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feedback linearisation with this controller's limits (see `attitude_setpoint`)."""
        return attitude_setpoint(acc, yaw, self.max_tilt, self.min_vertical)

    def command_setpoint(
        self,
        state: ControllerState,
        ref: RefSample,
        f_hat: np.ndarray,
        out: Setpoint,
        residual: np.ndarray | None = None,
        override: np.ndarray | None = None,
        lookahead: float = 0.0,
    ) -> None:
        """The control-rate step in one compiled pass, for (W, V, ...) float64 arrays.

        Same meaning as `__call__` followed by `setpoint`: u = a_ref - K (x - x_ref) - f_hat,
        plus `residual` (W, V, 3) m/s^2 when given, replaced by `override` (W, V, 3) m/s^2
        where that is finite; then feedback linearisation towards the heading
        yaw + yaw_rate * lookahead (s). Writes into the buffers of `out`.
        """
        command_setpoint_kernel(
            state.pos, state.vel, state.yaw, ref.pos, ref.vel, ref.acc, ref.yaw, ref.yaw_rate, f_hat,
            f_hat if residual is None else residual, f_hat if override is None else override,  # (unread when None)
            residual is not None, override is not None, self._Kt, lookahead, math.tan(self.max_tilt),
            self.min_vertical, *out,
        )


def attitude_setpoint(
    acc: np.ndarray, yaw: np.ndarray, max_tilt: float = np.deg2rad(MAX_TILT_DEG), min_vertical: float = MIN_THRUST_G * GRAVITY
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
        math.tan(max_tilt), min_vertical,
    )
    return thrust.reshape(batch), rot.reshape(batch + (3, 3))


@njit
def _attitude_setpoint_kernel(acc, yaw, tan_tilt, min_vertical):
    n = acc.shape[0]
    thrust = np.empty(n)
    rot = np.empty((n, 3, 3))
    for i in range(n):
        thrust[i] = setpoint_one(acc[i, 0], acc[i, 1], acc[i, 2], yaw[i], tan_tilt, min_vertical, rot[i])
    return thrust, rot


@njit
def setpoint_one(ax, ay, az, yaw, tan_tilt, min_vertical, rot):
    """One vehicle of `attitude_setpoint`: writes R_d into rot (3, 3), returns the thrust (m/s^2)."""
    fx, fy, fz = ax, ay, max(az + GRAVITY, min_vertical)
    nxy = np.sqrt(fx * fx + fy * fy)
    limit = tan_tilt * fz
    if nxy > limit:  # keep the heading of the lateral command, shorten it to the tilt limit
        fx, fy = fx * limit / nxy, fy * limit / nxy
    t = np.sqrt(fx * fx + fy * fy + fz * fz)
    b3x, b3y, b3z = fx / t, fy / t, fz / t
    # b2 = b3 x c1 / |.| with c1 = (cos yaw, sin yaw, 0) the heading; b1 = b2 x b3
    c, s = np.cos(yaw), np.sin(yaw)
    b2x, b2y, b2z = -b3z * s, b3z * c, b3x * s - b3y * c
    norm = np.sqrt(b2x * b2x + b2y * b2y + b2z * b2z)
    b2x, b2y, b2z = b2x / norm, b2y / norm, b2z / norm
    rot[0, 0], rot[1, 0], rot[2, 0] = b2y * b3z - b2z * b3y, b2z * b3x - b2x * b3z, b2x * b3y - b2y * b3x
    rot[0, 1], rot[1, 1], rot[2, 1] = b2x, b2y, b2z
    rot[0, 2], rot[1, 2], rot[2, 2] = b3x, b3y, b3z
    return t


@njit
def command_setpoint_kernel(
    pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual,
    use_override, Kt, lookahead, tan_tilt, min_vertical, acc_out, yaw_rate_out, thrust_out, rot_out,
):
    """Compiled body of `FeedbackLinearisedLQR.command_setpoint` on (W, V, ...) arrays; residual and
    override (W, V, 3) are read only where use_residual / use_override say so (flags, not None
    arguments: one compiled form serves every combination)."""
    W, V = pos.shape[0], pos.shape[1]
    err = np.empty(7)
    for w in range(W):
        for i in range(V):
            for k in range(3):
                err[k] = pos[w, i, k] - ref_pos[w, i, k]
                err[3 + k] = vel[w, i, k] - ref_vel[w, i, k]
            d = yaw[w, i] - ref_yaw[w, i]
            err[6] = (d + np.pi) % (2.0 * np.pi) - np.pi  # wrap_angle
            for k in range(4):
                fb = 0.0  # K (x - x_ref), row k
                for j in range(7):
                    fb += err[j] * Kt[j, k]
                if k < 3:
                    a = ref_acc[w, i, k] - fb - f_hat[w, i, k]
                    if use_residual:
                        a = a + residual[w, i, k]
                    if use_override and np.isfinite(override[w, i, k]):
                        a = override[w, i, k]
                    acc_out[w, i, k] = a
                else:
                    yaw_rate_out[w, i] = ref_yaw_rate[w, i] - fb
            yaw_des = yaw[w, i] + yaw_rate_out[w, i] * lookahead
            thrust_out[w, i] = setpoint_one(
                acc_out[w, i, 0], acc_out[w, i, 1], acc_out[w, i, 2], yaw_des, tan_tilt, min_vertical, rot_out[w, i]
            )
