"""A field with memory: what it offers (`StatefulField`, `is_stateful_field`), its wake over a batch of worlds
(`FieldMemory`) and the check that it works (`check_stateful_field`).

These sit below `sim.field`, whose `check_field` steps a stateful field before any flight, and
below `sim.aggregation`: they combine per-pair forces by a law they are given and know the
linear one only as the sum over leaders. `sim.field_memory` adds what needs the predictors (the
oracle that reads a simulator's wake) and re-exports these names, where users import them.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol, runtime_checkable

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.vehicles import DEFAULT_VEHICLE

__all__ = ["StatefulField", "is_stateful_field", "FieldMemory", "combined", "check_stateful_field"]

_METHODS = ("initial_state", "step", "forces")


@runtime_checkable
class StatefulField(Protocol):
    """A field with memory, as the simulator steps it (`FieldMemory`) in place of calling a law.

    ``state`` is a NamedTuple (or dataclass) of arrays whose leading axis is the world. It may
    also offer ``for_vehicles(kinds) -> field``: the same field for V vehicles of these kinds.
    """

    def initial_state(self, n_worlds: int, n_vehicles: int) -> Any:
        """An empty wake for W worlds of V vehicles."""

    def step(self, state: Any, dt: float, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray,
             thrust: Any = None, wind: Any = None) -> Any:
        """Advance the wake in place by dt (s)."""

    def forces(self, state: Any, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(W, V, V, 3) m/s^2: each vehicle's wake (axis 1) on each vehicle (axis 2), diagonal 0."""


def is_stateful_field(field: Any) -> bool:
    """Whether `field` is a field with memory (`StatefulField`: each of its methods callable)."""
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
    """(W, V, 3) m/s^2: per-pair forces (W, V, V, 3) at (pos, rot) combined by `law` (None: linear, the
    sum over leaders that `sim.aggregation.LinearSuperposition.combine` computes)."""
    forces, pos, rot = last
    if law is None:
        return np.asarray(forces, dtype=np.float64).sum(axis=-3)
    return np.asarray(law.combine(forces, pos, rot))


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
