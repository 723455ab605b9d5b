"""The Crazyflie firmware's event-based uSD log (version 2) to a real flight's log, through a mapping.

`read_events_flight(files, mapping)` decodes each file exactly (`crazyflie_usd.read_usd_events`;
one file per vehicle) and takes the records of the mapping's event (``fixedFrequency`` by default:
the periodic log of the deck's configuration). A `downwash.real_logs.mapping.UsdMapping` (a
``format = "crazyflie-usd-events"`` TOML file; `mapping.default_usd_mapping` when none is given)
says which variables give each quantity and their scale to SI units, listing alternatives the first
logged one of which is used:

| quantity | e.g. (the default mapping) | gives |
|---|---|---|
| ``position`` | ``stateEstimate.x/y/z`` (m), ``stateEstimateZ.x/y/z`` (int16 mm, scale 0.001) | ``pos_est`` |
| ``velocity`` | ``stateEstimate.vx..`` (m/s), ``stateEstimateZ.vx..`` (mm/s) | ``vel_est`` |
| ``quaternion`` | ``stateEstimate.qw..qz``, or ``stateEstimateZ.quat`` compressed | ``quat_est`` |
| ``setpoint_position`` | ``ctrltarget.x..`` (m), ``ctrltargetZ.x..`` (mm) | ``ref_pos`` |
| ``setpoint_velocity`` | ``ctrltarget.vx..`` (m/s), ``ctrltargetZ.vx..`` (mm/s) | ``ref_vel`` |
| ``pwm``, ``battery`` | ``pwm.m1_pwm..``, ``motor.m1..`` (0-65535); ``pm.vbat`` (V), ``.vbatMV`` (mV) | thrust |
| ``thrust`` | instead of pwm: a variable of the collective thrust (N) | thrust |

(velocity and the setpoint are optional.)

The time is each record's 64-bit microsecond stamp (its steps must look like microseconds of a
1-1000 Hz log and increase). Without a velocity, the positions' central differences; without a
setpoint velocity, the setpoints' (its position absent: NaN, not logged); the flight's ``config``
says which variables gave what. Several files (one per vehicle) are aligned at their first
records (``align="start"``: logging started at one broadcast, as in the Neural-Swarm data set) or
on the stamps as they are (``align="clock"``: synchronised clocks), every vehicle on one grid at
``rate_hz`` over the span all cover. An event or variable the mapping needs and the file lacks is
an `EventsMappingError` naming the file, the event and what it holds; values in other units
(`mapping.check_units`: a position in mm read with scale 1) a `UnitMismatchError`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError, LogError
from downwash_core.vehicles import ThrustMap, get_vehicle
from downwash.real_logs.convert import real_flight, resample, vehicle_arrays
from downwash.real_logs.crazyflie_usd import USD_EVENTS_FORMAT, UsdLog, decompress_quaternions, read_usd_events
from downwash.real_logs.mapping import (UnitMismatchError, UsdMapping, Variables, check_units, default_usd_mapping,
                                        load_mapping, thrust_map_of)
from sim.logs import FlightLog

__all__ = ["EventsMappingError", "ALIGNS", "STAMP_STEP_US", "read_events_flight"]

ALIGNS = ("start", "clock")
STAMP_STEP_US = (1_000, 1_000_000)  # us: the median step of a 1-1000 Hz log's microsecond stamps


class EventsMappingError(LogError):
    """An event-based log that does not hold what its mapping says: names the file, the event and the variables."""


def read_events_flight(files: str | os.PathLike | Sequence[str | os.PathLike],
                       mapping: UsdMapping | str | os.PathLike | None = None, *, names: Sequence[str] | None = None,
                       align: str = "start", thrust_map: ThrustMap | None = None) -> FlightLog:
    """The real flight of event-based uSD logs, one file per vehicle (named `names`, default the files'
    names), through `mapping` (a `UsdMapping`, its TOML file, or None: the default mapping); thrust_map:
    instead of the mapping kind's (`get_vehicle(kind).thrust_map`). Module doc for the rest."""
    paths = [Path(files)] if isinstance(files, (str, os.PathLike)) else [Path(f) for f in files]
    mapping = _mapping(mapping)
    names = [p.name for p in paths] if names is None else list(names)
    if not paths or len(names) != len(paths) or len(set(names)) != len(names):
        raise ConfigError(f"names: one distinct name per file ({len(paths)} files), got {names!r}")
    if align not in ALIGNS:
        raise ConfigError(f"align: got {align!r}; allowed: {', '.join(ALIGNS)}")
    if mapping.pwm:
        thrust_map = thrust_map_of(mapping.kind, thrust_map, "mapping: usd")
    logs = [_event_log(p, mapping.event) for p in paths]
    stamps = [_stamps(log) for log in logs]
    starts = [int(s[0]) if align == "start" else min(int(x[0]) for x in stamps) for s in stamps]
    times = [(s - s0).astype(np.float64) * 1e-6 for s, s0 in zip(stamps, starts)]
    start, end = max(t[0] for t in times), min(t[-1] for t in times)
    if end - start < 2.0 / mapping.rate_hz:
        raise EventsMappingError(f"{', '.join(map(str, paths))}: the logs do not overlap in time for two samples at "
                                 f"{mapping.rate_hz:g} Hz (align={align!r})")
    grid = start + np.arange(int(math.floor((end - start) * mapping.rate_hz + 1e-9)) + 1) / mapping.rate_hz
    used: dict[str, dict[str, Any]] = {}
    per = [_vehicle(log, t, grid, mapping, thrust_map, used.setdefault(n, {})) for log, t, n in zip(logs, times, names)]
    mass = mapping.mass if mapping.mass is not None else get_vehicle(mapping.kind).mass
    meta: dict[str, Any] = {
        "source": {"format": USD_EVENTS_FORMAT, "event": mapping.event, "mapping": dict(mapping.source or {}),
                   "files": [{k: log.source[k] for k in ("file", "format", "sha256")} for log in logs]},
        "vehicles": names, "frames": names, "masses": [mass] * len(names),
        "config": {"rate_hz": mapping.rate_hz, "align": align, "start_s": float(start), "variables": used,
                   **({"thrust_map": thrust_map.source or "the caller's"} if mapping.pwm else {})},
    }
    if mapping.kind:
        meta["kinds"] = [mapping.kind] * len(names)
    return real_flight(grid - start, per, meta)


def _mapping(mapping: UsdMapping | str | os.PathLike | None) -> UsdMapping:
    if mapping is None:
        return default_usd_mapping()
    if isinstance(mapping, UsdMapping):
        return mapping
    loaded = load_mapping(mapping)
    if not isinstance(loaded, UsdMapping):
        raise ConfigError(f"{mapping}: format: an event-based uSD log needs a mapping of format "
                          "'crazyflie-usd-events'")
    return loaded


def _event_log(path: Path, event: str) -> UsdLog:
    """The records of one event of a file (decoded exactly, or UsdFormatError); at least two."""
    events = read_usd_events(path)
    if event not in events:
        raise EventsMappingError(f"{path}: no event {event!r} (its events: {', '.join(events) or 'none'})")
    log = events[event]
    if len(log) < 2:
        raise EventsMappingError(f"{path}: event {event!r}: {len(log)} records, a flight needs two or more")
    return log


def _stamps(log: UsdLog) -> np.ndarray:
    """The records' stamps (N,) int64 us; UnitMismatchError unless they step like microseconds of a
    1-1000 Hz log, EventsMappingError where one does not increase."""
    where = f"{log.source['file']}: event {log.source['event']!r}"
    stamps = log.fields["timestamp"].astype(np.int64)
    steps = np.diff(stamps)
    step = float(np.median(steps))
    if not STAMP_STEP_US[0] <= step <= STAMP_STEP_US[1]:
        raise UnitMismatchError(f"{where}: unit mismatch: the timestamp steps by {step:g} per record; expected "
                                f"microseconds of a 1-1000 Hz log ({STAMP_STEP_US[0]}-{STAMP_STEP_US[1]})")
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise EventsMappingError(f"{where}: the timestamp of record {k} ({stamps[k]} us) does not increase (the one "
                                 f"before: {stamps[k - 1]} us)")
    return stamps


def _pick(log: UsdLog, quantity: str, alternatives: tuple[Variables, ...], required: bool,
          used: dict[str, Any]) -> np.ndarray | None:
    """(N, C) in SI units of the first alternative whose variables are all logged; None when none is
    and the quantity is optional, EventsMappingError naming what was looked for when it is not."""
    for alt in alternatives:
        if all(name in log.fields for name in alt.names):
            used[quantity] = list(alt.names)
            if alt.compressed:
                return decompress_quaternions(log.fields[alt.names[0]])
            return np.stack([log.fields[n].astype(np.float64) for n in alt.names], axis=1) * alt.scale
    if required:
        looked = " or ".join("(" + ", ".join(a.names) + ")" for a in alternatives)
        raise EventsMappingError(f"{log.source['file']}: event {log.source['event']!r}: no {quantity}: none of "
                                 f"{looked} is logged (its variables: {', '.join(list(log.fields)[1:])})")
    return None


def _vehicle(log: UsdLog, t: np.ndarray, grid: np.ndarray, mapping: UsdMapping, thrust_map: ThrustMap | None,
             used: dict[str, Any]) -> dict[str, np.ndarray]:
    """One vehicle's log arrays on the grid from its event's records at times t (N,) s."""
    where = f"{log.source['file']}: event {log.source['event']!r}"
    pos = _pick(log, "position", mapping.position, True, used)
    quat = _pick(log, "quaternion", mapping.quaternion, True, used)
    check_units(where, pos=pos, quat=quat)  # before differencing it
    vel = _pick(log, "velocity", mapping.velocity, False, used)
    if vel is None:
        vel, used["velocity"] = np.gradient(pos, t, axis=0), "differenced positions"
    check_units(where, vel=vel)
    ref_pos = _pick(log, "setpoint_position", mapping.setpoint_position, False, used)
    if ref_pos is None:
        ref_pos, used["setpoint_position"] = np.full_like(pos, np.nan), "not logged (NaN)"
    else:
        check_units(f"{where}: setpoint", pos=ref_pos)
    ref_vel = _pick(log, "setpoint_velocity", mapping.setpoint_velocity, False, used)
    if ref_vel is None and np.isnan(ref_pos).all():
        ref_vel, used["setpoint_velocity"] = np.full_like(pos, np.nan), "not logged (NaN)"
    elif ref_vel is None:
        ref_vel, used["setpoint_velocity"] = np.gradient(ref_pos, t, axis=0), "differenced setpoints"
    if not np.isnan(ref_vel).all():
        check_units(f"{where}: setpoint", vel=ref_vel)
    mass = mapping.mass if mapping.mass is not None else get_vehicle(mapping.kind).mass
    thrust = _thrust(log, t, grid, mapping, thrust_map, mass, where, used)
    return vehicle_arrays(t, grid, pos=pos, vel=vel, quat=quat, ref_pos=ref_pos, ref_vel=ref_vel, thrust=thrust,
                          mass=mass)


def _thrust(log: UsdLog, t: np.ndarray, grid: np.ndarray, mapping: UsdMapping, thrust_map: ThrustMap | None,
            mass: float, where: str, used: dict[str, Any]) -> np.ndarray:
    """The collective thrust (G,) N on the grid: a thrust variable's, or the PWM's and battery's through the map."""
    if mapping.thrust:
        thrust = _pick(log, "thrust", mapping.thrust, True, used)[:, 0]
        check_units(where, thrust=thrust, mass=mass)
        return np.interp(grid, t, thrust)
    assert thrust_map is not None  # read_events_flight found it
    pwm = _pick(log, "pwm", mapping.pwm, True, used)
    vbat = _pick(log, "battery", mapping.battery, True, used)[:, 0]
    check_units(where, pwm=pwm, vbat=vbat)
    thrust = thrust_map.thrust(resample(t, grid, pwm), np.interp(grid, t, vbat)).sum(axis=1)
    check_units(f"{where}: thrust from the PWM", thrust=thrust, mass=mass)
    return thrust
