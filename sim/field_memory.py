"""A ground truth with memory in the loop: a stateful field's state across a simulator's worlds.

Most fields are laws of the states at this instant (`sim.field`: ``field(p_a, v_a, R_a, p_b,
v_b)``). A *stateful* field remembers what the vehicles shed (`sim.fields.shed.ShedWake`: wake
elements carried down by their own induced velocity and by the wind) and offers

    initial_state(W, V) -> state           an empty wake for W worlds of V vehicles
    step(state, dt, pos, vel, rot, thrust=None, wind=None)   advance it in place by dt (s)
    forces(state, pos, vel, rot) -> (W, V, V, 3) m/s^2        each vehicle's wake (axis 1)
                                                             on each vehicle (axis 2), diagonal 0

with ``state`` a NamedTuple (or dataclass) of arrays whose leading axis is the world.
`FieldMemory` holds that state for a `sim.simulator.Simulator`: it steps the wake once per
autopilot tick with the true states and the wind at the vehicles (the wake is convected by
the air), combines the per-pair forces by the aggregation law, and resets a world's wake
with the world. A flight with a stateful field flies the simulator's readable path (the fused
tick has no pass for it yet); an `OraclePredictor` of the same field reads the per-pair forces
the simulator has just computed, combined by its own law, so it sees the same truth.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.vehicles import DEFAULT_VEHICLE
from sim.aggregation import LinearSuperposition
from sim.predictor import OraclePredictor, PerWorldPredictor

__all__ = ["is_stateful", "FieldMemory", "MemoryOracle", "kept_memory", "memory_oracle", "check_stateful_field"]

_METHODS = ("initial_state", "step", "forces")


def is_stateful(field: Any) -> bool:
    """Whether `field` is a field with memory (the protocol of the module docstring)."""
    return all(callable(getattr(field, m, None)) for m in _METHODS)


def _arrays(state: Any) -> dict[str, np.ndarray]:
    """The arrays of a state (NamedTuple or dataclass), by name."""
    items = state._asdict() if hasattr(state, "_asdict") else {f.name: getattr(state, f.name)
                                                                  for f in dataclasses.fields(state)}
    return {k: v for k, v in items.items() if isinstance(v, np.ndarray)}


class FieldMemory:
    """A stateful field's wake over W worlds of V vehicles, stepped every dt (s).

    source: the field the simulator flies; kinds: each vehicle's kind name, given to a field with
    ``for_vehicles(kinds)`` unless every vehicle is the paper quad (`field`: the field so bound)."""

    def __init__(self, source: Any, W: int, V: int, dt: float, kinds: Any = ()):
        bind = getattr(source, "for_vehicles", None)
        mixed = any(k != DEFAULT_VEHICLE for k in kinds)
        self.source, self.field = source, bind(list(kinds)) if mixed and callable(bind) else source
        self.W, self.V, self.dt = W, V, float(dt)
        self.state = self.field.initial_state(W, V)
        self.last = (np.zeros((W, V, V, 3)), None, None)  # the latest `advance`'s (forces, pos, rot): an oracle's

    def reset(self, worlds: np.ndarray) -> None:
        """Empty the wakes of these worlds (their rows of a fresh state)."""
        fresh = _arrays(self.field.initial_state(self.W, self.V))
        for name, a in _arrays(self.state).items():
            if a.ndim and a.shape[0] == self.W:
                a[worlds] = fresh[name][worlds]
        self.last[0][worlds] = 0.0

    def advance(self, pos: np.ndarray, vel: np.ndarray, vel_air: np.ndarray, rot: np.ndarray,
                wind: np.ndarray | None, law: Any = None) -> np.ndarray:
        """Step the wake by dt with the vehicles' true states (pos, vel (W, V, 3) over the ground, rot
        (W, V, 3, 3)) and each world's air velocity (wind (W, 3) m/s or None), then the force on every
        vehicle (W, V, 3) from the wake, at its velocity relative to the air (vel_air), combined by
        `law` (None: linear superposition)."""
        self.field.step(self.state, self.dt, pos, vel, rot, wind=wind)
        self.last = (np.asarray(self.field.forces(self.state, pos, vel_air, rot)), pos, rot)
        return combined(self.last, law)


def combined(last: tuple, law: Any = None) -> np.ndarray:
    """(W, V, 3) m/s^2: per-pair forces (W, V, V, 3) at (pos, rot) combined by `law` (None: linear)."""
    forces, pos, rot = last
    return np.asarray((LinearSuperposition() if law is None else law).combine(forces, pos, rot))


class MemoryOracle:
    """The oracle of a stateful field: the per-pair forces the simulator computed last (it knows the wake),
    combined by the oracle's own aggregation law, as an `OraclePredictor` combines its field's; of the
    given worlds only (indices, None: all), for the worlds a `PerWorldPredictor` gives it."""

    def __init__(self, memory: FieldMemory, aggregation: Any = None, worlds: np.ndarray | None = None):
        self.memory, self.aggregation, self.worlds = memory, aggregation, worlds

    def __call__(self, estimated: Any, true: Any = None) -> np.ndarray:
        last = self.memory.last
        if self.worlds is not None:
            last = tuple(None if a is None else a[self.worlds] for a in last)
        return combined(last, self.aggregation)

    def describe(self) -> dict[str, Any]:
        return {"type": "oracle", "field": getattr(self.memory.source, "describe", lambda: {})()}


def kept_memory(memory: FieldMemory | None, field: Any, W: int, V: int, dt: float,
                kinds: Any = ()) -> FieldMemory | None:
    """A simulator's memory for `field`: the one it has while the field is the same (the wake lives on
    when other components change), a fresh one for a new stateful field, None for a field without memory."""
    if memory is not None and memory.source is field:
        return memory
    return FieldMemory(field, W, V, dt, kinds) if is_stateful(field) else None


def memory_oracle(memory: FieldMemory | None, predictor: Any, worlds: np.ndarray | None = None) -> Any:
    """The oracle that reads `memory` when `predictor` is an `OraclePredictor` of its field (or a
    `PerWorldPredictor` with such oracles among its predictors: a copy with them replaced), else None.
    ConfigError for the oracle of a field with memory that the simulator does not fly: no one steps its wake."""
    if type(predictor) is PerWorldPredictor:
        inner = [memory_oracle(memory, p, group) for p, group in zip(predictor.predictors, predictor.groups)]
        if all(p is None for p in inner):
            return None
        out = copy.copy(predictor)
        out.predictors = [p if q is None else q for p, q in zip(predictor.predictors, inner)]
        return out
    if type(predictor) is not OraclePredictor:
        return None
    if memory is not None and predictor.field is memory.source:
        return MemoryOracle(memory, predictor.aggregation, worlds)
    if is_stateful(predictor.field):
        raise ConfigError(f"predictor: an OraclePredictor of the field with memory {type(predictor.field).__name__} "
                          "knows the wake only when the simulator flies that same field object (field=...)")
    return None


def check_stateful_field(field: Any, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, label: str,
                         finite: bool = True) -> None:
    """ConfigError unless a stateful field steps and returns (W, V, V, 3) per-pair forces, finite unless
    `finite` is False: a few steps on the given states (pos, vel (W, V, 3), rot (W, V, 3, 3))."""
    W, V = pos.shape[:2]
    try:
        memory = FieldMemory(field, W, V, 0.01)
        for _ in range(5):
            out = memory.advance(pos, vel, vel, rot, None)
        forces = memory.last[0]
    except (TypeError, ValueError, IndexError, AttributeError) as e:
        raise ConfigError(f"{label}: a field with memory must offer initial_state(W, V), step(state, dt, pos, vel, "
                          f"rot, thrust=None, wind=None) and forces(state, pos, vel, rot); using it failed: "
                          f"{type(e).__name__}: {e}") from e
    if forces.shape != (W, V, V, 3):
        raise ConfigError(f"{label}: forces(...) must be (W, V, V, 3) = {(W, V, V, 3)}, got {forces.shape}")
    if finite and not np.all(np.isfinite(out)):
        raise ConfigError(f"{label}: returned non-finite accelerations (m/s^2) for followers near a leader: "
                          f"{out.tolist()}")
