"""Validation RMSE against minutes of training data (the paper's figure 3 and table).

    python -m experiments.sample_efficiency [--collection-dir DIR] [--trials N] [--workers N] [--quick]

For each training length (each stage shortened proportionally, whole flights or
flight prefixes) and each of several trials (different subsets and seeds), the
three models are trained and evaluated on the whole validation set of the staged
collection. The label-noise floor (labels against the true mean field) is the line
no model can go below. Runs the staged collection first if its data is missing.

The trials of one minute point train as one ensemble per model kind
(`downwash.ensemble.train_ensemble`): each trial's model is bit-identical to its
own `train_model` with the same data subset and seed, so the numbers are those of
one training after another, only sooner. The ensembles (model kinds x minute points)
are spread over ``--workers`` processes (one intra-op thread each).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import ConfigError
from downwash.datasets import Dataset, concatenate, find_logs, load_dataset, shorten_per_stage
from downwash.ensemble import train_ensemble
from downwash.labels import label_noise_floor
from downwash.models import MODEL_KINDS
from downwash.staged import ensure_collection, train_config
from downwash.train import rmse
from experiments.common import PipelineArgs, ProgressBar, arg, format_table, parse_args, resolve_pipeline, setup_logging, write_results

__all__ = ["EfficiencyArgs", "run", "main"]

MINUTES = (1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0)  # plus the full set


@dataclass(frozen=True)
class EfficiencyArgs(PipelineArgs):
    trials: int = arg(10, "trials per point (different data subsets and seeds)")
    minutes: str = arg(",".join(str(m) for m in MINUTES), "comma list of training minutes; the full set is always added")
    workers: int = arg(0, "processes training ensembles side by side (0: one per CPU core, at most 4; 1 with --quick)")


def trial_data(train_all: Dataset, minutes: list[float], i: int, trials: int, seed: int) -> list[Dataset]:
    """The training subsets of minute point i, one per trial (the same draws for every model kind)."""
    full = minutes[-1]
    return [train_all if minutes[i] >= full else
            shorten_per_stage(train_all, minutes[i], np.random.default_rng([seed, trial, i])) for trial in range(trials)]


_WORKER: dict = {}


def _init_worker(train_all: Dataset, val: Dataset) -> None:
    import torch

    torch.set_num_threads(1)  # one core per worker (training sets one thread anyway; this is for evaluation)
    _WORKER.update(train_all=train_all, val=val)


def _train_point(kind: str, i: int, minutes: list[float], trials: int, seed: int, quick: bool,
                 train_all: Dataset | None = None, val: Dataset | None = None) -> tuple[str, int, list[float]]:
    """Validation RMSE of every trial of minute point i for one model kind: one ensemble."""
    train_all = _WORKER["train_all"] if train_all is None else train_all
    val = _WORKER["val"] if val is None else val
    data = trial_data(train_all, minutes, i, trials, seed)
    configs = [train_config(seed + trial, quick) for trial in range(trials)]
    models = train_ensemble(kind, data, configs)
    return kind, i, [rmse(model, val)[0] for model, _ in models]


def run(args: EfficiencyArgs) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        wanted = sorted({float(m) for m in args.minutes.split(",") if m.strip()})
    except ValueError as e:
        raise ConfigError(f"--minutes: expected a comma list of numbers, got {args.minutes!r}") from e
    if any(m <= 0 for m in wanted):
        raise ConfigError(f"--minutes: every value must be > 0, got {wanted}")
    if args.trials < 1:
        raise ConfigError(f"--trials: expected >= 1, got {args.trials}")
    if args.workers < 0:
        raise ConfigError(f"--workers: expected >= 0 (0: one per core), got {args.workers}")
    p = resolve_pipeline(args)
    collection = ensure_collection(p.collection_dir, p.models_dir, p.config, p.field, ProgressBar)
    t_start = time.perf_counter()
    train_dirs = sorted(collection.glob("stage*/train"))
    val_dirs = sorted(collection.glob("stage*/val"))
    if not train_dirs or not val_dirs:
        raise ConfigError(f"{collection}: expected stage*/train and stage*/val folders of flight logs")
    train_all = concatenate([load_dataset(d) for d in train_dirs])
    val = concatenate([load_dataset(d) for d in val_dirs])
    floor = label_noise_floor([p for d in val_dirs for p in find_logs(d)])
    full = train_all.n_minutes
    minutes = [m for m in wanted if m < full] + [full]
    trials = min(args.trials, 2) if args.quick else args.trials

    rmse_runs = {m: np.zeros((len(minutes), trials)) for m in MODEL_KINDS}
    bar = ProgressBar("sample efficiency", "models")
    # one ensemble per (kind, minute point); the deep model's (the slowest) and the longest first
    tasks = sorted(((kind, i) for kind in MODEL_KINDS for i in range(len(minutes))),
                   key=lambda t: (t[0] != "deep", -t[1]))
    workers = min(args.workers or (1 if args.quick else min(os.cpu_count() or 1, 4)), len(tasks))
    total, done = len(minutes) * trials * len(MODEL_KINDS), 0
    if workers <= 1:
        points = (_train_point(kind, i, minutes, trials, args.seed, args.quick, train_all, val) for kind, i in tasks)
        for kind, i, values in points:
            rmse_runs[kind][i] = values
            done += trials
            bar(done, total)
    else:
        # spawn: a fresh interpreter per worker (no forked torch/OpenMP state); the data goes once per worker
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_init_worker, initargs=(train_all, val)) as pool:
            futures = [pool.submit(_train_point, kind, i, minutes, trials, args.seed, args.quick) for kind, i in tasks]
            for future in as_completed(futures):
                kind, i, values = future.result()
                rmse_runs[kind][i] = values
                done += trials
                bar(done, total)

    results = {
        "minutes": minutes, "trials": trials, "noise_floor": floor["rmse_mean"],
        "noise_floor_applied": floor["rmse"], "validation_minutes": val.n_minutes,
        "models": {k: {"rmse_mean": v.mean(axis=1).tolist(), "rmse_std": v.std(axis=1).tolist(),
                       "rmse_runs": v.tolist()} for k, v in rmse_runs.items()},
        "wall_seconds": time.perf_counter() - t_start,
        "workers": workers,
    }
    out = Path(args.out)
    path = write_results(out, results, args, p.provenance())

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    colors = {"shallow": "tab:orange", "deep": "tab:blue", "equivariant": "tab:green", "equivariant_general": "tab:purple"}
    for kind, r in results["models"].items():
        mean, std = np.array(r["rmse_mean"]), np.array(r["rmse_std"])
        ax.plot(minutes, mean, "o-", color=colors.get(kind), label=kind)
        ax.fill_between(minutes, mean - std, mean + std, color=colors.get(kind), alpha=0.2)
    ax.axhline(floor["rmse_mean"], color="k", ls="--", lw=1, label="label noise floor")
    ax.set_xlabel("training flight time (min)"), ax.set_ylabel("validation RMSE (m/s^2)")
    ax.set_title(f"sample efficiency ({trials} trials per point)"), ax.legend()
    fig.tight_layout()
    fig.savefig(out / "sample_efficiency.png", dpi=110)
    plt.close(fig)

    rows = []
    for kind, r in results["models"].items():
        rows.append([kind] + [f"{m:.3f} +/- {s:.3f}" for m, s in zip(r["rmse_mean"], r["rmse_std"])])
    print(format_table(rows, ["model"] + [f"{m:g} min" for m in minutes]))
    print(f"label noise floor: {floor['rmse_mean']:.4f} m/s^2")
    print(f"\nwrote {path} and sample_efficiency.png in {out}/")
    return results


def main(argv=None) -> dict:
    setup_logging()
    return run(parse_args(EfficiencyArgs, "sample_efficiency", argv, __doc__))


if __name__ == "__main__":
    main()
