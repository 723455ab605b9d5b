"""What every env class shares, single, vector or multi-agent: the env side of the one engine.

`TaskEnv` is a mixin placed before `gymnasium.Env`, `gymnasium.vector.VectorEnv` or
`pettingzoo.ParallelEnv` in an env's bases; it owns the config, the batched task (a
`downwash_envs.engine.TaskWorlds`), the render mode and the lazily made renderer.
`VectorAutoreset` adds what the two vector envs share: a generator per world (world i of
`reset(seed=s)` seeded with s + i, as a `SyncVectorEnv`'s envs are) and Gymnasium's
autoreset modes (next step, same step, disabled), written once. `FollowerEnvBase` binds the
follower task to them (the swarm's binding is in `downwash_envs.swarm`).

Also here: the spaces, the reset-option checks, a vector env's reset plan, the autoreset
mode's check, pickling an env as the call that made it, `ResetNeededError` (step() before
the first reset()) and `EpisodeEndedError` (step() on an ended world with autoreset disabled).
"""

from __future__ import annotations

import functools
from typing import Any, Mapping, NamedTuple, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode

from downwash_envs.config import FollowerConfig, make_config
from downwash_envs.engine import TaskWorlds
from downwash_envs.observation import obs_bounds
from downwash_envs.rendering import Renderer
from downwash_envs.task import FollowerWorlds
from sim.simulator import Simulator

__all__ = [
    "TaskEnv", "VectorAutoreset", "AutoresetStep", "FollowerEnvBase", "ResetNeededError", "EpisodeEndedError",
    "agent_spaces", "make_spaces", "check_reset_options", "vector_reset_plan", "check_autoreset_mode",
    "pickled_as_constructed",
]  # fmt: skip

RENDER_MODES = ("rgb_array",)


class ResetNeededError(gym.error.ResetNeeded, RuntimeError):
    """step() on an env with no episode to step: before its first reset() (a new env, or an unpickled
    copy, which is a new env), or a PettingZoo env whose episode has ended. Gymnasium's
    `ResetNeeded` (what its OrderEnforcing wrapper raises), so that envs made directly, not
    through `gym.make`, refuse alike; also a RuntimeError, as the swarm env raised before."""


class EpisodeEndedError(ResetNeededError, AssertionError):
    """step() with autoreset disabled while a world's episode has ended and it was not reset.
    `SyncVectorEnv` refuses this with an assertion, so code written against it catches an
    AssertionError; it is also a `ResetNeeded`, which is what it means."""


def check_autoreset_mode(mode: Any) -> AutoresetMode:
    """`mode` (an `AutoresetMode` or its string value, as `SyncVectorEnv` takes) as the enum;
    ValueError naming the allowed ones."""
    if isinstance(mode, AutoresetMode):
        return mode
    for member in AutoresetMode:
        if isinstance(mode, str) and mode == member.value:
            return member
    allowed = ", ".join(f"AutoresetMode.{m.name} ({m.value!r})" for m in AutoresetMode)
    raise ValueError(f"autoreset_mode: got {mode!r}; allowed: {allowed}")


def agent_spaces(low: np.ndarray, high: np.ndarray) -> tuple[spaces.Box, spaces.Box]:
    """(observation Box [low, high] float32, action Box [-1, 1]^3 float32) of one agent in one world."""
    obs = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
    act = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
    return obs, act


def make_spaces(cfg: FollowerConfig) -> tuple[spaces.Box, spaces.Box]:
    """(observation Box (OBS_DIM,) float32, action Box [-1, 1]^3 float32) of one follower world; an
    action of 1 is `cfg.bound` m/s^2."""
    return agent_spaces(*obs_bounds(cfg.bound))


def check_reset_options(options: Mapping[str, Any] | None, allowed: tuple[str, ...]) -> None:
    """ValueError naming the allowed reset options when `options` has others."""
    if options:
        unknown = sorted(set(options) - set(allowed))
        if unknown:
            what = ", ".join(allowed) if allowed else "none (configure episodes through the env's options)"
            raise ValueError(f"reset options: unknown {unknown}; allowed: {what}")


def vector_reset_plan(
    n_worlds: int, seed: Any, options: Mapping[str, Any] | None
) -> tuple[list[int | None], np.ndarray]:
    """(a seed or None per world, the worlds to reset (n_worlds,) bool) of a vector env's
    `reset(seed=..., options=...)`: seed None, an int s (world i gets s + i) or one per world;
    options only ``{"reset_mask": mask}``. ValueError naming what is wrong."""
    if seed is None:
        seeds: list[int | None] = [None] * n_worlds
    elif isinstance(seed, (int, np.integer)):
        seeds = [int(seed) + i for i in range(n_worlds)]
    else:
        seeds = list(seed)
        if len(seeds) != n_worlds:
            raise ValueError(f"seed: a list of seeds needs one per world ({n_worlds}), got {len(seeds)}")
    options = dict(options or {})
    mask = options.pop("reset_mask", None)
    check_reset_options(options, allowed=("reset_mask",))
    if mask is None:
        return seeds, np.ones(n_worlds, bool)
    mask = np.asarray(mask)
    if mask.shape != (n_worlds,) or mask.dtype != np.bool_ or not mask.any():
        raise ValueError(f"reset options['reset_mask']: expected a bool array ({n_worlds},) with a True, got {mask!r}")
    return seeds, mask


def pickled_as_constructed(cls: type) -> type:
    """Class decorator: an env pickles as the call that made it, and unpickles as a fresh env
    made by the same call (not reset). Its simulator (MuJoCo data, a `mujoco.batch`, compiled
    buffers, helper threads) cannot be copied, and a pickled copy of those objects is an env
    that silently does not move; libraries that copy envs by pickling them (SuperSuit,
    subprocess vector envs) get a working env instead. The copy does not carry the original's
    generator or its episode (nor its step counter): like any new env it raises
    `ResetNeededError` on step() until reset(); seed that reset."""
    init = cls.__init__

    @functools.wraps(init)
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if type(self) is cls:  # the outermost call: a subclass records its own
            self._construction = (args, kwargs)
        init(self, *args, **kwargs)

    def __reduce__(self):
        args, kwargs = self._construction
        return (_construct, (type(self), args, kwargs))

    cls.__init__ = __init__
    cls.__reduce__ = __reduce__
    return cls


def _construct(cls: type, args: tuple, kwargs: dict) -> Any:
    return cls(*args, **kwargs)


class TaskEnv:
    """Shared state: `config`, `render_mode`, `metadata["render_fps"]`, `_worlds`, `_renderer`.

    The env class defines `metadata` (with ``"render_modes": RENDER_MODES``, plus ``"human"`` for
    MuJoCo's interactive viewer, `downwash_envs.viewer`, whose window `_renderer` then holds)
    and `_build_worlds`.
    """

    config: Any
    _worlds: TaskWorlds

    def _build_worlds(self, options: Mapping[str, Any], n_worlds: int, n_threads: int) -> TaskWorlds:
        """Validate the options (before anything is built) and build the task's worlds."""
        raise NotImplementedError

    def _setup(self, options: Mapping[str, Any], render_mode: str | None, n_worlds: int, n_threads: int = 0) -> None:
        """Validate the render mode and the options, build the task; the spaces are the caller's."""
        modes = type(self).metadata.get("render_modes", RENDER_MODES)  # "human" where the class lists it
        if render_mode is not None and render_mode not in modes:
            raise ValueError(f"render_mode: got {render_mode!r}; allowed: None, {', '.join(modes)}")
        if render_mode == "human":  # MuJoCo's viewer (downwash_envs.viewer): no display fails here, before any work
            from downwash_envs import viewer

            viewer.check_display("render_mode='human'")
            viewer.render_on_step(self)
        self._worlds = worlds = self._build_worlds(options, n_worlds, n_threads)
        self.config = worlds.cfg
        self.render_mode = render_mode
        self.metadata = {**type(self).metadata, "render_fps": worlds.task.control_hz}  # one frame per env step
        self._renderer: Any = None
        # the worlds never reset: built with placeholder episodes, they must not be stepped (`_check_reset`)
        self._unreset = np.ones(n_worlds, bool)
        self._all_reset = False  # once True, stays True (a world never becomes unreset again)

    def _mark_reset(self, worlds: Any) -> None:
        """Record that `worlds` (indices or a (W,) mask) have started an episode."""
        self._unreset[worlds] = False

    def _check_reset(self) -> None:
        """ResetNeededError unless every world has been reset at least once (one attribute read once they have)."""
        if self._all_reset:
            return
        if self._unreset.size == 1 and self._unreset[0]:
            raise ResetNeededError(
                "step() before reset(): call reset() first (a new env, or an unpickled copy of one, has no episode "
                "to step)"
            )
        if self._unreset.any():
            never = np.flatnonzero(self._unreset).tolist()
            raise ResetNeededError(
                f"step() before reset(): world(s) {never} have never been reset; call reset() first (a new env, "
                "or an unpickled copy of one, has no episode to step; reset(options={'reset_mask': mask}) resets "
                "only the masked worlds)"
            )
        self._all_reset = True

    @property
    def dt(self) -> float:
        """s, one env step (the controller period)."""
        return self._worlds.sim_config.rates.control_dt

    @property
    def simulator(self) -> Simulator:
        """The underlying `sim.simulator.Simulator` (batched over the env's worlds), for diagnostics."""
        return self._worlds.sim

    def _frames(self, worlds: Sequence[int]) -> list[np.ndarray] | None:
        """One (height, width, 3) uint8 frame per world; None (and a warning) without a render_mode."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; make the env with render_mode='rgb_array'")
            return None
        sim = self._worlds.sim
        if self.render_mode == "human":  # the window shows the first world; render() returns None
            if self._renderer is None:
                from downwash_envs.viewer import Viewer

                self._renderer = Viewer.of_simulator(sim, what="render_mode='human'")
            self._renderer.show_world(sim, worlds[0], pace=self.dt)
            return None
        if self._renderer is None:
            task = self._worlds.task
            self._renderer = Renderer(self._worlds.scene, task.render_width, task.render_height)
        frames = []
        for w in worlds:
            targets = self._worlds.camera_targets(w)  # (the true state, before the frame's mj_forward)
            frames.append(self._renderer.render(sim.physics.mjdata(w), *targets))
        return frames

    def _close_renderer(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class AutoresetStep(NamedTuple):
    """A vector step under the env's autoreset mode (`VectorAutoreset._autoreset_step`)."""

    outcome: Any  # the task's step outcome (with `terminated`); next step: zero for the resetting worlds
    terminated: np.ndarray  # (W,) bool; next step: False for the resetting worlds
    truncated: np.ndarray  # (W,) bool: at the horizon; next step: False for the resetting worlds
    # (W,) bool: the worlds that started a new episode at this step; next step: instead of stepping
    # (their actions ignored), same step: after the step that ended their episode; disabled: none
    resetting: np.ndarray
    reset_indices: np.ndarray  # (n,) their indices, ascending
    episodes: list  # (n,) their new episodes
    obs: np.ndarray  # (W, ...) float32: the new episodes' first for the resetting worlds
    final_obs: np.ndarray | None = None  # same step: (W, ...) float32 at the step's end, before the resets


class VectorAutoreset:
    """The vector envs' worlds bookkeeping: a generator and an episode clock per world, the
    seeded reset, and Gymnasium's autoreset modes (`autoreset_mode`), step for step as
    `SyncVectorEnv` runs them:

    - next step (Gymnasium's default): the step after a world terminates or truncates resets
      it; its actions are ignored and its outcome is zero.
    - same step: a world that terminates or truncates is reset within that step; the step
      returns the new episode's first observation, and the ended one's last observation
      (`AutoresetStep.final_obs`) for the env to report.
    - disabled: nothing resets by itself; stepping while a world's episode has ended raises
      `EpisodeEndedError` (reset it with ``reset(options={"reset_mask": mask})``).
    """

    _worlds: TaskWorlds

    def _init_autoreset(self, n_worlds: int, mode: AutoresetMode = AutoresetMode.NEXT_STEP) -> None:
        self.autoreset_mode = mode  # as SyncVectorEnv's attribute of the same name
        self._rngs: list[np.random.Generator | None] = [None] * n_worlds  # one per world, as SyncVectorEnv's envs
        # the worlds whose episode ended at the last step: next step resets them at the next;
        # disabled refuses to step until they are reset; same step never leaves one
        self._ended = np.zeros(n_worlds, bool)
        self._elapsed = np.zeros(n_worlds, np.int64)

    def _start_episodes(self, worlds: np.ndarray) -> list:
        """Draw episodes for `worlds` from their generators (unseeded ones made on first use) and start them."""
        episodes = []
        for w in worlds:
            if self._rngs[w] is None:
                self._rngs[w], _ = seeding.np_random()
            episodes.append(self._worlds.new_episode(self._rngs[w]))
        self._worlds.reset_worlds(worlds, episodes)
        self._elapsed[worlds] = 0
        self._mark_reset(worlds)
        return episodes

    def _seeded_reset(self, seed: Any, options: Mapping[str, Any] | None) -> tuple[np.ndarray, np.ndarray, list]:
        """`reset(seed, options)` of the worlds: (the worlds reset, their mask (W,) bool, their episodes)."""
        seeds, mask = vector_reset_plan(self._ended.size, seed, options)
        worlds = np.flatnonzero(mask)
        for w in worlds:
            if seeds[w] is not None:
                self._rngs[w], _ = seeding.np_random(int(seeds[w]))
        episodes = self._start_episodes(worlds)
        self._ended[worlds] = False
        return worlds, mask, episodes

    def _horizon_reached(self, max_steps: int | None) -> np.ndarray:
        """(W,) bool: the worlds whose episode clock reached `max_steps` (None: no horizon)."""
        return self._elapsed >= max_steps if max_steps is not None else np.zeros(self._elapsed.size, bool)

    def _autoreset_step(self, actions: np.ndarray, max_steps: int | None) -> AutoresetStep:
        """Step the worlds with checked `actions` under `autoreset_mode`. max_steps: the truncation
        horizon (None: none). The caller checks `_check_reset` first."""
        if self.autoreset_mode is AutoresetMode.NEXT_STEP:
            return self._next_step_autoreset(actions, max_steps)
        if self.autoreset_mode is AutoresetMode.DISABLED and self._ended.any():  # before anything steps
            ended = np.flatnonzero(self._ended).tolist()
            raise EpisodeEndedError(
                f"step() with autoreset_mode={AutoresetMode.DISABLED.value!r}: the episode of world(s) {ended} has "
                "ended; reset them first with reset(options={'reset_mask': mask})"
            )
        outcome = self._worlds.step(actions, None)
        self._elapsed += 1
        obs = self._worlds.observe(fresh=False)
        terminated, truncated = outcome.terminated, self._horizon_reached(max_steps)
        ended = terminated | truncated
        disabled = self.autoreset_mode is AutoresetMode.DISABLED
        if disabled:
            self._ended = ended
        if disabled or not ended.any():
            none = np.zeros_like(ended)
            return AutoresetStep(outcome, terminated, truncated, none, np.flatnonzero(none), [], obs)
        reset_indices = np.flatnonzero(ended)  # same step: the ended worlds start anew now
        episodes = self._start_episodes(reset_indices)
        final_obs, obs = obs, obs.copy()
        obs[ended] = self._worlds.observe()[ended]
        return AutoresetStep(outcome, terminated, truncated, ended, reset_indices, episodes, obs, final_obs)

    def _next_step_autoreset(self, actions: np.ndarray, max_steps: int | None) -> AutoresetStep:
        """Step the worlds with `actions`; those that ended at the last step start anew instead."""
        resetting = self._ended
        stepping = ~resetting
        any_reset = bool(resetting.any())
        outcome = self._worlds.step(actions, stepping if any_reset else None)
        self._elapsed += stepping
        truncated = self._horizon_reached(max_steps)
        reset_indices, episodes = np.flatnonzero(resetting), []
        if any_reset:
            episodes = self._start_episodes(reset_indices)
            truncated = truncated & stepping
            obs = self._worlds.observe()
        else:
            obs = self._worlds.observe(fresh=False)
        terminated = outcome.terminated
        self._ended = terminated | truncated
        return AutoresetStep(outcome, terminated, truncated, resetting, reset_indices, episodes, obs)


class FollowerEnvBase(TaskEnv):
    """The follower task on the env engine: `make_config` options, `FollowerWorlds`."""

    config: FollowerConfig
    _worlds: FollowerWorlds

    def _build_worlds(self, options: Mapping[str, Any], n_worlds: int, n_threads: int) -> FollowerWorlds:
        return FollowerWorlds(make_config(options), n_worlds, n_threads)
