"""The fused tick: a whole controller tick of the loop as ONE compiled call.

The fast path of `sim.simulator.Simulator` (`fast=True`, the default, taken when every
component has a compiled form: see `sim.plan.make_plan`) runs each controller tick
through `_fused_kernel` (made by `_make_fused_kernel`; one variant with and one without
the wind stages, `FUSED_KERNELS`). The tick is a short composition of compiled stages over
typed bundles (`sim.tick_stages`): sensing and estimation, wind, prediction and guard, the
field, control (the LQR's kernel or a controller's compiled form, `controllers.compiled`, and
the safety filter), actuation, physics and, at the end of a tick, the monitor. The stages call
the same passes as the readable path (`sim.passes`), so both fly the same bits. The kernel
steps the physics itself: `mj_step` on a single world's MjData (`sim.physics.mj_step_address`),
or, for a `mujoco.batch.Batch`, each world's state row loaded into a scratch MjData, stepped
and saved, as the batch does it (`_BatchPhysics.native_step`), with the worlds split into
chunks that the caller's thread and its helper threads take from one atomic counter, all
inside compiled code (`sim.fork_join`: no Python lock per tick or chunk). A batch whose worlds
have models of their own (`set_body_mass`) is stepped by the batch between one call per
autopilot tick (`STEP_CALLER`).

Per call the kernel gets two tables instead of some hundred arguments (`sim.fused_abi`: their
layouts and the intrinsics that read them); `sim.plan.Plan` fills them and keeps every
addressed array alive, and `sim.tick_stages` reads them once per chunk into bundles. The
tick's log row is one flat array (`sim.rows`) that the first autopilot tick writes.

Limits: a MuJoCo fatal error (`mju_error`, not a warning) inside the kernel may end the
process instead of raising (on the readable path a batch marks that world diverged).
tests/test_fast_path.py checks that both paths fly bit-identical logs, and
tests/test_simulator_kernels.py that each variant compiles once per layout of the physics
state (a single MjData, C-contiguous; a batch's rows, strided). numba checks a cached
kernel against its own file only: after editing `sim/passes.py` or `sim/tick_stages.py` (or
another module whose kernels this one calls), delete the caches (`downwash_core.jit`).
"""

from __future__ import annotations

from numba import carray

from downwash_core.jit import njit
from sim import fork_join
from sim.fused_abi import STEP_CALLER, T_NSUB, T_V, T_W, f64p, i64p
from sim.tick_stages import (PhysicsArrays, actuate_stage, buffers_bundle, control_bundle, control_stage, field_stage,
                             inputs_bundle, monitor_bundle, monitor_stage, physics_stage, predict_stage,
                             prediction_bundle, sense_stage, stepping_bundle, vehicles_bundle, wind_bundle,
                             wind_force_stage, wind_stage, world_bundle)

__all__ = ["FUSED_KERNELS"]


@njit
def _published(ctl, role):
    """A helper thread's view of the tick the caller published (`sim.fork_join.publish`): the kernel's
    arguments but the physics state, as typed arrays."""
    tab = carray(i64p(ctl[fork_join.ARG_TAB]), (ctl[fork_join.ARG_TAB_SIZE],))
    fc = carray(f64p(ctl[fork_join.ARG_FC]), (ctl[fork_join.ARG_FC_SIZE],))
    n_chunks = ctl[fork_join.ARG_N_CHUNKS]
    own = ctl[fork_join.ARG_CHUNKS] + (role - fork_join.HELPER + 1) * n_chunks * 4 * 8
    n, V = tab[T_W], tab[T_V]
    return (tab, fc, carray(i64p(own), (n_chunks, 4)), carray(f64p(ctl[fork_join.ARG_REF_POS]), (n, V, 3)),
            carray(f64p(ctl[fork_join.ARG_REF_VEL]), (n, V, 3)), carray(f64p(ctl[fork_join.ARG_REF_ACC]), (n, V, 3)),
            carray(f64p(ctl[fork_join.ARG_REF_YAW]), (n, V)), carray(f64p(ctl[fork_join.ARG_REF_YAW_RATE]), (n, V)),
            carray(f64p(ctl[fork_join.ARG_RESIDUAL]), (n, V, 3)),
            carray(f64p(ctl[fork_join.ARG_OVERRIDE]), (n, V, 3)),
            carray(f64p(ctl[fork_join.ARG_ROW]), (ctl[fork_join.ARG_ROW_SIZE],)), ctl[fork_join.ARG_ACTIONS],
            ctl[fork_join.ARG_SUB_START], ctl[fork_join.ARG_SUB_STOP])


def _make_fused_kernel(with_wind: bool):
    """The fused kernel with or without the wind stages. `with_wind` is a constant of the closure, so
    numba prunes the branches it does not take before typing: a flight without wind never
    compiles the wind stages (seconds of every fresh build)."""

    @njit
    def _fused_kernel(tab, fc, qpos, qvel, ctrl, xfrc, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate,
                      residual, override, actions, row, sub_start, sub_stop, chunks, ctl, role):
        """Autopilot ticks sub_start..sub_stop-1 of one controller tick for the chunks of worlds this
        thread takes, as the readable path runs them.

        tab, fc: the plan's tables (`sim.fused_abi`); qpos, qvel, ctrl (W, n), xfrc (W, nbody, 6): the
        live physics state; ref_*: the reference at the tick's start ((W, V, 3), (W, V));
        residual, override: (W, V, 3) m/s^2 C-contiguous, as in `Simulator.tick`, each used only
        where actions (bit 0: residual, bit 1: override) says so; row: the tick's
        flat row (`sim.rows.row_layout`), written by sub-tick 0; chunks (n, 4) int64: per chunk its first
        and last + 1 world, the address of this thread's scratch MjData and of its warnings.
        Worlds are independent: chunks run on separate threads. Unless the caller steps the physics
        (`STEP_CALLER`), each sub-tick also steps it, and once the last sub-tick has run the monitor
        runs too. ctl, role: see `sim.fork_join`: alone (SOLO) this call runs every chunk; as MAIN it
        publishes the tick, takes chunks with the helpers and joins them; as HELPER + t it serves ticks
        (from the control block: the arguments passed to it, but for the physics state, are
        placeholders of their types) until idle.
        Returns how many worlds ended (0 when the monitor did not run), or what `sim.fork_join` says
        for a helper or an unjoined caller.
        """
        helper = role >= fork_join.HELPER
        total = 0
        while True:  # a helper: once per tick it serves; the others: once
            if helper:  # the tick's arguments, as the caller published them
                code = fork_join.await_tick(ctl, role - fork_join.HELPER)
                if code != 1:
                    return code
                (tab, fc, chunks, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, residual, override, row, actions,
                 sub_start, sub_stop) = _published(ctl, role)
            elif role == fork_join.MAIN:
                fork_join.publish(ctl, tab, fc, chunks, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, residual,
                                  override, row, actions, sub_start, sub_stop)
            vehicles, stepping = vehicles_bundle(tab), stepping_bundle(tab)
            n_taken = 0
            for taken in range(chunks.shape[0]):  # alone: every chunk in turn; else those the shared counter gives
                ci = taken if role == fork_join.SOLO else fork_join.fetch_add(ctl.ctypes.data + 8 * fork_join.NEXT, 1)
                if ci >= chunks.shape[0]:
                    break
                n_taken += 1
                w0, w1 = chunks[ci, 0], chunks[ci, 1]  # this chunk's worlds, with this thread's scratch MjData
                world, prediction = world_bundle(tab, w0, w1), prediction_bundle(tab, w0, w1)
                physics = PhysicsArrays(qpos[w0:w1], qvel[w0:w1], ctrl[w0:w1], xfrc[w0:w1])
                inputs = inputs_bundle(tab, row, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, residual, override,
                                       w0, w1)
                for sub in range(sub_start, sub_stop):
                    buf = buffers_bundle(tab, row, sub == 0, w0, w1)  # the row's on the first sub-tick
                    n_due = sense_stage(fc, world, physics, buf)
                    vel_air = buf.kin[1]
                    if with_wind:  # a constant: numba prunes the branch it does not take
                        wind = wind_bundle(tab, row, sub == 0, w0, w1)
                        vel_air = wind_stage(fc, world, wind, buf)
                    if n_due:  # the predictor at its rate, held
                        predict_stage(fc, prediction, vehicles, world, buf, vel_air)
                    field_stage(vehicles, world, buf, vel_air)
                    if sub == 0:  # the controller at its rate, and the safety filter
                        control_stage(fc, control_bundle(tab, w0, w1), vehicles, world, buf, inputs, row, actions)
                    actuate_stage(fc, vehicles, world, physics, buf, inputs.u_cmd)
                    if with_wind:
                        wind_force_stage(vehicles, world, physics, wind)
                    physics_stage(stepping, world, chunks[ci])
                if stepping.mode != STEP_CALLER and sub_stop == tab[T_NSUB]:  # a complete tick: check its worlds
                    total += monitor_stage(fc, stepping, monitor_bundle(tab, w0, w1), world, physics, row)
            if helper:
                fork_join.report(ctl, role - fork_join.HELPER, total, n_taken)
                total = 0
            elif role == fork_join.MAIN:
                return fork_join.join(ctl, total)
            else:
                return total

    return _fused_kernel


FUSED_KERNELS = (_make_fused_kernel(False), _make_fused_kernel(True))  # by wind on
