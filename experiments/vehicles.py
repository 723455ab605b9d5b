"""List the registered vehicle kinds: their numbers, their wakes and where each number comes from.

    python -m experiments.vehicles                      # every kind
    python -m experiments.vehicles --only crazyflie_2_1,x500

One line per kind (name, mass, arm length, thrust-to-weight, motor time constant, hover
induced velocity v_h = sqrt(m g / (2 rho n pi r^2)), the paper law's strength scale, and
the source), printed and written to `<out>/results.json` under `vehicles`, each with every
number, the derived ones and the full source, one line per number. The listing flies
nothing: --seed and --quick change nothing, and --field is refused. See
downwash_core/vehicles.py and docs/fields.md ("Vehicles of other kinds").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from downwash_core.errors import ConfigError
from experiments.common import (CommonArgs, arg, comma_items, format_table, out_lock, parse_args, run_main, script,
                                setup_logging, write_results)

__all__ = ["VehiclesArgs", "VEHICLE_NAMES", "listing", "run", "main"]

# a static copy of downwash_core.vehicles.VEHICLE_NAMES for --help (tests/test_vehicles.py ties them)
VEHICLE_NAMES = ("paper_quad", "crazyflie_2_1", "x500", "crazyflie_large")


@dataclass(frozen=True)
class VehiclesArgs(CommonArgs):
    """--seed, --quick and --field do not apply (the listing flies nothing)."""

    only: str = arg("", f"a comma list of vehicle kinds, of {', '.join(VEHICLE_NAMES)} (default: all of them)")


def _selected(only: str) -> list[str]:
    from downwash_core.vehicles import VEHICLES

    names = comma_items(only) or list(VEHICLES)
    unknown = [n for n in names if n not in VEHICLES]
    if unknown:
        raise ConfigError(f"--only: unknown vehicle kinds {unknown}; allowed: {', '.join(VEHICLES)}")
    return names


def listing(names: Sequence[str] | None = None) -> list[dict]:
    """[VehicleKind.describe()] of the named kinds (default: all), in registry order."""
    from downwash_core.vehicles import VEHICLES

    return [VEHICLES[n].describe() for n in (names or list(VEHICLES))]


def run(args: VehiclesArgs) -> dict:
    """The listing: printed as a table and written to <out>/results.json."""
    if args.field:
        raise ConfigError("--field: the vehicle listing flies nothing and takes no field")
    names = _selected(args.only)  # before anything is written
    results = {"vehicles": listing(names)}
    rows = [(v["name"], v["mass"], v["arm_length"], v["thrust_to_weight"], v["motor_time_constant"],
             v["hover_induced_velocity"], v["so2_strength_scale"], v["source"].strip().splitlines()[0])
            for v in results["vehicles"]]
    print(format_table(rows, ("name", "mass kg", "arm m", "T/W", "motor tau s", "v_h m/s", "so2 scale", "source")))
    path = write_results(args.out, results, args)
    print(f"\nwrote {path}")
    return results


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    args = parse_args(VehiclesArgs, "vehicles", argv, __doc__)
    with out_lock(args, "vehicles"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
