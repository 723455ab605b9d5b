"""The Crazyflie firmware's position controllers, above the vehicle's autopilot: Mellinger's and the cascaded PID.

Both take the firmware's default numbers for the Crazyflie 2.1, read from
bitcraze/crazyflie-firmware at tag 2026.08 (commit 54f31e2; the files cited are the same at
2a18fc2 on master, 2026-08-21). Only the numbers and the structure they plug into are taken from
the firmware (GPL); the controllers are written from their papers and the structure described
here. Both command accelerations (collective specific thrust and a desired attitude, which the
autopilot turns into each vehicle's rotor thrusts through its own mass), so the firmware's
force gains are divided by the mass they were tuned with, `CF_MASS`, and the PID's thrust
command by its hover value, `PID_VEL_THRUST_BASE`: the firmware's closed loop, the same for any
vehicle kind (`controllers.registry`).

`MellingerController`
---------------------
Mellinger & Kumar 2011 (ICRA, "Minimum snap trajectory generation and control for quadrotors"),
sec. IV: the desired force from the position and velocity errors and the reference's
acceleration, e_p = p_ref - p, e_v = v_ref - v (the signs of the firmware; the paper writes
e = p - p_ref with minus signs, the same law),

    F / m = a_ref + Kp e_p + Kd e_v + Ki int(e_p) + g e3 - f_hat,

its direction the desired body z axis, the heading the reference's yaw (x_c = [cos, sin, 0],
y_B = z_B x x_c, x_B = y_B x z_B), and the thrust F . z_B. The integral, which the paper has
not, is the firmware's (controller_mellinger.c): e_p dt summed each step and clamped to
+-i_range per axis, its anti-windup. The predicted downwash f_hat (m/s^2) is subtracted from
the specific force; `residual` and `override` act on the acceleration as the interface says.

Stated deviations: (1) the attitude loop of the paper (the SO(3) error and its moments) is
the vehicle's autopilot here (`controllers.autopilot`: Lee et al.'s attitude error too), which
receives the desired attitude and the collective thrust; the projection F . z_B onto the
current body axis is the autopilot's (it scales the thrust by z_B,des . z_B), as the
interface's state holds no attitude. (2) The desired force passes through feedback
linearisation's limits, the LQR's (a tilt of at most 35 deg, a vertical specific force of at
least 0.25 g), where the firmware has none (a downward force would turn it over). (3) It runs
at the simulator's 50 Hz, the firmware at 500 Hz (`ATTITUDE_RATE_HZ`).

`CrazyfliePID`
--------------
The structure of the firmware's position_controller_pid.c with its default numbers (below),
written as a textbook cascade, every error taken in the frame of the vehicle's heading
(x forward, y left, z up, as the firmware does):

    position PI (a P on x and y):  v_sp = clamp(Kp_pos e_p + Ki_pos int(e_p), +-1.1 m/s)
    velocity PI:                   pitch, roll = clamp(Kp_vel e_v + Ki_vel int(e_v), +-22 deg), then +-20 deg
                                   thrust = T_hover + clamp(Kp_vz e_vz + Ki_vz int(e_vz), +-T_full / 2),
                                   at least T_min and at most T_full

with e_p = p_ref - p, e_v = v_sp - v, each integrator clamped to the firmware's PID integration
limit (5000, pid.h: in practice the output limits bound these loops, as on the vehicle). The
set-point is the reference's position only: in position mode the firmware's PID takes no
velocity or acceleration feed-forward, so a moving reference is followed with a lag of about
v_ref / Kp_pos (0.2 m at 0.4 m/s); that is what a lab flying it sees.

The firmware's thrust is a 16-bit command whose hover value is PID_VEL_THRUST_BASE; here it is
collective specific thrust with hover exactly g (thrust command / 36000 x g), so at the
reference with no error the command is gravity compensation exactly; its floor is
20000 / 36000 g and its ceiling the vehicle's full thrust (thrust_to_weight g, the firmware's
UINT16_MAX; none without a vehicle kind: the autopilot saturates each vehicle's rotors). As in
the firmware, the thrust is not divided by the tilt's cosine.

Downwash compensation: the pitch, roll and thrust are an acceleration a = T R(yaw, pitch, roll) e3
- g e3; the predicted downwash f_hat is subtracted from it, `residual` and `override` act on it,
and feedback linearisation (the LQR's limits, 35 deg and 0.25 g) gives the autopilot its
thrust and attitude; without compensation that returns the PID's own thrust and tilt. Stated
deviations: the firmware's attitude PIDs are the autopilot here, and the loop runs at the
simulator's 50 Hz (the firmware's at 100 Hz, `POSITION_RATE_HZ`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from controllers.compiled import finish_one
from controllers.lab_common import LabController, PerWorldState, number_in, positive, three
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.params import GRAVITY

__all__ = ["FIRMWARE", "CF_MASS", "MellingerGains", "MellingerController", "PIDGains", "CrazyfliePID"]

FIRMWARE = "bitcraze/crazyflie-firmware 2026.08 (commit 54f31e2)"

# src/platform/interface/platform_defaults_cf2.h: CF_MASS of a Crazyflie 2.1 without the thrust upgrade
# kit (0.0325 kg with it); controller_mellinger.c's `mass`, with which its force gains are tuned.
CF_MASS = 0.029  # kg
# src/modules/interface/stabilizer_types.h: the rates the firmware runs them at (here: the simulator's 50 Hz)
POSITION_RATE_HZ = 100  # POSITION_RATE, position_controller_pid.c
ATTITUDE_RATE_HZ = 500  # ATTITUDE_RATE, controller_mellinger.c (position and attitude alike)

# src/modules/src/controller/controller_mellinger.c, the defaults of `g_self`: force gains on the
# position error (ref - state), its rate and its integral, and the integral's clamp.
MELLINGER_KP_XY = 0.4  # N/m, kp_xy
MELLINGER_KD_XY = 0.2  # N s/m, kd_xy
MELLINGER_KI_XY = 0.05  # N/(m s), ki_xy
MELLINGER_I_RANGE_XY = 2.0  # m s, i_range_xy
MELLINGER_KP_Z = 1.25  # N/m, kp_z
MELLINGER_KD_Z = 0.4  # N s/m, kd_z
MELLINGER_KI_Z = 0.05  # N/(m s), ki_z
MELLINGER_I_RANGE_Z = 0.4  # m s, i_range_z

# src/modules/src/controller/position_controller_pid.c with the defaults of
# src/platform/interface/platform_defaults_cf2.h (x, y, z): position PID -> velocity set-point,
# velocity PID -> pitch/roll (deg) and thrust. Every kd and kff is 0 there (so is the D term's
# 20 Hz filter: nothing to filter).
PID_POS_KP = (2.0, 2.0, 2.0)  # 1/s, PID_POS_{X,Y,Z}_KP
PID_POS_KI = (0.0, 0.0, 0.5)  # 1/s^2, PID_POS_{X,Y,Z}_KI
PID_POS_VEL_MAX = (1.0, 1.0, 1.0)  # m/s, PID_POS_VEL_{X,Y,Z}_MAX (z: at least 0.5, position_controller_pid.c)
PID_VEL_MAX_OVERHEAD = 1.1  # -, velMaxOverhead: the position PIDs' output limit is the maximum times this
PID_VEL_KP = (25.0, 25.0, 25.0)  # PID_VEL_{X,Y,Z}_KP: deg per m/s (x, y); thrust / PID_THRUST_SCALE per m/s (z)
PID_VEL_KI = (1.0, 1.0, 15.0)  # PID_VEL_{X,Y,Z}_KI: the same per m (the integral of the velocity error)
PID_VEL_RP_MAX_DEG = 20.0  # deg, PID_VEL_ROLL_MAX and PID_VEL_PITCH_MAX: roll and pitch are clamped to this
PID_RP_LIMIT_OVERHEAD = 1.1  # -, rpLimitOverhead: the velocity PIDs' output limit is the maximum times this
PID_THRUST_SCALE = 1000.0  # thrust per unit of the z velocity PID's output, thrustScale
PID_VEL_THRUST_BASE = 36000.0  # PID_VEL_THRUST_BASE: "approximate throttle needed when in perfect hover"
PID_VEL_THRUST_MIN = 20000.0  # PID_VEL_THRUST_MIN: the least thrust the PID commands
PID_THRUST_MAX = 65535.0  # UINT16_MAX: the thrust command's full scale; the z PID's output limit is half of it
# src/utils/interface/pid.h: DEFAULT_PID_INTEGRATION_LIMIT, the integrators' clamp (no position or velocity
# PID sets its own: pidSetIntegralLimit is called for the attitude PIDs only)
PID_INTEGRATION_LIMIT = 5000.0


def _gains(gains: Any, kind: type) -> Any:
    """`gains` when of `kind` (None: `kind.firmware()`); ConfigError naming what is taken otherwise."""
    if gains is None:
        return kind.firmware()
    if not isinstance(gains, kind):
        raise ConfigError(f"gains: expected a {kind.__name__} (or None: the firmware's), got {type(gains).__name__}")
    return gains


# ----------------------------------------------------------------------------- Mellinger


@dataclass(frozen=True)
class MellingerGains:
    """Per axis (x, y, z), in acceleration units: kp 1/s^2, kd 1/s, ki 1/s^3; i_range m s, the integral's clamp."""

    kp: tuple[float, float, float]
    kd: tuple[float, float, float]
    ki: tuple[float, float, float]
    i_range: tuple[float, float, float]

    def __post_init__(self) -> None:
        for name in ("kp", "kd", "ki", "i_range"):
            object.__setattr__(self, name, three(f"MellingerGains.{name}", getattr(self, name)))

    @classmethod
    def firmware(cls) -> "MellingerGains":
        """The Crazyflie firmware's defaults (controller_mellinger.c), force gains over its CF_MASS."""
        m = CF_MASS  # N per unit of error -> m/s^2 per unit
        return cls(kp=(MELLINGER_KP_XY / m, MELLINGER_KP_XY / m, MELLINGER_KP_Z / m),
                   kd=(MELLINGER_KD_XY / m, MELLINGER_KD_XY / m, MELLINGER_KD_Z / m),
                   ki=(MELLINGER_KI_XY / m, MELLINGER_KI_XY / m, MELLINGER_KI_Z / m),
                   i_range=(MELLINGER_I_RANGE_XY, MELLINGER_I_RANGE_XY, MELLINGER_I_RANGE_Z))


class MellingerController(LabController):
    """Mellinger & Kumar's position law with the firmware's integral (module doc), batched over (W, V).

    gains: `MellingerGains` (default: the firmware's); dt, max_tilt_deg, min_thrust_g: see
    `LabController`. State: the integral of the position error (W, V, 3) m s, cleared by `reset(worlds)`.
    """

    observer_bandwidth = 2.0  # rad/s, as chosen for it (results/observer_bandwidth.json; see FeedbackLinearisedLQR)

    def __init__(self, gains: MellingerGains | None = None, **limits: Any):
        super().__init__(**limits)
        self.gains = _gains(gains, MellingerGains)
        self._params = np.array([*(x for k in ("kp", "kd", "ki", "i_range") for x in getattr(self.gains, k)), self.dt,
                                 self._tan_tilt, self._min_vertical], dtype=np.float64)  # as _mellinger_step reads them
        self._state = PerWorldState(integral=(3,))

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), **asdict(self.gains), "source": f"{FIRMWARE}, controller_mellinger.c "
                f"(force gains / CF_MASS {CF_MASS} kg); Mellinger & Kumar 2011"}

@njit
def _mellinger_step(pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override,
                    use_residual, use_override, lookahead, state, params, acc_out, yaw_rate_out, thrust_out, rot_out):
    """The array form (`controllers.compiled`): params (kp, kd, ki, i_range (3 each), dt, tan_tilt, min_vertical),
    state (W, V, 3) the integral."""
    _mellinger_kernel(pos, vel, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override,
                      use_residual, use_override, params[0:3], params[3:6], params[6:9], params[9:12], params[12],
                      lookahead, params[13], params[14], state, acc_out, yaw_rate_out, thrust_out, rot_out)


@njit
def _mellinger_kernel(pos, vel, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override,
                      use_residual, use_override, kp, kd, ki, i_range, dt, lookahead, tan_tilt, min_vertical, integral,
                      acc_out, yaw_rate_out, thrust_out, rot_out):
    """One step on (W, V, ...) arrays: the integral advanced and clamped (the firmware integrates before
    it uses the integral), the acceleration command, then `finish_one`."""
    W, V = pos.shape[0], pos.shape[1]
    for w in range(W):
        for i in range(V):
            for k in range(3):
                e_p = ref_pos[w, i, k] - pos[w, i, k]
                e_v = ref_vel[w, i, k] - vel[w, i, k]
                s = min(max(integral[w, i, k] + e_p * dt, -i_range[k]), i_range[k])
                integral[w, i, k] = s
                acc_out[w, i, k] = ref_acc[w, i, k] + kp[k] * e_p + kd[k] * e_v + ki[k] * s - f_hat[w, i, k]
            yaw_rate_out[w, i] = ref_yaw_rate[w, i]
            yaw_des = ref_yaw[w, i] + ref_yaw_rate[w, i] * lookahead
            thrust_out[w, i] = finish_one(acc_out, w, i, residual, override, use_residual, use_override, yaw_des,
                                          tan_tilt, min_vertical, rot_out)


# ----------------------------------------------------------------------------- the cascaded PID


@dataclass(frozen=True)
class PIDGains:
    """The cascade's gains and limits per axis (x, y, z of the heading frame), in SI units.

    pos_kp 1/s, pos_ki 1/s^2, vel_max m/s (the position loop's output limit); vel_kp, vel_ki:
    rad per m/s and per m on x, y (tilt), m/s^2 per m/s and per m on z (specific thrust);
    tilt_limit rad (the velocity PIDs' output limit) and tilt_max rad (the clamp after it);
    thrust_range m/s^2 (the z PID's output limit about hover); thrust_min_g, g;
    i_limit: every integrator's clamp (m s for position, m for velocity).
    """

    pos_kp: tuple[float, float, float]
    pos_ki: tuple[float, float, float]
    vel_max: tuple[float, float, float]
    vel_kp: tuple[float, float, float]
    vel_ki: tuple[float, float, float]
    tilt_limit: float
    tilt_max: float
    thrust_range: float
    thrust_min_g: float
    i_limit: float

    def __post_init__(self) -> None:
        for name in ("pos_kp", "pos_ki", "vel_max", "vel_kp", "vel_ki"):
            object.__setattr__(self, name, three(f"PIDGains.{name}", getattr(self, name)))
        for name in ("tilt_limit", "tilt_max"):  # a tilt of 90 deg or more has no thrust direction to hold height
            object.__setattr__(self, name, number_in(f"PIDGains.{name}", getattr(self, name), 0.0, math.pi / 2, "rad"))
        for name in ("thrust_range", "i_limit"):
            object.__setattr__(self, name, positive(f"PIDGains.{name}", getattr(self, name)))
        object.__setattr__(self, "thrust_min_g",
                           number_in("PIDGains.thrust_min_g", self.thrust_min_g, 0.0, 1.0, "g", low_closed=True))

    @classmethod
    def firmware(cls) -> "PIDGains":
        """The firmware's defaults (module doc): tilt in radians, thrust in units of its hover command x g."""
        deg = math.pi / 180.0
        per_hover = PID_THRUST_SCALE / PID_VEL_THRUST_BASE * GRAVITY  # m/s^2 per unit of the z PID's output
        return cls(
            pos_kp=PID_POS_KP, pos_ki=PID_POS_KI,
            vel_max=tuple(max(v, 0.5 if k == 2 else 0.0) * PID_VEL_MAX_OVERHEAD for k, v in enumerate(PID_POS_VEL_MAX)),
            vel_kp=(PID_VEL_KP[0] * deg, PID_VEL_KP[1] * deg, PID_VEL_KP[2] * per_hover),
            vel_ki=(PID_VEL_KI[0] * deg, PID_VEL_KI[1] * deg, PID_VEL_KI[2] * per_hover),
            tilt_limit=PID_VEL_RP_MAX_DEG * PID_RP_LIMIT_OVERHEAD * deg, tilt_max=PID_VEL_RP_MAX_DEG * deg,
            thrust_range=PID_THRUST_MAX / 2.0 / PID_VEL_THRUST_BASE * GRAVITY,
            thrust_min_g=PID_VEL_THRUST_MIN / PID_VEL_THRUST_BASE, i_limit=PID_INTEGRATION_LIMIT,
        )


class CrazyfliePID(LabController):
    """The firmware's cascaded PID (module doc), batched over (W, V).

    gains: `PIDGains` (default: the firmware's); thrust_max_g: the thrust ceiling in g
    (None: none, the autopilot's rotor limits); dt, max_tilt_deg, min_thrust_g: see `LabController`.
    State: the position and velocity integrators (W, V, 3), cleared by `reset(worlds)`.
    """

    observer_bandwidth = 1.0  # rad/s, as chosen for it (results/observer_bandwidth.json; see FeedbackLinearisedLQR)

    def __init__(self, gains: PIDGains | None = None, thrust_max_g: float | None = None, **limits: Any):
        super().__init__(**limits)
        self.gains = _gains(gains, PIDGains)
        # above hover (1 g), or the PID could not hold height
        self.thrust_max_g = None if thrust_max_g is None else number_in("thrust_max_g", thrust_max_g, 1.0, math.inf, "g")
        g = self.gains
        self._params = np.array([*g.pos_kp, *g.pos_ki, *g.vel_max, *g.vel_kp, *g.vel_ki, g.tilt_limit, g.tilt_max,
                                 g.thrust_range, g.thrust_min_g * GRAVITY,
                                 np.inf if thrust_max_g is None else self.thrust_max_g * GRAVITY, g.i_limit, self.dt,
                                 self._tan_tilt, self._min_vertical], dtype=np.float64)  # as _pid_step reads them
        self._state = PerWorldState(pos_integral=(3,), vel_integral=(3,))

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), **asdict(self.gains), "thrust_max_g": self.thrust_max_g,
                "source": f"{FIRMWARE}, position_controller_pid.c and platform_defaults_cf2.h "
                          f"(tilt in rad, thrust x g / PID_VEL_THRUST_BASE)"}

@njit
def _pid_step(pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual,
              use_override, lookahead, state, params, acc_out, yaw_rate_out, thrust_out, rot_out):
    """The array form (`controllers.compiled`): params (pos_kp, pos_ki, vel_max, vel_kp, vel_ki (3 each),
    tilt_limit, tilt_max, thrust_range, thrust_min, thrust_max, i_limit, dt, tan_tilt, min_vertical), state
    (W, V, 6) the position and velocity integrators."""
    _pid_kernel(pos, vel, yaw, ref_pos, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual, use_override,
                params[0:3], params[3:6], params[6:9], params[9:12], params[12:15], params[15], params[16], params[17],
                params[18], params[19], params[20], params[21], lookahead, params[22], params[23], state[:, :, 0:3],
                state[:, :, 3:6], acc_out, yaw_rate_out, thrust_out, rot_out)


@njit
def _pi(integral, w, i, k, error, kp, ki, dt, i_limit, limit):
    """One PI of the firmware's pid.c: the integral advanced and clamped first, the output clamped."""
    s = min(max(integral[w, i, k] + error * dt, -i_limit), i_limit)
    integral[w, i, k] = s
    return min(max(kp * error + ki * s, -limit), limit)


@njit
def _pid_kernel(pos, vel, yaw, ref_pos, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual, use_override,
                pos_kp, pos_ki, vel_max, vel_kp, vel_ki, tilt_limit, tilt_max, thrust_range, thrust_min, thrust_max,
                i_limit, dt, lookahead, tan_tilt, min_vertical, pos_integral, vel_integral,
                acc_out, yaw_rate_out, thrust_out, rot_out):
    """One step of the cascade on (W, V, ...) arrays (module doc), then `finish_one`."""
    W, V = pos.shape[0], pos.shape[1]
    err = np.empty(3)
    v_body = np.empty(3)
    cmd = np.empty(3)
    for w in range(W):
        for i in range(V):
            c, s = np.cos(yaw[w, i]), np.sin(yaw[w, i])  # the heading frame: world x, y rotated by the yaw
            ex, ey = ref_pos[w, i, 0] - pos[w, i, 0], ref_pos[w, i, 1] - pos[w, i, 1]
            err[0], err[1], err[2] = c * ex + s * ey, -s * ex + c * ey, ref_pos[w, i, 2] - pos[w, i, 2]
            v_body[0] = c * vel[w, i, 0] + s * vel[w, i, 1]
            v_body[1] = -s * vel[w, i, 0] + c * vel[w, i, 1]
            v_body[2] = vel[w, i, 2]
            for k in range(3):
                v_sp = _pi(pos_integral, w, i, k, err[k], pos_kp[k], pos_ki[k], dt, i_limit, vel_max[k])
                limit = tilt_limit if k < 2 else thrust_range
                cmd[k] = _pi(vel_integral, w, i, k, v_sp - v_body[k], vel_kp[k], vel_ki[k], dt, i_limit, limit)
            tilt_x = min(max(cmd[0], -tilt_max), tilt_max)  # pitch: towards +x of the heading frame
            tilt_y = min(max(cmd[1], -tilt_max), tilt_max)  # roll: towards +y
            thrust = min(max(GRAVITY + cmd[2], thrust_min), thrust_max)
            # thrust direction R_z(yaw) R_y(tilt_x) R_x(-tilt_y) e3, in the world frame
            bx, by, bz = np.cos(tilt_y) * np.sin(tilt_x), np.sin(tilt_y), np.cos(tilt_y) * np.cos(tilt_x)
            acc_out[w, i, 0] = thrust * (c * bx - s * by) - f_hat[w, i, 0]
            acc_out[w, i, 1] = thrust * (s * bx + c * by) - f_hat[w, i, 1]
            acc_out[w, i, 2] = thrust * bz - GRAVITY - f_hat[w, i, 2]
            yaw_rate_out[w, i] = ref_yaw_rate[w, i]
            yaw_des = ref_yaw[w, i] + ref_yaw_rate[w, i] * lookahead
            thrust_out[w, i] = finish_one(acc_out, w, i, residual, override, use_residual, use_override, yaw_des,
                                          tan_tilt, min_vertical, rot_out)


MellingerController.step_function = _mellinger_step
CrazyfliePID.step_function = _pid_step
