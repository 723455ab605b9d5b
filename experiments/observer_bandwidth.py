"""The disturbance observer's bandwidth, chosen once on the training fields under each controller: how
`DEFAULT_BANDWIDTH` (the LQR's) and each controller's ``observer_bandwidth`` were set.

    python -m experiments.observer_bandwidth                          # every controller (lqr, mellinger, pid, indi)
    python -m experiments.observer_bandwidth --controllers mellinger   # one
    python -m experiments.observer_bandwidth --quick                  # two candidates, short flights

The `dob` condition (`sim.observer.DisturbanceObserver`) has one setting, its bandwidth: too low
and it lags every wake it crosses, too high and it passes on the noise of a differenced velocity
and chases its own command. It is chosen as a lab would, on the flights the models learn from and
never on an experiment's test flights: the follower flies each staged-collection stage's training
patterns (`downwash.staged_provenance.STAGES`, the collection's pattern seeds and leader, the field
of --field, the default so2), compensating with the observer alone, once per candidate bandwidth,
all candidates on the same flights and seeds as one batch. The criterion is the follower's mean
3-D tracking error (`sim.metrics`, crashed flights at the crash penalty); the chosen bandwidth is
the lowest whose error is not significantly larger than the best's (the paired 95 % interval of
the difference over the flights reaches 0): of equally good settings, the one that passes on the
least measurement noise and keeps the most margin to the delay of the control loop. The observer
estimates what the controller's command misses, so the choice is made under each controller: one
whose own loop already rejects part of a disturbance (INDI measures the acceleration; the firmware's
controllers integrate) leaves the observer less to do and fights one that is too fast.

Writes <out>/results.json, under `controllers` per controller: per candidate its mean 3-D error,
the paired 95 % interval of its difference to the best one's over the flights, its crash count and
the observer's RMS estimation error (its prediction against the field the follower felt); `best`
and `chosen`. The committed results/observer_bandwidth.json is tied to `DEFAULT_BANDWIDTH` and to
each controller's ``observer_bandwidth`` (`sim.observer.bandwidth_for`) by a test.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from experiments.common import (CONTROLLER_NAMES, CommonArgs, arg, comma_items, comma_numbers, format_table,
                                names_check, out_lock, parse_args, run_main, script, setup_logging, write_results)

__all__ = ["BandwidthArgs", "CANDIDATES", "run", "main"]

CANDIDATES = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)  # rad/s: time constants from 1 s down to 31 ms (1.6 ticks at 50 Hz)


@dataclass(frozen=True)
class BandwidthArgs(CommonArgs):
    flights: int = arg(4, "training flights per stage (the first of each stage's training flights)", ge=1, le=64)
    seconds: float = arg(28.5, "length of each flight, s (the collection's)", ge=2.0, le=120.0)
    candidates: str = arg(",".join(f"{b:g}" for b in CANDIDATES), "a comma list of bandwidths, rad/s, each > 0")
    controllers: str = arg(",".join(CONTROLLER_NAMES), f"a comma list of the follower's outer-loop controllers "
                           f"({', '.join(CONTROLLER_NAMES)}): a choice under each (the observer estimates what the "
                           "command misses, so its best bandwidth depends on the controller)",
                           check=names_check(CONTROLLER_NAMES))


def _candidates(text: str) -> list[float]:
    try:
        values = comma_numbers(text)
    except ValueError:
        values = []
    if not values or not all(np.isfinite(v) and v > 0 for v in values) or len(set(values)) != len(values):
        raise ConfigError(f"--candidates: expected distinct bandwidths > 0 rad/s as a comma list, got {text!r}")
    return values


def _paired_interval(diff: np.ndarray) -> list[float]:
    """The 95 % t interval of the mean of paired differences (a single flight: its value twice)."""
    from scipy import stats

    if len(diff) < 2:
        return [float(diff.mean())] * 2
    half = stats.t.ppf(0.975, len(diff) - 1) * diff.std(ddof=1) / np.sqrt(len(diff))
    return [float(diff.mean() - half), float(diff.mean() + half)]


def _choose(args: BandwidthArgs, controller: str, bandwidths: list[float]) -> dict[str, Any]:
    """Every candidate flown under `controller` on the stages' training flights: per candidate its error,
    paired interval to the best, estimation RMS and crashes; the best and the chosen bandwidth."""
    from controllers.registry import make_controller
    from downwash.staged_provenance import STAGES
    from downwash.stages import Stage
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Mixed, stack
    from experiments.common import load_field
    from sim.flight import fly
    from sim.metrics import tracking_metrics
    from sim.observer import DisturbanceObserver
    from sim.predictor import PerWorldPredictor

    flights = 1 if args.quick else args.flights
    seconds = 3.0 if args.quick else args.seconds
    field = load_field(args.field)
    # the stages as the collection flies them (downwash.staged): pattern seed (seed, k), noise seeds from seed
    stages = [Stage(f"stage{k}", LEADER_POSITION, (s["separation"],), ((args.seed, k),), args.seed * 100_000 + 1000 * k)
              for k, s in enumerate(STAGES)]
    n_train, C = max(flights, 12), len(bandwidths)
    per_candidate = len(stages) * flights
    # world (candidate c, stage k, flight i) = c * per_candidate + k * flights + i: every candidate flies the
    # same flights (a flight's patterns come from its own generator, so a repeated index is the same flight)
    refs = [stage.reference(list(range(flights)) * C, n_train, 0, seconds) for stage in stages]
    worlds = [[c * per_candidate + k * flights + i for c in range(C) for i in range(flights)] for k in range(len(stages))]
    leader, follower = (Mixed([(r.refs[v], w) for r, w in zip(refs, worlds)]) for v in (0, 1))
    seeds = [stage.flight_seed + i for stage in stages for i in range(flights)] * C
    predictor = PerWorldPredictor([DisturbanceObserver(bandwidth=b) for b in bandwidths],
                                  np.repeat(np.arange(len(bandwidths)), per_candidate))
    logs = fly(stages[0].scene(), stack([leader, follower]), seeds, seconds, field=field, predictor=predictor,
               controller=make_controller(controller), meta={"experiment": "observer_bandwidth"})
    errors = np.array([tracking_metrics(L)["pos_err_3d_mean"] for L in logs]).reshape(len(bandwidths), per_candidate)
    estimation = [float(np.sqrt(np.mean(np.concatenate([
        np.sum((L["f_hat"][:, 1] - L["field_mean"][:, 1]) ** 2, axis=-1) for L in logs[c * per_candidate:(c + 1) * per_candidate]]))))
        for c in range(len(bandwidths))]
    crashes = [int(sum(not L.ok for L in logs[c * per_candidate:(c + 1) * per_candidate])) for c in range(len(bandwidths))]
    best = int(np.argmin(errors.mean(axis=1)))
    intervals = [_paired_interval(errors[c] - errors[best]) for c in range(C)]
    chosen = min((b for b, ci in zip(bandwidths, intervals) if ci[0] <= 0.0), default=bandwidths[best])
    return {"candidates": [{"bandwidth": b, "pos_err_3d_mean": float(errors[c].mean()), "minus_best_ci95": intervals[c],
                            "estimation_rms": estimation[c], "crashes": crashes[c]} for c, b in enumerate(bandwidths)],
            "best": bandwidths[best], "chosen": chosen, "flights_per_stage": flights, "seconds": seconds}


def run(args: BandwidthArgs) -> dict:
    """Fly every candidate under each controller on the stages' training flights; print and write the choices."""
    from downwash.staged_provenance import STAGES

    bandwidths = _candidates("1,2" if args.quick and args.candidates == BandwidthArgs.candidates else args.candidates)
    controllers = comma_items(args.controllers)
    chosen = {c: _choose(args, c, bandwidths) for c in controllers}
    first = chosen[controllers[0]]
    results: dict[str, Any] = {
        "experiment": "observer_bandwidth", "flights_per_stage": first["flights_per_stage"],
        "seconds": first["seconds"], "stages": [s["separation"] for s in STAGES],
        "criterion": "mean 3-D tracking error of the follower",
        "rule": "the lowest bandwidth whose paired 95 % interval against the best reaches 0",
        "controllers": {c: {k: v for k, v in r.items() if k not in ("flights_per_stage", "seconds")}
                        for c, r in chosen.items()},
    }
    for c, r in results["controllers"].items():
        rows = [(f"{e['bandwidth']:g}", f"{e['pos_err_3d_mean'] * 100:.2f}", "[{:+.2f}, {:+.2f}]".format(
            *(100 * x for x in e["minus_best_ci95"])), f"{e['estimation_rms']:.3f}", e["crashes"])
            for e in r["candidates"]]
        print(f"\n{c}:")
        print(format_table(rows, ("bandwidth rad/s", "3-D error cm", "minus best, 95% CI cm", "estimate RMS m/s^2",
                                  "crashes")))
        print(f"best: {r['best']:g} rad/s; chosen: {r['chosen']:g} rad/s ({results['rule']})")
    path = write_results(args.out, results, args)
    print(f"\nwrote {path}")
    return results


def main(argv: Sequence[str] | None = None) -> dict:
    setup_logging()
    args = parse_args(BandwidthArgs, "observer_bandwidth", argv, __doc__)
    _candidates(args.candidates)  # before anything is written
    with out_lock(args, "observer_bandwidth"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
