"""List every registered component: fields, models, vehicles, presets, sensors, controllers and aggregation laws.

    python -m experiments.registry                      # every kind
    python -m experiments.registry --kind fields        # one kind (or a comma list)

Each entry with its description, its parameters (type and default: what a spec
NAME:KEY=VALUE,... sets, `downwash_core.registry`) and the plugin that registered it, if one
did (the entry-point group `downwash_testbed.plugins`: the installed plugins are loaded, and
listed with what became of each). Printed, and written to `<out>/results.json` under
`registry` ({kind: [entry]}) and `plugins`. The listing flies nothing: --seed and --quick
change nothing, and --field is refused. The models' listing imports torch.
"""

from __future__ import annotations

import importlib
import textwrap
from dataclasses import dataclass
from typing import Any, Sequence

from downwash_core.errors import ConfigError
from experiments.common import (CommonArgs, arg, comma_items, names_check, out_lock, parse_args, run_main, script,
                                setup_logging, write_results)

__all__ = ["RegistryArgs", "KINDS", "listing", "run", "main"]

# kind -> (module, registry): each a downwash_core.registry.Registry (imported only when listed)
KINDS = {
    "fields": ("sim.fields.registry", "FIELDS"),
    "models": ("downwash.registry", "MODEL_KINDS"),
    "vehicles": ("downwash_core.vehicles", "VEHICLES"),
    "presets": ("sim.presets", "PRESETS"),
    "sensors": ("sim.sensors", "SENSORS"),
    "controllers": ("controllers.registry", "CONTROLLERS"),
    "aggregations": ("sim.aggregation", "AGGREGATIONS"),
}


@dataclass(frozen=True)
class RegistryArgs(CommonArgs):
    """--seed, --quick and --field do not apply (the listing flies nothing)."""

    kind: str = arg("", f"the kinds to list, a comma list of {', '.join(KINDS)} (default: all of them)",
                    check=names_check(tuple(KINDS), empty=True))


def _entries(kind: str) -> list[dict[str, Any]]:
    """The kind's registry's listing (plugins loaded)."""
    module, name = KINDS[kind]
    return getattr(importlib.import_module(module), name).listing()


def listing(kinds: Sequence[str] | None = None) -> dict[str, Any]:
    """{"registry": {kind: [entry]}, "plugins": [what each installed plugin did]} of the kinds (default: all)."""
    from downwash_core.registry import PLUGINS

    out = {"registry": {kind: _entries(kind) for kind in (kinds or list(KINDS))}}
    return {**out, "plugins": list(PLUGINS.plugins)}


def _params(entry: dict[str, Any]) -> str:
    return ", ".join(f"{k}: {p['type']} = {p['default']!r}" for k, p in entry["params"].items()) or "(no parameters)"


def _print(results: dict[str, Any]) -> None:
    for kind, entries in results["registry"].items():
        print(f"{kind} ({len(entries)})")
        width = max((len(e["name"]) for e in entries), default=0) + 2
        for e in entries:
            plugin = f" [plugin {e['plugin']}]" if e.get("plugin") else ""
            print(f"  {e['name'].ljust(width)}{e['description']}{plugin}")
            print(textwrap.fill(_params(e), 116, initial_indent=" " * (width + 4), subsequent_indent=" " * (width + 4)))
        print()
    for p in results["plugins"]:
        print(f"plugin {p['name']} ({p['value']}): {p['status']}, {p['registrations']} registrations")


def run(args: RegistryArgs) -> dict:
    """The listing: printed and written to <out>/results.json."""
    if args.field:
        raise ConfigError("--field: the registry listing flies nothing and takes no field")
    kinds = comma_items(args.kind)
    results = listing(kinds)
    _print(results)
    path = write_results(args.out, results, args)
    print(f"\nwrote {path}")
    return results


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    args = parse_args(RegistryArgs, "registry", argv, __doc__)
    with out_lock(args, "registry"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
