"""The tracking experiments, one table-driven entry: every condition on the same seeds, in one batch.

    python -m experiments.lemniscate [--conditions baseline,oracle] [--seeds 5] [--quick]
    python -m experiments.transect   [--conditions baseline,oracle] [--seeds 5] [--quick]
    python -m experiments.lemniscate --video flight.mp4   # also an mp4 of the first seed, conditions side by side

Paper section 5: Alpha hovers at 2.5 m; Bravo flies beneath it. `TRACKS` holds each
experiment's reference and its shape options (each becomes a command-line flag);
the conditions are those of `downwash.conditions`. Writes results.json,
prints a table and saves the figures beside it. `--video PATH` also writes
an mp4 of every condition's first seed side by side, the leader's wake drawn
(`downwash_envs.video`; needs `pip install -e ".[video]"` and an OpenGL backend, checked before
any flight).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from downwash_core.params import LEADER_POSITION, SEPARATION_RANGE
from experiments.common import (CONDITIONS, DEFAULT_CONDITIONS, FLIGHT_SECONDS_MAX, SEED_COUNT_MAX, WIND_HELP,
                                FlightArgs, ProgressBar, arg, check_options, format_table, load_wind, names_check,
                                out_lock, parse_args, resolve_pipeline, seed_count_check, setup_logging, wind_check,
                                write_results)
from experiments.components import check_controller, flight_components, flown_record, guard_config

__all__ = ["TRACKS", "TrackingArgs", "run", "main"]

LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here (paper: 2.5 m up)


@dataclass(frozen=True)
class Track:
    """One tracking experiment: the follower's reference and its shape options."""

    doc: str  # the experiment's description (its --help)
    reference: str  # a name of `downwash_trajectories.make_reference`
    period: float  # s, one period: the default flight length
    shape: dict[str, tuple[float, str, dict[str, float]]]  # option -> (default, help, range), passed to the reference


TRACKS = {
    "lemniscate": Track(
        "Lemniscate (figure-eight) beneath a hovering leader, every condition on the same seeds. Its crossing "
        "point lies directly beneath Alpha, so Bravo passes through the wake twice per period.",
        "lemniscate", 20.0,
        {"half_length": (1.0, "half extent of the figure-eight along x, m", {"gt": 0.0, "le": 10.0}),
         "half_width": (0.5, "half extent along y, m", {"gt": 0.0, "le": 10.0})},
    ),
    "transect": Track(
        "Transect: back and forth along y at x = 0.2 m beneath a hovering leader (the paper's translation "
        "experiment), every condition on the same seeds.",
        "transect", 12.0,
        {"x_offset": (0.2, "lateral offset of the transect line from the leader, m", {"ge": -10.0, "le": 10.0}),
         "half_length": (1.2, "half length of the transect along y, m", {"gt": 0.0, "le": 10.0})},
    ),
}


@dataclass(frozen=True)
class TrackingArgs(FlightArgs):
    # the flights' controller and simulator settings, and the guard's of the guarded conditions (the staged
    # collection behind the models flies the defaults)

    conditions: str = arg(",".join(DEFAULT_CONDITIONS), "comma list of " + ", ".join(CONDITIONS), check=names_check(CONDITIONS))
    seeds: int = arg(10, f"number of seeds (flights per condition, at most {SEED_COUNT_MAX})", ge=1,
                     check=seed_count_check, quick=1)
    separation: float = arg(0.6, "vertical separation below the leader, m", ge=SEPARATION_RANGE[0], le=SEPARATION_RANGE[1])
    duration: float = arg(0.0, "flight length, s (0: one period of the reference)", ge=0.0, le=FLIGHT_SECONDS_MAX,
                          quick=2.0)
    wind: str = arg("off", WIND_HELP, check=wind_check)
    video: str = arg("", "also write an mp4 of the first seed of every condition, side by side with the wake "
                         "drawn, to this path (.mp4; needs pip install -e '.[video]')", output="file")


def args_class(track: str) -> type:
    """TrackingArgs plus the track's shape options."""
    fields = [(name, float, arg(default, help_text, **bounds))
              for name, (default, help_text, bounds) in TRACKS[track].shape.items()]
    return dataclasses.make_dataclass(f"{track.title()}Args", fields, bases=(TrackingArgs,), frozen=True)


def _validate(args: TrackingArgs) -> list[str]:
    """Check every option before any flight starts (parse_args has; again here for options built in
    Python); returns the condition list."""
    from downwash.conditions import parse_conditions

    check_options(args)
    return check_controller(args, parse_conditions(args.conditions))


def run(track: str, args: Any) -> dict:
    """Fly every condition x seed in one batch; write results.json and figures into args.out."""
    from downwash.conditions import fly_conditions, guard_record, kinds_in_data, learned
    from downwash.staged import ensure_models
    from downwash_trajectories import Hover, make_reference, stack
    from sim.metrics import aggregate_conditions
    from sim.scene import build_scene

    spec = TRACKS[track]
    conditions = _validate(args)
    components, guard = flight_components(args), guard_config(args)  # the tables, checked before any flight
    wind = load_wind(args.wind)
    scene = build_scene()
    if args.video:
        from downwash_envs.video import check_video_output  # imageio and an OpenGL context only when asked for

        check_video_output(args.video, scene)
    p = resolve_pipeline(args, models=learned(conditions))
    field = p.field
    checkpoints = ensure_models(p.models_dir, learned(conditions), p.collection_dir, p.config, field, ProgressBar)
    t_start = time.perf_counter()
    K = args.seeds
    W = len(conditions) * K
    duration = args.duration or spec.period
    center = LEADER - np.array([0.0, 0.0, args.separation])
    shape = {name: getattr(args, name) for name in spec.shape}
    follower = make_reference(spec.reference, center, W, period=spec.period, **shape)
    reference = stack([Hover(LEADER, n_worlds=W), follower])
    seeds = list(range(args.seed, args.seed + K))
    per_condition = fly_conditions(scene, conditions, reference, seeds, duration, field, checkpoints,
                                   meta={"experiment": track}, guard=guard, wind=wind, **components)
    flight_seconds = time.perf_counter() - t_start

    results: dict[str, Any] = {"experiment": track, "separation": args.separation, "duration": duration,
                               "seeds": seeds, "conditions": aggregate_conditions(per_condition),
                               "guard": guard_record(conditions, guard)}  # the settings flown
    for c, inside in kinds_in_data(conditions, checkpoints, scene).items():  # (the guard's retention criterion)
        results["conditions"][c]["kinds_in_data"] = inside
    results["wall_seconds"] = time.perf_counter() - t_start
    results["flight_wall_seconds"] = flight_seconds
    out = Path(args.out)
    flown = flown_record(args, components)  # what made the numbers
    path = write_results(out, results, args, {**(p.provenance() if checkpoints else {}), **flown})
    _figures(out, track, per_condition)
    print(_table(track, results))
    print(f"\nwrote {path} and figures in {out}/")
    if args.video:
        _video(args.video, scene, per_condition, field)
    return results


def _video(path: str, scene, per_cond_logs: dict, field) -> None:
    """The first seed of every condition side by side (at most 4 per row), the wake drawn."""
    from downwash_envs.video import logs_video

    t0 = time.perf_counter()
    n = logs_video(path, scene, {c: clogs[0] for c, clogs in per_cond_logs.items()}, field=field,
                   columns=min(len(per_cond_logs), 4))
    print(f"wrote {path} ({n} frames, seed {next(iter(per_cond_logs.values()))[0].meta['seed']}, "
          f"{time.perf_counter() - t0:.1f} s)")


def main(track: str, argv=None) -> dict:
    setup_logging()
    args = parse_args(args_class(track), track, argv, TRACKS[track].doc)
    with out_lock(args, track):
        return run(track, args)


def _table(name: str, results: dict) -> str:
    rows = []
    for c, e in results["conditions"].items():
        rows.append([
            c, e["pos_err_3d_mean"], e["pos_err_xy_mean"], e["pos_err_z_mean"], e["pos_err_3d_peak"], e["vel_err_3d_mean"],
            f"{100 * e['improvement_pos_3d']:.1f}%" if "improvement_pos_3d" in e else "-",
            f"{100 * e['improvement_pos_z']:.1f}%" if "improvement_pos_z" in e else "-",
            f"{e['gap_to_oracle_pos_3d']:+.4f}" if "gap_to_oracle_pos_3d" in e else "-",
            f"{100 * e['crash_rate']:.0f}%",
        ])
    header = ["condition", "pos3d m", "posxy m", "posz m", "peak3d m", "vel3d m/s", "impr 3d", "impr z", "gap oracle m",
              "crashed"]
    sep = results["separation"]
    return f"\n{name}: {len(results['seeds'])} seeds, separation {sep} m, {results['duration']:.1f} s\n" + format_table(rows, header)


COLORS = {"no_downwash": "0.5", "baseline": "tab:red", "oracle": "k", "shallow": "tab:orange",
          "deep": "tab:blue", "equivariant": "tab:green", "equivariant_general": "tab:purple"}


def _figures(out: Path, name: str, per_cond_logs: dict) -> None:
    import matplotlib

    from sim.metrics import tracking_errors

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # errors over time (first seed), position and velocity, vertical and 3D, as the paper's fig. 6
    fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    keys = [("pos_z", "|e_z| pos (m)"), ("vel_z", "|e_z| vel (m/s)"), ("pos_3d", "|e| pos 3D (m)"), ("vel_3d", "|e| vel 3D (m/s)")]
    for c, clogs in per_cond_logs.items():
        e = tracking_errors(clogs[0])
        for ax, (k, label) in zip(axes, keys):
            ax.plot(clogs[0]["t"], e[k], color=COLORS.get(c), label=c, lw=1.2)
            ax.set_ylabel(label)
    axes[0].legend(ncol=3, fontsize=8)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(f"{name}: tracking errors over time (seed {clogs[0].meta['seed']})")
    fig.tight_layout()
    fig.savefig(out / "errors_over_time.png", dpi=110)
    plt.close(fig)

    # error distributions over all seeds
    fig, axes = plt.subplots(1, 4, figsize=(12, 3.5))
    for ax, (k, label) in zip(axes, keys):
        data = [np.concatenate([tracking_errors(L)[k] for L in clogs]) for clogs in per_cond_logs.values()]
        parts = ax.violinplot(data, showmeans=True)
        for body, c in zip(parts["bodies"], per_cond_logs):
            body.set_facecolor(COLORS.get(c))
        ax.set_xticks(range(1, len(data) + 1), list(per_cond_logs), rotation=45, fontsize=8)
        ax.set_title(label, fontsize=9)
    fig.suptitle(f"{name}: error distributions (all seeds)")
    fig.tight_layout()
    fig.savefig(out / "error_distributions.png", dpi=110)
    plt.close(fig)

    # flown path beside the reference (first seed), top and side views
    fig, (top, side) = plt.subplots(1, 2, figsize=(11, 4.5))
    first = next(iter(per_cond_logs.values()))[0]
    f, lead = first.meta["follower"], first.meta["leader"]
    top.plot(first["ref_pos"][:, f, 0], first["ref_pos"][:, f, 1], "k--", lw=1, label="reference")
    side.plot(first["ref_pos"][:, f, 1], first["ref_pos"][:, f, 2], "k--", lw=1, label="reference")
    for c, clogs in per_cond_logs.items():
        p = clogs[0]["pos"][:, f]
        top.plot(p[:, 0], p[:, 1], color=COLORS.get(c), lw=1, label=c)
        side.plot(p[:, 1], p[:, 2], color=COLORS.get(c), lw=1)
    p_lead = first["pos"][0, lead]
    top.plot(p_lead[0], p_lead[1], "k^", ms=9, label="leader")
    top.set_xlabel("x (m)"), top.set_ylabel("y (m)"), top.axis("equal"), top.legend(fontsize=8)
    side.set_xlabel("y (m)"), side.set_ylabel("z (m)")
    side.set_title("side view (y-z)", fontsize=9), top.set_title("top view", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "paths.png", dpi=110)
    plt.close(fig)
