"""The swarm task, batched over worlds: options, episodes, references, observation (the engine does the rest).

`SwarmWorlds` is the swarm task on the one engine (`downwash_envs.engine.TaskWorlds`, as the
follower task `downwash_envs.task.FollowerWorlds`): every follower of a `sim.presets`
preset an agent, every vehicle's wake acting on every other vehicle and combined by the
aggregation law (`sim.aggregation`). The envs (`downwash_envs.swarm`: the PettingZoo
`SwarmEnv`, the batched `SwarmVectorEnv`) are views of it; their docstring describes the
agents, the observation, the reward and the options.

Here: the options (`SwarmConfig`, `make_swarm_config`), the observation layout and its
table, the readable observation (`own_block`, `neighbour_block`, `swarm_observation`) and its
compiled twin `observe_kernel`, the episodes (`draw_swarm_episode`), and the agents' names.

Shapes: W worlds, V vehicles, A agents (the followers), K neighbour slots, D = obs_dim(K);
positions m, velocities m/s, accelerations and actions m/s^2, all world frame, z up.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Mapping, NamedTuple, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.provenance import describe
from downwash_core.roles import MAX_VEHICLES, Role
from downwash_core.validate import count
from downwash_envs.config import (
    REWARD_WEIGHTS, FollowerConfig, build_field, make_config, number_option, predictor_of, unknown_options_error,
)
from downwash_envs.engine import TaskWorlds, VehicleScales, check_action, draw_vehicle_scales, env_controller
from downwash_envs.observation import OBSERVATION, ObsEntry, layout_table, layout_bounds, layout_slices, table_row
from downwash_envs.reward import REWARD_TERMS
from sim.aggregation import DEFAULT_AGGREGATION, LinearSuperposition, make_aggregation
from sim.neighbours import NeighbourSet, select_into, select_neighbours
from sim.predictor import OraclePredictor
from sim.presets import Preset, make_preset
from sim.scene import Scene, build_scene
from sim.observer import bandwidth_for
from downwash_trajectories import Cached, TimeShifted

__all__ = [
    "SHARED_OPTIONS", "OWN_OBSERVATION", "NEIGHBOUR_OBSERVATION", "OWN_DIM", "NEIGHBOUR_DIM",
    "observation_layout", "obs_dim", "obs_slices", "swarm_obs_bounds", "swarm_observation_table",
    "own_block", "neighbour_block", "swarm_observation", "SwarmConfig", "make_swarm_config", "SwarmEpisode",
    "draw_swarm_episode", "swarm_episode_info", "agent_names", "SwarmStep", "SwarmWorlds",
]  # fmt: skip

# The FollowerConfig options that mean the same here (validated by downwash_envs.config); the
# single env's reference, separation, knobs and field/mass randomisations do not apply to a preset.
SHARED_OPTIONS = (
    "action_bound", "control_hz", "predictor", "max_tracking_error", *REWARD_WEIGHTS,
    "sim_config", "lqr", "controller", "turbulence", "render_width", "render_height", "randomize",
)  # fmt: skip

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
    return layout_slices(observation_layout(max_neighbours))


def swarm_obs_bounds(max_neighbours: int, action_bound: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (obs_dim(K),) float64; `action_bound` (m/s^2) bounds last_action."""
    return layout_bounds(observation_layout(max_neighbours), action_bound)


def swarm_observation_table() -> str:
    """The layout as a markdown table (index, name, meaning, unit, frame, bound; "b": the action
    bound), slot k written symbolically; columns padded to their widest cell, no trailing newline."""
    rows, start = [], 0
    for e in OWN_OBSERVATION:
        rows.append(table_row(f"{start}-{start + e.size - 1}" if e.size > 1 else f"{start}", e))
        start += e.size
    offset = 0
    for e in NEIGHBOUR_OBSERVATION:
        base = f"{OWN_DIM}+{NEIGHBOUR_DIM}k"
        index = base + (f"+({offset}-{offset + e.size - 1})" if e.size > 1 else (f"+{offset}" if offset else ""))
        rows.append(table_row(index, e, name=f"nk_{e.name}"))
        offset += e.size
    return layout_table(rows)


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


def swarm_observation(
    pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, ref: Any, agents: np.ndarray,
    last_action: np.ndarray, max_neighbours: int, low: np.ndarray, high: np.ndarray,
) -> np.ndarray:
    """(W, A, obs_dim(K)): the readable observation (own block, neighbour slots), clipped to
    [low, high] with NaN (a diverged world) read as 0; `SwarmWorlds` runs its compiled twin
    `observe_kernel`, which a test compares with this bit for bit."""
    W, A = pos.shape[0], len(agents)
    own = own_block(pos, vel, rot, ref, agents, last_action)
    nb = neighbour_block(pos, vel, rot, agents, max_neighbours).reshape(W, A, max_neighbours * NEIGHBOUR_DIM)
    o = np.clip(np.concatenate((own, nb), axis=-1), low, high)
    o[np.isnan(o)] = 0.0
    return o


@njit
def observe_kernel(pos, vel, rot, ref_pos, ref_vel, ref_acc, agents, last_action, low, high, out):
    """Compiled `swarm_observation`, written into out (W, A, D); the same arithmetic, world by world.

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
        out = {
            "preset": self.preset.describe(), "aggregation": describe(self.law), "field": describe(self.field),
            "max_neighbours": self.max_neighbours, "duration": self.duration, "random_phase": self.random_phase,
            **{k: describe(getattr(t, k)) for k in SHARED_OPTIONS if k not in ("render_width", "render_height",
                                                                                "randomize")},
        }  # fmt: skip
        if t.vehicle_spreads:  # off: the provenance written before the option existed
            out["randomize"] = t.vehicle_spreads
        return out


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
        raise unknown_options_error("the swarm env", unknown, allowed)
    if isinstance(preset, str):
        preset = make_preset(preset)
    elif not isinstance(preset, Preset):
        raise ConfigError(f"preset: expected a preset spec string or a sim.presets.Preset, got {type(preset).__name__}")
    if not any(role == Role.FOLLOWER for _, role in preset.vehicles):
        raise ConfigError(f"preset {preset.name!r}: has no follower, so no agent; allowed: presets with followers")
    if not isinstance(aggregation, str):
        raise ConfigError(f"aggregation: expected a law name, got {type(aggregation).__name__}")
    law = make_aggregation(aggregation)  # ConfigError naming the allowed laws
    V = preset.n_vehicles
    K = V - 1 if max_neighbours is None else count("max_neighbours", max_neighbours, 1, MAX_VEHICLES - 1)
    task = make_config({"field": field, **options})  # the shared options, checked by downwash_envs.config
    if duration is None:
        duration = float(preset.duration)
    else:
        duration = number_option("duration", duration, "s", 0.0, 1e5, lo_open=True)
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
    vehicle: VehicleScales | None = None  # the agents' drawn factors (`randomize`), (A,) each; None: nominal


def draw_swarm_episode(rng: np.random.Generator, cfg: SwarmConfig) -> SwarmEpisode:
    """Draw one episode, always in the same order (seed, then phase, then the `randomize` factors)."""
    sim_seed = int(rng.integers(0, 2**63 - 1))
    u = float(rng.uniform(0.0, 1.0))
    vehicle = draw_vehicle_scales(rng, cfg.task.vehicle_spreads, len(cfg.agents))
    return SwarmEpisode(sim_seed, u * cfg.preset.duration if cfg.random_phase else 0.0, vehicle)


def swarm_episode_info(ep: SwarmEpisode, n_agents: int) -> list[dict[str, Any]]:
    """Each agent's reset info: ``sim_seed``, ``phase`` (s) and, with `randomize`, its drawn
    factors ``mass_scale``, ``inertia_scale``, ``motor_lag_scale`` (plain Python numbers)."""
    common = {"sim_seed": ep.sim_seed, "phase": ep.phase}
    factors = {f"{k}_scale": v for k, v in (ep.vehicle._asdict() if ep.vehicle else {}).items() if v is not None}
    return [{**common, **{k: float(v[i]) for k, v in factors.items()}} for i in range(n_agents)]


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


_REWARD_INFO_KEYS = tuple(f"reward_{k}" for k in REWARD_TERMS)  # the info keys of the terms, in order


class SwarmStep(NamedTuple):
    """A step of the swarm's W worlds: terminated (W,) bool, and the per-agent info (see `SwarmWorlds.step`)."""

    terminated: np.ndarray
    info: dict[str, np.ndarray]


class SwarmWorlds(TaskWorlds):
    """W worlds of the swarm task on the engine: per-world episodes, batched obs and reward.

    Shapes: W worlds, V vehicles, A agents (the followers, `agent_index` (A,) into the
    scene), D = obs_dim(K).
    """

    def __init__(self, cfg: SwarmConfig, n_worlds: int, n_threads: int = 0):
        self.cfg = cfg
        preset, task = cfg.preset, cfg.task
        scene = _scene(tuple(preset.vehicles))
        agent_index = np.array([scene.vehicles.index(a) for a in cfg.agents], dtype=np.int64)
        self.agents = agent_names(preset, cfg.agents)
        self.K = cfg.max_neighbours
        # the preset's references (clearance checked at t = 0), shifted per world by the drawn phase
        sim = task.sim_base
        self._base_ref = preset.reference(n_worlds, sim.collision_radius_xy, sim.collision_radius_z)
        # linear superposition is the simulator's (and the oracle's) own sum; another law goes into their slot
        extra = {} if isinstance(cfg.law, LinearSuperposition) else {"aggregation": cfg.law}
        predictor = predictor_of(task.predictor, lambda: OraclePredictor(cfg.field, **extra), self,
                                 bandwidth_for(env_controller(task)))
        super().__init__(task, scene, agent_index, [SwarmEpisode(0, 0.0)] * int(n_worlds), n_threads,
                         field=cfg.field, predictor=predictor, **extra)
        self.obs_shape = (agent_index.size, obs_dim(self.K))
        self.obs_low, self.obs_high = swarm_obs_bounds(self.K, self.bound)

    def new_episode(self, rng: np.random.Generator) -> SwarmEpisode:
        return draw_swarm_episode(rng, self.cfg)

    def _reference(self) -> Cached:
        """The preset's references (W, V), each world's started at its episode's phase."""
        if not self.cfg.random_phase:
            return Cached(self._base_ref)
        return Cached(TimeShifted(self._base_ref, np.array([ep.phase for ep in self.episodes])))

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
        out = np.zeros((self.W, self.agent_index.size, 3))
        for i, agent in enumerate(self.agents):
            if agent in actions:
                out[:, i] = check_action(f"action of {agent}", actions[agent], shape)
        out *= self.bound  # normalised -> m/s^2
        return out

    def check_action_array(self, actions: Any) -> np.ndarray:
        """(W, A, 3) normalised actions, agent i's at [:, i] -> (W, A, 3) float64 m/s^2: `check_actions` of
        ``{agent i: actions[:, i]}`` in one pass, without the dict: the same numbers, and for a value that is
        not finite the same ValueError, naming the agent; a wrong shape is a ValueError naming the shapes."""
        actions, shape = np.asarray(actions), (self.W, self.agent_index.size, 3)
        if actions.shape != shape:
            raise ValueError(f"actions: expected shape {shape} (worlds, agents, action), got {actions.shape}")
        try:
            a = check_action("actions", actions, shape)  # a clipped float64 copy
        except ValueError:  # the readable check, agent by agent, says which and why
            return self.check_actions({agent: actions[:, i] for i, agent in enumerate(self.agents)}, self.agents,
                                      self.W)
        a *= self.bound  # normalised -> m/s^2
        return a

    def step(self, actions: np.ndarray, stepping: np.ndarray | None = None) -> SwarmStep:
        """Advance the `stepping` worlds (default all) one controller period with (W, A, 3) actions (m/s^2).

        Worlds not stepping must be reset before their next step (their outcome is zero).
        Returns terminated (W,) bool and info from the true state at the end of the step;
        info holds (W, A) arrays ``reward_<term>`` (REWARD_TERMS), ``reward`` (their sum),
        ``position_error`` (m), ``velocity_error`` (m/s), ``status`` (int64, the world's),
        and (W, A, 3) ``field_mean``, ``field_applied`` (m/s^2, the step's first autopilot tick).
        """
        out = self.advance(actions, stepping)
        W, A = out.reward.shape
        info: dict[str, np.ndarray] = dict(zip(_REWARD_INFO_KEYS, out.values))
        info["reward"] = out.reward
        info.update(position_error=out.values[6], velocity_error=out.values[7],
                    status=np.repeat(out.status[:, None], A, axis=1))
        for key in ("field_mean", "field_applied"):
            info[key] = out.row[key][:, self.agent_index] if out.row is not None else np.zeros((W, A, 3))
            if stepping is not None:
                info[key][~stepping] = 0.0
        return SwarmStep(out.terminated, info)

    # ---------------------------------------------------------------- observation (`observe`: the engine's)
    def _observe_into(self, rot: np.ndarray, ref: Any, out: np.ndarray) -> None:
        sim = self.sim
        observe_kernel(sim.pos_est, sim.vel_est, rot, ref.pos, ref.vel, ref.acc, self.agent_index,
                        self.last_action, self.obs_low, self.obs_high, out)

    def camera_targets(self, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The leader, the vehicle farthest from it, and no marker (several followers have one each)."""
        pos, top = self.sim.true_states().pos[w], self.scene.leader  # (V, 3) m
        far = int(np.nanargmax(np.linalg.norm(pos - pos[top], axis=-1))) if np.isfinite(pos).any() else top
        return pos[top], pos[far], np.full(3, np.nan)
