"""Speed of the simulation stack, as ratios measured in one run.

    python -m experiments.benchmark [--quick]

Every measurement runs once per round (`--repeats` rounds), each right after a window of bare
mj_step of its scene; a ratio is the median over rounds of the pair's ratio, a rate the median
over rounds (see `run`). `targets` holds the project's speed targets for four of the ratios.

Keys: bare_mj_step_per_s (the same scene, plain mj_step in a Python loop),
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
equivariant model summed over neighbours under formation5_*_summed.
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
Nothing here is a pass/fail test: the numbers are written down and printed.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from downwash_core.params import LEADER_POSITION, RATES
from experiments.common import (FLIGHT_SECONDS_MAX, CommonArgs, arg, format_table, load_field, out_lock, parse_args,
                                run_main, setup_logging, write_results, script)

if TYPE_CHECKING:  # annotations only: the stack is imported where it is measured
    from downwash.predictor import LearnedPredictor
    from sim.simulator import Simulator

LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here


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
           "swarm_native_over_supersuit": 3.0}


def start_data(preset: Any = None) -> tuple[Any, Any]:
    """(model, MjData) of the two-vehicle scene (or of `preset`'s) with its vehicles at their start: the
    state every bare and every MuJoCo-only window steps from, so that they step the same thing."""
    import mujoco

    from sim.scene import build_scene

    scene = build_scene() if preset is None else preset.scene()
    data = mujoco.MjData(scene.model)
    start = [[0, 0, 2.5], [0, 0, 1.9]] if preset is None else preset.reference(1)(np.zeros(1)).pos[0]
    data.qpos[scene.qpos_adr[:, None] + np.arange(3)] = start
    return scene.model, data


def bare_mj_step_per_s(n_steps: int, preset: Any = None) -> float:
    """Plain mj_step of the two-vehicle scene (or of `preset`'s, its vehicles at their start), in a
    Python loop: what a user's own loop around MuJoCo costs."""
    import mujoco

    model, data = start_data(preset)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        mujoco.mj_step(model, data)
    return n_steps / (time.perf_counter() - t0)


def mujoco_batch_steps_per_s(n_worlds: int, n_steps: int) -> float:
    """World steps per wall second of `mujoco.batch.Batch.step` alone (all cores, no control, 10 steps
    per call as the controller period): the physics' own ceiling for the batched ratios."""
    import mujoco.batch

    from sim.scene import build_scene

    batch = mujoco.batch.Batch(build_scene().model, n_worlds)
    calls = max(1, n_steps // (10 * n_worlds))
    t0 = time.perf_counter()
    for _ in range(calls):
        batch.step(nstep=10)
    return calls * 10 * n_worlds / (time.perf_counter() - t0)


class MujocoRollout:
    """MuJoCo's own batched stepping of a scene, to state our batched flights against: `mujoco.rollout`'s
    thread pool on the simulator's default threads (`sim.physics.resolve_threads(0)`), `n_worlds`
    worlds from the vehicles' start (`start_data`), no control. A window is one call with no state
    written out (there is no controller to stop for), so only MuJoCo's stepping is timed: its best
    rate on the scene, not a loop a user would write around it."""

    def __init__(self, n_worlds: int, preset: Any = None):
        import mujoco
        import mujoco.rollout

        from sim.physics import resolve_threads

        self.model, data = start_data(preset)
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        state = np.empty(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, data, state, spec)
        self.initial = np.ascontiguousarray(np.tile(state, (n_worlds, 1)))
        self.n_worlds = n_worlds
        n_threads = resolve_threads(0)
        self.pool = mujoco.rollout.Rollout(nthread=n_threads)
        self.data = [mujoco.MjData(self.model) for _ in range(n_threads)]
        self.models = [self.model] * n_worlds
        self.steps_per_s(n_worlds)  # first-call costs

    def steps_per_s(self, n_steps: int) -> float:
        """World steps per wall second of one rollout of about `n_steps` world steps in all."""
        nstep = max(1, n_steps // self.n_worlds)
        t0 = time.perf_counter()
        self.pool.rollout(self.models, self.data, self.initial, nstep=nstep, skip_checks=True)
        return nstep * self.n_worlds / (time.perf_counter() - t0)

    def close(self) -> None:
        self.pool.close()


def closed_loop_sim(n_worlds: int, field: Any, predictor: Any, fast: bool = True, preset: Any = None) -> Simulator:
    """The full stack with `predictor` at 45 Hz: the lemniscate 0.6 m below the leader, or `preset`'s
    flight; fast=False: the simulator's readable path. One tick flown (first-call costs)."""
    from downwash_trajectories import Hover, Lemniscate, stack
    from sim.scene import build_scene
    from sim.simulator import Simulator

    if preset is None:
        ref = stack([Hover(LEADER, n_worlds=n_worlds), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=n_worlds)])
        scene = build_scene()
    else:
        ref, scene = preset.reference(n_worlds), preset.scene()
    sim = Simulator(scene, ref, list(range(n_worlds)), field=field, predictor=predictor, fast=fast)
    sim.tick()
    return sim


def closed_loop_steps_per_s(sim: Simulator, seconds: float) -> float:
    """Physics steps per wall second, summed over the worlds still flying, of `seconds` more of `sim`'s
    flight (an ended world is not stepped, so it is not counted)."""
    n_ticks = int(round(seconds / sim.cfg.rates.control_dt))
    flying = int(sim.active.sum())
    t0 = time.perf_counter()
    for _ in range(n_ticks):
        sim.tick()
    return n_ticks * sim.cfg.rates.physics_per_control * flying / (time.perf_counter() - t0)


def run(args: BenchmarkArgs) -> dict:
    """Every measurement once per round, `repeats` rounds, each right after a bare mj_step window of
    its scene. This machine switches between a fast and a slow state every second or so (bare
    mj_step windows of 50 ms measure about 165k or 270k steps/s), so a ratio is the median over
    rounds of (rate / the bare rate just before it): both halves of a pair see the same state.
    Rates are medians over the rounds."""
    import mujoco

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
        measure[key] = (lambda f=f, s=s: closed_loop_steps_per_s(f, s), preset)
    measure.update({
        "env_steps_per_s_single": (lambda: env_steps_per_s_single(n_env, repeats=1) * per_env_step, None),
        "env_steps_per_s_vector64": (
            lambda: env_steps_per_s_vector(worlds, max(1, n_env // worlds * 4), repeats=1) * per_env_step, None),
    })
    rates: dict[str, list[float]] = {key: [] for key in ("bare_mj_step_per_s", "bare_mj_step_per_s_formation5", *measure)}
    ratios: dict[str, list[float]] = {key: [] for key in measure}
    for i in range(repeats):
        for key in alternate(list(measure), beside, i):
            fn, preset = measure[key]
            bare = bare_mj_step_per_s(n_bare, preset)
            rate = fn()
            rates["bare_mj_step_per_s" if preset is None else "bare_mj_step_per_s_formation5"].append(bare)
            rates[key].append(rate)
            ratios[key].append(rate / bare)
    for m in rollouts.values():
        m.close()
    r.update({key: float(np.median(v)) for key, v in rates.items()})
    for key in ("env_steps_per_s_single", "env_steps_per_s_vector64"):  # back in env steps
        r[key] /= per_env_step
    ratio = {key: float(np.median(v)) for key, v in ratios.items()}
    for suffix in ("", "_oracle", "_readable", "_guarded", "_shed"):
        r[f"serial_over_bare{suffix}"] = ratio[f"closed_loop_serial_steps_per_s{suffix}"]
        r[f"batched_over_bare{suffix}"] = ratio[f"closed_loop_batched_world_steps_per_s{suffix}"]
    for name in ("serial", "batched"):  # what the guard costs: within 10 % of the model alone
        r[f"guarded_over_unguarded_{name}"] = r[f"{name}_over_bare_guarded"] / r[f"{name}_over_bare"]
    for suffix in ("", "_oracle"):
        r[f"real_time_factor_serial{suffix}"] = r[f"closed_loop_serial_steps_per_s{suffix}"] * physics_dt
    r["mujoco_batch_over_bare"] = ratio["mujoco_batch_world_steps_per_s"]
    for ours, theirs in beside.items():  # each against its bare window, so a round's state cancels
        prefix = "formation5_" if ours.startswith("formation5") else ""
        r[f"{prefix}mujoco_rollout_over_bare"] = ratio[theirs]
        r[f"{prefix}batched_over_mujoco_rollout"] = float(np.median(np.array(ratios[ours]) / np.array(ratios[theirs])))
    for name in ("serial", "batched"):
        for suffix in ("", "_summed"):
            r[f"formation5_{name}_over_bare{suffix}"] = ratio[f"formation5_{name}_world_steps_per_s{suffix}"]
    r["env_single_physics_over_bare"] = ratio["env_steps_per_s_single"]
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


def contention(seconds: float, rounds: int) -> dict[str, Any]:
    """The vector env sharing the cores, with its default threads and with n_threads=1, alternated
    `rounds` times: an on-line learner's loop (16 worlds, one Adam update of a small MLP with
    torch at its default threads between env steps; `env_learner_loops_per_s`), and two
    processes of 64 worlds stepping at once against one alone (`concurrent_env_steps_per_s`).
    Medians of the rates and of the paired ratios: env_learner_threads_over_one_thread and
    two_processes_share_of_solo (the slower process's rate over the solo rate)."""
    from downwash_envs.evaluation import concurrent_env_steps_per_s, env_learner_loops_per_s

    loops: dict[int, list[float]] = {0: [], 1: []}
    solo: dict[int, list[float]] = {0: [], 1: []}
    share: dict[int, list[float]] = {0: [], 1: []}
    for _ in range(rounds):
        for n_threads in (0, 1):
            loops[n_threads].append(env_learner_loops_per_s(16, n_threads=n_threads, seconds=seconds, repeats=1))
            alone = concurrent_env_steps_per_s(1, 64, n_threads=n_threads, seconds=seconds)[0]
            together = concurrent_env_steps_per_s(2, 64, n_threads=n_threads, seconds=seconds)
            solo[n_threads].append(alone)
            share[n_threads].append(min(together) / alone)
    out: dict[str, Any] = {}
    for n_threads, suffix in ((0, ""), (1, "_one_thread")):
        out[f"env_learner_loops_per_s{suffix}"] = float(np.median(loops[n_threads]))
        out[f"env_steps_per_s_vector64_solo{suffix}"] = float(np.median(solo[n_threads]))
        out[f"two_processes_share_of_solo{suffix}"] = float(np.median(share[n_threads]))
    out["env_learner_threads_over_one_thread"] = float(np.median(np.array(loops[0]) / np.array(loops[1])))
    return out


def sb3_rollouts(num_envs: int, n_steps: int, rounds: int) -> dict[str, Any]:
    """SB3's rollout collection through the native vector env, SyncVectorEnv and DummyVecEnv,
    alternated `rounds` times (median rates, median paired ratios); empty without stable-baselines3."""
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        return {}
    import torch

    from downwash_envs.evaluation import SB3_BACKENDS, sb3_rollout_steps_per_s

    out: dict[str, Any] = {"sb3_worlds": num_envs}
    for suffix, threads in (("", 1), ("_torch_default_threads", torch.get_num_threads())):
        rates: dict[str, list[float]] = {b: [] for b in SB3_BACKENDS}
        for _ in range(rounds):
            for b in SB3_BACKENDS:
                rates[b].append(sb3_rollout_steps_per_s(num_envs, n_steps, backend=b, repeats=1, torch_threads=threads))
        for b in SB3_BACKENDS:
            out[f"sb3_rollout_steps_per_s_{b}{suffix}"] = float(np.median(rates[b]))
        for b in ("sync", "dummy"):
            out[f"sb3_native_over_{b}{suffix}"] = float(np.median(np.array(rates["native"]) / np.array(rates[b])))
        out[f"sb3_torch_threads{suffix}"] = threads
    return out


def swarm_rollouts(n_worlds: int, n_steps: int, rounds: int, preset: str = "stack3") -> dict[str, Any]:
    """Agent steps per wall second of `preset`'s swarm (the swarm env's default) under random actions, through
    the native SB3 adapter (its default threads, and n_threads=1: what batching alone gains) and through
    SuperSuit's `concat_vec_envs_v1` of `n_worlds` ParallelEnv copies (num_cpus=0, as examples/ppo_swarm.py
    ran it), the same worlds and agents and seeds; windows of `n_steps` steps, resets included, alternated
    `rounds` times (median rates, median paired ratios). Actions are drawn before the clock starts.
    Beside the native adapter, in the same rounds: MuJoCo's rollout of the preset's scene (`MujocoRollout`),
    the same worlds and simulated time, against the adapter's world-steps (its agent steps over the agents
    per world, times the physics steps per env step). Empty without the `rl` extra (stable-baselines3, SuperSuit)."""
    try:
        import stable_baselines3  # noqa: F401
        import supersuit as ss
    except ImportError:
        return {}
    from downwash_envs.swarm import parallel_env
    from downwash_envs.swarm_sb3 import make_vec_env

    backends = {
        "native": make_vec_env(n_worlds, preset=preset),
        "native_one_thread": make_vec_env(n_worlds, preset=preset, n_threads=1),
        "supersuit": ss.concat_vec_envs_v1(ss.pettingzoo_env_to_vec_env_v1(parallel_env(preset=preset)), n_worlds,
                                           num_cpus=0, base_class="stable_baselines3"),
    }
    num_envs = backends["native"].num_envs
    config = backends["native"].env.config
    mujoco_rollout = MujocoRollout(n_worlds, config.preset)
    physics_per_step = int(round(1.0 / (mujoco_rollout.model.opt.timestep * config.task.control_hz)))
    world_steps_per_agent_step = physics_per_step * n_worlds / num_envs
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, (n_steps, num_envs, 3)).astype(np.float32)
    for name, venv in backends.items():
        assert venv.num_envs == num_envs, (name, venv.num_envs, num_envs)
        if name == "supersuit":
            # copy w: SwarmEnv.reset(seed=w), as world w of the adapter seeded 0 (SuperSuit's SB3 wrapper
            # cannot pass a seed on: its reset(seed) calls the ConcatVecEnv's seed(), which it lacks)
            venv.venv.reset(seed=0)
        else:
            venv.seed(0)
            venv.reset()
        venv.step(actions[0])  # warm-up (first-call costs)

    def window(venv: Any) -> float:
        t0 = time.perf_counter()
        for a in actions:
            venv.step(a)
        return n_steps * num_envs / (time.perf_counter() - t0)

    rates: dict[str, list[float]] = {name: [] for name in backends}
    rollout_rates: list[float] = []
    for i in range(rounds):
        first = i % 2 == 0  # MuJoCo's rollout before the native adapter on even rounds, after it on odd ones
        for name, venv in backends.items():
            if name == "native" and first:
                rollout_rates.append(mujoco_rollout.steps_per_s(n_steps * physics_per_step * n_worlds))
            rates[name].append(window(venv))
            if name == "native" and not first:
                rollout_rates.append(mujoco_rollout.steps_per_s(n_steps * physics_per_step * n_worlds))
    for venv in backends.values():
        venv.close()
    mujoco_rollout.close()
    out: dict[str, Any] = {"swarm_preset": preset, "swarm_worlds": n_worlds, "swarm_agents": num_envs,
                           "swarm_rounds": rounds}
    for name in backends:
        out[f"swarm_agent_steps_per_s_{name}"] = float(np.median(rates[name]))
    supersuit = np.array(rates["supersuit"])
    out["swarm_native_over_supersuit"] = float(np.median(np.array(rates["native"]) / supersuit))
    out["swarm_native_one_thread_over_supersuit"] = float(np.median(np.array(rates["native_one_thread"]) / supersuit))
    native_world_steps = np.array(rates["native"]) * world_steps_per_agent_step
    out["swarm_world_steps_per_s_native"] = float(np.median(native_world_steps))
    out["swarm_mujoco_rollout_world_steps_per_s"] = float(np.median(rollout_rates))
    out["swarm_native_over_mujoco_rollout"] = float(np.median(native_world_steps / np.array(rollout_rates)))
    return out


def predictor_us_per_call(predictor: LearnedPredictor, n_worlds: int, n_calls: int) -> float:
    """Microseconds per call of a learned model in the predictor slot, at the states of n_worlds
    followers below a leader, with estimated states that differ from the true ones."""
    from downwash_core.state import VehicleStates

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


def deepsets_equivariant() -> Any:
    """A `deepsets_equivariant` model of sets (seeded initial weights) with four neighbour slots: every other
    vehicle of the 5-vehicle preset, as the swarm experiment flies it. Its output scale is 0: the kernel
    does all of its work (its cost does not depend on the weights) and predicts 0, so the flight flies
    on rather than ending in the crash an untrained model's push would cause."""
    import torch

    from downwash.checkpoint import Checkpoint
    from downwash.datasets import aggregation_record
    from downwash.registry import make_model
    from sim.neighbours import NeighbourSet

    torch.manual_seed(0)
    model = make_model("deepsets_equivariant").eval()
    model.out_scale.zero_()
    return Checkpoint(model, {"neighbours": NeighbourSet(4).describe(), "aggregation": aggregation_record("linear")})


def train_equivariant(minutes: float, field: Any) -> tuple[float, Any, Any]:
    """(wall seconds, model, the support of its data (`downwash.support`)): the equivariant model trained on
    `minutes` of 50 Hz samples of the true field.

    The samples are drawn like flight data (positions below the leader, speeds up to 1 m/s)
    with labels = true field + 0.1 m/s^2 noise: training cost depends on the sample count,
    not on where the labels came from.
    """
    from downwash.datasets import Dataset
    from downwash.train import TrainConfig, train_model

    rng = np.random.default_rng(0)
    n = int(minutes * 60 * 50)
    dp = np.stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), -rng.uniform(0.4, 1.8, n)], axis=1)
    v_b = rng.uniform(-1, 1, (n, 3)) * [1, 1, 0.3]
    v_a, R_a = np.zeros((n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    y = field(np.zeros((n, 3)), v_a, R_a, dp, v_b) + 0.1 * rng.normal(size=(n, 3))
    flight = np.arange(n) // 1425  # 28.5 s flights, as in the staged collection
    data = Dataset.from_pairs(dp, v_a, v_b, R_a, y, flight, t=(np.arange(n) % 1425) * RATES.control_dt, field_mean=y)
    t0 = time.perf_counter()
    model, _ = train_model("equivariant", data, None, TrainConfig(seed=0))
    return time.perf_counter() - t0, model, data.support()


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


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
