"""A multi-agent swarm env: every follower of an N-vehicle preset is an agent (PettingZoo).

`SwarmEnv` is a `pettingzoo.ParallelEnv` (make it with `parallel_env(...)`, or `env(...)`
for PettingZoo's AEC API);
`SwarmVectorEnv` steps W such worlds at once on one `mujoco.batch.Batch` and returns
per-agent arrays with a leading world axis. Both are thin views of one engine,
`SwarmWorlds` (W = 1 for the ParallelEnv), the multi-agent sibling of
`downwash_envs.task.FollowerWorlds`: the flight is the full stack of `sim.simulator.Simulator`
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
table is `markdown_table()` (a test checks it):

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
the preset's references; 0 unless `random_phase`). step: the reward terms,
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
options, validated there: action_bound, control_hz, predictor ("none" | "oracle"),
max_tracking_error, the reward weights, sim_config, lqr, turbulence, render_width,
render_height. Unknown names raise TypeError, bad values `downwash_core.errors.ConfigError`,
both before anything is built. `reset(options=...)`: the ParallelEnv takes none (any
given are ignored with a warning: PettingZoo's API test passes some), the vector env
``{"reset_mask": (W,) bool}``.

## Rendering
``render_mode="rgb_array"``: one (render_height, render_width, 3) uint8 frame per
world (`downwash_envs.rendering`, EGL picked when headless), the camera framing the leader and
the vehicle farthest from it; the leader is tinted orange, bravo cyan.

Not provided: a global `state()` for centralised critics, and an AEC (`env()`) form.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.provenance import describe
from downwash_core.roles import MAX_VEHICLES, Role
from downwash_core.status import Status
from downwash_core.validate import count, number
from downwash_envs.base import RENDER_MODES, pickled_as_constructed, vector_reset_plan
from downwash_envs.config import REWARD_WEIGHTS, FollowerConfig, build_field, make_config
from downwash_envs.observation import OBSERVATION, ObsEntry
from downwash_envs.rendering import Renderer
from downwash_envs.task import REWARD_TERMS, task_constants, task_kernel
from sim.aggregation import DEFAULT_AGGREGATION, LinearSuperposition, make_aggregation
from sim.neighbours import NeighbourSet, select_into, select_neighbours
from sim.physics import check_world_memory
from sim.predictor import OraclePredictor, ZeroPredictor
from sim.presets import Preset, make_preset
from sim.scene import Scene, build_scene
from sim.simulator import Simulator
from downwash_trajectories import Cached, TimeShifted

__all__ = [
    "SHARED_OPTIONS", "OWN_OBSERVATION", "NEIGHBOUR_OBSERVATION", "OWN_DIM", "NEIGHBOUR_DIM",
    "observation_layout", "obs_dim", "obs_slices", "obs_bounds", "markdown_table",
    "own_block", "neighbour_block", "observation", "SwarmConfig", "make_swarm_config", "SwarmEpisode",
    "draw_swarm_episode",
    "agent_names", "SwarmWorlds", "SwarmEnv", "SwarmVectorEnv", "parallel_env", "env",
]  # fmt: skip

# The FollowerConfig options that mean the same here (validated by downwash_envs.config); the
# single env's reference, separation, knobs and randomisations do not apply to a preset.
SHARED_OPTIONS = (
    "action_bound", "control_hz", "predictor", "max_tracking_error", *REWARD_WEIGHTS,
    "sim_config", "lqr", "turbulence", "render_width", "render_height",
)  # fmt: skip
_OK = int(Status.OK)

# ----------------------------------------------------------------------------- observation layout

_SINGLE = {e.name: e for e in OBSERVATION}
# the agent's own tracking features: the single env's entries that concern the follower itself
OWN_OBSERVATION: tuple[ObsEntry, ...] = tuple(
    _SINGLE[n]
    for n in ("v_follower", "pos_error", "vel_error", "ref_acc", "follower_x_axis", "follower_z_axis", "last_action")
)
# one neighbour slot (repeated K times, nearest first)
NEIGHBOUR_OBSERVATION: tuple[ObsEntry, ...] = (
    ObsEntry("mask", 1, "-", "-", 1.0, "1: a vehicle in slot k; 0: padding (the slot all 0)"),
    ObsEntry("dp", 3, "m", "world", 10.0, "p_follower - p_neighbour (as the single env's dp)"),
    ObsEntry("dv", 3, "m/s", "world", 40.0, "v_follower - v_neighbour"),
    ObsEntry("z_axis", 3, "-", "world", 1.0, "neighbour body z axis R_n[:, 2] (its wake's axis)"),
)
OWN_DIM = sum(e.size for e in OWN_OBSERVATION)  # 21
NEIGHBOUR_DIM = sum(e.size for e in NEIGHBOUR_OBSERVATION)  # 10 per slot


def observation_layout(max_neighbours: int) -> tuple[ObsEntry, ...]:
    """The whole vector's entries in order: the own block, then slots ``n0_*`` .. ``n{K-1}_*``."""
    slots = tuple(e._replace(name=f"n{k}_{e.name}") for k in range(max_neighbours) for e in NEIGHBOUR_OBSERVATION)
    return OWN_OBSERVATION + slots


def obs_dim(max_neighbours: int) -> int:
    return OWN_DIM + NEIGHBOUR_DIM * max_neighbours


def obs_slices(max_neighbours: int) -> dict[str, slice]:
    """name -> index range, for `observation_layout(max_neighbours)`."""
    out, start = {}, 0
    for e in observation_layout(max_neighbours):
        out[e.name] = slice(start, start + e.size)
        start += e.size
    return out


def obs_bounds(max_neighbours: int, action_bound: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (obs_dim(K),) float64; `action_bound` (m/s^2) bounds last_action."""
    high = np.concatenate(
        [np.full(e.size, action_bound if math.isnan(e.bound) else e.bound) for e in observation_layout(max_neighbours)]
    )
    return -high, high


def markdown_table() -> str:
    """The layout as a markdown table (index, name, meaning, unit, frame, bound; "b": the action
    bound), slot k written symbolically; columns padded to their widest cell, no trailing newline."""
    header = ("index", "name", "meaning", "unit", "frame", "bound")
    rows, start = [], 0
    for e in OWN_OBSERVATION:
        index = f"{start}-{start + e.size - 1}" if e.size > 1 else f"{start}"
        rows.append((index, e.name, e.meaning, e.unit, e.frame, "b" if math.isnan(e.bound) else f"{e.bound:g}"))
        start += e.size
    offset = 0
    for e in NEIGHBOUR_OBSERVATION:
        base = f"{OWN_DIM}+{NEIGHBOUR_DIM}k"
        index = base + (f"+({offset}-{offset + e.size - 1})" if e.size > 1 else (f"+{offset}" if offset else ""))
        rows.append((index, f"nk_{e.name}", e.meaning, e.unit, e.frame, f"{e.bound:g}"))
        offset += e.size
    widths = [max(len(r[i]) for r in (header, *rows)) for i in range(len(header))]

    def line(cells):
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"

    rule = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(header), rule, *(line(r) for r in rows)])


def own_block(
    pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, ref: Any, agents: np.ndarray, last_action: np.ndarray
) -> np.ndarray:
    """(W, A, OWN_DIM) in OWN_OBSERVATION order.

    pos, vel: (W, V, 3) m, m/s estimated; rot: (W, V, 3, 3) body to world; ref: a RefSample
    with (W, V, ...) arrays; agents: (A,) vehicle indices; last_action: (W, A, 3) m/s^2.
    """
    own = (
        vel[:, agents],
        pos[:, agents] - ref.pos[:, agents],
        vel[:, agents] - ref.vel[:, agents],
        ref.acc[:, agents],
        rot[:, agents][..., 0],  # (separate indexing: mixed with a slice, numpy would move the axes)
        rot[:, agents][..., 2],
        last_action,
    )
    return np.concatenate(own, axis=-1)


def neighbour_block(
    pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, agents: np.ndarray, max_neighbours: int
) -> np.ndarray:
    """(W, A, K, NEIGHBOUR_DIM): each agent's K neighbour slots, nearest first.

    pos, vel: (W, V, 3) m, m/s (estimated); rot: (W, V, 3, 3) body to world; agents: (A,)
    vehicle indices. The neighbours are the data's and the predictor's
    (`sim.neighbours.select_neighbours`: the other vehicles at a finite distance, nearest
    first, ties in scene order); each fills a slot [mask 1, dp, dv, z axis], the other
    slots are zero. Every operation is per row, so a world's slots do not depend on the
    batch, and relabelling the other vehicles does not change them (tests).
    """
    W = pos.shape[0]
    agents = np.asarray(agents, dtype=np.int64)
    A, K = agents.size, int(max_neighbours)
    out = np.zeros((W, A, K, NEIGHBOUR_DIM))
    index, mask = select_neighbours(pos, NeighbourSet(K))  # (W, V, K)
    index, mask = index[:, agents], mask[:, agents]  # (W, A, K)
    nb = np.where(mask, index, 0)
    w = np.arange(W)[:, None, None]
    m = mask[..., None]
    out[..., 0] = mask
    out[..., 1:4] = np.where(m, pos[:, agents, None, :] - pos[w, nb], 0.0)
    out[..., 4:7] = np.where(m, vel[:, agents, None, :] - vel[w, nb], 0.0)
    out[..., 7:10] = np.where(m, rot[w, nb][..., 2], 0.0)
    return out


def observation(
    pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, ref: Any, agents: np.ndarray,
    last_action: np.ndarray, max_neighbours: int, low: np.ndarray, high: np.ndarray,
) -> np.ndarray:
    """(W, A, obs_dim(K)): the readable observation (own block, neighbour slots), clipped to
    [low, high] with NaN (a diverged world) read as 0; `SwarmWorlds` runs its compiled twin
    `_observe_kernel`, which a test compares with this bit for bit."""
    W, A = pos.shape[0], len(agents)
    own = own_block(pos, vel, rot, ref, agents, last_action)
    nb = neighbour_block(pos, vel, rot, agents, max_neighbours).reshape(W, A, max_neighbours * NEIGHBOUR_DIM)
    o = np.clip(np.concatenate((own, nb), axis=-1), low, high)
    o[np.isnan(o)] = 0.0
    return o


@njit
def _observe_kernel(pos, vel, rot, ref_pos, ref_vel, ref_acc, agents, last_action, low, high, out):
    """Compiled `observation`, written into out (W, A, D); the same arithmetic, world by world.

    pos, vel (W, V, 3) estimated; rot (W, V, 3, 3); ref_* (W, V, 3); agents (A,); last_action
    (W, A, 3); low, high (D,). The neighbours are `sim.neighbours.select_into`'s (the compiled
    twin of the data's and the predictor's selection).
    """
    W, A, D = out.shape
    V = pos.shape[1]
    K = (D - OWN_DIM) // NEIGHBOUR_DIM
    key = np.empty(max(V - 1, 1))
    idx = np.empty(max(V - 1, 1), np.int64)
    for w in range(W):
        for i in range(A):
            a = agents[i]
            o = out[w, i]
            for k in range(3):
                o[k] = vel[w, a, k]
                o[3 + k] = pos[w, a, k] - ref_pos[w, a, k]
                o[6 + k] = vel[w, a, k] - ref_vel[w, a, k]
                o[9 + k] = ref_acc[w, a, k]
                o[12 + k] = rot[w, a, k, 0]
                o[15 + k] = rot[w, a, k, 2]
                o[18 + k] = last_action[w, i, k]
            n = select_into(pos, w, a, np.inf, K, key, idx)
            for s in range(K):
                base = OWN_DIM + NEIGHBOUR_DIM * s
                if s < n:
                    b = idx[s]
                    o[base] = 1.0
                    for k in range(3):
                        o[base + 1 + k] = pos[w, a, k] - pos[w, b, k]
                        o[base + 4 + k] = vel[w, a, k] - vel[w, b, k]
                        o[base + 7 + k] = rot[w, b, k, 2]
                else:
                    for k in range(NEIGHBOUR_DIM):
                        o[base + k] = 0.0
            for k in range(D):
                x = o[k]
                if x != x:
                    o[k] = 0.0
                elif x < low[k]:
                    o[k] = low[k]
                elif x > high[k]:
                    o[k] = high[k]


# ----------------------------------------------------------------------------- options


@dataclass(frozen=True)
class SwarmConfig:
    """Validated options of the swarm envs (see the module docstring).

    preset: the resolved `sim.presets.Preset`; aggregation: a `sim.aggregation` spec, law: its law;
    max_neighbours: K; duration: s, truncation time; random_phase: draw the start time;
    task: the shared options as an `downwash_envs.config.FollowerConfig` (its other fields are
    its defaults and unused); field: the field object.
    """

    preset: Preset
    aggregation: str
    law: Any
    max_neighbours: int
    duration: float
    random_phase: bool
    task: FollowerConfig
    field: Any

    @property
    def bound(self) -> float:
        """m/s^2, the action Box bound per axis."""
        return self.task.bound

    @property
    def agents(self) -> tuple[str, ...]:
        """The followers' names, in scene order."""
        return tuple(name for name, role in self.preset.vehicles if role == Role.FOLLOWER)

    @property
    def max_steps(self) -> int:
        """Env steps per episode (the truncation horizon)."""
        return int(round(self.duration * self.task.control_hz))

    def describe(self) -> dict[str, Any]:
        """Stable provenance of everything that affects a flight."""
        t = self.task
        return {
            "preset": self.preset.describe(), "aggregation": describe(self.law), "field": describe(self.field),
            "max_neighbours": self.max_neighbours, "duration": self.duration, "random_phase": self.random_phase,
            **{k: describe(getattr(t, k)) for k in SHARED_OPTIONS if k not in ("render_width", "render_height")},
        }  # fmt: skip


def make_swarm_config(
    preset: str | Preset = "stack3",
    field: Any = "so2",
    aggregation: str = DEFAULT_AGGREGATION,
    max_neighbours: int | None = None,
    duration: float | None = None,
    random_phase: bool = False,
    **options: Any,
) -> SwarmConfig:
    """A validated `SwarmConfig`; TypeError for unknown option names, ConfigError for bad values."""
    unknown = sorted(set(options) - set(SHARED_OPTIONS))
    if unknown:
        allowed = ("preset", "field", "aggregation", "max_neighbours", "duration", "random_phase", *SHARED_OPTIONS)
        raise TypeError(f"unknown option(s) {unknown}; allowed: {', '.join(allowed)}")
    if isinstance(preset, str):
        preset = make_preset(preset)
    elif not isinstance(preset, Preset):
        raise ConfigError(f"preset: expected a preset spec string or a sim.presets.Preset, got {type(preset).__name__}")
    if not any(role == Role.FOLLOWER for _, role in preset.vehicles):
        raise ConfigError(f"preset {preset.name!r}: has no follower, so no agent; allowed: presets with followers")
    if not isinstance(aggregation, str):
        raise ConfigError(f"aggregation: expected a law name, got {type(aggregation).__name__}")
    law = make_aggregation(aggregation)  # ConfigError naming the allowed laws
    if not isinstance(law, LinearSuperposition) and "aggregation" not in inspect.signature(Simulator).parameters:
        # transitional: until the simulator has its aggregation slot, only its built-in sum
        raise ConfigError(f"aggregation: {aggregation!r} needs the simulator's aggregation slot; allowed: linear")
    V = preset.n_vehicles
    K = V - 1 if max_neighbours is None else count("max_neighbours", max_neighbours, 1, MAX_VEHICLES - 1)
    task = make_config({"field": field, **options})  # the shared options, checked by downwash_envs.config
    if duration is None:
        duration = float(preset.duration)
    else:
        duration = number("duration", duration, "s", 0.0, 1e5, lo_open=True)
        if round(duration * task.control_hz) < 1:
            raise ConfigError(f"duration: {duration} s is shorter than one env step ({1.0 / task.control_hz} s)")
    if not isinstance(random_phase, (bool, np.bool_)):
        raise ConfigError(f"random_phase: expected True or False, got {random_phase!r}")
    built = build_field(field)
    return SwarmConfig(preset, aggregation, law, K, float(duration), bool(random_phase), task, built)


# ----------------------------------------------------------------------------- episodes


@dataclass(frozen=True)
class SwarmEpisode:
    """What is drawn per episode from the env's generator (the same draws in both env classes)."""

    sim_seed: int  # seeds the world's noise (motion capture, turbulence)
    phase: float  # s, start time within the preset's references (0 unless random_phase)


def draw_swarm_episode(rng: np.random.Generator, cfg: SwarmConfig) -> SwarmEpisode:
    """Draw one episode, always in the same order (seed, then phase)."""
    sim_seed = int(rng.integers(0, 2**63 - 1))
    u = float(rng.uniform(0.0, 1.0))
    return SwarmEpisode(sim_seed, u * cfg.preset.duration if cfg.random_phase else 0.0)


@functools.lru_cache(maxsize=16)
def _scene(vehicles: tuple[tuple[str, Role], ...]) -> Scene:
    """A preset's scene, compiled once per process (read-only: physics copies on write)."""
    return build_scene(vehicles)


# ----------------------------------------------------------------------------- the batched task


def agent_names(preset: Any, vehicles: Sequence[str]) -> tuple[str, ...]:
    """The agents' names by role and rank, `follower_0`, `follower_1`, ... in scene order: the
    vehicles' own names (bravo, charlie) would put each agent in a group of its own in
    libraries that group agents by the prefix before the last `_` (TorchRL, BenchMARL)."""
    role_of = {name: role.value for name, role in preset.vehicles}
    counts: dict[str, int] = {}
    names = []
    for v in vehicles:
        role = role_of[v]
        names.append(f"{role}_{counts.get(role, 0)}")
        counts[role] = counts.get(role, 0) + 1
    return tuple(names)


class SwarmWorlds:
    """W worlds of the swarm task on one Simulator: per-world episodes, batched obs and reward.

    Shapes: W worlds, V vehicles, A agents (the followers, `agent_index` (A,) into the
    scene), D = obs_dim(K).
    """

    def __init__(self, cfg: SwarmConfig, n_worlds: int, n_threads: int = 0):
        self.cfg = cfg
        self.W = W = int(n_worlds)
        preset, task = cfg.preset, cfg.task
        self.scene = scene = _scene(tuple(preset.vehicles))
        self.agent_index = np.array([scene.vehicles.index(a) for a in cfg.agents], dtype=np.int64)
        self.agents = agent_names(preset, cfg.agents)
        base = task.sim_base
        per_control = int(round(1.0 / (base.rates.autopilot_dt * task.control_hz)))
        rates = dataclasses.replace(base.rates, autopilot_per_control=per_control)
        self.sim_config = dataclasses.replace(base, rates=rates)
        self.bound = cfg.bound
        self.K = cfg.max_neighbours
        # the preset's references (clearance checked at t = 0), shifted per world by the drawn phase
        self._base_ref = preset.reference(W, self.sim_config.collision_radius_xy, self.sim_config.collision_radius_z)
        self.phase = np.zeros(W)  # s
        self.episodes: list[SwarmEpisode] = [SwarmEpisode(0, 0.0)] * W
        # linear superposition is the simulator's (and the oracle's) own sum; another law goes into their slot
        linear = isinstance(cfg.law, LinearSuperposition)
        extra = {} if linear else {"aggregation": cfg.law}
        predictor = OraclePredictor(cfg.field, **extra) if task.predictor == "oracle" else ZeroPredictor()
        self.sim = Simulator(
            scene, self._reference(), [0] * W, config=self.sim_config, field=cfg.field, predictor=predictor,
            controller=FeedbackLinearisedLQR(task.lqr), turbulence=task.turbulence, n_threads=n_threads, **extra,
        )
        A = self.agent_index.size
        self.last_action = np.zeros((W, A, 3))  # m/s^2, as applied (clipped)
        self._command = np.zeros((W, self.sim.V, 3))  # the simulator's residual; the leader's stays 0
        self._obs_cache: tuple[np.ndarray, Any] | None = None  # attitudes and reference of the last step
        self.obs_low, self.obs_high = obs_bounds(self.K, self.bound)
        self._task_constants = task_constants(task, self.bound)

    def _reference(self) -> Cached:
        ref = TimeShifted(self._base_ref, self.phase.copy()) if self.cfg.random_phase else self._base_ref
        return Cached(ref)

    # ---------------------------------------------------------------- reset
    def reset_worlds(self, worlds: Sequence[int], episodes: Sequence[SwarmEpisode]) -> None:
        """Start the given worlds on the given episodes (their reference's state at the drawn phase)."""
        worlds = np.asarray(worlds, dtype=np.int64)
        for w, ep in zip(worlds, episodes):
            self.episodes[w] = ep
            self.phase[w] = ep.phase
        self.sim.reset(worlds, seeds=[ep.sim_seed for ep in episodes], reference=self._reference())
        self.last_action[worlds] = 0.0
        self._obs_cache = None

    # ---------------------------------------------------------------- step
    def check_actions(self, actions: Mapping[str, Any], live: Sequence[str], n_worlds: int | None) -> np.ndarray:
        """{agent: (3,) or (W, 3)} -> (W, A, 3) float64 clipped to the bound; ValueError before any step.

        live: the agents that must act (every one of them, and no other); n_worlds None: one
        world, (3,) per agent.
        """
        if not isinstance(actions, Mapping):
            raise ValueError(f"actions: expected a dict {{agent: action}}, got {type(actions).__name__}")
        missing, extra = sorted(set(live) - set(actions)), sorted(set(actions) - set(live))
        if missing or extra:
            raise ValueError(
                f"actions: expected one per live agent {list(live)}; missing {missing}, unexpected {extra}"
            )
        shape = (3,) if n_worlds is None else (n_worlds, 3)
        A = self.agent_index.size
        out = None
        if len(live) == A:  # the usual case: one array for all, checked at once
            try:
                out = np.array([actions[agent] for agent in self.agents], dtype=np.float64)
            except (TypeError, ValueError):
                out = None
            if out is not None and (out.shape != (A, *shape) or not np.all(np.isfinite(out))):
                out = None
            if out is not None and n_worlds is not None:
                out = np.ascontiguousarray(out.transpose(1, 0, 2))  # (W, A, 3)
        if out is None:  # some agents are not live, or an action is bad: agent by agent, naming it
            out = np.zeros((self.W, A, 3))
            for i, agent in enumerate(self.agents):
                if agent in actions:
                    out[:, i] = self._check_one(agent, actions[agent], shape)
        else:
            out = out.reshape(self.W, A, 3)
        np.clip(out, -1.0, 1.0, out=out)
        out *= self.bound  # normalised -> m/s^2
        return out

    @staticmethod
    def _check_one(agent: str, action: Any, shape: tuple[int, ...]) -> np.ndarray:
        try:
            a = np.array(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action of {agent}: expected a float array {shape} in [-1, 1], got {action!r}") from None
        if a.shape != shape:
            raise ValueError(f"action of {agent}: expected shape {shape} (world frame, in [-1, 1]), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action of {agent}: must be finite (in [-1, 1]), got {a.tolist()}")
        return a

    def step(self, actions: np.ndarray, stepping: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Advance the `stepping` worlds (default all) one controller period with (W, A, 3) actions (m/s^2).

        Worlds not stepping must be reset before their next step. Returns (terminated (W,)
        bool, info) from the true state at the end of the step; info holds (W, A) arrays
        ``reward_<term>`` (REWARD_TERMS), ``reward`` (their sum), ``position_error``
        (m), ``velocity_error`` (m/s), ``status`` (int64, the world's), and (W, A, 3)
        ``field_mean``, ``field_applied`` (m/s^2, the step's first autopilot tick).
        """
        sim, ag, W, A = self.sim, self.agent_index, self.W, self.agent_index.size
        if stepping is not None and not stepping.all():
            sim.active &= stepping
        self._command[:, ag] = actions
        row = sim.tick(residual=self._command) if sim.active.any() else None
        true = sim.true_states()
        ref = sim.reference(sim.t)
        status = np.empty(W, np.int64)
        terms = np.empty((len(REWARD_TERMS), W, A))
        reward, pos_err, vel_err = np.empty((W, A)), np.empty((W, A)), np.empty((W, A))
        task_kernel(true.pos, true.vel, ref.pos, ref.vel, ag, actions, self.last_action, sim.status,
                     self._task_constants, status, terms, reward, pos_err, vel_err)
        terminated = status != _OK
        if stepping is None:
            self.last_action[:] = actions
        else:
            self.last_action[stepping] = actions[stepping]
        self._obs_cache = (true.rot, ref)
        info: dict[str, np.ndarray] = {f"reward_{k}": terms[i] for i, k in enumerate(REWARD_TERMS)}
        info["reward"] = reward
        info.update(position_error=pos_err, velocity_error=vel_err, status=np.repeat(status[:, None], A, axis=1))
        for key in ("field_mean", "field_applied"):
            info[key] = row[key][:, ag] if row is not None else np.zeros((W, A, 3))
        return terminated, info

    # ---------------------------------------------------------------- observation
    def observe(self, fresh: bool = True) -> np.ndarray:
        """(W, A, D) float32 in `observation_layout(K)`, clipped to its bounds (NaN -> 0).

        fresh=False reuses the attitudes and reference of the last step (no reset since).
        """
        sim = self.sim
        if fresh or self._obs_cache is None:
            rot, ref = sim.true_states().rot, sim.reference(sim.t)
        else:
            rot, ref = self._obs_cache
        o = np.empty((self.W, self.agent_index.size, obs_dim(self.K)))
        _observe_kernel(sim.pos_est, sim.vel_est, rot, ref.pos, ref.vel, ref.acc, self.agent_index,
                        self.last_action, self.obs_low, self.obs_high, o)
        return o.astype(np.float32)


# ----------------------------------------------------------------------------- the envs


class _SwarmBase:
    """What the two swarm envs share: config, engine, spaces, rendering."""

    metadata: dict[str, Any]
    _worlds: SwarmWorlds

    def _setup(self, options: dict[str, Any], render_mode: str | None, n_worlds: int, n_threads: int = 0) -> None:
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"render_mode: got {render_mode!r}; allowed: None, {', '.join(RENDER_MODES)}")
        self.config = cfg = make_swarm_config(**options)
        check_world_memory(n_worlds, len(cfg.preset.vehicles), name="n_worlds")  # before anything is allocated
        self.render_mode = render_mode
        self.metadata = {**type(self).metadata, "render_fps": cfg.task.control_hz}
        self._worlds = SwarmWorlds(cfg, n_worlds, n_threads)
        self.possible_agents: list[str] = list(self._worlds.agents)
        low, high = obs_bounds(cfg.max_neighbours, cfg.bound)
        # one space object per agent, returned as is each time (PettingZoo's API test checks identity)
        self.observation_spaces = {a: spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
                                   for a in self.possible_agents}
        self.action_spaces = {a: spaces.Box(-1.0, 1.0, (3,), np.float32) for a in self.possible_agents}
        self.max_steps = cfg.max_steps
        self._renderer: Renderer | None = None

    def observation_space(self, agent: str) -> spaces.Box:
        """Box (obs_dim(K),) float32 of one agent in one world."""
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Box:
        """Box (3,) float32, m/s^2, of one agent in one world."""
        return self.action_spaces[agent]

    @property
    def dt(self) -> float:
        """s, one env step (the controller period)."""
        return self._worlds.sim_config.rates.control_dt

    @property
    def simulator(self) -> Simulator:
        """The underlying `Simulator` (batched over the env's worlds), for diagnostics."""
        return self._worlds.sim

    def _frames(self, worlds: Sequence[int]) -> list[np.ndarray] | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; make the env with render_mode='rgb_array'")
            return None
        if self._renderer is None:
            t = self.config.task
            self._renderer = Renderer(self._worlds.scene, t.render_width, t.render_height)
        sim, top = self._worlds.sim, self._worlds.scene.leader
        pos = sim.true_states().pos  # (W, V, 3) m
        frames = []
        for w in worlds:
            far = int(np.nanargmax(np.linalg.norm(pos[w] - pos[w, top], axis=-1))) if np.isfinite(pos[w]).any() else top
            nowhere = np.full(3, np.nan)  # no reference marker: several followers have one each
            frames.append(self._renderer.render(sim.physics.mjdata(w), pos[w, top], pos[w, far], nowhere))
        return frames

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


@pickled_as_constructed
class SwarmEnv(_SwarmBase, ParallelEnv):
    """Every follower of a preset is an agent; one world, plain `MjData` (see the module docstring).

    reset(seed): episodes draw from the env's generator (`self.np_random`); the same seed
    and the same actions give the same trajectory, bit for bit.
    """

    metadata = {"name": "downwash_swarm_v0", "render_modes": list(RENDER_MODES), "render_fps": 50,
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
        ep = draw_swarm_episode(self.np_random, self.config)
        self._worlds.reset_worlds([0], [ep])
        self._elapsed = 0
        self.agents = list(self.possible_agents)
        obs = self._worlds.observe()[0]
        info = {"sim_seed": ep.sim_seed, "phase": ep.phase}
        return {a: obs[i] for i, a in enumerate(self.possible_agents)}, {a: dict(info) for a in self.agents}

    def step(self, actions: Mapping[str, Any]):
        if not self.agents:
            raise RuntimeError("step() with no live agents: the episode has ended; call reset()")
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
        frames = self._frames((0,))
        return None if frames is None else frames[0]


@pickled_as_constructed
class SwarmVectorEnv(_SwarmBase):
    """`n_worlds` swarm worlds on one `mujoco.batch.Batch`, per-agent arrays with a leading world axis.

    reset(seed=s) seeds world k with s + k (`reset(seed=[...])`: one per world), so world k
    equals `SwarmEnv.reset(seed=s + k)` step for step; `options={"reset_mask": (W,) bool}`
    resets only those worlds. step({agent: (W, 3)}) -> observations {agent: (W, D)}, rewards,
    terminations, truncations {agent: (W,)}, infos {agent: {key: (W, ...)}} (the ParallelEnv's
    keys). Autoreset on the next step (Gymnasium's default): the step after a world ends
    resets it; its actions are ignored, its reward is 0, terminated and truncated False,
    its observation the new episode's first, and ``infos[agent]["autoreset"]`` marks it
    (``sim_seed`` and ``phase`` give its episode). n_threads: the threads that step the worlds: 0 (default) one per
    core this process may use (its CPU affinity), 1..that many as given, anything else a
    ConfigError. Set 1 when other threads of the process need the cores, e.g. a learner's
    torch threads: the helper threads wait for work by spinning.
    """

    metadata = {"name": "downwash_swarm_vector_v0", "render_modes": list(RENDER_MODES), "render_fps": 50}

    def __init__(self, n_worlds: int = 8, render_mode: str | None = None, n_threads: int = 0, **options: Any):
        N = count("n_worlds", n_worlds, 1)
        self._setup(options, render_mode, n_worlds=N, n_threads=n_threads)
        self.n_worlds = N
        self.agents = list(self.possible_agents)  # every agent always has a row; ended worlds autoreset
        self._rngs: list[np.random.Generator | None] = [None] * N
        self._autoreset = np.zeros(N, bool)
        self._elapsed = np.zeros(N, np.int64)
        self._sim_seed = np.zeros(N, np.int64)
        self._phase = np.zeros(N)

    def _reset_worlds(self, worlds: np.ndarray) -> None:
        episodes = []
        for w in worlds:
            if self._rngs[w] is None:
                self._rngs[w], _ = seeding.np_random()
            episodes.append(draw_swarm_episode(self._rngs[w], self.config))
        self._worlds.reset_worlds(worlds, episodes)
        self._elapsed[worlds] = 0
        self._sim_seed[worlds] = [ep.sim_seed for ep in episodes]
        self._phase[worlds] = [ep.phase for ep in episodes]

    def reset(self, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None):
        N = self.n_worlds
        seeds, mask = vector_reset_plan(N, seed, options)
        worlds = np.flatnonzero(mask)
        for w in worlds:
            if seeds[w] is not None:
                self._rngs[w], _ = seeding.np_random(int(seeds[w]))
        self._reset_worlds(worlds)
        self._autoreset[worlds] = False
        obs = self._worlds.observe()
        info = {"sim_seed": self._sim_seed.copy(), "phase": self._phase.copy(), "autoreset": mask.copy()}
        return self._per_agent(obs), {a: dict(info) for a in self.possible_agents}

    def step(self, actions: Mapping[str, Any]):
        N = self.n_worlds
        a = self._worlds.check_actions(actions, self.possible_agents, N)
        resetting = self._autoreset
        stepping = ~resetting
        any_reset = bool(resetting.any())
        terminated, info = self._worlds.step(a, stepping if any_reset else None)
        self._elapsed += stepping
        truncated = self._elapsed >= self.max_steps
        if any_reset:
            worlds = np.flatnonzero(resetting)
            self._reset_worlds(worlds)
            terminated = terminated & stepping
            truncated = truncated & stepping
            for key, value in info.items():  # the reset worlds did not step: their step info is 0
                value[resetting] = 0
            obs = self._worlds.observe()
        else:
            obs = self._worlds.observe(fresh=False)
        self._autoreset = terminated | truncated
        observations = self._per_agent(obs)
        rewards = {ag: info["reward"][:, i] for i, ag in enumerate(self.possible_agents)}
        terms = {ag: terminated.copy() for ag in self.possible_agents}
        truncs = {ag: truncated.copy() for ag in self.possible_agents}
        infos = {}
        for i, ag in enumerate(self.possible_agents):
            infos[ag] = {k: v[:, i] for k, v in info.items() if k != "reward"}
            infos[ag].update(sim_seed=self._sim_seed.copy(), phase=self._phase.copy(), autoreset=resetting.copy())
        return observations, rewards, terms, truncs, infos

    def _per_agent(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        return {a: obs[:, i] for i, a in enumerate(self.possible_agents)}

    def render(self):
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
