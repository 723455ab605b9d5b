"""A field's compiled form: the contract by which a field of your own flies the fused tick.

The fused tick (`sim.fused`) runs the paper's field (`sim.field.DownwashField`) through its own kernel;
any other field joins it through one C function of `FIELD_SIGNATURE`, which the field returns from
``compiled_field()`` as a `CompiledField`:

    void field(n_worlds, n_vehicles, pos, vel, rot, scale, params, out)

- pos, vel (W, V, 3) m, m/s and rot (W, V, 3, 3), body to world: the true states (the velocities
  relative to the air, as the field sees them);
- scale (V_leader, V_follower): each ordered pair's factor on its push (1.0: the law as given);
- params (P,) float64: the field's constants;
- out (W, V, 3) m/s^2: on each follower j, the sum over leaders i != j of scale[i, j] times the push of
  i's wake on j, written in full.

Every pointer is C-contiguous; the fused tick calls it with a block of whole worlds at a time. You
write the law once, over one leader/follower pair, as a numba function:

    pair(p_a, v_a, R_a, p_b, v_b, params, out) -> None

p_a, v_a, p_b, v_b (3,) and R_a (3, 3) as in `sim.field.Field`; it writes the push (3,) m/s^2 into
`out`. `field_law(pair, n_params)` makes a `FieldLaw` of it: the compiled sum over pairs, which the
field's ``pairwise(pos, vel, rot)`` (the readable path, `sim.field.pairwise_field`) calls
(`FieldLaw.pairwise`), and the C function that runs the same sum (`FieldLaw.compiled`), so that
the two paths fly the same bits (tests/test_field_contract.py). The field keeps its readable
``__call__`` (checks, maps, non-linear aggregation laws without ``pair_forces``).

A field with a compiled form flies the fused tick under linear aggregation, and where every pair of
the scene flies it as given (a scene of paper quads; `sim.vehicle_params.scene_field`): a scene of
mixed kinds whose field has its own ``for_kinds`` flies the readable path. An `OraclePredictor` of
such a field flies the fused tick through the same C function; inside a `PerWorldPredictor` it flies
the readable path (the fused tick's per-world oracle is the paper field's kernel).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numba
import numpy as np
from numba import carray
from numba import types as nbt

from downwash_core.errors import ConfigError
from sim.field import unit_pair_scale

__all__ = ["FIELD_SIGNATURE", "CompiledField", "FieldLaw", "field_law", "checked_field"]

_F64P = nbt.CPointer(nbt.float64)
# (n_worlds, n_vehicles, pos, vel, rot, scale, params, out)
FIELD_SIGNATURE = nbt.void(nbt.int64, nbt.int64, *(_F64P,) * 6)


class CompiledField(NamedTuple):
    """A field's compiled form (module doc): the address of its C function of `FIELD_SIGNATURE`, its
    constants `params` (n_params,) float64, C-contiguous and kept alive by the field (the simulator reads
    them by address), and `n_params`, how many the C function reads."""

    address: int
    params: np.ndarray
    n_params: int


def _make_sum(pair: Callable[..., None]) -> Any:
    """The compiled sum over ordered pairs of `pair` (module doc), into out (W, V, 3)."""

    def pair_sum(pos, vel, rot, scale, params, out):  # pragma: no cover - compiled
        W, V = pos.shape[0], pos.shape[1]
        push = np.empty(3)
        for w in range(W):
            for j in range(V):
                for k in range(3):
                    out[w, j, k] = 0.0
            for i in range(V):  # leader
                for j in range(V):  # follower
                    if j == i:
                        continue
                    pair(pos[w, i], vel[w, i], rot[w, i], pos[w, j], vel[w, j], params, push)
                    c = scale[i, j]  # (x 1.0 is exact)
                    for k in range(3):
                        out[w, j, k] += c * push[k]

    def pair_terms(pos, vel, rot, scale, params, out):  # pragma: no cover - compiled
        W, V = pos.shape[0], pos.shape[1]
        push = np.empty(3)
        for w in range(W):
            for i in range(V):
                for j in range(V):
                    for k in range(3):
                        out[w, i, j, k] = 0.0
                    if j != i:
                        pair(pos[w, i], vel[w, i], rot[w, i], pos[w, j], vel[w, j], params, push)
                        for k in range(3):
                            out[w, i, j, k] = scale[i, j] * push[k]

    compile_ = numba.njit(fastmath=False, nogil=True)  # (strict IEEE, as downwash_core.jit; closures: not cached)
    return compile_(pair_sum), compile_(pair_terms)


class FieldLaw:
    """A pair law's sums over pairs and C function (module doc). `pair`: a numba-compiled function
    ``pair(p_a, v_a, R_a, p_b, v_b, params, out)``; `n_params`: the size of the params it reads.
    Compiled at first use (seconds); keep one per law (a module constant)."""

    def __init__(self, pair: Callable[..., None], n_params: int):
        if not isinstance(pair, numba.core.registry.CPUDispatcher):
            raise TypeError(f"field_law: pair must be a numba.njit function, got {type(pair).__name__}")
        if int(n_params) < 0:
            raise ConfigError(f"field_law: n_params must be >= 0, got {n_params}")
        self.pair, self.n_params = pair, int(n_params)
        self._sum, self._terms = _make_sum(pair)
        self._function: Any = None

    def check(self, params: Any, label: str = "params") -> np.ndarray:
        """`params` when it is a C-contiguous float64 array (n_params,), else ConfigError naming `label`."""
        if not (isinstance(params, np.ndarray) and params.dtype == np.float64 and params.flags.c_contiguous
                and params.shape == (self.n_params,)):
            got = f"{type(params).__name__} {getattr(params, 'dtype', '')} {getattr(params, 'shape', '')}"
            raise ConfigError(f"{label}: the field's law {self.pair.__name__} reads a C-contiguous float64 array of "
                              f"shape ({self.n_params},), got {got}")
        return params

    def pairwise(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, params: np.ndarray,
                 scale: np.ndarray | None = None) -> np.ndarray:
        """(W, V, 3) m/s^2: on every follower, the sum over leaders of the pair law, each pair's push times
        scale[leader, follower] (None: all 1); pos, vel (W, V, 3), rot (W, V, 3, 3). What the field's
        ``pairwise`` returns, and the C function computes, bit for bit."""
        if type(params) is not np.ndarray or params.shape != (self.n_params,) or params.dtype != np.float64:
            self.check(params)
        W, V = pos.shape[0], pos.shape[1]
        out = np.empty((W, V, 3))
        self._sum(pos, vel, rot, unit_pair_scale(V) if scale is None else scale, params, out)
        return out

    def pair_forces(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, params: np.ndarray,
                    scale: np.ndarray | None = None) -> np.ndarray:
        """(W, V_leader, V_follower, 3) m/s^2: every ordered pair's push times its scale, 0 on the diagonal
        (a field's ``pair_forces``, for the aggregation laws of `sim.aggregation`, readable path)."""
        self.check(params)
        W, V = pos.shape[0], pos.shape[1]
        out = np.empty((W, V, V, 3))
        self._terms(pos, vel, rot, unit_pair_scale(V) if scale is None else scale, params, out)
        return out

    @property
    def function(self) -> Any:
        """The C function of `FIELD_SIGNATURE` (a numba cfunc), compiled at the first use."""
        if self._function is None:
            pair_sum, size = self._sum, self.n_params

            def field(n_worlds, n_veh, pos, vel, rot, scale, params, out):  # pragma: no cover - compiled
                s3 = (n_worlds, n_veh, 3)
                pair_sum(carray(pos, s3), carray(vel, s3), carray(rot, (n_worlds, n_veh, 3, 3)),
                         carray(scale, (n_veh, n_veh)), carray(params, (size,)), carray(out, s3))

            self._function = numba.cfunc(FIELD_SIGNATURE, nopython=True)(field)
        return self._function

    def compiled(self, params: np.ndarray) -> CompiledField:
        """The field's compiled form with its constants `params` (checked; the field keeps them alive)."""
        return CompiledField(int(self.function.address), self.check(params), self.n_params)


def field_law(pair: Callable[..., None], n_params: int) -> FieldLaw:
    """The `FieldLaw` of a numba-compiled pair law reading `n_params` constants (module doc)."""
    return FieldLaw(pair, n_params)


def checked_field(compiled: Any, label: str) -> CompiledField:
    """`compiled` (what a field's ``compiled_field()`` returned) when it is a `CompiledField` with a
    function and C-contiguous float64 params (n_params,); ConfigError naming `label` otherwise."""
    if not isinstance(compiled, CompiledField):
        raise ConfigError(f"{label}.compiled_field(): expected a sim.field_contract.CompiledField, "
                          f"got {type(compiled).__name__}")
    params, n = compiled.params, compiled.n_params
    if not (isinstance(params, np.ndarray) and params.dtype == np.float64 and params.flags.c_contiguous
            and isinstance(n, (int, np.integer)) and params.shape == (n,)):
        got = f"{type(params).__name__} {getattr(params, 'dtype', '')} {getattr(params, 'shape', '')}"
        raise ConfigError(f"{label}.compiled_field(): its params must be a C-contiguous float64 array of shape "
                          f"({n},) (the n_params its C function reads), got {got}")
    if not isinstance(compiled.address, (int, np.integer)) or int(compiled.address) == 0:
        raise ConfigError(f"{label}.compiled_field(): its address must be a C function's (a FIELD_SIGNATURE cfunc's "
                          f"address), got {compiled.address!r}")
    return compiled
