"""The paper's staged data collection (section 5.A), batched and resumable.

    python -m experiments.staged_collection [--collection-dir DIR] [--models-dir DIR] [--quick]

Stage 0 flies far below the leader (1.35-1.75 m) with no model; stage 1 flies
closer with the stage-0 equivariant model compensating; stage 2 flies at about
0.5 m with the stage-1 model (clamped; with --guard-stages also behind the guard). After the last stage the final shallow, deep and
equivariant models are trained on all training data into --models-dir. A rerun
skips finished work; an interrupted run loses at most the flights in progress. The
manifest records every log's SHA-256: a rerun re-flies only missing logs and stops on an
altered or unlisted one, and a second run on the same folders waits for the first and
reuses its work.
Both folders default to runs/pipeline/<field>-<key>/, keyed by the provenance
(field, config, seed), so another field collects afresh. The pipeline is
`downwash.staged`; results.json goes to --out.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from experiments.common import (PipelineArgs, ProgressBar, arg, format_table, out_lock, parse_args, resolve_pipeline,
                                run_main, setup_logging, write_results, script)

__all__ = ["StagedArgs", "run", "main"]


def _at_most_cores(threads: int) -> str | None:
    """--threads may not exceed the cores this process may use (`sim.physics.usable_cores`, without importing sim)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return None if threads <= cores else f"expected 0 (every usable core) or 1-{cores} (the cores this process may use)"


@dataclass(frozen=True)
class StagedArgs(PipelineArgs):
    stage_minutes: float = arg(5.7, "training flight minutes per stage (paper: ~5.7, ~17 in all)", gt=0.0, le=60.0)
    val_ratio: float = arg(1.0, "validation minutes per training minute (paper: similar size)", ge=0.0, le=5.0)
    flight_seconds: float = arg(28.5, "length of one flight, s (12 flights of 28.5 s: 5.7 min per stage)", ge=2.0,
                                le=600.0)
    clamp: float = arg(6.0, "magnitude bound of the deployed model's prediction, m/s^2", gt=0.0)
    guard_stages: bool = arg(False, "deploy each stage model behind the guard (downwash.guard): it applies nothing "
                                    "where the closer stage leaves its training data (default: clamped only, as the "
                                    "paper)")
    threads: int = arg(0, "worker threads for batched flights (0: all cores); training uses one", ge=0,
                       check=_at_most_cores)
    batch_flights: int = arg(12, "flights flown as one batch, each log written when its batch lands (a kill loses at "
                                 "most one batch)", ge=1, le=256)


def run(args: StagedArgs) -> dict:
    """Collect all stages (resuming), train the final models; print and write the results."""
    from downwash.staged import collect

    p = resolve_pipeline(args, stage_minutes=args.stage_minutes, val_ratio=args.val_ratio,
                         flight_seconds=args.flight_seconds, clamp=args.clamp, guard=args.guard_stages, threads=args.threads,
                         batch_flights=args.batch_flights)
    results = collect(p.config, p.collection_dir, p.models_dir, p.field, ProgressBar)
    path = write_results(args.out, results, args, p.provenance())
    rows = [[s["stage"], f"{s['separation'][0]}-{s['separation'][1]}", s["minutes"], s["samples"],
             s["deployed_val_rmse"] if s["deployed_val_rmse"] is not None else "-"] for s in results["stages"]]
    print(format_table(rows, ["stage", "separation m", "minutes", "samples", "deployed val RMSE"]))
    rows = [[k, m["val_rmse"] if m["val_rmse"] is not None else "-", m["train_seconds"]]
            for k, m in results["models"].items()]
    print(format_table(rows, ["model", "val RMSE m/s^2", "train s"]))
    if results["noise_floor"]:
        print(f"label noise floor (labels vs true mean field): {results['noise_floor']['rmse_mean']:.4f} m/s^2")
    print(f"\nwrote {path}; logs in {p.collection_dir}/, models in {p.models_dir}/ ({results['wall_seconds']:.1f} s)")
    return results


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(StagedArgs, "staged_collection", argv, __doc__)
    with out_lock(args, "staged_collection"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
