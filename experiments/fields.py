"""List the registered ground-truth fields: `python -m experiments.fields`.

One line per field (name, description, symmetry), printed and written to
`<out>/results.json` under `fields`, each with its parameters (name: type, and the
values its preset fixes). `--seed` and `--quick` are accepted and ignored (nothing is
flown); `--field SPEC` also resolves and checks that spec and records its
description, so a spec can be tried here before a long run. See docs/fields.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from core.provenance import describe
from experiments.common import CommonArgs, format_table, load_field, parse_args, setup_logging, write_results
from sim.fields.registry import FIELDS

__all__ = ["FieldsArgs", "listing", "run", "main"]


@dataclass(frozen=True)
class FieldsArgs(CommonArgs):
    """The common options only (--seed and --quick do nothing here)."""


def listing() -> list[dict]:
    """[{name, description, symmetry, parameters: {name: type}, preset: {name: value}}] in registry order."""
    return [
        {"name": e.name, "description": e.description, "symmetry": e.symmetry,
         "parameters": {k: t.__name__ for k, t in e.params.items()}, "preset": dict(e.preset)}
        for e in FIELDS.values()
    ]


def run(args: FieldsArgs) -> dict:
    """The listing (and the --field spec, resolved and checked); print and write it."""
    results: dict = {"fields": listing()}
    if args.field:  # resolved and checked before anything is written
        results["selected"] = {"spec": args.field, "field": describe(load_field(args.field))}
    path = write_results(args.out, results, args)
    print(format_table([(f["name"], f["description"], f["symmetry"]) for f in results["fields"]],
                       ("name", "description", "symmetry")))
    if "selected" in results:
        print(f"\n--field {args.field}: {results['selected']['field']}")
    print(f"\nwrote {path}")
    return results


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    return run(parse_args(FieldsArgs, "fields", argv, __doc__))


if __name__ == "__main__":
    main()
