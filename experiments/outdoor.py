"""The paper's outdoor regime (its section 6): a moving leader, the follower beneath it, ambient wind.

    python -m experiments.outdoor [--leader circle|line] [--speed 1.5] [--wind light:mean=2,0,0] [--quick]

Alpha flies a horizontal circle (or a straight line) at `--speed` m/s (0.5-3); Bravo
tracks the point `--separation` below it (and `--lateral` to its side, so it sits on
the wake's flank where the radial force acts). The wind (`--wind`, a mean wind plus
Dryden gusts, see `sim.wind`) acts on both vehicles through their airframe drag and
convects the wake: its axis follows the leader's airspeed, not its ground speed. Every
condition flies the same seeds in one batch: the references, the oracle (the true mean
wake at the true, air-relative state), the models of the staged collection, trained
indoors on a hovering leader in still air (`<kind>`: how far they carry into a regime they
never saw), and the same kinds trained on the indoor flights plus the outdoor stages of
`downwash.outdoor_collection` (`<kind>-outdoor`: a moving leader in wind, collected and
trained on the first run; `--trained` picks which). The models with memory
(`equivariant_memory`, `deep_memory`) also read where the leader was over the last 0.27 s.

Sweeps. `--sweep-speeds 0.5,1,2,3` flies every condition again at each speed (same seeds and
wind) and plots its improvement against the leader's speed; `--sweep-winds` flies them in each of
several winds at `--speed`; `--sweep-fields "so2;momentum;shed"` runs the whole experiment (collection,
training, flights and these sweeps) on each of those ground truths as well, one Ray task per
truth (`--workers`, `--address`; `--workers 1` runs them one after the other, without Ray).
Writes results.json (with the leader's airspeed range and the sweeps), a table and the figures.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import LEADER_POSITION
from experiments.common import (CONDITIONS, DEFAULT_FIELD, FLIGHT_SECONDS_MAX, SEED_COUNT_MAX, WIND_HELP, FlightArgs,
                                ProgressBar, arg, check_options, comma_items, comma_numbers, field_check, format_table,
                                load_field, load_wind, names_check, one_of, out_lock, parse_args, resolve_pipeline,
                                run_main, script, seed_count_check, setup_logging, wind_check, write_results)
from experiments.components import check_controller, flight_components, flown_record, guard_config

__all__ = ["OutdoorArgs", "LEADERS", "LEADER_SPEED_RANGE", "run", "main"]

LEADERS = ("circle", "line")
TRAINED = ("indoor", "outdoor")  # the data the learned conditions were trained on
LEADER_SPEED_RANGE = (0.5, 3.0)  # m/s, the leader's ground speed (the paper's outdoor, sustained-speed regime)


# The checks of the list options, run while parsing (before the stack is imported): each returns what is
# expected when the text is bad, else None.


def _trained_check(text: str) -> str | None:
    trained = comma_items(text)
    if not trained or not set(trained) <= set(TRAINED) or len(set(trained)) != len(trained):
        return f"expected a comma list of {', '.join(TRAINED)}, each at most once"
    return None


def _speeds_check(text: str) -> str | None:
    try:
        speeds = comma_numbers(text)
    except ValueError:
        speeds = None
    lo, hi = LEADER_SPEED_RANGE
    if speeds is None or not all(lo <= v <= hi for v in speeds) or len(set(speeds)) != len(speeds):
        return f"expected a comma list of distinct speeds in {lo}-{hi} m/s"
    return None


def _each(check: Callable[[str], str | None], option: str, what: str) -> Callable[[str], str | None]:
    """A `check` for a ;-list of distinct specs, each one that `option` takes (its `check`)."""

    def items_check(text: str) -> str | None:
        items = _items(text)
        if len(set(items)) != len(items):
            return f"duplicate {what} in {items}"
        for spec in items:
            problem = check(spec)
            if problem:
                return f"{option}: {problem}"
        return None

    return items_check


_winds_check = _each(wind_check, "--wind", "winds")
_fields_check = _each(field_check, "--field", "truths")


@dataclass(frozen=True)
class OutdoorArgs(FlightArgs):
    # the flights' controller and simulator settings, and the guard's of the guarded conditions (the outdoor
    # stages, like the staged collection, fly the defaults)

    conditions: str = arg(",".join(CONDITIONS), "comma list of " + ", ".join(CONDITIONS), check=names_check(CONDITIONS))
    seeds: int = arg(10, f"number of seeds (flights per condition, at most {SEED_COUNT_MAX})", ge=1,
                     check=seed_count_check, quick=1)
    leader: str = arg("circle", "the leader's path: circle (radius --radius) or line (along +x)", check=one_of(LEADERS))
    speed: float = arg(1.5, "the leader's ground speed, m/s", ge=LEADER_SPEED_RANGE[0], le=LEADER_SPEED_RANGE[1])
    radius: float = arg(2.0, "radius of the leader's circle, m", ge=1.0, le=10.0)
    separation: float = arg(0.6, "the follower's depth below the leader, m", ge=0.3, le=2.0)
    lateral: float = arg(0.1, "the follower's offset from beneath the leader along y, m", ge=0.0, le=1.0)
    wind: str = arg("light:mean=2,0,0", WIND_HELP, check=wind_check)
    duration: float = arg(20.0, "flight length, s", gt=0.0, le=FLIGHT_SECONDS_MAX, quick=2.0)
    trained: str = arg("indoor,outdoor", "the models the learned conditions fly, comma list: indoor (the staged "
                                         "collection's) and outdoor (also trained on the outdoor stages: <kind>-outdoor)",
                       check=_trained_check)
    outdoor_minutes: float = arg(1.0, "training flight minutes per wind setting of the outdoor stages", gt=0.0, le=60.0)
    sweep_speeds: str = arg("", "also fly every condition at these leader speeds (comma list, m/s, in 0.5-3) and plot "
                                "each one's improvement against the speed (improvement_vs_speed.png)",
                        check=_speeds_check)
    sweep_winds: str = arg("", "also fly every condition in each of these winds at --speed (';'-separated --wind specs, "
                               "e.g. 'off;light:mean=2,0,0;moderate:mean=2,0,0')", check=_winds_check)
    sweep_fields: str = arg("", "also run the whole experiment, sweeps included, on each of these ground truths (';'-separated "
                                "--field specs, e.g. 'momentum;shed'), one Ray task each, into <out>/truths/",
                        check=_fields_check)
    workers: int = arg(0, "CPUs of the local Ray for --sweep-fields (0: all cores; 1: no Ray, one truth after the "
                          "other); unused with --address", ge=0)
    address: str = arg("", "address of a running Ray cluster for --sweep-fields (ray start --head)")


def _validate(args: OutdoorArgs) -> list[str]:
    """Check every option before any flight (parse_args has checked each alone; again here for options
    built in Python); returns the condition list."""
    from downwash.conditions import parse_conditions

    check_options(args)
    conditions = check_controller(args, parse_conditions(args.conditions))
    fields = _items(args.sweep_fields)
    if _main_field(args) in fields:
        raise ConfigError(f"--sweep-fields: expected distinct truths other than --field ({_main_field(args)}), "
                          f"got {fields}")
    for spec in _items(args.sweep_winds):
        try:
            load_wind(spec)
        except ConfigError as e:
            raise ConfigError(f"--sweep-winds: {e}") from e
    for spec in fields:
        try:
            load_field(spec)
        except ConfigError as e:  # a parameter or an import path: name the option that gave it
            raise ConfigError(f"--sweep-fields: {e}") from e
    return conditions


def _items(text: str) -> list[str]:
    """The ';'-separated items of a sweep option (a wind or field spec may hold commas)."""
    return [t.strip() for t in text.split(";") if t.strip()]


def _main_field(args: OutdoorArgs) -> str:
    return args.field or DEFAULT_FIELD


def _trained(args: OutdoorArgs) -> list[str]:
    """The data mixes of --trained, in order."""
    return comma_items(args.trained)


def _references(args: OutdoorArgs, W: int):
    """The leader's path and the follower `--separation` beneath it, `--lateral` to its side."""
    from downwash_trajectories import Offset, stack

    leader = _leader_reference(args, W)
    return stack([leader, Offset(leader, (0.0, args.lateral, -args.separation))])


def _leader_reference(args: OutdoorArgs, W: int):
    from downwash_trajectories import Circle, Line

    top = np.array(LEADER_POSITION)
    if args.leader == "circle":
        return Circle(top, radius=args.radius, speed=args.speed, n_worlds=W)
    start = top - np.array([0.5 * args.speed * args.duration, 0.0, 0.0])  # the line is centred on the origin
    return Line(start, (args.speed, 0.0, 0.0), duration=args.duration, n_worlds=W)


def run(args: OutdoorArgs) -> dict:
    """Fly every condition x seed with the moving leader and the wind; write results, table and figure."""
    from downwash.conditions import data_variant, fly_conditions, guard_record, kinds_in_data, learned
    from downwash.staged import ensure_models
    from downwash_core.provenance import describe
    from sim.metrics import aggregate_conditions
    from sim.scene import build_scene

    conditions = _validate(args)
    components, guard = flight_components(args), guard_config(args)  # the tables, checked before any flight
    trained = _trained(args)
    wind = load_wind(args.wind)
    p = resolve_pipeline(args, models=learned(conditions))
    checkpoints = ensure_models(p.models_dir, learned(conditions), p.collection_dir, p.config, p.field, ProgressBar)
    outdoor = None
    if "outdoor" in trained and learned(conditions):
        outdoor = _outdoor_models(args, p, learned(conditions))
        checkpoints.update({f"{k}-outdoor": path for k, path in outdoor["checkpoints"].items()})
    models = [c for c in conditions if learned([c])]
    conditions = [c for c in conditions if c not in models or "indoor" in trained] + [
        data_variant(c, "outdoor") for c in models if outdoor is not None]
    t_start = time.perf_counter()
    K = args.seeds
    W = len(conditions) * K
    seeds = list(range(args.seed, args.seed + K))

    def fly_at(a: OutdoorArgs, air: Any = wind) -> dict:
        return fly_conditions(build_scene(), conditions, _references(a, W), seeds, a.duration, p.field, checkpoints,
                              meta={"experiment": "outdoor"}, guard=guard, wind=air, **components)

    per_condition = fly_at(args)
    kinds = kinds_in_data(conditions, checkpoints, build_scene())  # (the guard's retention criterion)
    results: dict[str, Any] = {
        "experiment": "outdoor", "leader": args.leader, "speed": args.speed, "separation": args.separation,
        "lateral": args.lateral, "duration": args.duration, "seeds": seeds,
        "wind": None if wind is None else describe(wind), "leader_airspeed": _airspeed(per_condition),
        "conditions": _with_kinds(aggregate_conditions(per_condition), kinds), "guard": guard_record(conditions, guard),
        "trained": trained,
        "outdoor_collection": None if outdoor is None else {
            **{k: outdoor[k] for k in ("key", "minutes", "stages", "models", "data_winds", "dir", "wall_seconds")},
            "deployed": outdoor["provenance"]["outdoor"]["deployed"]},  # what the outdoor stages flew with
    }
    speeds = comma_numbers(args.sweep_speeds)
    if speeds:  # the same conditions, seeds and wind at each speed
        by_speed = [aggregate_conditions(fly_at(dataclasses.replace(args, speed=v))) for v in speeds]
        results["sweep"] = {"speeds": speeds, "conditions": _with_kinds(_per_point(by_speed, conditions), kinds)}
    winds = _items(args.sweep_winds)
    if winds:  # the same conditions, seeds and speed in each wind
        by_wind = [aggregate_conditions(fly_at(args, load_wind(spec))) for spec in winds]
        results["wind_sweep"] = {"winds": winds, "conditions": _with_kinds(_per_point(by_wind, conditions), kinds)}
    if _items(args.sweep_fields):
        results["truths"] = {_main_field(args): _truth_summary(results, args.out), **_other_truths(args)}
    results["wall_seconds"] = time.perf_counter() - t_start
    out = Path(args.out)
    flown = flown_record(args, components)  # what made the numbers
    path = write_results(out, results, args, {**(p.provenance() if checkpoints else {}), **flown})
    _figure(out, per_condition, results)
    if "sweep" in results or any(t.get("sweep") for t in results.get("truths", {}).values()):
        _speed_figure(out, results, _main_field(args))
    print(_table(results, args.wind))
    for spec, truth in results.get("truths", {}).items():
        if truth.get("sweep"):
            print(f"\n{spec}: improvement over the baseline at each leader speed (m/s)\n" + format_table(
                [[c] + [_pct(x) for x in e["improvement_pos_3d"]] for c, e in truth["sweep"]["conditions"].items()],
                ["condition"] + [str(v) for v in truth["sweep"]["speeds"]]))
    print(f"\nwrote {path} and {out / 'errors_over_time.png'}")
    return results


def _with_kinds(conditions: dict[str, dict], kinds: dict[str, bool]) -> dict[str, dict]:
    """Each learned condition's entry with whether its model's vehicle kinds were in its data."""
    for c, inside in kinds.items():
        conditions[c]["kinds_in_data"] = inside
    return conditions


def _per_point(points: list[dict], conditions: list[str]) -> dict:
    """{condition: {improvement_pos_3d, crash_rate, pos_err_3d_mean: [...]}} over sweep points' aggregated
    conditions (the errors tell how much of the baseline's error the downwash causes at each point)."""
    keys = ("improvement_pos_3d", "crash_rate", "pos_err_3d_mean")
    return {c: {k: [point[c].get(k) for point in points] for k in keys} for c in conditions}


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def _truth_summary(results: dict, out: str) -> dict:
    """What the truths' comparison keeps of one truth's results."""
    keys = ("improvement_pos_3d", "crash_rate", "crash_rate_ci95", "gap_to_oracle_pos_3d", "kinds_in_data")
    return {"dir": out, "wall_seconds": results.get("wall_seconds"), "sweep": results.get("sweep"),
            "wind_sweep": results.get("wind_sweep"),
            "conditions": {c: {k: e[k] for k in keys if k in e} for c, e in results["conditions"].items()}}


def _other_truths(args: OutdoorArgs) -> dict:
    """The whole experiment on each truth of --sweep-fields (one Ray task each, or in turn with --workers 1)."""
    from downwash.sweep import map_on_ray

    jobs = [dataclasses.replace(args, field=spec, out=str(Path(args.out) / "truths" / _slug(spec)), sweep_fields="")
            for spec in _items(args.sweep_fields)]
    done = [_truth_task(a) for a in jobs] if args.workers == 1 and not args.address else map_on_ray(
        _truth_task, jobs, args.workers, args.address)
    return {a.field: _truth_summary(r, a.out) for a, r in zip(jobs, done)}


def _truth_task(args: OutdoorArgs) -> dict:
    """One truth's whole experiment (a Ray task): its results."""
    setup_logging()
    return run(args)


def _slug(spec: str) -> str:
    """A folder name for a field spec."""
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in spec)


def _outdoor_models(args: OutdoorArgs, p: Any, kinds: list[str]) -> dict:
    """The outdoor stages beside the pipeline's collection (keyed by their provenance) and the kinds
    trained on indoor + outdoor flights, collected and trained when missing."""
    from downwash.outdoor_collection import OutdoorCollectionConfig, collect_outdoor, outdoor_provenance
    from downwash.staged import DEPLOYED_KIND, ensure_models
    from downwash_core.provenance import fingerprint

    cfg = OutdoorCollectionConfig(stage_minutes=args.outdoor_minutes, seed=args.seed, quick=args.quick,
                                  threads=p.config.threads)
    out = p.collection_dir.parent / f"outdoor-{fingerprint(outdoor_provenance(cfg, p.record))}"
    deployed = ensure_models(p.models_dir, [DEPLOYED_KIND], p.collection_dir, p.config, p.field, ProgressBar)
    made = collect_outdoor(cfg, out, p.collection_dir, p.record, p.field, kinds, deployed[DEPLOYED_KIND], ProgressBar)
    return {**made, "dir": str(out)}


def _airspeed(per_condition: dict) -> dict[str, float]:
    """The leader's airspeed |v - u_air| over every flight (m/s): what weakens and tilts its wake."""
    speeds = []
    for logs in per_condition.values():
        for L in logs:
            vel = L["vel"][:, L.meta["leader"]]
            air = L["wind"][:, L.meta["leader"]] if "wind" in L.arrays else np.zeros_like(vel)  # logged with wind on
            speeds.append(np.linalg.norm(vel - air, axis=-1))
    s = np.concatenate(speeds)
    return {"mean": float(s.mean()), "min": float(s.min()), "max": float(s.max())}


def _table(results: dict, wind_spec: str) -> str:
    rows = []
    for c, e in results["conditions"].items():
        rows.append([c, e["pos_err_3d_mean"], e["pos_err_z_mean"], e["pos_err_3d_peak"],
                     f"{100 * e['improvement_pos_3d']:.1f}%" if "improvement_pos_3d" in e else "-",
                     f"{e['gap_to_oracle_pos_3d']:+.4f}" if "gap_to_oracle_pos_3d" in e else "-",
                     f"{100 * e['crash_rate']:.0f}%"])
    a = results["leader_airspeed"]
    wind = "no wind" if results["wind"] is None else f"wind {wind_spec}"
    head = (f"\noutdoor: leader on a {results['leader']} at {results['speed']} m/s (airspeed {a['min']:.2f}-"
            f"{a['max']:.2f} m/s), {wind}, {len(results['seeds'])} seeds, {results['duration']:.0f} s")
    return head + "\n" + format_table(rows, ["condition", "pos3d m", "posz m", "peak3d m", "impr 3d", "gap oracle m",
                                             "crashed"])


def _figure(out: Path, per_condition: dict, results: dict) -> None:
    import matplotlib

    from sim.metrics import tracking_errors

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    for c, logs in per_condition.items():
        ax.plot(logs[0]["t"], tracking_errors(logs[0])["pos_3d"], label=c, lw=1.1)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("|e| pos 3D (m)")
    ax.legend(ncol=4, fontsize=8)
    ax.set_title(f"outdoor: {results['leader']} at {results['speed']} m/s, seed {results['seeds'][0]}")
    fig.tight_layout()
    fig.savefig(out / "errors_over_time.png", dpi=110)
    plt.close(fig)


def _speed_figure(out: Path, results: dict, truth: str) -> None:
    """Each condition's improvement over the baseline against the leader's speed (--sweep-speeds), one
    panel per ground truth (--sweep-fields)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truths = {spec: t["sweep"] for spec, t in results.get("truths", {}).items() if t.get("sweep")}
    panels = truths or {truth: results["sweep"]}
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 3.8), squeeze=False)
    for ax, (spec, sweep) in zip(axes[0], panels.items()):
        for c, e in sweep["conditions"].items():
            if c in ("no_downwash", "baseline"):
                continue
            ax.plot(sweep["speeds"], [100 * (x if x is not None else np.nan) for x in e["improvement_pos_3d"]], "o-",
                    label=c, lw=1.1)
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel("leader speed (m/s)")
        ax.set_ylabel("improvement of 3D error over baseline (%)")
        ax.set_ylim(max(ax.get_ylim()[0], -150.0), 100.0)
        ax.set_title(f"truth {spec}: leader on a {results['leader']}, {len(results['seeds'])} seeds per point", fontsize=9)
    axes[0][-1].legend(ncol=2, fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "improvement_vs_speed.png", dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    args = parse_args(OutdoorArgs, "outdoor", argv, __doc__)
    with out_lock(args, "outdoor"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
