"""Gymnasium environments: a follower quadrotor in a hovering leader's downwash.

The leader ("alpha") hovers; the follower ("bravo") tracks a reference below it,
through or beside the leader's wake, flying the full stack of `sim.simulator`
(motors, autopilot, Kalman-filtered motion capture, 500 Hz physics, the
ground-truth downwash field with turbulence). The agent commands the follower's
acceleration once per controller period.

Importing `downwash_envs` registers the ids with gymnasium and imports nothing else (no
MuJoCo, no torch: the entry points are strings). Without a prior import, use the
module-qualified id ``gymnasium.make("downwash_envs:downwash/Follower-v2")``.

- ``downwash/Follower-v2``: the paper's lemniscate beneath the leader, 0.6 m below
  it, 500 steps (10 s at 50 Hz).
- ``downwash/FollowerPasses-v2``: randomised passes and hovers through and beside
  the wake (the staged data collection's patterns), 0.5-1.2 m below, 1000 steps.

Every option of `downwash_envs.config.FollowerConfig` is a `make` keyword; `action_mode` is
``"residual"`` (default) or ``"acceleration"``. Example::

    import gymnasium as gym
    import downwash_envs  # registers the ids

    env = gym.make("downwash/Follower-v2", action_mode="residual", separation=0.5)
    obs, info = env.reset(seed=0)
    for _ in range(500):
        action = env.action_space.sample()  # (3,) in [-1, 1]: times action_bound m/s^2, added to the LQR command
        obs, reward, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            obs, info = env.reset()

    vec = gym.make_vec("downwash/Follower-v2", num_envs=64)   # native batched env
    obs, infos = vec.reset(seed=0)                           # (64, 30)
    obs, rewards, terminations, truncations, infos = vec.step(vec.action_space.sample())

The built-in LQR with and without the oracle (action 0 in residual mode; the
oracle is the env option ``predictor="oracle"``)::

    from downwash_envs import evaluate_lqr
    base = evaluate_lqr(oracle=False, seed=0)["pos_err_3d_mean"]    # m, the follower's mean 3D error
    oracle = evaluate_lqr(oracle=True, seed=0)["pos_err_3d_mean"]   # m, with the true mean field: lower

Modules (one role each):

- `downwash_envs.config`: `FollowerConfig` (the options), `make_config`, allowed values
- `downwash_envs.observation`: the observation layout, its bounds and its markdown table
- `downwash_envs.reward`: the reward and termination both tasks share
- `downwash_envs.engine`: the one engine, W worlds of a task on one simulator (`TaskWorlds`), and the
  per-episode vehicle randomisation (the `randomize` option)
- `downwash_envs.task`: the follower task on the engine (`FollowerWorlds`): episodes, references, observation
- `downwash_envs.swarm_task`: the swarm task on the engine (`SwarmWorlds`): options, episodes, observation
- `downwash_envs.rendering`: offscreen frames (EGL chosen automatically when headless)
- `downwash_envs.base`: the env side every env class shares: setup, spaces, rendering, the vector autoreset
- `downwash_envs.follower`: `DownwashFollowerEnv` and `DownwashFollowerVectorEnv`
- `downwash_envs.evaluation`: `evaluate_lqr` and the env speed benchmarks
- `downwash_envs.swarm`: the multi-agent env (PettingZoo `SwarmEnv` via `parallel_env`, batched `SwarmVectorEnv`)
- `downwash_envs.video`: mp4 of flights, conditions side by side, the wake drawn

The public names of these modules are also attributes of `downwash_envs`, imported on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

from gymnasium.envs.registration import register as _register
from gymnasium.envs.registration import registry as _registry

NAMESPACE = "downwash"  # gymnasium's namespace/Name-vN: the ids cannot collide with another package's
ENV_IDS = (f"{NAMESPACE}/Follower-v2", f"{NAMESPACE}/FollowerPasses-v2")

# id -> (make kwargs, max_episode_steps)
_SPECS = {
    f"{NAMESPACE}/Follower-v2": ({}, 500),
    f"{NAMESPACE}/FollowerPasses-v2": ({"reference": "passes", "separation": (0.5, 1.2)}, 1000),
}

for _id, (_kwargs, _steps) in _SPECS.items():
    if _id not in _registry:  # re-imports (importlib.reload) must not warn about overriding
        _register(
            id=_id,
            entry_point="downwash_envs.follower:DownwashFollowerEnv",
            vector_entry_point="downwash_envs.follower:DownwashFollowerVectorEnv",
            max_episode_steps=_steps,
            kwargs=_kwargs,
        )
del _id, _kwargs, _steps

# public name -> the module that defines it; imported on first access (PEP 562), so that
# `import downwash_envs` stays light
_LAZY = {
    **dict.fromkeys(("DownwashFollowerEnv", "DownwashFollowerVectorEnv"), "downwash_envs.follower"),
    **dict.fromkeys(("evaluate_lqr", "env_steps_per_s_single", "env_steps_per_s_vector"), "downwash_envs.evaluation"),
    **dict.fromkeys(("OBSERVATION", "OBS_DIM", "OBS_SLICES", "observation_table"), "downwash_envs.observation"),
    **dict.fromkeys(("REWARD_TERMS",), "downwash_envs.reward"),
    **dict.fromkeys(("SwarmEnv", "SwarmVectorEnv", "parallel_env"), "downwash_envs.swarm"),  # needs the multiagent extra
    **dict.fromkeys(("logs_video", "write_conditions_video"), "downwash_envs.video"),  # needs the video extra
    **dict.fromkeys((
        "FollowerConfig", "make_config", "ACTION_MODES", "ENV_REFERENCES", "ENV_REFERENCE_KWARGS", "PREDICTORS",
        "CONTROL_HZ_ALLOWED", "DEFAULT_MAX_EPISODE_STEPS", "DEFAULT_FIELD_RANDOMIZATION", "FIELD_RANDOMIZABLE",
        "VEHICLE_RANDOMIZABLE",
    ), "downwash_envs.config"),
}  # fmt: skip

__all__ = ["ENV_IDS", *_LAZY]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'downwash_envs' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
