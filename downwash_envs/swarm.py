"""A multi-agent swarm env: every follower of an N-vehicle preset is an agent (PettingZoo).

`SwarmEnv` is a `pettingzoo.ParallelEnv` (make it with `parallel_env(...)`, or `env(...)`
for PettingZoo's AEC API);
`SwarmVectorEnv` steps W such worlds at once on one `mujoco.batch.Batch` and returns
per-agent arrays with a leading world axis. Both are thin views of the swarm task,
`downwash_envs.swarm_task.SwarmWorlds` (W = 1 for the ParallelEnv), on the same engine as the
follower task (`downwash_envs.engine`; the env side and the vector autoreset:
`downwash_envs.base`): the flight is the full stack of `sim.simulator.Simulator`
on a `sim.presets` scene, every vehicle's wake acting on every other vehicle and
combined by the aggregation law (`sim.aggregation`). World k of
`SwarmVectorEnv.reset(seed=s)` is, bit for bit, `SwarmEnv.reset(seed=s + k)` (a test).

Example::

    from downwash_envs.swarm import parallel_env, SwarmVectorEnv

    env = parallel_env(preset="stack3", field="so2")
    obs, infos = env.reset(seed=0)                      # {"follower_0": (41,), "follower_1": (41,)}
    while env.agents:
        actions = {a: env.action_space(a).sample() for a in env.agents}
        obs, rewards, terminations, truncations, infos = env.step(actions)

    vec = SwarmVectorEnv(64, preset="stack3")
    obs, infos = vec.reset(seed=0)                      # {"follower_0": (64, 41), ...}
    obs, rewards, terminations, truncations, infos = vec.step({a: np.zeros((64, 3)) for a in vec.agents})

## Agents and actions
The agents are the preset's followers, named by role and rank in scene order
(`stack3`: follower_0 = bravo, follower_1 = charlie), so that libraries which group
agents by name (TorchRL, BenchMARL) put them in one group; the top vehicle, the
leader, flies its plain LQR. An agent's action is Box(-1, 1, (3,), float32), world
frame, normalised: a residual acceleration of action x b m/s^2 added to its LQR
command, as the single env's residual mode (b = `action_bound`, default 5); action 0
is the baseline controller. Actions are clipped to the box; NaN, inf, a wrong shape, a
missing or an unknown agent raise ValueError before any stepping.

## Observation
Box, float32, (21 + 10 K,) per agent, K = `max_neighbours` (default: every other
vehicle, V - 1). Positions and velocities are the vehicles' Kalman-filtered
motion-capture estimates, attitudes the onboard (true) ones, as in the single env
(whose entries the own block reuses, `downwash_envs.observation.OBSERVATION`). Then K
neighbour slots, one per other vehicle (the leader included), nearest first by the
estimated distance |dp| (ties in scene order); slots beyond the V - 1 others are
padding, all zero with mask 0; with K < V - 1 only the K nearest are seen. Slot k
(k = 0 .. K-1) starts at index 21 + 10 k. The layout is `observation_layout(K)`; this
table is `swarm_observation_table()` (a test checks it):

| index        | name            | meaning                                             | unit  | frame | bound |
|--------------|-----------------|-----------------------------------------------------|-------|-------|-------|
| 0-2          | v_follower      | follower velocity                                   | m/s   | world | 20    |
| 3-5          | pos_error       | p_follower - p_ref                                  | m     | world | 10    |
| 6-8          | vel_error       | v_follower - v_ref                                  | m/s   | world | 25    |
| 9-11         | ref_acc         | reference acceleration a_ref                        | m/s^2 | world | 25    |
| 12-14        | follower_x_axis | follower body x axis R_b[:, 0] (heading)            | -     | world | 1     |
| 15-17        | follower_z_axis | follower body z axis R_b[:, 2] (thrust direction)   | -     | world | 1     |
| 18-20        | last_action     | previous action as applied (0 after reset)          | m/s^2 | world | b     |
| 21+10k       | nk_mask         | 1: a vehicle in slot k; 0: padding (the slot all 0) | -     | -     | 1     |
| 21+10k+(1-3) | nk_dp           | p_follower - p_neighbour (as the single env's dp)   | m     | world | 10    |
| 21+10k+(4-6) | nk_dv           | v_follower - v_neighbour                            | m/s   | world | 40    |
| 21+10k+(7-9) | nk_z_axis       | neighbour body z axis R_n[:, 2] (its wake's axis)   | -     | world | 1     |

Entries are clipped to their bound; a diverged world's NaN reads 0.

## Reward
Per agent, the single env's terms (`downwash_envs.task.REWARD_TERMS`, same default weights),
each in ``info["reward_<term>"]`` and summed in that order (as `downwash_envs.task.task_terms`): alive bonus,
-w_p |e_p|, -w_v |e_v| (agent's true position / velocity error, capped at 10),
-w_a |a|^2 / b^2, -w_da |a - a_prev|^2 / b^2, and the termination penalty. The world
is shared, so its end is shared: every agent loses the alive bonus and pays the
penalty on the terminating step.

## Episode end
terminated (all agents at once): the world ended (`Simulator.status`: a collision
with the ground or between any two vehicles, divergence) or any follower left its
tracking box (farther than `max_tracking_error` from its reference, `Status.LEFT_BOX`).
truncated (all agents): after `duration` seconds (default the preset's), i.e.
round(duration * control_hz) steps. The ParallelEnv then empties `agents`.

## Info
reset: ``sim_seed`` (the world's noise seed) and ``phase`` (s, the start time within
the preset's references; 0 unless `random_phase`), and with `randomize` the agent's drawn
``mass_scale``, ``inertia_scale``, ``motor_lag_scale`` (those asked for). step: the reward terms,
``position_error`` (m), ``velocity_error`` (m/s), ``status`` (a `downwash_core.status.Status`
code), and the true downwash on the agent during the step's first autopilot tick
(the flight log row's): ``field_mean`` and ``field_applied`` (mean + turbulence),
(3,) m/s^2, world frame.

## Options
`preset`: a `sim.presets` spec ("pair", "stack3", "stack4", "stack:n=N", "swap",
"formation5") or a `Preset`; `field`: a field spec ("so2", "momentum:...", see
docs/fields.md) or object; `aggregation`: a `sim.aggregation` law spec ("linear", ...);
`max_neighbours`: K in 1-7 (None: V - 1); `duration`: s; `random_phase`: start each
episode at a drawn time of the preset's period (a custom `Preset` must then keep its
vehicles apart over the whole period, as the built-in ones do); and these `downwash_envs.config.FollowerConfig`
options, validated there: action_bound, control_hz, predictor ("none" | "oracle" | a predictor object),
max_tracking_error, the reward weights, sim_config, lqr, turbulence, render_width,
render_height, randomize (every agent's mass, inertia and motor lag drawn per episode,
each agent its own factors; the leader keeps its nominal vehicle). Unknown names raise
TypeError, bad values `downwash_core.errors.ConfigError`, both before anything is built.
`reset(options=...)`: the ParallelEnv takes none (any given are ignored with a warning:
PettingZoo's API test passes some), the vector env ``{"reset_mask": (W,) bool}``.
`step()` before the first `reset()` (also on an unpickled copy, which is a new env; in the
vector env, while any world has never been reset), or on a ParallelEnv whose episode has
ended, raises `downwash_envs.base.ResetNeededError`, a `gymnasium.error.ResetNeeded`.

## Rendering
``render_mode="rgb_array"``: one (render_height, render_width, 3) uint8 frame per
world (`downwash_envs.rendering`, EGL picked when headless), the camera framing the leader and
the vehicle farthest from it; the leader is tinted orange, bravo cyan.
``render_mode="human"``: MuJoCo's passive viewer (`downwash_envs.viewer`, as the follower
env's), opened at the first `reset()` and synced after every `step()`, paced to real time;
the leader orange, the followers cyan, every vehicle's wake drawn (each acts on the
others), every follower's current reference marked; `render()` returns None, `close()`
closes the window; the vector env shows world 0. Without a display the constructor
raises ConfigError saying what to do (``xvfb-run -a``, or "rgb_array").

Not provided: a global `state()` for centralised critics, and an AEC (`env()`) form.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from downwash_core.validate import count
from downwash_envs.base import (
    RENDER_MODES, AutoresetStep, ResetNeededError, TaskEnv, VectorAutoreset, agent_spaces, pickled_as_constructed,
)
from downwash_envs.config import make_config  # noqa: F401  (the shared options' validation, as before the split)
from downwash_envs.swarm_task import (  # noqa: F401  (the task's names, importable from here as before)
    NEIGHBOUR_DIM, NEIGHBOUR_OBSERVATION, OWN_DIM, OWN_OBSERVATION, SHARED_OPTIONS, SwarmConfig, SwarmEpisode,
    SwarmWorlds, observe_kernel, agent_names, draw_swarm_episode, make_swarm_config, neighbour_block, obs_dim,
    obs_slices, observation_layout, own_block, swarm_episode_info, swarm_obs_bounds, swarm_observation,
    swarm_observation_table,
)
from sim.aggregation import DEFAULT_AGGREGATION
from sim.physics import check_world_memory
from sim.presets import Preset
from sim.simulator import Simulator  # noqa: F401  (as before the split: tests replace it to catch early builds)

__all__ = [
    "SHARED_OPTIONS", "OWN_OBSERVATION", "NEIGHBOUR_OBSERVATION", "OWN_DIM", "NEIGHBOUR_DIM",
    "observation_layout", "obs_dim", "obs_slices", "swarm_obs_bounds", "swarm_observation_table",
    "own_block", "neighbour_block", "swarm_observation", "SwarmConfig", "make_swarm_config", "SwarmEpisode",
    "draw_swarm_episode",
    "agent_names", "SwarmWorlds", "SwarmEnv", "SwarmVectorEnv", "parallel_env", "env",
]  # fmt: skip


class _SwarmBase(TaskEnv):
    """The swarm task on the env engine: its options, its worlds, one pair of spaces per agent."""

    metadata: dict[str, Any]
    config: SwarmConfig
    _worlds: SwarmWorlds

    def _build_worlds(self, options: Mapping[str, Any], n_worlds: int, n_threads: int) -> SwarmWorlds:
        cfg = make_swarm_config(**options)
        check_world_memory(n_worlds, len(cfg.preset.vehicles), name="n_worlds")  # before anything is allocated
        return SwarmWorlds(cfg, n_worlds, n_threads)

    def _setup(self, options: dict[str, Any], render_mode: str | None, n_worlds: int, n_threads: int = 0) -> None:
        super()._setup(options, render_mode, n_worlds, n_threads)
        self.possible_agents: list[str] = list(self._worlds.agents)
        # one space object per agent, returned as is each time (PettingZoo's API test checks identity)
        self.observation_spaces, self.action_spaces = {}, {}
        low, high = self._worlds.obs_low, self._worlds.obs_high
        for a in self.possible_agents:
            self.observation_spaces[a], self.action_spaces[a] = agent_spaces(low, high)
        self.max_steps = self.config.max_steps

    def observation_space(self, agent: str) -> spaces.Box:
        """Box (obs_dim(K),) float32 of one agent in one world."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        """Box (3,) float32, m/s^2, of one agent in one world."""
        return self.action_spaces[agent]

    def close(self) -> None:
        self._close_renderer()

    def _open_viewer(self) -> None:
        """In human mode, open the window with every vehicle's wake drawn (not only the leader's, the
        follower env's default): here every vehicle's wake acts on the others."""
        if self.render_mode == "human" and self._renderer is None:
            from downwash_envs.viewer import Viewer

            sim = self._worlds.sim
            self._renderer = Viewer.of_simulator(sim, wake_vehicles=range(sim.V), what="render_mode='human'")


@pickled_as_constructed
class SwarmEnv(_SwarmBase, ParallelEnv):
    """Every follower of a preset is an agent; one world, plain `MjData` (see the module docstring).

    reset(seed): episodes draw from the env's generator (`self.np_random`); the same seed
    and the same actions give the same trajectory, bit for bit.
    """

    metadata = {"name": "downwash_swarm_v1", "render_modes": [*RENDER_MODES, "human"], "render_fps": 50,
                "is_parallelizable": True}  # fmt: skip

    def __init__(self, render_mode: str | None = None, **options: Any):
        self._setup(options, render_mode, n_worlds=1)
        self.agents: list[str] = []
        self.np_random: np.random.Generator | None = None
        self._elapsed = 0

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):
        if options:
            gym.logger.warn(f"reset options {sorted(options)} ignored: the swarm env takes none")
        if seed is not None or self.np_random is None:
            self.np_random, _ = seeding.np_random(seed)
        ep = self._worlds.new_episode(self.np_random)
        self._worlds.reset_worlds([0], [ep])
        self._mark_reset(0)
        self._elapsed = 0
        self.agents = list(self.possible_agents)
        obs = self._worlds.observe()[0]
        infos = swarm_episode_info(ep, len(self.agents))
        return {a: obs[i] for i, a in enumerate(self.possible_agents)}, dict(zip(self.agents, infos))

    def step(self, actions: Mapping[str, Any]):
        if not self.agents:
            self._check_reset()  # before the first reset(): say so
            raise ResetNeededError("step() with no live agents: the episode has ended; call reset()")
        a = self._worlds.check_actions(actions, self.agents, None)
        terminated, info = self._worlds.step(a, None)
        self._elapsed += 1
        obs = self._worlds.observe(fresh=False)[0]
        done = bool(terminated[0])
        trunc = self._elapsed >= self.max_steps
        # plain Python numbers per agent (one tolist per key), (3,) arrays for the field
        values = {k: (list(v[0]) if v.ndim == 3 else v[0].tolist()) for k, v in info.items()}
        rewards_all = values.pop("reward")
        observations, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for i, agent in enumerate(self.possible_agents):
            observations[agent] = obs[i]
            rewards[agent] = rewards_all[i]
            terms[agent], truncs[agent] = done, trunc
            infos[agent] = {k: v[i] for k, v in values.items()}
        if done or trunc:
            self.agents = []
        return observations, rewards, terms, truncs, infos

    def render(self):
        self._open_viewer()
        frames = self._frames((0,))
        return None if frames is None else frames[0]


@pickled_as_constructed
class SwarmVectorEnv(_SwarmBase, VectorAutoreset):
    """`n_worlds` swarm worlds on one `mujoco.batch.Batch`, per-agent arrays with a leading world axis.

    reset(seed=s) seeds world k with s + k (`reset(seed=[...])`: one per world), so world k
    equals `SwarmEnv.reset(seed=s + k)` step for step; `options={"reset_mask": (W,) bool}`
    resets only those worlds. step({agent: (W, 3)}) -> observations {agent: (W, D)}, rewards,
    terminations, truncations {agent: (W,)}, infos {agent: {key: (W, ...)}} (the ParallelEnv's
    keys). Autoreset on the next step (Gymnasium's default): the step after a world ends
    resets it; its actions are ignored, its reward is 0, terminated and truncated False,
    its observation the new episode's first, and ``infos[agent]["autoreset"]`` marks it
    (``sim_seed`` and ``phase`` give its episode). `reset_arrays` and `step_arrays` are reset and step
    without the per-agent dicts: whole (W, A, ...) arrays, agent i's at [:, i] (the SB3 adapter's path,
    `downwash_envs.swarm_sb3`). n_threads: the threads that step the worlds: 0 (default) one per
    core this process may use (its CPU affinity), 1..that many as given, anything else a
    ConfigError. Set 1 when other threads of the process need the cores, e.g. a learner's
    torch threads: the helper threads wait for work by spinning.
    """

    metadata = {"name": "downwash_swarm_vector_v1", "render_modes": [*RENDER_MODES, "human"], "render_fps": 50}

    def __init__(self, n_worlds: int = 8, render_mode: str | None = None, n_threads: int = 0, **options: Any):
        N = count("n_worlds", n_worlds, 1)
        self._setup(options, render_mode, n_worlds=N, n_threads=n_threads)
        self.n_worlds = N
        self.agents = list(self.possible_agents)  # every agent always has a row; ended worlds autoreset
        self._init_autoreset(N)
        # each world's episode info (`swarm_episode_info`), (W, A) per key; reported with every step
        A, spreads = len(self.agents), self.config.task.vehicle_spreads
        self._episode_info = {"sim_seed": np.zeros((N, A), np.int64), "phase": np.zeros((N, A)),
                              **{f"{k}_scale": np.ones((N, A)) for k in spreads}}

    def _record_episodes(self, worlds: np.ndarray, episodes: list[SwarmEpisode]) -> None:
        for w, ep in zip(worlds, episodes):
            for i, info in enumerate(swarm_episode_info(ep, len(self.agents))):
                for key, value in info.items():
                    self._episode_info[key][w, i] = value

    def _infos(self, info: dict[str, np.ndarray], resetting: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        """Each agent's infos: `info`'s (W, A, ...) columns, its episode info, and the autoreset mask."""
        infos = {}
        for i, ag in enumerate(self.possible_agents):
            infos[ag] = {k: v[:, i] for k, v in info.items() if k != "reward"}
            infos[ag].update({k: v[:, i].copy() for k, v in self._episode_info.items()}, autoreset=resetting.copy())
        return infos

    def reset(self, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None):
        obs, mask = self.reset_arrays(seed, options)
        return self._per_agent(obs), self._infos({}, mask)

    def step(self, actions: Mapping[str, Any]):
        self._check_reset()
        a = self._worlds.check_actions(actions, self.possible_agents, self.n_worlds)
        result = self._step_checked(a)
        info = result.outcome.info
        rewards = {ag: info["reward"][:, i] for i, ag in enumerate(self.possible_agents)}
        terms = {ag: result.terminated.copy() for ag in self.possible_agents}
        truncs = {ag: result.truncated.copy() for ag in self.possible_agents}
        return self._per_agent(result.obs), rewards, terms, truncs, self._infos(info, result.resetting)

    def _per_agent(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {a: obs[:, i] for i, a in enumerate(self.possible_agents)}

    # ---------------------------------------------------------------- the same, as whole arrays
    def reset_arrays(self, seed: Any = None, options: Mapping[str, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`reset(seed, options)` without the per-agent dicts: (observations (W, A, D) float32, agent i's at
        [:, i]; the reset worlds' mask (W,) bool); their episode info is in `episode_arrays`."""
        worlds, mask, episodes = self._seeded_reset(seed, options)
        self._record_episodes(worlds, episodes)
        return self._worlds.observe(), mask

    def step_arrays(self, actions: np.ndarray) -> AutoresetStep:
        """`step` without the per-agent dicts (the SB3 adapter's, `downwash_envs.swarm_sb3`): the actions as
        one (W, A, 3) array, agent i's at [:, i] (the same checks and errors); returns the autoreset step
        (`downwash_envs.base.AutoresetStep`): obs (W, A, D) float32 (a new array), terminated and truncated
        (W,), resetting, and ``outcome.info``, the task's {key: (W, A, ...)} columns, ``reward`` included.
        The episode info that `step` adds to each agent's info is `episode_arrays`."""
        self._check_reset()
        return self._step_checked(self._worlds.check_action_array(actions))

    @property
    def episode_arrays(self) -> dict[str, np.ndarray]:
        """Each world's current episode info, {key: (W, A)} (``sim_seed``, ``phase``, the drawn scales): the
        env's own arrays, rewritten at each reset (copy what you keep)."""
        return self._episode_info

    def _step_checked(self, actions: np.ndarray) -> AutoresetStep:
        result = self._autoreset_step(actions, self.max_steps)
        self._record_episodes(result.reset_indices, result.episodes)
        return result

    def render(self):
        self._open_viewer()
        frames = self._frames(range(self.n_worlds))
        return None if frames is None else tuple(frames)


def parallel_env(
    preset: str | Preset = "stack3",
    field: Any = "so2",
    aggregation: str = DEFAULT_AGGREGATION,
    max_neighbours: int | None = None,
    duration: float | None = None,
    render_mode: str | None = None,
    **options: Any,
) -> SwarmEnv:
    """The PettingZoo ParallelEnv (PettingZoo's module convention); options as `make_swarm_config`."""
    return SwarmEnv(render_mode=render_mode, preset=preset, field=field, aggregation=aggregation,
                    max_neighbours=max_neighbours, duration=duration, **options)


def env(**options: Any) -> Any:
    """The same env through PettingZoo's AEC API (agents act in turn; PettingZoo's module
    convention): `parallel_env(**options)` converted by `pettingzoo.utils.parallel_to_aec`."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(parallel_env(**options))
