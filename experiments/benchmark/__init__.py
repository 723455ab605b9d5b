"""Speed of the simulation stack, as ratios measured in one run.

    python -m experiments.benchmark [--quick]

Every measurement runs once per round (`--repeats` rounds), each right after a window of bare
mj_step of its scene; a ratio is the median over rounds of the pair's ratio, a rate the median
over rounds (see `run`). `targets` holds the project's speed targets for some of the ratios.

Keys: bare_mj_step_per_s (the same scene, plain mj_step in a Python loop, as a user's loop runs it:
with the timer callback the mujoco bindings install for MjData.timer), bare_mj_step_per_s_no_timer
(the same loop with that timer off, as the simulator steps: `sim.physics.profiling_timer_off`) and
the ratios against it, *_over_bare_no_timer and *_over_mujoco_rollout_no_timer (MuJoCo's rollout
with the timer off too: physics against physics),
closed_loop_serial_steps_per_s, real_time_factor_serial and serial_over_bare (one
flight, the full stack with the trained equivariant model at 45 Hz, the stack a
user runs), closed_loop_batched_world_steps_per_s (64 worlds on all cores) and
batched_over_bare; the same with the oracle predictor under *_oracle; the same
flights on the simulator's readable path (`Simulator(fast=False)`, the compiled
passes around Python calls, as before the fused tick) under *_readable, so that one
run shows what the fused tick gains; the same flights in the wake with memory (`--field shed`,
`sim.fields.shed`, whose state is stepped on the readable path) under *_shed, its cost in the
loop; the same flights with the model behind the guard (`downwash.guard`, its pass in the fused
tick, a support that holds the flights, so that it passes the prediction through: the same flight
plus the guard's work) under *_guarded, and their ratios to the model alone
(guarded_over_unguarded_serial, guarded_over_unguarded_batched); the predictor's cost per call, the
training time and the envs' speed: env_steps_per_s_single (one `gymnasium.make` env, wrappers included)
and env_single_physics_over_bare (its physics steps per second over bare), likewise for the
native vector env of 64 worlds; mujoco_batch_world_steps_per_s and mujoco_batch_over_bare
(`mujoco.batch.Batch.step` of 64 worlds alone, no control: the ceiling of the batched
ratios on the machine measured). For the 5-vehicle preset (`formation5`, every wake on every
vehicle) with the equivariant deep sets (`deepsets_equivariant`, a model of sets, four
neighbours each): bare_mj_step_per_s_formation5 (plain mj_step of that scene),
formation5_serial_over_bare and formation5_batched_over_bare; the same with the trained
equivariant model summed over neighbours under formation5_*_summed. A user's components through the
public compiled contracts, as docs/extending.md writes them (`experiments.benchmark.recipes`), each with
the oracle predictor: the PD controller (`controllers.compiled`) under *_pd_recipe and its speed over the
built-in LQR's, compiled_controller_over_builtin_{serial,batched}; the Gaussian jet (`sim.field_contract`,
its oracle too) under *_jet_recipe and its speed over the paper field's, compiled_field_over_builtin_*;
and the labs' Crazyflie Mellinger controller, through the same contract, under *_mellinger and
mellinger_over_builtin_* (a different law, with more work per tick than the LQR).
Against MuJoCo's own batched stepping of the same scene (`mujoco.rollout.Rollout`, the simulator's
threads, the same worlds, no control; `MujocoRollout`), measured in the same rounds right beside our
batched flight of that scene, in alternating order: mujoco_rollout_world_steps_per_s,
mujoco_rollout_over_bare and batched_over_mujoco_rollout (the pair: our batched ratio over the
rollout's, round by round, median) and the same under formation5_*; for the swarm below,
swarm_mujoco_rollout_world_steps_per_s and swarm_native_over_mujoco_rollout (the native adapter's
world-steps per second, swarm_world_steps_per_s_native, over the rollout's of its scene).
RL glue: stable-baselines3's PPO rollout collection (the policy's forward pass and the
env steps) through the native vector env and its adapter, through Gymnasium's
SyncVectorEnv of single envs (the same adapter) and through SB3's own DummyVecEnv, 16
worlds each, alternated: sb3_rollout_steps_per_s_{native,sync,dummy},
sb3_native_over_sync and sb3_native_over_dummy (medians of the paired ratios; torch at
one thread, as the examples run it), and the same under *_torch_default_threads.
The multi-agent swarm (`swarm_rollouts`): agent steps per second of random actions through the
native SB3 adapter (`downwash_envs.swarm_sb3`, every world on one batched simulator) and through
SuperSuit's vector env of ParallelEnv copies (one simulator each, stepped in turn), the same
preset and worlds, alternated: swarm_agent_steps_per_s_{native,native_one_thread,supersuit},
swarm_native_over_supersuit and swarm_native_one_thread_over_supersuit (medians of the paired ratios).
Sharing the cores (`contention`): env_learner_loops_per_s (16 worlds and an Adam update of a
small MLP per step, torch at its default threads) with the env's default threads over
n_threads=1 (env_learner_threads_over_one_thread), and two processes of 64 worlds at once:
the slower one's rate over one alone (two_processes_share_of_solo), each also with
n_threads=1 (*_one_thread).
A ratio of two of our flights (guarded_over_unguarded_*, compiled_controller_over_builtin_*,
compiled_field_over_builtin_*, mellinger_over_builtin_*) is measured side by side: after its own
window each such flight flies again right beside the flight it is compared with, the order
alternating by round, and the ratio is the median of those per-round quotients (`side_by_side`),
as a change of code is measured by paired rounds. Each simulation ratio also comes with a
distribution-free 95 % interval of its median over the rounds (`median_interval`), under
ratio_intervals: how far the run's own rounds leave it uncertain.
Nothing here is a pass/fail test: the numbers are written down and printed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from downwash_core.params import RATES
# the measurements (LEADER and start_data: re-exported, as before the measuring functions had a module)
from experiments.benchmark.measures import (LEADER, MujocoRollout, bare_mj_step_per_s, closed_loop_sim,  # noqa: F401
                                            closed_loop_steps_per_s, contention, deepsets_equivariant,
                                            mujoco_batch_steps_per_s, predictor_us_per_call, sb3_rollouts, start_data,
                                            swarm_rollouts, train_equivariant)
from experiments.benchmark.recipes import load_recipes
from experiments.common import (FLIGHT_SECONDS_MAX, CommonArgs, arg, format_table, load_field, out_lock, parse_args,
                                setup_logging, write_results, script)


@dataclass(frozen=True)
class BenchmarkArgs(CommonArgs):
    seconds: float = arg(20.0, "simulated seconds per window of one flight (and of bare mj_step); a batched "
                               "window flies 4 / worlds of it", gt=0.0, le=FLIGHT_SECONDS_MAX)
    worlds: int = arg(64, "worlds in the batched measurement (a sanity bound: memory grows with the worlds)", ge=1,
                      le=4096)
    repeats: int = arg(15, "rounds: each measurement once per round, paired with a bare window (medians reported)",
                       ge=1, le=1000)


# The project's targets for the ratios, written into results.json beside the measurements.
TARGETS = {"serial_over_bare": 0.8, "batched_over_bare": 1.7, "formation5_serial_over_bare": 0.5,
           "formation5_batched_over_bare": 1.5, "batched_over_mujoco_rollout": 0.9,
           "formation5_batched_over_mujoco_rollout": 0.6, "env_single_physics_over_bare": 0.3,
           "sb3_native_over_sync": 2.0, "env_learner_threads_over_one_thread": 1.0, "two_processes_share_of_solo": 0.4,
           "guarded_over_unguarded_serial": 0.9, "guarded_over_unguarded_batched": 0.9,
           "swarm_native_over_supersuit": 3.0, "compiled_controller_over_builtin_serial": 0.9,
           "compiled_controller_over_builtin_batched": 0.9, "compiled_field_over_builtin_serial": 0.9,
           "compiled_field_over_builtin_batched": 0.9}


def run(args: BenchmarkArgs) -> dict:
    """Every measurement once per round, `repeats` rounds, each right after a bare mj_step window of
    its scene. This machine switches between a fast and a slow state every second or so (bare
    mj_step windows of 50 ms measure about 165k or 270k steps/s), so a ratio is the median over
    rounds of (rate / the bare rate just before it): both halves of a pair see the same state.
    Rates are medians over the rounds."""
    import mujoco

    from controllers.crazyflie import MellingerController
    from downwash.guard import GuardedPredictor
    from downwash.support import Support
    from downwash.predictor import LearnedPredictor
    from downwash_envs.evaluation import env_steps_per_s_single, env_steps_per_s_vector
    from sim.predictor import OraclePredictor
    from sim.fields.registry import make_field
    from sim.presets import make_preset
    from sim.scene import build_scene

    field = load_field(args.field)
    seconds = 1.0 if args.quick else args.seconds
    repeats = 1 if args.quick else args.repeats
    worlds = min(args.worlds, 8) if args.quick else args.worlds
    physics_dt = build_scene().model.opt.timestep
    n_bare = int(seconds / physics_dt)
    n_env = n_bare // 20  # env steps per window: about the wall time of a bare window

    r: dict[str, Any] = {"cpu_count": os.cpu_count(), "mujoco": mujoco.__version__, "quick": args.quick}
    # The stack a user runs has a trained model in the loop: train the equivariant model first
    # (on the field's own samples) and fly it; the oracle's figures follow under *_oracle.
    seconds_train, model, support = train_equivariant(0.5 if args.quick else 17.0, field)
    held = Support(support.lo - 10.0, support.hi + 10.0, support.margin)  # (its data's, widened to hold the flights)
    r["train_seconds_equivariant_full"] = seconds_train
    learned = LearnedPredictor(model, clamp=6.0)
    five = make_preset("formation5")  # the 5-vehicle preset, against its own bare step
    shed = make_field("shed")  # the wake with memory: the same flights with its state stepped (readable path)
    sets = LearnedPredictor(deepsets_equivariant(), clamp=6.0)
    recipes = load_recipes()  # a user's controller and field with compiled forms, as docs/extending.md writes them
    jet = recipes.CompiledGaussianJet()
    batched_seconds = seconds * 4 / worlds  # a batched window: about the wall time of a serial one on 2 cores
    flights = {  # key: (the flight, which continues from round to round; simulated seconds per window)
        "closed_loop_serial_steps_per_s": (closed_loop_sim(1, field, learned), seconds),
        "closed_loop_batched_world_steps_per_s": (closed_loop_sim(worlds, field, learned), batched_seconds),
        "closed_loop_serial_steps_per_s_oracle": (closed_loop_sim(1, field, OraclePredictor(field)), seconds),
        "closed_loop_batched_world_steps_per_s_oracle": (
            closed_loop_sim(worlds, field, OraclePredictor(field)), batched_seconds),
        "closed_loop_serial_steps_per_s_readable": (closed_loop_sim(1, field, learned, fast=False), seconds),
        "closed_loop_batched_world_steps_per_s_readable": (
            closed_loop_sim(worlds, field, learned, fast=False), batched_seconds),
        "closed_loop_serial_steps_per_s_guarded": (closed_loop_sim(1, field, GuardedPredictor(learned, held)), seconds),
        "closed_loop_batched_world_steps_per_s_guarded": (
            closed_loop_sim(worlds, field, GuardedPredictor(learned, held)), batched_seconds),
        "closed_loop_serial_steps_per_s_shed": (closed_loop_sim(1, shed, learned), seconds),
        "closed_loop_batched_world_steps_per_s_shed": (closed_loop_sim(worlds, shed, learned), batched_seconds),
        "closed_loop_serial_steps_per_s_pd_recipe": (
            closed_loop_sim(1, field, OraclePredictor(field), controller=recipes.CompiledPD()), seconds),
        "closed_loop_batched_world_steps_per_s_pd_recipe": (
            closed_loop_sim(worlds, field, OraclePredictor(field), controller=recipes.CompiledPD()), batched_seconds),
        "closed_loop_serial_steps_per_s_jet_recipe": (closed_loop_sim(1, jet, OraclePredictor(jet)), seconds),
        "closed_loop_batched_world_steps_per_s_jet_recipe": (
            closed_loop_sim(worlds, jet, OraclePredictor(jet)), batched_seconds),
        "closed_loop_serial_steps_per_s_mellinger": (
            closed_loop_sim(1, field, OraclePredictor(field), controller=MellingerController()), seconds),
        "closed_loop_batched_world_steps_per_s_mellinger": (
            closed_loop_sim(worlds, field, OraclePredictor(field), controller=MellingerController()), batched_seconds),
        "formation5_serial_world_steps_per_s": (closed_loop_sim(1, field, sets, preset=five), seconds),
        "formation5_batched_world_steps_per_s": (closed_loop_sim(worlds, field, sets, preset=five), batched_seconds),
        "formation5_serial_world_steps_per_s_summed": (closed_loop_sim(1, field, learned, preset=five), seconds),
        "formation5_batched_world_steps_per_s_summed": (
            closed_loop_sim(worlds, field, learned, preset=five), batched_seconds),
    }
    rollouts = {"mujoco_rollout_world_steps_per_s": MujocoRollout(worlds),
                "formation5_mujoco_rollout_world_steps_per_s": MujocoRollout(worlds, five)}
    beside = {"closed_loop_batched_world_steps_per_s": "mujoco_rollout_world_steps_per_s",
              "formation5_batched_world_steps_per_s": "formation5_mujoco_rollout_world_steps_per_s"}
    per_env_step = RATES.physics_per_control
    # key: (rate in physics steps per s (the envs': env steps x steps per env step), whose bare it is paired with)
    measure: dict[str, tuple[Any, Any]] = {
        "mujoco_batch_world_steps_per_s": (lambda: mujoco_batch_steps_per_s(worlds, n_bare * 4), None),
    }
    for key, (f, s) in flights.items():
        preset = five if key.startswith("formation5") else None
        if key in beside:  # MuJoCo's rollout of the scene, the same world-steps, next to our flight
            measure[beside[key]] = (lambda m=rollouts[beside[key]]: m.steps_per_s(n_bare * 4), preset)
            measure[beside[key] + "_no_timer"] = (
                lambda m=rollouts[beside[key]]: m.steps_per_s(n_bare * 4, timer=False), preset)
        measure[key] = (lambda f=f, s=s: closed_loop_steps_per_s(f, s), preset)
    measure.update({
        "env_steps_per_s_single": (lambda: env_steps_per_s_single(n_env, repeats=1) * per_env_step, None),
        "env_steps_per_s_vector64": (
            lambda: env_steps_per_s_vector(worlds, max(1, n_env // worlds * 4), repeats=1) * per_env_step, None),
    })
    bares = [f"bare_mj_step_per_s{scene}{timer}" for scene in ("", "_formation5") for timer in ("", "_no_timer")]
    rates: dict[str, list[float]] = {key: [] for key in (*bares, *measure)}
    ratios: dict[str, list[float]] = {key: [] for key in measure}
    no_timer: dict[str, list[float]] = {key: [] for key in measure}  # over the bare step without MuJoCo's timer
    # a ratio of two of our flights (a user's component or the guard against the built-in flight): after its own
    # window, each flight flies again right beside its partner, the order alternating by round (`side_by_side`)
    partners = {f"{flight}_{what}": f"{flight}{base}" for flight in ("closed_loop_serial_steps_per_s",
                                                                     "closed_loop_batched_world_steps_per_s")
                for what, base in (("pd_recipe", "_oracle"), ("jet_recipe", "_oracle"), ("mellinger", "_oracle"),
                                   ("guarded", ""))}
    beside_quotients: dict[str, list[float]] = {key: [] for key in partners}
    for i in range(repeats):
        for key in alternate(list(measure), beside, i):
            fn, preset = measure[key]
            scene = "" if preset is None else "_formation5"
            bare, bare_no_timer = bare_mj_step_per_s(n_bare, preset), bare_mj_step_per_s(n_bare, preset, timer=False)
            rate = fn()
            rates[f"bare_mj_step_per_s{scene}"].append(bare)
            rates[f"bare_mj_step_per_s{scene}_no_timer"].append(bare_no_timer)
            rates[key].append(rate)
            ratios[key].append(rate / bare)
            no_timer[key].append(rate / bare_no_timer)
            if key in partners:
                beside_quotients[key].append(side_by_side(fn, measure[partners[key]][0], i % 2 == 1))
    for m in rollouts.values():
        m.close()
    r.update({key: float(np.median(v)) for key, v in rates.items()})
    for key in ("env_steps_per_s_single", "env_steps_per_s_vector64"):  # back in env steps
        r[key] /= per_env_step
    ratio = {key: float(np.median(v)) for key, v in ratios.items()}
    rounds_of: dict[str, Any] = {}  # each simulation ratio's per-round values, for its interval
    for suffix in ("", "_oracle", "_readable", "_guarded", "_shed"):
        for name, flight in (("serial", "closed_loop_serial_steps_per_s"),
                             ("batched", "closed_loop_batched_world_steps_per_s")):
            r[f"{name}_over_bare{suffix}"] = ratio[f"{flight}{suffix}"]
            rounds_of[f"{name}_over_bare{suffix}"] = ratios[f"{flight}{suffix}"]
    beside_ratios = (("guarded", "guarded_over_unguarded"),  # what the guard costs: within 10 % of the model alone
                     ("pd_recipe", "compiled_controller_over_builtin"), ("jet_recipe", "compiled_field_over_builtin"),
                     ("mellinger", "mellinger_over_builtin"))
    for name in ("serial", "batched"):
        flight = f"closed_loop_{name}_{'steps' if name == 'serial' else 'world_steps'}_per_s"
        for what, ratio_name in beside_ratios:
            rounds_of[f"{ratio_name}_{name}"] = beside_quotients[f"{flight}_{what}"]
            r[f"{ratio_name}_{name}"] = float(np.median(beside_quotients[f"{flight}_{what}"]))
        # a user's controller and field through the public compiled contracts (controllers.compiled,
        # sim.field_contract), and the lab's Mellinger controller, each over bare (their ratios to the built-in LQR and
        # field above, side by side)
        for what in ("pd_recipe", "jet_recipe", "mellinger"):
            r[f"{name}_over_bare_{what}"] = ratio[f"{flight}_{what}"]
    for suffix in ("", "_oracle"):
        r[f"real_time_factor_serial{suffix}"] = r[f"closed_loop_serial_steps_per_s{suffix}"] * physics_dt
    r["mujoco_batch_over_bare"] = ratio["mujoco_batch_world_steps_per_s"]
    for ours, theirs in beside.items():  # each against its bare window, so a round's state cancels
        prefix = "formation5_" if ours.startswith("formation5") else ""
        r[f"{prefix}mujoco_rollout_over_bare"] = ratio[theirs]
        rounds_of[f"{prefix}batched_over_mujoco_rollout"] = np.array(ratios[ours]) / np.array(ratios[theirs])
        r[f"{prefix}batched_over_mujoco_rollout"] = float(np.median(rounds_of[f"{prefix}batched_over_mujoco_rollout"]))
        r[f"{prefix}batched_over_mujoco_rollout_no_timer"] = float(
            np.median(np.array(ratios[ours]) / np.array(ratios[theirs + "_no_timer"])))
    # the same flights against MuJoCo without its profiling timer, which the simulator turns off while it steps
    for key, name in (("closed_loop_serial_steps_per_s", "serial_over_bare_no_timer"),
                      ("closed_loop_batched_world_steps_per_s", "batched_over_bare_no_timer"),
                      ("formation5_serial_world_steps_per_s", "formation5_serial_over_bare_no_timer"),
                      ("formation5_batched_world_steps_per_s", "formation5_batched_over_bare_no_timer")):
        r[name] = float(np.median(no_timer[key]))
    for name in ("serial", "batched"):
        for suffix in ("", "_summed"):
            r[f"formation5_{name}_over_bare{suffix}"] = ratio[f"formation5_{name}_world_steps_per_s{suffix}"]
            rounds_of[f"formation5_{name}_over_bare{suffix}"] = ratios[f"formation5_{name}_world_steps_per_s{suffix}"]
    r["env_single_physics_over_bare"] = ratio["env_steps_per_s_single"]
    rounds_of["env_single_physics_over_bare"] = ratios["env_steps_per_s_single"]
    r["ratio_intervals"] = {key: median_interval(v) for key, v in sorted(rounds_of.items())}
    r["env_vector64_physics_over_bare"] = ratio["env_steps_per_s_vector64"]
    r["rounds"] = repeats
    r["batched_worlds"] = worlds
    r["predictor_us_per_call_batch64"] = predictor_us_per_call(learned, 64, 50 if args.quick else 2000)
    r["predictor_us_per_call_batch1"] = predictor_us_per_call(learned, 1, 50 if args.quick else 2000)
    r.update(sb3_rollouts(4 if args.quick else 16, 16 if args.quick else 256, 1 if args.quick else 3))
    r.update(swarm_rollouts(4 if args.quick else 16, 16 if args.quick else 200, 1 if args.quick else 5))
    r.update(contention(0.3 if args.quick else 2.0, 1 if args.quick else 5))
    r["targets"] = dict(TARGETS)
    return r


def side_by_side(fn: Any, partner: Any, partner_first: bool) -> float:
    """fn's rate over partner's, each one window right after the other (partner_first: partner's window first): two
    of our flights compared as paired rounds compare them, no bare window between them to add its own noise."""
    if partner_first:
        theirs = partner()
        return fn() / theirs
    ours = fn()
    return ours / partner()


def median_interval(values: Any, level: float = 0.95) -> list[float] | None:
    """[lo, hi]: a distribution-free interval of the median of independent rounds, the order statistics
    x_(k) and x_(n+1-k) (1-based) with k the largest for which P(B < k) <= (1 - level) / 2, B ~ Binomial(n, 1/2)
    (the median lies below x_(k) only if fewer than k rounds do): it holds the median with probability at
    least `level` whatever the rounds' distribution. 15 rounds give x_(4) and x_(12) (96.5 %). None when
    there are too few rounds for any such interval (fewer than 6 at 95 %)."""
    from scipy.stats import binom

    x = np.sort(np.asarray(values, dtype=np.float64))
    n = len(x)
    k = 0
    while k + 1 <= n // 2 and binom.cdf(k, n, 0.5) <= (1.0 - level) / 2.0:  # P(B <= k) = P(B < k + 1)
        k += 1
    return None if k == 0 else [float(x[k - 1]), float(x[n - k])]


def alternate(keys: list[str], beside: dict[str, str], round_index: int) -> list[str]:
    """`keys` in order, with each pair of `beside` (our flight: MuJoCo's rollout just before it) swapped on
    every other round, so that neither side of a pair always runs first."""
    if round_index % 2 == 0:
        return keys
    out = list(keys)
    for ours, theirs in beside.items():
        i, j = out.index(ours), out.index(theirs)
        out[i], out[j] = out[j], out[i]
    return out


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(BenchmarkArgs, "benchmark", argv, __doc__)
    with out_lock(args, "benchmark"):
        results = run(args)
        path = write_results(args.out, results, args)
    rows = [[k, v] for k, v in results.items() if isinstance(v, float)]
    print(format_table(rows, ["key", "value"]))
    print(f"\nwrote {path}")
    return results


cli = script(main)  # the console script (pyproject.toml); `python -m experiments.benchmark` runs __main__.py
