"""Which logged signal is which field of a flight log: a small TOML mapping, loaded and checked.

A mapping file has one of two flavours, named by its ``format`` key:

- ``format = "ros2-bag"`` (`BagMapping`, read by `downwash.real_logs.ros2_bag`): per vehicle
  (``[vehicles.<name>]``) the topics of its pose, twist, IMU, setpoint and thrust (a thrust in N,
  or four rotor PWMs with the battery voltage through the kind's thrust map), its kind and mass;
- ``format = "crazyflie-usd-events"`` (`UsdMapping`, read by
  `downwash.real_logs.crazyflie_events`): the event of the Crazyflie's event-based uSD log and
  which of its variables give position, velocity, attitude, setpoint, PWM and battery, each with
  the scale to SI units; a quantity may list alternatives, the first whose variables are logged
  is used (the default mapping, `default_usd_mapping`, lists the firmware's common names).

`load_mapping` reads a file and `parse_mapping` a dict of the same keys: an unknown key, a missing
section or a value out of range is a `ConfigError` naming the file, the key and what is allowed.
`check_units` is what the mappings promise of the data (SI units), checked on the way in: a
position in mm, a voltage in mV or a thrust in grams is a `UnitMismatchError` naming the stream.
The format of both flavours, with examples, is in docs/real-flights.md.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from downwash_core.errors import ConfigError, LogError
from downwash_core.params import GRAVITY
from downwash_core.vehicles import VEHICLES, ThrustMap, get_vehicle

__all__ = ["BAG_FORMAT", "USD_FORMAT", "STAMPS", "TWIST_FRAMES", "Stream", "BagVehicle", "BagMapping", "Variables",
           "UsdMapping", "UnitMismatchError", "load_mapping", "parse_mapping", "default_usd_mapping",
           "field_steps", "thrust_map_of", "check_units", "POSITION_LIMIT", "SPEED_LIMIT", "VBAT_LIMIT",
           "THRUST_TO_WEIGHT_LIMIT"]

BAG_FORMAT = "ros2-bag"
USD_FORMAT = "crazyflie-usd-events"
STAMPS = ("header", "receive")  # a message's time: its header's stamp (receive time without one), or the bag's
TWIST_FRAMES = ("world", "body")
RATE_RANGE = (10.0, 500.0)  # Hz, the flight's grid (as every reader)

# What SI data of a lab's flight stays within; beyond, a stream is in other units
POSITION_LIMIT = 100.0  # m: no lab is larger (a mm position of 0.1 m is 100)
SPEED_LIMIT = 50.0  # m/s: no multirotor of the registry flies faster (mm/s exceed it at 5 cm/s)
VBAT_LIMIT = 60.0  # V: a 14-cell battery (a 1-cell battery in mV reads 3000-4200)
THRUST_TO_WEIGHT_LIMIT = 20.0  # -: a thrust in grams-force reads ~100 times the weight in N
PWM_MAX = 65535  # the firmware's motor ratio

_TOP_KEYS = {BAG_FORMAT: ("format", "rate_hz", "stamps", "vehicles"), USD_FORMAT: ("format", "rate_hz", "usd")}
_VEHICLE_KEYS = ("kind", "mass", "pose", "twist", "twist_frame", "imu", "setpoint", "thrust", "pwm", "battery")
_STREAM_KEYS = ("topic", "field", "scale")
# a pose's and an IMU's types say where their values are: no field
_ROLE_KEYS = {"pose": ("topic", "scale"), "imu": ("topic",), "setpoint": (*_STREAM_KEYS, "velocity_field")}
_USD_KEYS = ("event", "kind", "mass", "position", "velocity", "quaternion", "setpoint_position",
             "setpoint_velocity", "pwm", "battery", "thrust")
_USD_SIZES = {"position": 3, "velocity": 3, "quaternion": 4, "setpoint_position": 3, "setpoint_velocity": 3,
              "pwm": 4, "battery": 1, "thrust": 1}
_SEGMENT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+)(?::(\d+))?\])?$")


class UnitMismatchError(LogError):
    """A logged stream whose values are not in the units the mapping promises (mm for m, mV for V)."""


@dataclass(frozen=True)
class Stream:
    """A bag topic and, where its type does not say, the field path of the value in its messages
    (``pose.position``, ``data[0:4]``); `scale` multiplies the value into SI units; `velocity_field`
    only for a setpoint whose message also holds its velocity."""

    topic: str
    field: str | None = None
    scale: float = 1.0
    velocity_field: str | None = None


@dataclass(frozen=True)
class BagVehicle:
    """One vehicle of a bag: its streams (None: not logged), its kind (registry name) and mass (kg,
    None: the kind's); `twist_frame` None means the message type's convention (module ros2_bag)."""

    name: str
    pose: Stream
    twist: Stream | None = None
    twist_frame: str | None = None
    imu: Stream | None = None
    setpoint: Stream | None = None
    thrust: Stream | None = None
    pwm: Stream | None = None
    battery: Stream | None = None
    kind: str | None = None
    mass: float | None = None


@dataclass(frozen=True)
class BagMapping:
    """A ROS 2 bag's mapping: its vehicles, the grid's rate (Hz), the stamps used, and `source` (the
    mapping file and its SHA-256, for the flight's provenance)."""

    vehicles: tuple[BagVehicle, ...]
    rate_hz: float = 100.0
    stamps: str = "header"
    source: Mapping[str, Any] | None = None


@dataclass(frozen=True)
class Variables:
    """Logged variables that give one quantity, times `scale` in SI units; `compressed`: one variable
    holding the firmware's compressed quaternion."""

    names: tuple[str, ...]
    scale: float = 1.0
    compressed: bool = False


@dataclass(frozen=True)
class UsdMapping:
    """An event-based uSD log's mapping: the event whose records hold the variables, per quantity
    its alternatives (the first whose variables are all logged is used; () for not logged), the
    vehicle's kind and mass (kg, None: the kind's), the grid's rate (Hz) and the mapping's source."""

    event: str
    position: tuple[Variables, ...]
    quaternion: tuple[Variables, ...]
    velocity: tuple[Variables, ...] = ()
    setpoint_position: tuple[Variables, ...] = ()
    setpoint_velocity: tuple[Variables, ...] = ()
    pwm: tuple[Variables, ...] = ()
    battery: tuple[Variables, ...] = ()
    thrust: tuple[Variables, ...] = ()
    kind: str | None = None
    mass: float | None = None
    rate_hz: float = 100.0
    source: Mapping[str, Any] | None = None


# ----------------------------------------------------------------------------- loading


def load_mapping(path: str | os.PathLike) -> BagMapping | UsdMapping:
    """The mapping of a TOML file (module doc); ConfigError naming the file and what is wrong."""
    path = Path(path)
    try:
        raw = path.read_bytes()
        data = tomllib.loads(raw.decode("utf-8"))
    except OSError as e:
        raise ConfigError(f"{path}: cannot read the mapping: {e.strerror or e}") from e
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"{path}: not a TOML mapping: {e}") from None
    return parse_mapping(data, str(path), {"file": str(path), "sha256": hashlib.sha256(raw).hexdigest()})


def default_usd_mapping() -> UsdMapping:
    """The shipped mapping of the Crazyflie firmware's common log variables (mappings/crazyflie_usd.toml)."""
    ref = resources.files("downwash.real_logs") / "mappings" / "crazyflie_usd.toml"
    with resources.as_file(ref) as path:
        mapping = load_mapping(path)
    assert isinstance(mapping, UsdMapping), "the shipped mapping is of the uSD flavour"
    return mapping


def parse_mapping(data: Mapping[str, Any], where: str = "mapping",
                  source: Mapping[str, Any] | None = None) -> BagMapping | UsdMapping:
    """The mapping of a dict of the file's keys; `where` names it in errors, `source` is kept."""
    fmt = data.get("format")
    if fmt not in _TOP_KEYS:
        raise ConfigError(f"{where}: format: got {fmt!r}; allowed: {', '.join(map(repr, _TOP_KEYS))}")
    _known(data, _TOP_KEYS[fmt], where)
    rate = _number(data, "rate_hz", where, 100.0, RATE_RANGE)
    if fmt == BAG_FORMAT:
        stamps = data.get("stamps", "header")
        if stamps not in STAMPS:
            raise ConfigError(f"{where}: stamps: got {stamps!r}; allowed: {', '.join(STAMPS)}")
        vehicles = _table(data, "vehicles", where, required=True)
        if not vehicles:
            raise ConfigError(f"{where}: [vehicles]: no vehicle; add a section [vehicles.<name>] per vehicle")
        return BagMapping(tuple(_bag_vehicle(n, v, f"{where}: vehicles.{n}") for n, v in vehicles.items()),
                          rate, stamps, source)
    return _usd_mapping(_table(data, "usd", where, required=True), f"{where}: usd", rate, source)


def _known(table: Mapping[str, Any], allowed: tuple[str, ...], where: str) -> None:
    unknown = [k for k in table if k not in allowed]
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r}; allowed: {', '.join(allowed)}")


def _table(data: Mapping[str, Any], key: str, where: str, required: bool = False) -> dict[str, Any]:
    value = data.get(key)
    if value is None and not required:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: [{key}]: " + ("missing section" if value is None else
                                                   f"expected a table, got {value!r}"))
    return value


def _number(table: Mapping[str, Any], key: str, where: str, default: float | None,
            bounds: tuple[float, float] = (0.0, math.inf)) -> float | None:
    """A number in (low, high] (low 0: positive), or the default when the key is absent."""
    value = table.get(key, default)
    if value is None:
        return None
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and bounds[0] <= value <= bounds[1]
    if not ok or (bounds[0] == 0.0 and value == 0):
        low = "> 0" if bounds[0] == 0.0 else f"{bounds[0]:g}-{bounds[1]:g}"
        raise ConfigError(f"{where}: {key}: got {value!r}; allowed: a number {low}")
    return float(value)


def _kind_and_mass(table: Mapping[str, Any], where: str) -> tuple[str | None, float | None]:
    kind, mass = table.get("kind"), _number(table, "mass", where, None)
    if kind is not None:
        try:
            get_vehicle(kind)
        except ConfigError as e:
            raise ConfigError(f"{where}: kind: {e}") from None
    elif mass is None:
        raise ConfigError(f"{where}: neither kind nor mass: the thrust's acceleration needs the mass "
                          "(mass = <kg>, or kind = <a registered kind>)")
    return kind, mass


def thrust_map_of(kind: str | None, given: ThrustMap | None, where: str) -> ThrustMap:
    """The thrust map for a vehicle's PWM: `given`, else its kind's; ConfigError naming the kinds that have one."""
    found = given or (get_vehicle(kind).thrust_map if kind else None)
    if found is None:
        having = ", ".join(k.name for k in VEHICLES.values() if k.thrust_map is not None)
        raise ConfigError(f"{where}: pwm needs a thrust map: kind {kind!r} has none (kinds with one: {having}), or "
                          "pass a ThrustMap to the reader")
    return found


def field_steps(path: str, where: str = "field") -> tuple[tuple[str, int | slice | None], ...]:
    """The steps of a field path (``msg.`` optional): ``pose.position`` -> (("pose", None), ("position",
    None)); ``data[0:4]`` -> (("data", slice(0, 4)),). ConfigError for another syntax."""
    parts = path.split(".")
    parts = parts[1:] if parts[0] == "msg" and len(parts) > 1 else parts
    steps = []
    for part in parts:
        m = _SEGMENT.match(part)
        if not m:
            raise ConfigError(f"{where}: {path!r} is not a field path (names joined by '.', each with an "
                              "optional [i] or [i:j], e.g. 'pose.position' or 'data[0:4]')")
        index = None if m.group(2) is None else (
            int(m.group(2)) if m.group(3) is None else slice(int(m.group(2)), int(m.group(3))))
        steps.append((m.group(1), index))
    return tuple(steps)


def _stream(value: Any, where: str, keys: tuple[str, ...] = _STREAM_KEYS) -> Stream:
    """A topic name, or a table {topic, field, scale[, velocity_field]}."""
    if isinstance(value, str):
        value = {"topic": value}
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: expected a topic name or a table ({', '.join(keys)}), got {value!r}")
    _known(value, keys, where)
    topic = value.get("topic")
    if not isinstance(topic, str) or not topic.startswith("/"):
        raise ConfigError(f"{where}: topic: expected a topic name starting with '/', got {topic!r}")
    for key in ("field", "velocity_field"):
        if key in value:
            if not isinstance(value[key], str):
                raise ConfigError(f"{where}: {key}: expected a field path, got {value[key]!r}")
            field_steps(value[key], f"{where}: {key}")
    scale = _number(value, "scale", where, 1.0)
    return Stream(topic, value.get("field"), scale, value.get("velocity_field"))


def _bag_vehicle(name: str, table: Any, where: str) -> BagVehicle:
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: expected a table [vehicles.{name}], got {table!r}")
    _known(table, _VEHICLE_KEYS, where)
    if "pose" not in table:
        raise ConfigError(f"{where}: pose: missing (the topic of the vehicle's pose: PoseStamped or Odometry)")
    streams = {k: _stream(table[k], f"{where}.{k}", _ROLE_KEYS.get(k, _STREAM_KEYS))
               for k in ("pose", "twist", "imu", "setpoint", "thrust", "pwm", "battery") if k in table}
    if ("thrust" in streams) == ("pwm" in streams):
        raise ConfigError(f"{where}: give exactly one of thrust (a topic of the collective thrust in N) and pwm "
                          "(the four rotors' PWM, with battery and kind)")
    if "pwm" in streams and "battery" not in streams:
        raise ConfigError(f"{where}: pwm needs battery (the battery voltage topic): the thrust map takes both")
    frame = table.get("twist_frame")
    if frame is not None and frame not in TWIST_FRAMES:
        raise ConfigError(f"{where}: twist_frame: got {frame!r}; allowed: {', '.join(TWIST_FRAMES)}")
    kind, mass = _kind_and_mass(table, where)
    return BagVehicle(name, twist_frame=frame, kind=kind, mass=mass, **streams)


def _variables(value: Any, key: str, where: str) -> tuple[Variables, ...]:
    """One quantity's alternatives: a table {variables, scale} (quaternion: or {compressed}) or a list of them."""
    tables = value if isinstance(value, list) else [value]
    out = []
    for i, table in enumerate(tables):
        at = f"{where}.{key}" + (f"[{i}]" if isinstance(value, list) else "")
        if not isinstance(table, dict):
            raise ConfigError(f"{at}: expected a table (variables = [...], scale = ...), got {table!r}")
        allowed = ("variables", "compressed") if key == "quaternion" else ("variables", "scale")
        _known(table, allowed, at)
        if key == "quaternion" and ("variables" in table) == ("compressed" in table):
            raise ConfigError(f"{at}: give variables (qw, qx, qy, qz) or compressed (one packed uint32), not both")
        if "compressed" in table:
            if not isinstance(table["compressed"], str) or not table["compressed"]:
                raise ConfigError(f"{at}: compressed: expected a variable name, got {table['compressed']!r}")
            out.append(Variables((table["compressed"],), 1.0, True))
            continue
        names = table.get("variables")
        size = _USD_SIZES[key]
        if not (isinstance(names, list) and len(names) == size and all(isinstance(n, str) and n for n in names)):
            raise ConfigError(f"{at}: variables: expected {size} variable name{'s' * (size > 1)}, got {names!r}")
        out.append(Variables(tuple(names), _number(table, "scale", at, 1.0)))
    return tuple(out)


def _usd_mapping(table: dict[str, Any], where: str, rate: float, source: Mapping[str, Any] | None) -> UsdMapping:
    _known(table, _USD_KEYS, where)
    event = table.get("event", "fixedFrequency")
    if not isinstance(event, str) or not event:
        raise ConfigError(f"{where}: event: expected an event name, got {event!r}")
    quantities = {k: _variables(table[k], k, where) for k in _USD_SIZES if k in table}
    for key in ("position", "quaternion"):
        if key not in quantities:
            raise ConfigError(f"{where}: {key}: missing (the variables of the vehicle's {key})")
    if ("thrust" in quantities) == ("pwm" in quantities):
        raise ConfigError(f"{where}: give exactly one of thrust (a variable in N) and pwm (four PWM variables, "
                          "with battery and kind)")
    if "pwm" in quantities and "battery" not in quantities:
        raise ConfigError(f"{where}: pwm needs battery (the battery voltage variable): the thrust map takes both")
    kind, mass = _kind_and_mass(table, where)
    return UsdMapping(event=event, kind=kind, mass=mass, rate_hz=rate, source=source, **quantities)


# ----------------------------------------------------------------------------- the units, checked on the data


def check_units(where: str, *, pos: np.ndarray | None = None, vel: np.ndarray | None = None,
                quat: np.ndarray | None = None, thrust: np.ndarray | None = None, mass: float | None = None,
                pwm: np.ndarray | None = None, vbat: np.ndarray | None = None) -> None:
    """UnitMismatchError naming `where` (and the stream) unless the data are SI: pos (N, 3) m within
    POSITION_LIMIT, vel (N, 3) m/s within SPEED_LIMIT, quat (N, 4) of unit norm, thrust (N,) N at
    most THRUST_TO_WEIGHT_LIMIT times the weight of `mass` kg, pwm (N, 4) in 0-65535 (not a 0-1
    ratio), vbat (N,) V within VBAT_LIMIT. Every value must be finite (LogError otherwise)."""
    for name, value in (("position", pos), ("velocity", vel), ("quaternion", quat), ("thrust", thrust),
                        ("pwm", pwm), ("battery", vbat)):
        if value is not None and not np.isfinite(value).all():
            row = int(np.argmax(~np.isfinite(np.asarray(value).reshape(len(value), -1)).all(axis=1)))
            raise LogError(f"{where}: {name}: a value that is not a finite number at sample {row}")
    _limit(where, "position", pos, POSITION_LIMIT, "m", "mm")
    _limit(where, "velocity", vel, SPEED_LIMIT, "m/s", "mm/s")
    _limit(where, "battery", vbat, VBAT_LIMIT, "V", "mV")
    if quat is not None and len(quat):
        with np.errstate(over="ignore"):  # a damaged value of 1e200 has an infinite norm: refused just below
            norm = np.linalg.norm(quat, axis=1)
        worst = int(np.argmax(np.abs(norm - 1.0)))
        if abs(norm[worst] - 1.0) > 0.1:
            raise UnitMismatchError(f"{where}: unit mismatch: quaternion of norm {norm[worst]:g} at sample {worst}; "
                                    "expected unit quaternions (w, x, y, z)")
    if thrust is not None and mass is not None:
        _limit(where, "thrust", thrust, THRUST_TO_WEIGHT_LIMIT * mass * GRAVITY, "N", "grams-force or mN")
    if pwm is not None and len(pwm):
        low, high = float(np.min(pwm)), float(np.max(pwm))
        if low < 0 or high > PWM_MAX:
            raise UnitMismatchError(f"{where}: unit mismatch: pwm spans {low:g}-{high:g}; expected 0-{PWM_MAX}")
        if 0 < high <= 1.0:
            raise UnitMismatchError(f"{where}: unit mismatch: pwm reaches only {high:g}: a 0-1 ratio? expected "
                                    f"0-{PWM_MAX} (set scale = {PWM_MAX})")


def _limit(where: str, name: str, value: np.ndarray | None, limit: float, unit: str, suspect: str) -> None:
    if value is None or not len(value):
        return
    peak = float(np.max(np.abs(value)))
    if peak > limit:
        raise UnitMismatchError(f"{where}: unit mismatch: {name} reaches {peak:g}; in {unit} it stays within "
                                f"{limit:g} {unit}: is it in {suspect}? (set the mapping's scale)")
