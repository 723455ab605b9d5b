"""ROS 2 bags (MCAP or sqlite3 storage) to a real flight's log, through a topic mapping.

`read_bag_flight(bag, mapping)` reads the topics a `downwash.real_logs.mapping.BagMapping` names
(a ``format = "ros2-bag"`` TOML file) with `rosbags` (pure Python, no ROS install; the ``logs``
extra), the bag's own message definitions first and ROS 2 Humble's for a bag without them. Per
vehicle:

| stream | message types | gives |
|---|---|---|
| ``pose`` | PoseStamped, PoseWithCovarianceStamped, TransformStamped, Odometry | position m, attitude |
| ``twist`` | TwistStamped (world frame), Odometry (body: its child frame); any, with ``field`` | velocity m/s |
| ``imu`` | Imu | its type checked: a flight log has no array for it |
| ``setpoint`` | PoseStamped, Odometry, PointStamped; any, with ``field`` (``velocity_field``) | reference m (m/s) |
| ``thrust`` | Float32, Float64; any, with ``field`` | collective thrust N |
| ``pwm``, ``battery`` | *MultiArray (``data[0:4]``); BatteryState (``voltage``), Float32/64 | thrust by `ThrustMap` |

(geometry_msgs, nav_msgs, sensor_msgs and std_msgs types; twist, IMU and setpoint optional.)

An Odometry pose gives the twist too (unless ``twist`` names another topic). Without a twist the
velocity is the positions' central differences, and without a setpoint its arrays are NaN (not
logged); the flight's ``config`` says which. A message's time is its header's stamp (a message
without a header: the bag's receive time), or the receive time for every message with ``stamps =
"receive"``. Each vehicle's streams are interpolated at its pose's stamps, then every vehicle onto
one uniform grid at ``rate_hz`` over the span all the topics cover (``t`` 0 at its start; the
start's stamp, s since the epoch, is ``config.start_s``). ``u_cmd`` is ``R e3 T / m - g e3``
(`downwash.real_logs.convert`).

Strict: a missing topic, a topic of another type, an empty topic, stamps that do not increase (or
are all 0: unset), a topic whose message count differs from the count the bag declares
(metadata.yaml, or the MCAP summary; a lone .db3 file declares none apart from its rows), data in
other units (`mapping.check_units`: a position in mm) or a file rosbags cannot parse raise
`BagFormatError` (a `UnitMismatchError` for units) naming the bag and the topic; a bad mapping
raises `ConfigError`. A sqlite3 file whose size is not its header's page count times its page size
(cut short) is refused before it is opened; an MCAP file cut anywhere has lost its end magic.

What no reader can see: neither storage as rosbags writes it has a checksum over the messages (its
MCAP chunks hold a CRC of 0). A changed byte inside a message's serialised data, or in the receive
time of a message read on that clock (one without a header, or any with ``stamps = "receive"``;
sqlite3 keeps it twice, in the row and in its timestamp index, which the query reads), is read as
written unless a check above catches it. An MCAP file whose chunks carry a CRC-32 (the mcap
library's default) has such a change caught by rosbags. A changed byte anywhere else is refused or
changes nothing read (tests/test_real_logs_ros2.py flips and cuts bytes of both storages).
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from downwash_core.errors import ConfigError, LogError
from downwash_core.geometry import quat_to_mat
from downwash_core.vehicles import ThrustMap, get_vehicle
from downwash.real_logs.convert import real_flight, resample, vehicle_arrays
from downwash.real_logs.mapping import (BagMapping, BagVehicle, Stream, check_units, field_steps, load_mapping,
                                        thrust_map_of)
from sim.logs import FlightLog

__all__ = ["BAG_FORMATS", "INSTALL_HINT", "BagFormatError", "read_bag_flight", "POSE_TYPES", "TWIST_TYPES",
           "SETPOINT_TYPES", "THRUST_TYPES", "PWM_TYPES", "BATTERY_TYPES", "IMU_TYPES"]

BAG_FORMATS = {".db3": "ros2-bag-sqlite3", ".mcap": "ros2-bag-mcap"}  # storage file suffix -> format
INSTALL_HINT = 'pip install "downwash-testbed[logs]"'
# message type -> field paths of (position, orientation)
POSE_TYPES = {
    "geometry_msgs/msg/PoseStamped": ("pose.position", "pose.orientation"),
    "geometry_msgs/msg/PoseWithCovarianceStamped": ("pose.pose.position", "pose.pose.orientation"),
    "geometry_msgs/msg/TransformStamped": ("transform.translation", "transform.rotation"),
    "nav_msgs/msg/Odometry": ("pose.pose.position", "pose.pose.orientation"),
}
# message type -> (field path of the linear velocity, its frame by the type's convention)
TWIST_TYPES = {"geometry_msgs/msg/TwistStamped": ("twist.linear", "world"),
               "nav_msgs/msg/Odometry": ("twist.twist.linear", "body")}  # nav_msgs: "in child_frame_id"
SETPOINT_TYPES = {"geometry_msgs/msg/PoseStamped": "pose.position", "nav_msgs/msg/Odometry": "pose.pose.position",
                  "geometry_msgs/msg/PointStamped": "point"}
THRUST_TYPES = {"std_msgs/msg/Float32": "data", "std_msgs/msg/Float64": "data"}
PWM_TYPES = {f"std_msgs/msg/{t}MultiArray": "data[0:4]" for t in ("Float32", "Float64", "Int16", "UInt16", "Int32",
                                                                   "UInt32", "Int64", "UInt64")}
BATTERY_TYPES = {"sensor_msgs/msg/BatteryState": "voltage", **THRUST_TYPES}
IMU_TYPES = ("sensor_msgs/msg/Imu",)
# role -> the types it takes without a field, each with its field path
_ROLE_TYPES = {"pose": POSE_TYPES, "twist": {k: p for k, (p, _) in TWIST_TYPES.items()}, "setpoint": SETPOINT_TYPES,
               "thrust": THRUST_TYPES, "pwm": PWM_TYPES, "battery": BATTERY_TYPES, "imu": dict.fromkeys(IMU_TYPES)}
_SQLITE_MAGIC = b"SQLite format 3\0"


class BagFormatError(LogError):
    """A bag that is not what its mapping says, or not readable: the message names the bag and the topic."""


@dataclass
class _Topic:
    """One topic's reading: its type, its stamps (ns) and, per extraction key, its values."""

    name: str
    msgtype: str
    declared: int
    extract: dict[tuple[str, str], tuple[tuple, int]] = field(default_factory=dict)  # key -> (steps, size)
    stamps: list[int] = field(default_factory=list)
    values: dict[tuple[str, str], list[np.ndarray]] = field(default_factory=dict)
    clock: str = "header"


def _rosbags() -> dict[str, Any]:
    """rosbags' reader, typestore and the exceptions its parsers raise on a damaged file, imported here
    (the ``logs`` extra is optional); ConfigError with the install hint when it is missing."""
    try:
        import apsw
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.rosbag2 import ReaderError
        from rosbags.serde import SerdeError
        from rosbags.typesys import Stores, TypesysError, get_typestore
        try:  # the zstd rosbags decompresses with: the standard library's from Python 3.14
            from compression import zstd
        except ImportError:
            from backports import zstd
    except ImportError as e:
        raise ConfigError(f"reading ROS 2 bags needs rosbags ({e}); install it: {INSTALL_HINT}") from None
    # rosbags' own errors, sqlite's (apsw), the decompressors' (zstd; lz4's RuntimeError), and what its
    # parsers let through on damaged bytes: seen when the tests flip bytes, struct and UTF-8 errors
    # (ValueError), a lookup of a damaged id (KeyError), an absurd length (Overflow-, MemoryError), ord()
    # of an empty read (TypeError); read off its code, a seek before a short file's start (OSError), its
    # asserts on a message definition's layout, an index or a read past a record (IndexError, EOFError)
    failures = (AnyReaderError, ReaderError, SerdeError, TypesysError, apsw.Error, zstd.ZstdError, RuntimeError,
                struct.error, ValueError, KeyError, OverflowError, MemoryError, TypeError, IndexError, EOFError,
                OSError, AssertionError)
    return {"AnyReader": AnyReader, "typestore": get_typestore(Stores.ROS2_HUMBLE), "failures": failures}


def read_bag_flight(bag: str | os.PathLike, mapping: BagMapping | str | os.PathLike, *,
                    thrust_maps: Mapping[str, ThrustMap] | None = None) -> FlightLog:
    """The real flight of a ROS 2 bag (a bag folder with metadata.yaml, or one .mcap or .db3 file)
    through `mapping` (a `BagMapping` or its TOML file); thrust_maps: vehicle name -> a `ThrustMap`
    for its PWM, instead of its kind's (`get_vehicle(kind).thrust_map`). Module doc for the rest."""
    if not isinstance(mapping, BagMapping):
        loaded = load_mapping(mapping)
        if not isinstance(loaded, BagMapping):
            raise ConfigError(f"{mapping}: format: a ROS 2 bag needs a mapping of format 'ros2-bag'")
        mapping = loaded
    maps = _thrust_maps(mapping, thrust_maps or {})
    lib = _rosbags()
    path = Path(bag)
    files = _bag_files(path)
    topics = _read_topics(path, mapping, lib)
    return _flight(path, mapping, topics, maps, files)


def _thrust_maps(mapping: BagMapping, given: Mapping[str, ThrustMap]) -> dict[str, ThrustMap]:
    """Each PWM vehicle's thrust map: given, else its kind's; ConfigError when it has none."""
    unknown = set(given) - {v.name for v in mapping.vehicles}
    if unknown:
        raise ConfigError(f"thrust_maps: no vehicle {sorted(unknown)} in the mapping (its vehicles: "
                          f"{', '.join(v.name for v in mapping.vehicles)})")
    return {v.name: thrust_map_of(v.kind, given.get(v.name), f"vehicles.{v.name}")
            for v in mapping.vehicles if v.pwm is not None}


# ----------------------------------------------------------------------------- the files


def _bag_files(path: Path) -> list[dict[str, str]]:
    """The bag's files with their format and SHA-256 (metadata.yaml and the storage files, or the one
    file); BagFormatError for no storage file, an unreadable file or a sqlite3 file cut short."""
    if not path.exists():
        raise BagFormatError(f"{path}: no such bag (a folder with metadata.yaml, or a .mcap or .db3 file)")
    paths = sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]
    storages = [p for p in paths if p.suffix in BAG_FORMATS]
    if not storages:
        raise BagFormatError(f"{path}: no storage file (.mcap or .db3) in it")
    out = []
    for p in paths:
        digest = hashlib.sha256()
        try:
            with p.open("rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    digest.update(chunk)
        except OSError as e:
            raise BagFormatError(f"{p}: cannot read it: {e.strerror or e}") from e
        if p.suffix == ".db3":
            _check_sqlite_size(p)
        out.append({"file": str(p), "format": BAG_FORMATS.get(p.suffix, "ros2-bag-metadata"),
                    "sha256": digest.hexdigest()})
    return out


def _check_sqlite_size(path: Path) -> None:
    """BagFormatError unless the file's size is its header's page count times its page size (sqlite
    reads a missing page as zeros, so a file cut short could otherwise read as a shorter bag)."""
    with path.open("rb") as f:
        head = f.read(100)
    size = path.stat().st_size
    if len(head) < 100 or not head.startswith(_SQLITE_MAGIC):
        raise BagFormatError(f"{path}: byte 0: not a sqlite3 database (no 'SQLite format 3' header)")
    page = int.from_bytes(head[16:18], "big")
    page = 65536 if page == 1 else page
    pages, counter, valid_for = (int.from_bytes(head[i:i + 4], "big") for i in (28, 24, 92))
    if counter == valid_for and pages * page != size:  # the header's page count is valid (sqlite >= 3.7.0)
        raise BagFormatError(f"{path}: byte {min(size, pages * page)}: the header says {pages} pages of {page} "
                             f"bytes ({pages * page} bytes), the file has {size}: cut short or damaged")


# ----------------------------------------------------------------------------- the topics


def _streams(v: BagVehicle) -> dict[str, Stream]:
    out = {k: getattr(v, k) for k in ("pose", "twist", "imu", "setpoint", "thrust", "pwm", "battery")}
    return {k: s for k, s in out.items() if s is not None}


def _plan(mapping: BagMapping, connections: dict[str, Any], where: str) -> dict[str, _Topic]:
    """Per topic to read: what to take from its messages (vehicle, quantity) -> (field steps, size);
    BagFormatError for a missing topic or one of another type, ConfigError for a misplaced field."""
    topics: dict[str, _Topic] = {}

    def need(vehicle: str, role: str, stream: Stream, quantity: str, path: str, size: int) -> None:
        con = connections[stream.topic]
        topic = topics.setdefault(stream.topic, _Topic(stream.topic, con.msgtype, con.msgcount))
        topic.extract[(vehicle, quantity)] = (field_steps(path, f"vehicles.{vehicle}.{role}"), size)

    for v in mapping.vehicles:
        for role, stream in _streams(v).items():
            if stream.topic not in connections:
                raise BagFormatError(f"{where}: topic {stream.topic}: not in the bag (vehicles.{v.name}.{role}; "
                                     f"its topics: {', '.join(sorted(connections)) or 'none'})")
            msgtype = connections[stream.topic].msgtype
            for quantity, path, size in _extractions(v, role, stream, msgtype, where):
                need(v.name, role, stream, quantity, path, size)
        if v.twist is None and connections[v.pose.topic].msgtype in TWIST_TYPES:  # an Odometry's twist
            need(v.name, "pose", v.pose, "vel", TWIST_TYPES[connections[v.pose.topic].msgtype][0], 3)
    return topics


def _extractions(v: BagVehicle, role: str, stream: Stream, msgtype: str, where: str) -> list[tuple[str, str, int]]:
    """(quantity, field path, size) to take from one stream's messages, by its role and type;
    BagFormatError for a type the role does not take (without a field that says where)."""
    allowed = _ROLE_TYPES[role]
    if stream.field is None and msgtype not in allowed:
        raise BagFormatError(f"{where}: topic {stream.topic}: type {msgtype}, vehicles.{v.name}.{role} takes "
                             f"{', '.join(allowed)}" + ("" if role in ("pose", "imu") else " (or give a field)"))
    if role == "imu":
        return []  # a flight log has no array for it: its type is checked, its messages are not read
    if role == "pose":
        return [("pos", POSE_TYPES[msgtype][0], 3), ("quat", POSE_TYPES[msgtype][1], 4)]
    size = {"twist": 3, "setpoint": 3, "thrust": 1, "pwm": 4, "battery": 1}[role]
    out = [({"twist": "vel", "setpoint": "ref_pos"}.get(role, role), stream.field or allowed[msgtype], size)]
    if role == "setpoint" and stream.velocity_field:
        out.append(("ref_vel", stream.velocity_field, 3))
    return out


def _read_topics(path: Path, mapping: BagMapping, lib: dict[str, Any]) -> dict[str, _Topic]:
    """Every mapped topic read whole, or a named error: nothing read in part is passed on."""
    failures = lib["failures"]
    try:
        reader = lib["AnyReader"]([path], default_typestore=lib["typestore"])
        reader.open()
    except failures as e:
        raise BagFormatError(f"{path}: not a readable ROS 2 bag: {type(e).__name__}: {e}") from None
    try:
        connections = {c.topic: c for c in reader.connections}
        topics = _plan(mapping, connections, str(path))
        wanted = [connections[name] for name in topics]
        messages = reader.messages(connections=wanted) if wanted else iter(())
        while True:
            try:
                con, received, raw = next(messages)
                msg = reader.deserialize(raw, con.msgtype)
            except StopIteration:
                break
            except failures as e:
                raise BagFormatError(f"{path}: damaged bag, reading its messages: {type(e).__name__}: {e}") from None
            _take(topics[con.topic], msg, received, mapping.stamps, path)
    finally:
        try:
            reader.close()
        except failures:  # closing a reader whose file was damaged: the error that matters was raised
            pass
    for topic in topics.values():
        _check_topic(topic, path)
    return topics


def _take(topic: _Topic, msg: Any, received: int, stamps: str, path: Path) -> None:
    """One message's stamp (ns) and values into its topic's reading."""
    k = len(topic.stamps)
    header = getattr(msg, "header", None)
    if stamps == "header" and header is not None:
        topic.stamps.append(int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec))
    elif isinstance(received, int):
        topic.clock = "receive"
        topic.stamps.append(received)
    else:  # sqlite hands back what a damaged row holds, a text or a blob
        raise BagFormatError(f"{path}: topic {topic.name}: message {k}: receive time {received!r:.40} is not an "
                             "integer: damaged bag")
    for key, (steps, size) in topic.extract.items():
        value = _resolve(msg, steps, topic, key, path)
        if hasattr(value, "w") and size == 4:  # a geometry_msgs Quaternion (x, y, z, w): here (w, x, y, z)
            value = (value.w, value.x, value.y, value.z)
        elif hasattr(value, "x") and size == 3:  # a Point or Vector3
            value = (value.x, value.y, value.z)
        try:
            array = np.asarray(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            array = np.empty(0)
        if array.size != size:
            raise BagFormatError(f"{path}: topic {topic.name}: message {k}: vehicles.{key[0]} {key[1]} takes "
                                 f"{size} number{'s' * (size > 1)}, the field holds {value!r:.80}")
        topic.values.setdefault(key, []).append(array)


def _resolve(msg: Any, steps: tuple, topic: _Topic, key: tuple[str, str], path: Path) -> Any:
    """The value at a field path of a message; ConfigError naming the mapping's vehicle, the topic and its fields."""
    value = msg
    for name, index in steps:
        if not hasattr(value, name):
            fields = [f for f in getattr(value, "__dataclass_fields__", {}) if not f.startswith("__")]
            raise ConfigError(f"{path}: vehicles.{key[0]}: topic {topic.name} ({topic.msgtype}): no field {name!r} "
                              f"(there: {', '.join(fields) or 'none'})")
        value = getattr(value, name)
        if index is not None:
            try:
                value = value[index]
            except (IndexError, TypeError):
                raise ConfigError(f"{path}: vehicles.{key[0]}: topic {topic.name}: field {name!r} has no "
                                  f"[{index}]") from None
    return value


def _check_topic(topic: _Topic, path: Path) -> None:
    """BagFormatError for a topic with no messages, another count than the bag declares, unset header
    stamps or stamps that do not increase."""
    where = f"{path}: topic {topic.name}"
    if not topic.stamps:
        raise BagFormatError(f"{where}: no messages")
    if len(topic.stamps) != topic.declared:
        raise BagFormatError(f"{where}: {len(topic.stamps)} messages read, the bag declares {topic.declared}: "
                             "damaged bag")
    stamps = np.asarray(topic.stamps, dtype=np.int64)
    if topic.clock == "header" and not stamps.any():
        raise BagFormatError(f"{where}: every header stamp is 0 (unset): read it with stamps = \"receive\"")
    steps = np.diff(stamps)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise BagFormatError(f"{where}: {topic.clock} stamp of message {k} ({_seconds(stamps[k])} s) does not "
                             f"increase (the one before: {_seconds(stamps[k - 1])} s)")


def _seconds(ns: int) -> str:
    """A stamp in ns as exact decimal seconds."""
    return f"{'-' if ns < 0 else ''}{abs(int(ns)) // 1_000_000_000}.{abs(int(ns)) % 1_000_000_000:09d}"


# ----------------------------------------------------------------------------- the flight


def _series(topic: _Topic, vehicle: str, quantity: str, t0: int) -> tuple[np.ndarray, np.ndarray]:
    """(times s from t0 ns, values (N, C)) of one quantity of one vehicle."""
    t = (np.asarray(topic.stamps, dtype=np.int64) - t0) * 1e-9
    return t, np.stack(topic.values[(vehicle, quantity)])


def _at(topic: _Topic, vehicle: str, quantity: str, t0: int, t: np.ndarray) -> np.ndarray:
    """One quantity of a vehicle, (N, C), interpolated at times t (N,) s from t0."""
    times, values = _series(topic, vehicle, quantity, t0)
    return resample(times, t, values)


def _vehicle(v: BagVehicle, topics: dict[str, _Topic], t0: int, grid: np.ndarray, thrust_map: ThrustMap | None,
             where: str, notes: dict[str, Any]) -> dict[str, np.ndarray]:
    """One vehicle's log arrays on the grid (s from t0), its streams checked for units; notes: what
    the flight's config says of it (where its velocity, setpoint and thrust come from)."""
    pose = topics[v.pose.topic]
    t, pos = _series(pose, v.name, "pos", t0)
    _, quat = _series(pose, v.name, "quat", t0)
    pos = pos * v.pose.scale
    check_units(f"{where}: topic {pose.name}", pos=pos, quat=quat)
    twist = v.twist or (v.pose if (v.name, "vel") in pose.values else None)  # an Odometry's own twist
    if twist is not None:
        vel = _at(topics[twist.topic], v.name, "vel", t0, t) * twist.scale
        frame = v.twist_frame or TWIST_TYPES.get(topics[twist.topic].msgtype, ("", "world"))[1]
        if frame == "body":  # to the world frame by the attitude at the same time
            vel = np.einsum("nij,nj->ni", quat_to_mat(quat / np.linalg.norm(quat, axis=1, keepdims=True)), vel)
        notes["velocity"] = f"{twist.topic} ({frame} frame)"
    else:
        vel = np.gradient(pos, t, axis=0)
        notes["velocity"] = "differenced positions (no twist topic)"
    check_units(f"{where}: vehicles.{v.name} velocity from {notes['velocity']}", vel=vel)
    ref_pos, ref_vel = _setpoint(v, topics, t0, t, where, notes)
    mass = v.mass if v.mass is not None else get_vehicle(v.kind).mass
    thrust = _thrust(v, topics, t0, grid, thrust_map, mass, where, notes)
    return vehicle_arrays(t, grid, pos=pos, vel=vel, quat=quat, ref_pos=ref_pos, ref_vel=ref_vel, thrust=thrust,
                          mass=mass)


def _setpoint(v: BagVehicle, topics: dict[str, _Topic], t0: int, t: np.ndarray, where: str,
              notes: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The reference position and velocity (N, 3) at the pose's times t; NaN when not logged."""
    if v.setpoint is None:
        notes["setpoint"] = "not logged (NaN)"
        return np.full((t.size, 3), np.nan), np.full((t.size, 3), np.nan)
    topic, s = topics[v.setpoint.topic], v.setpoint
    times, ref = _series(topic, v.name, "ref_pos", t0)
    ref = ref * s.scale
    check_units(f"{where}: topic {s.topic}", pos=ref)  # before differencing it
    if s.velocity_field:
        ref_vel = _series(topic, v.name, "ref_vel", t0)[1] * s.scale
        notes["setpoint"] = f"{s.topic} (velocity: {s.velocity_field})"
    else:
        ref_vel = np.gradient(ref, times, axis=0) if times.size > 1 else np.zeros_like(ref)
        notes["setpoint"] = f"{s.topic} (velocity: differenced setpoints)"
    check_units(f"{where}: topic {s.topic}", vel=ref_vel)
    return resample(times, t, ref), resample(times, t, ref_vel)


def _thrust(v: BagVehicle, topics: dict[str, _Topic], t0: int, grid: np.ndarray, thrust_map: ThrustMap | None,
            mass: float, where: str, notes: dict[str, Any]) -> np.ndarray:
    """The collective thrust (G,) N on the grid: the thrust topic's, or the PWM's and battery's through the map."""
    if v.thrust is not None:
        times, thrust = _series(topics[v.thrust.topic], v.name, "thrust", t0)
        thrust = thrust[:, 0] * v.thrust.scale
        check_units(f"{where}: topic {v.thrust.topic}", thrust=thrust, mass=mass)
        notes["thrust"] = f"{v.thrust.topic} (N)"
        return np.interp(grid, times, thrust)
    assert v.pwm is not None and v.battery is not None and thrust_map is not None  # mapping and _thrust_maps
    pwm_t, pwm = _series(topics[v.pwm.topic], v.name, "pwm", t0)
    bat_t, vbat = _series(topics[v.battery.topic], v.name, "battery", t0)
    pwm, vbat = pwm * v.pwm.scale, vbat[:, 0] * v.battery.scale
    check_units(f"{where}: topic {v.pwm.topic}", pwm=pwm)
    check_units(f"{where}: topic {v.battery.topic}", vbat=vbat)
    notes["thrust"] = (f"{v.pwm.topic} and {v.battery.topic} through the thrust map of "
                       f"{thrust_map.source or 'the caller'}")
    thrust = thrust_map.thrust(resample(pwm_t, grid, pwm), np.interp(grid, bat_t, vbat)).sum(axis=1)
    check_units(f"{where}: vehicles.{v.name} thrust from its PWM", thrust=thrust, mass=mass)
    return thrust


def _flight(path: Path, mapping: BagMapping, topics: dict[str, _Topic], maps: dict[str, ThrustMap],
            files: list[dict[str, str]]) -> FlightLog:
    """The flight log of the topics read: every vehicle on one grid over the span every topic covers."""
    used = [topic for topic in topics.values() if topic.values]
    t0 = min(topic.stamps[0] for topic in used)
    start = max(topic.stamps[0] for topic in used) - t0
    end = min(topic.stamps[-1] for topic in used) - t0
    if end - start < 2e9 / mapping.rate_hz:
        spans = {topic.name: f"{(topic.stamps[0] - t0) * 1e-9:.3f}-{(topic.stamps[-1] - t0) * 1e-9:.3f} s"
                 for topic in used}
        raise BagFormatError(f"{path}: the topics do not overlap in time for two samples at {mapping.rate_hz:g} Hz "
                             f"(their spans from the first stamp: {spans})")
    count = int(math.floor((end - start) * 1e-9 * mapping.rate_hz + 1e-9)) + 1
    grid = start * 1e-9 + np.arange(count) / mapping.rate_hz
    notes: dict[str, dict[str, Any]] = {v.name: {} for v in mapping.vehicles}
    per = [_vehicle(v, topics, t0, grid, maps.get(v.name), str(path), notes[v.name]) for v in mapping.vehicles]
    for v in mapping.vehicles:
        if v.imu is not None:
            notes[v.name]["imu"] = f"{v.imu.topic}: not used (a flight log has no array for a measured acceleration)"
    storage = next(f["format"] for f in files if f["format"] in BAG_FORMATS.values())
    meta: dict[str, Any] = {
        "source": {"format": storage, "files": files, "mapping": dict(mapping.source or {}),
                   "topics": {t.name: {"type": t.msgtype, "messages": len(t.stamps), "stamps": t.clock}
                              for t in topics.values()}},
        "vehicles": [v.name for v in mapping.vehicles], "frames": [v.name for v in mapping.vehicles],
        "masses": [v.mass if v.mass is not None else get_vehicle(v.kind).mass for v in mapping.vehicles],
        "config": {"rate_hz": mapping.rate_hz, "stamps": mapping.stamps, "start_s": (t0 + start) * 1e-9,
                   "streams": notes},
    }
    if all(v.kind for v in mapping.vehicles):
        meta["kinds"] = [v.kind for v in mapping.vehicles]
    return real_flight(grid - grid[0], per, meta)
