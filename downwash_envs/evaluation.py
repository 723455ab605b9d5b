"""Evaluating the built-in LQR through the envs, and the envs' speed (for experiments.benchmark)."""

from __future__ import annotations

import time
from typing import Any, Callable

import gymnasium as gym
import numpy as np

from downwash_envs.config import DEFAULT_MAX_EPISODE_STEPS
from downwash_envs.follower import DownwashFollowerVectorEnv

__all__ = ["evaluate_lqr", "env_steps_per_s_single", "env_steps_per_s_vector", "SB3_BACKENDS", "sb3_rollout_steps_per_s"]


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


def env_steps_per_s_single(n_steps: int = 2000, *, repeats: int = 3, seed: int = 0, **options: Any) -> float:
    """Env steps per wall second of one `gymnasium.make("downwash/Follower-v1")` (with its
    wrappers), random actions, resets included; the best of `repeats` runs. The actions are
    drawn from the action space before the clock starts: the env's cost, not the sampler's
    (`Box.sample` alone costs about a third of an env step)."""
    env = gym.make("downwash/Follower-v1", **options)
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(n_steps)]
    env.reset(seed=seed)
    env.step(actions[0])  # warm-up

    def run() -> int:
        for action in actions:
            _, _, term, trunc, _ = env.step(action)
            if term or trunc:
                env.reset()
        return n_steps

    rate = _best_rate(run, repeats)
    env.close()
    return rate


def env_steps_per_s_vector(num_envs: int = 64, n_steps: int = 200, *, repeats: int = 3, seed: int = 0,
                           **options: Any) -> float:
    """Env steps (summed over worlds) per wall second of the native vector env
    (`gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`), random actions drawn
    before the clock starts, autoresets included; the best of `repeats` runs."""
    envs = gym.make_vec("downwash/Follower-v1", num_envs=num_envs, vectorization_mode="vector_entry_point", **options)
    envs.action_space.seed(seed)
    actions = [envs.action_space.sample() for _ in range(n_steps)]
    envs.reset(seed=seed)
    envs.step(actions[0])  # warm-up

    def run() -> int:
        for action in actions:
            envs.step(action)
        return n_steps * num_envs

    rate = _best_rate(run, repeats)
    envs.close()
    return rate


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
    fns = [lambda: gym.make("downwash/Follower-v1", **options) for _ in range(num_envs)]
    if backend == "native":
        venv = make_vec_env("downwash/Follower-v1", num_envs=num_envs, **options)
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
