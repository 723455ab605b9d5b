"""The follower downwash_envs: `DownwashFollowerEnv` (gymnasium.Env) and `DownwashFollowerVectorEnv`.

Two thin classes on the one engine (the follower task `downwash_envs.task.FollowerWorlds`
on `downwash_envs.engine.TaskWorlds`, bound to the env side by `downwash_envs.base.FollowerEnvBase`;
the vector env's autoreset is `downwash_envs.base.VectorAutoreset`, shared with the swarm's):

- `DownwashFollowerEnv`: a `gymnasium.Env` (one world, plain `MjData`).
- `DownwashFollowerVectorEnv`: a native `gymnasium.vector.VectorEnv` whose worlds
  share one `mujoco.batch.Batch` (each of Gymnasium 1.x's autoreset modes; next step,
  its default, unless asked). Step for step it equals `gymnasium.vector.SyncVectorEnv`
  of single envs made with the same options, seeds and autoreset mode (world i of
  `reset(seed=s)` uses seed s + i).
"""

from __future__ import annotations

from typing import Any, Sequence

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from downwash_core.validate import count
from downwash_envs.base import (
    RENDER_MODES, FollowerEnvBase, VectorAutoreset, check_autoreset_mode, check_reset_options, make_spaces,
    pickled_as_constructed,
)
from downwash_envs.config import DEFAULT_MAX_EPISODE_STEPS
from downwash_envs.task import Episode, episode_info
from sim.physics import check_world_memory

__all__ = ["DownwashFollowerEnv", "DownwashFollowerVectorEnv"]


@pickled_as_constructed
class DownwashFollowerEnv(FollowerEnvBase, gym.Env):
    """The follower tracks a reference below a hovering leader, in the leader's downwash.

    ## Actions
    Box(-1, 1, (3,), float32), world frame (z up), normalised: action x b is the
    acceleration in m/s^2, b = `action_bound` (default 5 in residual mode, 10 in
    acceleration mode); clipped to the box; NaN, inf or a wrong shape raise ValueError
    before any stepping.

    - ``residual``: added to the follower's LQR acceleration command
      `u = a_ref - K (x - x_ref) - f_hat`; action 0 is the plain LQR (the
      compensation task: the ideal action cancels the downwash, -f).
    - ``acceleration``: the follower's whole acceleration command (gravity
      excluded; its feedback linearisation still turns it into thrust and tilt,
      tilt limited to 35 deg, vertical specific force >= 0.25 g).

    ## Observation
    Box, float32, (30,); the vehicle's own knowledge: positions and velocities are
    the Kalman-filtered motion-capture estimates at the observation time, attitudes
    the onboard (true) ones; the reference is sampled at the same time. The layout
    is `downwash_envs.observation.OBSERVATION` (this table is `downwash_envs.observation.observation_table()`,
    which a test checks):

    | index | name            | meaning                                           | unit  | frame | bound |
    |-------|-----------------|---------------------------------------------------|-------|-------|-------|
    | 0-2   | dp              | p_follower - p_leader                             | m     | world | 10    |
    | 3-5   | v_follower      | follower velocity                                 | m/s   | world | 20    |
    | 6-8   | v_leader        | leader velocity                                   | m/s   | world | 20    |
    | 9-11  | pos_error       | p_follower - p_ref                                | m     | world | 10    |
    | 12-14 | vel_error       | v_follower - v_ref                                | m/s   | world | 25    |
    | 15-17 | ref_acc         | reference acceleration a_ref                      | m/s^2 | world | 25    |
    | 18-20 | follower_x_axis | follower body x axis R_b[:, 0] (heading)          | -     | world | 1     |
    | 21-23 | follower_z_axis | follower body z axis R_b[:, 2] (thrust direction) | -     | world | 1     |
    | 24-26 | leader_z_axis   | leader body z axis R_a[:, 2] (the wake's axis)    | -     | world | 1     |
    | 27-29 | last_action     | previous action as applied (0 after reset)        | m/s^2 | world | b     |

    Entries are clipped to their bound (never reached in a live episode: the
    tracking box ends it first).

    ## Reward
    reward = sum of six terms, each in ``info["reward_<name>"]`` (REWARD_TERMS order),
    from the true state at the end of the step, e_p = p - p_ref, e_v = v - v_ref:

    | term        | value                                                   | default weight |
    |-------------|---------------------------------------------------------|----------------|
    | alive       | +alive_reward while the episode goes on                 | 1.0            |
    | position    | -position_cost_weight * norm(e_p)  (m)                  | 2.0            |
    | velocity    | -velocity_cost_weight * norm(e_v)  (m/s)                | 0.5            |
    | action      | -action_cost_weight * norm(a)^2 / b^2                   | 0.05           |
    | action_rate | -action_rate_cost_weight * norm(a - a_prev)^2 / b^2     | 0.05           |
    | termination | -termination_penalty on the terminating step            | 50.0           |

    The alive bonus and the termination penalty keep crashing from paying off;
    the action-rate term discourages chattering that the motors (30 ms lag) cannot
    follow. norm(e_p) and norm(e_v) are capped at 10 (a diverged state is not finite).

    ## Episode end
    terminated: collision with the ground or the leader, divergence (NaN, MuJoCo
    instability), or the follower farther than `max_tracking_error` (default 1 m)
    from its reference (the tracking box). ``info["status"]`` is a `downwash_core.status.Status`
    code: 0 ok, 1 diverged, 2 ground collision, 3 vehicle collision, 4 left the box
    (`Status(code).label` gives the name).
    truncated: by gymnasium's TimeLimit at the registered max_episode_steps.

    ## Info
    reset: the drawn episode parameters: ``separation`` (m; passes: the first
    waypoint's depth), ``mass_scale``, ``field_scale_<constant>`` per randomised
    field constant, and with `randomize` ``inertia_scale`` and ``motor_lag_scale``
    where drawn. step: the reward terms ``reward_<name>``, ``position_error`` (m)
    and ``velocity_error`` (m/s) (true state, capped), ``status``.

    ## Options
    See `downwash_envs.config.FollowerConfig` (every field is a keyword); unknown names raise
    TypeError naming the allowed ones, bad values ValueError naming the allowed range.
    `reset(options=...)` takes no options. `step()` before the first `reset()` (also on an
    unpickled copy, which is a new env) raises `gymnasium.error.ResetNeeded`. Randomness:
    every episode draws its parameters and its noise seed from `self.np_random`.

    ## Rendering
    ``render_mode="rgb_array"``: `render()` returns a (render_height, render_width, 3)
    uint8 frame; on a headless Linux machine EGL is chosen automatically (see
    `downwash_envs.rendering`). ``render_mode="human"``: MuJoCo's passive viewer with
    the leader's wake drawn, synced at each step (`downwash_envs.viewer`); without a
    display it fails at construction, saying what to do.

    ## Version history
    See docs/envs.md, "Versions": an id's version moves whenever the same seed and actions
    can give other observations, rewards or terminations, or a space changes.

    - v2: rotor saturation keeps attitude first (an episode whose actions saturate the
      rotors flies differently from v1); `step()` before `reset()` raises `ResetNeeded`.
    - v1: ids in the ``downwash`` namespace; observations float32; actions normalised to
      [-1, 1] (x `action_bound` m/s^2); flights bit-identical on every CPU.
    - v0 (``DownwashFollower-v0``, ``DownwashFollowerPasses-v0``): float64 observations,
      actions in m/s^2.
    """

    metadata = {"render_modes": [*RENDER_MODES, "human"], "render_fps": 50}

    def __init__(self, render_mode: str | None = None, **options: Any):
        if "autoreset_mode" in options:  # make_vec(..., vectorization_mode="sync") passes its keywords here
            raise TypeError(
                "autoreset_mode: an option of the vector env, not of the single env; for "
                "gym.make_vec(..., vectorization_mode='sync') pass vector_kwargs={'autoreset_mode': ...}"
            )
        self._setup(options, render_mode, n_worlds=1)
        self.observation_space, self.action_space = make_spaces(self.config)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        check_reset_options(options, allowed=())
        ep = self._worlds.new_episode(self.np_random)
        self._worlds.reset_worlds([0], [ep])
        self._mark_reset(0)
        return self._worlds.observe()[0], episode_info(self.config, ep)

    def step(self, action: Any):
        self._check_reset()
        a = self._worlds.check_actions(action, (3,))
        out = self._worlds.step(a[None], None)
        obs = self._worlds.observe(fresh=False)[0]
        return obs, out.reward[0].item(), bool(out.terminated[0]), False, out.world_info(0)

    def render(self):
        frames = self._frames((0,))
        return None if frames is None else frames[0]

    def close(self) -> None:
        self._close_renderer()


@pickled_as_constructed
class DownwashFollowerVectorEnv(FollowerEnvBase, VectorAutoreset, VectorEnv):
    """`num_envs` follower worlds on one `mujoco.batch.Batch`: Gymnasium's VectorEnv API.

    Observations (num_envs, 30), actions (num_envs, 3), rewards/terminations/
    truncations (num_envs,), infos a dict of arrays with ``_key`` masks, as
    `SyncVectorEnv` builds them. Step for step identical to `SyncVectorEnv` of
    `DownwashFollowerEnv`s with the same options, seeds and autoreset mode: world i of
    `reset(seed=s)` uses seed s + i; `reset(seed=[...])` one per world.

    autoreset_mode: a `gymnasium.vector.AutoresetMode` or its value (also
    `metadata["autoreset_mode"]` and the attribute `autoreset_mode`), as `SyncVectorEnv`:

    - ``NextStep`` (default): the step after a world terminates or truncates resets it
      (its action is ignored, reward 0, terminated and truncated False, the reset's
      observation and info).
    - ``SameStep``: the step on which a world ends resets it at once: its reward and flags
      are the ending step's, its observation and info the new episode's;
      ``infos["final_obs"]`` (an object array, None elsewhere) and ``infos["final_info"]``
      (a vector info dict) hold the ended episode's last ones, masked by ``_final_obs``
      and ``_final_info``.
    - ``Disabled``: no world resets by itself; `reset(options={"reset_mask": mask})`
      resets the ended ones, and `step()` while one has not been raises
      `downwash_envs.base.EpisodeEndedError` (an AssertionError, as `SyncVectorEnv`'s
      refusal, and a `gymnasium.error.ResetNeeded`) before any world steps.

    num_envs: worlds. max_episode_steps: truncation horizon (None or -1: none;
    `make_vec` passes the registered one). n_threads: the threads that step the worlds: 0 (default) one per
    core this process may use (its CPU affinity), 1..that many as given, anything else a
    ConfigError. Set 1 when other threads of the process need the cores, e.g. a learner's
    torch threads: the helper threads wait for work by spinning.
    Other keywords: `FollowerConfig` (see `DownwashFollowerEnv` for the spaces,
    reward and termination). `reset(options={"reset_mask": mask})` resets only
    the masked worlds; `step()` raises `gymnasium.error.ResetNeeded` while any world has never
    been reset. `render()` returns one frame per world.

    `gym.make_vec(id, num_envs, autoreset_mode=...)` passes the mode here (the vector
    entry point takes keywords, not `vector_kwargs`).
    """

    metadata = {"render_modes": [*RENDER_MODES, "human"], "render_fps": 50, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 8,
        render_mode: str | None = None,
        max_episode_steps: int | None = DEFAULT_MAX_EPISODE_STEPS,
        n_threads: int = 0,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        **options: Any,
    ):
        mode = check_autoreset_mode(autoreset_mode)
        N = count("num_envs", num_envs, 1)
        check_world_memory(N, 2, name="num_envs")  # the leader and the follower; before anything is allocated
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer))
            or (max_episode_steps < 1 and max_episode_steps != -1)
        ):
            raise ValueError(
                f"max_episode_steps: expected None, -1 (no limit) or an integer >= 1, got {max_episode_steps!r}"
            )
        self._setup(options, render_mode, n_worlds=N, n_threads=n_threads)
        self.metadata["autoreset_mode"] = mode  # this instance's (the class's is the default)
        self.num_envs = N
        self.max_episode_steps = None if max_episode_steps in (None, -1) else int(max_episode_steps)
        self.single_observation_space, self.single_action_space = make_spaces(self.config)
        self.observation_space = batch_space(self.single_observation_space, N)
        self.action_space = batch_space(self.single_action_space, N)
        self._init_autoreset(N, mode)

    def _reset_info(self, worlds: np.ndarray, episodes: list[Episode]) -> dict[str, np.ndarray]:
        """The reset infos of `worlds` (their episodes' parameters) as (num_envs,) arrays, 0 elsewhere."""
        infos = [episode_info(self.config, ep) for ep in episodes]
        out = {}
        for key in infos[0] if infos else ():
            arr = np.zeros(self.num_envs, dtype=type(infos[0][key]))
            arr[worlds] = [i[key] for i in infos]
            out[key] = arr
        return out

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None):
        N = self.num_envs
        worlds, mask, episodes = self._seeded_reset(seed, options)
        if isinstance(seed, (int, np.integer)):
            super().reset(seed=int(seed))
        infos = _vector_infos(N, (self._reset_info(worlds, episodes), mask))
        return self._worlds.observe(), infos

    def step(self, actions: Any):
        self._check_reset()
        N = self.num_envs
        a = self._worlds.check_actions(actions, (N, 3))
        result = self._autoreset_step(a, self.max_episode_steps)
        reset_info = self._reset_info(result.reset_indices, result.episodes) if result.episodes else {}
        step_info = result.outcome.info()
        infos = _vector_infos(N, (step_info, ~result.resetting), (reset_info, result.resetting))
        if result.final_obs is not None:  # same step: the ended episodes' last observation and info
            ended = result.resetting
            final_obs = np.full(N, None, dtype=object)
            for w in result.reset_indices:
                final_obs[w] = result.final_obs[w]
            infos.update(final_obs=final_obs, _final_obs=ended.copy(),
                         final_info=_vector_infos(N, (step_info, ended)), _final_info=ended.copy())
        return result.obs, result.outcome.reward, result.terminated, result.truncated, infos

    def render(self):
        frames = self._frames(range(self.num_envs))
        return None if frames is None else tuple(frames)

    def close_extras(self, **kwargs: Any) -> None:
        self._close_renderer()


def _vector_infos(n: int, *parts: tuple[dict[str, np.ndarray], np.ndarray]) -> dict[str, np.ndarray]:
    """Infos as SyncVectorEnv assembles them from (info, mask) parts, each info's (n,) arrays standing for
    the worlds its (n,) bool mask marks: per key the values (0 where absent) and a `_key` mask."""
    out: dict[str, np.ndarray] = {}
    for info, mask in parts:
        if not mask.any():
            continue
        for key, value in info.items():
            value = np.asarray(value)
            if key in out:
                out[key] = np.where(mask, value, out[key])
                out[f"_{key}"] = out[f"_{key}"] | mask
            else:
                out[key] = np.where(mask, value, np.zeros((), value.dtype)).astype(value.dtype)
                out[f"_{key}"] = mask.copy()
    return out
