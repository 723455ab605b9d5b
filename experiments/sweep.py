"""Validation RMSE over a grid of fields x models x training minutes x seeds, resumable, on Ray.

    python -m experiments.sweep [--field 'so2;momentum'] [--models shallow,deep,equivariant]
                                [--minutes 1,5,15] [--seeds 0,1,2,3,4] [--workers N | --address HOST:PORT]
                                [--cache-dir runs/cells] [--batch 10] [--quick]

Each cell (one field, one model kind, one training length, one seed) is one
trained model whose validation RMSE is cached as a JSON file under a key of
everything that determines it: a rerun skips the cached cells, and a killed sweep
resumes where it stopped; sweeps sharing a --cache-dir compute each cell once (a
cell another sweep is computing is waited for). Every field's staged collection is
made first, once, and its logs checked against its manifest, in this process; the
missing cells then train in batches of ``--batch`` cells of one field and one kind,
each batch one ensemble, as Ray tasks of one CPU: on a local Ray of ``--workers``
CPUs (default: all usable cores, and at most those) or, with ``--address``, on a
running cluster (its nodes need this package installed; the cache is written here).
The numbers depend neither on the batching nor on the nodes. A local Ray is shut
down however the sweep ends (Ctrl-C and SIGTERM included; the cells done are cached).
The logic is `downwash.sweep`.

Results: per (field, model, minutes) the mean RMSE over the seeds with a 95 %
bootstrap CI, and the paper's claim tested seed by seed (equivariant at 5 min
against the best baseline at 15 min, on the same data subsets): results.json,
results.md (tables) and sweep.png in --out.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

from downwash.sweep import ADDRESS_TIMEOUT, address_problem, workers_problem  # cheap: no torch, no Ray
from experiments.common import (FIELD_NAMES, PAIRWISE_KINDS, PAPER_MINUTES, PAPER_MODELS, CommonArgs, PipelineArgs,
                                ProgressBar, arg, format_table, parse_args, resolve_pipeline, run_main,
                                setup_logging, out_lock, write_results, script)
from experiments.components import (training_config)

__all__ = ["SweepArgs", "grid_of", "run", "main"]


@dataclass(frozen=True)
class SweepArgs(CommonArgs):
    config_tables: ClassVar[tuple[str, ...]] = ("training",)  # the training of every cell (its seed is the cell's)

    field: str = arg("", "the fields, separated by ';': each NAME[:KEY=VALUE,...] with NAME one of "
                         f"{', '.join(FIELD_NAMES)} (python -m experiments.fields lists their parameters; '' is "
                         "so2) or MODULE:FACTORY")
    models: str = arg(",".join(PAPER_MODELS), f"comma list of model kinds: {', '.join(PAIRWISE_KINDS)}")
    minutes: str = arg(",".join(f"{m:g}" for m in PAPER_MINUTES), "comma list of training minutes; the full set "
                                                                    "is always added")
    seeds: str = arg(",".join(str(s) for s in range(10)), "comma list of trial seeds (each one data subset and "
                                                          "training seed, shared by all models); a grid too large "
                                                          "for one sweep is refused before any work, with its size")
    workers: int = arg(0, "CPUs of the local Ray: 0 (all usable cores) or at most the cores this machine lets the "
                          "sweep use; unused with --address (the cluster's CPUs run the tasks) but bounded the same",
                       ge=0, check=workers_problem)
    address: str = arg("", "a running Ray cluster: HOST:PORT of its head (as ray start --head prints it), "
                           "ray://HOST:PORT or auto (the one ray start runs on this machine); checked before any "
                           f"work, nothing answering within {ADDRESS_TIMEOUT:g} s is an error; default: a local Ray",
                       check=address_problem)
    cache_dir: str = arg("runs/cells", "folder of the cached cell results (shared with sample_efficiency)", output="dir")
    batch: int = arg(5, "cells per Ray task, trained as one ensemble of one field and one model kind (5: the "
                        "fastest per model on 2 cores)", ge=1)


def grid_of(args: SweepArgs) -> Any:
    """The sweep's `downwash.sweep_cells.SweepGrid`, its training from the [training] table (the defaults,
    and so the cells' cache keys, unchanged without it); ConfigError before any work."""
    from downwash.sweep import grid_from_text

    grid = grid_from_text(args.field, args.models, args.minutes, args.seeds, args.quick)
    return replace(grid, training=training_config(args))


def run(args: SweepArgs) -> dict:
    from downwash.sweep import check_address, check_execution, run_sweep

    check_address(args.address)  # a cluster that is not there shows now, before the stack is imported
    from downwash.sweep_report import claim_text, markdown, minute_labels, plot_field, table_rows
    from downwash_core.io import atomic_write_bytes

    t_start = time.perf_counter()
    grid = grid_of(args)
    check_execution(args.workers, args.batch, args.address)
    pipelines = {spec: resolve_pipeline(PipelineArgs(seed=args.seed, quick=args.quick, field=spec))
                 for spec in grid.fields}
    results = run_sweep(grid, pipelines, args.cache_dir, workers=args.workers, address=args.address,
                        batch=args.batch, progress=ProgressBar)
    results["wall_seconds"] = time.perf_counter() - t_start
    out = Path(args.out)
    path = write_results(out, results, args, {"pipelines": {s: p.provenance() for s, p in pipelines.items()}})
    atomic_write_bytes(out / "results.md", markdown(results["fields"]).encode())

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results["fields"])
    fig, axes = plt.subplots(1, n, figsize=(6.5 * n, 4.2), squeeze=False)
    for ax, (spec, r) in zip(axes[0], results["fields"].items()):
        plot_field(ax, r, f"field {spec or 'default'} ({len(r['seeds'])} seeds, 95 % CI)")
        print(f"field {spec or 'default'}:")
        print(format_table(table_rows(r), ["model"] + minute_labels(r["minutes"])))
        print(claim_text(r))
    fig.tight_layout()
    fig.savefig(out / "sweep.png", dpi=110)
    plt.close(fig)
    c = results["cells"]
    shared = f" ({results['computed_elsewhere']} by another sweep meanwhile)" if results["computed_elsewhere"] else ""
    print(f"\n{c['total']} cells: {c['cached']} cached{shared}, {c['computed']} computed; wrote {path}, results.md "
          f"and sweep.png in {out}/ ({results['wall_seconds']:.1f} s)")
    return results


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(SweepArgs, "sweep", argv, __doc__)
    with out_lock(args, "sweep"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
