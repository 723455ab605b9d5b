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
free air). Each per-neighbour model kind is trained on the training flights' pairs (each
vehicle with its nearest other vehicle), each model of sets on every vehicle's two others,
reading the vehicle kinds, and all are judged on the test flights, per type, beside no model
at all and beside the data set's own per-type errors where the clone holds its
``learning/log.txt``. Then two of the paper's questions on real data: per-neighbour models
trained on the two-vehicle flights only, judged where two vehicles fly above (by the nearest,
and summed over both); and learning curves (`--curve-fractions` of the training flights,
`--curve-seeds` draws each), with the equivariant model on a third of the flights paired seed
by seed against the best baseline on all of them. The registered wakes are fitted to the
training flights (`--fit-fields`, bootstrap intervals over flights, each fit written to
``<out>/fitted/<field>.json`` for ``--field fitted:PATH``) and judged on the test flights'
forces; the test flights of `--replay-tasks` are flown in the simulator against default and
fitted fields (`--replay-fields`, `--replay-gains`), their tracking beside the real one, and
the equivariant model trained here (kept in ``<out>/models``) flies them in the loop as
``equivariant-real``. Writes results.json (counts of files, flights, records and
rejections, the reading time, the label scatter in free air, per type the samples and each
model's RMSE, the pairs-to-triples result, the fits, the replays, the curves) and a table.

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
from experiments.options import PAIRWISE_KINDS, comma_items, comma_numbers, names_check

__all__ = ["RealFlightsArgs", "run", "decode", "main"]

DEFAULT_MODELS = "shallow,deep,equivariant,equivariant_general"
DEFAULT_SET_MODELS = "deepsets_equivariant,deepsets"
_PAIR_KINDS = tuple(k for k in PAIRWISE_KINDS if "memory" not in k)  # the models with memory need a history
_SET_KINDS = ("deepsets_equivariant", "deepsets")  # trained reading the vehicle kinds (downwash.set_models)
DEFAULT_FIT_FIELDS = "so2,momentum,jet,pybullet"
_GAINS = ("default", "crazyflie")
_FIT_FIELDS = ("so2", "momentum", "jet", "pybullet")  # downwash.field_fit.DEFAULT_FIT
PUBLISHED_UNITS = ("the data set's learning/log.txt: per type the mean squared error of the vertical force after "
                   "training, on that script's training samples, in gram-force squared (mse_gf2); z_rmse is its "
                   "root as the target's acceleration, m/s^2")


def _globs_check(text: str) -> str | None:
    globs = comma_items(text)
    if not globs:
        return "expected a comma list of globs of task folders relative to --data"
    if any(g.startswith("/") or ".." in Path(g).parts for g in globs):
        return "expected globs relative to --data (no absolute path, no ..)"
    return None


def _folder_check(text: str) -> str | None:
    return None if not text or Path(text).is_dir() else "expected an existing folder"


def _fractions_check(text: str) -> str | None:
    try:
        values = comma_numbers(text)
    except ValueError:
        return "expected a comma list of fractions in (0, 1]"
    ok = values and all(0 < v <= 1 for v in values) and values == sorted(set(values))
    return None if ok else "expected an increasing comma list of fractions in (0, 1], e.g. 0.04,0.11,0.33,1"


def _task_glob_check(text: str) -> str | None:
    ok = not text or ("/" not in text and ".." not in text and text.strip() == text)
    return None if ok else "expected a glob of task folder names (e.g. swap_*), no '/', or empty for none"


def _replay_check(text: str) -> str | None:
    names = comma_items(text)
    allowed = (*_FIT_FIELDS, *(f"fitted-{f}" for f in _FIT_FIELDS))
    bad = [n for n in names if n not in allowed]
    return f"unknown {bad}; allowed: a comma list of {', '.join(allowed)}" if bad or len(set(names)) != len(names) else None


@dataclass(frozen=True)
class RealFlightsArgs(CommonArgs):
    data: str = arg("", "the Neural-Swarm data set: a clone of its repository or its data/training folder",
                    check=_folder_check)
    train: str = arg("datacollection19*/*,datacollection20*/*,datacollection22*/*,datacollection23*/*",
                     "comma list of globs of the task folders to train on, relative to --data", check=_globs_check)
    test: str = arg("datacollection21*/*", "comma list of globs of the task folders to test on (default: the day "
                    "whose flights hold every interaction type)", check=_globs_check)
    models: str = arg(DEFAULT_MODELS, f"comma list of the per-neighbour models to train, of {', '.join(_PAIR_KINDS)}",
                      check=names_check(_PAIR_KINDS))
    set_models: str = arg(DEFAULT_SET_MODELS, "comma list of the models of sets to train reading the vehicle kinds, "
                          f"of {', '.join(_SET_KINDS)} (empty: none)", check=names_check(_SET_KINDS, empty=True))
    all_flights: bool = arg(False, "keep the flights the data set's summaries (learning/datacollection*_summary "
                            "in the clone) leave out")
    stride: int = arg(2, "keep every stride-th sample of the 100 Hz labels (2: the controller's 50 Hz)", ge=1, le=100)
    motor_lag: float = arg(0.0, "s, a first-order lag from each rotor's PWM to its thrust (0: none)", ge=0.0, le=1.0)
    curve_fractions: str = arg("0.04,0.11,0.33,1", "the shares of the training flights of the learning curves",
                               check=_fractions_check, quick="0.33,1")
    fit_fields: str = arg(DEFAULT_FIT_FIELDS, "comma list of the registered fields to fit to the training flights, "
                          f"of {', '.join(_FIT_FIELDS)} (empty: none)", check=names_check(_FIT_FIELDS, empty=True))
    boot: int = arg(100, "bootstrap refits per fitted field (whole flights resampled; 0: no intervals, else 10-2000)",
                    check=lambda v: None if v == 0 or 10 <= v <= 2000 else "expected 0 or 10-2000", quick=10)
    replay_tasks: str = arg("swap_*", "glob of the test flights' task folders whose setpoints are flown in the simulator "
                            "(sim and real side by side, and the real-trained model in the loop; empty: none)",
                            check=_task_glob_check)
    replay_fields: str = arg("so2,fitted-so2,fitted-momentum", "comma list of the fields the replays fly: a "
                             "registered field's default constants (so2) or its fit (fitted-so2)", check=_replay_check,
                             quick="fitted-so2")
    replay_gains: str = arg("default,crazyflie", "comma list of the controller gains the replays fly with: the "
                            "LQR's default weights, or weights whose gain is the Crazyflie firmware's default "
                            "position PD (as stiff as the real vehicles flew)", check=names_check(_GAINS))
    replay_seeds: int = arg(1, "simulated worlds per replayed flight", ge=1, le=20)
    curve_seeds: int = arg(3, "seeds per point of the learning curves (each a draw of flights and a training; "
                           "0: no curves)", ge=0, le=20, quick=2)


def _root(data: str) -> Path:
    if not data:
        raise ConfigError("--data: the folder of the data set is needed (a clone of github.com/aerorobotics/"
                          "neural-swarm, or its data/training folder)")
    root = Path(data)
    if not root.is_dir():
        raise ConfigError(f"--data: {root} is not a folder")
    return root / "data" / "training" if (root / "data" / "training").is_dir() else root


def _rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")


def _wake(types: np.ndarray) -> np.ndarray:
    """The samples with a vehicle above (not free air, not the ground alone)."""
    return ~(np.char.startswith(types, "none2") | np.char.startswith(types, "Ge2"))


def _pair_predictions(model, data) -> np.ndarray:
    """(N, 3) m/s^2: a per-neighbour model's prediction for every sample, 0 where it has no neighbour."""
    from downwash.train import predict

    out = np.zeros((len(data), 3))
    out[np.flatnonzero(data.mask[:, 0])] = predict(model, data)  # the real pairs, in sample order (K = 1)
    return out


def _summed_predictions(model, sets) -> np.ndarray:
    """(N, 3): a per-neighbour model summed over each sample's neighbours (the paper's naive law)."""
    from downwash.checkpoint import wrap_pairwise
    from downwash.train import predict

    return predict(wrap_pairwise(model, sets.neighbours).model, sets)


def _train_pairs(kinds, train, config, seed=None) -> dict:
    from downwash.train import train_model

    return {kind: train_model(kind, train, None, config, seed=seed) for kind in kinds}


def _per_type(test_y, types, predictions: dict[str, np.ndarray], published: dict) -> dict:
    out = {}
    for t in sorted(set(types)):
        sel = types == t
        out[t] = {"n_test": int(sel.sum()), "rmse": {"none": _rmse(test_y[sel])},
                  "z_rmse": {"none": _rmse(test_y[sel, 2])}}
        for name, pred in predictions.items():
            out[t]["rmse"][name] = _rmse((test_y - pred)[sel])
            out[t]["z_rmse"][name] = _rmse((test_y - pred)[sel, 2])
        if t in published:
            out[t]["published"] = published[t]
    return out


def _published(root: Path) -> tuple[dict, str | None]:
    from downwash.real_logs.neural_swarm import published_errors

    for path in (root.parent.parent / "learning" / "log.txt", root / "learning" / "log.txt"):
        if path.is_file():
            return published_errors(path), str(path)
    return {}, None


def _summaries(root: Path) -> dict[str, dict[str, set[str]]]:
    """The data set's summaries of its days, where the clone holds them: day -> task -> flights kept."""
    from downwash.real_logs.neural_swarm import summary_flights

    for folder in (root.parent.parent / "learning", root / "learning"):
        if folder.is_dir():
            return {p.name.removesuffix("_summary"): summary_flights(p)
                    for p in sorted(folder.glob("datacollection*_summary")) if p.is_file()}
    return {}


def _pairs_to_triples(kinds, flights, data, sets, config) -> dict:
    """Per-neighbour models trained on the two-vehicle training flights only, judged on the test samples
    with two vehicles above: by the nearest one, and summed over both; beside the same kinds trained
    on every training flight."""
    from downwash.real_logs.flights import labelled_samples

    pairs = [(ref, f) for ref, f in flights["train"] if f.n_vehicles == 2]
    if not pairs:
        return {"skipped": "no two-vehicle training flights"}
    train_pairs, _ = labelled_samples(pairs, data["stride"])
    test, types = data["test"]
    triple = np.array([len(t.split("2")[0]) == 2 for t in types])
    if not triple.any():
        return {"skipped": "no test samples with two vehicles above"}
    out = {"n_train": len(train_pairs), "n_test": int(triple.sum()), "none": _rmse(test.y[triple]), "models": {}}
    for kind, (model, _) in _train_pairs(kinds, train_pairs, config).items():
        out["models"][kind] = {"nearest": _rmse((test.y - _pair_predictions(model, test))[triple]),
                               "summed": _rmse((test.y - _summed_predictions(model, sets))[triple])}
    return out


def _n_flights(fraction: float, n: int) -> int:
    return min(n, max(2, round(fraction * n)))  # two at least: one is held out for early stopping


def _learning_curves(args, kinds, flights, test, types, config) -> dict:
    """RMSE on the test samples with a vehicle above, each model trained on a share of the training
    flights of two or three vehicles (a per-neighbour model learns from pairs only; drawn per seed, the
    same draw for every model), and the paper's claim paired by seed:
    the equivariant model on a third of the flights against the best baseline on all of them."""
    from downwash.real_logs.flights import labelled_samples
    from downwash.sweep_stats import paired_comparison

    wake = _wake(types)
    fractions = comma_numbers(args.curve_fractions)
    train = [(ref, f) for ref, f in flights["train"] if f.n_vehicles > 1]
    if len(train) < 2:
        return {"skipped": "fewer than two training flights of two or more vehicles"}
    points = {kind: {f: {} for f in fractions} for kind in kinds}
    for seed in range(args.curve_seeds):
        order = np.random.default_rng([args.seed, seed]).permutation(len(train))
        for f in fractions:
            chosen = [train[i] for i in order[:_n_flights(f, len(train))]]
            samples, _ = labelled_samples(chosen, args.stride)
            for kind, (model, _) in _train_pairs(kinds, samples, config, seed=args.seed + seed).items():
                points[kind][f][seed] = _rmse((test.y - _pair_predictions(model, test))[wake])
    curves = {kind: [{"fraction": f, "flights": _n_flights(f, len(train)), "rmse": list(v.values()),
                      "mean": float(np.mean(list(v.values())))} for f, v in per.items()] for kind, per in points.items()}
    out = {"n_test": int(wake.sum()), "none": _rmse(test.y[wake]), "curves": curves}
    small = min(fractions, key=lambda f: abs(f - 1 / 3))
    baselines = [k for k in ("shallow", "deep") if k in kinds]
    if "equivariant" in kinds and baselines and args.curve_seeds >= 2:
        out["claim"] = {"model": "equivariant", "fraction": small, "baselines": baselines, "baseline_fraction": 1.0,
                        **paired_comparison(points["equivariant"][small],
                                            [points[b][max(fractions)] for b in baselines], seed=args.seed)}
    return out


def _fitted_fields(args, flights) -> dict:
    """Each field of --fit-fields fitted to the training flights (bootstrap intervals over flights,
    written to <out>/fitted/<field>.json for ``--field fitted:PATH``), and the default and fitted
    constants' forces against the test flights' measured ones."""
    from downwash.field_fit import (bootstrap_fit, compare_forces, fit_field, pair_states, randomization_ranges,
                                    write_fitted)
    from sim.fields.registry import make_field

    names = comma_items(args.fit_fields)
    if not names:
        return {}
    train, test = pair_states(flights["train"], args.stride), pair_states(flights["test"], args.stride)
    out = {}
    for name in names:
        t0 = time.perf_counter()
        fit = bootstrap_fit(name, train, n_boot=args.boot, seed=args.seed) if args.boot else fit_field(name, train)
        path = write_fitted(Path(args.out) / "fitted" / f"{name}.json", fit)
        out[name] = {"fit": fit.describe(), "file": str(path), "seconds": time.perf_counter() - t0,
                     "ranges": randomization_ranges(fit, f"fitted:{path}") if args.boot else None,
                     "test": {"default": compare_forces(make_field(name), test), "fitted": compare_forces(fit, test)}}
    return out


def _replays(args, flights, fitted: dict, model_path: Path | None) -> dict:
    """The test flights of --replay-tasks flown in the simulator against each field of --replay-fields:
    their tracking beside the real one, and (with an equivariant model trained here) that model in
    the loop beside no model and the field's oracle."""
    import fnmatch

    from downwash.real_logs.replay import compare_tracking, crazyflie_stiff_lqr, fly_real_model
    from sim.fields.registry import make_field

    chosen = [(ref, f) for ref, f in flights["test"] if fnmatch.fnmatch(ref.folder.name, args.replay_tasks)]
    names = comma_items(args.replay_fields)
    if not args.replay_tasks or not chosen or not names:
        return {"skipped": "no test flight matches --replay-tasks" if names else "no --replay-fields"}
    seeds = [args.seed + k for k in range(args.replay_seeds)]
    out: dict = {"flights": len(chosen), "tasks": args.replay_tasks, "tracking": {}, "in_loop": {}}
    for gains in comma_items(args.replay_gains):
        controller = {"controller": crazyflie_stiff_lqr()} if gains == "crazyflie" else {}
        for name in names:
            base = name.removeprefix("fitted-")
            field = f"fitted:{fitted[base]['file']}" if name != base else make_field(base)
            key = f"{name}|{gains}"
            t0 = time.perf_counter()
            out["tracking"][key] = {**compare_tracking(chosen, field, seeds=seeds, **controller),
                                    "seconds": time.perf_counter() - t0}
            if model_path is not None:
                t0 = time.perf_counter()
                out["in_loop"][key] = {**fly_real_model(chosen, field, model_path, seeds=seeds, **controller),
                                       "seconds": time.perf_counter() - t0}
    return out


def run(args: RealFlightsArgs) -> dict:
    from downwash.real_logs.flights import find_flights, labelled_samples, read_flights
    from downwash.staged import train_config
    from downwash.train import predict, save_trained, train_model
    from sim.neighbours import NeighbourSet

    t0 = time.perf_counter()
    root = _root(args.data)
    unfitted = [n for n in comma_items(args.replay_fields) if n.startswith("fitted-") and n[7:] not in comma_items(args.fit_fields)]
    if args.replay_tasks and unfitted:
        raise ConfigError(f"--replay-fields: {unfitted[0]} needs {unfitted[0][7:]} in --fit-fields")
    refs = {role: find_flights(root, comma_items(text)) for role, text in (("train", args.train), ("test", args.test))}
    both = sorted({r.name for r in refs["train"]} & {r.name for r in refs["test"]})
    if both:
        raise ConfigError(f"--train and --test share {len(both)} flights (e.g. {both[0]}): hold out whole folders")
    lag = args.motor_lag or None
    listed = {} if args.all_flights else _summaries(root)
    flights, rejected = {}, []
    for role, chosen in refs.items():
        flights[role], bad = read_flights(chosen, motor_time_constant=lag, listed=listed)
        rejected += [{**b, "role": role} for b in bad]
    read_seconds = time.perf_counter() - t0
    files = sum(len(r.files) for chosen in refs.values() for r in chosen)
    records = sum(len(f["t"]) * f.n_vehicles for role in flights for _, f in flights[role])
    data = {role: labelled_samples(flights[role], args.stride) for role in flights}
    sets = {role: labelled_samples(flights[role], args.stride, NeighbourSet(max_neighbours=2))[0]
            for role in flights}  # a flight holds at most three vehicles
    data["stride"] = args.stride

    train, types_train = data["train"]
    test, types_test = data["test"]
    free = train.y[np.char.startswith(types_train, "none2")]
    kinds, set_kinds = comma_items(args.models), comma_items(args.set_models)
    config = train_config(args.seed, args.quick)
    predictions, models, model_path = {}, {}, None
    for kind, (model, history) in _train_pairs(kinds, train, config).items():
        predictions[kind] = _pair_predictions(model, test)
        if kind == "equivariant":  # flown in the loop by the replays, and kept for the user
            model_path = Path(args.out) / "models" / "equivariant.pt"
            save_trained(model_path, model, history, train)
        models[kind] = {"epochs": history["epochs"], "seconds": history["seconds"], "n_train": history["n_train"]}
    for kind in set_kinds:
        model, history = train_model(kind, sets["train"], None, config, kinds=True)
        predictions[f"{kind}_kinds"] = predict(model, sets["test"])
        models[f"{kind}_kinds"] = {"epochs": history["epochs"], "seconds": history["seconds"],
                                   "n_train": history["n_train"]}
    for name, pred in predictions.items():
        models[name]["rmse"] = _rmse(test.y - pred)
        models[name]["rmse_wake"] = _rmse((test.y - pred)[_wake(types_test)])
    published, published_file = _published(root)
    per_type = _per_type(test.y, types_test, predictions, published)
    for t, row in per_type.items():
        row["n_train"] = int(np.sum(types_train == t))
    fitted = _fitted_fields(args, flights)
    results = {
        "data": str(root), "files": files, "records": records, "summaries": sorted(listed),
        "flights": {role: len(flights[role]) for role in ("train", "test")}, "rejected": rejected,
        "read_seconds": read_seconds,
        "samples": {"train": len(train), "test": len(test), "stride": args.stride},
        "free_air_label": {"n": int(len(free)), "mean": free.mean(axis=0).tolist() if len(free) else None,
                           "scatter": free.std(axis=0).tolist() if len(free) else None},
        "no_model_rmse": _rmse(test.y), "no_model_rmse_wake": _rmse(test.y[_wake(types_test)]),
        "models": models, "per_type": per_type,
        "published": {"file": published_file, "units": PUBLISHED_UNITS} if published else None,
        "pairs_to_triples": _pairs_to_triples(kinds, flights, data, sets["test"], config),
        "fitted_fields": fitted, "replays": _replays(args, flights, fitted, model_path),
        "learning_curves": (_learning_curves(args, kinds, flights, test, types_test, config)
                            if args.curve_seeds else None),
    }  # fmt: skip
    results["wall_seconds"] = time.perf_counter() - t0
    path = write_results(args.out, results, args, {"source": "Neural-Swarm data set (aerorobotics/neural-swarm)"})
    _print(results, list(predictions), path)
    return results


def _print(results: dict, names: list[str], path: Path) -> None:
    print(f"{results['files']} files, {sum(results['flights'].values())} flights read ({len(results['rejected'])} "
          f"rejected), {results['records']} vehicle records in {results['read_seconds']:.1f} s")
    rows = [[t, v["n_train"], v["n_test"], v["rmse"]["none"], *(v["rmse"][k] for k in names)]
            for t, v in results["per_type"].items()]
    print("test RMSE per interaction type, m/s^2 (3 axes):")
    print(format_table(rows, ["type", "n train", "n test", "no model", *names]))
    print(f"wrote {path}")


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
