"""The fused path's plan: whether a simulator's components can fly it, and its bound tables.

`make_plan(sim, bound)` decides, each time a `sim.simulator.Simulator` binds its components,
between the fused compiled tick (`sim.fused`) and the readable path: it returns a `Plan`
when every component has a compiled form, else None. It reads the simulator's public attributes
and, of what the simulator derives when it binds, only what the simulator hands it as `bound`
(`PlanInputs`, a frozen view). The fused path needs

- the controller: exactly `controllers.lqr.FeedbackLinearisedLQR` (any `LQRConfig`; not a
  subclass, which may override `command_setpoint`), whose gains and limits run as
  `controllers.lqr.command_setpoint_kernel`, or one with a compiled form (`controllers.compiled`:
  ``compiled_controller(W, V)``, not with the safety layer), see `flies_compiled_controller`;
- the autopilot: a `controllers.autopilot.Autopilot` (its per-vehicle tables, `Autopilot.tables`);
- the field: a `sim.field.DownwashField` with scalar constants and linear aggregation
  (`_packed_field`), whose pairwise sum is `DownwashField.pairwise` with the scene's
  per-pair factors (`sim.vehicle_params`: all 1.0 for paper quads); or, under linear
  aggregation, a field with a compiled form, ``compiled_field()`` (`sim.field_contract`),
  that every pair of the scene flies as given (`_compiled_field`; its C function by address);
- the predictor: a `ZeroPredictor`, an `OraclePredictor` of such a field (a compiled form's too; inside a
  `PerWorldPredictor`, only the paper field's), a predictor whose
  `compiled()` returns a `sim.predictor.CompiledPredictor` (a C function), or a
  `PerWorldPredictor` of those (`_per_world_tables`); none with state (`sim.predictor.is_stateful`)
  but a guard whose ``compiled_guard(W, V)`` gives its model's C function and its own pass,
  alone or among the predictors of a `PerWorldPredictor` (alone, its monitor runs compiled at
  the end of the kernel's tick too, in place of the simulator's call of ``observe``);
- the sensor: any the simulator takes: of the family of `sim.sensors` (its `compiled()` stds in `fc`),
  or with a compiled law (`sim.sensor_contract`: its C function, constants and state by address in
  `tab`, sensor_fn 0: none); its episode's offsets `mocap_offset` in `tab`;
- the physics: a single MjData or a `mujoco.batch.Batch` whose stepping functions are found
  (`sim.physics`), and buffers laid out as the kernel reads them (else `_NoPlan`).
A safety filter (`sim.safety`) flies with every plan: its C function (`SafetyFilter.address`),
constants and per-world estimates (`SafetyFilter.state`) by address in `tab` (safety_fn 0: none).

A `Plan` holds the kernel's tables (`sim.fused.TAB`, `FC`) and every array they address,
so the addresses stay valid for the plan's lifetime; the simulator rebuilds it when a
component is replaced (assigning the attribute does) or the physics' models change.
The worlds of a batch are split into chunks for the helper threads (`_chunk_sizes`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.autopilot import Autopilot
from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError
from sim.aggregation import LinearSuperposition
from sim.field import DownwashField
from sim.field_contract import CompiledField, checked_field
from sim.fused import FUSED_KERNELS
from sim.fused_abi import (FATAL_MAX, FC, PRED_C, PRED_ORACLE, PRED_PER_WORLD, PRED_ZERO, STEP_CALLER, STEP_ROWS,
                           STEP_SERIAL, TAB)
from sim.physics import SerialPhysics
from sim.predictor import (CompiledGuard, CompiledPredictor, OraclePredictor, PerWorldPredictor, ZeroPredictor,
                           is_stateful)
from sim.rows import row_layout
from sim.stateful_field import is_stateful_field
from sim.vehicle_params import scene_field, told_kinds

__all__ = ["PlanInputs"]


@dataclass(frozen=True)
class PlanInputs:
    """What the plan reads of a simulator beyond its public attributes: what `Simulator._bind` derives
    from the components, and the state arrays the fused tick addresses (the simulator updates them in
    place; the tick writes them). Each field is the simulator's attribute of the same name with a
    leading underscore, handed over by the simulator when it binds (`names`)."""

    scene_predictor: Any  # the predictor as the scene binds it (`sim.vehicle_params.scene_predictor`)
    wind_on: bool
    layout: np.ndarray  # (V, 7) int64: per vehicle its qpos and qvel addresses, body id and actuator ids
    noise: np.ndarray  # (W, block, V, 9): each world's noise block
    wind_noise: np.ndarray  # (W, block, 3, 2): each world's gust draws
    cursor: np.ndarray  # (W,) int64: each world's next row of its noise block
    due: np.ndarray  # (W,) bool: the worlds whose prediction is due
    rot_des: np.ndarray  # (W, V, 3, 3), the control's setpoint for the autopilot
    yaw_rate_des: np.ndarray  # (W, V) rad/s
    thrust_acc: np.ndarray  # (W, V) m/s^2
    mass_believed: np.ndarray  # (W, V) kg, the controller's model
    ap_gain: np.ndarray  # (V, 14, 4), the autopilot's tables per vehicle
    max_thrust: np.ndarray  # (V,) N
    status_new: np.ndarray  # (W,) int64: how each world ended this tick (0: it did not)
    sigma_p: float  # m, the sensor's white position noise
    sigma_att: float  # rad, its attitude noise
    kf_gain_p: float  # the Kalman filter's steady-state gains
    kf_gain_v: float
    ou_a: float  # the turbulence's recursion over one autopilot tick
    ou_b: float
    turbulence_intensity: float
    prediction_period: float  # s
    safety_filter: Any  # the CBF filter on the commands (`sim.safety.SafetyFilter`), or None
    sensor_law: Any  # the sensor's compiled law (`sim.sensor_contract.CompiledSensorLaw`, checked), or None

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The fields, in order."""
        return tuple(f.name for f in dataclasses.fields(cls))


class _NoPlan(Exception):
    """A buffer is not laid out as the fused kernel reads it: the readable path runs instead."""


def flies_compiled_controller(controller: Any) -> bool:
    """Whether `controller` runs inside the fused kernel: exactly a `FeedbackLinearisedLQR` (its gains
    and limits are read into the plan), or a controller with a compiled form, ``compiled_controller(W, V)``
    (`controllers.compiled`); any other controller, an LQR subclass included, runs in Python."""
    return type(controller) is FeedbackLinearisedLQR or callable(getattr(controller, "compiled_controller", None))


def _c_array(a: Any, dtype: Any, name: str, leading: tuple[int, ...] = ()) -> np.ndarray:
    """A compiled form's array as the kernel reads it by address: never copied (a controller's memory is
    the one its ``reset`` clears), so ConfigError unless it is C-contiguous of `dtype` with these leading axes."""
    if not (isinstance(a, np.ndarray) and a.dtype == dtype and a.flags.c_contiguous and a.shape[:len(leading)] == leading
            and a.ndim == len(leading) + 1):
        got = f"{type(a).__name__} {getattr(a, 'dtype', '')} {getattr(a, 'shape', '')}"
        raise ConfigError(f"compiled_controller: its {name} must be a C-contiguous {np.dtype(dtype).name} array "
                          f"of shape {(*leading, 'n')}, got {got}")
    return a


def make_plan(sim: Any, bound: PlanInputs) -> Plan | None:
    """The fused path's plan for simulator `sim`, whose bound state is `bound`, when every component
    has a compiled form (see the module docstring), else None: the readable path."""
    field_packed = _packed_field(sim.field, sim.aggregation)
    field_law = None if field_packed is not None else _compiled_field(sim.field, sim.aggregation, sim.vehicle_params)
    if (field_packed is None and field_law is None) or not flies_compiled_controller(sim.controller):
        return None
    if type(sim.controller) is not FeedbackLinearisedLQR and bound.safety_filter is not None:
        return None  # the safety layer redoes the LQR's own step (controllers.compiled)
    if not isinstance(sim.autopilot, Autopilot):
        return None
    guard = None
    if is_stateful(bound.scene_predictor) and type(bound.scene_predictor) is not PerWorldPredictor:
        parts = getattr(bound.scene_predictor, "compiled_guard", lambda W, V: None)(sim.W, sim.V)
        if parts is None:  # its resets and due worlds: only a guard's pass has them compiled
            return None
        guarded, guard = parts
    ph, n_threads = sim.physics, 1
    if isinstance(ph, SerialPhysics):
        stepping, native = STEP_SERIAL, ph.native_step()
        if native is None:
            return None
    else:
        # at least _CHUNK_WORLDS worlds per thread of the batch's, each thread with its MjData (chunks: `_chunk_sizes`)
        n_threads = max(1, min(ph.batch.nthread, sim.W // _CHUNK_WORLDS))
        native = ph.native_step(n_threads)
        stepping = STEP_ROWS if native is not None else STEP_CALLER
        if native is None:
            n_threads = 1
    predictor, compiled, oracle_packed, per_world, oracle_law = sim.predictor, None, np.zeros(16), None, None
    if guard is not None:
        code, compiled = PRED_C, guarded
    elif type(predictor) is ZeroPredictor:
        code = PRED_ZERO
    elif type(predictor) is PerWorldPredictor:
        per_world = _per_world_tables(predictor, sim.W, sim.vehicle_params, bound.scene_predictor)
        if per_world is None:
            return None
        code = PRED_PER_WORLD
    elif type(predictor) is OraclePredictor:
        packed = _packed_field(predictor.field, predictor.aggregation)
        if packed is None:  # a field's compiled form, as the truth's
            oracle_law = _compiled_field(predictor.field, predictor.aggregation, sim.vehicle_params)
            if oracle_law is None:
                return None
        code, oracle_packed = PRED_ORACLE, np.zeros(16) if packed is None else packed
    else:
        compiled = getattr(bound.scene_predictor, "compiled", lambda: None)()  # told the scene's kinds (`_bind`)
        if compiled is None:
            return None
        code = PRED_C
    try:
        return Plan(sim, bound, stepping, native, field_packed, oracle_packed, code, compiled, n_threads, per_world,
                    guard, (field_law, oracle_law))
    except _NoPlan:
        return None


class Plan:
    """The fast path's bound state: the tables of `_fused_kernel` and every array they address.

    Built from a simulator's current components and bound state (`make_plan`); holding the
    arrays here keeps every address in the tables valid for the plan's lifetime.
    chunks: (n_threads, n, 4) int64, the n world ranges (`_chunk_sizes`) as thread t runs them, with
    its scratch MjData (see `_make_fused_kernel`); the threads take the ranges in turn from one
    counter (`sim.fork_join`).
    """

    def __init__(self, sim: Any, bound: PlanInputs, stepping: int, physics_native: tuple | None,
                 field_packed: np.ndarray, oracle_packed: np.ndarray, predictor_code: int,
                 compiled: CompiledPredictor | None, n_threads: int, per_world: dict[str, Any] | None = None,
                 guard: CompiledGuard | None = None,
                 laws: tuple[CompiledField | None, CompiledField | None] = (None, None)):
        W, V, cfg, r = sim.W, sim.V, sim.cfg, sim.cfg.rates
        ph = sim.physics
        self.revision = ph.revision
        self.stepping = stepping
        self.n_sub, self.noise_block = r.autopilot_per_control, cfg.noise_block  # autopilot ticks: a tick's, a block's
        pw_guards = per_world is not None and bool(per_world["pw_guard_fn"].any())
        self.row_layout, self.row_size = row_layout(W, V, bound.wind_on, guard is not None or pw_guards)
        wind_consts = sim.wind.kernel_constants() if bound.wind_on else (np.zeros(3), np.zeros(3), np.ones(3), np.eye(3), 1.0)
        lqr = type(sim.controller) is FeedbackLinearisedLQR  # else a compiled form (controllers.compiled)
        law = None if lqr else sim.controller.compiled_controller(W, V)
        keep: dict[str, np.ndarray] = {
            "layout": bound.layout, "noise": bound.noise, "cursor": bound.cursor, "pos_est": sim.pos_est,
            "vel_est": sim.vel_est, "t": sim.t, "next_prediction": sim.next_prediction, "due": bound.due,
            "field_enabled": sim.field_enabled, "turb": sim.turb, "rot_des": bound.rot_des,
            "yaw_rate_des": bound.yaw_rate_des, "thrust_acc": bound.thrust_acc, "mass_believed": bound.mass_believed,
            "ap_gain": bound.ap_gain, "max_thrust": bound.max_thrust, "active": sim.active,
            "f_hat": sim.f_hat, "tick_index": sim.tick_index, "status_new": bound.status_new,
            "kin": np.empty((5, W, V, 3)), "quat": np.empty((W, V, 4)), "rot": np.empty((W, V, 3, 3)),
            "quat_est": np.empty((W, V, 4)), "rot_est": np.empty((W, V, 3, 3)), "yaw": np.empty((W, V)),
            "applied": np.empty((W, V, 3)), "mean": np.empty((W, V, 3)), "pred": np.empty((W, V, 3)),
            "Kt": np.ascontiguousarray(sim.controller.K.T if lqr else np.zeros((7, 4)), dtype=np.float64),
            "field_packed": np.zeros(16) if field_packed is None else field_packed,
            "oracle_packed": oracle_packed, "gust": sim.gust_state, "wind_noise": bound.wind_noise,
            "wind_mean": wind_consts[0], "wind_sigma": wind_consts[1], "wind_length": wind_consts[2],
            "wind_axes": wind_consts[3], "air": np.empty((W, V, 3)), "vel_air": np.empty((W, V, 3)),
            "wind_acc": np.empty((W, V, 3)), "diverged": np.zeros(W, bool), "mocap_offset": sim.mocap_offset,
            # each vehicle's numbers and each pair's (sim.vehicle_params)
            "mass": sim.vehicle_params.mass, "drag_gain": sim.vehicle_params.drag_gain,
            "field_scale": sim.vehicle_params.field_scale, "radius_xy": sim.vehicle_params.collision_xy,
            "radius_z": sim.vehicle_params.collision_z,
        }
        per_world = per_world if per_world is not None else _per_world_tables(ZeroPredictor(), W, None)
        keep.update({name: a for name, a in per_world.items() if name.startswith("pw_")})
        self.per_world = per_world  # keeps the worlds' predictors' functions and constants alive
        if compiled is not None:
            keep["predictor_params"] = np.ascontiguousarray(compiled.params, dtype=np.float64)
            keep["predictor_iparams"] = np.ascontiguousarray(compiled.iparams, dtype=np.int64)
        if guard is not None:  # its state by address: the guard's own arrays, which its calls and resets share
            keep.update(guard_params=guard.params, guard_iparams=guard.iparams, guard_state=guard.state,
                        guard_applied=guard.applied)
        # the guard's monitor runs at the end of the kernel's tick (not when the caller steps the physics:
        # the kernel runs one autopilot tick per call then, and the simulator calls observe)
        self.monitors = guard is not None and guard.monitor != 0 and stepping != STEP_CALLER
        if self.monitors:
            keep.update(monitor_params=guard.monitor_params, monitor_iparams=guard.monitor_iparams, seen=guard.seen,
                        seen_t=guard.seen_t)
        safety = self.safety = bound.safety_filter  # (kept: its constants and C function, by address)
        if safety is not None:
            keep.update(safety_params=safety.params, safety_lower=safety.lower, safety_upper=safety.upper,
                        safety_state=safety.state)  # (its estimates: the readable path's too)
        # the truth's and the oracle's compiled forms (sim.field_contract), kept with their constants, by address;
        # a scene flies them as given: every pair's factor 1.0
        self.laws = field_law, oracle_law = laws
        keep["field_fn_scale"] = np.ones((V, V))
        if field_law is not None:
            keep["field_params"] = field_law.params
        if oracle_law is not None:
            keep["oracle_params"] = oracle_law.params
        sensor = self.sensor_law = bound.sensor_law  # (kept: its constants and state, by address; the state is
        if sensor is not None:  # the simulator's, which the readable path reads and its resets set)
            keep.update(sensor_params=sensor.params, sensor_state=sensor.state)
        if law is not None:  # (kept: its constants and memory, by address; the memory is the controller's own)
            keep.update(controller_params=_c_array(law.params, np.float64, "params"),
                        controller_state=_c_array(law.state, np.float64, "state", (W, V)))
        tab = dict.fromkeys(TAB, 0)
        tab.update(W=W, V=V, block=cfg.noise_block, n_sub=self.n_sub,
                   n_physics=r.physics_per_autopilot, stepping=stepping, predictor=predictor_code,
                   guard=int(guard is not None), guard_fn=0 if guard is None else int(guard.address),
                   pw_guarded=int(pw_guards), monitor_fn=int(guard.monitor) if self.monitors else 0,
                   seen_stride=guard.seen.strides[0] if self.monitors else 0,
                   safety_fn=0 if safety is None else safety.address,
                   controller_fn=0 if law is None else int(law.address),
                   controller_width=0 if law is None else law.state.shape[2],
                   field_fn=0 if field_law is None else int(field_law.address),
                   oracle_fn=0 if oracle_law is None else int(oracle_law.address),
                   sensor_fn=0 if sensor is None else int(sensor.address),
                   sensor_width=0 if sensor is None else sensor.state.shape[2])
        sizes = _chunk_sizes(W, n_threads, _TAIL_WORLDS)
        chunks = np.zeros((n_threads, len(sizes), 4), np.int64)  # as run by each thread: its own MjData
        bounds = np.concatenate([[0], np.cumsum(sizes)])
        chunks[:, :, 0], chunks[:, :, 1] = bounds[:-1], bounds[1:]
        if stepping == STEP_SERIAL:
            step_fn, model, data, warnings = physics_native
            if warnings.dtype != np.int32 or warnings.strides[0] % 4 or warnings.size <= FATAL_MAX:
                raise _NoPlan("unexpected layout of MuJoCo's warning counts")
            self.warnings = warnings
            tab.update(step_fn=step_fn, model=model, data=data, warnings=warnings.ctypes.data,
                       warning_stride=warnings.strides[0] // 4)
        elif stepping == STEP_ROWS:
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
        self.compiled, self.guard = compiled, guard  # keep the predictor's and the guard's functions referenced
        if compiled is not None:
            tab["predictor_fn"] = int(compiled.address)
        storage = {"kin": "pos", "t": "t", "quat": "quat", "quat_est": "quat_est", "yaw": "yaw_est",
                   "applied": "field_applied", "ref_pos": "ref_pos", "ref_vel": "ref_vel", "ref_acc": "ref_acc",
                   "u_cmd": "u_cmd", "f_hat": "f_hat", "mean": "field_mean", "wind": "wind", "wind_acc": "wind_acc",
                   "guard": "applied"}
        for slot, name in storage.items():
            if name in self.row_layout:
                tab["row_" + slot] = self.row_layout[name][0]
        self.tab = np.array([tab[name] for name in TAB], dtype=np.int64)
        self.chunks = chunks
        self.own_chunks = chunks[0]  # the calling thread's (a view made once, not each tick)
        self.n_threads = n_threads
        limits = sim.controller if lqr else None  # (the LQR's limits; a compiled form keeps its own in params)
        fc = {
            "sigma_p": bound.sigma_p, "sigma_att": bound.sigma_att, "kf_gain_p": bound.kf_gain_p,
            "kf_gain_v": bound.kf_gain_v, "ou_a": bound.ou_a, "ou_b": bound.ou_b,
            "intensity": bound.turbulence_intensity,
            "dt": r.autopilot_dt, "prediction_period": bound.prediction_period, "lookahead": r.control_dt,
            "tan_tilt": math.tan(limits.max_tilt) if lqr else 0.0, "min_vertical": limits.min_vertical if lqr else 0.0,
            "min_airspeed": wind_consts[4], "max_distance": cfg.max_distance, "ground": cfg.ground_clearance,
        }
        self.fc = np.array([float(fc[name]) for name in FC])
        self.leading_args = (self.tab, self.fc, ph.qpos, ph.qvel, ph.ctrl, ph.xfrc_applied)  # of every kernel call
        self.kernel = FUSED_KERNELS[int(bound.wind_on)]
        self.no_action = np.zeros((W, V, 3))  # stands in for an absent residual or override


_CHUNK_WORLDS = 4  # fewest worlds per thread of the fused kernel's work (12 worlds: 1.2x faster on 2 threads than 8)
# fewest worlds in a chunk: the last chunks are the wait for the slower thread (64 worlds on 2 threads:
# a tail of 2-world chunks ticks in 0.974x the time of one of 4-world chunks, the median of 120
# interleaved pairs of 20-tick windows)
_TAIL_WORLDS = 2


def _chunk_sizes(n_worlds: int, n_threads: int, smallest: int) -> list[int]:
    """Worlds per chunk, large first and halving (guided scheduling): a thread that starts late or
    runs slower takes the small chunks at the end, so the threads finish together (64 worlds on
    2 threads, smallest 2: 16, 16, 8, 8, 4, 4, 2, 2, 2, 2; with smallest 4, 1.04x the speed of 8
    equal chunks, measured). One chunk for one thread."""
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


def _per_world_tables(predictor: Any, W: int, vehicles: Any, bound: Any = None) -> dict[str, Any] | None:
    """The fused kernel's tables for a `PerWorldPredictor` (a `ZeroPredictor`: all worlds zero): per
    world its predictor's code, C function, constants' addresses and oracle field, and for a guard's
    worlds the guard's pass, constants and the addresses of the world's rows of its state (pw_*; 0:
    no guard); the compiled forms (kept alive); None when one of its predictors has no compiled form.
    bound: the same predictor as the scene binds it (`sim.vehicle_params.scene_predictor`), whose
    guards are those the simulator calls and resets on the readable path: their state is the one."""
    if isinstance(predictor, PerWorldPredictor) and predictor.n_worlds != W:
        return None  # the readable path names the mismatch
    groups = predictor.groups if isinstance(predictor, PerWorldPredictor) else [np.arange(W)]
    predictors = predictor.predictors if isinstance(predictor, PerWorldPredictor) else [predictor]
    out: dict[str, Any] = {"pw_code": np.zeros(W, np.int64), "pw_fn": np.zeros(W, np.int64),
                           "pw_params": np.zeros(W, np.int64), "pw_iparams": np.zeros(W, np.int64),
                           "pw_oracle": np.zeros((W, 16)), "compiled": [],
                           **{f"pw_guard_{k}": np.zeros(W, np.int64) for k in ("fn", "params", "iparams", "state",
                                                                              "applied")}}
    scene_bound = bound.predictors if isinstance(bound, PerWorldPredictor) else predictors
    for p, own, worlds in zip(predictors, scene_bound, groups):
        if type(p) is ZeroPredictor:
            continue
        if is_stateful(own):  # a guard (its group's state: row k of its arrays for the group's k-th world)
            parts = getattr(own, "compiled_guard", lambda W, V: None)(len(worlds), vehicles.n_vehicles)
            if parts is None:
                return None
            p, guard = parts  # (its model's compiled form, flown below)
            out["compiled"].append(guard)
            rows = np.arange(len(worlds))
            out["pw_guard_fn"][worlds] = guard.address
            out["pw_guard_state"][worlds] = guard.state.ctypes.data + rows * guard.state.strides[0]
            out["pw_guard_params"][worlds], out["pw_guard_iparams"][worlds] = (guard.params.ctypes.data,
                                                                               guard.iparams.ctypes.data)
            out["pw_guard_applied"][worlds] = guard.applied.ctypes.data + rows * guard.applied.strides[0]
        if type(p) is OraclePredictor:
            packed = _packed_field(p.field, p.aggregation)
            if packed is None:
                return None
            out["pw_code"][worlds], out["pw_oracle"][worlds] = PRED_ORACLE, packed
            continue
        compiled = (p if isinstance(p, CompiledPredictor)  # (a guard's model, above)
                    else getattr(told_kinds(p, vehicles), "compiled", lambda: None)())
        if compiled is None:
            return None
        params = np.ascontiguousarray(compiled.params, dtype=np.float64)
        iparams = np.ascontiguousarray(compiled.iparams, dtype=np.int64)
        out["compiled"].append((compiled, params, iparams))
        out["pw_code"][worlds], out["pw_fn"][worlds] = PRED_C, int(compiled.address)
        out["pw_params"][worlds], out["pw_iparams"][worlds] = params.ctypes.data, iparams.ctypes.data
    return out


def _packed_field(field: Any, aggregation: Any) -> np.ndarray | None:
    """A field's constants for the fused kernel (`DownwashField` with scalar constants and linear
    aggregation, whose `pairwise` is `sim.field_kernels.pairwise_kernel`), else None."""
    if aggregation is not None and not isinstance(aggregation, LinearSuperposition):
        return None
    if not isinstance(field, DownwashField) or type(field).pairwise is not DownwashField.pairwise:
        return None
    if type(field).__call__ is not DownwashField.__call__:
        return None
    packed = field.packed
    if packed is None or packed.shape != (16,):
        return None
    return np.ascontiguousarray(packed, dtype=np.float64)


def _compiled_field(field: Any, aggregation: Any, vehicles: Any) -> CompiledField | None:
    """A field's compiled form (`sim.field_contract`, checked: ConfigError for one the kernel cannot read)
    under linear aggregation, for a field without memory that every pair of the scene flies as given
    (`sim.vehicle_params.scene_field`; a pair of kinds with a field of its own flies the readable path),
    else None."""
    if aggregation is not None and not isinstance(aggregation, LinearSuperposition):
        return None
    make = getattr(field, "compiled_field", None)
    if not callable(make) or is_stateful_field(field) or scene_field(field, vehicles) is not field:
        return None
    return checked_field(make(), type(field).__name__)
