"""A documented CSV layout any lab can write from its own logger, read into a real flight's log.

One file per flight, one row per vehicle and sample, the columns named with their units in
brackets (the order is free, further columns are ignored):

| column | unit | what |
|---|---|---|
| `t[s]` | s | time on one clock for every vehicle (the logger's) |
| `vehicle` | - | the vehicle's name (any text without a comma) |
| `x[m]`, `y[m]`, `z[m]` | m | position, world frame, z up (the lab's estimate, fused with its motion capture) |
| `vx[m/s]`, `vy[m/s]`, `vz[m/s]` | m/s | velocity, world frame |
| `qw`, `qx`, `qy`, `qz` | - | attitude, body to world (normalised on reading) |
| `ref_x[m]` ... `ref_vz[m/s]` | m, m/s | the setpoint's position and velocity |
| `thrust[N]` | N | the rotors' total thrust (from the lab's thrust map of its commands) |
| `mass[kg]` | kg | the vehicle's mass |
| `kind` (optional) | - | a registered vehicle kind (`downwash_core.vehicles.VEHICLES`), for models of kinds |

`read_csv_flight` reads a whole file or raises `TabularFormatError` naming the file, the line
and the column: a missing column, a column in another unit (`x[mm]`), a value that is not a
finite number, a vehicle's times that do not increase, a vehicle whose mass or kind changes.
Every vehicle is resampled onto one uniform grid from the latest first sample to the earliest
last one. `write_csv_flight` writes the layout (the tests' files, and a template for yours).
A CSV file carries no checksum: a changed digit that still parses is read as written.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import os
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from downwash_core.errors import ConfigError, LogError
from downwash_core.io import atomic_write_bytes
from downwash_core.vehicles import VEHICLES
from downwash.real_logs.convert import real_flight, vehicle_arrays
from sim.logs import FlightLog

__all__ = ["CSV_LAYOUT", "COLUMNS", "TabularFormatError", "read_csv_flight", "write_csv_flight"]

CSV_LAYOUT = "downwash-real-flight-csv-1"
# name -> unit ("" for none): the columns every file holds
COLUMNS = {
    "t": "s", **{a: "m" for a in ("x", "y", "z")}, **{a: "m/s" for a in ("vx", "vy", "vz")},
    **{q: "" for q in ("qw", "qx", "qy", "qz")}, **{f"ref_{a}": "m" for a in ("x", "y", "z")},
    **{f"ref_{a}": "m/s" for a in ("vx", "vy", "vz")}, "thrust": "N", "mass": "kg",
}
_HEADER = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[([^\]]*)\])?\s*$")


class TabularFormatError(LogError):
    """A CSV flight that is not the documented layout: the message names the file, line and column."""


def _columns(header: list[str], where: str) -> dict[str, int]:
    """name -> index of the layout's columns (and `vehicle`, `kind`) in a header; unit mismatches refused."""
    found: dict[str, tuple[int, str]] = {}
    for i, cell in enumerate(header):
        m = _HEADER.match(cell)
        if m:
            found.setdefault(m.group(1), (i, m.group(2) or ""))
    for name, unit in COLUMNS.items():
        if name not in found:
            raise TabularFormatError(f"{where}: line 1: no column {name}[{unit}]" if unit else
                                     f"{where}: line 1: no column {name}")
        if found[name][1] != unit:
            raise TabularFormatError(f"{where}: line 1: unit mismatch: column {header[found[name][0]]!r} is in "
                                     f"{found[name][1] or 'no unit'}; this layout takes {name}"
                                     + (f"[{unit}]" if unit else " without a unit"))
    if "vehicle" not in found:
        raise TabularFormatError(f"{where}: line 1: no column vehicle")
    return {name: found[name][0] for name in (*COLUMNS, "vehicle", *(["kind"] if "kind" in found else []))}


def read_csv_flight(path: str | os.PathLike, rate_hz: float = 100.0) -> FlightLog:
    """The real flight of a CSV file in the documented layout (module doc), on a grid at `rate_hz`."""
    if not 10.0 <= rate_hz <= 500.0:
        raise ConfigError(f"rate_hz: allowed 10-500 Hz, got {rate_hz!r}")
    path = Path(path)
    try:
        raw = path.read_bytes()
        text = raw.decode("utf-8")
    except OSError as e:
        raise TabularFormatError(f"{path}: cannot read it: {e.strerror or e}") from e
    except UnicodeDecodeError as e:
        raise TabularFormatError(f"{path}: byte {e.start}: not UTF-8 text") from None
    rows = list(csv.reader(io.StringIO(text)))
    if not rows:
        raise TabularFormatError(f"{path}: empty file (no header)")
    cols = _columns(rows[0], str(path))
    samples: dict[str, list[list[float]]] = {}
    fixed: dict[str, tuple[float, str | None]] = {}
    for line, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) <= max(cols.values()):
            raise TabularFormatError(f"{path}: line {line}: {len(row)} values, the header has {len(rows[0])}")
        values = []
        for name in COLUMNS:
            cell = row[cols[name]]
            try:
                value = float(cell)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                raise TabularFormatError(f"{path}: line {line}: column {rows[0][cols[name]]!r}: not a finite "
                                         f"number: {cell!r}")
            values.append(value)
        vehicle = row[cols["vehicle"]].strip()
        kind = (row[cols["kind"]].strip() or None) if "kind" in cols else None
        mass = values[list(COLUMNS).index("mass")]
        if fixed.setdefault(vehicle, (mass, kind)) != (mass, kind):
            raise TabularFormatError(f"{path}: line {line}: vehicle {vehicle!r} changes its mass or kind "
                                     f"({fixed[vehicle]} before, {(mass, kind)} here)")
        series = samples.setdefault(vehicle, [])
        if series and values[0] <= series[-1][0]:
            raise TabularFormatError(f"{path}: line {line}: vehicle {vehicle!r}: time {values[0]:g} s does not "
                                     f"increase (the last was {series[-1][0]:g} s)")
        series.append(values)
    short = [v for v, s in samples.items() if len(s) < 2]
    if not samples or short:
        raise TabularFormatError(f"{path}: every vehicle needs two samples or more ({short or 'no vehicle'})")
    for vehicle, (mass, kind) in fixed.items():
        if not mass > 0:
            raise TabularFormatError(f"{path}: vehicle {vehicle!r}: mass must be > 0 kg, got {mass:g}")
        if kind is not None and kind not in VEHICLES:
            raise TabularFormatError(f"{path}: vehicle {vehicle!r}: unknown kind {kind!r} (registered: "
                                     f"{', '.join(VEHICLES)})")
    data = {v: np.asarray(s) for v, s in samples.items()}
    start, end = max(d[0, 0] for d in data.values()), min(d[-1, 0] for d in data.values())
    if not end > start:
        raise TabularFormatError(f"{path}: the vehicles' samples do not overlap in time")
    grid = start + np.arange(int(math.floor((end - start) * rate_hz)) + 1) / rate_hz
    idx = {name: i for i, name in enumerate(COLUMNS)}
    block = lambda d, *names: d[:, [idx[n] for n in names]]  # noqa: E731
    per = []
    for d in data.values():
        thrust = np.interp(grid, d[:, 0], d[:, idx["thrust"]])
        per.append(vehicle_arrays(
            d[:, 0], grid, pos=block(d, "x", "y", "z"), vel=block(d, "vx", "vy", "vz"),
            quat=block(d, "qw", "qx", "qy", "qz"), ref_pos=block(d, "ref_x", "ref_y", "ref_z"),
            ref_vel=block(d, "ref_vx", "ref_vy", "ref_vz"), thrust=thrust, mass=d[0, idx["mass"]]))
    kinds = [k for _, k in fixed.values()]
    meta: dict[str, Any] = {
        "source": {"format": CSV_LAYOUT, "files": [{"file": str(path), "format": CSV_LAYOUT,
                                                    "sha256": hashlib.sha256(raw).hexdigest()}]},
        "vehicles": list(data), "frames": list(data), "masses": [m for m, _ in fixed.values()],
        "config": {"rate_hz": rate_hz, "start_s": float(start)},
    }
    if all(k for k in kinds):
        meta["kinds"] = kinds
    return real_flight(grid - start, per, meta)


def write_csv_flight(path: str | os.PathLike, vehicles: Mapping[str, Mapping[str, Any]]) -> None:
    """Write a flight in the documented layout: vehicles maps a name to its columns (each `COLUMNS`
    name, plus an optional ``kind``), arrays (N,) or, for mass and kind, one value. Atomic."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["t[s]", "vehicle", *(f"{n}[{u}]" if u else n for n, u in COLUMNS.items() if n != "t"), "kind"])
    for name, columns in vehicles.items():
        n = len(np.asarray(columns["t"]))
        values = {k: np.broadcast_to(np.asarray(columns[k], dtype=np.float64), (n,)) for k in COLUMNS}
        for i in range(n):
            writer.writerow([repr(float(values["t"][i])), name,
                             *(repr(float(values[k][i])) for k in COLUMNS if k != "t"), columns.get("kind", "")])
    atomic_write_bytes(path, out.getvalue().encode())
