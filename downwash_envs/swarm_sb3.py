"""The batched swarm env as a stable-baselines3 `VecEnv` for one shared policy (needs the `rl` extra).

SB3 learns one policy over a flat batch of envs; for a swarm whose agents share a policy
each agent of each world is one such env (one *slot*), as SuperSuit's
`pettingzoo_env_to_vec_env_v1` + `concat_vec_envs_v1` make of W copies of the ParallelEnv.
SuperSuit steps those copies one after the other, each on its own simulator; this adapter
steps all W worlds of a `downwash_envs.swarm.SwarmVectorEnv` in one batched simulator step
per `step_wait`.

Slots: num_envs = W x A (A agents, the preset's followers); slot ``w * A + i`` is agent
``possible_agents[i]`` of world w (SuperSuit's order). Actions (W x A, 3), observations
(W x A, D) float32, rewards (W x A,) float32, one info dict per slot with the
ParallelEnv's step keys and the episode's (``sim_seed``, ``phase``, the drawn scales).

Episode ends: a swarm world ends for all its agents at once (a crash, divergence or any
follower leaving its box terminates the world; the time limit truncates it), so the A slots
of a world are always done together and no slot ever waits, finished, for its world-mates:
there is no dead-agent filler. SB3 expects the reset in the same step, the native env resets
at its next one, so after a step the adapter resets the ended worlds at once (the native
``reset(options={"reset_mask": done})``): each of their slots gets done True,
``info["terminal_observation"]`` (its last observation), ``info["TimeLimit.truncated"]``
(True when the time limit, not a termination, ended it) and the new episode's first
observation; its ``reset_infos`` entry holds the new episode's info.

Seeding: ``seed(s)`` then ``reset()`` seeds world w with s + w, so world w is, step for step,
`SwarmEnv.reset(seed=s + w)` (and `SwarmVectorEnv.reset(seed=s)`'s world w); later resets
continue each world's generator.

Example::

    from stable_baselines3 import PPO
    from downwash_envs.swarm_sb3 import make_vec_env

    venv = make_vec_env(n_worlds=16, seed=0, preset="stack3")   # 32 slots: 16 worlds x 2 agents
    PPO("MlpPolicy", venv).learn(100_000)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import (
    VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn, tile_images,
)

from downwash_envs.swarm import SwarmVectorEnv

__all__ = ["SwarmSB3VecEnv", "make_vec_env"]


class SwarmSB3VecEnv(VecEnv):
    """A `SwarmVectorEnv` seen through SB3's `VecEnv` API, one slot per agent per world (see the module
    docstring for the slot order, the episode ends and the seeding)."""

    def __init__(self, env: SwarmVectorEnv):
        if not isinstance(env, SwarmVectorEnv):
            raise TypeError(f"env: expected a downwash_envs.swarm.SwarmVectorEnv, got {type(env).__name__}")
        mode = getattr(env, "autoreset_mode", AutoresetMode.NEXT_STEP)
        if mode != AutoresetMode.NEXT_STEP:  # the adapter resets ended worlds itself, through reset_mask
            raise ValueError(f"env: expected a vector env with next-step autoreset (the default), got {mode!r}")
        self.env = env
        self.agents: list[str] = list(env.possible_agents)
        self.n_worlds, self.n_agents = env.n_worlds, len(self.agents)
        # every agent has the same spaces (a shared policy needs that); the first stands for all
        first = self.agents[0]
        super().__init__(self.n_worlds * self.n_agents, env.observation_space(first), env.action_space(first))
        self._actions: np.ndarray | None = None

    # ------------------------------------------------------------------ seeding, reset
    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """World w gets seed + w at the next reset() (every slot of a world lists its world's seed)."""
        if seed is None:  # as SB3: drawn, so that later resets differ from run to run
            seed = int(np.random.randint(0, np.iinfo(np.uint32).max, dtype=np.uint32))
        self._seeds = [int(seed) + w for w in range(self.n_worlds) for _ in range(self.n_agents)]
        return self._seeds

    def set_options(self, options: list[dict] | dict | None = None) -> None:
        """The swarm's episodes are configured through the env's options, not reset options: any given
        here is refused at once rather than dropped at the next reset."""
        if options and (isinstance(options, dict) or any(options)):
            raise ValueError(f"set_options: the swarm env takes no reset options, got {options!r}; configure "
                             "episodes through the env's options (make_vec_env(..., duration=..., ...))")
        self._reset_options()

    def reset(self) -> VecEnvObs:
        world_seeds = self._seeds[:: self.n_agents]
        seeds = None if all(s is None for s in world_seeds) else list(world_seeds)
        obs, _ = self.env.reset_arrays(seed=seeds)
        self.reset_infos = self._episode_infos()
        self._reset_seeds()
        self._reset_options()
        self._actions = None
        return obs.reshape(self.num_envs, -1)

    # ------------------------------------------------------------------ step
    def step_async(self, actions: np.ndarray) -> None:
        """Store the (num_envs, 3) actions; a wrong shape is refused here, NaN or inf by the native
        env's check, both before any world steps."""
        actions = np.asarray(actions)
        expected = (self.num_envs, *self.action_space.shape)
        if actions.shape != expected:
            raise ValueError(f"actions: expected shape {expected} (worlds x agents, action), got {actions.shape}")
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        """One batched step of every world as whole arrays (no per-agent dicts on the way): slot w*A + i is
        row (w, i) of the native env's (W, A, ...) arrays, so observations, rewards and info columns are
        reshapes; only the info dicts are built per slot, from one list per key."""
        if self._actions is None:
            raise RuntimeError("step_wait: call step_async (or step) first")
        per_world = self._actions.reshape(self.n_worlds, self.n_agents, -1)
        self._actions = None
        result = self.env.step_arrays(per_world)
        terminated, truncated = result.terminated, result.truncated
        world_done = terminated | truncated  # a world's end is shared by its agents
        flat_obs = result.obs.reshape(self.num_envs, -1)  # the step's own fresh array: written below, not copied
        info = result.outcome.info
        reward = info["reward"].reshape(-1).astype(np.float32)
        done = world_done.repeat(self.n_agents)
        keys, episode = [k for k in info if k != "reward"], self.env.episode_arrays
        out_infos = self._slot_dicts(
            [*keys, *episode, "TimeLimit.truncated"],
            [*(info[k] for k in keys), *episode.values(), truncated & ~terminated],
        )
        if world_done.any():
            slots = np.flatnonzero(done)
            final = flat_obs[slots]  # a copy: the ended episodes' last observations
            new_obs, _ = self.env.reset_arrays(options={"reset_mask": world_done})
            flat_obs[slots] = new_obs.reshape(self.num_envs, -1)[slots]
            new_infos = self._episode_infos(slots)
            for slot, terminal, new_info in zip(slots.tolist(), final, new_infos):
                out_infos[slot]["terminal_observation"] = terminal
                self.reset_infos[slot] = new_info
        return flat_obs, reward, done, out_infos

    # ------------------------------------------------------------------ slots
    def _slot_dicts(self, keys: list[str], columns: list[np.ndarray], slots: np.ndarray | None = None
                    ) -> list[dict[str, Any]]:
        """One dict {key: value} per slot (or per slot of `slots`, in that order) from per-key columns of
        shape (W, A, ...) (or (W,): the world's, every agent's): plain Python numbers, (3,) arrays (views
        of the column) for vectors. One list per key, then each slot's dict from its values."""
        lists = []
        for column in columns:
            if column.ndim == 1:  # per world
                flat = column.repeat(self.n_agents)
            elif column.ndim == 2:
                flat = column.reshape(self.num_envs)
            else:
                flat = column.reshape(self.num_envs, *column.shape[2:])
            if slots is not None:
                flat = flat[slots]
            lists.append(flat.tolist() if flat.ndim == 1 else list(flat))
        return [dict(zip(keys, values)) for values in zip(*lists)]

    def _episode_infos(self, slots: np.ndarray | None = None) -> list[dict[str, Any]]:
        """The reset info of every slot (or of `slots`): its world's current episode's (the native
        ``sim_seed``, ``phase``, the drawn scales; not its ``autoreset`` mask)."""
        episode = self.env.episode_arrays
        return self._slot_dicts(list(episode), list(episode.values()), slots)

    def _checked_indices(self, indices: VecEnvIndices) -> list[int]:
        found = list(self._get_indices(indices))
        bad = [i for i in found if not -self.num_envs <= int(i) < self.num_envs]
        if bad:
            raise IndexError(f"indices: {bad} out of range for {self.num_envs} slots ({self.n_worlds} worlds x "
                             f"{self.n_agents} agents)")
        return found

    # ------------------------------------------------------------------ attributes, methods
    # Every slot's env is the one native env that holds every world.
    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.env, attr_name)] * len(self._checked_indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Sets it on the one native env, so for every slot, whichever `indices` are given."""
        self._checked_indices(indices)
        setattr(self.env, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        """Called once on the one native env; its result stands for every index asked for."""
        n = len(self._checked_indices(indices))
        result = getattr(self.env, method_name)(*method_args, **method_kwargs)
        return [result] * n

    def env_is_wrapped(self, wrapper_class: type, indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(self._checked_indices(indices))

    # ------------------------------------------------------------------ rendering, close
    def get_images(self) -> Sequence[np.ndarray | None]:
        """One frame per slot: each agent's world's frame."""
        frames = self.env.render()
        if frames is None:
            return [None] * self.num_envs
        return [frames[w] for w in range(self.n_worlds) for _ in range(self.n_agents)]

    def render(self, mode: str | None = None) -> np.ndarray | None:
        """``rgb_array``: the worlds' frames tiled, each world once (not once per agent)."""
        if self.render_mode == "rgb_array" and mode in (None, "rgb_array"):
            return tile_images(list(self.env.render()))
        return super().render(mode)

    def close(self) -> None:
        self.env.close()


def make_vec_env(n_worlds: int = 16, seed: int | None = None, render_mode: str | None = None, n_threads: int = 0,
                 **options: Any) -> SwarmSB3VecEnv:
    """`SwarmVectorEnv(n_worlds, **options)` for SB3, n_worlds x agents slots; `seed` seeds the first
    reset (world w: seed + w). Options as `downwash_envs.swarm`; n_threads as `SwarmVectorEnv`
    (set 1 when a learner's torch threads share the cores)."""
    venv = SwarmSB3VecEnv(SwarmVectorEnv(n_worlds, render_mode=render_mode, n_threads=n_threads, **options))
    if seed is not None:
        venv.seed(seed)
    return venv
