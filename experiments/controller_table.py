"""The tracking experiments under every controller labs fly, with and without the models.

    python -m experiments.controller_table                  # lemniscate and transect, every controller
    python -m experiments.controller_table --controllers lqr,indi --quick

Runs `python -m experiments.lemniscate` and `python -m experiments.transect` once per
controller of --controllers (`controllers.registry`: the paper's LQR, the Crazyflie firmware's
Mellinger and cascaded PID, INDI), with the conditions of --conditions on the same seeds, each
into <out>/<track>-<controller>/ (its own results.json and figures), and tabulates per
controller and condition the follower's mean 3-D error, its improvement over that controller's
baseline and the crash rate. The models are the staged collection's, trained under the LQR (the
pipeline is the same for every controller). `integral` adds integral action to the LQR only, so
the other controllers fly the conditions without it. Written to <out>/results.json under `table`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from downwash_core.errors import ConfigError
from experiments.common import (CONDITIONS, CONTROLLER_NAMES, SEED_COUNT_MAX, PipelineArgs, arg, comma_items,
                                format_table, names_check, out_lock, parse_args, run_main, script, seed_count_check,
                                setup_logging, write_results)

__all__ = ["ControllerTableArgs", "TRACKS", "KEYS", "run", "main"]

TRACKS = ("lemniscate", "transect")
KEYS = ("pos_err_3d_mean", "improvement_pos_3d", "crash_rate", "crash_rate_ci95")  # per condition, what the table keeps
_CONDITIONS = "no_downwash,baseline,oracle,integral,dob,equivariant,equivariant_guarded,equivariant_dob"


@dataclass(frozen=True)
class ControllerTableArgs(PipelineArgs):
    controllers: str = arg(",".join(CONTROLLER_NAMES), "comma list of controllers: " + ", ".join(CONTROLLER_NAMES),
                           check=names_check(CONTROLLER_NAMES))
    conditions: str = arg(_CONDITIONS, "comma list of conditions, of " + ", ".join(CONDITIONS),
                          check=names_check(CONDITIONS))
    seeds: int = arg(10, f"flights per condition (at most {SEED_COUNT_MAX})", ge=1, check=seed_count_check, quick=1)


def run(args: ControllerTableArgs) -> dict:
    """Each track under each controller; print and write the table."""
    from experiments.tracking import args_class
    from experiments.tracking import run as run_track

    if args.field:
        raise ConfigError("--field: the controller table flies the default field (the models' training field)")
    out = Path(args.out)
    table: dict[str, dict[str, Any]] = {}
    for track in TRACKS:
        for controller in comma_items(args.controllers):
            conditions = [c for c in comma_items(args.conditions) if controller == "lqr" or c != "integral"]
            flight = args_class(track)(out=str(out / f"{track}-{controller}"), seed=args.seed, quick=args.quick,
                                       collection_dir=args.collection_dir, models_dir=args.models_dir,
                                       controller=controller, conditions=",".join(conditions), seeds=args.seeds,
                                       duration=2.0 if args.quick else 0.0)
            r = run_track(track, flight)
            table.setdefault(controller, {})[track] = {
                "conditions": {c: {k: e.get(k) for k in KEYS} for c, e in r["conditions"].items()},
                "seeds": len(r["seeds"]), "duration": r["duration"]}
    results = {"experiment": "controller_table", "tracks": list(TRACKS), "table": table}
    rows = [[controller, c] + [f"{e[t]['conditions'][c]['pos_err_3d_mean']:.4f}" if c in e[t]["conditions"] else "-"
                               for t in TRACKS]
            for controller, e in table.items() for c in e[TRACKS[0]]["conditions"]]
    print(format_table(rows, ["controller", "condition", *(f"{t} 3-D m" for t in TRACKS)]))
    path = write_results(out, results, args)
    print(f"\nwrote {path}")
    return results


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    args = parse_args(ControllerTableArgs, "controller_table", argv, __doc__)
    with out_lock(args, "controller_table"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)

