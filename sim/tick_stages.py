"""The fused tick's stages: compiled functions over typed state bundles, which `sim.fused` composes.

The address table (`sim.fused_abi`) is read here once per chunk of worlds, by the bundle makers,
into named tuples of typed arrays; the stages take bundles, never the table:

- `World`: the worlds' own state (estimates, clocks, the controller's set-points, the prediction), and
  `Sensing`, the sensor's compiled law when it has one (`sim.sensor_contract`; fn 0: the family's pass);
- `Vehicles`: each vehicle's and pair's constants (`sim.vehicle_params`), the gain, the field's (the paper
  field's constants, or a compiled form's C function, `sim.field_contract`);
- `PhysicsArrays`: the caller's physics state of the chunk's worlds; `Inputs`: the tick's reference and
  actions; `Buffers`: the sub-tick's kinematics and forces (the log row's on the first sub-tick);
- `Wind`, `Prediction`, `Control`, `Stepping`, `Monitor`: what the wind, the predictor and guard,
  the controller and safety filter, the physics stepping and the end-of-tick checks need.

Stages, in a tick's order: `sense_stage` (motion capture and the Kalman filter), `wind_stage`,
`predict_stage` (the predictor at its rate, the guard, the hold), `field_stage`, `control_stage`
(the controller at its rate, the safety filter, the row), `actuate_stage` (autopilot, mixer,
turbulence), `physics_stage`, `monitor_stage` (status and the guard's monitor). Each calls the
passes the readable path calls (`sim.passes`), in the same order, so both paths fly the same bits.
The stages and bundle makers are inlined into the tick (`downwash_core.jit.njit_inline`): called as
functions, with their bundles passed by value, they cost a single world's tick 13 % of its speed.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import carray

from controllers.lqr import command_setpoint_kernel
from downwash_core.jit import njit, njit_inline
from sim.field_kernels import pairwise_kernel
from sim.fused_abi import (
    F_DT, F_GROUND, F_INTENSITY, F_KF_P, F_KF_V, F_LOOKAHEAD, F_MAX_DISTANCE, F_MIN_AIRSPEED, F_MIN_VERTICAL,
    F_OU_A, F_OU_B, F_PRED_PERIOD, F_SIGMA_ATT, F_SIGMA_P, F_TAN_TILT, FATAL_0, FATAL_1, FATAL_2, FATAL_MAX,
    PRED_C, PRED_ORACLE, PRED_PER_WORLD, PRED_ZERO, STEP_ROWS, STEP_SERIAL, T_ACTIVE, T_AIR, T_AP_GAIN, T_APPLIED,
    T_BATCH_WARNINGS, T_BLOCK, T_CONTROLLER_FN, T_CONTROLLER_PARAMS, T_CONTROLLER_STATE, T_CONTROLLER_WIDTH,
    T_CURSOR, T_DATA, T_DIVERGED, T_DRAG_GAIN, T_DUE, T_F_HAT, T_FIELD_FN, T_FIELD_FN_SCALE, T_FIELD_ON,
    T_FIELD_PACKED, T_FIELD_PARAMS, T_FIELD_SCALE, T_GET_STATE_FN, T_GUARD, T_GUARD_APPLIED, T_GUARD_FN,
    T_GUARD_IPARAMS, T_GUARD_PARAMS, T_GUARD_STATE, T_GUST, T_KIN, T_KT, T_LAYOUT, T_MASS, T_MASS_BELIEVED,
    T_MAX_THRUST, T_MEAN, T_MOCAP_OFFSET, T_MODEL, T_MONITOR_FN, T_MONITOR_IPARAMS, T_MONITOR_PARAMS, T_NEXT_PRED,
    T_NOISE, T_NPHYS, T_NSTATE, T_NWARNINGS, T_ORACLE_FN, T_ORACLE_PACKED, T_ORACLE_PARAMS, T_POS_EST, T_PRED,
    T_PRED_FN, T_PRED_IPARAMS, T_PRED_OUT, T_PRED_PARAMS, T_PW_CODE, T_PW_FN, T_PW_GUARD_APPLIED, T_PW_GUARD_FN,
    T_PW_GUARD_IPARAMS, T_PW_GUARD_PARAMS, T_PW_GUARD_STATE, T_PW_GUARDED, T_PW_IPARAMS, T_PW_ORACLE, T_PW_PARAMS,
    T_QUAT, T_QUAT_EST, T_RADIUS_XY, T_RADIUS_Z, T_ROT, T_ROT_DES, T_ROT_EST, T_ROW_APPLIED, T_ROW_F_HAT,
    T_ROW_GUARD, T_ROW_KIN, T_ROW_MEAN, T_ROW_QUAT, T_ROW_QUAT_EST, T_ROW_REF_ACC, T_ROW_REF_POS, T_ROW_REF_VEL,
    T_ROW_T, T_ROW_U_CMD, T_ROW_WIND, T_ROW_WIND_ACC, T_ROW_YAW, T_SAFETY_FN, T_SAFETY_LOWER, T_SAFETY_PARAMS,
    T_SAFETY_STATE, T_SAFETY_UPPER, T_SEEN, T_SEEN_STRIDE, T_SEEN_T, T_SENSOR_FN, T_SENSOR_PARAMS, T_SENSOR_STATE,
    T_SENSOR_WIDTH, T_SET_STATE_FN, T_STATE, T_STATE_SPEC,
    T_STATUS_NEW, T_STEP_FN, T_STEPPING, T_T, T_THRUST, T_TICK_INDEX, T_TURB, T_V, T_VEL_AIR, T_VEL_EST, T_W,
    T_WARNING_STRIDE, T_WARNINGS, T_WIND_ACC, T_WIND_AXES, T_WIND_LENGTH, T_WIND_MEAN, T_WIND_NOISE, T_WIND_SIGMA,
    T_YAW, T_YAW_RATE_DES, boolp, call_controller, call_field, call_mj_step, call_monitor, call_predictor,
    call_state, f64p, i32p, i64p,
)
from sim.passes import (actuate_kernel, hold_kernel, sense_kernel, sense_law_kernel, status_kernel,
                        wind_advance_kernel, wind_force_kernel, wind_sense_kernel)
from sim.predictor import GUARD_STATE_WIDTH
from sim.safety_kernels import STATE_WIDTH as _SAFETY_STATE_WIDTH

World = namedtuple("World", [
    "n_worlds", "V", "w0", "w1", "layout", "noise", "cursor", "pos_est", "vel_est", "t", "next_prediction", "due",
    "field_on", "turb", "mocap_offset", "rot_des", "yaw_rate_des", "thrust_acc", "mass_believed", "active", "f_hat",
    "rot", "rot_est", "pred", "sensor"])
Sensing = namedtuple("Sensing", ["fn", "params", "state"])  # a sensor's compiled law: addresses (state: at w0)
Vehicles = namedtuple("Vehicles", ["ap_gain", "max_thrust", "mass", "field_scale", "Kt", "field_packed", "field_fn",
                                   "field_params", "field_fn_scale"])
PhysicsArrays = namedtuple("PhysicsArrays", ["qpos", "qvel", "ctrl", "xfrc"])
Inputs = namedtuple("Inputs", ["ref_pos", "ref_vel", "ref_acc", "ref_yaw", "ref_yaw_rate", "residual", "override",
                               "u_cmd"])
Buffers = namedtuple("Buffers", ["kin", "quat", "quat_est", "yaw", "applied", "mean"])
Wind = namedtuple("Wind", ["air", "wind_acc", "vel_air", "gust", "noise", "mean", "sigma", "length", "axes",
                           "drag_gain"])
Prediction = namedtuple("Prediction", [
    "kind", "fn", "params", "iparams", "oracle_packed", "pw_code", "pw_fn", "pw_params", "pw_iparams", "pw_oracle",
    "pw_guard_fn", "pw_guard_params", "pw_guard_iparams", "pw_guard_state", "pw_guard_applied", "guard", "guard_fn",
    "guard_params", "guard_iparams", "guard_state", "guard_applied", "oracle_fn", "oracle_params", "oracle_scale"])
Control = namedtuple("Control", [
    "fn", "params", "state", "safety_fn", "safety_params", "safety_lower", "safety_upper", "safety_state", "guard",
    "guard_applied", "pw_guarded", "pw_guard_applied", "row_t", "row_ref_pos", "row_ref_vel", "row_ref_acc",
    "row_f_hat", "row_guard"])
Stepping = namedtuple("Stepping", [
    "mode", "n_physics", "step_fn", "set_state_fn", "get_state_fn", "model", "data", "states", "state_spec",
    "batch_warnings", "warnings", "warning_stride"])
Monitor = namedtuple("Monitor", [
    "diverged", "tick_index", "status_new", "radius_xy", "radius_z", "fn", "params", "iparams", "guard_state",
    "seen", "seen_t", "row_t", "row_vel_est", "row_u_cmd"])


# ----------------------------------------------------------------------------- helpers


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


@njit
def _f64(address, shape, w0, w1):
    """Worlds w0..w1-1 of the float64 array at `address`, of shape (n_worlds, ...) = shape. (An address, not
    a table slot: a constant slot would compile one version per slot.)"""
    return carray(f64p(address), shape)[w0:w1]


@njit
def _i64(address, n, w0, w1):
    """Worlds w0..w1-1 of the int64 array (n,) at `address`."""
    return carray(i64p(address), (n,))[w0:w1]


# ----------------------------------------------------------------------------- the bundles (the table, read once)


@njit_inline
def world_bundle(tab, w0, w1):
    n, V = tab[T_W], tab[T_V]
    return World(
        n, V, w0, w1, carray(i64p(tab[T_LAYOUT]), (V, 7)), _f64(tab[T_NOISE], (n, tab[T_BLOCK], V, 9), w0, w1),
        carray(i64p(tab[T_CURSOR]), (n,))[w0:w1], _f64(tab[T_POS_EST], (n, V, 3), w0, w1),
        _f64(tab[T_VEL_EST], (n, V, 3), w0, w1), _f64(tab[T_T], (n,), w0, w1), _f64(tab[T_NEXT_PRED], (n,), w0, w1),
        carray(boolp(tab[T_DUE]), (n,))[w0:w1], carray(boolp(tab[T_FIELD_ON]), (n,))[w0:w1],
        _f64(tab[T_TURB], (n, V, 3), w0, w1), _f64(tab[T_MOCAP_OFFSET], (n, V, 3), w0, w1),
        _f64(tab[T_ROT_DES], (n, V, 3, 3), w0, w1), _f64(tab[T_YAW_RATE_DES], (n, V), w0, w1),
        _f64(tab[T_THRUST], (n, V), w0, w1), _f64(tab[T_MASS_BELIEVED], (n, V), w0, w1),
        carray(boolp(tab[T_ACTIVE]), (n,))[w0:w1], _f64(tab[T_F_HAT], (n, V, 3), w0, w1),
        _f64(tab[T_ROT], (n, V, 3, 3), w0, w1), _f64(tab[T_ROT_EST], (n, V, 3, 3), w0, w1),
        _f64(tab[T_PRED_OUT], (n, V, 3), w0, w1),
        Sensing(tab[T_SENSOR_FN], tab[T_SENSOR_PARAMS], tab[T_SENSOR_STATE] + 8 * V * tab[T_SENSOR_WIDTH] * w0))


@njit_inline
def vehicles_bundle(tab):
    V = tab[T_V]
    return Vehicles(carray(f64p(tab[T_AP_GAIN]), (V, 14, 4)), carray(f64p(tab[T_MAX_THRUST]), (V,)),
                    carray(f64p(tab[T_MASS]), (V,)), carray(f64p(tab[T_FIELD_SCALE]), (V, V)),
                    carray(f64p(tab[T_KT]), (7, 4)), carray(f64p(tab[T_FIELD_PACKED]), (16,)), tab[T_FIELD_FN],
                    tab[T_FIELD_PARAMS], tab[T_FIELD_FN_SCALE])


@njit_inline
def inputs_bundle(tab, row, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, residual, override, w0, w1):
    n, V = tab[T_W], tab[T_V]
    u_cmd = _row_view(row, tab[T_ROW_U_CMD], n, V * 3, w0, w1).reshape((w1 - w0, V, 3))
    return Inputs(ref_pos[w0:w1], ref_vel[w0:w1], ref_acc[w0:w1], ref_yaw[w0:w1], ref_yaw_rate[w0:w1],
                  residual[w0:w1], override[w0:w1], u_cmd)


@njit_inline
def buffers_bundle(tab, row, first, w0, w1):
    """The sub-tick's kinematics and forces: the log row's fields on the first autopilot tick (which writes
    the row, and its time), the plan's scratch buffers on the later ones."""
    n, V = tab[T_W], tab[T_V]
    W, V3 = w1 - w0, V * 3
    if first:
        kin = row[tab[T_ROW_KIN]:tab[T_ROW_KIN] + 5 * n * V3].reshape((5, n, V, 3))[:, w0:w1]
        quat = _row_view(row, tab[T_ROW_QUAT], n, V * 4, w0, w1).reshape((W, V, 4))
        quat_est = _row_view(row, tab[T_ROW_QUAT_EST], n, V * 4, w0, w1).reshape((W, V, 4))
        yaw = _row_view(row, tab[T_ROW_YAW], n, V, w0, w1)
        applied = _row_view(row, tab[T_ROW_APPLIED], n, V3, w0, w1).reshape((W, V, 3))
        mean = _row_view(row, tab[T_ROW_MEAN], n, V3, w0, w1).reshape((W, V, 3))
    else:
        kin = carray(f64p(tab[T_KIN]), (5, n, V, 3))[:, w0:w1]
        quat = _f64(tab[T_QUAT], (n, V, 4), w0, w1)
        quat_est = _f64(tab[T_QUAT_EST], (n, V, 4), w0, w1)
        yaw = _f64(tab[T_YAW], (n, V), w0, w1)
        applied = _f64(tab[T_APPLIED], (n, V, 3), w0, w1)
        mean = _f64(tab[T_MEAN], (n, V, 3), w0, w1)
    return Buffers(kin, quat, quat_est, yaw, applied, mean)


@njit_inline
def wind_bundle(tab, row, first, w0, w1):
    n, V = tab[T_W], tab[T_V]
    W, V3 = w1 - w0, V * 3
    if first:
        air = _row_view(row, tab[T_ROW_WIND], n, V3, w0, w1).reshape((W, V, 3))
        wind_acc = _row_view(row, tab[T_ROW_WIND_ACC], n, V3, w0, w1).reshape((W, V, 3))
    else:
        air = _f64(tab[T_AIR], (n, V, 3), w0, w1)
        wind_acc = _f64(tab[T_WIND_ACC], (n, V, 3), w0, w1)
    return Wind(air, wind_acc, _f64(tab[T_VEL_AIR], (n, V, 3), w0, w1), _f64(tab[T_GUST], (n, 3, 2), w0, w1),
                _f64(tab[T_WIND_NOISE], (n, tab[T_BLOCK], 3, 2), w0, w1), carray(f64p(tab[T_WIND_MEAN]), (3,)),
                carray(f64p(tab[T_WIND_SIGMA]), (3,)), carray(f64p(tab[T_WIND_LENGTH]), (3,)),
                carray(f64p(tab[T_WIND_AXES]), (3, 3)), carray(f64p(tab[T_DRAG_GAIN]), (V,)))


@njit_inline
def prediction_bundle(tab, w0, w1):
    n = tab[T_W]
    return Prediction(
        tab[T_PRED], tab[T_PRED_FN], tab[T_PRED_PARAMS], tab[T_PRED_IPARAMS],
        carray(f64p(tab[T_ORACLE_PACKED]), (16,)), _i64(tab[T_PW_CODE], n, w0, w1), _i64(tab[T_PW_FN], n, w0, w1),
        _i64(tab[T_PW_PARAMS], n, w0, w1), _i64(tab[T_PW_IPARAMS], n, w0, w1),
        _f64(tab[T_PW_ORACLE], (n, 16), w0, w1), _i64(tab[T_PW_GUARD_FN], n, w0, w1),
        _i64(tab[T_PW_GUARD_PARAMS], n, w0, w1), _i64(tab[T_PW_GUARD_IPARAMS], n, w0, w1),
        _i64(tab[T_PW_GUARD_STATE], n, w0, w1), _i64(tab[T_PW_GUARD_APPLIED], n, w0, w1), tab[T_GUARD],
        tab[T_GUARD_FN], tab[T_GUARD_PARAMS], tab[T_GUARD_IPARAMS],
        tab[T_GUARD_STATE] + 8 * tab[T_V] * GUARD_STATE_WIDTH * w0, tab[T_GUARD_APPLIED] + 8 * tab[T_V] * w0,
        tab[T_ORACLE_FN], tab[T_ORACLE_PARAMS], tab[T_FIELD_FN_SCALE])


@njit_inline
def control_bundle(tab, w0, w1):
    n, V = tab[T_W], tab[T_V]
    return Control(
        tab[T_CONTROLLER_FN], tab[T_CONTROLLER_PARAMS],
        tab[T_CONTROLLER_STATE] + 8 * V * tab[T_CONTROLLER_WIDTH] * w0, tab[T_SAFETY_FN], tab[T_SAFETY_PARAMS],
        tab[T_SAFETY_LOWER], tab[T_SAFETY_UPPER], tab[T_SAFETY_STATE] + 8 * V * _SAFETY_STATE_WIDTH * w0,
        tab[T_GUARD], _f64(tab[T_GUARD_APPLIED], (n, V, 1), w0, w1), tab[T_PW_GUARDED],
        _i64(tab[T_PW_GUARD_APPLIED], n, w0, w1), tab[T_ROW_T], tab[T_ROW_REF_POS],
        tab[T_ROW_REF_VEL], tab[T_ROW_REF_ACC], tab[T_ROW_F_HAT], tab[T_ROW_GUARD])


@njit_inline
def stepping_bundle(tab):
    n = tab[T_W]
    warnings_size = FATAL_MAX * tab[T_WARNING_STRIDE] + 1
    return Stepping(
        tab[T_STEPPING], tab[T_NPHYS], tab[T_STEP_FN], tab[T_SET_STATE_FN], tab[T_GET_STATE_FN], tab[T_MODEL],
        tab[T_DATA], carray(f64p(tab[T_STATE]), (n, tab[T_NSTATE])), tab[T_STATE_SPEC],
        carray(i32p(tab[T_BATCH_WARNINGS]), (n, tab[T_NWARNINGS], 2)),
        carray(i32p(tab[T_WARNINGS]), (warnings_size,)), tab[T_WARNING_STRIDE])


@njit_inline
def monitor_bundle(tab, w0, w1):
    n, V = tab[T_W], tab[T_V]
    V3 = 3 * V
    return Monitor(
        carray(boolp(tab[T_DIVERGED]), (n,))[w0:w1], carray(i64p(tab[T_TICK_INDEX]), (n,))[w0:w1],
        carray(i64p(tab[T_STATUS_NEW]), (n,))[w0:w1], carray(f64p(tab[T_RADIUS_XY]), (V, V)),
        carray(f64p(tab[T_RADIUS_Z]), (V, V)), tab[T_MONITOR_FN], tab[T_MONITOR_PARAMS],
        tab[T_MONITOR_IPARAMS], tab[T_GUARD_STATE] + 8 * V * GUARD_STATE_WIDTH * w0,
        tab[T_SEEN] + tab[T_SEEN_STRIDE] * w0, tab[T_SEEN_T] + 8 * w0, tab[T_ROW_T] + w0,
        tab[T_ROW_KIN] + 4 * n * V3 + V3 * w0, tab[T_ROW_U_CMD] + V3 * w0)


# ----------------------------------------------------------------------------- the stages


@njit_inline
def sense_stage(fc, world, physics, buf):
    """Motion capture and the Kalman filter (`sim.passes.sense_kernel`, or `sense_law_kernel` with a sensor's
    compiled law, `sim.sensor_contract`); returns how many worlds' prediction is due."""
    s = world.sensor
    if s.fn != 0:
        return sense_law_kernel(
            physics.qpos, physics.qvel, world.layout, world.noise, world.cursor, s.fn, s.params, s.state,
            world.mocap_offset, fc[F_KF_P], fc[F_KF_V], world.pos_est, world.vel_est, world.t, world.next_prediction,
            world.due, buf.kin, buf.quat, world.rot, buf.quat_est, world.rot_est, buf.yaw,
        )
    return sense_kernel(
        physics.qpos, physics.qvel, world.layout, world.noise, world.cursor, fc[F_SIGMA_P], fc[F_SIGMA_ATT],
        world.mocap_offset, fc[F_KF_P], fc[F_KF_V], world.pos_est, world.vel_est, world.t, world.next_prediction,
        world.due, buf.kin, buf.quat, world.rot, buf.quat_est, world.rot_est, buf.yaw,
    )


@njit_inline
def wind_stage(fc, world, wind, buf):
    """The gusts felt (the air's velocity and the drag) and advanced; returns the velocities relative to the air."""
    vel = buf.kin[1]
    wind_sense_kernel(wind.gust, wind.axes, wind.mean, wind.drag_gain, vel, wind.air, wind.vel_air, wind.wind_acc)
    wind_advance_kernel(wind.gust, wind.noise, world.cursor, vel, fc[F_DT], wind.mean, wind.sigma, wind.length,
                         fc[F_MIN_AIRSPEED], np.empty((3, 2, 2)), np.empty((3, 2, 2)))
    return wind.vel_air


@njit
def _predict_world(p, vehicles, buf, vel_air, world, w):
    """World w of a `PerWorldPredictor`: its own predictor, and its guard's pass over the prediction."""
    pos, rot, pred, kin, V = buf.kin[0], world.rot, world.pred, buf.kin, world.V
    code = p.pw_code[w]
    if code == PRED_ORACLE:
        _copy_into(pred[w:w + 1], pairwise_kernel(pos[w:w + 1], vel_air[w:w + 1], rot[w:w + 1], p.pw_oracle[w],
                                                   vehicles.field_scale))
    elif code == PRED_C:  # one world: its rows of C-contiguous (W, ...) arrays
        call_predictor(p.pw_fn[w], 1, V, kin[3][w].ctypes.data, kin[4][w].ctypes.data, world.rot_est[w].ctypes.data,
                        pos[w].ctypes.data, vel_air[w].ctypes.data, rot[w].ctypes.data, p.pw_params[w],
                        p.pw_iparams[w], pred[w].ctypes.data)
        if p.pw_guard_fn[w] != 0:  # its guard's pass, on the world's rows of the guard's state
            call_predictor(p.pw_guard_fn[w], 1, V, kin[3][w].ctypes.data, kin[4][w].ctypes.data,
                            world.rot_est[w].ctypes.data, world.due.ctypes.data + w, pred[w].ctypes.data,
                            p.pw_guard_state[w], p.pw_guard_applied[w], p.pw_guard_params[w], p.pw_guard_iparams[w])
    else:
        for i in range(V):
            for k in range(3):
                pred[w, i, k] = 0.0


@njit_inline
def predict_stage(fc, p, vehicles, world, buf, vel_air):
    """The predictor at its rate (due worlds), the guard's pass over it, then the hold into f_hat."""
    pos, rot, pred, kin = buf.kin[0], world.rot, world.pred, buf.kin
    W = world.w1 - world.w0
    if p.kind == PRED_ZERO:
        pred[:] = 0.0
    elif p.kind == PRED_ORACLE and p.oracle_fn != 0:  # a field's compiled form (sim.field_contract)
        call_field(p.oracle_fn, W, world.V, pos.ctypes.data, vel_air.ctypes.data, rot.ctypes.data, p.oracle_scale,
                   p.oracle_params, pred.ctypes.data)
    elif p.kind == PRED_ORACLE:
        _copy_into(pred, pairwise_kernel(pos, vel_air, rot, p.oracle_packed, vehicles.field_scale))
    elif p.kind == PRED_PER_WORLD:  # world by world, each its own predictor, as PerWorldPredictor
        for w in range(W):
            _predict_world(p, vehicles, buf, vel_air, world, w)
    else:  # every array here is a block of whole worlds of a C-contiguous (W, ...) array
        call_predictor(p.fn, W, world.V, kin[3].ctypes.data, kin[4].ctypes.data, world.rot_est.ctypes.data,
                        pos.ctypes.data, vel_air.ctypes.data, rot.ctypes.data, p.params, p.iparams, pred.ctypes.data)
    if p.guard:  # the guard's pass over the prediction (sim.predictor.CompiledGuard; a GUARD_SIGNATURE has the
        call_predictor(  # PREDICTOR_SIGNATURE's argument types)
            p.guard_fn, W, world.V, kin[3].ctypes.data, kin[4].ctypes.data, world.rot_est.ctypes.data,
            world.due.ctypes.data, pred.ctypes.data, p.guard_state, p.guard_applied, p.guard_params, p.guard_iparams,
        )
    hold_kernel(world.f_hat, pred, world.due, world.next_prediction, fc[F_PRED_PERIOD])


@njit_inline
def field_stage(vehicles, world, buf, vel_air):
    """The ground-truth wakes: every pair's mean push into buf.mean, the paper field's (`sim.field_kernels.pairwise_kernel`)
    or a field's compiled form's (`sim.field_contract`: its C function, on these worlds' C-contiguous rows)."""
    if vehicles.field_fn != 0:
        call_field(vehicles.field_fn, world.w1 - world.w0, world.V, buf.kin[0].ctypes.data, vel_air.ctypes.data,
                   world.rot.ctypes.data, vehicles.field_fn_scale, vehicles.field_params, buf.mean.ctypes.data)
    else:
        _copy_into(buf.mean, pairwise_kernel(buf.kin[0], vel_air, world.rot, vehicles.field_packed,
                                              vehicles.field_scale))


@njit_inline
def control_stage(fc, c, vehicles, world, buf, inputs, row, actions):
    """The controller (the LQR's kernel or a compiled form, `controllers.compiled`), the safety filter, and the
    tick's fields of the row (time, reference, f_hat, the guard's applied fraction)."""
    W, V, n, w0, w1 = world.w1 - world.w0, world.V, world.n_worlds, world.w0, world.w1
    kin, f_hat, u_cmd = buf.kin, world.f_hat, inputs.u_cmd
    for w in range(W):
        row[c.row_t + w0 + w] = world.t[w]
    _copy_into(_row_view(row, c.row_ref_pos, n, 3 * V, w0, w1).reshape((W, V, 3)), inputs.ref_pos)
    _copy_into(_row_view(row, c.row_ref_vel, n, 3 * V, w0, w1).reshape((W, V, 3)), inputs.ref_vel)
    _copy_into(_row_view(row, c.row_ref_acc, n, 3 * V, w0, w1).reshape((W, V, 3)), inputs.ref_acc)
    state = (kin[3], kin[4], buf.yaw, inputs.ref_pos, inputs.ref_vel, inputs.ref_acc, inputs.ref_yaw,
             inputs.ref_yaw_rate, f_hat)
    limits = (vehicles.Kt, fc[F_LOOKAHEAD], fc[F_TAN_TILT], fc[F_MIN_VERTICAL], u_cmd, world.yaw_rate_des,
              world.thrust_acc, world.rot_des)
    if c.fn != 0:  # a controller's compiled form (controllers.compiled)
        flags = np.empty(2, np.int64)
        flags[0], flags[1] = actions & 1, (actions >> 1) & 1
        call_controller(
            c.fn, W, V, kin[3].ctypes.data, kin[4].ctypes.data, buf.yaw.ctypes.data, inputs.ref_pos.ctypes.data,
            inputs.ref_vel.ctypes.data, inputs.ref_acc.ctypes.data, inputs.ref_yaw.ctypes.data,
            inputs.ref_yaw_rate.ctypes.data, f_hat.ctypes.data, inputs.residual.ctypes.data,
            inputs.override.ctypes.data, flags.ctypes.data, fc.ctypes.data + 8 * F_LOOKAHEAD, c.state, c.params,
            u_cmd.ctypes.data, world.yaw_rate_des.ctypes.data, world.thrust_acc.ctypes.data,
            world.rot_des.ctypes.data,
        )
    else:
        command_setpoint_kernel(*state, inputs.residual, inputs.override, (actions & 1) != 0, (actions & 2) != 0,
                                 *limits)
    if c.safety_fn != 0:  # the CBF filter (sim.safety.SAFETY_SIGNATURE), then the LQR's step again
        counts = np.zeros(2, np.int64)  # with the filtered command as override, as the readable path
        call_predictor(c.safety_fn, W, V, kin[3].ctypes.data, kin[4].ctypes.data, f_hat.ctypes.data,
                        u_cmd.ctypes.data, c.safety_params, c.safety_lower, c.safety_upper, counts.ctypes.data,
                        c.safety_state)  # the chunk's rows of its estimates
        if counts[0] != 0:
            no, yes = actions < 0, actions >= 0  # (False, True, not literals: the call's types as above)
            command_setpoint_kernel(*state, inputs.residual, u_cmd, no, yes, *limits)
    _copy_into(_row_view(row, c.row_f_hat, n, 3 * V, w0, w1).reshape((W, V, 3)), f_hat)
    if c.guard:
        _copy_into(_row_view(row, c.row_guard, n, V, w0, w1).reshape((W, V, 1)), c.guard_applied)
    elif c.pw_guarded:  # each guard's worlds its applied fraction, NaN in the others
        applied_row = _row_view(row, c.row_guard, n, V, w0, w1)
        for w in range(W):
            for i in range(V):
                applied_row[w, i] = (carray(f64p(c.pw_guard_applied[w]), (V,))[i] if c.pw_guard_applied[w] != 0
                                     else np.nan)


@njit_inline
def actuate_stage(fc, vehicles, world, physics, buf, u_cmd):
    """The autopilot, the mixer and the forces: rotors, the wakes' and turbulence's pushes (`actuate_kernel`)."""
    actuate_kernel(
        world.field_on, world.noise, world.cursor, world.turb, fc[F_OU_A], fc[F_OU_B], fc[F_INTENSITY],
        vehicles.mass, physics.xfrc, world.layout, physics.qvel, world.rot_des, world.yaw_rate_des,
        world.thrust_acc, world.mass_believed, vehicles.ap_gain, vehicles.max_thrust, physics.ctrl,
        world.pos_est, world.vel_est, fc[F_DT], world.t, world.active, buf.mean, buf.applied, world.rot, u_cmd,
    )


@njit_inline
def wind_force_stage(vehicles, world, physics, wind):
    """The gusts' drag, added to the forces."""
    wind_force_kernel(physics.xfrc, world.layout, vehicles.mass, wind.wind_acc)


@njit_inline
def physics_stage(s, world, chunk):
    """The physics' steps of one autopilot tick: mj_step on the single world's MjData, or each world's state
    row stepped in this thread's scratch MjData (`_step_rows`); nothing when the caller steps it."""
    if s.mode == STEP_SERIAL:
        if world.active[0]:
            for _ in range(s.n_physics):
                call_mj_step(s.step_fn, s.model, s.data)
    elif s.mode == STEP_ROWS:
        _step_rows(s, world.active, world.w0, world.w1, chunk[2], chunk[3])


@njit
def _step_rows(s, active, w0, w1, data, data_warnings):
    """Step worlds w0..w1-1 (active (w1 - w0,)) as mujoco.batch.Batch.step does: each world's state
    row loaded into the scratch MjData `data`, n_physics mj_step, the row saved back; the
    MjData's warnings (mjNWARNING, 2) [last info, count] at data_warnings are cleared before
    and added to the world's (the batch's `warning`) after."""
    n_warn = s.batch_warnings.shape[1]
    scratch = carray(i32p(data_warnings), (n_warn, 2))
    for w in range(w1 - w0):
        if not active[w]:
            continue
        row = s.states[w0 + w]
        for i in range(n_warn):
            scratch[i, 0] = 0
            scratch[i, 1] = 0
        call_state(s.set_state_fn, s.model, data, row.ctypes.data, s.state_spec)
        for _ in range(s.n_physics):
            call_mj_step(s.step_fn, s.model, data)
        call_state(s.get_state_fn, s.model, data, row.ctypes.data, s.state_spec)
        for i in range(n_warn):
            if scratch[i, 1] > 0:
                s.batch_warnings[w0 + w, i, 0] = scratch[i, 0]
                s.batch_warnings[w0 + w, i, 1] += scratch[i, 1]


@njit_inline
def monitor_stage(fc, s, m, world, physics, row):
    """The end of a complete tick: which worlds diverged (MuJoCo's fatal warnings), the status pass (ground,
    distance, collisions); then the guard's monitor on the row (its observe). Returns how many worlds ended."""
    W = world.w1 - world.w0
    if s.mode == STEP_SERIAL:  # MuJoCo's warning counts: int32, every warning_stride-th one
        step = s.warning_stride
        m.diverged[0] = s.warnings[FATAL_0 * step] > 0 or s.warnings[FATAL_1 * step] > 0 or \
            s.warnings[FATAL_2 * step] > 0
    else:
        for w in range(W):  # as sim.physics._mark_fatal: counts since the world's reset
            c = s.batch_warnings[world.w0 + w]
            m.diverged[w] = c[FATAL_0, 1] > 0 or c[FATAL_1, 1] > 0 or c[FATAL_2, 1] > 0
    ended = status_kernel(physics.qpos, world.layout, physics.qvel, m.diverged, world.active, m.tick_index,
                           fc[F_MAX_DISTANCE], fc[F_GROUND], m.radius_xy, m.radius_z, m.status_new)
    if m.fn != 0:  # the guard's monitor on these worlds' row: t, vel_est (the row's kin block, slot 4) and u_cmd
        base = row.ctypes.data
        call_monitor(m.fn, W, world.V, base + 8 * m.row_t, base + 8 * m.row_vel_est, base + 8 * m.row_u_cmd,
                      m.guard_state, m.seen, m.seen_t, m.params, m.iparams)
    return ended
