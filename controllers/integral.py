"""The LQR with integral action on the position error: the first tool against a steady disturbance.

The state of `controllers.lqr` is augmented with the integral of the position error,
x = [int(p - p_ref) (3), p - p_ref (3), v - v_ref (3), psi - psi_ref], and the gain comes from
python-control on the augmented system (d/dt int = p - p_ref),

    u = a_ref - K_i int(p - p_ref) - K (x - x_ref) - f_hat,

so a constant disturbance leaves no steady position error. Anti-windup by conditional
integration: a world and vehicle whose command the actuators cannot follow (the tilt limit or
the thrust floor of feedback linearisation cut it, or the command is overridden) does not
integrate that tick, and the integral's authority is bounded (``max_integral_acc`` m/s^2 per
axis). The integral is state: ``reset(worlds)`` clears it, as the simulator does at a world's reset.
"""

from __future__ import annotations

import math
from typing import Any

import control
import numpy as np

from controllers.lqr import DEFAULT_Q, ControllerState, FeedbackLinearisedLQR, LQRConfig, Setpoint, check_weight
from downwash_core.errors import ConfigError
from downwash_core.numerics import cpu_independent, matmul_rows
from downwash_core.params import GRAVITY, RATES
from downwash_core.state import RefSample

__all__ = ["IntegralLQR", "integral_lqr_gain", "DEFAULT_QI"]

# Weights of the position error's integral, one per axis: the vertical weighted as the LQR
# weights the vertical position (8 against 1), so the integral acts within about a second.
DEFAULT_QI = (0.5, 0.5, 4.0)


def integral_lqr_gain(q: Any = tuple(np.diag(DEFAULT_Q)), qi: Any = DEFAULT_QI, r: Any = (0.8, 0.8, 0.8, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """(K_i (3, 3), K (4, 7)): the continuous-time LQR gain of the augmented system from `control.lqr`,
    split into the integral's columns and the state's, rounded past LAPACK's last bits
    (`downwash_core.numerics.cpu_independent`)."""
    Q = check_weight(np.diag(np.concatenate([np.asarray(qi, float), np.asarray(q, float)])), 10, "Q", definite=False)
    R = check_weight(np.diag(np.asarray(r, float)), 4, "R", definite=True)
    A = np.zeros((10, 10))
    A[0:3, 3:6] = np.eye(3)  # d/dt int(e_p) = e_p
    A[3:6, 6:9] = np.eye(3)  # d/dt e_p = e_v
    B = np.zeros((10, 4))
    B[6:9, 0:3] = np.eye(3)
    B[9, 3] = 1.0
    K, _, _ = control.lqr(A, B, Q, R)
    K = cpu_independent(K)
    return K[:3, :3].copy(), K[:, 3:].copy()


class IntegralLQR:
    """The feedback-linearised LQR with integral action on the position error (module doc).

    config: the LQR's weights and limits (`LQRConfig`); qi: the integral's weights (3,);
    dt: s, the controller period the integral advances by; max_integral_acc: m/s^2, the most the
    integral may command per axis.
    """

    stateful = True

    def __init__(self, config: LQRConfig | None = None, qi: Any = DEFAULT_QI, dt: float = RATES.control_dt,
                 max_integral_acc: float = 0.5 * GRAVITY):
        qi = tuple(float(x) for x in qi)
        if len(qi) != 3 or not all(math.isfinite(x) and x > 0 for x in qi):
            raise ConfigError(f"qi: expected 3 finite weights > 0, got {qi}")
        for name, value in (("dt", dt), ("max_integral_acc", max_integral_acc)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"{name}: expected a finite number > 0, got {value!r}")
        self.config = config if config is not None else LQRConfig()
        self.qi, self.dt, self.max_integral_acc = qi, float(dt), float(max_integral_acc)
        self.K_i, self.K = integral_lqr_gain(self.config.q, qi, self.config.r)
        # the state feedback runs through the LQR's own compiled pass with these gains
        self._inner = FeedbackLinearisedLQR(self.config, gain=self.K)
        self._limit = self.max_integral_acc / np.abs(np.diag(self.K_i))  # m s per axis: the bound's integral
        self._integral: np.ndarray | None = None  # (W, V, 3) m s, the position error's integral

    def describe(self) -> dict[str, Any]:
        return {"type": type(self).__name__, **self.config.to_dict(), "qi": list(self.qi), "dt": self.dt,
                "max_integral_acc": self.max_integral_acc}

    @property
    def integral(self) -> np.ndarray | None:
        """(W, V, 3) m s: the position error's integral (None before the first command)."""
        return self._integral

    def reset(self, worlds: Any = None) -> None:
        """These worlds (None: all) start with no integral."""
        if self._integral is not None:
            self._integral[slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64)] = 0.0

    def command_setpoint(self, state: ControllerState, ref: RefSample, f_hat: np.ndarray, out: Setpoint,
                         residual: np.ndarray | None = None, override: np.ndarray | None = None,
                         lookahead: float = 0.0) -> None:
        """The LQR's command with the integral's term as a feed-forward, then the integral advanced
        where the actuators follow (module doc); fills `out` as `FeedbackLinearisedLQR.command_setpoint`."""
        W, V = state.pos.shape[:2]
        if self._integral is None or self._integral.shape[:2] != (W, V):
            self._integral = np.zeros((W, V, 3))
        bound = self.max_integral_acc
        integral_acc = np.clip(matmul_rows(self._integral, self.K_i.T.copy()), -bound, bound)  # (W, V, 3) K_i int(e)
        # the integral's term enters as part of the prediction subtracted: one compiled pass, the same limits
        self._inner.command_setpoint(state, ref, f_hat + integral_acc, out, residual, override, lookahead)
        achieved = out.thrust[..., None] * out.rot[..., :, 2] - np.array([0.0, 0.0, GRAVITY])
        follows = np.all(np.abs(achieved - out.acc) <= 1e-9 * (1.0 + np.abs(out.acc)), axis=-1)
        if override is not None:
            follows &= ~np.any(np.isfinite(override), axis=-1)
        step = np.where(follows[..., None], (state.pos - ref.pos) * self.dt, 0.0)
        self._integral += step
        np.clip(self._integral, -self._limit, self._limit, out=self._integral)  # bounded authority
