"""Registered wakes fitted to real labels, with bootstrap intervals over flights, and compared with them.

    states = pair_states(read)                        # read: (ref, FlightLog) of real flights
    fit = bootstrap_fit("so2", states, n_boot=100)     # or fit_field(...) without intervals
    write_fitted("so2.json", fit)                      # then --field fitted:so2.json
    randomization_ranges(fit); compare_forces(fit, held_out)

Samples (`pair_states`, `downwash.field_fit_samples`, which says how each follower's one leader is
picked): real labelled samples, each a follower with one leader.
Fit (`fit_field`): least squares of a few float parameters of a registered field (`DEFAULT_FIT`; fitting
every constant is ill-posed), scaled for each pair's kinds (`sim.vehicle_params.pair_field`), to the
labels y (N, 3) m/s^2 over three axes; parameters with positive bounds in log space (relative steps).
Intervals (`bootstrap_fit`): whole flights drawn with replacement (a flight's samples are correlated).
A fit carries its data's digest (`PairStates.data_digest`: another selection or subset, another digest).
The samples, `PairStates` and `pair_states`, are `downwash.field_fit_samples`' (re-exported here).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares

from downwash_core.errors import ConfigError, DataError
from downwash_core.io import atomic_write_json
from downwash_core.provenance import code_version, describe
from downwash.field_fit_samples import FRAME_KINDS, PairStates, pair_states
from downwash.real_logs.flights import WAKE_DEPTH, WAKE_RADIUS
from sim.field import DownwashField
from sim.field_memory import is_stateful_field
from sim.fields.fitted import build_fitted, fitted_record, read_fitted
from sim.fields.registry import FIELDS
from sim.vehicle_params import pair_field

__all__ = ["PairStates", "FittedField", "DEFAULT_FIT", "FRAME_KINDS", "ENV_SCALABLE", "ENV_FACTOR_RANGE",
           "pair_states", "field_forces", "fit_field", "bootstrap_fit", "write_fitted", "load_fitted",
           "randomization_ranges", "compare_forces"]

# Fitted by default (a strength and a width), bounds in each parameter's unit. so2: on-axis strength m/s^2,
# width at the leader m (its decay and growth with depth trade off against these over the data's 0.2-1.5 m);
# momentum: thrust (a factor on m g) and spreading rate; jet: the paper's B_d and S; pybullet: C1 N and C2.
DEFAULT_FIT: Mapping[str, Mapping[str, tuple[float, float]]] = {
    "so2": {"strength": (0.1, 200.0), "width0": (0.005, 1.0)},
    "momentum": {"thrust_scale": (0.05, 10.0), "spreading_rate": (0.01, 1.0)},
    "jet": {"decay_constant": (0.5, 200.0), "spreading_rate": (0.005, 1.0)},
    "pybullet": {"dw_coeff_1": (20.0, 1e5), "dw_coeff_2": (0.005, 5.0)},
}
# DownwashField constants the envs scale per episode and the factors they allow: downwash_envs.config's
# FIELD_RANDOMIZABLE and FIELD_SCALE_RANGE (downwash may not import the envs; a test ties them)
ENV_SCALABLE = ("strength", "strength_depth", "width0", "width_slope", "approach_gain", "approach_speed",
                "radial_gain", "radial_offset", "radial_speed_gain", "radial_speed", "leader_speed_scale")
ENV_FACTOR_RANGE = (0.1, 5.0)
_LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")
_INFORMATIVE = 1e-4  # m/s^2: a sample whose prediction and its derivatives stay below this is left out of refits
_EDGES = {"vertical": (0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.6), "lateral": (0.0, 0.1, 0.2, 0.3, 0.4, 0.6, 1.0)}  # m


def _entry(name: str) -> Any:
    """The registry entry of a field that can be fitted (a stateless dataclass of its parameters)."""
    if not isinstance(name, str) or name not in FIELDS:
        raise ConfigError(f"field: unknown name {name!r}; registered: {', '.join(FIELDS)}")
    entry, field = FIELDS[name], FIELDS[name].make()
    if is_stateful_field(field):
        raise ConfigError(f"field {name!r} has memory (a wake shed over time): it cannot be fitted to single samples")
    if not dataclasses.is_dataclass(field) or not all(hasattr(field, k) for k in entry.params):
        raise ConfigError(f"field {name!r}: builds a {type(field).__name__}, not a dataclass holding its parameters "
                          f"({', '.join(entry.params)}): it cannot be rebuilt from a fit")
    return entry


def _param_bounds(entry: Any, p: str, given: Any, known: Any, default_field: Any, base: dict) -> tuple[float, float]:
    """One fitted parameter's bounds (given, else DEFAULT_FIT's, else its default / 20 to x 20), checked."""
    if p not in entry.params or entry.params[p] is not float or p in base:
        what = ("is not one" if p not in entry.params else f"is {entry.params[p].__name__}, not float" if
                entry.params[p] is not float else "is fixed in base")
        raise ConfigError(f"field {entry.name!r}: parameter {p!r} {what}; fitted can be its float parameters "
                          f"{[k for k, t in entry.params.items() if t is float and k not in base]}")
    v0 = float(getattr(default_field, p))
    lo, hi = given or known or ((v0 / 20, v0 * 20) if v0 > 0 else (None, None))
    if lo is None or not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ConfigError(f"bounds[{p!r}]: expected finite (low, high) with low < high, got {(lo, hi)}")
    for v in (lo, hi):
        entry.make(**base, **{p: v})  # the field's own check names a bound it does not accept
    return float(lo), float(hi)


def _fit_spec(entry: Any, params: Sequence[str] | None, bounds: Mapping[str, Any] | None,
              base: Mapping[str, Any] | None) -> tuple[dict[str, tuple[float, float]], dict[str, Any], Any]:
    """({param: bounds}, the base overrides, the field at the defaults), checked (ConfigError); DEFAULT_FIT
    is the field's or that of a field of the same factory (so2-c4 takes so2's)."""
    base, bounds = dict(base or {}), dict(bounds or {})
    known = next((fit for name, fit in DEFAULT_FIT.items()
                  if name == entry.name or (name in FIELDS and FIELDS[name].factory is entry.factory)), {})
    default_field = entry.make(**base)
    names = list(known if params is None else params)
    if not names or set(bounds) - set(names):
        raise ConfigError(f"field {entry.name!r}: fitted parameters {names} (params=...), bounds for {list(bounds)}: "
                          "name one or more parameters, and bounds only for those")
    return ({p: _param_bounds(entry, p, bounds.get(p), known.get(p), default_field, base) for p in names}, base,
            default_field)


def field_forces(field: Any, states: PairStates) -> np.ndarray:
    """(N, 3) m/s^2, world frame: `field` (a field object or a `FittedField`) scaled for each sample's
    pair of kinds (`sim.vehicle_params.pair_field`) on the leader's and follower's states."""
    field = field.make() if isinstance(field, FittedField) else field
    out = np.zeros((len(states), 3))
    for leader, follower, idx, arrays in states.groups:
        out[idx] = pair_field(field, leader, follower)(*arrays)
    return out


def _rmse(err: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(err)))) if err.size else float("nan")


class _Problem:
    """The residual (3N,) m/s^2 of a fit in its coordinates x (log of a parameter with positive bounds)."""

    def __init__(self, entry: Any, bounds: Mapping[str, tuple[float, float]], base: dict, states: PairStates):
        self.entry, self.names, self.base, self.states = entry, list(bounds), base, states
        self.lo, self.hi = (np.array([bounds[p][i] for p in self.names]) for i in (0, 1))
        self.log = self.lo > 0
        self.bounds = tuple(self.to_x(dict(zip(self.names, b))) for b in (self.lo, self.hi))

    def to_x(self, values: Mapping[str, float]) -> np.ndarray:
        v = np.clip([values[p] for p in self.names], self.lo, self.hi)
        return np.where(self.log, np.log(np.where(self.log, v, 1.0)), v)

    def values(self, x: np.ndarray) -> dict[str, float]:
        return {p: float(a) for p, a in zip(self.names, np.clip(np.where(self.log, np.exp(x), x), self.lo, self.hi))}

    def residual(self, x: np.ndarray) -> np.ndarray:
        values = self.values(x)
        r = (field_forces(self.entry.make(**self.base, **values), self.states) - self.states.y).ravel()
        if not np.all(np.isfinite(r)):
            raise ConfigError(f"field {self.entry.name!r} with {values}: non-finite predictions")
        return r

    def solve(self, start: Mapping[str, float], loss: str, f_scale: float, max_nfev: int) -> Any:
        # xtol 1e-4: parameters to 0.01 %, far inside any interval the data give
        return least_squares(self.residual, self.to_x(start), bounds=self.bounds, loss=loss, f_scale=f_scale,
                             max_nfev=max_nfev, xtol=1e-4, ftol=1e-6)


@dataclass(frozen=True)
class FittedField:
    """A registered field fitted to real labels (`fit_field`, `bootstrap_fit`)."""

    base: str  # the registered field
    params: Mapping[str, float]  # the fitted parameters
    fixed: Mapping[str, Any]  # every other parameter, as fitted with
    bounds: Mapping[str, tuple[float, float]]
    rmse_before: float  # m/s^2 over three axes on the fit's samples, the default constants
    rmse_after: float  # m/s^2, the fitted ones
    n_samples: int
    n_flights: int
    data_digest: str
    selection: Mapping[str, Any]
    source: str
    loss: str = "linear"
    f_scale: float = 1.0
    intervals: Mapping[str, tuple[float, float]] | None = None  # 95 % bootstrap percentiles
    bootstrap: Mapping[str, Any] | None = None
    optimizer: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    code: Mapping[str, Any] | None = None  # the code version that fitted it (a file's); None: this one

    def describe(self) -> dict[str, Any]:
        """Everything but the bootstrap's replicates, JSON-ready (for results files)."""
        boot = {k: v for k, v in (self.bootstrap or {}).items() if k != "replicates"}
        return {**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)}, "bootstrap": boot or None}

    def record(self) -> dict[str, Any]:
        """What `write_fitted` writes (`sim.fields.fitted.fitted_record`): every field and the code version."""
        return fitted_record(**{f.name: getattr(self, f.name) for f in dataclasses.fields(self)} | {
            "code": self.code or code_version()})

    def make(self) -> Any:
        """The field: the base field with these parameters, its provenance naming the data digest."""
        return build_fitted(self.record(), f"fitted {self.base}")


def fit_field(name: str, states: PairStates, params: Sequence[str] | None = None,
              bounds: Mapping[str, tuple[float, float]] | None = None, base: Mapping[str, Any] | None = None,
              loss: str = "linear", f_scale: float = 1.0, max_nfev: int = 100) -> FittedField:
    """Least squares of the registered field `name`'s float `params` (default DEFAULT_FIT) within `bounds`
    from their defaults, the others at their defaults or `base`, to `states`' labels; loss, f_scale (m/s^2):
    `least_squares`' robust loss. ConfigError for an unknown field, a parameter that is no float or that
    the kinds set, bad bounds; DataError for empty states."""
    entry = _entry(name)
    if loss not in _LOSSES or not (isinstance(f_scale, (int, float)) and math.isfinite(f_scale) and f_scale > 0):
        raise ConfigError(f"loss {loss!r}, f_scale {f_scale!r}: allowed a loss of {', '.join(_LOSSES)} and f_scale > 0 "
                          "(m/s^2)")
    bounds, base, default_field = _fit_spec(entry, params, bounds, base)
    if not isinstance(states, PairStates) or len(states) == 0:
        raise DataError(f"fit_field({name!r}): no samples to fit to")
    for (p, (lo, hi)), (leader, follower, _, _) in itertools.product(bounds.items(), states.groups):
        a, b = (pair_field(entry.make(**base, **{p: v}), leader, follower) for v in (lo, hi))
        if getattr(a, p, lo) == getattr(b, p, hi):  # pair_field overwrites it: fitting it would do nothing
            raise ConfigError(f"field {name!r}: parameter {p!r} is set by the vehicle kinds ({leader.name} over "
                              f"{follower.name}, sim.vehicle_params.pair_field): fitting it has no effect")
    problem, t0 = _Problem(entry, bounds, base, states), time.perf_counter()
    sol = problem.solve({p: float(getattr(default_field, p)) for p in bounds}, loss, f_scale, max_nfev)
    fitted = problem.values(sol.x)
    field = entry.make(**base, **fitted)
    fixed = {k: getattr(field, k) for k in entry.params if k not in fitted}
    return FittedField(
        base=name, params=fitted, fixed={k: (v.item() if isinstance(v, np.generic) else v) for k, v in fixed.items()},
        bounds=bounds, rmse_before=_rmse(field_forces(default_field, states) - states.y),
        rmse_after=_rmse(problem.residual(sol.x)), n_samples=len(states), n_flights=states.n_flights,
        data_digest=states.data_digest, selection=dict(states.selection), source=states.source, loss=loss,
        f_scale=float(f_scale), optimizer={"nfev": int(sol.nfev), "max_nfev": max_nfev, "status": int(sol.status),
                                           "message": sol.message, "seconds": time.perf_counter() - t0},
    )  # fmt: skip


def _informative(problem: _Problem, params: Mapping[str, float]) -> np.ndarray:
    """(N,) bool: the samples whose prediction, or its change per unit of a fitted x (central differences),
    exceeds _INFORMATIVE in some axis at `params`: the others' residuals do not move with the parameters."""
    x = problem.to_x(params)
    size = problem.residual(x) + problem.states.y.ravel()
    for h in np.eye(x.size) * 1e-4:
        size = np.maximum(np.abs(size), np.abs(problem.residual(x + h) - problem.residual(x - h)) / 2e-4)
    return size.reshape(-1, 3).max(axis=1) > _INFORMATIVE


def _refits(problem: _Problem, full: FittedField, informative: np.ndarray, n_boot: int, rng: np.random.Generator,
            max_samples: int) -> list[dict[str, float]]:
    """The fitted parameters of `n_boot` replicates of `problem.states` (bootstrap_fit), warm started at `full`."""
    states, flights = problem.states, np.unique(problem.states.flight)
    members = [np.flatnonzero((states.flight == f) & informative) for f in flights]
    out = []
    for _ in range(n_boot):
        counts = np.bincount(rng.integers(0, flights.size, flights.size), minlength=flights.size)
        index = np.concatenate([np.tile(m, c) for m, c in zip(members, counts) if c])
        if index.size > max_samples:
            index = rng.choice(index, size=max_samples, replace=False)
        problem.states = states.subset(index)
        x = problem.solve(full.params, full.loss, full.f_scale, full.optimizer.get("max_nfev", 100)).x
        out.append(problem.values(x))
    problem.states = states
    return out


def bootstrap_fit(name: str, states: PairStates, n_boot: int = 100, seed: int = 0, max_samples: int = 5_000,
                  full: FittedField | None = None, **fit: Any) -> FittedField:
    """`fit_field` on all samples (or `full`, a fit already made of these states) with 95 % percentile
    intervals over `n_boot` replicates: whole flights drawn with replacement, each replicate refitted by
    least squares from the full fit's parameters on at most `max_samples` samples drawn uniformly from
    its informative ones (`_informative`; the subsample adds some scatter: intervals if anything wide).
    `fit`: fit_field's keywords. DataError for fewer than two flights."""
    for label, value, lo in (("n_boot", n_boot, 10), ("max_samples", max_samples, 100)):
        if not isinstance(value, int) or isinstance(value, bool) or value < lo:
            raise ConfigError(f"{label}: expected an integer >= {lo}, got {value!r}")
    if len(states) and states.n_flights < 2:
        raise DataError(f"bootstrap_fit({name!r}): {states.n_flights} flight: the bootstrap resamples whole flights")
    if full is None:
        full = fit_field(name, states, **fit)
    elif full.base != name or full.data_digest != states.data_digest:
        raise ConfigError(f"full: a fit of {full.base!r} to data {full.data_digest[:12]}..., not of {name!r} to these "
                          f"states ({states.data_digest[:12]}...)")
    # the refits: the full fit's parameters, bounds and loss, every other parameter as it was fixed
    t0, (bounds, base, _) = time.perf_counter(), _fit_spec(_entry(name), list(full.params), full.bounds, full.fixed)
    problem = _Problem(_entry(name), bounds, base, states)
    informative = _informative(problem, full.params)
    replicates = _refits(problem, full, informative, n_boot, np.random.default_rng(seed), max_samples)
    intervals = {p: tuple(float(q) for q in np.percentile([r[p] for r in replicates], [2.5, 97.5])) for p in full.params}
    boot = {"n_boot": n_boot, "seed": seed, "max_samples": max_samples, "n_informative": int(informative.sum()),
            "seconds": time.perf_counter() - t0, "resampled": "whole flights, with replacement", "replicates": replicates}
    return dataclasses.replace(full, intervals=intervals, bootstrap=boot)


def write_fitted(path: str | Path, fitted: FittedField) -> Path:
    """Write a fitted field atomically as JSON (`FittedField.record`); a spec ``fitted:PATH`` flies it."""
    if not isinstance(fitted, FittedField):
        raise ConfigError(f"write_fitted: expected a FittedField, got {type(fitted).__name__}")
    atomic_write_json(path, fitted.record())
    return Path(path)


def load_fitted(path: str | Path, data_digest: str | None = None) -> FittedField:
    """The `FittedField` of a file `write_fitted` wrote; DataError for a missing, edited or malformed file,
    or one fitted to other data than `data_digest` (when given)."""
    record = read_fitted(path, data_digest)
    build_fitted(record, str(path))  # its base field and parameters exist here
    kw = {f.name: record[f.name] for f in dataclasses.fields(FittedField) if f.name in record}
    try:
        return FittedField(**{**kw, "bounds": {k: tuple(v) for k, v in record["bounds"].items()}, "intervals": None
                              if record["intervals"] is None else {k: tuple(v) for k, v in record["intervals"].items()}})
    except (KeyError, TypeError, AttributeError) as e:
        raise DataError(f"{path}: not a fitted field record of this version: {type(e).__name__}: {e}") from None


def randomization_ranges(fitted: FittedField, spec: str | None = None) -> dict[str, Any]:
    """The 95 % intervals as domain-randomisation ranges: "field", the envs' `field` option that flies the fit
    (`spec`, e.g. ``fitted:PATH``, else the base spec with the fitted parameters); "field_randomization",
    {constant: (low, high)} factors on the fitted values as `downwash_envs.config.FollowerConfig` takes them for
    any field (so2, momentum, jet, pybullet): low/high the interval's ends over the fitted value, ordered, clipped
    to ENV_FACTOR_RANGE (None only where a factor cannot say it: a fitted value of 0, or a `DownwashField`
    constant outside ENV_SCALABLE, which the envs do not scale); "absolute", {param: [low, high]} in the
    parameter's unit. ConfigError without intervals."""
    if not fitted.intervals:
        raise ConfigError(f"randomization_ranges: the fit of {fitted.base!r} has no intervals (use bootstrap_fit)")
    absolute = {p: [float(lo), float(hi)] for p, (lo, hi) in fitted.intervals.items()}
    factors = None
    so2 = isinstance(fitted.make(), DownwashField)
    if all(fitted.params[p] != 0 and (p in ENV_SCALABLE or not so2) for p in absolute):
        clip = lambda x: float(min(max(x, ENV_FACTOR_RANGE[0]), ENV_FACTOR_RANGE[1]))  # noqa: E731
        factors = {p: tuple(sorted((clip(lo / fitted.params[p]), clip(hi / fitted.params[p]))))
                   for p, (lo, hi) in absolute.items()}
    field = spec or f"{fitted.base}:" + ",".join(f"{p}={v!r}" for p, v in fitted.params.items())
    return {"field": field, "field_randomization": factors, "absolute": absolute, "base": fitted.base,
            "data_digest": fitted.data_digest}


def _bin_table(measured: np.ndarray, predicted: np.ndarray, value: np.ndarray, edges: Sequence[float]) -> list[dict]:
    """Per bin of `value` (N,): n, RMSE of the field and of none (m/s^2, 3 axes), the vertical component's
    mean measured and predicted (m/s^2; the wake's profile) and the measured mean's standard error."""
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        i = (value >= lo) & (value < hi)
        n, zm, zp = int(i.sum()), measured[i, 2], predicted[i, 2]
        out.append({"lo": lo, "hi": hi, "n": n, "rmse": _rmse(measured[i] - predicted[i]) if n else None,
                    "rmse_zero": _rmse(measured[i]) if n else None, "z_measured": float(zm.mean()) if n else None,
                    "z_predicted": float(zp.mean()) if n else None,
                    "z_measured_sem": float(zm.std() / math.sqrt(n)) if n > 1 else None})
    return out


def compare_forces(field: Any, states: PairStates, bins: Mapping[str, Sequence[float]] | None = None) -> dict[str, Any]:
    """Predicted against measured force, JSON-ready: RMSE (m/s^2, 3 axes) of the field and of none, in all
    and per flight, and per bin (`_bin_table`) of the leader's height above the follower ("vertical", of
    the samples within `lateral_max` laterally) and of the horizontal offset ("lateral", of the samples
    `depth` below their leader). field: a field object or a `FittedField`; bins: {"vertical": edges, ...} m."""
    edges = {k: [float(e) for e in (bins or {}).get(k, default)] for k, default in _EDGES.items()}
    for k, e in {**(bins or {}), **edges}.items():
        if k not in _EDGES or len(e) < 2 or np.any(np.diff(e) <= 0):
            raise ConfigError(f"bins[{k!r}]: expected at least two increasing edges (m) of {', '.join(_EDGES)}")
    if len(states) == 0:
        raise DataError("compare_forces: no samples")
    pred = field_forces(field, states)
    up = states.p_a[:, 2] - states.p_b[:, 2]
    lateral = np.linalg.norm(states.p_a[:, :2] - states.p_b[:, :2], axis=1)
    per_flight = [{"flight": states.flight_names[f], "n": int(i.sum()), "rmse": _rmse(pred[i] - states.y[i]),
                   "rmse_zero": _rmse(states.y[i])} for f in np.unique(states.flight) for i in (states.flight == f,)]
    tables = {"vertical": (lateral < WAKE_RADIUS, up), "lateral": ((up > WAKE_DEPTH[0]) & (up < WAKE_DEPTH[1]), lateral)}
    return {"field": describe(field.make() if isinstance(field, FittedField) else field), "n_samples": len(states),
            "data_digest": states.data_digest, "rmse": _rmse(pred - states.y), "rmse_zero": _rmse(states.y),
            "per_flight": per_flight, "lateral_max": WAKE_RADIUS, "depth": list(WAKE_DEPTH),
            **{k: _bin_table(states.y[m], pred[m], v[m], edges[k]) for k, (m, v) in tables.items()}}
