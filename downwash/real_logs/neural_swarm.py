"""The Neural-Swarm data set's onboard logs as flight logs, in SI units, vehicles aligned.

The data set (Shi et al., "Neural-Swarm2", github.com/aerorobotics/neural-swarm, no licence:
point the readers at your own clone) holds Crazyflie 2.x flights logged onboard by the uSD
deck (`downwash.real_logs.crazyflie_usd`): one file per vehicle and flight, ``cf<ID>_<NN>``,
the vehicles of one flight sharing ``NN`` in one task folder (``swap_sl``, ``randomwalk_ssl``, ...).
Logging started on every vehicle at one broadcast, so each log's first tick is the common
start (`read_flight`); the residual offset is checked by the setpoints' cross-correlation
(`setpoint_offset`).

The logged variables (the firmware's compressed state, integers):

| variable | unit | here |
|---|---|---|
| ``tick`` | us (uint32, wraps) | ``t`` s from the first tick |
| ``stateEstimateZ.x/y/z`` | mm | ``pos_est``, ``mocap_pos`` m (the onboard estimate fuses the motion capture) |
| ``stateEstimateZ.vx/vy/vz`` | mm/s | ``vel_est`` m/s |
| ``stateEstimateZ.quat`` | compressed quaternion | ``quat_est`` (w, x, y, z), ``yaw_est`` |
| ``ctrltargetZ.x/y/z``, ``.vx/vy/vz`` | mm, mm/s | ``ref_pos``, ``ref_vel`` |
| ``pwm.m1_pwm`` ... ``m4_pwm`` | 0-65535 | with ``pm.vbatMV`` (mV): the thrust (`ThrustMap`) |

``u_cmd`` is the acceleration of the rotors' thrust less gravity, ``R e3 T / m - g e3``, with T
from each rotor's PWM and the battery voltage (optionally through a first-order motor lag,
``motor_time_constant``: the PWM is what was asked of the motors; the thrust maps are those of the
vehicle kinds ``crazyflie_2_1`` and ``crazyflie_large`` of `downwash_core.vehicles`): so the labels
``f = a - u`` (`downwash.labels`) are the paper's residual force per mass, ``a - R T / m + g e3``, whatever model flew. The
reference's acceleration is not logged (``ref_acc`` 0) and neither is the prediction in use
(``f_hat`` NaN).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY
from downwash_core.vehicles import ThrustMap, get_vehicle
from downwash.real_logs.convert import real_flight, resample, vehicle_arrays
from downwash.real_logs.crazyflie_usd import UsdFormatError, UsdLog, decompress_quaternions, read_usd_sync
from sim.logs import FlightLog

__all__ = ["LoggedVehicle", "NEURAL_SWARM_VEHICLES", "VEHICLE_IDS", "REQUIRED_FIELDS", "flight_files",
           "read_flight", "flight_from_logs", "motor_lag", "setpoint_offset", "published_errors", "summary_flights",
           "TICK_WRAP"]

TICK_WRAP = 2**32  # us: the tick is a uint32 (71.6 minutes)
_TICK_STEP_US = (2_000, 50_000)  # a log at 20-500 Hz: its tick steps by 2-50 ms in microseconds
_FILE = re.compile(r"^cf(\d+)_(\d+)$")


@dataclass(frozen=True)
class LoggedVehicle:
    """A logged vehicle: its registered kind (`downwash_core.vehicles`, which holds its rotor thrust
    map) and its mass as the lab weighed it (kg; labels use it), with the mass's source."""

    name: str
    kind: str
    mass: float
    source: str

    @property
    def thrust_map(self) -> ThrustMap:
        return get_vehicle(self.kind).thrust_map


_SOURCE = "Neural-Swarm data set (github.com/aerorobotics/neural-swarm), data/training/datacollection*/"
NEURAL_SWARM_VEHICLES = {
    # 32 g as the data set's training code uses it (learning/training.py); the registry's crazyflie_2_1
    # (drone-models) weighs 31.9 g
    "small": LoggedVehicle("small", "crazyflie_2_1", 0.032, _SOURCE + "readme.txt; mass: learning/training.py"),
    "large": LoggedVehicle("large", "crazyflie_large", 0.067, _SOURCE + "parrot_frame.txt (mass: 67g)"),
}
VEHICLE_IDS = {50: "small", 51: "small", 52: "small", 100: "large", 101: "large", 102: "large"}

REQUIRED_FIELDS = (
    "tick", *(f"stateEstimateZ.{a}" for a in ("x", "y", "z", "vx", "vy", "vz", "quat")),
    *(f"ctrltargetZ.{a}" for a in ("x", "y", "z", "vx", "vy", "vz")),
    *(f"pwm.m{i}_pwm" for i in range(1, 5)), "pm.vbatMV",
)


def flight_files(folder: str | os.PathLike) -> dict[str, list[Path]]:
    """The flights of one task folder: flight number ``NN`` -> its vehicles' files ``cf<ID>_<NN>``, by ID."""
    flights: dict[str, list[Path]] = {}
    for path in sorted(Path(folder).iterdir()):
        m = _FILE.match(path.name)
        if m and path.is_file():
            flights.setdefault(m.group(2), []).append(path)
    return {k: sorted(v, key=lambda p: int(_FILE.match(p.name).group(1))) for k, v in sorted(flights.items())}


def _vehicle(path: Path) -> LoggedVehicle:
    m = _FILE.match(path.name)
    ident = int(m.group(1)) if m else None
    if ident not in VEHICLE_IDS:
        raise ConfigError(f"{path}: not a vehicle of the data set (known: "
                          f"{', '.join(f'cf{i} ({k})' for i, k in VEHICLE_IDS.items())})")
    return NEURAL_SWARM_VEHICLES[VEHICLE_IDS[ident]]


def _seconds(log: UsdLog) -> np.ndarray:
    """The log's times in s from its first tick, the tick's wraps undone; UsdFormatError unless the
    tick steps like microseconds at 20-500 Hz (the data set's CSV headers call it ms)."""
    tick = log.fields["tick"].astype(np.int64)
    steps = np.diff(tick)
    steps = np.where(steps < 0, steps + TICK_WRAP, steps)
    where = log.source.get("file", "log")
    if steps.size == 0:
        raise UsdFormatError(f"{where}: fewer than two records")
    step = float(np.median(steps))
    if not _TICK_STEP_US[0] <= step <= _TICK_STEP_US[1]:
        raise UsdFormatError(f"{where}: unit mismatch: 'tick' steps by {step:g} per record; expected microseconds "
                             f"of a 20-500 Hz log ({_TICK_STEP_US[0]}-{_TICK_STEP_US[1]})")
    if np.any(steps <= 0):
        raise UsdFormatError(f"{where}: 'tick' does not increase at record {int(np.argmax(steps <= 0)) + 1}")
    return np.concatenate([[0.0], np.cumsum(steps)]) * 1e-6


def motor_lag(thrust: np.ndarray, dt: float, time_constant: float | None) -> np.ndarray:
    """thrust (N,) sampled every dt s through a first-order lag of `time_constant` s (exact for a
    thrust held over each step), from rest at its first value; None: unchanged."""
    if time_constant is None:
        return thrust
    alpha = 1.0 - math.exp(-dt / time_constant)
    out = np.empty_like(thrust)
    out[0] = thrust[0]
    for k in range(1, len(thrust)):  # a few thousand steps per flight
        out[k] = out[k - 1] + alpha * (thrust[k - 1] - out[k - 1])
    return out


def _vehicle_arrays(log: UsdLog, vehicle: LoggedVehicle, t: np.ndarray, grid: np.ndarray,
                    time_constant: float | None) -> dict[str, np.ndarray]:
    f = log.fields
    col = lambda *names, scale=1e-3: np.stack([f[n].astype(np.float64) for n in names], axis=1) * scale  # noqa: E731
    pwm = resample(t, grid, col(*(f"pwm.m{i}_pwm" for i in range(1, 5)), scale=1.0))
    vbat = np.interp(grid, t, f["pm.vbatMV"].astype(np.float64)) * 1e-3
    thrust = motor_lag(vehicle.thrust_map.thrust(pwm, vbat).sum(axis=1), float(grid[1] - grid[0]), time_constant)
    return vehicle_arrays(
        t, grid, pos=col(*(f"stateEstimateZ.{a}" for a in "xyz")), vel=col(*(f"stateEstimateZ.v{a}" for a in "xyz")),
        quat=decompress_quaternions(f["stateEstimateZ.quat"]), ref_pos=col(*(f"ctrltargetZ.{a}" for a in "xyz")),
        ref_vel=col(*(f"ctrltargetZ.v{a}" for a in "xyz")), thrust=thrust, mass=vehicle.mass)


def flight_from_logs(logs: Sequence[UsdLog], vehicles: Sequence[LoggedVehicle], names: Sequence[str],
                     rate_hz: float = 100.0, motor_time_constant: float | None = None) -> FlightLog:
    """One flight of decoded logs (one per vehicle, each started at one broadcast): every vehicle's
    signals in SI units on one uniform grid at `rate_hz` from the common start to the first log's end
    (module doc); motor_time_constant: s, the thrust's first-order lag behind the PWM (None: none)."""
    if not 10.0 <= rate_hz <= 500.0:
        raise ConfigError(f"rate_hz: allowed 10-500 Hz, got {rate_hz!r}")
    if motor_time_constant is not None and not 0.0 < motor_time_constant <= 1.0:
        raise ConfigError(f"motor_time_constant: allowed (0, 1] s or None, got {motor_time_constant!r}")
    for log in logs:
        missing = [n for n in REQUIRED_FIELDS if n not in log.fields]
        if missing:
            raise UsdFormatError(f"{log.source.get('file', 'log')}: not a Neural-Swarm onboard log: no {missing}")
    times = [_seconds(log) for log in logs]
    end = min(t[-1] for t in times)
    grid = np.arange(int(math.floor(end * rate_hz)) + 1) / rate_hz
    per = [_vehicle_arrays(log, v, t, grid, motor_time_constant) for log, v, t in zip(logs, vehicles, times)]
    return real_flight(grid, per, {
        "source": {"format": logs[0].source.get("format"), "files": [dict(log.source) for log in logs]},
        "vehicles": list(names), "frames": [v.name for v in vehicles], "kinds": [v.kind for v in vehicles],
        "masses": [v.mass for v in vehicles],
        "config": {"rate_hz": rate_hz, "motor_time_constant": motor_time_constant,
                   "thrust_maps": {v.name: v.thrust_map.source for v in vehicles}},
    })


def read_flight(files: Sequence[str | os.PathLike], rate_hz: float = 100.0,
                motor_time_constant: float | None = None) -> FlightLog:
    """The flight of the data set's files of its vehicles (``cf<ID>_<NN>``, one flight number), as
    `flight_from_logs`; ConfigError for a vehicle ID the data set does not have."""
    paths = [Path(f) for f in files]
    vehicles = [_vehicle(p) for p in paths]
    return flight_from_logs([read_usd_sync(p) for p in paths], vehicles, [p.name.split("_")[0] for p in paths],
                            rate_hz, motor_time_constant)


def setpoint_offset(log: FlightLog, a: int, b: int, max_lag_s: float = 1.0) -> float:
    """s: the lag that best aligns vehicle b's setpoint speed with vehicle a's (the peak of their
    cross-correlation within +-max_lag_s). Vehicles of one task start and stop their moves together
    (a swap moves them in opposite directions), so the speeds' peak is at 0 when the common start holds."""
    dt = float(log["t"][1] - log["t"][0])
    x, y = (np.linalg.norm(log["ref_vel"][:, v], axis=1) for v in (a, b))
    x, y = x - x.mean(), y - y.mean()
    lags = np.arange(-int(max_lag_s / dt), int(max_lag_s / dt) + 1)
    n = len(x)
    score = [np.sum(x[max(0, -k):n - max(0, k)] * y[max(0, k):n - max(0, -k)]) for k in lags]
    return float(lags[int(np.argmax(score))] * dt)


_PUBLISHED = re.compile(r"^(\w+2[SL]) loss after training ([0-9.eE+-]+)\s*$")


def published_errors(log_file: str | os.PathLike) -> dict[str, dict[str, float]]:
    """The data set's own per-type errors (its ``learning/log.txt``, the training run the repository
    reports): interaction type -> ``mse_gf2``, the mean squared error of the vertical force as that
    script computes it (gram-force squared, on its training samples after training), and ``z_rmse``,
    its root as an acceleration of the target vehicle (m/s^2: gram-force x 1e-3 g / the target's mass),
    comparable with a vertical RMSE here. Empty when the file holds no such line."""
    out = {}
    for line in Path(log_file).read_text(errors="replace").splitlines():
        m = _PUBLISHED.match(line.strip())
        if m:
            frame = "small" if m.group(1).endswith("S") else "large"
            mse = float(m.group(2))
            out[m.group(1)] = {"mse_gf2": mse,
                               "z_rmse": math.sqrt(mse) * 1e-3 * GRAVITY / NEURAL_SWARM_VEHICLES[frame].mass}
    return out


_SUMMARY_TASK = re.compile(r"^#\s*(?:\(\d+\)\s*)?\./([\w-]+)/?\s*(?:;.*)?$")
_SUMMARY_NUMBERS = re.compile(r"^#\s*(\[[^\]]*\]|(?:\d+\s*(?:\(\w+\))?\s*)+)$")


def summary_flights(summary_file: str | os.PathLike) -> dict[str, set[str]]:
    """The flights the data set's summary of a day (its ``learning/datacollection<NN>_summary``) lists
    per task folder: task -> the flight numbers ``NN`` it keeps. A task line (``# ./swap_sl; cf 51 & 101``
    or ``# (11) ./swap_sl; ...``) followed by a line of numbers (``# ['00', '01']`` or ``# 00(LS) 01(SL)``)."""
    out: dict[str, set[str]] = {}
    lines = [line.strip() for line in Path(summary_file).read_text(errors="replace").splitlines()]
    for task_line, numbers_line in zip(lines, lines[1:]):
        task, numbers = _SUMMARY_TASK.match(task_line), _SUMMARY_NUMBERS.match(numbers_line)
        if task and numbers:
            out[task.group(1)] = set(re.findall(r"\d+", re.sub(r"\(\w+\)", "", numbers.group(1))))
    return out
