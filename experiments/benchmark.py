"""Speed of the simulation stack, as ratios measured in one run (DESIGN section 10).

    python -m experiments.benchmark [--quick]

Keys: bare_mj_step_per_s (the same scene, plain mj_step in a Python loop),
closed_loop_serial_steps_per_s, real_time_factor_serial and serial_over_bare (one
flight, the full stack with the trained equivariant model at 45 Hz, the stack a
user runs), closed_loop_batched_world_steps_per_s (64 worlds on all cores) and
batched_over_bare; the same with the oracle predictor under *_oracle; the same
flights on the simulator's readable path (`Simulator(fast=False)`, the compiled
passes around Python calls, as before the fused tick) under *_readable, so that one
run shows what the fused tick gains; the predictor's cost per call, the training
time and the envs' speed. For the 5-vehicle preset (`formation5`, every wake on every
vehicle, the learned equivariant model summed over neighbours): bare_mj_step_per_s_formation5
(plain mj_step of that scene), formation5_serial_over_bare and formation5_batched_over_bare.
Nothing here is a pass/fail test: the numbers are written down and printed.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from core.params import LEADER_POSITION, RATES
from core.state import VehicleStates
from downwash.datasets import Dataset
from downwash.predictor import LearnedPredictor
from downwash.train import TrainConfig, train_model
from envs.evaluation import env_steps_per_s_single, env_steps_per_s_vector
from experiments.common import CommonArgs, arg, format_table, load_field, parse_args, setup_logging, write_results
from sim.predictor import OraclePredictor
from sim.presets import make_preset
from sim.scene import build_scene
from sim.simulator import Simulator
from trajectories import Hover, Lemniscate, stack

LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here


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


def bare_mj_step_per_s(n_steps: int, repeats: int, preset: Any = None) -> float:
    """Plain mj_step of the two-vehicle scene (or of `preset`'s, its vehicles at their start)."""
    scene = build_scene() if preset is None else preset.scene()
    data = mujoco.MjData(scene.model)
    start = [[0, 0, 2.5], [0, 0, 1.9]] if preset is None else preset.reference(1)(np.zeros(1)).pos[0]
    data.qpos[scene.qpos_adr[:, None] + np.arange(3)] = start

    def run():
        for _ in range(n_steps):
            mujoco.mj_step(scene.model, data)

    return n_steps / _best(run, repeats)


def closed_loop_steps_per_s(n_worlds: int, seconds: float, repeats: int, field: Any, predictor: Any,
                            fast: bool = True, preset: Any = None) -> float:
    """Physics steps per wall second, summed over worlds, full stack with `predictor` at 45 Hz
    (the lemniscate 0.6 m below the leader, or `preset`'s flight); fast=False: the simulator's
    readable path."""
    if preset is None:
        ref = stack([Hover(LEADER, n_worlds=n_worlds), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=n_worlds)])
        scene = build_scene()
    else:
        ref, scene = preset.reference(n_worlds), preset.scene()
    sim = Simulator(scene, ref, list(range(n_worlds)), field=field, predictor=predictor, fast=fast)
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
    # The stack a user runs has a trained model in the loop: train the equivariant model first
    # (on the field's own samples) and fly it; the oracle's figures follow under *_oracle.
    seconds_train, model = train_equivariant(0.5 if args.quick else 17.0, field)
    r["train_seconds_equivariant_full"] = seconds_train
    learned = LearnedPredictor(model, clamp=6.0)
    r["bare_mj_step_per_s"] = bare_mj_step_per_s(n_bare, repeats)
    for suffix, predictor in (("", learned), ("_oracle", OraclePredictor(field))):
        serial = closed_loop_steps_per_s(1, seconds, repeats, field, predictor)
        batched = closed_loop_steps_per_s(worlds, seconds, repeats, field, predictor)
        r[f"closed_loop_serial_steps_per_s{suffix}"] = serial
        r[f"real_time_factor_serial{suffix}"] = serial * physics_dt
        r[f"serial_over_bare{suffix}"] = serial / r["bare_mj_step_per_s"]
        r[f"closed_loop_batched_world_steps_per_s{suffix}"] = batched
        r[f"batched_over_bare{suffix}"] = batched / r["bare_mj_step_per_s"]
    for name, n_worlds in (("serial", 1), ("batched", worlds)):  # the same flights on the readable path
        rate = closed_loop_steps_per_s(n_worlds, seconds, repeats, field, learned, fast=False)
        key = "closed_loop_serial_steps_per_s_readable" if n_worlds == 1 else "closed_loop_batched_world_steps_per_s_readable"
        r[key] = rate
        r[f"{name}_over_bare_readable"] = rate / r["bare_mj_step_per_s"]
    five = make_preset("formation5")  # issue 10: the 5-vehicle preset against its own bare step
    r["bare_mj_step_per_s_formation5"] = bare_mj_step_per_s(n_bare, repeats, five)
    for name, n_worlds in (("serial", 1), ("batched", worlds)):
        rate = closed_loop_steps_per_s(n_worlds, seconds, repeats, field, learned, preset=five)
        r[f"formation5_{name}_world_steps_per_s"] = rate
        r[f"formation5_{name}_over_bare"] = rate / r["bare_mj_step_per_s_formation5"]
    r["batched_worlds"] = worlds
    r["predictor_us_per_call_batch64"] = predictor_us_per_call(learned, 64, 50 if args.quick else 2000)
    r["predictor_us_per_call_batch1"] = predictor_us_per_call(learned, 1, 50 if args.quick else 2000)
    r["env_steps_per_s_single"] = env_steps_per_s_single(100 if args.quick else 2000, repeats=repeats)
    r["env_steps_per_s_vector64"] = env_steps_per_s_vector(worlds, 20 if args.quick else 200, repeats=repeats)
    r["env_vector64_physics_over_bare"] = r["env_steps_per_s_vector64"] * RATES.physics_per_control / r["bare_mj_step_per_s"]
    return r


def predictor_us_per_call(predictor: LearnedPredictor, n_worlds: int, n_calls: int) -> float:
    """Microseconds per call of a learned model in the predictor slot, at the states of n_worlds
    followers below a leader, with estimated states that differ from the true ones."""
    rng = np.random.default_rng(0)
    pos = LEADER + rng.normal(scale=0.3, size=(n_worlds, 2, 3))
    pos[:, 1, 2] -= 0.6
    states = VehicleStates(pos, rng.normal(size=(n_worlds, 2, 3)), np.broadcast_to(np.eye(3), (n_worlds, 2, 3, 3)).copy())
    estimated = VehicleStates(states.pos + 1e-3, states.vel + 1e-2, states.rot)
    predictor(estimated, states)
    t0 = time.perf_counter()
    for _ in range(n_calls):
        predictor(estimated, states)
    return (time.perf_counter() - t0) / n_calls * 1e6


def train_equivariant(minutes: float, field: Any) -> tuple[float, Any]:
    """(wall seconds, model): the equivariant model trained on `minutes` of 50 Hz samples of the true field.

    The samples are drawn like flight data (positions below the leader, speeds up to 1 m/s)
    with labels = true field + 0.1 m/s^2 noise: training cost depends on the sample count,
    not on where the labels came from.
    """
    rng = np.random.default_rng(0)
    n = int(minutes * 60 * 50)
    dp = np.stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), -rng.uniform(0.4, 1.8, n)], axis=1)
    v_b = rng.uniform(-1, 1, (n, 3)) * [1, 1, 0.3]
    v_a, R_a = np.zeros((n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    y = field(np.zeros((n, 3)), v_a, R_a, dp, v_b) + 0.1 * rng.normal(size=(n, 3))
    flight = np.arange(n) // 1425  # 28.5 s flights, as in the staged collection
    data = Dataset(dp, v_a, v_b, R_a, y, flight, np.zeros(n, int), (np.arange(n) % 1425) * RATES.control_dt, y)
    t0 = time.perf_counter()
    model, _ = train_model("equivariant", data, None, TrainConfig(seed=0))
    return time.perf_counter() - t0, model


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
