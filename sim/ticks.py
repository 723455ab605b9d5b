"""The simulator's two ways through a controller tick, as mixins of `sim.simulator.Simulator`.

`FusedTicks` drives the fused kernel (`sim.fused`): the tick's reference (a stacked one sampled into
storage the simulator keeps) and actions into its arguments, one call per stretch of autopilot ticks
(the whole tick unless the noise blocks need a refill within it; one per autopilot tick when the
caller steps the physics), and the helper threads that take chunks of worlds (`sim.fork_join`). `ReadableTicks`
runs each autopilot tick as the compiled passes (`sim.passes`) around the Python components
(predictor, field, reference, controller, safety filter). Both write the same log row, bit for bit
(tests/test_fast_path.py). They use the simulator's own state; `Simulator` alone builds it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from controllers.lqr import ControllerState, Setpoint
from downwash_core.state import VehicleStates
from downwash_trajectories.combinators import StackedReference
from sim import fork_join
from sim.aggregation import wake_field
from sim.fused_abi import FC, STEP_CALLER, TAB
from sim.passes import (actuate_kernel, hold_kernel, sense_kernel, sense_law_kernel, Sensed, wind_advance_kernel,
                        wind_force_kernel, wind_sense_kernel)
from sim.plan import Plan
from sim.rows import Row

__all__ = ["FusedTicks", "ReadableTicks", "kernel_array", "as_batch"]

NO_CONTROL = fork_join.new_control()  # the control block of a call alone, which never reads it


class FusedTicks:
    """A controller tick through the fused kernel (`Simulator(fast=True)` with a plan)."""

    _helpers: Any

    def _tick_fused(self, plan: Plan, residual: np.ndarray | None, override: np.ndarray | None) -> Row:
        """One controller tick through `_fused_kernel` (see the module docstring)."""
        reference = self.reference
        if type(reference) is StackedReference and reference.n_vehicles == self.V:  # into kept storage
            reference.fill(self.t, *self._ref_storage)
            head = plan.leading_args + self._ref_views
        else:
            ref = reference(self.t)
            refs = (ref.pos, ref.vel, ref.acc, ref.yaw, ref.yaw_rate)
            if plan.n_threads > 1:  # the helpers read them by address, as C-contiguous arrays
                refs = tuple(kernel_array(x) for x in refs)
            head = plan.leading_args + refs
        flat = np.empty(plan.row_size)
        args = head + (plan.no_action if residual is None else kernel_array(residual),
                       plan.no_action if override is None else kernel_array(override),
                       (residual is not None) + 2 * (override is not None), flat)
        n_sub, block = plan.n_sub, plan.noise_block
        if plan.stepping != STEP_CALLER and self._cursor_max + n_sub <= block:  # the whole tick in one call
            if self._call(plan, args, 0, n_sub):  # (the loop below without its bookkeeping: 2-3 % of a tick, measured)
                self._end_worlds(self._status_new)
            return Row(flat, plan.row_layout)
        sub, diverged, n_ended = 0, None, 0
        caller_steps = plan.stepping == STEP_CALLER
        while sub < n_sub:
            if self._cursor_max >= block:
                self._refill_used()
            # the rest of the tick in one call (up to a refill of the noise blocks), unless the
            # caller steps the physics: then one autopilot tick per call
            stop = min(sub + 1 if caller_steps else n_sub, sub + block - self._cursor_max)
            n_ended = self._call(plan, args, sub, stop)
            if caller_steps:
                d = self.physics.step(self.cfg.rates.physics_per_autopilot, self.active)
                diverged = d if diverged is None else diverged | d
            sub = stop
        if caller_steps:
            self._check(diverged)
        elif n_ended:
            self._end_worlds(self._status_new)
        return Row(flat, plan.row_layout)

    def _call(self, plan: Plan, args: tuple, sub: int, stop: int) -> int:
        """Autopilot ticks sub..stop-1 through the kernel, on this thread alone or with the helpers; counts
        them used of the noise blocks. Returns how many worlds ended."""
        if plan.n_threads == 1:
            n_ended = plan.kernel(*args, sub, stop, plan.own_chunks, NO_CONTROL, fork_join.SOLO)
        else:
            n_ended = self._run_threads(plan, args, sub, stop)
        self.__dict__["_cursor_max"] += stop - sub  # (not a bound input: skips __setattr__)
        return n_ended

    def _run_threads(self, plan: Plan, args: tuple, sub: int, stop: int) -> int:
        """Autopilot ticks sub..stop-1 on this thread and the helpers (`sim.fork_join`); returns how
        many worlds ended. The helpers serve every plan of this simulator (a plan is rebuilt
        when a component changes, e.g. at each autoreset of an env with randomised fields)."""
        helpers = self.__dict__.get("_helpers")
        if helpers is None or not helpers.alive or helpers.key != (plan.kernel, plan.n_threads):
            helpers = self._start_helpers(plan)  # first use, or a forked child (no threads of its own)
        ctl, role = (helpers.ctl, fork_join.MAIN) if helpers.start_tick() else (NO_CONTROL, fork_join.SOLO)
        return helpers.end_tick(plan.kernel(*args, sub, stop, plan.own_chunks, ctl, role), stop - sub)

    def _start_helpers(self, plan: Plan) -> fork_join.Helpers:
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
        fixed = (np.zeros(len(TAB), np.int64), np.zeros(len(FC))) + plan.leading_args[2:] \
            + (np.zeros((W, V, 3)),) * 3 + (np.zeros((W, V)),) * 2 + (np.zeros((W, V, 3)),) * 2 \
            + (0, np.zeros(1), 0, 0, np.zeros((1, 4), np.int64))

        def serve(t: int) -> int:
            return kernel(*fixed, ctl, fork_join.HELPER + t)

        helpers = fork_join.Helpers(plan.n_threads - 1, serve, ctl, owner=self)
        helpers.key = (kernel, plan.n_threads)
        self.__dict__["_helpers"] = helpers
        return helpers


class ReadableTicks:
    """A controller tick as compiled passes around the Python components (`Simulator(fast=False)`, or a
    component without a compiled form)."""

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
            sensed = Sensed.empty(W, V) if first else self._reused  # the first tick's arrays become the row
            kin, quat, rot, quat_est, rot_est, yaw, applied = sensed
            pos, vel, mocap, pos_est, vel_est = kin
            # motion capture (the family's law, or a sensor's compiled law: sim.sensor_contract) and Kalman update
            sense = sense_kernel if self._sensor_law is None else sense_law_kernel
            n_due = sense(*self._sense_args, kin, quat, rot, quat_est, rot_est, yaw)

            # the wind at each vehicle, its drag, and the next gust state; the wakes see vel - u_air
            vel_air = vel
            if wind:
                air, vel_air, wind_acc = tuple(np.empty((W, V, 3)) for _ in range(3)) if first else self._wind_reused
                wind_sense_kernel(self.gust_state, *self._wind_sense_consts, vel, air, vel_air, wind_acc)
                wind_advance_kernel(self.gust_state, self._wind_noise, self._cursor, vel, *self._wind_advance_consts)

            # downwash field, applied as an external force until the next autopilot tick (a wake with memory
            # steps first, carried by the air); before the predictor, whose oracle may read it
            mean = (wake_field(self._scene_field, pos, vel_air, rot, self.aggregation) if self._memory is None else
                    self._memory.advance(pos, vel, vel_air, rot, air.mean(axis=1) if wind else None, self.aggregation))

            # predictor at 45 Hz, held: it sees what a lab measures, the truth only for oracles
            if n_due:
                pred = self._scene_predictor(VehicleStates(pos_est, vel_est, rot_est), VehicleStates(pos, vel_air, rot),
                                             **({"due": self._due} if self._predictor_state else {}))
                hold_kernel(self.f_hat, as_batch(pred, (W, V, 3)), self._due, self.next_prediction, self._prediction_period)

            if first:  # the LQR and feedback linearisation at 50 Hz
                ref = self.reference(self.t)
                cmd_acc = np.empty((W, V, 3))  # m/s^2, the command applied (row u_cmd)
                state = ControllerState(pos_est, vel_est, yaw)
                setpoint = Setpoint(cmd_acc, self._yaw_rate_des, self._thrust_acc, self._rot_des)
                self.controller.command_setpoint(state, ref, self.f_hat, setpoint, residual, override, r.control_dt)
                if self._safety_filter is not None:  # filtered, then feedback linearisation again where it acted
                    self._safety_filter.apply(self.controller, state, ref, self.f_hat, setpoint, r.control_dt)
                row = {
                    "t": t_start, "pos": pos, "vel": vel, "quat": quat,
                    "pos_est": pos_est, "vel_est": vel_est, "quat_est": quat_est, "yaw_est": yaw,
                    "mocap_pos": mocap, "ref_pos": ref.pos, "ref_vel": ref.vel, "ref_acc": ref.acc,
                    "u_cmd": cmd_acc, "f_hat": self.f_hat.copy(), "field_mean": mean, "field_applied": applied,
                }
                if wind:
                    row["wind"], row["wind_acc"] = air, wind_acc
                if (fraction := getattr(self._scene_predictor, "applied", None)) is not None:  # a guard's
                    row["applied"] = np.array(fraction, dtype=np.float64)

            # field and turbulence into xfrc_applied, autopilot into ctrl, Kalman prediction, clocks
            actuate_kernel(*self._actuate_args, mean, applied, rot, cmd_acc)
            if wind:
                wind_force_kernel(ph.xfrc_applied, self._layout, self.vehicle_params.mass, wind_acc)
            self.__dict__["_cursor_max"] += 1
            d = ph.step(r.physics_per_autopilot, self.active)
            diverged = d if diverged is None else diverged | d
        self._check(diverged)
        return row


def kernel_array(x: np.ndarray) -> np.ndarray:
    """x (float64) as the fused kernel reads it: C-contiguous and writeable (a copy only when it is not)."""
    flags = x.flags
    return x if flags.c_contiguous and flags.writeable else np.require(x, np.float64, ("C", "W"))


def as_batch(x: Any, shape: tuple[int, ...]) -> np.ndarray:
    """x as a float64 array of exactly `shape` (broadcast, read-only, only when it differs)."""
    x = np.asarray(x, dtype=np.float64)
    return x if x.shape == shape else np.broadcast_to(x, shape)

