"""Tracking metrics of a flight, in SI units, and their aggregation over conditions.

Crashed flights. A flight that ends early (collision, divergence) must not make its
condition look better by being averaged over its shorter life. The rule: a metric is
always taken over the flight's planned duration, and every tick after the crash
counts with the crash penalty, max(CRASH_PENALTY, the largest error before the
crash) per error quantity (1 m for position, 1 m/s for velocity: the size of the
envs' tracking box). Each condition also reports its `crash_rate` and which seeds
crashed.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.status import Status
from sim.logs import FlightLog

__all__ = [
    "TRACKING_METRICS", "IMPROVEMENT_METRICS", "CRASH_PENALTY", "tracking_errors", "planned_ticks",
    "tracking_metrics", "follower_metrics", "improvement", "compensation_shares", "wilson_interval",
    "aggregate_conditions",
]

TRACKING_METRICS = (
    "pos_err_3d_mean", "pos_err_xy_mean", "pos_err_z_mean", "pos_err_3d_peak",
    "vel_err_3d_mean", "vel_err_xy_mean", "vel_err_z_mean",
)
# improvement_<name>: fraction by which a condition's metric is smaller than the baseline's
IMPROVEMENT_METRICS = {"improvement_pos_3d": "pos_err_3d_mean", "improvement_pos_z": "pos_err_z_mean", "improvement_vel_3d": "vel_err_3d_mean"}
CRASH_PENALTY = {"pos": 1.0, "vel": 1.0}  # m, m/s: the least error counted for each tick after a crash


def tracking_errors(log: FlightLog, vehicle: int | None = None) -> dict[str, np.ndarray]:
    """Per-tick errors of one vehicle (default: the log's follower): true state minus reference.

    Returns pos_3d, pos_xy, pos_z (m) and vel_3d, vel_xy, vel_z (m/s), each (T,).
    """
    v = log.meta["follower"] if vehicle is None else vehicle
    dp = log["pos"][:, v] - log["ref_pos"][:, v]
    dv = log["vel"][:, v] - log["ref_vel"][:, v]
    return {
        "pos_3d": np.linalg.norm(dp, axis=1), "pos_xy": np.linalg.norm(dp[:, :2], axis=1), "pos_z": np.abs(dp[:, 2]),
        "vel_3d": np.linalg.norm(dv, axis=1), "vel_xy": np.linalg.norm(dv[:, :2], axis=1), "vel_z": np.abs(dv[:, 2]),
    }


def planned_ticks(log: FlightLog) -> int:
    """Controller ticks the flight was meant to last (its `duration` meta), at least its rows."""
    rates = log.meta.get("config", {}).get("rates", {})
    if len(log) >= 2:
        dt = float(np.median(np.diff(log["t"])))
    else:
        dt = rates["physics_dt"] * rates["physics_per_autopilot"] * rates["autopilot_per_control"]
    duration = log.meta.get("duration")
    return max(len(log), int(round(duration / dt))) if duration else len(log)


def tracking_metrics(log: FlightLog, vehicle: int | None = None) -> dict[str, float]:
    """The scalar metrics of TRACKING_METRICS for one flight, over its planned duration: the
    ticks after a crash count with the crash penalty (see the module docstring)."""
    if len(log) == 0:
        raise ConfigError("tracking_metrics: the log has no rows")
    e = tracking_errors(log, vehicle)
    missing = planned_ticks(log) - len(log) if log.meta.get("status", Status.OK) != Status.OK else 0
    out = {}
    for key, x in e.items():  # "pos_3d" -> "pos_err_3d_mean"
        quantity, axes = key.split("_")
        if missing:
            penalty = max(CRASH_PENALTY[quantity], float(np.nan_to_num(x, nan=np.inf).max()))
            x = np.concatenate([np.nan_to_num(x, nan=penalty), np.full(missing, penalty)])
            e[key] = x
        out[f"{quantity}_err_{axes}_mean"] = float(x.mean())
    out["pos_err_3d_peak"] = float(e["pos_3d"].max())
    return {k: out[k] for k in TRACKING_METRICS}


def _followers(log: FlightLog) -> list[int]:
    """Every vehicle of the log that is not its leader (the pair's follower)."""
    roles = log.meta.get("roles") or []
    return [v for v, r in enumerate(roles) if r != "leader"] or [log.meta["follower"]]


def follower_metrics(log: FlightLog) -> dict[str, float]:
    """TRACKING_METRICS averaged over every follower of the log (a swarm's metrics: each
    vehicle that flies in a wake counts once; the peak is the largest of theirs)."""
    each = [tracking_metrics(log, v) for v in _followers(log)]
    out = {m: float(np.mean([e[m] for e in each])) for m in TRACKING_METRICS}
    out["pos_err_3d_peak"] = max(e["pos_err_3d_peak"] for e in each)
    return out


def compensation_shares(logs: list[FlightLog]) -> dict[str, float] | None:
    """How much of a guarded model's prediction was applied (the logs' ``applied``, `sim.predictor`):
    the shares of (tick, follower) at full (>= 99.9 %), partial and no (<= 0.1 %) compensation over
    the flights; None for logs without a guard."""
    values = []
    for L in logs:
        if "applied" not in L.arrays:
            continue
        a = L["applied"][:, _followers(L)].ravel()
        values.append(a[np.isfinite(a)])
    a = np.concatenate(values) if values else np.zeros(0)
    if a.size == 0:
        return None
    full, none = float(np.mean(a >= 0.999)), float(np.mean(a <= 0.001))
    return {"full": full, "partial": 1.0 - full - none, "none": none}


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The Wilson score interval (95 % by default) of a rate of k events in n trials: unlike k/n +- its
    normal error it stays inside [0, 1] and is not empty at 0 of 10 crashes (0 to 28 %)."""
    if not (isinstance(n, (int, np.integer)) and n >= 1 and 0 <= k <= n):
        raise ConfigError(f"wilson_interval: expected 0 <= k <= n and n >= 1, got k={k}, n={n}")
    p, z2 = k / n, z * z
    centre, half = (p + z2 / (2 * n)) / (1 + z2 / n), z * np.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    # (exact ends at 0 and n events, where rounding would leave them a hair inside)
    return 0.0 if k == 0 else float(centre - half), 1.0 if k == n else float(centre + half)


def improvement(metrics: dict[str, float], baseline: dict[str, float]) -> dict[str, float]:
    """Fractions by which `metrics` improve on `baseline` (0.36: 36 % smaller error)."""
    return {name: 1.0 - metrics[m] / baseline[m] for name, m in IMPROVEMENT_METRICS.items()}


def aggregate_conditions(per_condition: dict[str, list[FlightLog]], baseline: str = "baseline",
                         oracle: str = "oracle", unmodelled: tuple[str, ...] = ("no_downwash",),
                         metrics: Callable[[FlightLog], dict[str, float]] | None = None) -> dict[str, dict]:
    """Metrics per condition from logs flown on the same seeds (seed k is the k-th log of each).

    Each condition gets the mean over seeds of every TRACKING_METRICS entry (crashed
    flights counted by the crash rule of the module docstring), the per-seed values
    under `per_seed` (with `crashed`, bool), `crash_rate` (the fraction of seeds that
    crashed) with its Wilson 95 % interval `crash_rate_ci95`, and `failed_flights` (messages). With a `baseline`
    condition, every other condition but the `unmodelled` ones gets the paired
    IMPROVEMENT_METRICS (per seed, then their mean); with an `oracle` too, every
    compensating condition gets `gap_to_oracle_pos_3d` (m): how much larger its mean 3D
    position error is than the oracle's. `metrics(log)` gives one flight's TRACKING_METRICS
    (default `tracking_metrics`, the log's follower; `follower_metrics` for a swarm). A guarded
    condition also gets `compensation` (`compensation_shares`).
    """
    metrics = tracking_metrics if metrics is None else metrics
    out: dict[str, dict] = {}
    for c, logs in per_condition.items():
        per_seed = [metrics(L) for L in logs]
        entry: dict = {m: float(np.mean([p[m] for p in per_seed])) for m in TRACKING_METRICS}
        entry["per_seed"] = {m: [p[m] for p in per_seed] for m in TRACKING_METRICS}
        entry["per_seed"]["crashed"] = [not L.ok for L in logs]
        entry["crash_rate"] = float(np.mean(entry["per_seed"]["crashed"]))
        entry["crash_rate_ci95"] = list(wilson_interval(int(sum(entry["per_seed"]["crashed"])), len(logs)))
        entry["failed_flights"] = [L.meta["message"] for L in logs if not L.ok]
        if (shares := compensation_shares(logs)) is not None:  # a guarded condition
            entry["compensation"] = shares
        out[c] = entry
    if baseline not in out:
        return out
    base = out[baseline]["per_seed"]
    n = len(base[TRACKING_METRICS[0]])
    for c, entry in out.items():
        if c == baseline or c in unmodelled:
            continue
        imps = [improvement({m: entry["per_seed"][m][k] for m in TRACKING_METRICS},
                            {m: base[m][k] for m in TRACKING_METRICS}) for k in range(n)]
        for key in IMPROVEMENT_METRICS:
            entry["per_seed"][key] = [i[key] for i in imps]
            entry[key] = float(np.mean(entry["per_seed"][key]))
    if oracle in out:
        for c, entry in out.items():
            if c not in (baseline, oracle) and c not in unmodelled:
                entry["gap_to_oracle_pos_3d"] = entry["pos_err_3d_mean"] - out[oracle]["pos_err_3d_mean"]
    return out
