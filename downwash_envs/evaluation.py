"""Evaluating the built-in LQR through the envs, and the envs' speed (for experiments.benchmark)."""

from __future__ import annotations

import time
from typing import Any, Callable

import gymnasium as gym
import numpy as np

from downwash_envs.config import DEFAULT_MAX_EPISODE_STEPS
from downwash_envs.follower import DownwashFollowerVectorEnv

__all__ = ["evaluate_lqr", "env_steps_per_s_single", "env_steps_per_s_vector", "SB3_BACKENDS", "sb3_rollout_steps_per_s",
           "env_learner_loops_per_s", "concurrent_env_steps_per_s"]


def evaluate_lqr(
    oracle: bool,
    *,
    num_envs: int = 4,
    n_steps: int | None = None,
    seed: int = 0,
    **options: Any,
) -> dict[str, float]:
    """Fly the built-in LQR (residual action 0) for one episode per world; returns error statistics.

    oracle: True -> the LQR subtracts the true mean field (env option predictor="oracle").
    num_envs: worlds (seeds seed .. seed + num_envs - 1); the same seeds give the same
        episodes and noise with and without the oracle.
    n_steps: env steps per episode (default: DEFAULT_MAX_EPISODE_STEPS).
    options: further env options (reference, separation, control_hz, field knobs, ...).

    Returns pos_err_3d_mean (m), vel_err_3d_mean (m/s), pos_err_3d_peak (m),
    return_mean (episode reward), terminated (episodes ended early), env_steps.
    """
    options = {**options, "action_mode": "residual", "predictor": "oracle" if oracle else "none"}
    n_steps = DEFAULT_MAX_EPISODE_STEPS if n_steps is None else int(n_steps)
    env = DownwashFollowerVectorEnv(num_envs, max_episode_steps=n_steps, **options)
    env.reset(seed=seed)
    zeros = np.zeros((num_envs, 3), np.float32)
    alive = np.ones(num_envs, bool)
    pos, vel, peak, ret = [], [], np.zeros(num_envs), np.zeros(num_envs)
    terminated_any = np.zeros(num_envs, bool)
    for _ in range(n_steps):
        _, reward, term, trunc, info = env.step(zeros)
        pos.append(info["position_error"][alive])
        vel.append(info["velocity_error"][alive])
        peak = np.where(alive, np.maximum(peak, info["position_error"]), peak)
        ret += np.where(alive, reward, 0.0)
        terminated_any |= alive & term
        alive &= ~(term | trunc)  # each world's first episode only (the next step would autoreset it)
        if not alive.any():
            break
    env.close()
    return {
        "pos_err_3d_mean": float(np.concatenate(pos).mean()),
        "vel_err_3d_mean": float(np.concatenate(vel).mean()),
        "pos_err_3d_peak": float(peak.max()),
        "return_mean": float(ret.mean()),
        "terminated": int(terminated_any.sum()),
        "env_steps": int(sum(len(p) for p in pos)),
    }


def _best_rate(fn: Callable[[], int], repeats: int) -> float:
    """The best of `repeats` runs of `fn` (which returns how many steps it took), in steps per second."""
    best = 0.0
    for _ in range(repeats):
        t0 = time.perf_counter()
        n = fn()
        best = max(best, n / (time.perf_counter() - t0))
    return best


def _random_steps_per_s(env: Any, n_steps: int, repeats: int, seed: int, num_envs: int | None = None) -> float:
    """Steps (summed over worlds) per wall second of `env` under `n_steps` random actions drawn from
    its action space before the clock starts; the best of `repeats` runs; closes `env`.
    num_envs: a vector env's worlds (it autoresets); None: a single env, reset here when an episode ends."""
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(n_steps)]
    env.reset(seed=seed)
    env.step(actions[0])  # warm-up

    def run() -> int:
        for action in actions:
            _, _, term, trunc, _ = env.step(action)
            if num_envs is None and (term or trunc):
                env.reset()
        return n_steps * (num_envs or 1)

    rate = _best_rate(run, repeats)
    env.close()
    return rate


def env_steps_per_s_single(n_steps: int = 2000, *, repeats: int = 3, seed: int = 0, **options: Any) -> float:
    """Env steps per wall second of one `gymnasium.make("downwash/Follower-v2")` (with its
    wrappers), random actions, resets included; the best of `repeats` runs. The actions are
    drawn from the action space before the clock starts: the env's cost, not the sampler's
    (`Box.sample` alone costs about a third of an env step)."""
    return _random_steps_per_s(gym.make("downwash/Follower-v2", **options), n_steps, repeats, seed)


def env_steps_per_s_vector(num_envs: int = 64, n_steps: int = 200, *, repeats: int = 3, seed: int = 0,
                           **options: Any) -> float:
    """Env steps (summed over worlds) per wall second of the native vector env
    (`gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`), random actions drawn
    before the clock starts, autoresets included; the best of `repeats` runs."""
    envs = gym.make_vec("downwash/Follower-v2", num_envs=num_envs, vectorization_mode="vector_entry_point", **options)
    return _random_steps_per_s(envs, n_steps, repeats, seed, num_envs)


SB3_BACKENDS = ("native", "sync", "dummy")


def sb3_rollout_steps_per_s(num_envs: int = 16, n_steps: int = 256, *, backend: str = "native", repeats: int = 3,
                            seed: int = 0, torch_threads: int = 1, **options: Any) -> float:
    """Env steps (summed over worlds) per wall second of stable-baselines3's PPO rollout
    collection (`collect_rollouts`: the policy's forward pass, the env steps, the buffer)
    through `backend`: "native", the native vector env through the adapter
    (`downwash_envs.sb3`); "sync", Gymnasium's `SyncVectorEnv` of `num_envs` single envs
    through the same adapter; "dummy", SB3's own `DummyVecEnv` of single envs (what SB3
    users get without the adapter). The best of `repeats` rollouts of `n_steps` steps.
    Needs the `rl` extra.

    torch_threads: torch's intra-op threads during the measurement (restored after);
    one suits a small MLP policy, and on a small machine more take the simulator's cores."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from downwash_envs.sb3 import SB3VecEnv, make_vec_env

    if backend not in SB3_BACKENDS:
        raise ValueError(f"backend: expected one of {list(SB3_BACKENDS)}, got {backend!r}")
    fns = [lambda: gym.make("downwash/Follower-v2", **options) for _ in range(num_envs)]
    if backend == "native":
        venv = make_vec_env("downwash/Follower-v2", num_envs=num_envs, **options)
    elif backend == "sync":
        venv = SB3VecEnv(gym.vector.SyncVectorEnv(fns))
    else:
        venv = DummyVecEnv(fns)
    venv.seed(seed)
    model = PPO("MlpPolicy", venv, n_steps=n_steps, batch_size=n_steps, seed=seed, device="cpu")
    _, callback = model._setup_learn(n_steps * num_envs * (repeats + 1), callback=None)
    callback.on_training_start(locals(), globals())

    def run() -> int:
        model.collect_rollouts(model.env, callback, model.rollout_buffer, n_rollout_steps=n_steps)
        return n_steps * num_envs

    threads = torch.get_num_threads()
    torch.set_num_threads(torch_threads)
    try:
        model.collect_rollouts(model.env, callback, model.rollout_buffer, n_rollout_steps=8)  # warm-up
        rate = _best_rate(run, repeats)
    finally:
        torch.set_num_threads(threads)
    venv.close()
    return rate


def env_learner_loops_per_s(num_envs: int = 16, *, n_threads: int = 0, seconds: float = 2.0, repeats: int = 3,
                            seed: int = 0) -> float:
    """Iterations per wall second of the loop of an on-line learner: one step of the native vector
    env (random actions), then one Adam update of a small MLP (two hidden layers of 64, a batch
    of 256) with torch at its default threads; the best of `repeats` spells of `seconds`.
    The simulator's helper threads and torch's share the cores: this measures whether the
    helpers stay out of the learner's way (n_threads: the env's option; 1, no helpers)."""
    import torch

    envs = gym.make_vec("downwash/Follower-v2", num_envs=num_envs, vectorization_mode="vector_entry_point",
                        n_threads=n_threads)
    envs.reset(seed=seed)
    envs.action_space.seed(seed)
    actions = [envs.action_space.sample() for _ in range(64)]
    generator = torch.Generator().manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(32, 64), torch.nn.Tanh(), torch.nn.Linear(64, 64), torch.nn.Tanh(),
                              torch.nn.Linear(64, 1))
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    x, y = torch.randn(256, 32, generator=generator), torch.randn(256, 1, generator=generator)

    def iteration(k: int) -> None:
        envs.step(actions[k % len(actions)])
        optimizer.zero_grad()
        torch.nn.functional.mse_loss(net(x), y).backward()
        optimizer.step()

    for k in range(20):  # warm-up
        iteration(k)
    best = 0.0
    for _ in range(repeats):
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            iteration(n)
            n += 1
        best = max(best, n / (time.perf_counter() - t0))
    envs.close()
    return best


def _env_steps_in_process(num_envs: int, n_threads: int, seconds: float, seed: int, ready: Any, start: Any,
                          rates: Any) -> None:
    envs = gym.make_vec("downwash/Follower-v2", num_envs=num_envs, vectorization_mode="vector_entry_point",
                        n_threads=n_threads)
    envs.reset(seed=seed)
    envs.action_space.seed(seed)
    actions = [envs.action_space.sample() for _ in range(64)]
    for action in actions[:10]:  # warm-up
        envs.step(action)
    ready.put(True)
    start.wait()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        envs.step(actions[n % len(actions)])
        n += 1
    rates.put(n * num_envs / (time.perf_counter() - t0))
    envs.close()


def concurrent_env_steps_per_s(n_processes: int = 2, num_envs: int = 64, *, n_threads: int = 0,
                               seconds: float = 3.0, seed: int = 0) -> list[float]:
    """Env steps (summed over worlds) per wall second of each of `n_processes` processes that step
    a native vector env at the same time (as a subprocess vector env or several seeds of an RL
    run do); started together once every process has built its env. n_threads: each env's option."""
    import multiprocessing
    from queue import Empty

    ctx = multiprocessing.get_context("spawn")
    ready, start, rates = ctx.Queue(), ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_env_steps_in_process, args=(num_envs, n_threads, seconds, seed + i, ready, start, rates))
             for i in range(n_processes)]
    for proc in procs:
        proc.start()
    try:
        result = []
        for queue, wanted in ((ready, n_processes), (rates, n_processes)):
            got = []
            while len(got) < wanted:  # a process that failed ends the wait (its traceback is on stderr)
                try:
                    got.append(queue.get(timeout=1.0))
                except Empty:
                    if any(proc.exitcode not in (None, 0) for proc in procs):
                        raise RuntimeError("a benchmark process ended before reporting; see its error above") from None
            if queue is ready:
                start.set()
            result = got
    finally:
        for proc in procs:
            proc.join(timeout=60)
            if proc.is_alive():
                proc.kill()
    return sorted(result)
