"""Sensors: what the loop measures of each vehicle, as components (motion capture first).

Motion capture samples every vehicle's position and attitude on the autopilot grid (100 Hz);
the Kalman filter (`sim.estimation`) turns the positions into the estimates the controller
flies on, and the controller's heading, the learned models and the labels use the measured
attitude. The sensor is chosen by `SimConfig.mocap` (default `MocapConfig()`, the `mocap`
entry). Every sensor here is of one family, which the compiled sense pass
(`sim.passes.sense_kernel`, inside the fused tick too) runs with the sensor's `compiled()`
constants and the per-episode offsets the simulator draws at each reset:

    position:  m = p + position_std * xi_p + offset     xi_p ~ N(0, I3), fresh each sample
    attitude:  q_m = q exp(attitude_std * xi_q / 2)      xi_q ~ N(0, I3), a body-frame rotation vector
    offset:    (V, 3) m, constant over an episode: `episode_offset(rng, V)`, drawn at reset from the
               world's own sensor stream default_rng([seed, SENSOR_STREAM])

The white draws xi are columns 0:6 of the world's noise block, whatever the sensor, and the
offsets come from a stream of their own: a sensor with offsets sees the same white noise as
one without, and `mocap` draws nothing at reset, so its flights are those of before sensors
were components, bit for bit. `measure` is the readable law (NumPy, batched (W, V, ...));
tests/test_sensors.py checks the compiled pass against it and both paths' flights against
each other. A new sensor of this family needs only its parameters and `episode_offset`
(docs/extending.md, "A new sensor noise model"); one outside it (outliers, dropouts,
latency) brings its own compiled law, ``compiled_sensor(W, V)`` (`sim.sensor_contract`), which the
same sense pass runs in place of the family's on both paths; `check_sensor` refuses a sensor with
neither.

Registered (`SENSORS`, a `downwash_core.registry.Registry`, which plugins add to; `make_sensor`;
`resolve_sensor_spec("NAME[:KEY=VALUE,...]")`, the registries' one spec grammar):

- `mocap` (`MocapConfig`, the default): white noise of 0.5 mm per position axis and 2 mrad
  per attitude axis, sample by sample (a marker-based system's jitter);
- `mocap_biased` (`BiasedMocap`): the same, plus a constant position offset per vehicle and
  episode, N(0, position_bias^2) per axis (2 mm). A rigid body's pivot (the marker centroid
  fixed when the body is defined in the motion-capture software) sits a few mm from the
  vehicle's centre of mass, and each calibration leaves the frame's origin off by about as
  much; re-placed markers or a recalibration between experiments give a new offset. The
  filter cannot tell it from the truth: the vehicle flies displaced by -offset.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from types import MappingProxyType
from typing import Any, Callable, ClassVar, Mapping, NamedTuple, Protocol, runtime_checkable

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.geometry import perturb_quat
from downwash_core.registry import Entry, Registry

__all__ = ["Sensor", "CompiledSensor", "MocapConfig", "BiasedMocap", "SensorEntry", "SENSORS", "DEFAULT_SENSOR",
           "SENSOR_STREAM", "register_sensor", "make_sensor", "resolve_sensor_spec", "check_sensor",
           "draw_episode_offset"]

SENSOR_STREAM = 0x4D4F4341  # "MOCA": world w's per-episode offsets come from default_rng([seed_w, SENSOR_STREAM])
DEFAULT_SENSOR = "mocap"


class CompiledSensor(NamedTuple):
    """The constants of the compiled sense pass (see the module docstring)."""

    position_std: float  # m, white noise per position axis
    attitude_std: float  # rad, white noise per axis of the body-frame rotation vector


@runtime_checkable
class Sensor(Protocol):
    """What the simulator asks of a sensor (`SimConfig.mocap`); `isinstance(x, Sensor)` checks that it has
    each member (not their signatures)."""

    name: ClassVar[str]  # its registry name, and the label of its errors
    process_accel_noise: float  # m/s^2, the Kalman filter's process noise (an estimator setting it carries)

    @property
    def measurement_noise(self) -> float:
        """m, the position noise std per axis that the Kalman filter assumes."""

    def compiled(self) -> CompiledSensor: ...

    def episode_offset(self, rng: np.random.Generator, n_vehicles: int) -> np.ndarray: ...

    def measure(self, pos: np.ndarray, quat: np.ndarray, normals: np.ndarray,
                offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]: ...

    def describe(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class MocapConfig:
    """`mocap`: motion capture with white Gaussian noise, and the Kalman filter's process noise."""

    position_noise: float = 0.0005  # m, std of each motion-capture position axis
    attitude_noise: float = 0.002  # rad, std of each axis of the attitude error (body-frame rotation vector)
    process_accel_noise: float = 2.0  # m/s^2, std of unmodelled acceleration (downwash is ~1-3)

    name: ClassVar[str] = "mocap"
    # allowed ranges, inclusive: (low, high, unit). Beyond 0.1 m or 0.5 rad it is no motion capture.
    RANGES: ClassVar[Mapping[str, tuple[float, float, str]]] = MappingProxyType({
        "position_noise": (0.0, 0.1, "m"), "attitude_noise": (0.0, 0.5, "rad"),
        "process_accel_noise": (0.0, 100.0, "m/s^2"),
    })

    def __post_init__(self) -> None:
        for key, (low, high, unit) in self.RANGES.items():
            value = getattr(self, key)
            try:
                inside = low <= value <= high  # NaN is not
            except TypeError:  # not a number
                inside = False
            if not inside:
                raise ConfigError(f"{self.name} {key}: allowed {low} to {high} {unit}, got {value!r}")

    @property
    def measurement_noise(self) -> float:
        """m, the white position noise: what the Kalman filter can average away (an offset it cannot)."""
        return float(self.position_noise)

    def compiled(self) -> CompiledSensor:
        return CompiledSensor(float(self.position_noise), float(self.attitude_noise))

    def episode_offset(self, rng: np.random.Generator, n_vehicles: int) -> np.ndarray:
        """(V, 3) m, the constant position offset of each vehicle this episode: none (draws nothing)."""
        return np.zeros((n_vehicles, 3))

    def measure(self, pos: np.ndarray, quat: np.ndarray, normals: np.ndarray,
                offset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The readable law: measured positions (..., 3) m and attitudes (..., 4) (w, x, y, z).

        pos (..., 3) m and quat (..., 4) true, world frame, body to world; normals (..., 6)
        standard normals ([0:3] position, [3:6] attitude); offset (..., 3) m, this episode's
        (`episode_offset`; None: none). The arithmetic of the compiled pass, in its order.
        """
        std = self.compiled()
        measured = pos + std.position_std * normals[..., :3]
        if offset is not None:
            measured = measured + offset
        return measured, perturb_quat(quat, std.attitude_std * normals[..., 3:6])

    def describe(self) -> dict[str, Any]:
        # the default's record is the one logs and collection keys have always held (the class
        # was defined in sim.estimation, which still exports it): old results' provenance matches
        path = "sim.estimation.MocapConfig" if type(self) is MocapConfig else \
            f"{type(self).__module__}.{type(self).__qualname__}"
        return {"type": path, **asdict(self)}


@dataclass(frozen=True)
class BiasedMocap(MocapConfig):
    """`mocap_biased`: `mocap` plus a constant position offset per vehicle and episode (see the module docstring)."""

    position_bias: float = 0.002  # m, std of each axis of the per-episode offset

    name: ClassVar[str] = "mocap_biased"
    RANGES: ClassVar[Mapping[str, tuple[float, float, str]]] = MappingProxyType({
        **MocapConfig.RANGES, "position_bias": (0.0, 0.05, "m"),  # beyond 5 cm: a wrongly defined body
    })

    def episode_offset(self, rng: np.random.Generator, n_vehicles: int) -> np.ndarray:
        """(V, 3) m, N(0, position_bias^2) per axis, independent per vehicle."""
        return self.position_bias * rng.standard_normal((n_vehicles, 3))


def check_sensor(sensor: Any, label: str = "SimConfig.mocap") -> Any:
    """`sensor` when it has the interface of `Sensor` and finite, non-negative compiled constants, or,
    outside the family, a compiled law (``compiled_sensor``, `sim.sensor_contract`: checked when the
    simulator asks for it, with its batch's sizes); ConfigError naming `label` otherwise."""
    law = hasattr(sensor, "compiled_sensor")
    needs = ("measurement_noise", "process_accel_noise", "episode_offset", "describe") + \
        (() if law else ("compiled", "measure"))
    missing = [a for a in needs if not hasattr(sensor, a)]
    if missing:
        raise ConfigError(f"{label}: a sensor needs {', '.join(missing)} (see sim.sensors.Sensor; registered: "
                          f"{', '.join(SENSORS)}), got {type(sensor).__name__}")
    if law:
        return sensor
    constants = sensor.compiled()
    if not isinstance(constants, CompiledSensor) or not all(math.isfinite(c) and c >= 0 for c in constants):
        raise ConfigError(f"{label}: compiled() must give a CompiledSensor of finite stds >= 0 (a sensor outside "
                          f"the family of sim.sensors brings a compiled law, compiled_sensor: "
                          f"sim.sensor_contract), got {constants!r}")
    return sensor


def draw_episode_offset(sensor: Any, seed: int, n_vehicles: int) -> np.ndarray:
    """The sensor's offsets (V, 3) m for an episode of the world with `seed`, from its own stream."""
    offset = np.asarray(sensor.episode_offset(np.random.default_rng([seed, SENSOR_STREAM]), n_vehicles), np.float64)
    if offset.shape != (n_vehicles, 3) or not np.isfinite(offset).all():
        raise ConfigError(f"{type(sensor).__name__}.episode_offset: expected finite ({n_vehicles}, 3) m, "
                          f"got shape {offset.shape}")
    return offset


# ----------------------------------------------------------------------------- the registry
SensorEntry = Entry  # one registered sensor: factory(**params) -> sensor; params {name: type} it accepts
SENSORS = Registry("sensor", group="sensors", default=DEFAULT_SENSOR,
                   description="sensors: what the loop measures of each vehicle (SimConfig.mocap)")


@SENSORS.adder
def register_sensor(name: str, factory: Callable[..., Any], description: str,
                    params: Mapping[str, type] | None = None) -> Entry:
    """Register `factory` under `name` (not yet taken); params default to a dataclass factory's fields,
    typed by their annotations (`downwash_core.registry.infer_params`)."""
    return SENSORS.register(name, factory, description, params=params)


def make_sensor(name: str = DEFAULT_SENSOR, **params: Any) -> Any:
    """The registered sensor `name` with `params`, e.g. make_sensor("mocap_biased", position_bias=0.003)."""
    return SENSORS.make(name, **params)


def resolve_sensor_spec(spec: str, label: str = "sensor") -> Any:
    """The sensor a spec "NAME[:KEY=VALUE,...]" names ("" is the default, `mocap`); ConfigError otherwise."""
    return SENSORS.resolve(spec, label)


register_sensor("mocap", MocapConfig, "motion capture, white noise: 0.5 mm per position axis, 2 mrad of attitude; "
                "the default")
register_sensor("mocap_biased", BiasedMocap, "mocap plus a constant position offset per vehicle and episode, "
                "2 mm per axis (marker pivot and calibration)")
