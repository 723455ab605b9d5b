"""Flight logs: one row per controller tick, compressed `.npz`, atomic writes.

A log holds the arrays below (T rows, V vehicles) plus a JSON metadata record with
the schema version, the full flight config and the seed. Loading checks all of it
and names the file in every error, so a truncated or foreign file never reaches
training silently.

A real flight (a lab's log read by `downwash.real_logs`) is a log like any other, with a
``source`` in its metadata (the file, its format and digest) and without the arrays of
the truth (`TRUTH_ARRAYS`), which no lab has; labels and data sets read the same arrays
from both.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from downwash_core.errors import LogError
from downwash_core.io import atomic_write_bytes, to_json
from downwash_core.status import Status

__all__ = [
    "SCHEMA_VERSION",
    "ARRAY_SPECS",
    "OPTIONAL_SPECS",
    "TRUTH_ARRAYS",
    "FlightLog",
    "LogError",
    "save_log",
    "load_log",
]

SCHEMA_VERSION = 2  # 2: quat_est (the motion-capture attitude) added

# name -> (trailing shape after (T,), meaning). V is the number of vehicles.
ARRAY_SPECS: dict[str, tuple[tuple[str, ...], str]] = {
    "t": ((), "s, time of the controller tick"),
    "pos": (("V", 3), "m, true position, world frame (z up)"),
    "vel": (("V", 3), "m/s, true velocity, world frame"),
    "quat": (("V", 4), "true attitude, MuJoCo (w, x, y, z), body to world"),
    "pos_est": (("V", 3), "m, Kalman-filter position estimate used by the controller"),
    "vel_est": (("V", 3), "m/s, Kalman-filter velocity estimate"),
    "quat_est": (("V", 4), "motion-capture attitude (w, x, y, z), body to world: what predictors and labels use"),
    "yaw_est": (("V",), "rad, heading used by the controller (of the motion-capture attitude)"),
    "mocap_pos": (("V", 3), "m, latest motion-capture position (noisy)"),
    "ref_pos": (("V", 3), "m, reference position"),
    "ref_vel": (("V", 3), "m/s, reference velocity"),
    "ref_acc": (("V", 3), "m/s^2, reference acceleration (feed-forward)"),
    "u_cmd": (("V", 3), "m/s^2, commanded acceleration actually applied, compensation included, gravity excluded"),
    "f_hat": (("V", 3), "m/s^2, downwash prediction in use (held 45 Hz output; 0 without a model)"),
    "field_mean": (("V", 3), "m/s^2, true mean downwash on the vehicle at the tick"),
    "field_applied": (("V", 3), "m/s^2, downwash actually applied at the tick (mean + turbulence)"),
}
# what only a simulator knows: a real flight's log (meta "source") has none of them
TRUTH_ARRAYS = ("pos", "vel", "quat", "field_mean", "field_applied")
# logged when their component is there: the wind (`sim.wind`) and a guard's applied fraction (`sim.predictor`)
OPTIONAL_SPECS: dict[str, tuple[tuple[str, ...], str]] = {
    "wind": (("V", 3), "m/s, the air's velocity at the vehicle (mean + gust)"),
    "wind_acc": (("V", 3), "m/s^2, the wind's drag on the vehicle"),
    "applied": (("V",), "fraction of the model's prediction applied at its last due call (a guard; NaN: no guard)"),
}


@dataclass
class FlightLog:
    """One flight of one world.

    arrays: name -> (T, ...) array, see ARRAY_SPECS.
    meta: JSON-serialisable dict; always holds schema_version, seed, config,
      vehicles (names), roles, leader and follower (indices), status (a `Status`
      code; a flight that ends early keeps its rows up to the end), message; a real
      flight's also its ``source`` (and its arrays lack `TRUTH_ARRAYS`).
    """

    arrays: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def __len__(self) -> int:
        return int(self.arrays["t"].shape[0])

    @property
    def real(self) -> bool:
        """A lab's flight (its meta has a ``source``): no truth arrays."""
        return "source" in self.meta

    @property
    def n_vehicles(self) -> int:
        return int(self.arrays["pos_est"].shape[1])

    @property
    def ok(self) -> bool:
        return self.meta.get("status", Status.OK) == Status.OK


def save_log(path: str | os.PathLike, log: FlightLog) -> None:
    """Save a flight log atomically as compressed `.npz` (arrays + `__meta__` JSON)."""
    _check_arrays(log.arrays, where=str(path), real="source" in log.meta)
    meta = dict(log.meta)
    meta["schema_version"] = SCHEMA_VERSION
    buf = io.BytesIO()
    meta_bytes = np.frombuffer(to_json(meta).encode(), dtype=np.uint8)
    np.savez_compressed(buf, __meta__=meta_bytes, **log.arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_log(path: str | os.PathLike) -> FlightLog:
    """Load and validate a flight log; raises LogError naming the file on any problem."""
    path = Path(path)
    if not path.is_file():
        raise LogError(f"{path}: no such log file")
    try:
        with np.load(path, allow_pickle=False) as z:
            contents = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise LogError(f"{path}: not a readable .npz flight log (truncated or foreign file): {e}") from e
    if "__meta__" not in contents:
        raise LogError(f"{path}: not a flight log of this project (no __meta__ record)")
    try:
        meta = json.loads(contents.pop("__meta__").tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise LogError(f"{path}: corrupt metadata record: {e}") from e
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise LogError(f"{path}: schema version {version!r}, this code reads version {SCHEMA_VERSION}")
    _check_arrays(contents, where=str(path), real="source" in meta)
    return FlightLog(contents, meta)


def _check_arrays(arrays: dict[str, np.ndarray], where: str, real: bool = False) -> None:
    """LogError unless `arrays` hold every array of ARRAY_SPECS (a real flight: all but TRUTH_ARRAYS,
    which it must not hold) in its shape."""
    specs = {k: v for k, v in ARRAY_SPECS.items() if not (real and k in TRUTH_ARRAYS)}
    missing = sorted(set(specs) - set(arrays))
    if missing:
        raise LogError(f"{where}: missing arrays {missing}")
    if real and set(TRUTH_ARRAYS) & set(arrays):
        raise LogError(f"{where}: a real flight (its metadata has a source) holds simulator truth arrays "
                       f"{sorted(set(TRUTH_ARRAYS) & set(arrays))}")
    T = arrays["t"].shape[0] if arrays["t"].ndim == 1 else None
    if T is None:
        raise LogError(f"{where}: 't' must be 1-D, got shape {arrays['t'].shape}")
    V = arrays["pos_est"].shape[1] if arrays["pos_est"].ndim == 3 else None
    for name, (trail, _) in specs.items():
        shape = arrays[name].shape
        expected = (T,) + tuple(V if d == "V" else d for d in trail)
        if shape != expected:
            raise LogError(f"{where}: array '{name}' has shape {shape}, expected {expected}")
