"""Outer-loop incremental nonlinear dynamic inversion (INDI): disturbance rejection from measured acceleration.

Smeur, de Croon & Chu 2016 ("Adaptive incremental nonlinear dynamic inversion for attitude control
of micro air vehicles", JGCD) for the increment; Smeur, de Croon & Chu 2018 ("Cascaded incremental
nonlinear dynamic inversion for MAV disturbance rejection", Control Engineering Practice) and
Tal & Karaman 2021 ("Accurate tracking of aggressive quadrotor trajectories using incremental
nonlinear dynamic inversion and differential flatness", IEEE TCST) for the outer loop. A virtual
acceleration from the tracking errors (e = ref - state),

    nu_k = a_ref + Kp e_p + Kd e_v,

and the command as an increment on the acceleration the vehicle was last asked for,

    u_k = u_f,k-1 + (nu_k - a_f,k),

where a_f is the measured acceleration and u_f the previous commands, each through the same
low-pass filter, so the two are delayed alike: whatever accelerates the vehicle beyond its
command (a slowly varying disturbance, a thrust that is not quite what was believed) shows in
a_f - u_f and is cancelled without a model of it. With nothing unmodelled (the vehicle delivers
what it is asked) a_f = u_f, and the command is nu: the PD law.

Measured acceleration: the finite difference of the estimated velocity over each control
period, (v_k - v_k-1) / dt (what a lab's motion capture gives; an estimator that predicts with the
commanded acceleration, as the simulator's Kalman filter does, puts the command in it and its
corrections carry the rest), through a second-order
Butterworth low-pass at `CUTOFF_HZ` (1.5 Hz, bilinear with pre-warping at the control rate).
The attitude loop is this outer loop's actuator, and u_f stands for what it delivers without a
model of its lag, so the filter must be slower than that loop (the autopilot's 14 rad/s, 2.2 Hz;
the Crazyflie's rotor lag of 86 ms, 1.9 Hz): at 5 Hz the increment rings at the attitude loop's
frequency (lateral commands of 3-4 m/s^2 rms hovering beneath a leader, against 0.3-0.4 at
1.5 Hz, measured in the simulator's so2 field), while at 1.5 Hz a wake crossed in about half a
second is still rejected. The previous command u_f is the acceleration feedback
linearisation delivered, after its tilt and thrust limits (the vehicle cannot be asked for
more, and feeding back the unlimited command would wind the increment up).

Downwash compensation: INDI measures a steady downwash itself, so subtracting the prediction
f_hat whole would count it twice. The prediction enters as the part the filter has not yet
seen, -(f_hat - f_hat,f) with f_hat,f through the same filter: it anticipates the wake that
the measurement reports a filter delay late, and fades as the measurement takes over.
`residual` and `override` act on the command as the interface says.

Gains: Kp and Kd are the default LQR's per axis (`controllers.lqr.lqr_gain` of `LQRConfig()`:
Kp 1.12, 1.12, 3.16 s^-2, Kd 1.50, 1.50, 2.54 s^-1), so the tracking loop's bandwidth is the
LQR's (about 1.1 rad/s lateral, 1.8 rad/s vertical, damping 0.71) and the two differ by the
incremental disturbance rejection only. The attitude loop is the vehicle's autopilot.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from controllers.compiled import finish_one
from controllers.lab_common import LabController, PerWorldState, positive, three
from controllers.lqr import LQRConfig, lqr_gain
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.params import GRAVITY

__all__ = ["CUTOFF_HZ", "butterworth2", "lqr_matched_gains", "INDIController"]

# Hz, the low-pass of the measured acceleration and of the previous commands: below the attitude loop (module doc)
CUTOFF_HZ = 1.5


def butterworth2(cutoff_hz: float, dt: float) -> np.ndarray:
    """(b0, b1, b2, a1, a2) of a second-order Butterworth low-pass at `cutoff_hz` sampled every `dt` s:
    y_k = b0 x_k + b1 x_k-1 + b2 x_k-2 - a1 y_k-1 - a2 y_k-2 (bilinear transform, the cut-off pre-warped),
    unit gain at DC."""
    if not 0.0 < cutoff_hz < 0.5 / dt:
        raise ConfigError(f"cutoff_hz: allowed (0, {0.5 / dt:g}) Hz (below the Nyquist frequency), got {cutoff_hz!r}")
    k = math.tan(math.pi * cutoff_hz * dt)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    b0 = k * k * norm
    return np.array([b0, 2.0 * b0, b0, 2.0 * (k * k - 1.0) * norm, (1.0 - math.sqrt(2.0) * k + k * k) * norm])


def lqr_matched_gains(config: LQRConfig | None = None) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(Kp, Kd) per axis: the diagonal of the LQR gain of `config` (default `LQRConfig()`), the
    position and velocity blocks, so a PD law with them has the LQR's linear closed loop."""
    cfg = config if config is not None else LQRConfig()
    K = lqr_gain(np.diag(cfg.q), np.diag(cfg.r))
    return tuple(float(K[k, k]) for k in range(3)), tuple(float(K[k, 3 + k]) for k in range(3))


class INDIController(LabController):
    """Outer-loop INDI (module doc), batched over (W, V).

    kp (3,) 1/s^2, kd (3,) 1/s: default `lqr_matched_gains()`; cutoff_hz: the filter's cut-off;
    dt, max_tilt_deg, min_thrust_g: see `LabController`. State per world and vehicle: the
    previous velocity, the three filters' states (acceleration, command, prediction) and the
    filtered previous command and prediction, cleared by `reset(worlds)` (a fresh world's first step
    has measured no acceleration: its command is nu less the whole prediction).
    """

    observer_bandwidth = 1.0  # rad/s, as chosen for it (results/observer_bandwidth.json; see FeedbackLinearisedLQR)

    def __init__(self, kp: Any = None, kd: Any = None, cutoff_hz: float = CUTOFF_HZ, **limits: Any):
        super().__init__(**limits)
        default_kp, default_kd = lqr_matched_gains()
        self.kp = three("kp", default_kp if kp is None else kp, strictly_positive=True)
        self.kd = three("kd", default_kd if kd is None else kd, strictly_positive=True)
        self._lqr_matched = kp is None and kd is None
        self.cutoff_hz = positive("cutoff_hz", cutoff_hz)
        self._filter = butterworth2(self.cutoff_hz, self.dt)
        self._params = np.array([*self.kp, *self.kd, *self._filter, self.dt, self._tan_tilt, self._min_vertical],
                                dtype=np.float64)  # as _indi_step reads them
        self._state = PerWorldState(primed=(), vel_prev=(3,), acc_filter=(3, 2), cmd_filter=(3, 2),
                                    prediction_filter=(3, 2), cmd_filtered=(3,), prediction_filtered=(3,))

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "kp": list(self.kp), "kd": list(self.kd), "cutoff_hz": self.cutoff_hz,
                "filter": "second-order Butterworth",
                "gains": "the default LQR's diagonal (lqr_matched_gains)" if self._lqr_matched else "given"}

@njit
def _indi_step(pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual,
               use_override, lookahead, state, params, acc_out, yaw_rate_out, thrust_out, rot_out):
    """The array form (`controllers.compiled`): params (kp, kd (3 each), the biquad (5), dt, tan_tilt,
    min_vertical), state (W, V, 28) as `INDIController._state` lays it out (primed, vel_prev, the three
    filters' (3, 2) states, cmd_filtered, prediction_filtered)."""
    _indi_kernel(pos, vel, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual,
                 use_override, params[0:3], params[3:6], params[6:11], params[11], lookahead, params[12], params[13],
                 state[:, :, 0], state[:, :, 1:4], state[:, :, 4:10], state[:, :, 10:16], state[:, :, 16:22],
                 state[:, :, 22:25], state[:, :, 25:28], acc_out, yaw_rate_out, thrust_out, rot_out)


@njit
def _lowpass(states, w, i, k, x, c):
    """One sample x through the biquad c = (b0, b1, b2, a1, a2) (transposed direct form II): its two
    states are states[w, i, 2 k] and states[w, i, 2 k + 1] (a filter's (3, 2) states, flattened)."""
    y = c[0] * x + states[w, i, 2 * k]
    states[w, i, 2 * k] = c[1] * x - c[3] * y + states[w, i, 2 * k + 1]
    states[w, i, 2 * k + 1] = c[2] * x - c[4] * y
    return y


@njit
def _indi_kernel(pos, vel, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual,
                 use_override, kp, kd, c, dt, lookahead, tan_tilt, min_vertical, primed, vel_prev, acc_filter,
                 cmd_filter, prediction_filter, cmd_filtered, prediction_filtered, acc_out, yaw_rate_out, thrust_out,
                 rot_out):
    """One step on (W, V, ...) arrays (module doc): the measured acceleration filtered, the increment,
    `finish_one`, then the delivered command and the prediction into their filters for the next step
    (each filter's output at step k has seen the samples up to k - 1, as a_f has seen the accelerations
    they caused)."""
    W, V = pos.shape[0], pos.shape[1]
    for w in range(W):
        for i in range(V):
            for k in range(3):
                acc_f = 0.0  # a fresh world has measured none yet (its filters hold zeros)
                if primed[w, i] != 0.0:
                    acc_f = _lowpass(acc_filter, w, i, k, (vel[w, i, k] - vel_prev[w, i, k]) / dt, c)
                vel_prev[w, i, k] = vel[w, i, k]
                nu = ref_acc[w, i, k] + kp[k] * (ref_pos[w, i, k] - pos[w, i, k]) + kd[k] * (ref_vel[w, i, k] - vel[w, i, k])
                acc_out[w, i, k] = nu + (cmd_filtered[w, i, k] - acc_f) - (f_hat[w, i, k] - prediction_filtered[w, i, k])
                prediction_filtered[w, i, k] = _lowpass(prediction_filter, w, i, k, f_hat[w, i, k], c)
            primed[w, i] = 1.0
            yaw_rate_out[w, i] = ref_yaw_rate[w, i]
            yaw_des = ref_yaw[w, i] + ref_yaw_rate[w, i] * lookahead
            thrust = finish_one(acc_out, w, i, residual, override, use_residual, use_override, yaw_des, tan_tilt,
                                min_vertical, rot_out)
            thrust_out[w, i] = thrust
            for k in range(3):  # the acceleration delivered: thrust along the desired body z, less gravity
                delivered = thrust * rot_out[w, i, k, 2] - (GRAVITY if k == 2 else 0.0)
                cmd_filtered[w, i, k] = _lowpass(cmd_filter, w, i, k, delivered, c)


INDIController.step_function = _indi_step
