"""Validation RMSE against minutes of training data (the paper's figure 3 and table).

    python -m experiments.sample_efficiency [--collection-dir DIR] [--quick]

For each training length (each stage shortened proportionally, whole flights or
flight prefixes) and each of several trials (different subsets and seeds), the
three models are trained and evaluated on the whole validation set of the staged
collection. The label-noise floor (labels against the true mean field) is the line
no model can go below. Runs the staged collection first if its data is missing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import ConfigError
from downwash.datasets import concatenate, find_logs, load_dataset, shorten_per_stage
from downwash.labels import label_noise_floor
from downwash.models import MODEL_KINDS
from downwash.staged import ensure_collection, train_config
from downwash.train import rmse, train_model
from experiments.common import PipelineArgs, ProgressBar, arg, format_table, parse_args, resolve_pipeline, setup_logging, write_results

__all__ = ["EfficiencyArgs", "run", "main"]

MINUTES = (1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0)  # plus the full set


@dataclass(frozen=True)
class EfficiencyArgs(PipelineArgs):
    trials: int = arg(5, "trials per point (different data subsets and seeds)")
    minutes: str = arg(",".join(str(m) for m in MINUTES), "comma list of training minutes; the full set is always added")


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
    bar = ProgressBar("sample efficiency", 30)
    total, done = len(minutes) * trials * len(MODEL_KINDS), 0
    for i, minute in enumerate(minutes):
        for trial in range(trials):
            rng = np.random.default_rng([args.seed, trial, i])
            data = train_all if minute >= full else shorten_per_stage(train_all, minute, rng)
            for kind in MODEL_KINDS:
                model, _ = train_model(kind, data, None, train_config(args.seed + trial, args.quick))
                rmse_runs[kind][i, trial] = rmse(model, val)[0]
                done += 1
                bar(done, total)

    results = {
        "minutes": minutes, "trials": trials, "noise_floor": floor["rmse_mean"],
        "noise_floor_applied": floor["rmse"], "validation_minutes": val.n_minutes,
        "models": {k: {"rmse_mean": v.mean(axis=1).tolist(), "rmse_std": v.std(axis=1).tolist(),
                       "rmse_runs": v.tolist()} for k, v in rmse_runs.items()},
        "wall_seconds": time.perf_counter() - t_start,
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
