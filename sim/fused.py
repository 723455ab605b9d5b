"""The fused tick: a whole controller tick of the loop as ONE compiled call.

The fast path of `sim.simulator.Simulator` (`fast=True`, the default, taken when every
component has a compiled form: see `sim.plan._make_plan`) runs each controller tick
through `_fused_kernel` (made by `_make_fused_kernel`; one variant with and one without
the wind passes, `_FUSED_KERNELS`). It calls the same passes as the readable path
(`sim.passes`), the field kernel (`sim.field._pairwise_kernel`), the LQR
(`controllers.lqr._command_setpoint_kernel`), the predictor's and the safety filter's C functions, and steps
the physics itself: `mj_step` on a single world's MjData (`sim.physics.mj_step_address`),
or, for a `mujoco.batch.Batch`, each world's state row loaded into a scratch MjData,
stepped and saved, as the batch does it (`_step_rows`, `_BatchPhysics.native_step`), with
the worlds split into chunks that the caller's thread and its helper threads take from
one atomic counter, all inside compiled code (`sim.fork_join`: no Python lock per tick
or chunk). A batch whose worlds have models of their own (`set_body_mass`) is stepped by
the batch between one call per autopilot tick (`_STEP_CALLER`).

Per call the kernel gets two tables instead of some hundred arguments (numba checks each
argument's type on every call, ~0.15 us each): `tab` (int64: sizes, codes, buffer
addresses, row offsets; its entries are named by `_TAB` and indexed by the `_T_*`
constants) and `fc` (float64 constants, `_FC` and `_F_*`). `sim.plan._Plan` fills them and
keeps every addressed array alive; the pointer and call intrinsics here turn its
addresses into typed arrays and C calls. The tick's log row is one flat array
(`sim.rows`) that the first autopilot tick writes.

Limits: a MuJoCo fatal error (`mju_error`, not a warning) inside the kernel may end the
process instead of raising (on the readable path a batch marks that world diverged).
tests/test_fast_path.py checks that both paths fly bit-identical logs, and
tests/test_simulator_kernels.py that each variant compiles once per layout of the physics
state (a single MjData, C-contiguous; a batch's rows, strided). numba checks a cached
kernel against its own file only: after editing `sim/passes.py` (or another module whose
kernels this one calls), delete the caches (`downwash_core.jit`).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import carray, types
from numba.core.extending import intrinsic

from controllers.lqr import _command_setpoint_kernel
from downwash_core.jit import njit
from sim import fork_join
from sim.field import _pairwise_kernel
from sim.passes import (_actuate_kernel, _hold_kernel, _sense_kernel, _status_kernel, _wind_advance_kernel,
                        _wind_force_kernel, _wind_sense_kernel)
from sim.physics import _FATAL_0, _FATAL_1, _FATAL_2
from sim.predictor import GUARD_STATE_WIDTH

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
def _call_predictor(typingctx, fn, n_worlds, n_veh, pos, vel, rot, true_pos, true_vel, true_rot, params, iparams, out):
    """A `sim.predictor.PREDICTOR_SIGNATURE` function at address fn; the array arguments are addresses."""
    return types.void(types.intp, types.int64, types.int64, *(types.intp,) * 9), _call_codegen(9)


@intrinsic
def _call_monitor(typingctx, fn, n_worlds, n_veh, t, vel, u, state, seen, seen_t, params, iparams):
    """A `sim.predictor.MONITOR_SIGNATURE` function at address fn; the array arguments are addresses."""
    return types.void(types.intp, types.int64, types.int64, *(types.intp,) * 8), _call_codegen(8)


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
    "mocap_offset", "max_thrust", "mass", "drag_gain", "field_scale", "radius_xy", "radius_z",
    "row_kin", "row_t", "row_quat", "row_quat_est", "row_yaw", "row_applied", "row_ref_pos", "row_ref_vel",
    "row_ref_acc", "row_u_cmd", "row_f_hat", "row_mean", "row_wind", "row_wind_acc",
    "guard", "guard_fn", "guard_params", "guard_iparams", "guard_state", "guard_applied", "row_guard",
    "pw_guard_fn", "pw_guard_params", "pw_guard_iparams", "pw_guard_state", "pw_guard_applied", "pw_guarded",
    "monitor_fn", "monitor_params", "monitor_iparams", "seen", "seen_stride", "seen_t",
    "safety_fn", "safety_params", "safety_lower", "safety_upper",
)
(_T_W, _T_V, _T_BLOCK, _T_NSUB, _T_NPHYS, _T_STEPPING, _T_STEP_FN, _T_SET_STATE_FN, _T_GET_STATE_FN, _T_MODEL,
 _T_DATA, _T_WARNINGS, _T_WARNING_STRIDE, _T_STATE, _T_NSTATE, _T_STATE_SPEC, _T_BATCH_WARNINGS, _T_NWARNINGS,
 _T_PRED, _T_PRED_FN, _T_PRED_PARAMS, _T_PRED_IPARAMS,
 _T_LAYOUT, _T_NOISE, _T_CURSOR, _T_POS_EST, _T_VEL_EST, _T_T, _T_NEXT_PRED, _T_DUE, _T_FIELD_ON, _T_TURB,
 _T_ROT_DES, _T_YAW_RATE_DES, _T_THRUST, _T_MASS_BELIEVED, _T_AP_GAIN, _T_ACTIVE, _T_F_HAT, _T_TICK_INDEX,
 _T_STATUS_NEW, _T_KIN, _T_QUAT, _T_ROT, _T_QUAT_EST, _T_ROT_EST, _T_YAW, _T_APPLIED, _T_MEAN, _T_PRED_OUT, _T_KT,
 _T_FIELD_PACKED, _T_ORACLE_PACKED, _T_GUST, _T_WIND_NOISE, _T_WIND_MEAN, _T_WIND_SIGMA, _T_WIND_LENGTH,
 _T_WIND_AXES, _T_AIR, _T_VEL_AIR, _T_WIND_ACC, _T_DIVERGED, _T_PW_CODE, _T_PW_FN, _T_PW_PARAMS, _T_PW_IPARAMS,
 _T_PW_ORACLE, _T_MOCAP_OFFSET, _T_MAX_THRUST, _T_MASS, _T_DRAG_GAIN, _T_FIELD_SCALE, _T_RADIUS_XY, _T_RADIUS_Z,
 _T_ROW_KIN, _T_ROW_T, _T_ROW_QUAT, _T_ROW_QUAT_EST, _T_ROW_YAW, _T_ROW_APPLIED, _T_ROW_REF_POS, _T_ROW_REF_VEL,
 _T_ROW_REF_ACC, _T_ROW_U_CMD, _T_ROW_F_HAT, _T_ROW_MEAN, _T_ROW_WIND, _T_ROW_WIND_ACC,
 _T_GUARD, _T_GUARD_FN, _T_GUARD_PARAMS, _T_GUARD_IPARAMS, _T_GUARD_STATE, _T_GUARD_APPLIED,
 _T_ROW_GUARD, _T_PW_GUARD_FN, _T_PW_GUARD_PARAMS, _T_PW_GUARD_IPARAMS, _T_PW_GUARD_STATE, _T_PW_GUARD_APPLIED,
 _T_PW_GUARDED, _T_MONITOR_FN, _T_MONITOR_PARAMS, _T_MONITOR_IPARAMS, _T_SEEN, _T_SEEN_STRIDE, _T_SEEN_T,
 _T_SAFETY_FN, _T_SAFETY_PARAMS, _T_SAFETY_LOWER, _T_SAFETY_UPPER) = range(len(_TAB))
# The plan's float table `fc` (float64), in this order.
# (Each vehicle's numbers are arrays of `tab`: mass, drag_gain, ap_gain, max_thrust (V, ...), and the
# pairs' field_scale, radius_xy, radius_z (V, V): `sim.vehicle_params`.)
_FC = (
    "sigma_p", "sigma_att", "kf_gain_p", "kf_gain_v", "ou_a", "ou_b", "intensity", "dt",
    "prediction_period", "lookahead", "tan_tilt", "min_vertical", "min_airspeed", "max_distance", "ground",
)
(_F_SIGMA_P, _F_SIGMA_ATT, _F_KF_P, _F_KF_V, _F_OU_A, _F_OU_B, _F_INTENSITY, _F_DT,
 _F_PRED_PERIOD, _F_LOOKAHEAD, _F_TAN_TILT, _F_MIN_VERTICAL, _F_MIN_AIRSPEED, _F_MAX_DISTANCE, _F_GROUND) = range(len(_FC))
# predictor codes: zero, oracle (field kernel), C function, and one of these per world (`PerWorldPredictor`)
_PRED_ZERO, _PRED_ORACLE, _PRED_C, _PRED_PER_WORLD = 0, 1, 2, 3


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
        flat row (`sim.rows.row_layout`), written by sub-tick 0; chunks (n, 4) int64: per chunk its first
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
                mocap_offset = carray(_f64p(tab[_T_MOCAP_OFFSET]), (n_worlds, V, 3))[w0:w1]
                rot_des = carray(_f64p(tab[_T_ROT_DES]), (n_worlds, V, 3, 3))[w0:w1]
                yaw_rate_des = carray(_f64p(tab[_T_YAW_RATE_DES]), (n_worlds, V))[w0:w1]
                thrust_acc = carray(_f64p(tab[_T_THRUST]), (n_worlds, V))[w0:w1]
                mass_believed = carray(_f64p(tab[_T_MASS_BELIEVED]), (n_worlds, V))[w0:w1]
                ap_gain = carray(_f64p(tab[_T_AP_GAIN]), (V, 14, 4))  # each vehicle's (sim.vehicle_params)
                max_thrust = carray(_f64p(tab[_T_MAX_THRUST]), (V,))
                mass = carray(_f64p(tab[_T_MASS]), (V,))
                field_scale = carray(_f64p(tab[_T_FIELD_SCALE]), (V, V))
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
                        qpos_w, qvel_w, layout, noise, cursor, fc[_F_SIGMA_P], fc[_F_SIGMA_ATT], mocap_offset,
                        fc[_F_KF_P], fc[_F_KF_V],
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
                        _wind_sense_kernel(gust, carray(_f64p(tab[_T_WIND_AXES]), (3, 3)), wind_mean,
                                           carray(_f64p(tab[_T_DRAG_GAIN]), (V,)), vel, air, vel_air, wind_acc)
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
                            _copy_into(pred, _pairwise_kernel(pos, vel_air, rot, carray(_f64p(tab[_T_ORACLE_PACKED]), (16,)),
                                                              field_scale))
                        elif kind == _PRED_PER_WORLD:  # world by world, each its own predictor, as PerWorldPredictor
                            pw_code = carray(_i64p(tab[_T_PW_CODE]), (n_worlds,))[w0:w1]
                            pw_fn = carray(_i64p(tab[_T_PW_FN]), (n_worlds,))[w0:w1]
                            pw_params = carray(_i64p(tab[_T_PW_PARAMS]), (n_worlds,))[w0:w1]
                            pw_iparams = carray(_i64p(tab[_T_PW_IPARAMS]), (n_worlds,))[w0:w1]
                            pw_oracle = carray(_f64p(tab[_T_PW_ORACLE]), (n_worlds, 16))[w0:w1]
                            pw_guard_fn = carray(_i64p(tab[_T_PW_GUARD_FN]), (n_worlds,))[w0:w1]
                            pw_guard_params = carray(_i64p(tab[_T_PW_GUARD_PARAMS]), (n_worlds,))[w0:w1]
                            pw_guard_iparams = carray(_i64p(tab[_T_PW_GUARD_IPARAMS]), (n_worlds,))[w0:w1]
                            pw_guard_state = carray(_i64p(tab[_T_PW_GUARD_STATE]), (n_worlds,))[w0:w1]
                            pw_guard_applied = carray(_i64p(tab[_T_PW_GUARD_APPLIED]), (n_worlds,))[w0:w1]
                            for w in range(W):
                                if pw_code[w] == _PRED_ORACLE:
                                    _copy_into(pred[w:w + 1], _pairwise_kernel(pos[w:w + 1], vel_air[w:w + 1], rot[w:w + 1],
                                                                               pw_oracle[w], field_scale))
                                elif pw_code[w] == _PRED_C:  # one world: its rows of C-contiguous (W, ...) arrays
                                    _call_predictor(
                                        pw_fn[w], 1, V, kin[3][w].ctypes.data, kin[4][w].ctypes.data, rot_est[w].ctypes.data,
                                        pos[w].ctypes.data, vel_air[w].ctypes.data, rot[w].ctypes.data, pw_params[w],
                                        pw_iparams[w], pred[w].ctypes.data,
                                    )
                                    if pw_guard_fn[w] != 0:  # its guard's pass, on the world's rows of the guard's state
                                        _call_predictor(
                                            pw_guard_fn[w], 1, V, kin[3][w].ctypes.data, kin[4][w].ctypes.data,
                                            rot_est[w].ctypes.data, due.ctypes.data + w, pred[w].ctypes.data,
                                            pw_guard_state[w], pw_guard_applied[w], pw_guard_params[w],
                                            pw_guard_iparams[w],
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
                        if tab[_T_GUARD]:  # the guard's pass over the prediction (sim.predictor.CompiledGuard)
                            _call_predictor(  # (a GUARD_SIGNATURE has the PREDICTOR_SIGNATURE's argument types)
                                tab[_T_GUARD_FN], W, V, kin[3].ctypes.data, kin[4].ctypes.data, rot_est.ctypes.data,
                                due.ctypes.data, pred.ctypes.data, tab[_T_GUARD_STATE] + 8 * V * GUARD_STATE_WIDTH * w0,
                                tab[_T_GUARD_APPLIED] + 8 * V * w0, tab[_T_GUARD_PARAMS], tab[_T_GUARD_IPARAMS],
                            )
                        _hold_kernel(f_hat, pred, due, next_prediction, fc[_F_PRED_PERIOD])

                    _copy_into(mean, _pairwise_kernel(pos, vel_air, rot, field_packed, field_scale))

                    if first:  # the LQR and feedback linearisation at 50 Hz
                        _copy_into(_row_view(row, tab[_T_ROW_REF_POS], n_worlds, V3, w0, w1).reshape((W, V, 3)), ref_pos_w)
                        _copy_into(_row_view(row, tab[_T_ROW_REF_VEL], n_worlds, V3, w0, w1).reshape((W, V, 3)), ref_vel_w)
                        _copy_into(_row_view(row, tab[_T_ROW_REF_ACC], n_worlds, V3, w0, w1).reshape((W, V, 3)), ref_acc_w)
                        state = (kin[3], kin[4], yaw, ref_pos_w, ref_vel_w, ref_acc_w, ref_yaw_w, ref_yaw_rate_w, f_hat)
                        limits = (Kt, fc[_F_LOOKAHEAD], fc[_F_TAN_TILT], fc[_F_MIN_VERTICAL], u_cmd, yaw_rate_des, thrust_acc, rot_des)
                        _command_setpoint_kernel(*state, residual_w, override_w, (actions & 1) != 0, (actions & 2) != 0, *limits)
                        if tab[_T_SAFETY_FN] != 0:  # the CBF filter (sim.safety.SAFETY_SIGNATURE), then the LQR's step again
                            counts = np.zeros(2, np.int64)  # with the filtered command as override, as the readable path
                            _call_predictor(tab[_T_SAFETY_FN], W, V, kin[3].ctypes.data, kin[4].ctypes.data, f_hat.ctypes.data,
                                            u_cmd.ctypes.data, tab[_T_SAFETY_PARAMS], tab[_T_SAFETY_LOWER],
                                            tab[_T_SAFETY_UPPER], counts.ctypes.data, counts.ctypes.data)
                            if counts[0] != 0:
                                no, yes = actions < 0, actions >= 0  # (False, True, not literals: the call's types as above)
                                _command_setpoint_kernel(*state, residual_w, u_cmd, no, yes, *limits)
                        _copy_into(_row_view(row, tab[_T_ROW_F_HAT], n_worlds, V3, w0, w1).reshape((W, V, 3)), f_hat)
                        if tab[_T_GUARD]:
                            _copy_into(_row_view(row, tab[_T_ROW_GUARD], n_worlds, V, w0, w1).reshape((W, V, 1)),
                                       carray(_f64p(tab[_T_GUARD_APPLIED]), (n_worlds, V, 1))[w0:w1])
                        elif tab[_T_PW_GUARDED]:  # each guard's worlds its applied fraction, NaN in the others
                            applied_row = _row_view(row, tab[_T_ROW_GUARD], n_worlds, V, w0, w1)
                            pw_applied = carray(_i64p(tab[_T_PW_GUARD_APPLIED]), (n_worlds,))[w0:w1]
                            for w in range(W):
                                for i in range(V):
                                    applied_row[w, i] = (carray(_f64p(pw_applied[w]), (V,))[i] if pw_applied[w] != 0
                                                         else np.nan)

                    _actuate_kernel(
                        field_on, noise, cursor, turb, fc[_F_OU_A], fc[_F_OU_B], fc[_F_INTENSITY], mass, xfrc_w, layout,
                        qvel_w, rot_des, yaw_rate_des, thrust_acc, mass_believed, ap_gain, max_thrust, ctrl_w,
                        pos_est, vel_est, dt, t, active, mean, applied, rot, u_cmd,
                    )
                    if with_wind:
                        _wind_force_kernel(xfrc_w, layout, mass, wind_acc)
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
                    fc[_F_MAX_DISTANCE], fc[_F_GROUND], carray(_f64p(tab[_T_RADIUS_XY]), (V, V)),
                    carray(_f64p(tab[_T_RADIUS_Z]), (V, V)),
                    carray(_i64p(tab[_T_STATUS_NEW]), (n_worlds,))[w0:w1],
                )
                if tab[_T_MONITOR_FN] != 0:  # the guard's monitor on these worlds' row (its observe): t, vel_est
                    # (the row's kin block, (5, W, V, 3), slot 4) and u_cmd
                    base, V3W = row.ctypes.data, 8 * V3 * w0
                    _call_monitor(tab[_T_MONITOR_FN], W, V, base + 8 * (tab[_T_ROW_T] + w0),
                                  base + 8 * (tab[_T_ROW_KIN] + 4 * n_worlds * V3) + V3W, base + 8 * tab[_T_ROW_U_CMD] + V3W,
                                  tab[_T_GUARD_STATE] + 8 * V * GUARD_STATE_WIDTH * w0, tab[_T_SEEN] + tab[_T_SEEN_STRIDE] * w0,
                                  tab[_T_SEEN_T] + 8 * w0, tab[_T_MONITOR_PARAMS], tab[_T_MONITOR_IPARAMS])
            if helper:
                fork_join.report(ctl, role - fork_join.HELPER, total, n_taken)
                total = 0
            elif role == fork_join.MAIN:
                return fork_join.join(ctl, total)
            else:
                return total

    return _fused_kernel


_FUSED_KERNELS = (_make_fused_kernel(False), _make_fused_kernel(True))  # by wind on
