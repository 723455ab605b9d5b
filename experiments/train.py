"""Train one downwash model on a folder of flight logs.

    python -m experiments.train --model equivariant --logs DIR --val-logs DIR [--minutes M]

Labels are f = a - u from each log (downwash.labels); early stopping holds out a
share of the training FLIGHTS; the validation logs are only evaluated. Writes the
checkpoint (weights + JSON metadata) and results.json with model, n_params,
train_rmse, val_rmse, val_rmse_axis and noise_floor (label error against the true
mean field on the validation logs: the RMSE a perfect model would reach).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from downwash_core.errors import ConfigError, DataError
from experiments.common import (PAIRWISE_KINDS, CommonArgs, arg, format_table, load_field, one_of, out_lock,
                                parse_args, run_main, setup_logging, write_results, script)
from experiments.components import (training_config)

__all__ = ["TrainArgs", "run", "main"]


@dataclass(frozen=True)
class TrainArgs(CommonArgs):
    config_tables: ClassVar[tuple[str, ...]] = ("training",)  # the training's settings

    model: str = arg("equivariant", "model kind: " + ", ".join(PAIRWISE_KINDS), check=one_of(PAIRWISE_KINDS))
    logs: str = arg("", "folder of training flight logs (.npz), searched recursively")
    val_logs: str = arg("", "folder of validation flight logs (.npz), searched recursively")
    minutes: float = arg(0.0, "shorten the training data to this many minutes, each stage proportionally (0: all)",
                         ge=0.0)
    feature_set: str = arg("", "equivariant model features: 5 (paper, level leader) or 6 (adds |v_a|); default per model")
    checkpoint: str = arg("", "checkpoint path (default OUT/<model>.pt)", output="file")


def run(args: TrainArgs) -> dict:
    from downwash.checkpoint import save_checkpoint
    from downwash.datasets import find_logs, load_dataset, shorten_per_stage
    from downwash.labels import label_noise_floor
    from downwash.models import PAIRWISE_KINDS, count_parameters
    from downwash.train import rmse, train_model
    from downwash_core.provenance import describe, differences

    if args.model not in PAIRWISE_KINDS:
        raise ConfigError(f"--model: unknown {args.model!r}; allowed: {', '.join(PAIRWISE_KINDS)}")
    if not args.logs or not args.val_logs:
        raise ConfigError("--logs and --val-logs: both folders of flight logs are required")
    for option, location in (("--logs", args.logs), ("--val-logs", args.val_logs)):
        if not Path(location).exists():  # a typo: a one-line usage error, not a traceback from the loader
            raise ConfigError(f"{option}: {location}: no such file or folder")
    if args.minutes < 0:
        raise ConfigError(f"--minutes: expected >= 0, got {args.minutes}")
    config = training_config(args)  # with the [training] table, checked before the logs are read
    train = load_dataset(args.logs, recursive=True)  # raises naming the folder or file when empty/foreign
    val_files = find_logs(args.val_logs, recursive=True)
    val = load_dataset(val_files)
    if val.provenance != train.provenance:
        raise DataError(f"--val-logs {args.val_logs}: flown with other settings than --logs {args.logs}:\n  "
                        + "\n  ".join(differences(val.provenance, train.provenance)))
    if args.field:  # the logs must have been flown on the field the user names
        want = describe(load_field(args.field))
        have = (train.provenance or {}).get("field")
        if have != want:
            raise DataError(f"--logs {args.logs}: flown on another field than --field {args.field}:\n  "
                            + "\n  ".join(differences(have, want)))
    if args.minutes:
        train = shorten_per_stage(train, args.minutes, np.random.default_rng(args.seed))
    t0 = time.perf_counter()
    model, history = train_model(args.model, train, None, config, progress=True, feature_set=args.feature_set or None)
    seconds = time.perf_counter() - t0
    ckpt = Path(args.checkpoint) if args.checkpoint else Path(args.out) / f"{args.model}.pt"
    train_rmse, _ = rmse(model, train)
    val_rmse, val_axis = rmse(model, val)
    floor = label_noise_floor(val_files)
    save_checkpoint(ckpt, model, {"training": {k: v for k, v in history.items() if k not in ("train_loss", "val_loss")},
                                  "data": train.summary(), "logs": args.logs, "val_logs": args.val_logs,
                                  "provenance": {"flights": train.provenance, "seed": args.seed}})
    results = {
        "model": args.model, "feature_set": model.feature_set, "n_params": count_parameters(model),
        "train_rmse": train_rmse, "val_rmse": val_rmse, "val_rmse_axis": list(map(float, val_axis)),
        "noise_floor": floor["rmse_mean"], "noise_floor_axis": floor["rmse_axis_mean"],
        "noise_floor_applied": floor["rmse"], "train_minutes": train.n_minutes, "val_minutes": val.n_minutes,
        "epochs": history["epochs"], "best_epoch": history["best_epoch"], "train_seconds": seconds,
        "checkpoint": str(ckpt),
    }
    path = write_results(args.out, results, args, {"flights": train.provenance})
    rows = [[k, v] for k, v in results.items() if isinstance(v, (int, float, str)) and k not in ("checkpoint",)]
    print(format_table(rows, ["key", "value"]))
    print(f"\nwrote {ckpt} and {path}")
    return results


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(TrainArgs, "train", argv, __doc__)
    with out_lock(args, "train"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
