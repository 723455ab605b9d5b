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

The protocol, `FieldMemory` and the check live in `sim.stateful_field` (below `sim.field`, which
checks a field before any flight) and are re-exported here; this module adds the oracle, which
needs the predictors.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from sim.predictor import OraclePredictor, PerWorldPredictor
from sim.stateful_field import FieldMemory, StatefulField, check_stateful_field, combined, is_stateful_field

__all__ = ["is_stateful_field", "StatefulField", "FieldMemory", "MemoryOracle", "kept_memory", "memory_oracle",
           "check_stateful_field"]


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
    return FieldMemory(field, W, V, dt, kinds) if is_stateful_field(field) else None


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
    if is_stateful_field(predictor.field):
        raise ConfigError(f"predictor: an OraclePredictor of the field with memory {type(predictor.field).__name__} "
                          "knows the wake only when the simulator flies that same field object (field=...)")
    return None
