"""Many vehicles: does summing two-vehicle models hold up, and what do models of sets learn?

    python -m experiments.swarm [--presets stack3,stack4,swap,formation5,...] [--aggregations linear,velocity]
                                [--seeds 10] [--quick] [--video swarm.mp4]

The paper's section 6 asks how downwash models carry over to many vehicles. For each
aggregation law of the ground truth (`sim.aggregation`: how the wakes of several
vehicles combine) this experiment
1. reuses the two-vehicle staged collection and its equivariant model (the lemniscate experiment's);
2. runs the swarm stages (`downwash.swarm_collection`: stacks of 3, then 4, vehicles,
   flown with the models so far) and the stages of other vehicle kinds, and trains the models
   of sets on the two-vehicle data only ("pair"), on all of it ("mixed"), and on all of it
   reading each vehicle's kind ("kinds");
3. flies every preset (`sim.presets`) with the conditions on the same seeds, in one
   batch per preset and law: baseline (no model), oracle (the true mean wake, combined
   by the law), summed_pairwise (the paper's two-vehicle equivariant model summed over
   neighbours), and deepsets_equivariant / deepsets from each data mix; then each learned
   condition behind the guard (`<condition>_guarded`, `downwash.guard`).
Metrics are taken over every follower of a flight (`sim.metrics.follower_metrics`). The
presets of other vehicle kinds (`heavy_over_light`, `crazyflie_stack`, `mixed_formation`)
ask whether the models carry over to other forces, and what knowing the kinds is worth;
each preset records how strong its wakes are: the mean magnitude of the true mean field on
its followers in the baseline flights (`force_mean`, m/s^2).
Writes `<out>/<preset>/results.json` and a figure per preset, and `<out>/results.json`
with all of them and the summary: per law and preset, each model's improvement over
the baseline and gap to the oracle.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from experiments.common import (AGGREGATIONS, FLIGHT_SECONDS_MAX, PRESETS, SEED_COUNT_MAX, FlightArgs, ProgressBar,
                                arg, check_options, format_table, out_lock, parse_args, resolve_pipeline, run_main,
                                seed_count_check, setup_logging, write_results, script)
from experiments.components import check_controller, flight_components, flown_record, guard_config

__all__ = ["SwarmArgs", "conditions", "run", "main"]

DEFAULT_PRESETS = "stack3,stack4,swap,formation5,heavy_over_light,crazyflie_stack,mixed_formation"


def conditions() -> list[str]:
    """baseline, oracle, summed_pairwise, then each trainable kind of sets from each data mix; then each
    learned one behind the guard (`downwash.guard`, "<condition>_guarded"); then the LQR with integral action,
    the disturbance observer, and each learned one with the observer on its residual ("<condition>_dob")."""
    from downwash.conditions import GUARDED, OBSERVED, UNLEARNED
    from downwash.swarm_collection import DATA_MIXES, TRAINABLE_SET_KINDS

    models = ["summed_pairwise"] + [f"{k}-{m}" for k in TRAINABLE_SET_KINDS for m in DATA_MIXES]
    return ["baseline", "oracle"] + models + [c + GUARDED for c in models] + list(UNLEARNED) + [c + OBSERVED for c in models]


def _specs_check(label: str, names: Sequence[str], notes: str = "") -> Any:
    """A `check` for a comma list of NAME[:KEY=VALUE,...] specs whose NAME is one of `names` (a plugin's
    preset included: `experiments.options.RegisteredNames`), run while parsing (before the stack is
    imported); the parameters are checked when the specs are built. notes: added to the allowed names."""

    def check(text: str) -> str | None:
        try:
            items = _split(text)
        except ValueError as e:
            return str(e)
        unknown = [spec for spec in items if spec.partition(":")[0].strip() not in names]
        return f"{label}: unknown {unknown[0]!r}; allowed: {', '.join(names)}{notes}" if unknown else None

    return check


@dataclass(frozen=True)
class SwarmArgs(FlightArgs):
    # the flights' controller, simulator and guard settings (the swarm stages, like the staged collection,
    # fly the defaults)

    presets: str = arg(DEFAULT_PRESETS, f"comma list of presets: {', '.join(PRESETS)} (stack:n=N takes N = 2-8, "
                                        "and spacing=)",
                       check=_specs_check("preset", PRESETS, " (stack takes n=2-8, spacing=; heavy_over_light "
                                                             "separation=)"))
    aggregations: str = arg("linear,velocity", "comma list of aggregation laws of the ground truth "
                                               f"({', '.join(AGGREGATIONS)}, with optional :KEY=VALUE)",
                            check=_specs_check("aggregation", AGGREGATIONS))
    seeds: int = arg(10, f"flights per condition, preset and law (at most {SEED_COUNT_MAX}; a crash rate is "
                         "reported with its Wilson interval)", ge=1,
                     check=seed_count_check, quick=1)
    duration: float = arg(0.0, "flight length, s (0: the preset's, at least 10 s)", ge=0.0, le=FLIGHT_SECONDS_MAX)
    swarm_minutes: float = arg(2.0, "training minutes per swarm stage (3, then 4 vehicles)", gt=0.0, le=60.0)
    video: str = arg("", "also write an mp4 of the first preset and law, the first seed of every condition side by "
                         "side with the wakes drawn (.mp4; needs pip install -e '.[video]')", output="file")


def _split(text: str) -> list[str]:
    """A comma list of specs whose parameters may hold commas: 'linear,shielding:eta=0.8,radius=0.3'
    is ['linear', 'shielding:eta=0.8,radius=0.3'] (a KEY=VALUE part belongs to the spec before it).
    ValueError for an empty list or one that names a spec twice."""
    items: list[str] = []
    for part in (x.strip() for x in text.split(",")):
        if items and "=" in part and ":" not in part:
            items[-1] += "," + part
        elif part:
            items.append(part)
    if not items:
        raise ValueError("expected a comma list")
    if len(set(items)) != len(items):
        raise ValueError("expected each at most once")
    return items


def _validate(args: SwarmArgs) -> tuple[list, list]:
    from sim.aggregation import make_aggregation
    from sim.presets import make_preset

    check_options(args)  # parse_args has; again for options built in Python
    check_controller(args)
    try:
        presets = [make_preset(p) for p in _split(args.presets)]  # ConfigError for a bad parameter (N)
        for p in presets:  # vehicles inside each other are named before any flight
            p.reference(1)
    except ConfigError as e:
        raise ConfigError(f"--presets: {e}") from e
    try:
        laws = [(a, make_aggregation(a)) for a in _split(args.aggregations)]
    except ConfigError as e:
        raise ConfigError(f"--aggregations: {e}") from e
    return presets, laws


def _model_paths(names: list[str], pair_model: Path, models_dir: Path, pair_models_dir: Path) -> dict[str, Path]:
    """{model: its checkpoint} of every learned condition's model ("<kind>-<mix>", "summed_pairwise")."""
    from downwash.conditions import UNLEARNED, model_of
    from downwash.swarm_collection import swarm_model_path

    out = {}
    for model in dict.fromkeys(model_of(c) for c in names if c not in ("baseline", "oracle", *UNLEARNED)):
        if model == "summed_pairwise":
            out[model] = pair_model
        else:
            kind, mix = model.rsplit("-", 1)
            out[model] = swarm_model_path(pair_models_dir if mix == "pair" else models_dir, kind, mix)
    return out


def _predictors(names: list[str], field: Any, law: Any, paths: dict[str, Path], neighbours,
                guard: dict[str, float], controller: Any = None) -> list:
    from downwash.checkpoint import wrap_pairwise
    from downwash.conditions import make_predictor
    from downwash.predictor import LearnedPredictor

    def load(model: str) -> Any:  # a set model of its neighbours, or the pair model summed over them
        if model == "summed_pairwise":  # assumes linear superposition: flown under every law, by design
            return LearnedPredictor(wrap_pairwise(paths[model], neighbours, expect_kind="equivariant"))
        mix = model.rsplit("-", 1)[1]
        return LearnedPredictor(paths[model], expect_neighbours=neighbours,
                                expect_aggregation=None if mix == "pair" else law)

    return [make_predictor(c, field, guard=guard, aggregation=law, load=load, controller=controller) for c in names]


def run(args: SwarmArgs) -> dict:
    from downwash.conditions import fly_predictors, guard_record, kinds_in_data
    from downwash.staged import ensure_models
    from downwash.swarm_collection import SwarmCollectionConfig, collect_swarm, pair_models_key, swarm_provenance
    from downwash_core.provenance import describe, fingerprint
    from sim.metrics import aggregate_conditions, follower_metrics

    presets, laws = _validate(args)
    components, guard = flight_components(args), guard_config(args)  # the tables, checked before any flight
    if args.video:
        from downwash_envs.video import check_video_output  # imageio and an OpenGL context only when asked for

        check_video_output(args.video, presets[0].scene())
    p = resolve_pipeline(args)
    pair_model = ensure_models(p.models_dir, ["equivariant"], p.collection_dir, p.config, p.field,
                               ProgressBar)["equivariant"]
    cfg = SwarmCollectionConfig(stage_minutes=args.swarm_minutes, seed=args.seed, quick=args.quick)
    t_start = time.perf_counter()
    names = conditions()
    K = args.seeds
    seeds = list(range(args.seed, args.seed + K))
    out = Path(args.out)
    guarded = guard_record(names)  # the guard's settings, as flown
    results: dict[str, Any] = {"experiment": "swarm", "seeds": seeds, "conditions": names, "laws": {}, "presets": {},
                               "guard": None if guarded is None else {**guarded, **guard}}
    first_logs = None
    pair_models_dir = p.collection_dir.parent / f"swarm-pair-{pair_models_key(cfg, p.record)}"  # shared by every law
    for law_name, law in laws:
        record = swarm_provenance(cfg, law, p.record)
        swarm_dir = p.collection_dir.parent / f"swarm-{law.name}-{fingerprint(record)}"
        collected = collect_swarm(cfg, swarm_dir, p.collection_dir, pair_model, p.record, p.field, law,
                                  pair_models_dir, ProgressBar)
        results["laws"][law_name] = {"law": describe(law), "collection_dir": str(swarm_dir),
                                     "models": collected["models"], "stages": collected["stages"]}
        paths = _model_paths(names, pair_model, swarm_dir / "models", pair_models_dir)
        predictors = _predictors(names, p.field, law, paths, cfg.neighbours, guard, components["controller"])
        for preset in presets:
            duration = args.duration or (2.0 if args.quick else max(preset.duration, 10.0))
            W = len(names) * K
            scene = preset.scene()
            per_condition = fly_predictors(scene, names, predictors, preset.reference(W), seeds, duration,
                                           meta={"experiment": "swarm", "preset": preset.name}, field=p.field,
                                           aggregation=law, **components,
                                           progress=ProgressBar(f"{preset.name}, {law_name}"))
            kinds = kinds_in_data(names, paths, scene)
            first_logs = first_logs or (preset, per_condition)
            entry = {"preset": preset.describe(), "law": law_name, "duration": duration, "seeds": seeds,
                     "force_mean": _force_mean(per_condition["baseline"]),
                     "conditions": aggregate_conditions(per_condition, metrics=follower_metrics)}
            for c, inside in kinds.items():
                entry["conditions"][c]["kinds_in_data"] = inside
            results["presets"].setdefault(preset.name, {})[law_name] = entry
    results["summary"] = _summary(results)
    results["force_mean"] = {law: {preset: by_law[law]["force_mean"] for preset, by_law in results["presets"].items()}
                             for law in results["summary"]}  # law -> preset -> m/s^2 (baseline flights)
    results["wall_seconds"] = time.perf_counter() - t_start
    provenance = {**p.provenance(), **flown_record(args, components)}
    for name, by_law in results["presets"].items():  # one results.json per preset
        write_results(out / name.replace(":", "_"), {"experiment": "swarm", "preset": name, "laws": by_law}, args,
                      provenance)
        _figure(out / name.replace(":", "_"), name, by_law)
    path = write_results(out, results, args, provenance)
    print(_table(results))
    print(f"\nwrote {path} and one folder per preset in {out}/")
    if args.video and first_logs is not None:
        from downwash_envs.video import logs_video

        preset, per_condition = first_logs
        n = logs_video(args.video, preset.scene(), {c: L[0] for c, L in per_condition.items()}, field=p.field,
                       columns=min(len(per_condition), 4))
        print(f"wrote {args.video} ({n} frames)")
    return results


def _force_mean(logs: Sequence[Any]) -> float:
    """m/s^2, the mean magnitude of the true mean field on the followers over the flights (their
    finite rows): how strong a preset's wakes are where its vehicles fly."""
    norms = []
    for log in logs:
        followers = [v for v, role in enumerate(log.meta["roles"]) if role != "leader"]
        f = np.linalg.norm(log["field_mean"][:, followers], axis=-1)
        norms.append(f[np.isfinite(f)])
    return float(np.mean(np.concatenate(norms)))


def _summary(results: dict) -> dict:
    """law -> preset -> condition -> (improvement over baseline, gap to the oracle), the README's question."""
    out: dict = {}
    for preset, by_law in results["presets"].items():
        for law, entry in by_law.items():
            out.setdefault(law, {})[preset] = {
                c: {"improvement_pos_3d": e.get("improvement_pos_3d"), "gap_to_oracle_pos_3d": e.get("gap_to_oracle_pos_3d"),
                    "pos_err_3d_mean": e["pos_err_3d_mean"], "crash_rate": e["crash_rate"],
                    "crash_rate_ci95": e.get("crash_rate_ci95"),
                    **({"kinds_in_data": e["kinds_in_data"]} if "kinds_in_data" in e else {}),
                    **({"compensation": e["compensation"]} if "compensation" in e else {})}
                for c, e in entry["conditions"].items()}
    return out


def _table(results: dict) -> str:
    lines = []
    for law, by_preset in results["summary"].items():
        rows = [[preset] + [_cell(e.get(c, {})) for c in results["conditions"][1:]] for preset, e in by_preset.items()]
        lines.append(f"\n{law} aggregation: improvement of the followers' 3D error over the baseline (gap to oracle, m)")
        lines.append(format_table(rows, ["preset"] + results["conditions"][1:]))
    return "\n".join(lines)


def _cell(e: dict) -> str:
    imp, gap = e.get("improvement_pos_3d"), e.get("gap_to_oracle_pos_3d")
    return ("-" if imp is None else f"{imp:+.0%}") + ("" if gap is None else f" ({gap:+.3f})")


def _figure(out: Path, preset: str, by_law: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    laws = list(by_law)
    names = list(next(iter(by_law.values()))["conditions"])
    fig, ax = plt.subplots(figsize=(9, 3.8))
    width = 0.8 / len(laws)
    for j, law in enumerate(laws):
        values = [by_law[law]["conditions"][c]["pos_err_3d_mean"] for c in names]
        ax.bar(np.arange(len(names)) + j * width, values, width, label=f"{law} aggregation")
    ax.set_xticks(np.arange(len(names)) + 0.4 - width / 2, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("followers' mean 3D error (m)")
    ax.set_title(f"{preset}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "errors.png", dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    args = parse_args(SwarmArgs, "swarm", argv, __doc__)
    with out_lock(args, "swarm"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
