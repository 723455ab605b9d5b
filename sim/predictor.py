"""The predictor slot: how a downwash model reaches the control loop.

`sim` never imports `downwash`; a learned model enters through this small
interface. The stepping loop calls the predictor at 45 Hz and holds the result
between calls; the controller subtracts it: `u = a_ref - K (x - x_ref) - f_hat`.

A predictor may also offer a compiled form, `compiled() -> CompiledPredictor | None`:
the address of a C function of `PREDICTOR_SIGNATURE` (a numba `cfunc`) that computes
exactly what `__call__` returns. The simulator's fused loop then calls it without
leaving compiled code (see `sim.simulator`); `__call__` stays the readable form, and
the predictor's own tests compare the two. `ZeroPredictor` and `OraclePredictor` need
no such function: the loop knows them.

A predictor may keep state between calls (`is_stateful`: e.g. a learned model with memory, which
remembers the estimates of its last calls). It then has ``reset(worlds)``, which the simulator
calls when it resets those worlds, and its call takes ``due=`` (W,) bool: the worlds whose
prediction is due now (the loop calls it when any world's is due; only the due worlds' rows are
used, and only their state should advance). Such a predictor serves one simulator at a time.
A predictor that scales its model's output (a guard) may hold ``applied`` (W, V): the fraction of
the prediction applied at its last due call, which the simulator logs per tick and vehicle. Such a
predictor flies the fused loop too (alone or in a `PerWorldPredictor`) when ``compiled_guard(W, V)``
returns its inner model's `CompiledPredictor` and a `CompiledGuard`: a C function of
`GUARD_SIGNATURE` that scales the inner prediction in place, advancing its state (``state``,
(W, V, `GUARD_STATE_WIDTH`), laid out as the guard likes) in the due worlds only and writing
``applied`` (W, V) there, exactly as ``__call__`` does; the loop holds both arrays by address, and
``reset`` resets ``state`` in place.
A predictor may also learn from the flight: ``observe(t, vel_est, u_cmd)``, when it has one (not
None), is called after every tick with the tick's row's (W,) times, (W, V, 3) estimated velocities
and (W, V, 3) applied commands (`sim.logs.ARRAY_SPECS`), from which it can tell the force each
vehicle felt (a guard's monitor, `downwash.guard`).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol, Sequence, runtime_checkable

import numpy as np
from numba import types as _nb

from downwash_core.errors import ConfigError
from downwash_core.state import VehicleStates
from sim.aggregation import wake_field

__all__ = [
    "VehicleStates",
    "Predictor",
    "ZeroPredictor",
    "OraclePredictor",
    "PerWorldPredictor",
    "CompiledPredictor",
    "PREDICTOR_SIGNATURE",
    "CompiledGuard",
    "GUARD_SIGNATURE",
    "GUARD_STATE_WIDTH",
    "MONITOR_SIGNATURE",
    "is_stateful",
]

_F64P, _I64P = _nb.CPointer(_nb.float64), _nb.CPointer(_nb.int64)
# void f(n_worlds, n_vehicles, pos, vel, rot, true_pos, true_vel, true_rot, params, iparams, out):
# the estimated states (W, V, 3) m, (W, V, 3) m/s, (W, V, 3, 3) and the true ones (velocity
# relative to the air, see `Predictor`), all C-contiguous float64; params / iparams the
# predictor's own constants (float64 / int64); out (W, V, 3) m/s^2, written in full.
PREDICTOR_SIGNATURE = _nb.void(_nb.int64, _nb.int64, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _I64P, _F64P)
# void g(n_worlds, n_vehicles, pos, vel, rot, due, pred, state, applied, params, iparams): the
# estimated states as above; due (W,) bool (one byte each); pred (W, V, 3) m/s^2 the inner prediction,
# scaled in place; state (W, V, GUARD_STATE_WIDTH) the guard's state and applied (W, V) its applied
# fraction, both advanced in the due worlds only; params / iparams the guard's own constants.
GUARD_STATE_WIDTH = 8  # float64 per world and vehicle of a guard's state (its layout is the guard's)
GUARD_SIGNATURE = _nb.void(_nb.int64, _nb.int64, _F64P, _F64P, _F64P, _nb.CPointer(_nb.uint8), _F64P, _F64P, _F64P,
                           _F64P, _I64P)
# void m(n_worlds, n_vehicles, t, vel_est, u_cmd, state, seen, seen_t, params, iparams): a guard's
# monitor after a tick (its ``observe``), from the tick's row: t (W,) s, vel_est (W, V, 3) m/s and
# u_cmd (W, V, 3) m/s^2; it advances the guard's state (W, V, GUARD_STATE_WIDTH), its own memory
# seen (W, V, iparams[0]) and seen_t (W,) in place; params / iparams its own constants.
MONITOR_SIGNATURE = _nb.void(_nb.int64, _nb.int64, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _I64P)


class CompiledPredictor(NamedTuple):
    """A predictor's compiled form for the simulator's fused loop.

    address: of a C function of `PREDICTOR_SIGNATURE` (e.g. `numba.cfunc(PREDICTOR_SIGNATURE)(f).address`)
      that writes exactly the predictor's `__call__` result into `out`.
    params: (n,) float64 and iparams: (m,) int64, C-contiguous, passed to it unchanged; the
      predictor keeps them (and the function) alive as long as it lives.
    """

    address: int
    params: np.ndarray
    iparams: np.ndarray


class CompiledGuard(NamedTuple):
    """A guard's compiled pass for the fused loop (module doc): the address of a C function of
    `GUARD_SIGNATURE`, its params (float64) and iparams (int64), and the float64 arrays it advances,
    ``state`` (W, V, `GUARD_STATE_WIDTH`) and ``applied`` (W, V), C-contiguous and owned by the guard.
    Optionally its ``observe`` compiled: the address of a C function of `MONITOR_SIGNATURE` (0: none,
    the simulator calls ``observe``), its constants and its memory (``seen`` (W, V, n) and
    ``seen_t`` (W,)), which the fused tick runs after each tick instead."""

    address: int
    params: np.ndarray
    iparams: np.ndarray
    state: np.ndarray
    applied: np.ndarray
    monitor: int = 0
    monitor_params: np.ndarray | None = None
    monitor_iparams: np.ndarray | None = None
    seen: np.ndarray | None = None
    seen_t: np.ndarray | None = None


@runtime_checkable
class Predictor(Protocol):
    """Anything that predicts the downwash acceleration on each vehicle.

    `estimated` is what the vehicles know (Kalman-filtered motion capture: positions,
    GROUND velocities, the motion-capture attitude), what a lab measures and all a
    learned model may use. `true` is the simulator's state, for oracles and
    diagnostics only: true positions and attitudes, and `true.vel` the velocity
    RELATIVE TO THE AMBIENT AIR (v - u_air; the ground velocity when there is no wind,
    see `sim.simulator`), the velocity that shapes a wake.
    Returns (W, V, 3) m/s^2, world frame, the summed effect of all other vehicles.
    """

    def __call__(self, estimated: VehicleStates, true: VehicleStates) -> np.ndarray: ...


def is_stateful(predictor: Any) -> bool:
    """Whether a predictor keeps state between calls: it has ``reset(worlds)`` and takes ``due=``
    (module doc), unless its ``stateful`` attribute says it keeps none now."""
    return callable(getattr(predictor, "reset", None)) and bool(getattr(predictor, "stateful", True))


class ZeroPredictor:
    """No model: the baseline controller."""

    def __call__(self, estimated: VehicleStates, true: VehicleStates) -> np.ndarray:
        return np.zeros_like(estimated.pos)


class OraclePredictor:
    """The true mean field (no turbulence) at the true state: the best any model can do.

    field: the ground-truth field; aggregation: how the wakes of several leaders combine
    (`sim.aggregation`, None: linear superposition), as in the simulator.
    """

    def __init__(self, field: Any, aggregation: Any = None):
        self.field = field
        self.aggregation = aggregation

    def __call__(self, estimated: VehicleStates, true: VehicleStates) -> np.ndarray:
        return wake_field(self.field, true.pos, true.vel, true.rot, self.aggregation)


class PerWorldPredictor:
    """Routes groups of worlds to different predictors (one batch, many conditions).

    predictors[i] serves the worlds where `assignment == i`.
    """

    def __init__(self, predictors: Sequence[Predictor], assignment: np.ndarray):
        assignment = np.asarray(assignment)
        if assignment.ndim != 1:
            raise ConfigError(f"assignment: expected a 1-D array of predictor indices, got shape {assignment.shape}")
        if assignment.size and (assignment.min() < 0 or assignment.max() >= len(predictors)):
            raise ConfigError(
                f"assignment: indices must lie in [0, {len(predictors) - 1}], "
                f"got [{assignment.min()}, {assignment.max()}]"
            )
        self.predictors = list(predictors)
        self.groups = [np.flatnonzero(assignment == i) for i in range(len(predictors))]
        self.n_worlds = assignment.size

    @property
    def stateful(self) -> bool:
        """Whether any of its predictors keeps state (`is_stateful`)."""
        return any(is_stateful(p) for p in self.predictors)

    @property
    def applied(self) -> np.ndarray | None:
        """(W, V) the fraction applied at the last call by the predictors that report one (module
        doc), NaN in the other worlds; None when none reports one."""
        parts = [(a, g) for p, g in zip(self.predictors, self.groups) if (a := getattr(p, "applied", None)) is not None]
        if not parts:
            return None
        out = np.full((self.n_worlds, parts[0][0].shape[1]), np.nan)
        for a, worlds in parts:
            out[worlds] = a
        return out

    @property
    def observe(self) -> Any:
        """Its predictors' ``observe`` (module doc), each given its worlds' rows; None when none has one."""
        observers = [(p.observe, g) for p, g in zip(self.predictors, self.groups)
                     if getattr(p, "observe", None) is not None and g.size]
        if not observers:
            return None

        def observe(t: np.ndarray, vel_est: np.ndarray, u_cmd: np.ndarray) -> None:
            for fn, worlds in observers:
                fn(t[worlds], vel_est[worlds], u_cmd[worlds])

        return observe

    def reset(self, worlds: np.ndarray | None = None) -> None:
        """Reset the state of the stateful predictors (`is_stateful`) in these worlds (None: all)."""
        for predictor, group in zip(self.predictors, self.groups):
            if is_stateful(predictor):
                predictor.reset(None if worlds is None else np.flatnonzero(np.isin(group, worlds)))

    def __call__(self, estimated: VehicleStates, true: VehicleStates, due: np.ndarray | None = None) -> np.ndarray:
        if estimated.pos.shape[0] != self.n_worlds:
            raise ValueError(f"PerWorldPredictor built for {self.n_worlds} worlds, called with {estimated.pos.shape[0]}")
        out = np.zeros_like(estimated.pos)
        for predictor, worlds in zip(self.predictors, self.groups):
            if worlds.size and not isinstance(predictor, ZeroPredictor):
                when = {"due": due[worlds]} if due is not None and is_stateful(predictor) else {}
                out[worlds] = predictor(estimated.select(worlds), true.select(worlds), **when)
        return out
