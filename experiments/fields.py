"""List the registered ground-truth fields, or run the lemniscate experiment on every one of them.

    python -m experiments.fields                 # the listing
    python -m experiments.fields --run [--quick] # the lemniscate from scratch on every field

One line per field (name, description, symmetry), printed and written to
`<out>/results.json` under `fields`, each with its parameters (name: type, and the
values its preset fixes). `--field SPEC` also resolves and checks that spec and records
its description, so a spec can be tried here before a long run. See docs/fields.md.

`--run` answers "how does each model fare when the air is not what it assumes": for
every registered field it runs the lemniscate experiment, `python -m experiments.lemniscate --field
NAME` (its own process, so each field collects and trains from scratch into its own
keyed pipeline folder unless that exists already; `--fresh` deletes nothing but points
each run at a new pipeline folder under --out), and tabulates per field and condition the
improvement over the baseline and the gap to the oracle, with each run's wall time, under
`table` (the README's field x model table is rendered from it), in runs/field_table unless --out.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from downwash_core.errors import ConfigError
from experiments.common import (CONDITIONS, FIELD_NAMES, CommonArgs, arg, comma_items, format_table, load_field,
                                out_lock, parse_args, registered_field_names, run_main, setup_logging, write_results,
                                script)

__all__ = ["FieldsArgs", "TABLE_KEYS", "listing", "run_every_field", "run", "main"]

# per condition, from each field's lemniscate results: what the field x model table shows
TABLE_KEYS = ("improvement_pos_3d", "improvement_pos_z", "gap_to_oracle_pos_3d", "pos_err_3d_mean", "crash_rate",
              "crash_rate_ci95", "kinds_in_data")


def _only_check(only: str) -> str | None:
    """--only while parsing (the registry's names without loading it): None when every name is registered."""
    allowed = registered_field_names()
    unknown = [n for n in comma_items(only) if n not in allowed]
    return f"unknown fields {unknown}; allowed: {', '.join(allowed)}" if unknown else None


@dataclass(frozen=True)
class FieldsArgs(CommonArgs):
    """--seed and --quick apply to --run only (the listing flies nothing)."""

    run: bool = arg(False, "run the lemniscate experiment (python -m experiments.lemniscate) on every registered field")
    only: str = arg("", f"with --run: a comma list of registered field names, of {', '.join(FIELD_NAMES)} "
                        "(default: all of them)", check=_only_check)
    fresh: bool = arg(False, "with --run: collect and train from scratch into <out>/pipeline/<field> "
                             "instead of reusing the keyed pipeline folders")


def listing() -> list[dict]:
    """[{name, description, symmetry, parameters: {name: type}, preset: {name: value}}] in registry order."""
    from sim.fields.registry import FIELDS

    return [
        {"name": e.name, "description": e.description, "symmetry": e.symmetry,
         "parameters": {k: t.__name__ for k, t in e.params.items()}, "preset": dict(e.preset)}
        for e in FIELDS.values()
    ]


def run_every_field(args: FieldsArgs, out: Path) -> dict:
    """{field: {wall_seconds, conditions: {condition: TABLE_KEYS}}}: the lemniscate on every registered field."""
    table = {}
    for name in _selected(args.only):
        run_dir = out / name
        cmd = [sys.executable, "-m", "experiments.lemniscate", "--field", name, "--seed", str(args.seed),
               "--out", str(run_dir)] + (["--quick"] if args.quick else [])
        if args.fresh:
            cmd += ["--collection-dir", str(out / "pipeline" / name / "collection"),
                    "--models-dir", str(out / "pipeline" / name / "models")]
        print(f"--field {name}: {' '.join(cmd[1:])}", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise ConfigError(f"the lemniscate on --field {name} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
        result = json.loads((run_dir / "results.json").read_text())
        table[name] = {
            "wall_seconds": wall, "seeds": len(result["seeds"]), "duration": result["duration"],
            "pipeline_key": result.get("provenance", {}).get("pipeline_key"),
            # (and each seed's 3-D error, for the paired intervals of the results page)
            "conditions": {c: {**{k: e.get(k) for k in TABLE_KEYS},
                               "per_seed": {"pos_err_3d_mean": e["per_seed"]["pos_err_3d_mean"]}}
                           for c, e in result["conditions"].items()},
        }
        print(f"--field {name}: {wall:.0f} s", flush=True)
    return table


def _selected(only: str) -> list[str]:
    from sim.fields.registry import FIELDS

    names = comma_items(only) or list(FIELDS)
    unknown = [n for n in names if n not in FIELDS]
    if unknown:
        raise ConfigError(f"--only: unknown fields {unknown}; allowed: {', '.join(FIELDS)}")
    return names


def _cell(entry: dict) -> str:
    improvement, gap = entry.get("improvement_pos_3d"), entry.get("gap_to_oracle_pos_3d")
    return ("-" if improvement is None else f"{improvement:+.0%}") + ("" if gap is None else f" ({gap:+.3f})")


def run(args: FieldsArgs) -> dict:
    """The listing (and the --field spec, resolved and checked); with --run the lemniscate experiment on every field."""
    if args.run and args.field:
        raise ConfigError("--field: not with --run, which runs every registered field (choose some with --only)")
    if args.only and not args.run:
        raise ConfigError("--only: only with --run")
    _selected(args.only)  # before any work
    results: dict = {"fields": listing()}
    if args.field:  # resolved and checked before anything is written
        from downwash_core.provenance import describe

        results["selected"] = {"spec": args.field, "field": describe(load_field(args.field))}
    print(format_table([(f["name"], f["description"], f["symmetry"]) for f in results["fields"]],
                       ("name", "description", "symmetry")))
    args = _with_out(args)
    if args.run:
        out = Path(args.out)
        results["table"] = run_every_field(args, out)
        conditions = [c for c in CONDITIONS if c in next(iter(results["table"].values()))["conditions"]]
        print("\nimprovement of 3D position error over the baseline (gap to the oracle, m):")
        print(format_table([[f] + [_cell(e["conditions"].get(c, {})) for c in conditions] + [f"{e['wall_seconds']:.0f} s"]
                            for f, e in results["table"].items()],
                           ["field"] + conditions + ["wall"]))
    path = write_results(args.out, results, args)
    if "selected" in results:
        print(f"\n--field {args.field}: {results['selected']['field']}")
    print(f"\nwrote {path}")
    return results


def _with_out(args: FieldsArgs) -> FieldsArgs:
    """--run has its own default folder: the report reads the table from runs/field_table/results.json."""
    if args.run and Path(args.out) == Path("runs") / "fields":  # the listing's default: --run keeps its table apart
        return dataclasses.replace(args, out=str(Path("runs") / "field_table"))
    return args


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    args = _with_out(parse_args(FieldsArgs, "fields", argv, __doc__))
    with out_lock(args, "fields"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
