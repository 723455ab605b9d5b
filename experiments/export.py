"""Export flight logs to the formats other tools read: the tabular CSV/Parquet layout and MCAP.

    python -m experiments.export LOG [LOG ...] --format parquet|mcap|csv --out DIR [--force]

Each LOG is a flight log written by the simulator (`sim.logs.save_log`, ``.npz``) or a file
`downwash.real_logs.tabular.read_tabular_flight` reads (``.csv``, ``.parquet``, ``.pq``); it is
written to ``DIR/<LOG's stem>.<format>``. Every log is read and checked, and every output path
too (an existing file is refused unless ``--force``), before anything is written; each file is
written atomically (`downwash_core.io`).

What is exported of each vehicle (a simulated log's truth arrays are not: a lab logs estimates):
position ``pos_est`` (m, world frame, z up), velocity ``vel_est`` (m/s, world), attitude
``quat_est`` ((w, x, y, z), body to world), the setpoint ``ref_pos`` (m), ``ref_vel`` (m/s),
``ref_acc`` (m/s^2, MCAP only) and the collective thrust (N),

    thrust = m (u_cmd + g e3) . (R(quat_est) e3)

the commanded acceleration plus gravity, projected on the body z axis, times the vehicle's mass
``m`` (kg: the registered kind's `VehicleKind.mass`, from the log's ``kinds`` or the paper quad;
a real flight's ``masses``). It is the exact inverse of the ``u_cmd`` a real flight's log derives
from its thrust (`downwash.real_logs.convert.vehicle_arrays`), and, for a simulated flight, the
autopilot's collective thrust ``m |a| (b3_des . b3)`` (`controllers.autopilot.rotor_thrusts`)
measured on the logged attitude rather than the true one.

``csv``, ``parquet``: exactly the layout of `downwash.real_logs.tabular` (its writers), one row
per vehicle and tick, ``kind`` the vehicle's registered kind where the log names it (a simulated
log always: the paper quad unless its ``kinds`` say otherwise).

``mcap``: JSON-encoded messages, each channel with a ``jsonschema`` schema; log and publish
time = the tick's time stamp ``t`` in ns; ``timestamp`` = the same time as ``{sec, nsec}``;
one channel per vehicle and signal group:

| channel | schema | fields (units) |
|---|---|---|
| ``/<vehicle>/pose`` | ``foxglove.PoseInFrame`` | ``timestamp``, ``frame_id`` ("world"), ``pose.position.{x,y,z}`` (m), ``pose.orientation.{x,y,z,w}`` (body to world) |
| ``/<vehicle>/twist`` | ``downwash.LinearTwist`` | ``timestamp``, ``frame_id`` ("world"), ``linear.{x,y,z}`` (m/s, world frame) |
| ``/<vehicle>/setpoint`` | ``downwash.Setpoint`` | ``timestamp``, ``frame_id``, ``position``, ``velocity``, ``acceleration`` (m, m/s, m/s^2, each ``{x,y,z}``) |
| ``/<vehicle>/thrust`` | ``downwash.Thrust`` | ``timestamp``, ``thrust`` (N, collective, body z), ``mass`` (kg) |

The flight's metadata goes into one MCAP metadata record named ``downwash.flight``:
``meta`` (the log's metadata as JSON: its provenance), ``source_file``, ``source_sha256``
(of the file read), and ``layout`` (`MCAP_LAYOUT`).

A bad input is one error naming it, before anything is written: a missing file, a log of
another kind (not a flight log, or a suffix no reader takes: `DataError`/`LogError`), an unknown
``--format``, an existing output without ``--force`` (`ConfigError`).
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from experiments.common import OneLineParser, run_main, script

__all__ = ["FORMATS", "MCAP_LAYOUT", "LOG_SUFFIXES", "Export", "command_parser", "vehicle_signals", "plan_exports",
           "export_logs", "main", "cli"]

FORMATS = {"csv": ".csv", "parquet": ".parquet", "mcap": ".mcap"}  # --format -> the output's suffix
LOG_SUFFIXES = (".npz", ".csv", ".parquet", ".pq")  # what the command reads
MCAP_LAYOUT = "downwash-export-mcap-1"
MCAP_METADATA = "downwash.flight"
_XYZ = {"type": "object", "properties": {a: {"type": "number"} for a in "xyz"}}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
# channel suffix -> (schema name, JSON schema)
MCAP_SCHEMAS: dict[str, tuple[str, dict]] = {
    "pose": ("foxglove.PoseInFrame", {"type": "object", "properties": {
        "timestamp": _TIME, "frame_id": {"type": "string"},
        "pose": {"type": "object", "properties": {
            "position": _XYZ,
            "orientation": {"type": "object", "properties": {a: {"type": "number"} for a in "xyzw"}}}}}}),
    "twist": ("downwash.LinearTwist", {"type": "object", "description": "velocity, m/s, world frame",
                                       "properties": {"timestamp": _TIME, "frame_id": {"type": "string"},
                                                      "linear": _XYZ}}),
    "setpoint": ("downwash.Setpoint", {"type": "object", "description": "m, m/s, m/s^2, world frame",
                                       "properties": {"timestamp": _TIME, "frame_id": {"type": "string"},
                                                      "position": _XYZ, "velocity": _XYZ, "acceleration": _XYZ}}),
    "thrust": ("downwash.Thrust", {"type": "object", "description": "collective thrust (N) along body z, mass (kg)",
                                   "properties": {"timestamp": _TIME, "thrust": {"type": "number"},
                                                  "mass": {"type": "number"}}}),
}


@dataclass(frozen=True)
class Export:
    """One checked export: the log read from `source` (its bytes' sha256), written to `target`."""

    source: Path
    target: Path
    log: Any  # sim.logs.FlightLog
    sha256: str


def command_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m experiments.export", description=__doc__.split("\n\n")[0],
                           allow_abbrev=False)
    parser.add_argument("logs", metavar="LOG", nargs="+",
                        help=f"flight logs: the simulator's .npz or the tabular layout ({', '.join(LOG_SUFFIXES)})")
    parser.add_argument("--format", required=True, help=f"the output format: {', '.join(FORMATS)}")
    parser.add_argument("--out", required=True, metavar="DIR", help="the output folder (made when missing)")
    parser.add_argument("--force", action="store_true", help="overwrite outputs that exist")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an expected error (a bad option or file) instead of one line")
    return parser


def _read_log(path: Path) -> Any:
    """The flight log of `path`: a .npz flight log or a tabular file; DataError naming the file otherwise."""
    from downwash_core.errors import DataError, LogError

    if not path.is_file():
        raise DataError(f"{path}: no such log file")
    suffix = path.suffix.lower()
    if suffix not in LOG_SUFFIXES:
        raise LogError(f"{path}: a log of another kind (suffix {suffix!r}); allowed: {', '.join(LOG_SUFFIXES)}")
    if suffix == ".npz":
        from sim.logs import load_log

        return load_log(path)
    from downwash.real_logs.tabular import read_tabular_flight

    return read_tabular_flight(path)


def _masses(log: Any, where: str) -> tuple[list[float], list[str | None]]:
    """Each vehicle's mass (kg) and registered kind (None: unknown): a real flight's ``masses``, else
    the kinds' masses (the log's ``kinds``, else the paper quad)."""
    from downwash_core.errors import LogError
    from downwash_core.vehicles import DEFAULT_VEHICLE, VEHICLES

    V = log.n_vehicles
    kinds = log.meta.get("kinds") or ([None] * V if log.real else [DEFAULT_VEHICLE] * V)
    if len(kinds) != V or any(k is not None and k not in VEHICLES for k in kinds):
        raise LogError(f"{where}: metadata 'kinds' {kinds!r}: expected {V} registered kinds ({', '.join(VEHICLES)})")
    masses = log.meta.get("masses")
    if masses is None:
        if None in kinds:
            raise LogError(f"{where}: a real flight without 'masses' or 'kinds' in its metadata: its thrust is unknown")
        masses = [VEHICLES[k].mass for k in kinds]
    if len(masses) != V or not all(isinstance(m, (int, float)) and m > 0 for m in masses):
        raise LogError(f"{where}: metadata 'masses' {masses!r}: expected {V} masses > 0 kg")
    return [float(m) for m in masses], list(kinds)


def vehicle_signals(log: Any, where: str = "log") -> dict[str, dict[str, Any]]:
    """vehicle name -> its exported signals: t (T,) s, pos (T, 3) m, vel (T, 3) m/s, quat (T, 4) (w, x, y, z),
    ref_pos (T, 3) m, ref_vel (T, 3) m/s, ref_acc (T, 3) m/s^2, thrust (T,) N (module doc), mass kg,
    kind (a registered name or None). LogError naming `where` and the array for a non-finite value."""
    import numpy as np

    from downwash_core.errors import LogError
    from downwash_core.geometry import quat_to_mat
    from downwash_core.params import GRAVITY

    masses, kinds = _masses(log, where)
    names = log.meta.get("vehicles") or [f"vehicle{v}" for v in range(log.n_vehicles)]
    for name in ("t", "pos_est", "vel_est", "quat_est", "ref_pos", "ref_vel", "ref_acc", "u_cmd"):
        a = np.asarray(log[name], np.float64)
        if not np.all(np.isfinite(a)):
            raise LogError(f"{where}: array '{name}' holds non-finite values at rows "
                           f"{np.unique(np.argwhere(~np.isfinite(a))[:, 0])[:5].tolist()}")
    if len(log) < 2:
        raise LogError(f"{where}: {len(log)} rows; an export needs two or more")
    t = np.asarray(log["t"], np.float64)
    out = {}
    for v, name in enumerate(names):
        q = np.asarray(log["quat_est"][:, v], np.float64)
        b3 = quat_to_mat(q)[..., 2]  # (T, 3) body z axis, world frame
        acc = np.asarray(log["u_cmd"][:, v], np.float64) + np.array([0.0, 0.0, GRAVITY])
        out[str(name)] = {
            "t": t, "pos": np.asarray(log["pos_est"][:, v], np.float64), "vel": np.asarray(log["vel_est"][:, v], np.float64),
            "quat": q, "ref_pos": np.asarray(log["ref_pos"][:, v], np.float64),
            "ref_vel": np.asarray(log["ref_vel"][:, v], np.float64), "ref_acc": np.asarray(log["ref_acc"][:, v], np.float64),
            "thrust": masses[v] * np.sum(acc * b3, axis=1), "mass": masses[v], "kind": kinds[v],
        }  # fmt: skip
    return out


def _tabular_columns(signals: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The `write_csv_flight` argument of `vehicle_signals`."""
    out = {}
    for name, s in signals.items():
        cols: dict[str, Any] = {"t": s["t"], "thrust": s["thrust"], "mass": s["mass"]}
        for i, a in enumerate("xyz"):
            cols[a], cols[f"v{a}"] = s["pos"][:, i], s["vel"][:, i]
            cols[f"ref_{a}"], cols[f"ref_v{a}"] = s["ref_pos"][:, i], s["ref_vel"][:, i]
        for i, a in enumerate("wxyz"):
            cols[f"q{a}"] = s["quat"][:, i]
        if s["kind"]:
            cols["kind"] = s["kind"]
        out[name] = cols
    return out


def _stamp(t: float) -> tuple[int, dict[str, int]]:
    ns = int(round(t * 1e9))
    return ns, {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _xyz(a: Any) -> dict[str, float]:
    return {"x": float(a[0]), "y": float(a[1]), "z": float(a[2])}


def write_mcap(path: str | os.PathLike, export: Export) -> None:
    """Write `export`'s log as MCAP (module doc), atomically."""
    from mcap.writer import Writer

    from downwash_core.errors import LogError
    from downwash_core.io import atomic_write_bytes, to_json

    signals = vehicle_signals(export.log, str(export.source))
    t0 = float(next(iter(signals.values()))["t"][0])
    if t0 < 0:
        raise LogError(f"{export.source}: time stamps start at {t0:g} s; MCAP log times are >= 0 ns")
    buf = io.BytesIO()
    writer = Writer(buf)
    writer.start(profile="", library="downwash-testbed experiments.export")
    schema_ids = {key: writer.register_schema(name, "jsonschema", json.dumps(schema).encode())
                  for key, (name, schema) in MCAP_SCHEMAS.items()}
    for vehicle, s in signals.items():
        ch = {key: writer.register_channel(f"/{vehicle}/{key}", "json", schema_ids[key]) for key in MCAP_SCHEMAS}
        for i, t in enumerate(s["t"]):
            ns, stamp = _stamp(float(t))
            w, x, y, z = (float(c) for c in s["quat"][i])
            messages = {
                "pose": {"timestamp": stamp, "frame_id": "world", "pose": {
                    "position": _xyz(s["pos"][i]), "orientation": {"x": x, "y": y, "z": z, "w": w}}},
                "twist": {"timestamp": stamp, "frame_id": "world", "linear": _xyz(s["vel"][i])},
                "setpoint": {"timestamp": stamp, "frame_id": "world", "position": _xyz(s["ref_pos"][i]),
                             "velocity": _xyz(s["ref_vel"][i]), "acceleration": _xyz(s["ref_acc"][i])},
                "thrust": {"timestamp": stamp, "thrust": float(s["thrust"][i]), "mass": s["mass"]},
            }
            for key, msg in messages.items():
                writer.add_message(ch[key], log_time=ns, data=json.dumps(msg).encode(), publish_time=ns, sequence=i)
    writer.add_metadata(MCAP_METADATA, {"meta": to_json(export.log.meta), "source_file": str(export.source),
                                        "source_sha256": export.sha256, "layout": MCAP_LAYOUT})
    writer.finish()
    atomic_write_bytes(path, buf.getvalue())


def plan_exports(logs: Sequence[str | os.PathLike], fmt: str, out: str | os.PathLike,
                 force: bool = False) -> list[Export]:
    """Read and check every log and output path, writing nothing: ConfigError for an unknown format or an
    output that exists (without `force`) or that two logs share; DataError/LogError naming a bad log."""
    from downwash_core.errors import ConfigError

    if fmt not in FORMATS:
        raise ConfigError(f"--format: unknown format {fmt!r}; allowed: {', '.join(FORMATS)}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out: {out} is a file; expected a folder")
    plans: list[Export] = []
    for given in logs:
        source = Path(given)
        log = _read_log(source)
        vehicle_signals(log, str(source))  # a log that cannot be exported stops here
        target = out / (source.stem + FORMATS[fmt])
        if any(p.target == target for p in plans):
            raise ConfigError(f"{source}: its output {target} is also another log's (logs of one stem)")
        if target.exists() and not force:
            raise ConfigError(f"{target}: exists; --force overwrites it")
        if target.is_dir():
            raise ConfigError(f"{target}: is a folder")
        plans.append(Export(source, target, log, hashlib.sha256(source.read_bytes()).hexdigest()))
    return plans


def export_logs(logs: Sequence[str | os.PathLike], fmt: str, out: str | os.PathLike,
                force: bool = False) -> list[Path]:
    """Export each log to `out` in `fmt` (module doc); every input checked before anything is written.
    Returns the paths written."""
    plans = plan_exports(logs, fmt, out, force)
    Path(out).mkdir(parents=True, exist_ok=True)
    for p in plans:
        if fmt == "mcap":
            write_mcap(p.target, p)
        else:
            from downwash.real_logs.tabular import write_csv_flight, write_parquet_flight

            columns = _tabular_columns(vehicle_signals(p.log, str(p.source)))
            (write_csv_flight if fmt == "csv" else write_parquet_flight)(p.target, columns)
    return [p.target for p in plans]


def main(argv: Sequence[str] | None = None) -> list[Path]:
    """Parse the arguments and export; an expected error is one line (`run_main`)."""
    args = command_parser().parse_args(argv)  # --debug: run_main re-raises expected errors
    written = export_logs(args.logs, args.format, args.out, args.force)
    for path in written:
        print(f"wrote {path}")
    return written


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
