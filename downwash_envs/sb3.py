"""The native vector env as a stable-baselines3 `VecEnv` (needs the `rl` extra).

SB3 drives vector envs through its own `VecEnv` API, not Gymnasium's, so without
this adapter an SB3 user wraps single envs in `DummyVecEnv` and loses the batched
simulator (one `mujoco.batch.Batch` for every world, compiled control). The
adapter maps the two autoreset conventions: the native env resets a finished world
at its *next* step (`AutoresetMode.NEXT_STEP`), SB3 expects it reset in the *same*
step, with the last observation in ``info["terminal_observation"]`` and
``info["TimeLimit.truncated"]`` set when the time limit (not a crash) ended it. So
after each step the adapter resets the finished worlds at once, through the native
``reset(options={"reset_mask": done})``.

Example::

    from stable_baselines3 import PPO
    from downwash_envs.sb3 import make_vec_env

    venv = make_vec_env("downwash/Follower-v2", num_envs=16, seed=0)
    PPO("MlpPolicy", venv).learn(100_000)

World i of ``make_vec_env(..., seed=s)`` is the single env ``reset(seed=s + i)``, as in
the native env.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

__all__ = ["SB3VecEnv", "make_vec_env"]


class SB3VecEnv(VecEnv):
    """A Gymnasium vector env with next-step autoreset and a ``reset_mask`` reset option
    (`downwash_envs.follower.DownwashFollowerVectorEnv`), seen through SB3's `VecEnv` API."""

    def __init__(self, env: gym.vector.VectorEnv):
        if env.metadata.get("autoreset_mode") != AutoresetMode.NEXT_STEP:
            raise ValueError(f"env: expected a vector env with next-step autoreset, got "
                             f"{env.metadata.get('autoreset_mode')!r}")
        self.env = env
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)
        self._actions: np.ndarray | None = None

    # The env's attributes are those of the one native env that holds every world.
    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.env, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self.env, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        """Called once on the one native env; its result stands for every index asked for."""
        result = getattr(self.env, method_name)(*method_args, **method_kwargs)
        return [result] * len(self._get_indices(indices))

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(self._get_indices(indices))

    def reset(self) -> VecEnvObs:
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        obs, infos = self.env.reset(seed=seeds)
        self.reset_infos = _split_infos(infos, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait: call step_async (or step) first")
        obs, reward, terminated, truncated, infos = self.env.step(self._actions)
        self._actions = None
        done = terminated | truncated
        out_infos = _split_infos(infos, self.num_envs)
        for i in range(self.num_envs):
            out_infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        if done.any():
            final = obs[done]
            new_obs, reset_infos = self.env.reset(options={"reset_mask": done})
            obs = obs.copy()
            obs[done] = new_obs[done]
            reset_split = _split_infos(reset_infos, self.num_envs)
            for k, i in enumerate(np.flatnonzero(done)):
                out_infos[i]["terminal_observation"] = final[k]
                self.reset_infos[i] = reset_split[i]
        return obs, reward.astype(np.float32), done, out_infos

    def close(self) -> None:
        self.env.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        frames = self.env.render()
        return list(frames) if frames is not None else [None] * self.num_envs


def _split_infos(infos: dict[str, Any], n: int) -> list[dict[str, Any]]:
    """Gymnasium's vector infos (arrays with `_key` masks) as one dict per world."""
    out: list[dict[str, Any]] = [{} for _ in range(n)]
    for key, value in infos.items():
        if key.startswith("_"):
            continue
        mask = infos.get(f"_{key}", np.ones(n, bool))
        for i in np.flatnonzero(mask):
            out[i][key] = value[i]
    return out


def make_vec_env(env_id: str = "downwash/Follower-v2", num_envs: int = 16, seed: int | None = None,
                 **options: Any) -> SB3VecEnv:
    """`gymnasium.make_vec(env_id, num_envs, **options)` (the native batched env) for SB3;
    `seed` seeds the first reset (world i: seed + i)."""
    import downwash_envs  # noqa: F401  (registers the ids)

    venv = SB3VecEnv(gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **options))
    if seed is not None:
        venv.seed(seed)
    return venv
