"""Real flights: the paper's models trained and judged on a lab's onboard logs (the Neural-Swarm data set).

    python -m experiments.real_flights --data PATH [--train GLOBS] [--test GLOBS] [--models ...]
    python -m experiments.real_flights decode FILE --csv OUT

PATH is a clone of the Neural-Swarm repository (github.com/aerorobotics/neural-swarm; it
carries no licence, so the testbed holds none of its files: point at your own clone) or its
``data/training`` folder. `--train` and `--test` each take a comma list of globs of task
folders relative to that folder, so a day, a task or a vehicle kind can be held out (the
default tests on June 16 2020, the day whose flights hold every interaction type of two and
three vehicles, and trains on the four other days).

Every flight is read exactly (`downwash.real_logs`: a file that is not exactly its format is
rejected, named, with the byte offset), its vehicles aligned at their first ticks (a swap
whose setpoints stay offset more than 0.05 s is rejected), labelled as the simulator's flights
are (``f = a - u``, ``u`` from each rotor's PWM and the battery voltage) and typed by who
flies above (``S2L``: a small vehicle above a large one; ``Ge2S``: near the ground; ``none2S``:
free air). Each model kind is trained on the training flights' pairs (each vehicle with its
nearest other vehicle) and judged on the test flights, per type, beside no model at all.
Writes results.json (counts of files, flights, records and rejections, the reading time, the
label scatter in free air, per type the samples and each model's RMSE) and a table.

``decode FILE --csv OUT`` writes one onboard log's records with the log's own field names
and raw values, for checking a reader against another decoder (the synchronous format, or
the current event-based one: one file per event, ``OUT``'s stem and the event's name).
"""

from __future__ import annotations

import csv
import io
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from downwash_core.errors import ConfigError
from experiments.common import (CommonArgs, OneLineParser, arg, check_writable, format_table, out_lock, parse_args,
                                run_main, setup_logging, write_results, script)
from experiments.options import PAIRWISE_KINDS, names_check

__all__ = ["RealFlightsArgs", "run", "decode", "main"]

DEFAULT_MODELS = "shallow,deep,equivariant,equivariant_general"
_PAIR_KINDS = tuple(k for k in PAIRWISE_KINDS if "memory" not in k)  # the models with memory need a history


def _globs_check(text: str) -> str | None:
    globs = [g.strip() for g in text.split(",") if g.strip()]
    if not globs:
        return "expected a comma list of globs of task folders relative to --data"
    if any(g.startswith("/") or ".." in Path(g).parts for g in globs):
        return "expected globs relative to --data (no absolute path, no ..)"
    return None


def _folder_check(text: str) -> str | None:
    return None if not text or Path(text).is_dir() else "expected an existing folder"


@dataclass(frozen=True)
class RealFlightsArgs(CommonArgs):
    data: str = arg("", "the Neural-Swarm data set: a clone of its repository or its data/training folder",
                    check=_folder_check)
    train: str = arg("datacollection19*/*,datacollection20*/*,datacollection22*/*,datacollection23*/*",
                     "comma list of globs of the task folders to train on, relative to --data", check=_globs_check)
    test: str = arg("datacollection21*/*", "comma list of globs of the task folders to test on (default: the day "
                    "whose flights hold every interaction type)", check=_globs_check)
    models: str = arg(DEFAULT_MODELS, f"comma list of the models to train, of {', '.join(_PAIR_KINDS)}",
                      check=names_check(_PAIR_KINDS))
    stride: int = arg(2, "keep every stride-th sample of the 100 Hz labels (2: the controller's 50 Hz)", ge=1, le=100)
    motor_lag: float = arg(0.0, "s, a first-order lag from each rotor's PWM to its thrust (0: none)", ge=0.0, le=1.0)


def _root(data: str) -> Path:
    if not data:
        raise ConfigError("--data: the folder of the data set is needed (a clone of github.com/aerorobotics/"
                          "neural-swarm, or its data/training folder)")
    root = Path(data)
    if not root.is_dir():
        raise ConfigError(f"--data: {root} is not a folder")
    return root / "data" / "training" if (root / "data" / "training").is_dir() else root


def _split(text: str) -> list[str]:
    return [g.strip() for g in text.split(",") if g.strip()]


def _predictions(model, data) -> np.ndarray:
    """(N, 3) m/s^2: a per-neighbour model's prediction for every sample, 0 where it has no neighbour."""
    from downwash.train import predict

    out = np.zeros((len(data), 3))
    out[np.flatnonzero(data.mask[:, 0])] = predict(model, data)  # the real pairs, in sample order (K = 1)
    return out


def _rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")


def run(args: RealFlightsArgs) -> dict:
    from downwash.real_logs.flights import find_flights, labelled_samples, read_flights
    from downwash.staged import train_config
    from downwash.train import train_model

    t0 = time.perf_counter()
    root = _root(args.data)
    refs = {role: find_flights(root, _split(text)) for role, text in (("train", args.train), ("test", args.test))}
    both = sorted({r.name for r in refs["train"]} & {r.name for r in refs["test"]})
    if both:
        raise ConfigError(f"--train and --test share {len(both)} flights (e.g. {both[0]}): hold out whole folders")
    lag = args.motor_lag or None
    flights, rejected = {}, []
    for role, chosen in refs.items():
        flights[role], bad = read_flights(chosen, motor_time_constant=lag)
        rejected += [{**b, "role": role} for b in bad]
    read_seconds = time.perf_counter() - t0
    files = sum(len(r.files) for chosen in refs.values() for r in chosen)
    records = sum(len(f["t"]) * f.n_vehicles for role in flights for _, f in flights[role])
    data = {role: labelled_samples(flights[role], args.stride) for role in flights}

    train, types_train = data["train"]
    test, types_test = data["test"]
    free = train.y[np.char.startswith(types_train, "none2")]
    kinds = _split(args.models)
    config = train_config(args.seed, args.quick)
    types = sorted(set(types_test))
    per_type = {t: {"n_train": int(np.sum(types_train == t)), "n_test": int(np.sum(types_test == t)),
                    "rmse": {"none": _rmse(test.y[types_test == t])}} for t in types}
    models = {}
    for kind in kinds:
        model, history = train_model(kind, train, None, config)
        pred = _predictions(model, test)
        models[kind] = {"rmse": _rmse(test.y - pred), "epochs": history["epochs"], "seconds": history["seconds"],
                        "n_train_pairs": history["n_train"]}
        for t in types:
            per_type[t]["rmse"][kind] = _rmse((test.y - pred)[types_test == t])
    results = {
        "data": str(root), "files": files, "records": records,
        "flights": {role: len(flights[role]) for role in flights}, "rejected": rejected,
        "read_seconds": read_seconds,
        "samples": {"train": len(train), "test": len(test), "stride": args.stride},
        "free_air_label": {"n": int(len(free)), "mean": free.mean(axis=0).tolist() if len(free) else None,
                           "scatter": free.std(axis=0).tolist() if len(free) else None},
        "no_model_rmse": _rmse(test.y), "models": models, "per_type": per_type,
        "wall_seconds": time.perf_counter() - t0,
    }  # fmt: skip
    path = write_results(args.out, results, args, {"source": "Neural-Swarm data set (aerorobotics/neural-swarm)"})
    header = ["type", "n train", "n test", "no model", *kinds]
    rows = [[t, v["n_train"], v["n_test"], v["rmse"]["none"], *(v["rmse"][k] for k in kinds)]
            for t, v in per_type.items()]
    print(f"{files} files, {sum(results['flights'].values())} flights read ({len(rejected)} rejected), "
          f"{records} vehicle records in {read_seconds:.1f} s")
    print("test RMSE per interaction type, m/s^2 (3 axes):")
    print(format_table(rows, header))
    print(f"wrote {path}")
    return results


def _write_csv(path: Path, log) -> None:
    from downwash_core.io import atomic_write_bytes

    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(log.fields)
    writer.writerows(zip(*(values.tolist() for values in log.fields.values())))
    atomic_write_bytes(path, text.getvalue().encode())


def decode(file: str, out_csv: str) -> list[Path]:
    """Write the records of `file`, a uSD deck log, as CSV with the log's field names and raw values:
    to `out_csv` for the synchronous format; for the event-based one, one file per event,
    ``<out_csv stem>.<event>.csv``. Returns the files written."""
    from downwash.real_logs.crazyflie_usd import read_usd_events, read_usd_sync

    out = check_writable("--csv", out_csv, "file")
    try:
        with open(file, "rb") as f:
            events = f.read(1) == b"\xbc"  # the event-based format's magic; the synchronous one starts with a count
    except OSError:
        events = False  # the reader names what is wrong
    logs = read_usd_events(file) if events else {"": read_usd_sync(file)}
    written = []
    for event, log in logs.items():
        path = out.with_name(f"{out.stem}.{event}{out.suffix}") if event else out
        _write_csv(path, log)
        written.append(path)
        print(f"{file}{' event ' + event if event else ''}: {len(log)} records of {len(log.fields)} fields -> {path}")
    return written


def main(argv: Sequence[str] | None = None) -> dict | list[Path]:
    argv = list(sys.argv[1:] if argv is None else argv)
    setup_logging()
    if argv[:1] == ["decode"]:
        parser = OneLineParser(prog="python -m experiments.real_flights decode",
                               description="write one onboard log's records as CSV, with its field names and raw values")
        parser.add_argument("file", help="the onboard log (Crazyflie uSD deck: synchronous, or event-based version 2)")
        parser.add_argument("--csv", required=True, help="the CSV file to write")
        ns = parser.parse_args(argv[1:])
        return decode(ns.file, ns.csv)
    args = parse_args(RealFlightsArgs, "real_flights", argv, __doc__)
    _root(args.data)  # before the lock and any import of the stack
    with out_lock(args, "real_flights"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
