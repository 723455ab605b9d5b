"""A sensor's compiled law: the contract by which a sensor outside the family of `sim.sensors` flies.

The sense pass runs the family of `sim.sensors` itself (white noise and an episode's offset,
`sim.passes.sense_kernel`); a sensor of any other law (dropouts, outliers, a latency) joins both
paths through one C function of `SENSOR_SIGNATURE`, which it returns from ``compiled_sensor(W, V)``
as a `CompiledSensorLaw`:

    void sensor(n_worlds, n_vehicles, pos, quat, normals, offset, state, params, m_pos, m_quat)

- pos (W, V, 3) m and quat (W, V, 4) (w, x, y, z), body to world: the true state at the sample;
- normals (W, V, 6): the sample's standard normals, columns 0:6 of each world's noise block
  (the draws the family takes: [0:3] position, [3:6] attitude), fresh each sample;
- offset (W, V, 3) m: the episode's offsets (the sensor's ``episode_offset``, as for the family);
- state (W, V, S) float64: the sensor's memory, one array per simulator (``compiled_sensor(W, V)``
  allocates it: a sensor is a setting that simulators share); params (P,) float64: its constants;
- m_pos (W, V, 3) m and m_quat (W, V, 4): the measurement, written in full.

Every pointer is C-contiguous. The sense pass (`sim.passes.sense_law_kernel`) calls it once per
autopilot tick with a block of whole worlds (state offset to the block's first world), on the readable
path and inside the fused tick alike, so both fly the same bits (tests/test_sensor_contract.py); the
law must treat worlds independently. At each reset of world w the simulator sets the world's rows
of the state (V, S) to ``sensor.episode_state(rng, V)`` (zeros for a sensor without one), rng the
world's own stream ``default_rng([seed, SENSOR_STATE_STREAM])``: the state's draws leave the noise
blocks and the offsets as they were, so a law that takes the family's arithmetic on the draws it is
given measures the family's noise exactly.

The law is written once, for one vehicle's sample, as a numba function

    sample(p, q, xi, offset, state, params, m, q_m) -> None

p (3,), q (4,), xi (6,), offset (3,), the vehicle's state row (S,), params (P,); it writes m (3,)
and q_m (4,). `sensor_law(sample, S, P)` makes a `SensorLaw` of it: the C function
(`SensorLaw.function`), the compiled form with a sensor's arrays (`SensorLaw.compiled`) and the
same loop on NumPy arrays (`SensorLaw.measure`, for checks and statistics). `checked_sensor_law`
refuses, before any flight, a compiled form the sense pass cannot read.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numba
import numpy as np
from numba import carray
from numba import types as nbt

from downwash_core.errors import ConfigError

__all__ = ["SENSOR_SIGNATURE", "SENSOR_STATE_STREAM", "CompiledSensorLaw", "SensorLaw", "sensor_law",
           "checked_sensor_law", "compiled_sensor_law", "episode_state"]

_F64P = nbt.CPointer(nbt.float64)
# (n_worlds, n_vehicles, pos, quat, normals, offset, state, params, m_pos, m_quat)
SENSOR_SIGNATURE = nbt.void(nbt.int64, nbt.int64, *(_F64P,) * 8)
SENSOR_STATE_STREAM = 0x53544154  # "STAT": world w's sensor state at reset comes from default_rng([seed_w, this])


class CompiledSensorLaw(NamedTuple):
    """A sensor's compiled law (module doc): the address of its C function of `SENSOR_SIGNATURE`, its
    constants `params` (P,) float64 and its memory `state` (W, V, S) float64, both C-contiguous and read
    by address (never copied: the state is the one the simulator sets at each reset)."""

    address: int
    params: np.ndarray
    state: np.ndarray


def _make_loop(sample: Callable[..., None]) -> Any:
    """The compiled loop of `sample` over worlds and vehicles (module doc)."""

    def loop(pos, quat, normals, offset, state, params, m_pos, m_quat):  # pragma: no cover - compiled
        for w in range(pos.shape[0]):
            for i in range(pos.shape[1]):
                sample(pos[w, i], quat[w, i], normals[w, i], offset[w, i], state[w, i], params, m_pos[w, i],
                       m_quat[w, i])

    return numba.njit(fastmath=False, nogil=True)(loop)  # (strict IEEE, as downwash_core.jit; a closure: not cached)


class SensorLaw:
    """A sample law's loop and C function (module doc). `sample`: a numba-compiled function
    ``sample(p, q, xi, offset, state, params, m, q_m)``; `state_width` S and `n_params` P: the sizes of
    the state row and the constants it reads. Compiled at first use (seconds); keep one per law."""

    def __init__(self, sample: Callable[..., None], state_width: int, n_params: int):
        if not isinstance(sample, numba.core.registry.CPUDispatcher):
            raise TypeError(f"sensor_law: sample must be a numba.njit function, got {type(sample).__name__}")
        if int(state_width) < 0 or int(n_params) < 0:
            raise ConfigError(f"sensor_law: state_width and n_params must be >= 0, got {state_width}, {n_params}")
        self.sample, self.state_width, self.n_params = sample, int(state_width), int(n_params)
        self._loop = _make_loop(sample)
        self._function: Any = None

    def measure(self, pos: np.ndarray, quat: np.ndarray, normals: np.ndarray, offset: np.ndarray, state: np.ndarray,
                params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The measured positions (W, V, 3) m and attitudes (W, V, 4) of one sample: the C function's loop on
        NumPy arrays (float64): pos (W, V, 3), quat (W, V, 4), normals (W, V, 6), offset (W, V, 3), the state
        (W, V, S), advanced in place, and params (P,)."""
        W, V = pos.shape[0], pos.shape[1]
        checked_sensor_law(CompiledSensorLaw(1, params, state), "SensorLaw.measure", W, V, self)
        m_pos, m_quat = np.empty((W, V, 3)), np.empty((W, V, 4))
        arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in (pos, quat, normals, offset)]
        self._loop(*arrays, state, params, m_pos, m_quat)
        return m_pos, m_quat

    @property
    def function(self) -> Any:
        """The C function of `SENSOR_SIGNATURE` (a numba cfunc), compiled at the first use."""
        if self._function is None:
            loop, width, size = self._loop, self.state_width, self.n_params

            def sensor(n_worlds, n_veh, pos, quat, normals, offset, state, params, m_pos,
                       m_quat):  # pragma: no cover - compiled
                s3, s4 = (n_worlds, n_veh, 3), (n_worlds, n_veh, 4)
                loop(carray(pos, s3), carray(quat, s4), carray(normals, (n_worlds, n_veh, 6)), carray(offset, s3),
                     carray(state, (n_worlds, n_veh, width)), carray(params, (size,)), carray(m_pos, s3),
                     carray(m_quat, s4))

            self._function = numba.cfunc(SENSOR_SIGNATURE, nopython=True)(sensor)
        return self._function

    def compiled(self, params: np.ndarray, state: np.ndarray) -> CompiledSensorLaw:
        """The sensor's compiled law with its constants `params` (P,) and memory `state` (W, V, S)."""
        return CompiledSensorLaw(int(self.function.address), params, state)


def sensor_law(sample: Callable[..., None], state_width: int, n_params: int) -> SensorLaw:
    """The `SensorLaw` of a numba-compiled sample law with a state row of `state_width` and `n_params` constants."""
    return SensorLaw(sample, state_width, n_params)


def _describe(a: Any) -> str:
    return f"{type(a).__name__} {getattr(a, 'dtype', '')} {getattr(a, 'shape', '')}"


def checked_sensor_law(compiled: Any, label: str, W: int, V: int, law: SensorLaw | None = None) -> CompiledSensorLaw:
    """`compiled` (what a sensor's ``compiled_sensor(W, V)`` returned) when the sense pass can read it: a
    `CompiledSensorLaw` with a function's address, C-contiguous float64 params (P,) and state (W, V, S) (of
    `law`'s sizes, when given); ConfigError naming `label` otherwise."""
    if not isinstance(compiled, CompiledSensorLaw):
        raise ConfigError(f"{label}.compiled_sensor(): expected a sim.sensor_contract.CompiledSensorLaw, "
                          f"got {type(compiled).__name__}")
    params, state = compiled.params, compiled.state
    n = law.n_params if law is not None else getattr(params, "size", -1)
    if not (isinstance(params, np.ndarray) and params.dtype == np.float64 and params.flags.c_contiguous
            and params.shape == (n,)):
        raise ConfigError(f"{label}.compiled_sensor(): its params must be a C-contiguous float64 array of shape "
                          f"(n_params,) = ({n},), got {_describe(params)}")
    width = law.state_width if law is not None else (state.shape[-1] if isinstance(state, np.ndarray) else -1)
    if not (isinstance(state, np.ndarray) and state.dtype == np.float64 and state.flags.c_contiguous
            and state.flags.writeable and state.shape == (W, V, width)):
        raise ConfigError(f"{label}.compiled_sensor(): its state must be a writeable C-contiguous float64 array of "
                          f"shape (W, V, S) = ({W}, {V}, S), got {_describe(state)}")
    if not isinstance(compiled.address, (int, np.integer)) or isinstance(compiled.address, bool) \
            or int(compiled.address) == 0:
        raise ConfigError(f"{label}.compiled_sensor(): its address must be a C function's (a SENSOR_SIGNATURE "
                          f"cfunc's address, SensorLaw.function.address), got {compiled.address!r}")
    return compiled


def compiled_sensor_law(sensor: Any, W: int, V: int) -> CompiledSensorLaw | None:
    """The compiled law of `sensor` for a batch of W worlds of V vehicles, checked (`checked_sensor_law`),
    or None for a sensor of the family of `sim.sensors` (no ``compiled_sensor``)."""
    make = getattr(sensor, "compiled_sensor", None)
    if make is None:
        return None
    if not callable(make):
        raise ConfigError(f"{type(sensor).__name__}.compiled_sensor: expected a method (W, V) -> CompiledSensorLaw, "
                          f"got {type(make).__name__}")
    return checked_sensor_law(make(W, V), type(sensor).__name__, W, V)


def episode_state(sensor: Any, seed: int, n_vehicles: int, width: int) -> np.ndarray:
    """The rows (V, S) of a world's sensor state at its reset: ``sensor.episode_state(rng, V)`` from the
    world's own stream default_rng([seed, SENSOR_STATE_STREAM]), or zeros for a sensor without one."""
    draw = getattr(sensor, "episode_state", None)
    if draw is None:
        return np.zeros((n_vehicles, width))
    state = np.asarray(draw(np.random.default_rng([seed, SENSOR_STATE_STREAM]), n_vehicles), dtype=np.float64)
    if state.shape != (n_vehicles, width) or not np.isfinite(state).all():
        raise ConfigError(f"{type(sensor).__name__}.episode_state: expected finite ({n_vehicles}, {width}) "
                          f"(the compiled law's state rows), got shape {state.shape}")
    return state
