"""The multi-rate stepping loop: physics, autopilot, field, wind, motion capture, controller, predictor.

Rates (downwash_core.params.Rates): physics 500 Hz; autopilot, downwash field, wind and motion
capture on the 100 Hz autopilot grid; the LQR at 50 Hz; the predictor at 45 Hz,
evaluated at the first autopilot tick after each 1/45 s and held in between.

Everything is batched over worlds W and vehicles V. Each world draws its noise
(motion capture, turbulence) from its own generator, and its wind gusts from a second
one of its own (`default_rng([seed, WIND_STREAM])`), so a world's flight does not
depend on which other worlds share its batch: the batched loop equals a loop of
single flights bit for bit, which a test checks; and a flight without wind draws
exactly the numbers it drew before wind existed.

The loop is assembled from components, each injected and each with its config in
its own module: the outer-loop `controller` (`controllers.lqr.FeedbackLinearisedLQR`),
the `autopilot` (`controllers.autopilot.Autopilot`), the `turbulence`
(`sim.turbulence.OUTurbulence`), the downwash `field` (`sim.field.DownwashField` or
any object with its call signature), how several wakes combine (`aggregation`,
`sim.aggregation`), the ambient `wind` (`sim.wind.DrydenWind`) and the `predictor`
(`sim.predictor`).

Ambient wind (`wind=DrydenWind(...)`; None or an `off` wind leave the loop and its
logs bit for bit as without it). The air velocity is u_air = mean + gust, ONE gust
state (3, 2) per world, shared by all its vehicles: the Dryden scale lengths (23 m
longitudinal and lateral, 3 m vertical at this testbed's altitudes, clamped at 10 ft;
50-200 m higher up) are far larger than the ~1 m between vehicles, so the gusts they
feel are one and the same; independent gusts per vehicle would be unphysical. The
state starts from the stationary distribution and advances on the autopilot grid by
the exact sampled recursion (`sim.wind`), its time scales set by the airspeed of the
world's mean vehicle velocity. The wind acts on every vehicle through the airframe
drag law, `sim.wind.drag_acceleration` with `sim.wind.AIRFRAME` (added to the external
force), and convects the wakes: the field is evaluated with velocities relative to
the air, v - u_air, so a wake's axis and skew follow its leader's airspeed, not its
ground speed. For a uniform wind this is exact Galilean invariance (the wake is a
property of the air mass: a leader hovering in a wind w sheds the wake of a leader
flying at -w through still air, and the follower's velocity relative to that air
sets its response). The oracle predictor gets the same air-relative truth; learned
predictors see the estimated ground velocities, what a lab measures. Logged rows
then hold `wind` (the air velocity at each vehicle, m/s) and `wind_acc` (the drag).

Two paths, one behaviour. The readable path runs each autopilot tick as compiled
passes around the pluggable Python calls (predictor, field, reference): `_sense_kernel`
(state, motion capture, Kalman update), `_wind_sense_kernel` / `_wind_advance_kernel`
(air velocity, drag, gusts), `_actuate_kernel` (field and turbulence into
`xfrc_applied`, autopilot into `ctrl`, Kalman prediction, clocks); the 50 Hz command is
one more (the controller's `command_setpoint`). The math stays in its module
(`controllers.autopilot.rotor_thrusts`, `sim.estimation.kf_update` / `kf_predict`,
`sim.turbulence.OUTurbulence`, `sim.wind`); tests check the passes against the readable
components. The fast path (`fast=True`, the default, taken when every component has a
compiled form: `DownwashField` with scalar constants and linear aggregation, a
`FeedbackLinearisedLQR`, a zero, oracle or compiled predictor (`sim.predictor.CompiledPredictor`),
or a `PerWorldPredictor` of those)
runs a whole controller tick as ONE compiled call, the fused kernel (`_make_fused_kernel`; one
variant with and one without the wind passes), which calls the
same passes, the field kernel and the predictor's C function, and steps the physics
itself: `mj_step` on a single world's MjData (`sim.physics.mj_step_address`), or, for a
`mujoco.batch.Batch`, each world's state row loaded into a scratch MjData, stepped and
saved, as the batch does it (`_BatchPhysics.native_step`), with the worlds split into
chunks that the caller's thread and its helper threads take from one atomic counter, all
inside compiled code (`sim.fork_join`: no Python lock per tick or chunk). A batch whose worlds
have models of their own (`set_body_mass`) is stepped by the batch between one call
per autopilot tick. Per call the kernel gets one table of buffer addresses (`_Plan`)
instead of some hundred arguments (numba checks each argument's type on every call,
~0.15 us each). Its rows are `Row`s, views of one flat array. Limits of the fused
path: a MuJoCo fatal error (`mju_error`, not a warning) inside it may end the process
instead of raising (on the readable path a batch marks that world diverged); and
the plan must be rebuilt when a component is replaced, which assigning the attribute
does. tests/test_fast_path.py checks that both paths fly bit-identical logs.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Iterator, NamedTuple, Sequence

import numpy as np
from llvmlite import ir
from numba import carray, types
from numba.core.extending import intrinsic

from controllers.autopilot import Autopilot, rotor_thrusts
from controllers.lqr import ControllerState, FeedbackLinearisedLQR, Setpoint, _command_setpoint_kernel
from downwash_core.errors import ConcurrentUseError, ConfigError
from downwash_core.geometry import perturb_quat_into, quat_to_rot
from downwash_core.jit import njit
from downwash_core.params import QUAD, RATES, QuadParams, Rates
from downwash_core.state import VehicleStates
from downwash_core.status import Status
from sim import fork_join
from sim.aggregation import LinearSuperposition, wake_field
from sim.estimation import MocapConfig, MocapKalmanFilter, kf_predict, kf_update
from sim.field import DownwashField, _pairwise_kernel, check_field
from sim.physics import _FATAL_0, _FATAL_1, _FATAL_2, _SerialPhysics, check_world_memory, make_physics
from sim.predictor import CompiledPredictor, OraclePredictor, PerWorldPredictor, Predictor, ZeroPredictor
from sim.scene import Scene
from sim.turbulence import OUTurbulence
from sim.wind import AIRFRAME, DrydenWind, coefficients_into, drag_gain_speed, gust_into, gust_step_into

__all__ = ["SimConfig", "Simulator", "Row", "WIND_STREAM"]

# Status codes as plain ints for the compiled status pass (numba freezes globals).
_OK, _DIVERGED, _GROUND, _VEHICLE = (int(s) for s in (Status.OK, Status.DIVERGED, Status.GROUND, Status.VEHICLE))
WIND_STREAM = 0x57494E44  # "WIND": world w's gusts come from default_rng([seed_w, WIND_STREAM])


@dataclass(frozen=True)
class SimConfig:
    """The vehicle, the rates, the motion capture and the failure checks of a flight.

    The controller, autopilot, turbulence, field, wind and predictor are components of
    the `Simulator`, each with its own settings.
    """

    rates: Rates = field(default_factory=lambda: RATES)
    quad: QuadParams = field(default_factory=lambda: QUAD)
    mocap: MocapConfig = field(default_factory=MocapConfig)
    ground_clearance: float = 0.03  # m, a vehicle centre below this height has hit the ground
    collision_radius_xy: float = 0.26  # m, vehicles closer than this laterally ...
    collision_radius_z: float = 0.08  # m, ... and vertically (ellipsoid) have collided
    max_distance: float = 100.0  # m, beyond this from the origin the flight has diverged
    noise_block: int = 256  # autopilot ticks of noise drawn per generator call

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class _Sensed(NamedTuple):
    """What one autopilot tick senses and applies, batched (W, V, ...); the first tick of a
    controller period writes into fresh arrays (they become the log row), later ones reuse."""

    kin: np.ndarray  # (5, W, V, 3): true position m, true velocity m/s, mocap position m, KF position m, KF velocity m/s
    quat: np.ndarray  # (W, V, 4) true attitude (w, x, y, z)
    rot: np.ndarray  # (W, V, 3, 3) true attitude, body to world
    quat_est: np.ndarray  # (W, V, 4) motion-capture attitude
    rot_est: np.ndarray  # (W, V, 3, 3) motion-capture attitude, body to world
    yaw: np.ndarray  # (W, V) rad, motion-capture heading
    applied: np.ndarray  # (W, V, 3) m/s^2, the field applied (mean + turbulence)

    @classmethod
    def empty(cls, W: int, V: int) -> "_Sensed":
        return cls(np.empty((5, W, V, 3)), np.empty((W, V, 4)), np.empty((W, V, 3, 3)), np.empty((W, V, 4)),
                   np.empty((W, V, 3, 3)), np.empty((W, V)), np.empty((W, V, 3)))


# ----------------------------------------------------------------------------- log rows

# The row of a controller tick: name -> trailing shape after (W,), in the order of the
# readable path's dicts. "wind" and "wind_acc" only when the wind is on.
_ROW_FIELDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("t", ()), ("pos", ("V", 3)), ("vel", ("V", 3)), ("quat", ("V", 4)), ("pos_est", ("V", 3)),
    ("vel_est", ("V", 3)), ("quat_est", ("V", 4)), ("yaw_est", ("V",)), ("mocap_pos", ("V", 3)),
    ("ref_pos", ("V", 3)), ("ref_vel", ("V", 3)), ("ref_acc", ("V", 3)), ("u_cmd", ("V", 3)), ("f_hat", ("V", 3)),
    ("field_mean", ("V", 3)), ("field_applied", ("V", 3)),
)
_WIND_ROW_FIELDS = (("wind", ("V", 3)), ("wind_acc", ("V", 3)))
# Storage order in the flat row: the five (W, V, 3) kinematic arrays of `_Sensed.kin`
# first and contiguous (the sense pass writes them as one (5, W, V, 3) block).
_ROW_STORAGE = ("pos", "vel", "mocap_pos", "pos_est", "vel_est", "t", "quat", "quat_est", "yaw_est", "field_applied",
                "ref_pos", "ref_vel", "ref_acc", "u_cmd", "f_hat", "field_mean", "wind", "wind_acc")


def _row_layout(W: int, V: int, wind: bool) -> tuple[dict[str, tuple[int, tuple[int, ...]]], int]:
    """({name: (offset, shape)}, size) of a flat row; shapes (W, ...) in the order of `_ROW_FIELDS`."""
    fields = dict(_ROW_FIELDS + (_WIND_ROW_FIELDS if wind else ()))
    shapes = {name: (W,) + tuple(V if d == "V" else d for d in trail) for name, trail in fields.items()}
    offsets, size = {}, 0
    for name in _ROW_STORAGE:
        if name in shapes:
            offsets[name] = size
            size += int(np.prod(shapes[name]))
    return {name: (offsets[name], shapes[name]) for name in fields}, size


class Row(Mapping):
    """One controller tick's log row (the fast path's): name -> (W, ...) float64 array.

    A read-only mapping with the keys of the readable path's dict rows; its arrays are
    views of one flat array written once by the tick and never again (fresh each tick).
    `flat` and `layout` ({name: (offset, shape)}) let `sim.flight` stack many rows at once.
    """

    __slots__ = ("flat", "layout")

    def __init__(self, flat: np.ndarray, layout: dict[str, tuple[int, tuple[int, ...]]]):
        self.flat = flat
        self.layout = layout

    def __getitem__(self, name: str) -> np.ndarray:
        offset, shape = self.layout[name]
        return self.flat[offset:offset + math.prod(shape)].reshape(shape)

    def __iter__(self) -> Iterator[str]:
        return iter(self.layout)

    def __len__(self) -> int:
        return len(self.layout)

    def __repr__(self) -> str:
        return f"Row({', '.join(self.layout)})"


# columns of Simulator._layout (V, 7), the per-vehicle address table of the kernels
_QPOS, _QVEL, _BODY, _ACT = 0, 1, 2, 3  # free joint in qpos, in qvel, body id, 4 actuator ids

# The readable path's per-autopilot-tick passes: as NumPy on these small arrays,
# per-call overhead cost several times MuJoCo's own step.


@njit
def _sense_kernel(
    qpos, qvel, layout, noise, cursor, sigma_p, sigma_att, gain_p, gain_v,
    pos_est, vel_est, t, next_prediction, due, kin, quat, rot, quat_est, rot_est, yaw_meas,
):
    """Read the true state, take the motion-capture sample and apply the Kalman update.

    The arguments before `kin` are the simulator's persistent buffers and constants,
    bound once (`Simulator._sense_args`); the last six are fresh each tick.

    qpos (W, nq), qvel (W, nv): live MuJoCo state; layout (V, 7): see Simulator._layout.
    noise (W, block, V, 9) standard normals read at each world's `cursor`: [0:3] mocap
    position, [3:6] mocap attitude (body-frame rotation vector), [6:9] turbulence.
    pos_est, vel_est (W, V, 3): the Kalman prior, updated in place to the posterior.
    Writes kin (5, W, V, 3) [true position m, true velocity m/s (world), mocap position m,
    posterior position m, posterior velocity m/s], quat (W, V, 4) (w, x, y, z) and
    rot (W, V, 3, 3) body to world (true), quat_est and rot_est (the mocap attitude,
    `downwash_core.geometry.perturb_quat` of the truth by sigma_att * noise), yaw_meas (W, V) rad
    (its heading), and due (W,) bool: the predictor is due (t >= next_prediction, 1 ns
    slack). Returns how many worlds are due.
    """
    W, V = pos_est.shape[0], pos_est.shape[1]
    n_due = 0
    for w in range(W):
        c = cursor[w]
        for i in range(V):
            a, b = layout[i, _QPOS], layout[i, _QVEL]
            for k in range(4):
                quat[w, i, k] = qpos[w, a + 3 + k]
            quat_to_rot(qpos[w, a + 3], qpos[w, a + 4], qpos[w, a + 5], qpos[w, a + 6], rot[w, i])
            q = quat_est[w, i]
            perturb_quat_into(
                quat[w, i, 0], quat[w, i, 1], quat[w, i, 2], quat[w, i, 3],
                sigma_att * noise[w, c, i, 3], sigma_att * noise[w, c, i, 4], sigma_att * noise[w, c, i, 5], q,
            )
            yaw_meas[w, i] = quat_to_rot(q[0], q[1], q[2], q[3], rot_est[w, i])
            for k in range(3):
                p = qpos[w, a + k]
                m = p + sigma_p * noise[w, c, i, k]
                kin[0, w, i, k] = p
                kin[1, w, i, k] = qvel[w, b + k]
                kin[2, w, i, k] = m
                pe, ve = kf_update(pos_est[w, i, k], vel_est[w, i, k], m, gain_p, gain_v)
                pos_est[w, i, k] = kin[3, w, i, k] = pe
                vel_est[w, i, k] = kin[4, w, i, k] = ve
        due[w] = t[w] >= next_prediction[w] - 1e-9
        n_due += due[w]
    return n_due


@njit
def _true_states_kernel(qpos, qvel, layout, pos, vel, rot):
    """pos, vel (W, V, 3) and rot (W, V, 3, 3) from qpos (W, nq), qvel (W, nv) at the addresses of
    layout (V, 7); the attitude as `downwash_core.geometry.quat_to_mat_fast` (no normalisation)."""
    for w in range(pos.shape[0]):
        for i in range(pos.shape[1]):
            a, b = layout[i, _QPOS], layout[i, _QVEL]
            for k in range(3):
                pos[w, i, k] = qpos[w, a + k]
                vel[w, i, k] = qvel[w, b + k]
            quat_to_rot(qpos[w, a + 3], qpos[w, a + 4], qpos[w, a + 5], qpos[w, a + 6], rot[w, i])


@njit
def _hold_kernel(f_hat, pred, due, next_prediction, period):
    """Take the new prediction (W, V, 3) m/s^2 where due (W,) and schedule the next (s), in place."""
    for w in range(f_hat.shape[0]):
        if due[w]:
            for i in range(f_hat.shape[1]):
                for k in range(3):
                    f_hat[w, i, k] = pred[w, i, k]
            next_prediction[w] = next_prediction[w] + period


@njit
def _actuate_kernel(
    field_on, noise, cursor, turb, decay, diffusion, intensity, mass, xfrc, layout,
    qvel, rot_des, yaw_rate_des, thrust_acc, mass_believed, ap_gain, max_thrust, ctrl,
    pos_est, vel_est, dt, t, active,
    mean, applied, rot, acc_cmd,
):
    """Apply the field, run the autopilot and the Kalman prediction, advance the clocks.

    mean (W, V, 3) m/s^2: mean field, zeroed in place where field_on (W,) is False.
    turb (W, V, 3): Ornstein-Uhlenbeck state, advanced in place with noise[w, cursor[w], :, 6:9]:
    turb = decay turb + diffusion xi; applied = mean + intensity |mean| turb (written to
    applied (W, V, 3) m/s^2, so the turbulence is zero outside the wake and scales with it),
    and mass * applied (N, world frame) into xfrc (W, nbody, 6) at each vehicle's body.
    Autopilot (controllers.autopilot.rotor_thrusts) on rot (W, V, 3, 3), body rates from
    qvel (W, nv), set-points rot_des (W, V, 3, 3), yaw_rate_des (W, V) rad/s,
    thrust_acc (W, V) m/s^2, mass_believed (W, V) kg -> rotor thrusts (N) into ctrl (W, nu).
    Addresses from layout (V, 7), see Simulator._layout. Kalman prediction of pos_est, vel_est (W, V, 3) over dt (s) with
    acc_cmd (W, V, 3) m/s^2, in place. Then t (W,) s advances by dt where active and
    every cursor by one.

    The arguments before `mean` are the simulator's persistent buffers and constants,
    bound once (`Simulator._actuate_args`); the last four are fresh each tick.
    """
    W, V = mean.shape[0], mean.shape[1]
    x = np.empty(14)
    out = np.empty(4)
    for w in range(W):
        c = cursor[w]
        for i in range(V):
            if not field_on[w]:
                for k in range(3):
                    mean[w, i, k] = 0.0  # assigned: a field that is NaN here is off all the same
            mag = np.sqrt(mean[w, i, 0] ** 2 + mean[w, i, 1] ** 2 + mean[w, i, 2] ** 2)
            for k in range(3):
                turb[w, i, k] = decay * turb[w, i, k] + diffusion * noise[w, c, i, 6 + k]
                applied[w, i, k] = mean[w, i, k] + intensity * mag * turb[w, i, k]
                xfrc[w, layout[i, _BODY], k] = mass * applied[w, i, k]
            b = layout[i, _QVEL] + 3
            rotor_thrusts(
                rot[w, i], qvel[w, b:b + 3], rot_des[w, i], yaw_rate_des[w, i], thrust_acc[w, i],
                mass_believed[w, i], ap_gain, max_thrust, x, out,
            )
            for k in range(4):
                ctrl[w, layout[i, _ACT + k]] = out[k]
            for k in range(3):
                pos_est[w, i, k], vel_est[w, i, k] = kf_predict(pos_est[w, i, k], vel_est[w, i, k], acc_cmd[w, i, k], dt)
        if active[w]:
            t[w] = t[w] + dt
        cursor[w] += 1


@njit
def _wind_sense_kernel(state, axes, mean, gain, vel, air, vel_air, wind_acc):
    """The wind at every vehicle from each world's gust state state (W, 3, 2) m/s.

    axes (3, 3), mean (3,) m/s: `DrydenWind.kernel_constants`; gain = rho C_d A / (2 m) (1/m).
    vel (W, V, 3) m/s true velocities. Writes air (W, V, 3) m/s (mean + gust, the same at
    every vehicle of a world), vel_air = vel - air and wind_acc (W, V, 3) m/s^2, the
    drag `sim.wind.drag_acceleration(air, vel, ...)`.
    """
    W, V = vel.shape[0], vel.shape[1]
    gust = np.empty(3)
    for w in range(W):
        gust_into(state[w], axes, gust)
        for i in range(V):
            for k in range(3):
                air[w, i, k] = mean[k] + gust[k]
                vel_air[w, i, k] = vel[w, i, k] - air[w, i, k]
            rx, ry, rz = air[w, i, 0] - vel[w, i, 0], air[w, i, 1] - vel[w, i, 1], air[w, i, 2] - vel[w, i, 2]
            f = drag_gain_speed(rx, ry, rz, gain)
            wind_acc[w, i, 0], wind_acc[w, i, 1], wind_acc[w, i, 2] = f * rx, f * ry, f * rz


@njit
def _wind_advance_kernel(state, noise, cursor, vel, dt, mean, sigma, length, min_airspeed, A, B):
    """Advance each world's gust state (W, 3, 2) one autopilot tick of dt (s), in place.

    The time scales come from the airspeed |mean_i v_i - mean wind| (floored at
    min_airspeed, m/s) of the world's mean vehicle velocity, vel (W, V, 3) m/s; the draws
    are noise[w, cursor[w]] (3, 2) of the world's wind block (W, block, 3, 2). sigma (3,)
    m/s, length (3,) m: `DrydenWind.kernel_constants`; A, B (3, 2, 2) scratch.
    """
    W, V = vel.shape[0], vel.shape[1]
    for w in range(W):
        mx, my, mz = 0.0, 0.0, 0.0
        for i in range(V):
            mx, my, mz = mx + vel[w, i, 0], my + vel[w, i, 1], mz + vel[w, i, 2]
        mx, my, mz = mx / V - mean[0], my / V - mean[1], mz / V - mean[2]
        airspeed = math.hypot(math.hypot(mx, my), mz)
        coefficients_into(dt, airspeed, sigma, length, min_airspeed, A, B)
        gust_step_into(state[w], noise[w, cursor[w]], A, B)


@njit
def _wind_force_kernel(xfrc, layout, mass, wind_acc):
    """Add the wind drag mass * wind_acc (W, V, 3) m/s^2 (N, world frame) to xfrc (W, nbody, 6)."""
    for w in range(wind_acc.shape[0]):
        for i in range(wind_acc.shape[1]):
            b = layout[i, _BODY]
            for k in range(3):
                xfrc[w, b, k] = xfrc[w, b, k] + mass * wind_acc[w, i, k]


# ----------------------------------------------------------------------------- the fused tick
# Raw addresses into typed pointers, and calls of C functions by address, for the fused
# kernel. Every address comes from an array or object that the `_Plan` keeps alive.


def _pointer_intrinsic(dtype: types.Type):
    """A compiled function: an integer address -> a typed pointer (`carray` reads it as an array)."""

    @intrinsic
    def pointer(typingctx, addr):
        sig = types.CPointer(dtype)(types.intp)
        return sig, lambda context, builder, sig, args: builder.inttoptr(args[0], context.get_value_type(sig.return_type))

    return pointer


_f64p, _i64p, _i32p, _boolp = (_pointer_intrinsic(t) for t in (types.float64, types.int64, types.int32, types.boolean))


_VOIDP = ir.IntType(8).as_pointer()
_FATAL_MAX = max(_FATAL_0, _FATAL_1, _FATAL_2)


@intrinsic
def _call_mj_step(typingctx, fn, model, data):
    """mj_step(model, data) through the function address fn (`sim.physics.mj_step_address`)."""
    sig = types.void(types.intp, types.intp, types.intp)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [_VOIDP, _VOIDP])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(args[1], _VOIDP), builder.inttoptr(args[2], _VOIDP)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _call_state(typingctx, fn, model, data, state, spec):
    """mj_setState / mj_getState(model, data, state, spec) through the function address fn."""
    sig = types.void(types.intp, types.intp, types.intp, types.intp, types.int64)

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [_VOIDP, _VOIDP, _VOIDP, i32])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(a, _VOIDP) for a in args[1:4]] + [builder.trunc(args[4], i32)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _call_predictor(typingctx, fn, n_worlds, n_veh, pos, vel, rot, true_pos, true_vel, true_rot, params, iparams, out):
    """A `sim.predictor.PREDICTOR_SIGNATURE` function at address fn; the array arguments are addresses."""
    sig = types.void(types.intp, types.int64, types.int64, *(types.intp,) * 9)

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        fnty = ir.FunctionType(ir.VoidType(), [i64, i64] + [_VOIDP] * 9)
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [args[1], args[2]] + [builder.inttoptr(a, _VOIDP) for a in args[3:]])
        return context.get_dummy_value()

    return sig, codegen


# How the fused kernel's physics steps: the caller steps it (a batch with models of its
# own per world), mj_step on the single world's MjData, or each world's state row loaded
# into a scratch MjData of its thread, stepped and saved (as mujoco.batch does).
_STEP_CALLER, _STEP_SERIAL, _STEP_ROWS = 0, 1, 2

# The plan's integer table `tab` (int64): sizes, codes, addresses and row offsets, in this order.
_TAB = (
    "W", "V", "block", "n_sub", "n_physics", "stepping", "step_fn", "set_state_fn", "get_state_fn", "model",
    "data", "warnings", "warning_stride", "state", "nstate", "state_spec", "batch_warnings", "n_warnings",
    "predictor", "predictor_fn", "predictor_params", "predictor_iparams",
    "layout", "noise", "cursor", "pos_est", "vel_est", "t", "next_prediction", "due", "field_enabled", "turb",
    "rot_des", "yaw_rate_des", "thrust_acc", "mass_believed", "ap_gain", "active", "f_hat", "tick_index",
    "status_new", "kin", "quat", "rot", "quat_est", "rot_est", "yaw", "applied", "mean", "pred", "Kt",
    "field_packed", "oracle_packed", "gust", "wind_noise", "wind_mean", "wind_sigma", "wind_length", "wind_axes",
    "air", "vel_air", "wind_acc", "diverged", "pw_code", "pw_fn", "pw_params", "pw_iparams", "pw_oracle",
    "row_kin", "row_t", "row_quat", "row_quat_est", "row_yaw", "row_applied", "row_ref_pos", "row_ref_vel",
    "row_ref_acc", "row_u_cmd", "row_f_hat", "row_mean", "row_wind", "row_wind_acc",
)
(_T_W, _T_V, _T_BLOCK, _T_NSUB, _T_NPHYS, _T_STEPPING, _T_STEP_FN, _T_SET_STATE_FN, _T_GET_STATE_FN, _T_MODEL,
 _T_DATA, _T_WARNINGS, _T_WARNING_STRIDE, _T_STATE, _T_NSTATE, _T_STATE_SPEC, _T_BATCH_WARNINGS, _T_NWARNINGS,
 _T_PRED, _T_PRED_FN, _T_PRED_PARAMS, _T_PRED_IPARAMS,
 _T_LAYOUT, _T_NOISE, _T_CURSOR, _T_POS_EST, _T_VEL_EST, _T_T, _T_NEXT_PRED, _T_DUE, _T_FIELD_ON, _T_TURB,
 _T_ROT_DES, _T_YAW_RATE_DES, _T_THRUST, _T_MASS_BELIEVED, _T_AP_GAIN, _T_ACTIVE, _T_F_HAT, _T_TICK_INDEX,
 _T_STATUS_NEW, _T_KIN, _T_QUAT, _T_ROT, _T_QUAT_EST, _T_ROT_EST, _T_YAW, _T_APPLIED, _T_MEAN, _T_PRED_OUT, _T_KT,
 _T_FIELD_PACKED, _T_ORACLE_PACKED, _T_GUST, _T_WIND_NOISE, _T_WIND_MEAN, _T_WIND_SIGMA, _T_WIND_LENGTH,
 _T_WIND_AXES, _T_AIR, _T_VEL_AIR, _T_WIND_ACC, _T_DIVERGED, _T_PW_CODE, _T_PW_FN, _T_PW_PARAMS, _T_PW_IPARAMS,
 _T_PW_ORACLE,
 _T_ROW_KIN, _T_ROW_T, _T_ROW_QUAT, _T_ROW_QUAT_EST, _T_ROW_YAW, _T_ROW_APPLIED, _T_ROW_REF_POS, _T_ROW_REF_VEL,
 _T_ROW_REF_ACC, _T_ROW_U_CMD, _T_ROW_F_HAT, _T_ROW_MEAN, _T_ROW_WIND, _T_ROW_WIND_ACC) = range(len(_TAB))
# The plan's float table `fc` (float64), in this order.
_FC = (
    "sigma_p", "sigma_att", "kf_gain_p", "kf_gain_v", "ou_a", "ou_b", "intensity", "mass", "max_thrust", "dt",
    "prediction_period", "lookahead", "tan_tilt", "min_vertical", "min_airspeed", "drag_gain",
    "max_distance", "ground", "radius_xy", "radius_z",
)
(_F_SIGMA_P, _F_SIGMA_ATT, _F_KF_P, _F_KF_V, _F_OU_A, _F_OU_B, _F_INTENSITY, _F_MASS, _F_MAX_THRUST, _F_DT,
 _F_PRED_PERIOD, _F_LOOKAHEAD, _F_TAN_TILT, _F_MIN_VERTICAL, _F_MIN_AIRSPEED, _F_DRAG_GAIN,
 _F_MAX_DISTANCE, _F_GROUND, _F_RADIUS_XY, _F_RADIUS_Z) = range(len(_FC))
# predictor codes: zero, oracle (field kernel), C function, and one of these per world (`PerWorldPredictor`)
_PRED_ZERO, _PRED_ORACLE, _PRED_C, _PRED_PER_WORLD = 0, 1, 2, 3


@njit
def _copy_into(dst, src):
    """dst[...] = src for two (W, V, 3) arrays, element by element: a slice assignment from an array
    makes numba compile its shape-mismatch message (string formatting), seconds of every fresh build."""
    for w in range(dst.shape[0]):
        for i in range(dst.shape[1]):
            for k in range(dst.shape[2]):
                dst[w, i, k] = src[w, i, k]


@njit
def _row_view(row, offset, n_worlds, trailing, w0, w1):
    """Worlds w0..w1-1 of a row field: row[offset:] read as (n_worlds, trailing) float64."""
    return row[offset:offset + n_worlds * trailing].reshape((n_worlds, trailing))[w0:w1]


def _make_fused_kernel(with_wind: bool):
    """The fused kernel with or without the wind passes. `with_wind` is a constant of the closure, so
    numba prunes the branches it does not take before typing: a flight without wind never
    compiles the wind passes (seconds of every fresh build)."""

    @njit
    def _fused_kernel(tab, fc, qpos, qvel, ctrl, xfrc, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate,
                      residual, override, actions, row, sub_start, sub_stop, chunks, ctl, role):
        """Autopilot ticks sub_start..sub_stop-1 of one controller tick for the chunks of worlds this
        thread takes, as the readable path runs them.

        tab, fc: the plan's tables (`_TAB`, `_FC`); qpos, qvel, ctrl (W, n), xfrc (W, nbody, 6): the
        live physics state; ref_*: the reference at the tick's start ((W, V, 3), (W, V));
        residual, override: (W, V, 3) m/s^2 C-contiguous, as in `Simulator.tick`, each used only
        where actions (bit 0: residual, bit 1: override) says so; row: the tick's
        flat row (`_row_layout`), written by sub-tick 0; chunks (n, 4) int64: per chunk its first
        and last + 1 world, the address of this thread's scratch MjData and of its warnings
        (stepping `_STEP_ROWS`). Worlds are independent: chunks run on separate threads.
        Unless the caller steps the physics (`_STEP_CALLER`), each sub-tick also steps it,
        and once the last sub-tick has run the status pass runs too. ctl, role: see
        `sim.fork_join`: alone (SOLO) this call runs every chunk; as MAIN it publishes the
        tick, takes chunks with the helpers and joins them; as HELPER + t it serves ticks
        (from the control block: the arguments passed to it, but for the physics state, are
        placeholders of their types) until idle.
        Returns how many worlds ended (0 when the status pass did not run), or what
        `sim.fork_join` says for a helper or an unjoined caller.
        """
        helper = role >= fork_join.HELPER
        total = 0
        while True:  # a helper: once per tick it serves; the others: once
            if helper:  # the tick's arguments, as the caller published them
                code = fork_join.await_tick(ctl, role - fork_join.HELPER)
                if code != 1:
                    return code
                tab = carray(_i64p(ctl[fork_join.ARG_TAB]), (ctl[fork_join.ARG_TAB_SIZE],))
                fc = carray(_f64p(ctl[fork_join.ARG_FC]), (ctl[fork_join.ARG_FC_SIZE],))
                n_chunks = ctl[fork_join.ARG_N_CHUNKS]
                own = ctl[fork_join.ARG_CHUNKS] + (role - fork_join.HELPER + 1) * n_chunks * 4 * 8
                chunks = carray(_i64p(own), (n_chunks, 4))
                n_worlds, V = tab[_T_W], tab[_T_V]
                ref_pos = carray(_f64p(ctl[fork_join.ARG_REF_POS]), (n_worlds, V, 3))
                ref_vel = carray(_f64p(ctl[fork_join.ARG_REF_VEL]), (n_worlds, V, 3))
                ref_acc = carray(_f64p(ctl[fork_join.ARG_REF_ACC]), (n_worlds, V, 3))
                ref_yaw = carray(_f64p(ctl[fork_join.ARG_REF_YAW]), (n_worlds, V))
                ref_yaw_rate = carray(_f64p(ctl[fork_join.ARG_REF_YAW_RATE]), (n_worlds, V))
                residual = carray(_f64p(ctl[fork_join.ARG_RESIDUAL]), (n_worlds, V, 3))
                override = carray(_f64p(ctl[fork_join.ARG_OVERRIDE]), (n_worlds, V, 3))
                row = carray(_f64p(ctl[fork_join.ARG_ROW]), (ctl[fork_join.ARG_ROW_SIZE],))
                actions = ctl[fork_join.ARG_ACTIONS]
                sub_start, sub_stop = ctl[fork_join.ARG_SUB_START], ctl[fork_join.ARG_SUB_STOP]
            elif role == fork_join.MAIN:
                fork_join.publish(ctl, tab, fc, chunks, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, residual,
                                  override, row, actions, sub_start, sub_stop)
            n_worlds, V, block = tab[_T_W], tab[_T_V], tab[_T_BLOCK]
            dt = fc[_F_DT]
            stepping = tab[_T_STEPPING]
            V3 = V * 3
            n_taken = 0
            for taken in range(chunks.shape[0]):  # alone: every chunk in turn; else those the shared counter gives
                ci = taken if role == fork_join.SOLO else fork_join.fetch_add(ctl.ctypes.data + 8 * fork_join.NEXT, 1)
                if ci >= chunks.shape[0]:
                    break
                n_taken += 1
                # chunk ci: worlds w0..w1-1, with this thread's scratch MjData (chunk[2], chunk[3])
                chunk = chunks[ci]
                w0, w1 = chunk[0], chunk[1]
                W = w1 - w0
                layout = carray(_i64p(tab[_T_LAYOUT]), (V, 7))
                noise = carray(_f64p(tab[_T_NOISE]), (n_worlds, block, V, 9))[w0:w1]
                cursor = carray(_i64p(tab[_T_CURSOR]), (n_worlds,))[w0:w1]
                pos_est = carray(_f64p(tab[_T_POS_EST]), (n_worlds, V, 3))[w0:w1]
                vel_est = carray(_f64p(tab[_T_VEL_EST]), (n_worlds, V, 3))[w0:w1]
                t = carray(_f64p(tab[_T_T]), (n_worlds,))[w0:w1]
                next_prediction = carray(_f64p(tab[_T_NEXT_PRED]), (n_worlds,))[w0:w1]
                due = carray(_boolp(tab[_T_DUE]), (n_worlds,))[w0:w1]
                field_on = carray(_boolp(tab[_T_FIELD_ON]), (n_worlds,))[w0:w1]
                turb = carray(_f64p(tab[_T_TURB]), (n_worlds, V, 3))[w0:w1]
                rot_des = carray(_f64p(tab[_T_ROT_DES]), (n_worlds, V, 3, 3))[w0:w1]
                yaw_rate_des = carray(_f64p(tab[_T_YAW_RATE_DES]), (n_worlds, V))[w0:w1]
                thrust_acc = carray(_f64p(tab[_T_THRUST]), (n_worlds, V))[w0:w1]
                mass_believed = carray(_f64p(tab[_T_MASS_BELIEVED]), (n_worlds, V))[w0:w1]
                ap_gain = carray(_f64p(tab[_T_AP_GAIN]), (14, 4))
                active = carray(_boolp(tab[_T_ACTIVE]), (n_worlds,))[w0:w1]
                f_hat = carray(_f64p(tab[_T_F_HAT]), (n_worlds, V, 3))[w0:w1]
                rot = carray(_f64p(tab[_T_ROT]), (n_worlds, V, 3, 3))[w0:w1]
                rot_est = carray(_f64p(tab[_T_ROT_EST]), (n_worlds, V, 3, 3))[w0:w1]
                pred = carray(_f64p(tab[_T_PRED_OUT]), (n_worlds, V, 3))[w0:w1]
                Kt = carray(_f64p(tab[_T_KT]), (7, 4))
                field_packed = carray(_f64p(tab[_T_FIELD_PACKED]), (16,))
                qpos_w, qvel_w, ctrl_w, xfrc_w = qpos[w0:w1], qvel[w0:w1], ctrl[w0:w1], xfrc[w0:w1]
                ref_pos_w, ref_vel_w, ref_acc_w = ref_pos[w0:w1], ref_vel[w0:w1], ref_acc[w0:w1]
                ref_yaw_w, ref_yaw_rate_w = ref_yaw[w0:w1], ref_yaw_rate[w0:w1]
                residual_w, override_w = residual[w0:w1], override[w0:w1]
                u_cmd = _row_view(row, tab[_T_ROW_U_CMD], n_worlds, V3, w0, w1).reshape((W, V, 3))
                kin_scratch = carray(_f64p(tab[_T_KIN]), (5, n_worlds, V, 3))

                for sub in range(sub_start, sub_stop):
                    first = sub == 0
                    if first:  # the first autopilot tick writes the row; later ones reuse scratch buffers
                        kin = row[tab[_T_ROW_KIN]:tab[_T_ROW_KIN] + 5 * n_worlds * V3].reshape((5, n_worlds, V, 3))[:, w0:w1]
                        quat = _row_view(row, tab[_T_ROW_QUAT], n_worlds, V * 4, w0, w1).reshape((W, V, 4))
                        quat_est = _row_view(row, tab[_T_ROW_QUAT_EST], n_worlds, V * 4, w0, w1).reshape((W, V, 4))
                        yaw = _row_view(row, tab[_T_ROW_YAW], n_worlds, V, w0, w1)
                        applied = _row_view(row, tab[_T_ROW_APPLIED], n_worlds, V3, w0, w1).reshape((W, V, 3))
                        mean = _row_view(row, tab[_T_ROW_MEAN], n_worlds, V3, w0, w1).reshape((W, V, 3))
                        for w in range(W):
                            row[tab[_T_ROW_T] + w0 + w] = t[w]
                    else:
                        kin = kin_scratch[:, w0:w1]
                        quat = carray(_f64p(tab[_T_QUAT]), (n_worlds, V, 4))[w0:w1]
                        quat_est = carray(_f64p(tab[_T_QUAT_EST]), (n_worlds, V, 4))[w0:w1]
                        yaw = carray(_f64p(tab[_T_YAW]), (n_worlds, V))[w0:w1]
                        applied = carray(_f64p(tab[_T_APPLIED]), (n_worlds, V, 3))[w0:w1]
                        mean = carray(_f64p(tab[_T_MEAN]), (n_worlds, V, 3))[w0:w1]
                    n_due = _sense_kernel(
                        qpos_w, qvel_w, layout, noise, cursor, fc[_F_SIGMA_P], fc[_F_SIGMA_ATT], fc[_F_KF_P], fc[_F_KF_V],
                        pos_est, vel_est, t, next_prediction, due, kin, quat, rot, quat_est, rot_est, yaw,
                    )
                    pos, vel = kin[0], kin[1]

                    vel_air = vel
                    if with_wind:  # a constant: numba prunes the branch it does not take
                        if first:
                            air = _row_view(row, tab[_T_ROW_WIND], n_worlds, V3, w0, w1).reshape((W, V, 3))
                            wind_acc = _row_view(row, tab[_T_ROW_WIND_ACC], n_worlds, V3, w0, w1).reshape((W, V, 3))
                        else:
                            air = carray(_f64p(tab[_T_AIR]), (n_worlds, V, 3))[w0:w1]
                            wind_acc = carray(_f64p(tab[_T_WIND_ACC]), (n_worlds, V, 3))[w0:w1]
                        vel_air = carray(_f64p(tab[_T_VEL_AIR]), (n_worlds, V, 3))[w0:w1]
                        gust = carray(_f64p(tab[_T_GUST]), (n_worlds, 3, 2))[w0:w1]
                        wind_mean = carray(_f64p(tab[_T_WIND_MEAN]), (3,))
                        _wind_sense_kernel(gust, carray(_f64p(tab[_T_WIND_AXES]), (3, 3)), wind_mean, fc[_F_DRAG_GAIN],
                                           vel, air, vel_air, wind_acc)
                        _wind_advance_kernel(
                            gust, carray(_f64p(tab[_T_WIND_NOISE]), (n_worlds, block, 3, 2))[w0:w1], cursor, vel, dt, wind_mean,
                            carray(_f64p(tab[_T_WIND_SIGMA]), (3,)), carray(_f64p(tab[_T_WIND_LENGTH]), (3,)), fc[_F_MIN_AIRSPEED],
                            np.empty((3, 2, 2)), np.empty((3, 2, 2)),
                        )

                    if n_due:  # the predictor at 45 Hz, held
                        kind = tab[_T_PRED]
                        if kind == _PRED_ZERO:
                            pred[:] = 0.0
                        elif kind == _PRED_ORACLE:
                            _copy_into(pred, _pairwise_kernel(pos, vel_air, rot, carray(_f64p(tab[_T_ORACLE_PACKED]), (16,))))
                        elif kind == _PRED_PER_WORLD:  # world by world, each its own predictor, as PerWorldPredictor
                            pw_code = carray(_i64p(tab[_T_PW_CODE]), (n_worlds,))[w0:w1]
                            pw_fn = carray(_i64p(tab[_T_PW_FN]), (n_worlds,))[w0:w1]
                            pw_params = carray(_i64p(tab[_T_PW_PARAMS]), (n_worlds,))[w0:w1]
                            pw_iparams = carray(_i64p(tab[_T_PW_IPARAMS]), (n_worlds,))[w0:w1]
                            pw_oracle = carray(_f64p(tab[_T_PW_ORACLE]), (n_worlds, 16))[w0:w1]
                            for w in range(W):
                                if pw_code[w] == _PRED_ORACLE:
                                    _copy_into(pred[w:w + 1], _pairwise_kernel(pos[w:w + 1], vel_air[w:w + 1], rot[w:w + 1],
                                                                               pw_oracle[w]))
                                elif pw_code[w] == _PRED_C:  # one world: its rows of C-contiguous (W, ...) arrays
                                    _call_predictor(
                                        pw_fn[w], 1, V, kin[3][w].ctypes.data, kin[4][w].ctypes.data, rot_est[w].ctypes.data,
                                        pos[w].ctypes.data, vel_air[w].ctypes.data, rot[w].ctypes.data, pw_params[w],
                                        pw_iparams[w], pred[w].ctypes.data,
                                    )
                                else:
                                    for i in range(V):
                                        for k in range(3):
                                            pred[w, i, k] = 0.0
                        else:  # every array here is a block of whole worlds of a C-contiguous (W, ...) array
                            _call_predictor(
                                tab[_T_PRED_FN], W, V, kin[3].ctypes.data, kin[4].ctypes.data, rot_est.ctypes.data,
                                pos.ctypes.data, vel_air.ctypes.data, rot.ctypes.data, tab[_T_PRED_PARAMS], tab[_T_PRED_IPARAMS],
                                pred.ctypes.data,
                            )
                        _hold_kernel(f_hat, pred, due, next_prediction, fc[_F_PRED_PERIOD])

                    _copy_into(mean, _pairwise_kernel(pos, vel_air, rot, field_packed))

                    if first:  # the LQR and feedback linearisation at 50 Hz
                        _copy_into(_row_view(row, tab[_T_ROW_REF_POS], n_worlds, V3, w0, w1).reshape((W, V, 3)), ref_pos_w)
                        _copy_into(_row_view(row, tab[_T_ROW_REF_VEL], n_worlds, V3, w0, w1).reshape((W, V, 3)), ref_vel_w)
                        _copy_into(_row_view(row, tab[_T_ROW_REF_ACC], n_worlds, V3, w0, w1).reshape((W, V, 3)), ref_acc_w)
                        state = (kin[3], kin[4], yaw, ref_pos_w, ref_vel_w, ref_acc_w, ref_yaw_w, ref_yaw_rate_w, f_hat)
                        limits = (Kt, fc[_F_LOOKAHEAD], fc[_F_TAN_TILT], fc[_F_MIN_VERTICAL], u_cmd, yaw_rate_des, thrust_acc, rot_des)
                        _command_setpoint_kernel(*state, residual_w, override_w, (actions & 1) != 0, (actions & 2) != 0, *limits)
                        _copy_into(_row_view(row, tab[_T_ROW_F_HAT], n_worlds, V3, w0, w1).reshape((W, V, 3)), f_hat)

                    _actuate_kernel(
                        field_on, noise, cursor, turb, fc[_F_OU_A], fc[_F_OU_B], fc[_F_INTENSITY], fc[_F_MASS], xfrc_w, layout,
                        qvel_w, rot_des, yaw_rate_des, thrust_acc, mass_believed, ap_gain, fc[_F_MAX_THRUST], ctrl_w,
                        pos_est, vel_est, dt, t, active, mean, applied, rot, u_cmd,
                    )
                    if with_wind:
                        _wind_force_kernel(xfrc_w, layout, fc[_F_MASS], wind_acc)
                    if stepping == _STEP_SERIAL:
                        if active[0]:
                            for _ in range(tab[_T_NPHYS]):
                                _call_mj_step(tab[_T_STEP_FN], tab[_T_MODEL], tab[_T_DATA])
                    elif stepping == _STEP_ROWS:
                        _step_rows(tab, active, w0, w1, chunk[2], chunk[3])

                if stepping == _STEP_CALLER or sub_stop != tab[_T_NSUB]:
                    continue
                # the tick is complete: check every world of the chunk
                diverged = carray(_boolp(tab[_T_DIVERGED]), (n_worlds,))[w0:w1]
                if stepping == _STEP_SERIAL:  # MuJoCo's warning counts: int32, every warning_stride-th one
                    step = tab[_T_WARNING_STRIDE]
                    warnings = carray(_i32p(tab[_T_WARNINGS]), (_FATAL_MAX * step + 1,))
                    diverged[0] = warnings[_FATAL_0 * step] > 0 or warnings[_FATAL_1 * step] > 0 or warnings[_FATAL_2 * step] > 0
                else:
                    batch_warnings = carray(_i32p(tab[_T_BATCH_WARNINGS]), (n_worlds, tab[_T_NWARNINGS], 2))
                    for w in range(W):  # as sim.physics._mark_fatal: counts since the world's reset
                        c = batch_warnings[w0 + w]
                        diverged[w] = c[_FATAL_0, 1] > 0 or c[_FATAL_1, 1] > 0 or c[_FATAL_2, 1] > 0
                total += _status_kernel(
                    qpos_w, layout, qvel_w, diverged, active, carray(_i64p(tab[_T_TICK_INDEX]), (n_worlds,))[w0:w1],
                    fc[_F_MAX_DISTANCE], fc[_F_GROUND], fc[_F_RADIUS_XY], fc[_F_RADIUS_Z],
                    carray(_i64p(tab[_T_STATUS_NEW]), (n_worlds,))[w0:w1],
                )
            if helper:
                fork_join.report(ctl, role - fork_join.HELPER, total, n_taken)
                total = 0
            elif role == fork_join.MAIN:
                return fork_join.join(ctl, total)
            else:
                return total

    return _fused_kernel


_FUSED_KERNELS = (_make_fused_kernel(False), _make_fused_kernel(True))  # by wind on
_NO_CONTROL = fork_join.new_control()  # the control block of a call alone, which never reads it


@njit
def _step_rows(tab, active, w0, w1, data, data_warnings):
    """Step worlds w0..w1-1 (active (w1 - w0,)) as mujoco.batch.Batch.step does: each world's state
    row loaded into the scratch MjData `data`, n_physics mj_step, the row saved back; the
    MjData's warnings (mjNWARNING, 2) [last info, count] at data_warnings are cleared before
    and added to the world's (the batch's `warning`) after."""
    n_warn = tab[_T_NWARNINGS]
    nstate = tab[_T_NSTATE]
    states = carray(_f64p(tab[_T_STATE]), (tab[_T_W], nstate))
    batch_warnings = carray(_i32p(tab[_T_BATCH_WARNINGS]), (tab[_T_W], n_warn, 2))
    scratch = carray(_i32p(data_warnings), (n_warn, 2))
    for w in range(w1 - w0):
        if not active[w]:
            continue
        row = states[w0 + w]
        for i in range(n_warn):
            scratch[i, 0] = 0
            scratch[i, 1] = 0
        _call_state(tab[_T_SET_STATE_FN], tab[_T_MODEL], data, row.ctypes.data, tab[_T_STATE_SPEC])
        for _ in range(tab[_T_NPHYS]):
            _call_mj_step(tab[_T_STEP_FN], tab[_T_MODEL], data)
        _call_state(tab[_T_GET_STATE_FN], tab[_T_MODEL], data, row.ctypes.data, tab[_T_STATE_SPEC])
        for i in range(n_warn):
            if scratch[i, 1] > 0:
                batch_warnings[w0 + w, i, 0] = scratch[i, 0]
                batch_warnings[w0 + w, i, 1] += scratch[i, 1]


class _NoPlan(Exception):
    """A buffer is not laid out as the fused kernel reads it: the readable path runs instead."""


class _Plan:
    """The fast path's bound state: the tables of `_fused_kernel` and every array they address.

    Built from the simulator's current components (`Simulator._make_plan`); holding the
    arrays here keeps every address in the tables valid for the plan's lifetime.
    chunks: (n_threads, n, 4) int64, the n world ranges (`_chunk_sizes`) as thread t runs them, with
    its scratch MjData (see `_make_fused_kernel`); the threads take the ranges in turn from one
    counter (`sim.fork_join`).
    """

    def __init__(self, sim: "Simulator", stepping: int, physics_native: tuple | None, field_packed: np.ndarray,
                 oracle_packed: np.ndarray, predictor_code: int, compiled: CompiledPredictor | None,
                 n_threads: int, per_world: dict[str, Any] | None = None):
        W, V, cfg, r = sim.W, sim.V, sim.cfg, sim.cfg.rates
        ph = sim.physics
        self.revision = ph.revision
        self.stepping = stepping
        self.n_sub = r.autopilot_per_control
        self.row_layout, self.row_size = _row_layout(W, V, sim._wind_on)
        wind_consts = sim.wind.kernel_constants() if sim._wind_on else (np.zeros(3), np.zeros(3), np.ones(3), np.eye(3), 1.0)
        keep: dict[str, np.ndarray] = {
            "layout": sim._layout, "noise": sim._noise, "cursor": sim._cursor, "pos_est": sim.pos_est,
            "vel_est": sim.vel_est, "t": sim.t, "next_prediction": sim.next_prediction, "due": sim._due,
            "field_enabled": sim.field_enabled, "turb": sim.turb, "rot_des": sim._rot_des,
            "yaw_rate_des": sim._yaw_rate_des, "thrust_acc": sim._thrust_acc, "mass_believed": sim._mass_believed,
            "ap_gain": np.ascontiguousarray(sim.autopilot.gain, dtype=np.float64), "active": sim.active,
            "f_hat": sim.f_hat, "tick_index": sim.tick_index, "status_new": sim._status_new,
            "kin": np.empty((5, W, V, 3)), "quat": np.empty((W, V, 4)), "rot": np.empty((W, V, 3, 3)),
            "quat_est": np.empty((W, V, 4)), "rot_est": np.empty((W, V, 3, 3)), "yaw": np.empty((W, V)),
            "applied": np.empty((W, V, 3)), "mean": np.empty((W, V, 3)), "pred": np.empty((W, V, 3)),
            "Kt": np.ascontiguousarray(sim.controller._Kt, dtype=np.float64), "field_packed": field_packed,
            "oracle_packed": oracle_packed, "gust": sim.gust_state, "wind_noise": sim._wind_noise,
            "wind_mean": wind_consts[0], "wind_sigma": wind_consts[1], "wind_length": wind_consts[2],
            "wind_axes": wind_consts[3], "air": np.empty((W, V, 3)), "vel_air": np.empty((W, V, 3)),
            "wind_acc": np.empty((W, V, 3)), "diverged": np.zeros(W, bool),
        }
        per_world = per_world if per_world is not None else _per_world_tables(ZeroPredictor(), W)
        keep.update({name: a for name, a in per_world.items() if name.startswith("pw_")})
        self.per_world = per_world  # keeps the worlds' predictors' functions and constants alive
        if compiled is not None:
            keep["predictor_params"] = np.ascontiguousarray(compiled.params, dtype=np.float64)
            keep["predictor_iparams"] = np.ascontiguousarray(compiled.iparams, dtype=np.int64)
        tab = dict.fromkeys(_TAB, 0)
        tab.update(W=W, V=V, block=cfg.noise_block, n_sub=self.n_sub,
                   n_physics=r.physics_per_autopilot, stepping=stepping, predictor=predictor_code)
        sizes = _chunk_sizes(W, n_threads, _CHUNK_WORLDS)
        chunks = np.zeros((n_threads, len(sizes), 4), np.int64)  # as run by each thread: its own MjData
        bounds = np.concatenate([[0], np.cumsum(sizes)])
        chunks[:, :, 0], chunks[:, :, 1] = bounds[:-1], bounds[1:]
        if stepping == _STEP_SERIAL:
            step_fn, model, data, warnings = physics_native
            if warnings.dtype != np.int32 or warnings.strides[0] % 4 or warnings.size <= _FATAL_MAX:
                raise _NoPlan("unexpected layout of MuJoCo's warning counts")
            self.warnings = warnings
            tab.update(step_fn=step_fn, model=model, data=data, warnings=warnings.ctypes.data,
                       warning_stride=warnings.strides[0] // 4)
        elif stepping == _STEP_ROWS:
            step_fn, set_state, get_state, model, state, spec, batch_warnings, scratch = physics_native
            keep.update(state=state, batch_warnings=batch_warnings)
            self.scratch = scratch  # one MjData per thread, as mujoco.batch keeps
            for t, d in enumerate(scratch):
                warning = d.warning  # (mjNWARNING,) records of two int32 [lastinfo, number]
                chunks[t, :, 2], chunks[t, :, 3] = int(d._address), warning.lastinfo.ctypes.data
                if warning.number.ctypes.data != warning.lastinfo.ctypes.data + 4 or warning.lastinfo.strides != (8,):
                    raise _NoPlan("unexpected layout of MuJoCo's warning records")
            tab.update(step_fn=step_fn, set_state_fn=set_state, get_state_fn=get_state, model=model,
                       nstate=state.shape[1], state_spec=spec, n_warnings=batch_warnings.shape[1])
        for name, a in keep.items():  # the kernel reads them as C-contiguous arrays of these types
            if not (isinstance(a, np.ndarray) and a.flags.c_contiguous
                    and a.dtype in (np.float64, np.int64, np.int32, np.bool_)):
                raise _NoPlan(f"{name} is not a C-contiguous array of a kernel type")
        tab.update({name: a.ctypes.data for name, a in keep.items()})
        self.arrays = keep
        self.compiled = compiled  # keeps the predictor's function referenced
        if compiled is not None:
            tab["predictor_fn"] = int(compiled.address)
        storage = {"kin": "pos", "t": "t", "quat": "quat", "quat_est": "quat_est", "yaw": "yaw_est",
                   "applied": "field_applied", "ref_pos": "ref_pos", "ref_vel": "ref_vel", "ref_acc": "ref_acc",
                   "u_cmd": "u_cmd", "f_hat": "f_hat", "mean": "field_mean", "wind": "wind", "wind_acc": "wind_acc"}
        for slot, name in storage.items():
            if name in self.row_layout:
                tab["row_" + slot] = self.row_layout[name][0]
        self.tab = np.array([tab[name] for name in _TAB], dtype=np.int64)
        self.chunks = chunks
        self.n_threads = n_threads
        lqr = sim.controller
        fc = {
            "sigma_p": sim._sigma_p, "sigma_att": sim._sigma_att, "kf_gain_p": sim._kf_gain_p,
            "kf_gain_v": sim._kf_gain_v, "ou_a": sim._ou_a, "ou_b": sim._ou_b, "intensity": sim._turbulence_intensity,
            "mass": sim.mass, "max_thrust": sim._max_thrust, "dt": r.autopilot_dt,
            "prediction_period": sim._prediction_period, "lookahead": r.control_dt,
            "tan_tilt": math.tan(lqr.max_tilt), "min_vertical": lqr.min_vertical,
            "min_airspeed": wind_consts[4], "drag_gain": sim._drag_gain, "max_distance": cfg.max_distance,
            "ground": cfg.ground_clearance, "radius_xy": cfg.collision_radius_xy, "radius_z": cfg.collision_radius_z,
        }
        self.fc = np.array([float(fc[name]) for name in _FC])
        self.leading_args = (self.tab, self.fc, ph.qpos, ph.qvel, ph.ctrl, ph.xfrc_applied)  # of every kernel call
        self.kernel = _FUSED_KERNELS[int(sim._wind_on)]
        self.no_action = np.zeros((W, V, 3))  # stands in for an absent residual or override


# Assigning one of these attributes of a Simulator rebinds its compiled passes at the next tick
# (its components, and the state arrays the passes address, which are meant to be updated in place).
_BOUND_INPUTS = frozenset({"field", "predictor", "controller", "autopilot", "turbulence", "wind", "aggregation",
                           "field_enabled", "fast", "t", "tick_index", "active", "pos_est", "vel_est", "turb",
                           "gust_state", "f_hat", "next_prediction"})


class Simulator:
    """W worlds of V vehicles flying the full stack; advance one controller tick at a time.

    reference: callable t (W,) -> RefSample with (W, V, ...) arrays (`downwash_trajectories.stack`).
    seeds: one int per world; a world's noise comes only from its own generators.
    config: `SimConfig` (vehicle, rates, motion capture, failure checks).
    Components (each defaults to the paper's):
      controller: the outer loop, `FeedbackLinearisedLQR(LQRConfig(...))` or any object
        with its `command_setpoint(state, ref, f_hat, out, residual, override, lookahead)`;
      autopilot: `Autopilot(quad, ...)` (its `gain` and `max_thrust` run compiled);
      turbulence: `OUTurbulence(intensity, time_constant)`;
      field: any object with the `DownwashField` call signature;
      aggregation: how the wakes of several leaders combine on a vehicle, passed to
        `sim.aggregation.wake_field` (None: linear superposition, `pairwise_field`);
      wind: `sim.wind.DrydenWind` (mean wind + Dryden gusts) or None (see the module
        docstring: one gust state per world, drag on every vehicle, wakes convected);
      predictor: `sim.predictor.Predictor`, evaluated at 45 Hz and held.
    field_enabled: (W,) bool, False for worlds flown without downwash.
    fast: take the fused compiled path when every component has a compiled form (the
      result is the same bit for bit; False forces the readable path).
    Components may be replaced between ticks (attributes of the same names); arrays such
    as `field_enabled`, `t` or `active` are updated in place only.
    """

    def __init__(
        self,
        scene: Scene,
        reference: Callable,
        seeds: Sequence[int],
        *,
        config: SimConfig | None = None,
        controller: Any | None = None,
        autopilot: Autopilot | None = None,
        turbulence: OUTurbulence | None = None,
        field: Any | None = None,
        predictor: Predictor | None = None,
        field_enabled: np.ndarray | None = None,
        n_threads: int = 0,
        wind: DrydenWind | None = None,
        aggregation: Any = None,
        fast: bool = True,
    ):
        object.__setattr__(self, "_bound", False)
        object.__setattr__(self, "_in_use", threading.RLock())  # one thread at a time (`_one_thread`)
        if wind is not None and not isinstance(wind, DrydenWind):
            raise ConfigError(f"wind: expected a sim.wind.DrydenWind or None, got {type(wind).__name__}")
        self.scene = scene
        self.cfg = cfg = config if config is not None else SimConfig()
        self.reference = reference
        self.controller = controller if controller is not None else FeedbackLinearisedLQR()
        self.autopilot = autopilot if autopilot is not None else Autopilot(cfg.quad)
        self.turbulence = turbulence if turbulence is not None else OUTurbulence()
        self.field = field if field is not None else DownwashField()
        self.predictor = predictor if predictor is not None else ZeroPredictor()
        self.aggregation = aggregation
        self.fast = bool(fast)
        seeds = [int(s) for s in seeds]
        W, V = len(seeds), scene.n_vehicles
        if W < 1:
            raise ConfigError("seeds: expected one seed per world, got none")
        self.W, self.V = W, V
        self.seeds = seeds
        self.field_enabled = np.ones(W, bool) if field_enabled is None else np.asarray(field_enabled, bool)
        if self.field_enabled.shape != (W,):
            raise ConfigError(f"field_enabled: expected shape ({W},), got {self.field_enabled.shape}")

        r = cfg.rates
        check_world_memory(W, V, name="worlds")  # before MuJoCo's batch and the state arrays are allocated
        self.physics = make_physics(scene.model, W, n_threads)
        self.kf = MocapKalmanFilter(r.autopilot_dt, cfg.mocap)
        self.mass = cfg.quad.mass

        # index arrays, resolved once
        qa, va = scene.qpos_adr, scene.qvel_adr
        self._pos_idx = qa[:, None] + np.arange(3)
        self._quat_idx = qa[:, None] + 3 + np.arange(4)
        self._vel_idx = va[:, None] + np.arange(3)
        # per vehicle: qpos address, qvel address, body id, 4 actuator ids (columns _QPOS.._ACT)
        self._layout = np.concatenate(
            [np.stack([qa, va, scene.body_ids], axis=1), scene.act_ids], axis=1
        ).astype(np.int64)
        # scalars of the hot loop that do not depend on the components, as Python floats
        self._prediction_period = 1.0 / r.predictor_hz  # s
        self._sigma_p, self._sigma_att = float(cfg.mocap.position_noise), float(cfg.mocap.attitude_noise)
        self._kf_gain_p, self._kf_gain_v = (float(g) for g in self.kf.gain)
        self._drag_gain = AIRFRAME.gain(self.mass)  # 1/m, of the wind's drag

        # per-world state beyond MuJoCo's; pos_est, vel_est, turb, gust_state, f_hat, t,
        # tick_index and next_prediction are updated in place (copy to keep a value; the
        # rows tick() returns are fresh already)
        self.t = np.zeros(W)  # s, time since each world's reset
        self.tick_index = np.zeros(W, np.int64)
        self.status = np.zeros(W, np.int64)
        self.message = [""] * W
        self.active = np.ones(W, bool)
        self.pos_est = np.zeros((W, V, 3))  # m, Kalman estimate (prior for the next sample)
        self.vel_est = np.zeros((W, V, 3))  # m/s
        self.turb = np.zeros((W, V, 3))  # -, Ornstein-Uhlenbeck turbulence state
        self.gust_state = np.zeros((W, 3, 2))  # m/s, each world's Dryden gust state (zeros without wind)
        self.f_hat = np.zeros((W, V, 3))  # m/s^2, held prediction
        self.next_prediction = np.zeros(W)  # s
        self._rngs: list[np.random.Generator] = [None] * W  # type: ignore[list-item]
        self._wind_rngs: list[np.random.Generator | None] = [None] * W
        self._noise = np.zeros((W, cfg.noise_block, V, 9))  # per tick: mocap position, attitude, turbulence
        self._wind_noise = np.zeros((W, cfg.noise_block, 3, 2))  # per tick: the gusts' draws (wind on only)
        self._mass_believed = np.full((W, V), cfg.quad.mass)  # kg, the controller's model
        self._cursor = np.zeros(W, np.int64)
        self._cursor_max = 0  # max(self._cursor), kept as a Python int (no reduction per tick)
        self._due = np.zeros(W, bool)
        self._reused = _Sensed.empty(W, V)  # buffers of the second and later autopilot ticks
        self._wind_reused = tuple(np.empty((W, V, 3)) for _ in range(3))  # air, vel_air, wind_acc, likewise
        self._rot_des = np.empty((W, V, 3, 3))  # body to world, set by the 50 Hz control
        self._yaw_rate_des = np.empty((W, V))  # rad/s
        self._thrust_acc = np.empty((W, V))  # m/s^2
        self._status_new = np.zeros(W, np.int64)
        self.row: Mapping[str, np.ndarray] = {}
        self.wind = wind
        self._bind()
        self.reset(np.arange(W), seeds)
        if field is not None:  # once, before any step: a bad field is named, not found mid-batch
            start = self.true_states()
            check_field(field, start.pos, start.vel, start.rot, finite=False)

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "wind" and "wind" in self.__dict__:  # its generators and gust states start at reset
            raise AttributeError("wind: set at construction (Simulator(..., wind=...)), not replaced afterwards")
        object.__setattr__(self, name, value)
        if name in _BOUND_INPUTS:
            object.__setattr__(self, "_bound", False)  # rebind at the next tick

    def _bind(self) -> None:
        """Bind the components' constants and the compiled passes' arguments (again after a change)."""
        cfg, r = self.cfg, self.cfg.rates
        self._wind_on = self.wind is not None and not self.wind.off
        self._ou_a, self._ou_b = self.turbulence.coefficients(r.autopilot_dt)
        self._max_thrust = float(self.autopilot.max_thrust)
        self._turbulence_intensity = float(self.turbulence.intensity)
        if self._wind_on:
            mean, sigma, length, axes, min_airspeed = self.wind.kernel_constants()
            self._wind_sense_consts = (axes, mean, self._drag_gain)
            self._wind_advance_consts = (r.autopilot_dt, mean, sigma, length, min_airspeed, np.zeros((3, 2, 2)),
                                         np.zeros((3, 2, 2)))
        # The readable path's compiled passes: their persistent arguments, bound once; every
        # array here is only ever updated in place, so each tick passes just the fresh ones.
        self._sense_args = (
            self.physics.qpos, self.physics.qvel, self._layout, self._noise, self._cursor,
            self._sigma_p, self._sigma_att, self._kf_gain_p, self._kf_gain_v,
            self.pos_est, self.vel_est, self.t, self.next_prediction, self._due,
        )
        self._actuate_args = (
            self.field_enabled, self._noise, self._cursor, self.turb,
            self._ou_a, self._ou_b, self._turbulence_intensity, self.mass, self.physics.xfrc_applied, self._layout,
            self.physics.qvel, self._rot_des, self._yaw_rate_des, self._thrust_acc, self._mass_believed,
            self.autopilot.gain, self._max_thrust, self.physics.ctrl,
            self.pos_est, self.vel_est, cfg.rates.autopilot_dt, self.t, self.active,
        )
        self._plan = self._make_plan() if self.fast else None
        object.__setattr__(self, "_bound", True)

    def _make_plan(self) -> _Plan | None:
        """The fused path's plan when every component has a compiled form, else None (readable path)."""
        field_packed = _packed_field(self.field, self.aggregation)
        if field_packed is None or type(self.controller) is not FeedbackLinearisedLQR:
            return None
        if not isinstance(self.autopilot, Autopilot):
            return None
        ph, n_threads = self.physics, 1
        if isinstance(ph, _SerialPhysics):
            stepping, native = _STEP_SERIAL, ph.native_step()
            if native is None:
                return None
        else:
            # worlds in chunks of >= _CHUNK_WORLDS on the batch's threads, each thread with its MjData
            n_threads = max(1, min(ph.batch.nthread, self.W // _CHUNK_WORLDS))
            native = ph.native_step(n_threads)
            stepping = _STEP_ROWS if native is not None else _STEP_CALLER
            if native is None:
                n_threads = 1
        predictor, compiled, oracle_packed, per_world = self.predictor, None, np.zeros(16), None
        if type(predictor) is ZeroPredictor:
            code = _PRED_ZERO
        elif type(predictor) is PerWorldPredictor:
            per_world = _per_world_tables(predictor, self.W)
            if per_world is None:
                return None
            code = _PRED_PER_WORLD
        elif type(predictor) is OraclePredictor:
            packed = _packed_field(predictor.field, predictor.aggregation)
            if packed is None:
                return None
            code, oracle_packed = _PRED_ORACLE, packed
        else:
            compiled = getattr(predictor, "compiled", lambda: None)()
            if compiled is None:
                return None
            code = _PRED_C
        try:
            return _Plan(self, stepping, native, field_packed, oracle_packed, code, compiled, n_threads, per_world)
        except _NoPlan:
            return None

    # ------------------------------------------------------------------ state access
    def true_states(self) -> VehicleStates:
        """The true states now (fresh arrays): positions (W, V, 3) m, velocities (W, V, 3) m/s
        (world frame, over the ground) and attitudes (W, V, 3, 3) body to world."""
        W, V = self.W, self.V
        pos, vel, rot = np.empty((W, V, 3)), np.empty((W, V, 3)), np.empty((W, V, 3, 3))
        _true_states_kernel(self.physics.qpos, self.physics.qvel, self._layout, pos, vel, rot)
        return VehicleStates(pos, vel, rot)

    # ------------------------------------------------------------------ reset
    def reset(self, worlds: np.ndarray, seeds: Sequence[int] | None = None, reference: Callable | None = None) -> None:
        """Start the given worlds afresh at their reference's t = 0 state, hovering level (one
        thread at a time, as `tick`)."""
        lock = self._one_thread("reset")
        try:
            self._reset(worlds, seeds, reference)
        finally:
            lock.release()

    def _reset(self, worlds: np.ndarray, seeds: Sequence[int] | None, reference: Callable | None) -> None:
        worlds = np.asarray(worlds, dtype=np.int64)
        if reference is not None:
            self.reference = reference
        if seeds is not None:
            for w, s in zip(worlds, seeds):
                self.seeds[w] = int(s)
        if not self._bound:
            self._bind()
        ph = self.physics
        ph.reset(worlds)
        ref = self.reference(np.zeros(self.W))
        qpos, qvel = ph.qpos, ph.qvel
        for w in worlds:  # per-world python is fine here: resets are rare
            qpos[w, self._pos_idx] = ref.pos[w]
            half = 0.5 * ref.yaw[w]
            qpos[w, self._quat_idx] = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], axis=-1)
            qvel[w] = 0.0
            qvel[w, self._vel_idx] = ref.vel[w]
            ph.act[w] = self.cfg.quad.hover_rotor_thrust
            ph.ctrl[w] = self.cfg.quad.hover_rotor_thrust
            ph.xfrc_applied[w] = 0.0
            self._rngs[w] = np.random.default_rng(self.seeds[w])
            if self._wind_on:  # the gusts start stationary, from the world's own wind stream
                self._wind_rngs[w] = np.random.default_rng([self.seeds[w], WIND_STREAM])
                self.gust_state[w] = self.wind.stationary_state(self._wind_rngs[w].standard_normal((3, 2)))
            else:
                self.gust_state[w] = 0.0
            self._refill(w)
        self.t[worlds] = 0.0
        self.tick_index[worlds] = 0
        self.status[worlds] = Status.OK
        for w in worlds:
            self.message[w] = ""
        self.active[worlds] = True
        self.pos_est[worlds] = ref.pos[worlds]
        self.vel_est[worlds] = ref.vel[worlds]
        self.turb[worlds] = 0.0
        self.f_hat[worlds] = 0.0
        self.next_prediction[worlds] = 0.0
        self._cursor_max = int(self._cursor.max())

    def _refill(self, w: int) -> None:
        self._noise[w] = self._rngs[w].standard_normal(self._noise.shape[1:])
        if self._wind_on:
            self._wind_noise[w] = self._wind_rngs[w].standard_normal(self._wind_noise.shape[1:])
        self._cursor[w] = 0

    def _refill_used(self) -> None:
        """Refill the noise block of every world whose draws are used up (each from its own streams)."""
        for w in np.flatnonzero(self._cursor >= self._noise.shape[1]):
            self._refill(w)
        self._cursor_max = int(self._cursor.max())

    # ------------------------------------------------------------------ one controller tick
    def _one_thread(self, what: str) -> threading.RLock:
        """The simulator's lock, taken for `what` by this thread; ConcurrentUseError at once when
        another thread holds it. A tick's helper threads wait for the thread that started it,
        so a second thread ticking the same simulator would wait on them forever or corrupt the
        worlds: it gets an error instead, never a hang."""
        lock = self.__dict__["_in_use"]
        if not lock.acquire(blocking=False):
            raise ConcurrentUseError(
                f"Simulator.{what}: another thread is inside this simulator. A simulator, and the env "
                f"that holds it, serves one thread at a time: make one env (or simulator) per thread")
        return lock

    def tick(self, residual: np.ndarray | None = None, override: np.ndarray | None = None) -> Mapping[str, np.ndarray]:
        """Advance every active world by one controller period; returns the tick's log row.

        One thread at a time: a call from a second thread while a tick or a reset is in
        progress raises ConcurrentUseError (see `_one_thread`).

        residual: (W, V, 3) m/s^2 added to the LQR command (e.g. an RL compensation action).
        override: (W, V, 3) m/s^2 replacing the LQR acceleration where finite (NaN keeps LQR).
        The row (name -> (W, ...) array, the names of `sim.logs.ARRAY_SPECS`, plus "wind"
        and "wind_acc" when the wind is on) describes the state at the start of the tick
        and the command applied during it; its arrays are fresh each tick and never
        written to afterwards. A dict on the readable path, a `Row` on the fused one.
        """
        W, V = self.W, self.V
        if residual is not None:
            residual = _as_batch(residual, (W, V, 3))
        if override is not None:
            override = _as_batch(override, (W, V, 3))
        lock = self._one_thread("tick")
        try:
            if not self._bound:
                self._bind()
            plan = self._plan
            if plan is not None and plan.revision != self.physics.revision:  # set_body_mass changed the worlds
                self._bind()
                plan = self._plan
            if plan is not None:
                row = self._tick_fused(plan, residual, override)
            else:
                row = self._tick_readable(residual, override)
            self.__dict__["row"] = row  # (not a bound input: skips __setattr__, once per tick)
        finally:
            lock.release()
        return row

    def _tick_fused(self, plan: _Plan, residual: np.ndarray | None, override: np.ndarray | None) -> Row:
        """One controller tick through `_fused_kernel` (see the module docstring)."""
        ref = self.reference(self.t)
        flat = np.empty(plan.row_size)
        n_sub, block = plan.n_sub, self.cfg.noise_block
        actions = (residual is not None) + 2 * (override is not None)
        residual = plan.no_action if residual is None else _kernel_array(residual)
        override = plan.no_action if override is None else _kernel_array(override)
        refs = (ref.pos, ref.vel, ref.acc, ref.yaw, ref.yaw_rate)
        if plan.n_threads > 1:  # the helpers read them by address, as C-contiguous arrays
            refs = tuple(_kernel_array(x) for x in refs)
        args = plan.leading_args + refs + (residual, override, actions, flat)
        sub, diverged, n_ended = 0, None, 0
        chunks = plan.chunks
        caller_steps = plan.stepping == _STEP_CALLER
        while sub < n_sub:
            if self._cursor_max >= block:
                self._refill_used()
            # the rest of the tick in one call (up to a refill of the noise blocks), unless the
            # caller steps the physics: then one autopilot tick per call
            stop = min(sub + 1 if caller_steps else n_sub, sub + block - self._cursor_max)
            if plan.n_threads == 1:
                n_ended = plan.kernel(*args, sub, stop, chunks[0], _NO_CONTROL, fork_join.SOLO)
            else:
                n_ended = self._run_threads(plan, args, sub, stop)
            self.__dict__["_cursor_max"] += stop - sub  # (not a bound input: skips __setattr__)
            if caller_steps:
                d = self.physics.step(self.cfg.rates.physics_per_autopilot, self.active)
                diverged = d if diverged is None else diverged | d
            sub = stop
        if caller_steps:
            self._check(diverged)
        elif n_ended:
            self._end_worlds(self._status_new)
        return Row(flat, plan.row_layout)

    def _run_threads(self, plan: _Plan, args: tuple, sub: int, stop: int) -> int:
        """Autopilot ticks sub..stop-1 on this thread and the helpers (`sim.fork_join`); returns how
        many worlds ended. The helpers serve every plan of this simulator (a plan is rebuilt
        when a component changes, e.g. at each autoreset of an env with randomised fields)."""
        helpers = self.__dict__.get("_helpers")
        if helpers is None or not helpers.alive or helpers.key != (plan.kernel, plan.n_threads):
            helpers = self._start_helpers(plan)  # first use, or a forked child (no threads of its own)
        ctl, role = (helpers.ctl, fork_join.MAIN) if helpers.start_tick() else (_NO_CONTROL, fork_join.SOLO)
        return helpers.end_tick(plan.kernel(*args, sub, stop, plan.chunks[0], ctl, role), stop - sub)

    def _start_helpers(self, plan: _Plan) -> fork_join.Helpers:
        """Threads 1..n-1, each serving ticks with its own chunk table and scratch MjData, whatever
        the plan (each tick's tables come through the control block). What they hold must not
        refer to the simulator, which stops them when it is collected."""
        previous = self.__dict__.get("_helpers")
        if previous is not None:
            previous.stop()  # (nothing in a forked child, whose copy has no threads)
        ctl = fork_join.new_control()
        W, V = self.W, self.V
        kernel = plan.kernel  # and the physics state: the same arrays for every plan of this simulator
        # placeholders of the arguments but the physics state's (a helper reads the tick's own from ctl)
        fixed = (np.zeros(len(_TAB), np.int64), np.zeros(len(_FC))) + plan.leading_args[2:] \
            + (np.zeros((W, V, 3)),) * 3 + (np.zeros((W, V)),) * 2 + (np.zeros((W, V, 3)),) * 2 \
            + (0, np.zeros(1), 0, 0, np.zeros((1, 4), np.int64))

        def serve(t: int) -> int:
            return kernel(*fixed, ctl, fork_join.HELPER + t)

        helpers = fork_join.Helpers(plan.n_threads - 1, serve, ctl, owner=self)
        helpers.key = (kernel, plan.n_threads)
        self.__dict__["_helpers"] = helpers
        return helpers

    def _tick_readable(self, residual: np.ndarray | None, override: np.ndarray | None) -> dict[str, np.ndarray]:
        """One controller tick as compiled passes around the Python components (see the module docstring)."""
        r = self.cfg.rates
        ph, W, V = self.physics, self.W, self.V
        wind = self._wind_on
        row: dict[str, np.ndarray] = {}
        t_start = self.t.copy()
        diverged = None
        for sub in range(r.autopilot_per_control):
            first = sub == 0
            if self._cursor_max >= self._noise.shape[1]:
                self._refill_used()
            sensed = _Sensed.empty(W, V) if first else self._reused  # the first tick's arrays become the row
            kin, quat, rot, quat_est, rot_est, yaw, applied = sensed
            pos, vel, mocap, pos_est, vel_est = kin
            # motion capture and Kalman update
            n_due = _sense_kernel(*self._sense_args, kin, quat, rot, quat_est, rot_est, yaw)

            # the wind at each vehicle, its drag, and the next gust state; the wakes see vel - u_air
            vel_air = vel
            if wind:
                air, vel_air, wind_acc = tuple(np.empty((W, V, 3)) for _ in range(3)) if first else self._wind_reused
                _wind_sense_kernel(self.gust_state, *self._wind_sense_consts, vel, air, vel_air, wind_acc)
                _wind_advance_kernel(self.gust_state, self._wind_noise, self._cursor, vel, *self._wind_advance_consts)

            # predictor at 45 Hz, held: it sees what a lab measures, the truth only for oracles
            if n_due:
                pred = self.predictor(VehicleStates(pos_est, vel_est, rot_est), VehicleStates(pos, vel_air, rot))
                _hold_kernel(self.f_hat, _as_batch(pred, (W, V, 3)), self._due, self.next_prediction, self._prediction_period)

            # downwash field, applied as an external force until the next autopilot tick
            mean = wake_field(self.field, pos, vel_air, rot, self.aggregation)

            if first:  # the LQR and feedback linearisation at 50 Hz
                ref = self.reference(self.t)
                cmd_acc = np.empty((W, V, 3))  # m/s^2, the command applied (row u_cmd)
                self.controller.command_setpoint(
                    ControllerState(pos_est, vel_est, yaw), ref, self.f_hat,
                    Setpoint(cmd_acc, self._yaw_rate_des, self._thrust_acc, self._rot_des),
                    residual, override, r.control_dt,
                )
                row = {
                    "t": t_start, "pos": pos, "vel": vel, "quat": quat,
                    "pos_est": pos_est, "vel_est": vel_est, "quat_est": quat_est, "yaw_est": yaw,
                    "mocap_pos": mocap, "ref_pos": ref.pos, "ref_vel": ref.vel, "ref_acc": ref.acc,
                    "u_cmd": cmd_acc, "f_hat": self.f_hat.copy(), "field_mean": mean, "field_applied": applied,
                }
                if wind:
                    row["wind"], row["wind_acc"] = air, wind_acc

            # field and turbulence into xfrc_applied, autopilot into ctrl, Kalman prediction, clocks
            _actuate_kernel(*self._actuate_args, mean, applied, rot, cmd_acc)
            if wind:
                _wind_force_kernel(ph.xfrc_applied, self._layout, self.mass, wind_acc)
            self.__dict__["_cursor_max"] += 1
            d = ph.step(r.physics_per_autopilot, self.active)
            diverged = d if diverged is None else diverged | d
        self._check(diverged)
        return row

    def _check(self, diverged: np.ndarray) -> None:
        """Count the tick for active worlds; end those that diverged or collided (they keep their rows)."""
        cfg = self.cfg
        status = self._status_new
        n_ended = _status_kernel(
            self.physics.qpos, self._layout, self.physics.qvel, diverged, self.active, self.tick_index,
            cfg.max_distance, cfg.ground_clearance, cfg.collision_radius_xy, cfg.collision_radius_z, status,
        )
        if n_ended:
            self._end_worlds(status)

    def _end_worlds(self, status: np.ndarray) -> None:
        for w in np.flatnonzero(status):
            self.status[w] = status[w]
            what = Status(int(status[w])).description
            self.message[w] = f"world {w} (seed {self.seeds[w]}): {what} at t = {self.t[w]:.2f} s"
            self.active[w] = False


_CHUNK_WORLDS = 4  # fewest worlds in a chunk of the fused kernel's work (12 worlds: 1.2x faster on 2 threads than 8)


def _chunk_sizes(n_worlds: int, n_threads: int, smallest: int) -> list[int]:
    """Worlds per chunk, large first and halving (guided scheduling): a thread that starts late or
    runs slower takes the small chunks at the end, so the threads finish together (64 worlds on
    2 threads: 16, 16, 8, 8, 4, 4, 4, 4; 1.04x the 8 equal chunks, measured). One chunk for one thread."""
    if n_threads == 1:
        return [n_worlds]
    sizes, left = [], n_worlds
    while left > 0:
        size = max(smallest, left // (2 * n_threads))
        for _ in range(n_threads):
            if left <= 0:
                break
            take = left if left - min(size, left) < smallest else min(size, left)  # no runt at the end
            sizes.append(take)
            left -= take
    return sizes


def _per_world_tables(predictor: Any, W: int) -> dict[str, Any] | None:
    """The fused kernel's tables for a `PerWorldPredictor` (a `ZeroPredictor`: all worlds zero): per
    world its predictor's code, C function, constants' addresses and oracle field (pw_*), and
    the compiled forms (kept alive); None when one of its predictors has no compiled form."""
    if isinstance(predictor, PerWorldPredictor) and predictor.n_worlds != W:
        return None  # the readable path names the mismatch
    groups = predictor.groups if isinstance(predictor, PerWorldPredictor) else [np.arange(W)]
    predictors = predictor.predictors if isinstance(predictor, PerWorldPredictor) else [predictor]
    out: dict[str, Any] = {"pw_code": np.zeros(W, np.int64), "pw_fn": np.zeros(W, np.int64),
                           "pw_params": np.zeros(W, np.int64), "pw_iparams": np.zeros(W, np.int64),
                           "pw_oracle": np.zeros((W, 16)), "compiled": []}
    for p, worlds in zip(predictors, groups):
        if type(p) is ZeroPredictor:
            continue
        if type(p) is OraclePredictor:
            packed = _packed_field(p.field, p.aggregation)
            if packed is None:
                return None
            out["pw_code"][worlds], out["pw_oracle"][worlds] = _PRED_ORACLE, packed
            continue
        compiled = getattr(p, "compiled", lambda: None)()
        if compiled is None:
            return None
        params = np.ascontiguousarray(compiled.params, dtype=np.float64)
        iparams = np.ascontiguousarray(compiled.iparams, dtype=np.int64)
        out["compiled"].append((compiled, params, iparams))
        out["pw_code"][worlds], out["pw_fn"][worlds] = _PRED_C, int(compiled.address)
        out["pw_params"][worlds], out["pw_iparams"][worlds] = params.ctypes.data, iparams.ctypes.data
    return out


def _packed_field(field: Any, aggregation: Any) -> np.ndarray | None:
    """A field's constants for the fused kernel (`DownwashField` with scalar constants and linear
    aggregation, whose `pairwise` is `_pairwise_kernel`), else None."""
    if aggregation is not None and not isinstance(aggregation, LinearSuperposition):
        return None
    if not isinstance(field, DownwashField) or type(field).pairwise is not DownwashField.pairwise:
        return None
    if type(field).__call__ is not DownwashField.__call__:
        return None
    packed = getattr(field, "_packed", None)
    if packed is None or packed.shape != (16,):
        return None
    return np.ascontiguousarray(packed, dtype=np.float64)


def _kernel_array(x: np.ndarray) -> np.ndarray:
    """x (float64) as the fused kernel reads it: C-contiguous and writeable (a copy only when it is not)."""
    flags = x.flags
    return x if flags.c_contiguous and flags.writeable else np.require(x, np.float64, ("C", "W"))


def _as_batch(x: Any, shape: tuple[int, ...]) -> np.ndarray:
    """x as a float64 array of exactly `shape` (broadcast, read-only, only when it differs)."""
    x = np.asarray(x, dtype=np.float64)
    return x if x.shape == shape else np.broadcast_to(x, shape)


@njit
def _status_kernel(qpos, layout, qvel, diverged, active, tick_index, max_distance, ground, radius_xy, radius_z, status):
    """Count the tick of active worlds (tick_index (W,), in place) and write into status (W,)
    the `Status` codes of those that end now (OK elsewhere).

    qpos (W, nq): vehicle positions (m) at qpos[w, layout[i, _QPOS] + (0, 1, 2)];
    diverged (W,) bool from the physics. Returns how many worlds end.
    """
    W, V = qpos.shape[0], layout.shape[0]
    q_adr = layout[:, _QPOS]
    n_ended = 0
    for w in range(W):
        status[w] = _OK
        if not active[w]:
            continue
        tick_index[w] += 1
        bad = diverged[w]
        for j in range(qvel.shape[1]):
            bad = bad or not np.isfinite(qvel[w, j])
        for i in range(V):
            for k in range(3):
                bad = bad or not (abs(qpos[w, q_adr[i] + k]) <= max_distance)  # NaN fails too
        if bad:
            status[w] = _DIVERGED
        else:
            for i in range(V):
                if qpos[w, q_adr[i] + 2] < ground:
                    status[w] = _GROUND
        if status[w] == _OK:
            for i in range(V):
                for j in range(i + 1, V):
                    a, b = q_adr[i], q_adr[j]
                    dx, dy, dz = qpos[w, a] - qpos[w, b], qpos[w, a + 1] - qpos[w, b + 1], qpos[w, a + 2] - qpos[w, b + 2]
                    if (dx * dx + dy * dy) / radius_xy**2 + dz * dz / radius_z**2 < 1.0:
                        status[w] = _VEHICLE
        n_ended += status[w] != _OK
    return n_ended
