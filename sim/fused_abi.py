"""The fused tick's interface with Python: the layouts of its two tables and the intrinsics that turn
their addresses into typed arrays and C calls.

Per call the kernel (`sim.fused`) gets two tables instead of some hundred arguments (numba checks
each argument's type on every call, ~0.15 us each): `tab` (int64: sizes, codes, buffer addresses,
row offsets; its entries are named by `TAB` and indexed by the `_T_*` constants) and `fc` (float64
constants, `FC` and `_F_*`). `sim.plan.Plan` fills them and keeps every addressed array alive;
`sim.tick_stages` reads them once per chunk of worlds into typed bundles, the only place that does.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic

from sim.physics import FATAL_0, FATAL_1, FATAL_2

# Raw addresses into typed pointers, and calls of C functions by address, for the fused
# kernel. Every address comes from an array or object that the `Plan` keeps alive.


def _pointer_intrinsic(dtype: types.Type):
    """A compiled function: an integer address -> a typed pointer (`carray` reads it as an array)."""

    @intrinsic
    def pointer(typingctx, addr):
        sig = types.CPointer(dtype)(types.intp)
        return sig, lambda context, builder, sig, args: builder.inttoptr(args[0], context.get_value_type(sig.return_type))

    return pointer


f64p, i64p, i32p, boolp = (_pointer_intrinsic(t) for t in (types.float64, types.int64, types.int32, types.boolean))


_VOIDP = ir.IntType(8).as_pointer()
FATAL_MAX = max(FATAL_0, FATAL_1, FATAL_2)


@intrinsic
def call_mj_step(typingctx, fn, model, data):
    """mj_step(model, data) through the function address fn (`sim.physics.mj_step_address`)."""
    sig = types.void(types.intp, types.intp, types.intp)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [_VOIDP, _VOIDP])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(args[1], _VOIDP), builder.inttoptr(args[2], _VOIDP)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def call_state(typingctx, fn, model, data, state, spec):
    """mj_setState / mj_getState(model, data, state, spec) through the function address fn."""
    sig = types.void(types.intp, types.intp, types.intp, types.intp, types.int64)

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [_VOIDP, _VOIDP, _VOIDP, i32])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [builder.inttoptr(a, _VOIDP) for a in args[1:4]] + [builder.trunc(args[4], i32)])
        return context.get_dummy_value()

    return sig, codegen


def _call_codegen(n_pointers: int):
    """The code of a call of a C function at an address: (n_worlds, n_vehicles, n_pointers addresses)."""

    def codegen(context, builder, signature, args):
        i64 = ir.IntType(64)
        fnty = ir.FunctionType(ir.VoidType(), [i64, i64] + [_VOIDP] * n_pointers)
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [args[1], args[2]] + [builder.inttoptr(a, _VOIDP) for a in args[3:]])
        return context.get_dummy_value()

    return codegen


@intrinsic
def call_predictor(typingctx, fn, n_worlds, n_veh, pos, vel, rot, true_pos, true_vel, true_rot, params, iparams, out):
    """A `sim.predictor.PREDICTOR_SIGNATURE` function at address fn; the array arguments are addresses."""
    return types.void(types.intp, types.int64, types.int64, *(types.intp,) * 9), _call_codegen(9)


@intrinsic
def call_controller(typingctx, fn, n_worlds, n_veh, pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat,
                     residual, override, flags, lookahead, state, params, acc, yaw_rate, thrust, rot):
    """A `controllers.compiled.CONTROLLER_SIGNATURE` function at address fn; the array arguments are addresses."""
    return types.void(types.intp, types.int64, types.int64, *(types.intp,) * 19), _call_codegen(19)


@intrinsic
def call_field(typingctx, fn, n_worlds, n_veh, pos, vel, rot, scale, params, out):
    """A `sim.field_contract.FIELD_SIGNATURE` function at address fn; the array arguments are addresses."""
    return types.void(types.intp, types.int64, types.int64, *(types.intp,) * 6), _call_codegen(6)


@intrinsic
def call_monitor(typingctx, fn, n_worlds, n_veh, t, vel, u, state, seen, seen_t, params, iparams):
    """A `sim.predictor.MONITOR_SIGNATURE` function at address fn; the array arguments are addresses."""
    return types.void(types.intp, types.int64, types.int64, *(types.intp,) * 8), _call_codegen(8)


@intrinsic
def call_sensor(typingctx, fn, n_worlds, n_veh, pos, quat, normals, offset, state, params, m_pos, m_quat):
    """A `sim.sensor_contract.SENSOR_SIGNATURE` function at address fn; the array arguments are addresses."""
    return types.void(types.intp, types.int64, types.int64, *(types.intp,) * 8), _call_codegen(8)


# How the fused kernel's physics steps: the caller steps it (a batch with models of its
# own per world), mj_step on the single world's MjData, or each world's state row loaded
# into a scratch MjData of its thread, stepped and saved (as mujoco.batch does).
STEP_CALLER, STEP_SERIAL, STEP_ROWS = 0, 1, 2

# The plan's integer table `tab` (int64): sizes, codes, addresses and row offsets, in this order.
TAB = (
    "W", "V", "block", "n_sub", "n_physics", "stepping", "step_fn", "set_state_fn", "get_state_fn", "model",
    "data", "warnings", "warning_stride", "state", "nstate", "state_spec", "batch_warnings", "n_warnings",
    "predictor", "predictor_fn", "predictor_params", "predictor_iparams",
    "layout", "noise", "cursor", "pos_est", "vel_est", "t", "next_prediction", "due", "field_enabled", "turb",
    "rot_des", "yaw_rate_des", "thrust_acc", "mass_believed", "ap_gain", "active", "f_hat", "tick_index",
    "status_new", "kin", "quat", "rot", "quat_est", "rot_est", "yaw", "applied", "mean", "pred", "Kt",
    "field_packed", "oracle_packed", "gust", "wind_noise", "wind_mean", "wind_sigma", "wind_length", "wind_axes",
    "air", "vel_air", "wind_acc", "diverged", "pw_code", "pw_fn", "pw_params", "pw_iparams", "pw_oracle",
    "mocap_offset", "max_thrust", "mass", "drag_gain", "field_scale", "radius_xy", "radius_z",
    "row_kin", "row_t", "row_quat", "row_quat_est", "row_yaw", "row_applied", "row_ref_pos", "row_ref_vel",
    "row_ref_acc", "row_u_cmd", "row_f_hat", "row_mean", "row_wind", "row_wind_acc",
    "guard", "guard_fn", "guard_params", "guard_iparams", "guard_state", "guard_applied", "row_guard",
    "pw_guard_fn", "pw_guard_params", "pw_guard_iparams", "pw_guard_state", "pw_guard_applied", "pw_guarded",
    "monitor_fn", "monitor_params", "monitor_iparams", "seen", "seen_stride", "seen_t",
    "safety_fn", "safety_params", "safety_lower", "safety_upper", "safety_state",
    "controller_fn", "controller_params", "controller_state", "controller_width",
    "field_fn", "field_params", "field_fn_scale", "oracle_fn", "oracle_params",
    "sensor_fn", "sensor_params", "sensor_state", "sensor_width",
)
(T_W, T_V, T_BLOCK, T_NSUB, T_NPHYS, T_STEPPING, T_STEP_FN, T_SET_STATE_FN, T_GET_STATE_FN, T_MODEL,
 T_DATA, T_WARNINGS, T_WARNING_STRIDE, T_STATE, T_NSTATE, T_STATE_SPEC, T_BATCH_WARNINGS, T_NWARNINGS,
 T_PRED, T_PRED_FN, T_PRED_PARAMS, T_PRED_IPARAMS,
 T_LAYOUT, T_NOISE, T_CURSOR, T_POS_EST, T_VEL_EST, T_T, T_NEXT_PRED, T_DUE, T_FIELD_ON, T_TURB,
 T_ROT_DES, T_YAW_RATE_DES, T_THRUST, T_MASS_BELIEVED, T_AP_GAIN, T_ACTIVE, T_F_HAT, T_TICK_INDEX,
 T_STATUS_NEW, T_KIN, T_QUAT, T_ROT, T_QUAT_EST, T_ROT_EST, T_YAW, T_APPLIED, T_MEAN, T_PRED_OUT, T_KT,
 T_FIELD_PACKED, T_ORACLE_PACKED, T_GUST, T_WIND_NOISE, T_WIND_MEAN, T_WIND_SIGMA, T_WIND_LENGTH,
 T_WIND_AXES, T_AIR, T_VEL_AIR, T_WIND_ACC, T_DIVERGED, T_PW_CODE, T_PW_FN, T_PW_PARAMS, T_PW_IPARAMS,
 T_PW_ORACLE, T_MOCAP_OFFSET, T_MAX_THRUST, T_MASS, T_DRAG_GAIN, T_FIELD_SCALE, T_RADIUS_XY, T_RADIUS_Z,
 T_ROW_KIN, T_ROW_T, T_ROW_QUAT, T_ROW_QUAT_EST, T_ROW_YAW, T_ROW_APPLIED, T_ROW_REF_POS, T_ROW_REF_VEL,
 T_ROW_REF_ACC, T_ROW_U_CMD, T_ROW_F_HAT, T_ROW_MEAN, T_ROW_WIND, T_ROW_WIND_ACC,
 T_GUARD, T_GUARD_FN, T_GUARD_PARAMS, T_GUARD_IPARAMS, T_GUARD_STATE, T_GUARD_APPLIED,
 T_ROW_GUARD, T_PW_GUARD_FN, T_PW_GUARD_PARAMS, T_PW_GUARD_IPARAMS, T_PW_GUARD_STATE, T_PW_GUARD_APPLIED,
 T_PW_GUARDED, T_MONITOR_FN, T_MONITOR_PARAMS, T_MONITOR_IPARAMS, T_SEEN, T_SEEN_STRIDE, T_SEEN_T,
 T_SAFETY_FN, T_SAFETY_PARAMS, T_SAFETY_LOWER, T_SAFETY_UPPER, T_SAFETY_STATE,
 T_CONTROLLER_FN, T_CONTROLLER_PARAMS, T_CONTROLLER_STATE, T_CONTROLLER_WIDTH,
 T_FIELD_FN, T_FIELD_PARAMS, T_FIELD_FN_SCALE, T_ORACLE_FN, T_ORACLE_PARAMS,
 T_SENSOR_FN, T_SENSOR_PARAMS, T_SENSOR_STATE, T_SENSOR_WIDTH) = range(len(TAB))
# The plan's float table `fc` (float64), in this order.
# (Each vehicle's numbers are arrays of `tab`: mass, drag_gain, ap_gain, max_thrust (V, ...), and the
# pairs' field_scale, radius_xy, radius_z (V, V): `sim.vehicle_params`.)
FC = (
    "sigma_p", "sigma_att", "kf_gain_p", "kf_gain_v", "ou_a", "ou_b", "intensity", "dt",
    "prediction_period", "lookahead", "tan_tilt", "min_vertical", "min_airspeed", "max_distance", "ground",
)
(F_SIGMA_P, F_SIGMA_ATT, F_KF_P, F_KF_V, F_OU_A, F_OU_B, F_INTENSITY, F_DT,
 F_PRED_PERIOD, F_LOOKAHEAD, F_TAN_TILT, F_MIN_VERTICAL, F_MIN_AIRSPEED, F_MAX_DISTANCE, F_GROUND) = range(len(FC))
# predictor codes: zero, oracle (field kernel), C function, and one of these per world (`PerWorldPredictor`)
PRED_ZERO, PRED_ORACLE, PRED_C, PRED_PER_WORLD = 0, 1, 2, 3
