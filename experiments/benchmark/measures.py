"""What the benchmark measures, one function each: bare mj_step, MuJoCo's own batched stepping, the
closed loop serial and batched, the learned predictor's call, SB3's and the swarm's rollouts, the
cores shared, and the models flown in those flights.

Each returns its rate (or its record of rates); `experiments.benchmark.run` pairs every measurement
with a bare mj_step window of its scene, round by round, and takes the medians. The stack is
imported inside the functions (a fast `--help`).
"""

from __future__ import annotations

import contextlib
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from downwash_core.params import LEADER_POSITION, RATES

if TYPE_CHECKING:  # annotations only: the stack is imported where it is measured
    from downwash.predictor import LearnedPredictor
    from sim.simulator import Simulator

__all__ = ["LEADER", "start_data", "bare_mj_step_per_s", "mujoco_batch_steps_per_s", "MujocoRollout",
           "closed_loop_sim", "closed_loop_steps_per_s", "contention", "sb3_rollouts", "swarm_rollouts",
           "predictor_us_per_call", "deepsets_equivariant", "train_equivariant"]

LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here


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


def bare_mj_step_per_s(n_steps: int, preset: Any = None, timer: bool = True) -> float:
    """Plain mj_step of the two-vehicle scene (or of `preset`'s, its vehicles at their start), in a
    Python loop: what a user's own loop around MuJoCo costs. timer=False: with the bindings' profiling
    timer off, as the simulator steps (`sim.physics.profiling_timer_off`)."""
    import mujoco

    from sim.physics import profiling_timer_off

    model, data = start_data(preset)
    with profiling_timer_off() if not timer else contextlib.nullcontext():
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

    def steps_per_s(self, n_steps: int, timer: bool = True) -> float:
        """World steps per wall second of one rollout of about `n_steps` world steps in all; timer=False:
        with the bindings' profiling timer off, as the simulator steps."""
        if not timer:
            from sim.physics import profiling_timer_off

            with profiling_timer_off():
                return self.steps_per_s(n_steps)
        nstep = max(1, n_steps // self.n_worlds)
        t0 = time.perf_counter()
        self.pool.rollout(self.models, self.data, self.initial, nstep=nstep, skip_checks=True)
        return nstep * self.n_worlds / (time.perf_counter() - t0)

    def close(self) -> None:
        self.pool.close()


def closed_loop_sim(n_worlds: int, field: Any, predictor: Any, fast: bool = True, preset: Any = None,
                    controller: Any = None) -> Simulator:
    """The full stack with `predictor` at 45 Hz: the lemniscate 0.6 m below the leader, or `preset`'s
    flight; fast=False: the simulator's readable path; controller: None, the LQR. One tick flown
    (first-call costs)."""
    from downwash_trajectories import Hover, Lemniscate, stack
    from sim.scene import build_scene
    from sim.simulator import Simulator

    if preset is None:
        ref = stack([Hover(LEADER, n_worlds=n_worlds), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=n_worlds)])
        scene = build_scene()
    else:
        ref, scene = preset.reference(n_worlds), preset.scene()
    sim = Simulator(scene, ref, list(range(n_worlds)), field=field, predictor=predictor, fast=fast,
                    controller=controller)
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
