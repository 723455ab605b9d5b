"""Speed of the simulation stack, as ratios measured in one run (DESIGN section 10).

    python -m experiments.benchmark [--quick]

Keys: bare_mj_step_per_s (the same scene, plain mj_step in a Python loop),
closed_loop_serial_steps_per_s and real_time_factor_serial (one flight, the full
stack with a 45 Hz predictor), closed_loop_batched_world_steps_per_s (64 worlds on
all cores) and batched_over_bare, plus the keys of later components when present.
Nothing here is a pass/fail test: the numbers are written down and printed.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from controllers.references import Hover, Lemniscate, stack
from experiments.common import CommonArgs, arg, format_table, load_field, parse_args, setup_logging, write_results
from sim.predictor import OraclePredictor
from sim.scene import build_scene
from sim.simulator import Simulator

LEADER = np.array([0.0, 0.0, 2.5])


@dataclass(frozen=True)
class BenchmarkArgs(CommonArgs):
    seconds: float = arg(20.0, "simulated seconds per closed-loop measurement")
    worlds: int = arg(64, "worlds in the batched measurement")
    repeats: int = arg(3, "repetitions; the best (least disturbed) is reported")


def _best(fn, repeats: int) -> float:
    """Fastest wall time of `repeats` runs of fn() (the least disturbed by other load)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def bare_mj_step_per_s(n_steps: int, repeats: int) -> float:
    scene = build_scene()
    data = mujoco.MjData(scene.model)
    data.qpos[scene.qpos_adr[:, None] + np.arange(3)] = [[0, 0, 2.5], [0, 0, 1.9]]

    def run():
        for _ in range(n_steps):
            mujoco.mj_step(scene.model, data)

    return n_steps / _best(run, repeats)


def _simulator(n_worlds: int, field: Any) -> Simulator:
    ref = stack([Hover(LEADER, n_worlds=n_worlds), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=n_worlds)])
    return Simulator(build_scene(), ref, list(range(n_worlds)), field=field, predictor=OraclePredictor(field))


def closed_loop_steps_per_s(n_worlds: int, seconds: float, repeats: int, field: Any) -> float:
    """Physics steps per wall second, summed over worlds, full stack."""
    sim = _simulator(n_worlds, field)
    n_ticks = int(round(seconds / sim.cfg.rates.control_dt))
    sim.tick()  # warm-up: first-call costs (allocation, JIT caches)

    def run():
        for _ in range(n_ticks):
            sim.tick()

    wall = _best(run, repeats)
    return n_ticks * sim.cfg.rates.physics_per_control * n_worlds / wall


def run(args: BenchmarkArgs) -> dict:
    field = load_field(args.field)
    seconds = 1.0 if args.quick else args.seconds
    repeats = 1 if args.quick else args.repeats
    worlds = min(args.worlds, 8) if args.quick else args.worlds
    physics_dt = build_scene().model.opt.timestep
    n_bare = int(seconds / physics_dt)

    r: dict[str, Any] = {"cpu_count": os.cpu_count(), "mujoco": mujoco.__version__, "quick": args.quick}
    r["bare_mj_step_per_s"] = bare_mj_step_per_s(n_bare, repeats)
    r["closed_loop_serial_steps_per_s"] = closed_loop_steps_per_s(1, seconds, repeats, field)
    r["real_time_factor_serial"] = r["closed_loop_serial_steps_per_s"] * physics_dt
    r["closed_loop_batched_world_steps_per_s"] = closed_loop_steps_per_s(worlds, seconds, repeats, field)
    r["batched_worlds"] = worlds
    r["batched_over_bare"] = r["closed_loop_batched_world_steps_per_s"] / r["bare_mj_step_per_s"]
    return r


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(BenchmarkArgs, "benchmark", argv, __doc__)
    results = run(args)
    path = write_results(args.out, results, args)
    rows = [[k, v] for k, v in results.items() if isinstance(v, float)]
    print(format_table(rows, ["key", "value"]))
    print(f"\nwrote {path}")
    return results


if __name__ == "__main__":
    main()
