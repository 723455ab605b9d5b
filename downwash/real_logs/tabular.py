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

The same layout can be a Parquet file (`pyarrow`, the ``logs`` extra): the same column names,
numbers as integer or floating columns, ``vehicle`` and ``kind`` as strings (a null kind: none).
`read_parquet_flight` checks what `read_csv_flight` checks, naming the file, ``row i`` (from 0) and
the column; a file pyarrow cannot read (cut short, damaged) is a `TabularFormatError` naming the
file. `write_parquet_flight` writes it with a CRC-32 on every page, and the reader verifies them,
so a changed byte in a page's data is refused; `read_tabular_flight` reads either by the suffix.
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

__all__ = ["CSV_LAYOUT", "PARQUET_LAYOUT", "COLUMNS", "TABULAR_SUFFIXES", "TabularFormatError", "read_csv_flight",
           "write_csv_flight", "read_parquet_flight", "write_parquet_flight", "read_tabular_flight"]

CSV_LAYOUT = "downwash-real-flight-csv-1"
PARQUET_LAYOUT = "downwash-real-flight-parquet-1"  # the same columns in a Parquet file
TABULAR_SUFFIXES = {".csv": CSV_LAYOUT, ".parquet": PARQUET_LAYOUT, ".pq": PARQUET_LAYOUT}
INSTALL_HINT = 'pip install "downwash-testbed[logs]"'
# name -> unit ("" for none): the columns every file holds
COLUMNS = {
    "t": "s", **{a: "m" for a in ("x", "y", "z")}, **{a: "m/s" for a in ("vx", "vy", "vz")},
    **{q: "" for q in ("qw", "qx", "qy", "qz")}, **{f"ref_{a}": "m" for a in ("x", "y", "z")},
    **{f"ref_{a}": "m/s" for a in ("vx", "vy", "vz")}, "thrust": "N", "mass": "kg",
}
_HEADER = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[([^\]]*)\])?\s*$")


class TabularFormatError(LogError):
    """A CSV or Parquet flight that is not the documented layout: the message names the file, the line
    (CSV) or row (Parquet) and the column."""


def _columns(header: list[str], where: str, at: str = "line 1") -> dict[str, int]:
    """name -> index of the layout's columns (and `vehicle`, `kind`) in a header; unit mismatches refused
    (`at` names the header's place: a CSV's line 1, a Parquet file's schema)."""
    found: dict[str, tuple[int, str]] = {}
    for i, cell in enumerate(header):
        m = _HEADER.match(cell)
        if m:
            found.setdefault(m.group(1), (i, m.group(2) or ""))
    for name, unit in COLUMNS.items():
        if name not in found:
            raise TabularFormatError(f"{where}: {at}: no column {name}[{unit}]" if unit else
                                     f"{where}: {at}: no column {name}")
        if found[name][1] != unit:
            raise TabularFormatError(f"{where}: {at}: unit mismatch: column {header[found[name][0]]!r} is in "
                                     f"{found[name][1] or 'no unit'}; this layout takes {name}"
                                     + (f"[{unit}]" if unit else " without a unit"))
    if "vehicle" not in found:
        raise TabularFormatError(f"{where}: {at}: no column vehicle")
    return {name: found[name][0] for name in (*COLUMNS, "vehicle", *(["kind"] if "kind" in found else []))}


def read_csv_flight(path: str | os.PathLike, rate_hz: float = 100.0) -> FlightLog:
    """The real flight of a CSV file in the documented layout (module doc), on a grid at `rate_hz`."""
    _check_rate(rate_hz)
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
    data = {v: np.asarray(series) for v, series in samples.items()}
    return _flight(path, raw, CSV_LAYOUT, data, fixed, rate_hz)


def _check_rate(rate_hz: float) -> None:
    if not (isinstance(rate_hz, (int, float)) and 10.0 <= rate_hz <= 500.0):
        raise ConfigError(f"rate_hz: allowed 10-500 Hz, got {rate_hz!r}")


def _flight(path: Path, raw: bytes, layout: str, data: dict[str, np.ndarray],
            fixed: dict[str, tuple[float, str | None]], rate_hz: float) -> FlightLog:
    """The flight of each vehicle's samples (N, len(COLUMNS)) in COLUMNS' order, its (mass, kind)
    checked, on one grid at `rate_hz` from the latest first sample to the earliest last one."""
    short = [v for v, d in data.items() if len(d) < 2]
    if not data or short:
        raise TabularFormatError(f"{path}: every vehicle needs two samples or more ({short or 'no vehicle'})")
    for vehicle, (mass, kind) in fixed.items():
        if not mass > 0:
            raise TabularFormatError(f"{path}: vehicle {vehicle!r}: mass must be > 0 kg, got {mass:g}")
        if kind is not None and kind not in VEHICLES:
            raise TabularFormatError(f"{path}: vehicle {vehicle!r}: unknown kind {kind!r} (registered: "
                                     f"{', '.join(VEHICLES)})")
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
        "source": {"format": layout, "files": [{"file": str(path), "format": layout,
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


# ----------------------------------------------------------------------------- the same layout as Parquet


def _pyarrow() -> tuple[Any, Any]:
    """(pyarrow, pyarrow.parquet), imported here (the ``logs`` extra is optional)."""
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError as e:
        raise ConfigError(f"Parquet flights need pyarrow ({e}); install it: {INSTALL_HINT}") from None
    return pyarrow, pyarrow.parquet


def _parquet_table(path: Path) -> tuple[bytes, Any, list[str]]:
    """(the file's bytes, its table, its column names), its pages' CRC-32s verified; TabularFormatError
    naming the file."""
    pa, pq = _pyarrow()
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise TabularFormatError(f"{path}: cannot read it: {e.strerror or e}") from e
    try:  # pyarrow's errors on a damaged file: its own, and the OSError (IOError) of a bad read
        table = pq.read_table(pa.BufferReader(raw), page_checksum_verification=True)
        names = table.column_names  # decoded here: a damaged name is not UTF-8
    except (pa.ArrowException, OSError, ValueError) as e:
        raise TabularFormatError(f"{path}: not a readable Parquet file: {e}") from None
    return raw, table, names


def _parquet_column(pa: Any, table: Any, index: int, where: str) -> np.ndarray:
    """A numeric column as float64 (N,), a null as NaN; TabularFormatError for a column of another type."""
    column = table.column(index)
    if not (pa.types.is_integer(column.type) or pa.types.is_floating(column.type)):
        raise TabularFormatError(f"{where}: schema: column {table.column_names[index]!r} holds {column.type}; "
                                 "this layout takes numbers")
    values = column.cast(pa.float64()).to_numpy()
    if column.null_count:
        row = int(np.argmax(column.is_null().to_numpy(zero_copy_only=False)))
        raise TabularFormatError(f"{where}: row {row}: column {table.column_names[index]!r}: no value (null)")
    return values


def _parquet_text(pa: Any, table: Any, index: int, where: str) -> list[str | None]:
    column = table.column(index)
    if not (pa.types.is_string(column.type) or pa.types.is_large_string(column.type)
            or pa.types.is_dictionary(column.type) and pa.types.is_string(column.type.value_type)):
        raise TabularFormatError(f"{where}: schema: column {table.column_names[index]!r} holds {column.type}; "
                                 "this layout takes text")
    return column.to_pylist()


def read_parquet_flight(path: str | os.PathLike, rate_hz: float = 100.0) -> FlightLog:
    """The real flight of a Parquet file in the documented layout (module doc), on a grid at `rate_hz`."""
    _check_rate(rate_hz)
    path = Path(path)
    raw, table, names = _parquet_table(path)
    pa, _ = _pyarrow()
    cols = _columns(names, str(path), at="schema")
    values = np.stack([_parquet_column(pa, table, cols[name], str(path)) for name in COLUMNS], axis=1)
    bad = ~np.isfinite(values)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise TabularFormatError(f"{path}: row {row}: column {table.column_names[cols[list(COLUMNS)[col]]]!r}: not a "
                                 f"finite number: {float(values[row, col])!r}")
    vehicles = _parquet_text(pa, table, cols["vehicle"], str(path))
    kinds = _parquet_text(pa, table, cols["kind"], str(path)) if "kind" in cols else [None] * len(vehicles)
    if None in vehicles:
        raise TabularFormatError(f"{path}: row {vehicles.index(None)}: column 'vehicle': no value")
    names = np.asarray([v.strip() for v in vehicles], dtype=object)
    kinds = np.asarray([(k or "").strip() or None for k in kinds], dtype=object)
    mass_at, data, fixed = list(COLUMNS).index("mass"), {}, {}
    for vehicle in dict.fromkeys(names):
        rows = np.flatnonzero(names == vehicle)
        _check_series(path, vehicle, rows, values[rows], kinds[rows], mass_at)
        data[vehicle], fixed[vehicle] = values[rows], (float(values[rows[0], mass_at]), kinds[rows[0]])
    return _flight(path, raw, PARQUET_LAYOUT, data, fixed, rate_hz)


def _check_series(path: Path, vehicle: str, rows: np.ndarray, values: np.ndarray, kinds: np.ndarray,
                  mass_at: int) -> None:
    """TabularFormatError naming the row where one vehicle's time does not increase or its mass or kind changes."""
    steps = np.diff(values[:, 0])
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise TabularFormatError(f"{path}: row {rows[k]}: vehicle {vehicle!r}: time {values[k, 0]:g} s does not "
                                 f"increase (the last was {values[k - 1, 0]:g} s)")
    changed = np.flatnonzero((values[:, mass_at] != values[0, mass_at]) | (kinds != kinds[0]))
    if changed.size:
        k = int(changed[0])
        before, here = (float(values[0, mass_at]), kinds[0]), (float(values[k, mass_at]), kinds[k])
        raise TabularFormatError(f"{path}: row {rows[k]}: vehicle {vehicle!r} changes its mass or kind "
                                 f"({before} before, {here} here)")


def write_parquet_flight(path: str | os.PathLike, vehicles: Mapping[str, Mapping[str, Any]]) -> None:
    """Write a flight in the documented layout as Parquet (the arguments of `write_csv_flight`), a
    CRC-32 on every page. Atomic."""
    pa, pq = _pyarrow()
    names, columns = [], {n: [] for n in COLUMNS}
    kinds: list[str | None] = []
    for name, given in vehicles.items():
        n = len(np.asarray(given["t"]))
        for k in COLUMNS:
            columns[k].append(np.broadcast_to(np.asarray(given[k], dtype=np.float64), (n,)))
        names += [name] * n
        kinds += [given.get("kind") or None] * n
    arrays = {"t[s]": np.concatenate(columns["t"]), "vehicle": pa.array(names, pa.string())}
    arrays.update({f"{n}[{u}]" if u else n: np.concatenate(columns[n]) for n, u in COLUMNS.items() if n != "t"})
    arrays["kind"] = pa.array(kinds, pa.string())
    out = pa.BufferOutputStream()
    pq.write_table(pa.table(arrays), out, write_page_checksum=True)
    atomic_write_bytes(path, out.getvalue().to_pybytes())


def read_tabular_flight(path: str | os.PathLike, rate_hz: float = 100.0) -> FlightLog:
    """The real flight of a file in the documented layout, CSV or Parquet by its suffix (`TABULAR_SUFFIXES`)."""
    suffix = Path(path).suffix.lower()
    if suffix not in TABULAR_SUFFIXES:
        raise ConfigError(f"{path}: suffix {suffix!r}: allowed {', '.join(TABULAR_SUFFIXES)} (CSV or Parquet)")
    reader = read_csv_flight if TABULAR_SUFFIXES[suffix] == CSV_LAYOUT else read_parquet_flight
    return reader(path, rate_hz)
