"""A controller's compiled form: the contract by which a controller of your own flies the fused tick.

The fused tick (`sim.fused`) runs the built-in LQR's kernel itself; any other controller joins it
through one C function of `CONTROLLER_SIGNATURE`, which it returns from ``compiled_controller(W, V)``
as a `CompiledController`:

    void law(n_worlds, n_vehicles, pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate,
             f_hat, residual, override, flags, lookahead, state, params, acc, yaw_rate, thrust, rot)

- pos, vel (W, V, 3) m, m/s and yaw (W, V) rad: the estimated state (`controllers.lqr.ControllerState`);
- ref_pos, ref_vel, ref_acc (W, V, 3) and ref_yaw, ref_yaw_rate (W, V): the reference at the tick's start;
- f_hat (W, V, 3) m/s^2: the held prediction, to compensate;
- residual, override (W, V, 3) m/s^2 and flags (2,) int64 (use_residual, use_override): the envs' action
  modes, as `command_setpoint` takes them (read only where the flag is set);
- lookahead (1,) float64 s: how far ahead to aim the heading (the controller period);
- state (W, V, S) float64: the controller's memory (integrators, filters), owned by it, zero when
  fresh and zeroed by its ``reset(worlds)``; params (P,) float64: its constants;
- acc (W, V, 3) m/s^2 (the command u applied, gravity excluded, compensation included), yaw_rate (W, V)
  rad/s, thrust (W, V) m/s^2 and rot (W, V, 3, 3): the outputs, `controllers.lqr.Setpoint`'s buffers,
  written in full.

Every pointer is C-contiguous. The fused tick calls it with a block of whole worlds at a time
(W the block's; state offset to the block's first world), so the law must treat worlds
independently. `controller_function(step, state_width, n_params)` builds the C function from an
array form (`step` below, numba-compiled), so a controller has one body for both paths: its
``command_setpoint`` (the readable path) calls `step` on NumPy arrays, the fused tick calls the same
`step` through the C function, and the two fly the same bits (`tests/test_controller_contract.py`):

    step(pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override,
         use_residual, use_override, lookahead, state, params, acc, yaw_rate, thrust, rot)

`run_step` is the readable path's call of it for `command_setpoint`. A controller with a compiled form
does not fly the fused tick together with the safety layer (`sim.safety` redoes the LQR's own step):
such a simulator takes the readable path.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numba
import numpy as np
from numba import carray
from numba import types as nbt

from controllers.lqr import setpoint_one
from downwash_core.jit import njit

__all__ = ["CONTROLLER_SIGNATURE", "CompiledController", "controller_function", "run_step", "finish_one"]

_F64P, _I64P = nbt.CPointer(nbt.float64), nbt.CPointer(nbt.int64)
# (n_worlds, n_vehicles, 11 state and reference pointers, flags, lookahead, state, params, 4 outputs)
CONTROLLER_SIGNATURE = nbt.void(nbt.int64, nbt.int64, *(_F64P,) * 11, _I64P, _F64P, _F64P, _F64P, *(_F64P,) * 4)


class CompiledController(NamedTuple):
    """A controller's compiled form (module doc): the address of its C function of `CONTROLLER_SIGNATURE`,
    its constants `params` (P,) float64 and its memory `state` (W, V, S) float64, both C-contiguous and kept
    alive by the controller (the simulator reads them by address)."""

    address: int
    params: np.ndarray
    state: np.ndarray


def controller_function(step: Callable[..., None], state_width: int, n_params: int) -> Any:
    """The C function of `CONTROLLER_SIGNATURE` (a numba cfunc; its ``address`` for `CompiledController`)
    that runs `step` (a numba-compiled array form, module doc) on the pointers it is given, with the
    state (W, V, state_width) and params (n_params,). Compiled at the call (seconds); keep the result."""
    if not isinstance(step, numba.core.registry.CPUDispatcher):
        raise TypeError(f"controller_function: step must be a numba.njit function, got {type(step).__name__}")
    width, size = int(state_width), int(n_params)

    def law(n_worlds, n_veh, pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual,
            override, flags, lookahead, state, params, acc, yaw_rate, thrust, rot):  # pragma: no cover - compiled
        s3, s1 = (n_worlds, n_veh, 3), (n_worlds, n_veh)
        f = carray(flags, (2,))
        step(carray(pos, s3), carray(vel, s3), carray(yaw, s1), carray(ref_pos, s3), carray(ref_vel, s3),
             carray(ref_acc, s3), carray(ref_yaw, s1), carray(ref_yaw_rate, s1), carray(f_hat, s3),
             carray(residual, s3), carray(override, s3), f[0] != 0, f[1] != 0, carray(lookahead, (1,))[0],
             carray(state, (n_worlds, n_veh, width)), carray(params, (size,)), carray(acc, s3), carray(yaw_rate, s1),
             carray(thrust, s1), carray(rot, (n_worlds, n_veh, 3, 3)))

    return numba.cfunc(CONTROLLER_SIGNATURE, nopython=True)(law)


def run_step(step: Callable[..., None], state: Any, ref: Any, f_hat: np.ndarray, out: Any,
             residual: np.ndarray | None, override: np.ndarray | None, lookahead: float, memory: np.ndarray,
             params: np.ndarray) -> None:
    """`step` on the readable path: `command_setpoint`'s arguments (`controllers.lqr.ControllerState`,
    `downwash_core.state.RefSample`, `controllers.lqr.Setpoint`) in the array form, memory (W, V, S)."""
    use_residual, use_override = residual is not None, override is not None
    step(state.pos, state.vel, state.yaw, ref.pos, ref.vel, ref.acc, ref.yaw, ref.yaw_rate, f_hat,
         residual if use_residual else f_hat, override if use_override else f_hat, use_residual, use_override,
         float(lookahead), memory, params, out.acc, out.yaw_rate, out.thrust, out.rot)


@njit
def finish_one(acc, w, i, residual, override, use_residual, use_override, yaw_des, tan_tilt, min_vertical, rot):
    """The end of one vehicle's step: acc[w, i] (W, V, 3) m/s^2 holds the controller's command (gravity
    excluded, the downwash compensated); `residual` is added, `override` replaces it where finite
    (flags, not None arguments, as the LQR's kernel), in place. Returns the collective specific
    thrust (m/s^2) and writes the desired attitude into rot[w, i] (feedback linearisation)."""
    for k in range(3):
        a = acc[w, i, k]
        if use_residual:
            a = a + residual[w, i, k]
        if use_override and np.isfinite(override[w, i, k]):
            a = override[w, i, k]
        acc[w, i, k] = a
    return setpoint_one(acc[w, i, 0], acc[w, i, 1], acc[w, i, 2], yaw_des, tan_tilt, min_vertical, rot[w, i])
