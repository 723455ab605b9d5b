"""Low-level attitude autopilot: geometric attitude control, mixer, motor saturation.

Runs on the autopilot grid (100 Hz by default), batched over any leading shape.
It takes the collective specific thrust and desired attitude from feedback
linearisation and returns per-rotor thrust commands (N), which the MuJoCo rotor
actuators follow with their first-order lag. One `Autopilot` is one vehicle's; the
simulator flies a scene of several kinds with `Autopilot.tables`: the same attitude loop
for every vehicle, each through its own inertia, mixer and rotor limit.

Saturation puts attitude first: when a rotor's demand exceeds its limit, every rotor's
demand drops by the excess (the torques kept, collective thrust given up), then each is
clipped to [0, limit]. This is what flight firmware does (the Crazyflie's power
distribution cap, PX4's mixer desaturation). Clipping each rotor on its own instead
throws away the torques exactly when a vehicle needs all its thrust: in a strong wake it
loses its attitude as well as its height, and falls.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from downwash_core.jit import njit
from downwash_core.params import QUAD, QuadParams
from downwash_core.vehicles import as_params

__all__ = ["mixer_matrix", "Autopilot", "rotor_thrusts"]


def mixer_matrix(params: QuadParams = QUAD) -> np.ndarray:
    """M (4, 4): [collective thrust N, torque x, torque y, torque z (N m)] = M @ rotor thrusts (N)."""
    r = params.rotor_positions
    return np.stack(
        [
            np.ones(4),
            r[:, 1],  # torque about x from thrust along z at (x, y): y * f
            -r[:, 0],  # torque about y: -x * f
            params.rotor_spin * params.yaw_moment_coeff,
        ]
    )


class Autopilot:
    """Attitude control on SO(3) (Lee et al. 2010) with rate damping and a yaw-rate set-point.

    Gains are natural frequencies (rad/s) and damping ratios of the attitude loop, turned
    into torques through the inertia, so they hold for any vehicle of `params`.

    The attitude error, the PD law and the mixer are all linear in
    [collective thrust, flattened R_d^T R, body rates, yaw-rate set-point], so they are
    folded into one (14, 4) matrix at construction: a handful of array operations per
    call for the whole batch (this runs at 100 Hz on every world).
    """

    def __init__(
        self,
        params: QuadParams = QUAD,
        omega_rp: float = 14.0,  # rad/s, roll/pitch natural frequency
        zeta_rp: float = 0.8,
        omega_yaw: float = 4.0,  # rad/s
        zeta_yaw: float = 0.9,
    ):
        self.params = as_params(params)  # the vehicle's numbers (a VehicleKind's as a plain QuadParams)
        self.gains = (omega_rp, zeta_rp, omega_yaw, zeta_yaw)  # the attitude loop, the same for any vehicle
        J = np.asarray(params.inertia)
        self.kR = J * np.array([omega_rp**2, omega_rp**2, omega_yaw**2])  # N m / rad
        self.kW = J * np.array([2 * zeta_rp * omega_rp, 2 * zeta_rp * omega_rp, 2 * zeta_yaw * omega_yaw])  # N m s
        self.mass = params.mass
        self.max_thrust = params.max_rotor_thrust
        mix_inv_t = np.linalg.inv(mixer_matrix(params)).T  # rows: collective, tau_x, tau_y, tau_z
        # e_R = 0.5 vee(E - E^T) with E = R_d^T R, flattened row-major: e_R = E9 @ vee
        vee = np.zeros((9, 3))
        for k, (plus, minus) in enumerate(((7, 5), (2, 6), (3, 1))):
            vee[plus, k], vee[minus, k] = 0.5, -0.5
        torque_rows = mix_inv_t[1:]
        self.gain = np.concatenate(  # (14, 4), also passed to compiled callers of rotor_thrusts
            [
                mix_inv_t[:1],  # collective thrust (N)
                vee @ (-self.kR[:, None] * torque_rows),  # attitude error
                -self.kW[:, None] * torque_rows,  # body rates
                self.kW[2] * torque_rows[2:3],  # yaw-rate set-point
            ]
        )

    def describe(self) -> dict:
        """The attitude loop and its saturation rule, for provenance (the vehicle's numbers are the scene's)."""
        omega_rp, zeta_rp, omega_yaw, zeta_yaw = self.gains
        return {"type": f"{type(self).__module__}.{type(self).__qualname__}", "omega_rp": omega_rp, "zeta_rp": zeta_rp,
                "omega_yaw": omega_yaw, "zeta_yaw": zeta_yaw, "saturation": "attitude_first"}

    def for_vehicle(self, params: QuadParams) -> "Autopilot":
        """This autopilot (the same natural frequencies and damping) for a vehicle of `params`:
        itself when `params` are its own vehicle's, so its `gain` flies as it is."""
        return self if as_params(params) == self.params else Autopilot(params, *self.gains)

    def tables(self, vehicles: Sequence[QuadParams]) -> tuple[np.ndarray, np.ndarray]:
        """The compiled callers' per-vehicle tables for V vehicles of these params: gain (V, 14, 4)
        and max_thrust (V,) N, each vehicle's through its own inertia, mixer and rotor limit."""
        each = [self.for_vehicle(q) for q in vehicles]
        gain = np.ascontiguousarray(np.stack([a.gain for a in each]), dtype=np.float64)
        return gain, np.array([float(a.max_thrust) for a in each])

    def __call__(
        self,
        rot: np.ndarray,
        omega: np.ndarray,
        rot_des: np.ndarray,
        yaw_rate_des: np.ndarray,
        thrust_acc: np.ndarray,
        mass: np.ndarray | float | None = None,
    ) -> np.ndarray:
        """Rotor thrust commands (..., 4) N in [0, max_rotor_thrust], attitude first (module doc).

        rot, rot_des: (..., 3, 3) body-to-world; omega: (..., 3) rad/s body frame;
        yaw_rate_des: (...,) rad/s; thrust_acc: (...,) m/s^2 collective thrust / mass.
        mass: the vehicle mass the controller believes in (kg), default the nominal one.
        """
        batch = thrust_acc.shape
        if not (isinstance(mass, np.ndarray) and mass.shape == batch):  # the loop passes a ready (W, V) array
            mass = np.broadcast_to(np.asarray(self.mass if mass is None else mass, dtype=float), batch)
        out = _autopilot_kernel(
            rot.reshape(-1, 3, 3), omega.reshape(-1, 3), rot_des.reshape(-1, 3, 3), yaw_rate_des.reshape(-1),
            thrust_acc.reshape(-1), mass.reshape(-1), self.gain, self.max_thrust,
        )
        return out.reshape(batch + (4,))


@njit
def _autopilot_kernel(rot, omega, rot_des, yaw_rate_des, thrust_acc, mass, gain, max_thrust):
    """Compiled body of Autopilot.__call__ on flat (n, ...) float64 arrays; returns (n, 4) N."""
    out = np.empty((rot.shape[0], 4))
    x = np.empty(14)
    for i in range(rot.shape[0]):
        rotor_thrusts(rot[i], omega[i], rot_des[i], yaw_rate_des[i], thrust_acc[i], mass[i], gain, max_thrust, x, out[i])
    return out


@njit
def rotor_thrusts(rot, omega, rot_des, yaw_rate_des, thrust_acc, mass, gain, max_thrust, x, out):
    """One vehicle of the autopilot, for compiled callers (the simulator's fused kernel).

    rot, rot_des: (3, 3) body-to-world; omega: (3,) rad/s body frame; yaw_rate_des rad/s;
    thrust_acc m/s^2; mass kg; gain: Autopilot.gain (14, 4); max_thrust N.
    x: (14,) scratch; out: (4,) receives the rotor thrusts (N): the demands less the largest one's
    excess over max_thrust (attitude first, module doc), clipped to [0, max_thrust].
    """
    for a in range(3):
        for b in range(3):  # E = R_d^T R, flattened row-major
            x[1 + 3 * a + b] = rot_des[0, a] * rot[0, b] + rot_des[1, a] * rot[1, b] + rot_des[2, a] * rot[2, b]
    # thrust projected on the current body axis (E[8] = b3_des . b3) keeps the vertical
    # acceleration right while the attitude converges
    x[0] = mass * thrust_acc * max(x[9], 0.5)
    x[10], x[11], x[12] = omega[0], omega[1], omega[2]
    x[13] = yaw_rate_des
    highest = -np.inf
    for k in range(4):
        acc = 0.0
        for j in range(14):
            acc += x[j] * gain[j, k]
        out[k] = acc
        highest = max(highest, acc)
    excess = max(highest - max_thrust, 0.0)
    for k in range(4):
        out[k] = min(max(out[k] - excess, 0.0), max_thrust)
