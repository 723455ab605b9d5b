"""Validation RMSE against minutes of training data (the paper's figure 3 and table).

    python -m experiments.sample_efficiency [--collection-dir DIR] [--trials N] [--workers N] [--quick]

A preset of the sweep (`downwash.sweep`, `python -m experiments.sweep`) on one
field (--field, default so2): minutes 1 to 15 (seven points) plus the full training
set, --trials trials (seeds seed .. seed + trials - 1) and the paper's three
models. Each stage is shortened proportionally; every model of a trial trains on
the same data subset with the same seed, so the models are compared trial by
trial. Each trained model is a cell cached under --cache-dir (shared with the
sweep): a rerun or a resumed run trains only what is missing, on a local Ray of
--workers CPUs (or the cluster at --address). The label-noise floor (labels
against the true mean field) is the line no model can go below. Runs the staged
collection first if its data is missing.

results.json keeps the keys the report reads (``minutes``, ``trials``,
``models.<kind>.rmse_mean/rmse_std/rmse_runs``, ``noise_floor``,
``validation_minutes``) and adds each point's 95 % bootstrap CI
(``models.<kind>.rmse_ci_low/rmse_ci_high``), the paired test of the paper's
claim (``claim``: equivariant at 5 min against the best baseline at 15 min) and
the cell counts (``cells``: total, cached, computed).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from typing import Any, ClassVar

from downwash_core.errors import ConfigError
from experiments.common import (PAIRWISE_KINDS, PAPER_MINUTES, PAPER_MODELS, SEED_COUNT_MAX, PipelineArgs, ProgressBar,
                                arg, comma_numbers, format_table, names_check, out_lock, parse_args, resolve_pipeline,
                                run_main, script, seed_count_check, setup_logging, write_results)
from experiments.components import (training_config)

__all__ = ["EfficiencyArgs", "MINUTES", "grid_of", "run", "main"]

MINUTES = PAPER_MINUTES  # plus the full set


def _minutes_check(text: str) -> str | None:
    """--minutes while parsing: what `downwash.sweep_cells.SweepGrid` takes, without importing it."""
    try:
        values = comma_numbers(text)
    except ValueError:
        values = [math.nan]
    return None if all(math.isfinite(v) and v > 0 for v in values) else "expected a comma list of numbers > 0 (min)"


@dataclass(frozen=True)
class EfficiencyArgs(PipelineArgs):
    config_tables: ClassVar[tuple[str, ...]] = ("training",)  # the training of every cell (its seed is the cell's)

    trials: int = arg(10, f"trials per point (different data subsets and seeds; at most {SEED_COUNT_MAX}; --quick: "
                          "at most 2)", ge=1, check=seed_count_check)
    minutes: str = arg(",".join(f"{m:g}" for m in MINUTES),
                       "comma list of training minutes; the full set is always added", check=_minutes_check)
    models: str = arg(",".join(PAPER_MODELS), f"comma list of model kinds: {', '.join(PAIRWISE_KINDS)}",
                      check=names_check(PAIRWISE_KINDS))
    workers: int = arg(0, "CPUs of the local Ray that trains the models (0: all cores)", ge=0)
    address: str = arg("", "address of a running Ray cluster; default: a local Ray")
    cache_dir: str = arg("runs/cells", "folder of the cached cell results (shared with experiments.sweep)", output="dir")
    batch: int = arg(5, "models per Ray task, trained as one ensemble (5 is the fastest per model on 2 cores)", ge=1)


def grid_of(args: EfficiencyArgs) -> Any:
    """The sweep this preset runs, a `downwash.sweep_cells.SweepGrid` (ConfigError before any work)."""
    from downwash.sweep import grid_from_text
    from downwash.sweep_cells import SweepGrid

    if isinstance(args.trials, bool) or args.trials < 1:
        raise ConfigError(f"--trials: expected >= 1, got {args.trials}")
    trials = min(args.trials, 2) if args.quick else args.trials
    seeds = ",".join(str(s) for s in range(args.seed, args.seed + trials))
    grid = grid_from_text("", args.models, args.minutes, seeds, args.quick)
    return SweepGrid(fields=(args.field,), models=grid.models, minutes=grid.minutes, seeds=grid.seeds,
                     quick=args.quick, training=training_config(args))


def run(args: EfficiencyArgs) -> dict:
    from downwash.sweep import check_execution, run_sweep
    from downwash.sweep_report import claim_text, markdown, minute_labels, plot_field, table_rows
    from downwash_core.io import atomic_write_bytes

    t_start = time.perf_counter()
    grid = grid_of(args)
    check_execution(args.workers, args.batch)
    p = resolve_pipeline(args)
    sweep = run_sweep(grid, {args.field: p}, args.cache_dir, workers=args.workers, address=args.address,
                      batch=args.batch, progress=ProgressBar)
    r = sweep["fields"][args.field]
    results = {
        "minutes": r["minutes"], "trials": len(r["seeds"]), "seeds": r["seeds"], "noise_floor": r["noise_floor"],
        "noise_floor_applied": r["noise_floor_applied"], "validation_minutes": r["validation_minutes"],
        "models": r["models"], "claim": r["claim"], "claim_skipped": r["claim_skipped"], "cells": sweep["cells"],
        "wall_seconds": time.perf_counter() - t_start, "workers": sweep["workers"],
    }  # fmt: skip
    out = Path(args.out)
    path = write_results(out, results, args, p.provenance())
    atomic_write_bytes(out / "results.md", markdown({args.field: r}).encode())

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    plot_field(ax, r, f"sample efficiency ({results['trials']} trials per point, 95 % CI)")
    fig.tight_layout()
    fig.savefig(out / "sample_efficiency.png", dpi=110)
    plt.close(fig)
    print(format_table(table_rows(r), ["model"] + minute_labels(r["minutes"])))
    print(f"label noise floor: {r['noise_floor']:.4f} m/s^2")
    print(claim_text(r))
    c = sweep["cells"]
    print(f"\n{c['total']} models: {c['cached']} cached, {c['computed']} trained; wrote {path}, results.md and "
          f"sample_efficiency.png in {out}/ ({results['wall_seconds']:.1f} s)")
    return results


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(EfficiencyArgs, "sample_efficiency", argv, __doc__)
    with out_lock(args, "sample_efficiency"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
