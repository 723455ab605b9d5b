"""One field per world: W stateless fields evaluated as one batched field, world w with field w.

`DownwashField` takes array constants, one per world; `MomentumWake`, `JetWake` and
`PybulletDownwash` convert theirs with float(). To fly such a field with different constants in
each world (the envs' `field_randomization`), build one field per world (`dataclasses.replace`)
and wrap them: `PerWorldFields(fields)` offers what the simulator, the aggregation laws and the
oracle predictor call on a field,

- ``__call__(p_a, v_a, R_a, p_b, v_b, **kw)`` on inputs whose broadcast batch shape starts with
  the world axis, (W, ...) (or 1, the same inputs for every world): world w's slice of each
  input (an input without the world axis, broadcast from the left, as it is) through field w;
- ``pairwise(pos, vel, rot)`` and ``pair_forces(pos, vel, rot)`` for (W, V, ...) states: world w's
  `sim.field.pairwise_field` / `pairwise_forces` of field w (a `DownwashField` of scalar constants
  takes its compiled kernel there);
- ``for_kinds(leader, follower)`` (`sim.vehicle_params.pair_field`): the wrapper of each world's
  field for that pair of kinds; ``describe()``: every world's field's provenance.

A loop over worlds in Python: one evaluation per world per call, so its cost grows with W (fine
for the tens of worlds of an env; a large batch of a randomised `DownwashField` should keep array
constants instead). It has no compiled form, so a simulator flying it takes the readable path
(`sim.plan._packed_field` accepts only a `DownwashField`). Fields with memory
(`sim.field_memory`) are refused: their state is batched over worlds already.

Shapes: W worlds, V vehicles; positions m, velocities m/s, accelerations m/s^2, world frame.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.provenance import describe
from sim.field import pairwise_field, pairwise_forces
from sim.field_memory import is_stateful_field
from sim.vehicle_params import pair_field

__all__ = ["PerWorldFields"]

_TRAILING = ((3,), (3,), (3, 3), (3,), (3,))  # p_a, v_a, R_a, p_b, v_b: one sample's shape


class PerWorldFields:
    """W fields flown as one: world w evaluated with ``fields[w]`` (module doc).

    fields: a sequence of W >= 1 callable, stateless fields with `DownwashField`'s call signature.
    ConfigError for an empty sequence, a field that is not callable, or one with memory.
    """

    def __init__(self, fields: Sequence[Any]):
        fields = tuple(fields)
        if not fields:
            raise ConfigError("PerWorldFields: expected one field per world, got none")
        for w, f in enumerate(fields):
            if is_stateful_field(f):
                raise ConfigError(f"PerWorldFields: fields[{w}] ({type(f).__name__}) has memory; allowed: "
                                  "stateless fields (a field with memory batches its own state over worlds)")
            if not callable(f):
                raise ConfigError(f"PerWorldFields: fields[{w}] is a {type(f).__name__}, not a field "
                                  "callable as field(p_a, v_a, R_a, p_b, v_b)")
        self.fields = fields

    @property
    def n_worlds(self) -> int:
        return len(self.fields)

    def __len__(self) -> int:
        return len(self.fields)

    def __repr__(self) -> str:
        return f"PerWorldFields({len(self.fields)} x {type(self.fields[0]).__name__})"

    def describe(self) -> dict[str, Any]:
        """Stable provenance: this class and each world's field's description, in world order."""
        return {"type": f"{type(self).__module__}.{type(self).__qualname__}",
                "fields": [describe(f) for f in self.fields]}

    def for_kinds(self, leader: Any, follower: Any) -> "PerWorldFields":
        """Each world's field for a `leader` and `follower` of these kinds (`sim.vehicle_params.pair_field`)."""
        paired = tuple(pair_field(f, leader, follower) for f in self.fields)
        return self if all(p is f for p, f in zip(paired, self.fields)) else PerWorldFields(paired)

    # ------------------------------------------------------------------ evaluation
    def __call__(self, p_a: np.ndarray, v_a: np.ndarray, R_a: np.ndarray, p_b: np.ndarray, v_b: np.ndarray,
                 **kwargs: Any) -> np.ndarray:
        """(W, ..., 3) m/s^2: world w's inputs through field w.

        p_a, v_a, p_b, v_b: (..., 3) m, m/s and R_a (..., 3, 3), world frame, whose batch shapes
        broadcast to (W, ...) or (1, ...); keyword arrays (e.g. `thrust`, (...)) are sliced alike.
        ConfigError when the broadcast batch has no leading world axis of length W or 1.
        """
        args = [np.asarray(x) for x in (p_a, v_a, R_a, p_b, v_b)]
        batches = [x.shape[: x.ndim - len(t)] for x, t in zip(args, _TRAILING)]
        kw_arrays = {k: np.asarray(v) for k, v in kwargs.items() if v is not None}
        batch = np.broadcast_shapes(*batches, *(v.shape for v in kw_arrays.values()))
        W = len(self.fields)
        if not batch or batch[0] not in (1, W):
            raise ConfigError(f"PerWorldFields: expected inputs batched over {W} worlds, (W, ..., 3) with W = {W}, "
                              f"got batch shape {batch}")
        nb = len(batch)

        def world(x: np.ndarray, b: tuple[int, ...], w: int) -> np.ndarray:
            if len(b) < nb:  # broadcast from the left: no world axis of its own
                return x
            return x[0] if x.shape[0] == 1 else x[w]

        out = np.empty((W, *batch[1:], 3))
        for w, field in enumerate(self.fields):
            sliced = [world(x, b, w) for x, b in zip(args, batches)]
            kw = {k: (world(kw_arrays[k], kw_arrays[k].shape, w) if k in kw_arrays else v) for k, v in kwargs.items()}
            out[w] = field(*sliced, **kw)
        return out

    def pairwise(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(W, V, 3) m/s^2: world w's `pairwise_field(fields[w], ...)`; pos, vel (W, V, 3), rot (W, V, 3, 3)."""
        self._check_worlds(pos)
        out = np.empty(pos.shape)
        for w, field in enumerate(self.fields):
            out[w] = pairwise_field(field, pos[w: w + 1], vel[w: w + 1], rot[w: w + 1])[0]
        return out

    def pair_forces(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(W, V_leader, V_follower, 3) m/s^2: world w's `pairwise_forces(fields[w], ...)`, 0 on the diagonal."""
        self._check_worlds(pos)
        W, V = pos.shape[:2]
        out = np.empty((W, V, V, 3))
        for w, field in enumerate(self.fields):
            out[w] = pairwise_forces(field, pos[w: w + 1], vel[w: w + 1], rot[w: w + 1])[0]
        return out

    def _check_worlds(self, pos: np.ndarray) -> None:
        if pos.shape[0] != len(self.fields):
            raise ConfigError(f"PerWorldFields: {len(self.fields)} worlds' fields, states of {pos.shape[0]} worlds "
                              f"(pos {pos.shape})")
