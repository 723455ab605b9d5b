"""Shared body of the tracking experiments (lemniscate, transect): conditions in one batch.

Every condition flies the same seeds, so the same motion-capture noise and
turbulence draws: worlds differ only in the predictor (and, for `no_downwash`,
in the field being off).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from experiments.common import CommonArgs, arg, format_table, load_field, write_results
from sim.flight import fly
from sim.params import LEADER_POSITION, SEPARATION_RANGE
from sim.metrics import IMPROVEMENT_METRICS, TRACKING_METRICS, improvement, tracking_errors, tracking_metrics
from sim.predictor import OraclePredictor, PerWorldPredictor, ZeroPredictor
from sim.scene import build_scene

__all__ = ["CONDITIONS", "LEARNED", "TrackingArgs", "run_tracking"]

log = logging.getLogger(__name__)

CONDITIONS = ("no_downwash", "baseline", "oracle", "shallow", "deep", "equivariant")
LEARNED = ("shallow", "deep", "equivariant")
LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here (paper: 2.5 m up)


@dataclass(frozen=True)
class TrackingArgs(CommonArgs):
    conditions: str = arg("no_downwash,baseline,oracle,shallow,deep,equivariant", "comma list of " + ", ".join(CONDITIONS))
    seeds: int = arg(5, "number of seeds (flights per condition)")
    separation: float = arg(0.6, f"vertical separation below the leader, m ({SEPARATION_RANGE[0]}-{SEPARATION_RANGE[1]})")
    models_dir: str = arg("runs/models", "where trained models are read (staged collection runs first if missing)")
    duration: float = arg(0.0, "flight length, s (0: one period of the reference)")


def parse_conditions(text: str) -> list[str]:
    names = [c.strip() for c in text.split(",") if c.strip()]
    if not names:
        raise ValueError(f"--conditions: expected a comma list of {', '.join(CONDITIONS)}, got {text!r}")
    unknown = [c for c in names if c not in CONDITIONS]
    if unknown:
        raise ValueError(f"--conditions: unknown {unknown}; allowed: {', '.join(CONDITIONS)}")
    if len(set(names)) != len(names):
        raise ValueError(f"--conditions: duplicate names in {names}")
    return names


def validate(args: TrackingArgs) -> list[str]:
    """Check every option before any flight starts; returns the condition list."""
    conditions = parse_conditions(args.conditions)
    lo, hi = SEPARATION_RANGE
    if not lo <= args.separation <= hi:
        raise ValueError(f"--separation: {args.separation} m is out of range; allowed {lo}-{hi} m")
    if args.seeds < 1:
        raise ValueError(f"--seeds: expected >= 1, got {args.seeds}")
    if args.duration < 0:
        raise ValueError(f"--duration: expected >= 0 s, got {args.duration}")
    return conditions


def _learned_predictors(conditions: list[str], args: TrackingArgs, field: Any) -> dict[str, Any]:
    """Load the learned models, running the staged collection first when any is missing."""
    wanted = [c for c in conditions if c in LEARNED]
    if not wanted:
        return {}
    from downwash.predictor import LearnedPredictor
    from experiments import staged_collection

    models_dir = Path(args.models_dir)
    missing = [c for c in wanted if not (models_dir / f"{c}.pt").is_file()]
    if missing:
        log.info("models %s missing in %s: running the staged collection first", missing, models_dir)
        staged_collection.run(staged_collection.StagedArgs(
            out=str(models_dir.parent / "staged_collection"), seed=args.seed, quick=args.quick,
            field=args.field, models_dir=str(models_dir),
        ), field=field)
    return {c: LearnedPredictor.from_checkpoint(models_dir / f"{c}.pt") for c in wanted}


def run_tracking(
    name: str,
    args: TrackingArgs,
    make_reference: Callable[[np.ndarray, int], Any],
    period: float,
) -> dict:
    """Fly every condition x seed in one batch; write results.json and figures into args.out.

    make_reference(center, n_worlds) -> the follower's reference; `center` is the point
    `separation` below the leader.
    """
    conditions = validate(args)
    field = load_field(args.field)
    predictors = _learned_predictors(conditions, args, field)
    t_start = time.perf_counter()

    K = args.seeds
    W = len(conditions) * K
    duration = args.duration or period
    from controllers.references import Hover, stack

    center = LEADER - np.array([0.0, 0.0, args.separation])
    reference = stack([Hover(LEADER, n_worlds=W), make_reference(center, W)])
    by_condition = []
    for c in conditions:
        if c in ("no_downwash", "baseline"):
            by_condition.append(ZeroPredictor())
        elif c == "oracle":
            by_condition.append(OraclePredictor(field))
        else:
            by_condition.append(predictors[c])
    predictor = PerWorldPredictor(by_condition, np.repeat(np.arange(len(conditions)), K))
    seeds = [args.seed + k for _ in conditions for k in range(K)]
    field_enabled = np.array([c != "no_downwash" for c in conditions for _ in range(K)])
    meta = [{"condition": c, "experiment": name} for c in conditions for _ in range(K)]
    logs = fly(
        build_scene(), reference, seeds, duration, field=field, predictor=predictor,
        field_enabled=field_enabled, meta=meta,
    )
    flight_seconds = time.perf_counter() - t_start

    results: dict[str, Any] = {"experiment": name, "separation": args.separation, "duration": duration,
                               "seeds": list(range(args.seed, args.seed + K)), "conditions": {}}
    per_cond_logs = {c: logs[i * K:(i + 1) * K] for i, c in enumerate(conditions)}
    for c, clogs in per_cond_logs.items():
        per_seed = [tracking_metrics(L) for L in clogs]
        entry: dict[str, Any] = {m: float(np.mean([p[m] for p in per_seed])) for m in TRACKING_METRICS}
        entry["per_seed"] = {m: [p[m] for p in per_seed] for m in TRACKING_METRICS}
        entry["failed_flights"] = [L.meta["message"] for L in clogs if not L.ok]
        results["conditions"][c] = entry
    if "baseline" in per_cond_logs:
        base = results["conditions"]["baseline"]["per_seed"]
        for c, entry in results["conditions"].items():
            if c in ("baseline", "no_downwash"):
                continue
            imps = [improvement({m: entry["per_seed"][m][k] for m in TRACKING_METRICS},
                                {m: base[m][k] for m in TRACKING_METRICS}) for k in range(K)]
            for key in IMPROVEMENT_METRICS:
                entry["per_seed"][key] = [i[key] for i in imps]
                entry[key] = float(np.mean(entry["per_seed"][key]))
        if "oracle" in results["conditions"]:
            oracle = results["conditions"]["oracle"]["pos_err_3d_mean"]
            for c in LEARNED:
                if c in results["conditions"]:
                    # learned-versus-oracle gap: how much larger the learned error is than the oracle's
                    results["conditions"][c]["gap_to_oracle_pos_3d"] = results["conditions"][c]["pos_err_3d_mean"] - oracle
    results["wall_seconds"] = time.perf_counter() - t_start
    results["flight_wall_seconds"] = flight_seconds

    out = Path(args.out)
    path = write_results(out, results, args)
    _figures(out, name, per_cond_logs)
    print(_table(name, results))
    print(f"\nwrote {path} and figures in {out}/")
    return results


def _table(name: str, results: dict) -> str:
    rows = []
    for c, e in results["conditions"].items():
        rows.append([
            c, e["pos_err_3d_mean"], e["pos_err_xy_mean"], e["pos_err_z_mean"], e["pos_err_3d_peak"], e["vel_err_3d_mean"],
            f"{100 * e['improvement_pos_3d']:.1f}%" if "improvement_pos_3d" in e else "-",
            f"{100 * e['improvement_pos_z']:.1f}%" if "improvement_pos_z" in e else "-",
            f"{e['gap_to_oracle_pos_3d']:+.4f}" if "gap_to_oracle_pos_3d" in e else "-",
        ])
    header = ["condition", "pos3d m", "posxy m", "posz m", "peak3d m", "vel3d m/s", "impr 3d", "impr z", "gap oracle m"]
    sep = results["separation"]
    return f"\n{name}: {len(results['seeds'])} seeds, separation {sep} m, {results['duration']:.1f} s\n" + format_table(rows, header)


def _figures(out: Path, name: str, per_cond_logs: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"no_downwash": "0.5", "baseline": "tab:red", "oracle": "k", "shallow": "tab:orange",
              "deep": "tab:blue", "equivariant": "tab:green"}
    # errors over time (first seed), position and velocity, vertical and 3D, as the paper's fig. 6
    fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    keys = [("pos_z", "|e_z| pos (m)"), ("vel_z", "|e_z| vel (m/s)"), ("pos_3d", "|e| pos 3D (m)"), ("vel_3d", "|e| vel 3D (m/s)")]
    for c, clogs in per_cond_logs.items():
        e = tracking_errors(clogs[0])
        for ax, (k, label) in zip(axes, keys):
            ax.plot(clogs[0]["t"], e[k], color=colors[c], label=c, lw=1.2)
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
            body.set_facecolor(colors[c])
        ax.set_xticks(range(1, len(data) + 1), list(per_cond_logs), rotation=45, fontsize=8)
        ax.set_title(label, fontsize=9)
    fig.suptitle(f"{name}: error distributions (all seeds)")
    fig.tight_layout()
    fig.savefig(out / "error_distributions.png", dpi=110)
    plt.close(fig)

    # flown path beside the reference (first seed), top and side views
    fig, (top, side) = plt.subplots(1, 2, figsize=(11, 4.5))
    first = next(iter(per_cond_logs.values()))[0]
    f = first.meta.get("follower", 1)
    top.plot(first["ref_pos"][:, f, 0], first["ref_pos"][:, f, 1], "k--", lw=1, label="reference")
    side.plot(first["ref_pos"][:, f, 1], first["ref_pos"][:, f, 2], "k--", lw=1, label="reference")
    for c, clogs in per_cond_logs.items():
        p = clogs[0]["pos"][:, f]
        top.plot(p[:, 0], p[:, 1], color=colors[c], lw=1, label=c)
        side.plot(p[:, 1], p[:, 2], color=colors[c], lw=1)
    lead = first["pos"][0, first.meta.get("leader", 0)]
    top.plot(lead[0], lead[1], "k^", ms=9, label="leader")
    top.set_xlabel("x (m)"), top.set_ylabel("y (m)"), top.axis("equal"), top.legend(fontsize=8)
    side.set_xlabel("y (m)"), side.set_ylabel("z (m)")
    side.set_title("side view (y-z)", fontsize=9), top.set_title("top view", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "paths.png", dpi=110)
    plt.close(fig)
