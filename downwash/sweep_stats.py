"""The statistics of a sweep: bootstrap confidence intervals and the paper's claim, seed by seed.

Per (field, model, minutes): the mean RMSE over seeds with a 95 % bootstrap
confidence interval (`bootstrap_ci`: `scipy.stats.bootstrap`, BCa, a fixed seed).
The paper's claim, "the equivariant model at 5 min beats the best baseline at
15 min" (`PAPER_CLAIM`), is tested seed by seed (`paired_comparison`): the
difference ``d_s = rmse(equivariant, 5, s) - min_b rmse(b, 15, s)``, its mean with
a bootstrap CI, and the fraction of seeds where ``d_s < 0``. The seeds pair the
trials: every kind of one (field, minutes, seed) trains on the same data subset
(`downwash.sweep_cells`). `summarize_field` gives both for one field's cells.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash.sweep_cells import FULL, Cell

__all__ = ["Claim", "PAPER_CLAIM", "bootstrap_ci", "paired_comparison", "summarize_field"]


@dataclass(frozen=True)
class Claim:
    """``model`` at ``minutes`` beats the best of ``baselines`` at ``baseline_minutes``, seed by seed."""

    model: str = "equivariant"
    minutes: float | str = 5.0  # or FULL
    baselines: tuple[str, ...] = ("shallow", "deep")
    baseline_minutes: float | str = 15.0

    def describe(self) -> str:
        at = lambda m: "the full set" if m == FULL else f"{m:g} min"  # noqa: E731
        return f"{self.model} at {at(self.minutes)} < min({', '.join(self.baselines)}) at {at(self.baseline_minutes)}"


PAPER_CLAIM = Claim()  # the paper's abstract: 5 min of data beat the baselines with 15 min


def bootstrap_ci(values: Sequence[float], confidence: float = 0.95, seed: int = 0,
                 n_resamples: int = 9999) -> tuple[float, float]:
    """The bootstrap confidence interval (low, high) of the mean of ``values``.

    `scipy.stats.bootstrap` (BCa) with a generator seeded by ``seed``: the same
    values give the same interval. Fewer than two values, or values that are all
    equal, have no spread to resample: the interval is the mean itself.
    """
    from scipy import stats

    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ConfigError(f"bootstrap_ci: expected a non-empty 1-D list of finite numbers, got {values!r}")
    if not 0 < confidence < 1:
        raise ConfigError(f"bootstrap_ci: confidence must be in (0, 1), got {confidence!r}")
    mean = float(np.mean(x))
    if x.size < 2 or np.ptp(x) <= 1e-12 * max(1.0, abs(mean)):
        return mean, mean
    res = stats.bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=n_resamples, method="BCa",
                          vectorized=True, random_state=np.random.default_rng(seed))
    low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
    if not (math.isfinite(low) and math.isfinite(high)):  # BCa undefined (e.g. one odd value): percentile
        res = stats.bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=n_resamples,
                              method="percentile", vectorized=True, random_state=np.random.default_rng(seed))
        low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return low, high


def paired_comparison(target: Mapping[int, float], baselines: Sequence[Mapping[int, float]],
                      seed: int = 0) -> dict[str, Any]:
    """Seed by seed: ``d_s = target[s] - min_b baselines[b][s]`` over the seeds all of them have.

    Returns n, seeds, differences, mean_difference with its bootstrap CI
    (`bootstrap_ci`), and fraction_holds, the share of seeds with ``d_s < 0``.
    ConfigError when no baseline is given or no seed is shared.
    """
    if not baselines:
        raise ConfigError("paired_comparison: no baseline given")
    seeds = sorted(set(target).intersection(*[set(b) for b in baselines]))
    if not seeds:
        raise ConfigError("paired_comparison: the target and the baselines share no seed (no pairs)")
    d = np.array([target[s] - min(b[s] for b in baselines) for s in seeds])
    low, high = bootstrap_ci(d, seed=seed)
    return {"n": len(seeds), "seeds": seeds, "differences": d.tolist(), "mean_difference": float(d.mean()),
            "ci_low": low, "ci_high": high, "fraction_holds": float(np.mean(d < 0))}


def summarize_field(cells: Sequence[Cell], results: Mapping[str, Mapping[str, Any]], floor: Mapping[str, Any],
                    claim: Claim = PAPER_CLAIM, seed: int = 0) -> dict[str, Any]:
    """The statistics of one field's cells (all of them must have results).

    Returns minutes (the FULL point as its length in minutes), seeds, models ->
    rmse_mean, rmse_std, rmse_ci_low, rmse_ci_high (per minute point) and rmse_runs
    (minutes x seeds), the label-noise floor and validation minutes, and ``claim``:
    `paired_comparison` at the claim's points, or None with ``claim_skipped`` saying why.
    """
    absent = [c.label for c in cells if c.key not in results]
    if absent:
        raise ConfigError(f"summarize_field: {len(absent)} cells have no result, e.g. {absent[:3]}")
    models = list(dict.fromkeys(c.model for c in cells))
    points = list(dict.fromkeys(c.minutes for c in cells))
    seeds = sorted({c.seed for c in cells})
    full = next((results[c.key]["train_minutes"] for c in cells if c.minutes == FULL), None)
    value = {(c.model, c.minutes, c.seed): results[c.key]["rmse"] for c in cells}
    out: dict[str, Any] = {
        "minutes": [full if m == FULL else m for m in points], "seeds": seeds, "models": {},
        "noise_floor": floor["rmse_mean"], "noise_floor_applied": floor["rmse"],
    }
    for kind in models:
        runs = np.array([[value[(kind, m, s)] for s in seeds] for m in points])
        cis = [bootstrap_ci(row, seed=seed) for row in runs]
        out["models"][kind] = {"rmse_mean": runs.mean(axis=1).tolist(), "rmse_std": runs.std(axis=1).tolist(),
                               "rmse_ci_low": [c[0] for c in cis], "rmse_ci_high": [c[1] for c in cis],
                               "rmse_runs": runs.tolist()}
    out["claim"], out["claim_skipped"] = None, None
    needed = [(claim.model, claim.minutes)] + [(b, claim.baseline_minutes) for b in claim.baselines]
    lacking = [f"{k} at {m if m == FULL else f'{m:g} min'}" for k, m in needed if k not in models or m not in points]
    if lacking:
        out["claim_skipped"] = f"not in the grid: {', '.join(lacking)}"
    else:
        per_seed = lambda k, m: {s: value[(k, m, s)] for s in seeds}  # noqa: E731
        out["claim"] = {"statement": claim.describe(), **dataclasses.asdict(claim),
                        **paired_comparison(per_seed(claim.model, claim.minutes),
                                            [per_seed(b, claim.baseline_minutes) for b in claim.baselines], seed)}
    return out
