"""What the single and the vector follower env share: construction, spaces, timing, rendering.

`FollowerEnvBase` is a mixin placed before `gymnasium.Env` / `gymnasium.vector.VectorEnv`
in the env classes' bases; it owns the config, the batched task (`FollowerWorlds`)
and the lazily made renderer.
"""

from __future__ import annotations

import functools
from typing import Any, Mapping, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from downwash_envs.config import FollowerConfig, make_config
from downwash_envs.observation import obs_bounds
from downwash_envs.rendering import Renderer
from downwash_envs.task import FollowerWorlds
from sim.simulator import Simulator

__all__ = ["FollowerEnvBase", "make_spaces", "check_reset_options", "vector_reset_plan", "pickled_as_constructed"]

RENDER_MODES = ("rgb_array",)

def make_spaces(cfg: FollowerConfig) -> tuple[spaces.Box, spaces.Box]:
    """(observation Box (OBS_DIM,) float32, action Box [-1, 1]^3 float32) of one world; an action
    of 1 is `cfg.bound` m/s^2."""
    low, high = obs_bounds(cfg.bound)
    obs = spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
    act = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
    return obs, act


def check_reset_options(options: Mapping[str, Any] | None, allowed: tuple[str, ...]) -> None:
    """ValueError naming the allowed reset options when `options` has others."""
    if options:
        unknown = sorted(set(options) - set(allowed))
        if unknown:
            what = ", ".join(allowed) if allowed else "none (configure episodes through the env's options)"
            raise ValueError(f"reset options: unknown {unknown}; allowed: {what}")


def vector_reset_plan(n_worlds: int, seed: Any, options: Mapping[str, Any] | None) -> tuple[list[int | None], np.ndarray]:
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
    generator: seed its reset."""
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


class FollowerEnvBase:
    """Shared state: `config`, `render_mode`, `metadata["render_fps"]`, `_worlds`, `_renderer`.

    The env class defines `metadata` (with ``"render_modes": RENDER_MODES``, plus ``"human"`` for
    MuJoCo's interactive viewer, `downwash_envs.viewer`, whose window `_renderer` then holds).
    """

    config: FollowerConfig
    _worlds: FollowerWorlds

    def _setup(self, options: Mapping[str, Any], render_mode: str | None, n_worlds: int, n_threads: int = 0) -> None:
        """Validate the options and the render mode, build the task; the spaces are the caller's."""
        modes = type(self).metadata.get("render_modes", RENDER_MODES)  # "human" where the class lists it
        if render_mode is not None and render_mode not in modes:
            raise ValueError(f"render_mode: got {render_mode!r}; allowed: None, {', '.join(modes)}")
        if render_mode == "human":  # MuJoCo's viewer (downwash_envs.viewer): no display fails here, before any work
            from downwash_envs import viewer

            viewer.check_display("render_mode='human'")
            viewer.render_on_step(self)
        self.config = cfg = make_config(options)
        self.render_mode = render_mode
        self.metadata = {**type(self).metadata, "render_fps": cfg.control_hz}  # one frame per env step
        self._worlds = FollowerWorlds(cfg, n_worlds, n_threads)
        self._renderer: Renderer | None = None

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
        if self.render_mode == "human":  # the window shows the first world; render() returns None
            if self._renderer is None:
                from downwash_envs.viewer import Viewer

                self._renderer = Viewer.of_simulator(self._worlds.sim, what="render_mode='human'")
            self._renderer.show_world(self._worlds.sim, worlds[0], pace=self.dt)
            return None
        if self._renderer is None:
            self._renderer = Renderer(self._worlds.scene, self.config.render_width, self.config.render_height)
        return [self._renderer.render_world(self._worlds.sim, w) for w in worlds]

    def _close_renderer(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
