"""The follower task, batched over worlds: episodes, references, observation (the engine does the rest).

`FollowerWorlds` is the follower task on the one engine (`downwash_envs.engine.TaskWorlds`):
W worlds on one `sim.simulator.Simulator` (one `MjData` for W = 1, a `mujoco.batch.Batch`
otherwise), the follower the one agent. The single and the vector env both run it, and both
draw episodes with `draw_episode`, which is why the vector env equals a `SyncVectorEnv` of
single envs step for step.

The reward and termination are the engine's (`downwash_envs.reward`, shared with the swarm
task; re-exported here). The observation is `observation` and its compiled twin
`observe_kernel`.

Shapes: W worlds, V vehicles (the scene's leader and follower); positions m,
velocities m/s, accelerations and actions m/s^2, all world frame, z up.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np

from downwash_core.jit import njit
from downwash_envs.config import FIELD_KNOBS, FollowerConfig, build_field, predictor_of
from downwash_envs.engine import TaskWorlds, VehicleScales, check_action, draw_vehicle_scales, env_controller
from downwash_envs.observation import OBS_DIM, OBS_SLICES, OBSERVATION, obs_bounds
from downwash_envs.reward import (  # noqa: F401  (the follower task's reward, defined once for both tasks)
    ERROR_CAP, INFO_KEYS, REWARD_TERMS, squared_norm, task_constants, task_kernel, task_terms,
)
from sim.field import DownwashField
from sim.fields.per_world import PerWorldFields
from sim.predictor import OraclePredictor
from sim.scene import Scene, build_scene
from sim.observer import bandwidth_for
from downwash_trajectories import Cached, Hover, TimeShifted, Waypoints, make_reference, random_passes, stack

__all__ = [
    "REWARD_TERMS", "INFO_KEYS", "ERROR_CAP", "Episode", "draw_episode", "nominal_episode", "episode_info",
    "task_constants", "task_terms", "task_kernel", "squared_norm", "observation", "StepOutcome", "FollowerWorlds",
]  # fmt: skip


# ----------------------------------------------------------------------------- episodes


@dataclass(frozen=True)
class Episode:
    """What is drawn per episode from the env's generator (the same draws in every env class)."""

    sim_seed: int  # seeds the world's noise (motion capture, turbulence)
    separation: float  # m
    phase: float  # -, fraction of the period at which the reference starts
    field_scales: tuple[float, ...]  # factors, in FollowerConfig.field_scales order
    mass_scale: float  # -, true / nominal follower mass
    # passes: points (K, 3) m, durations (K-1,) s, dwell (K,) s; None for the other references
    pattern: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    vehicle: VehicleScales | None = None  # the follower's drawn factors (mass_randomization, randomize); None: nominal


def draw_episode(rng: np.random.Generator, cfg: FollowerConfig) -> Episode:
    """Draw one episode's parameters, always in the same order (seed, separation, phase, ...; `randomize` last)."""
    sim_seed = int(rng.integers(0, 2**63 - 1))
    lo, hi = cfg.separation_range
    separation = float(rng.uniform(lo, hi))
    phase = float(rng.uniform(0.0, 1.0))
    scales = tuple(float(rng.uniform(a, b)) for a, b in cfg.field_scales.values())
    mass_scale = float(rng.uniform(*cfg.mass_randomization)) if cfg.mass_randomization is not None else 1.0
    pattern = None
    if cfg.reference == "passes":
        kw = dict(cfg.reference_kwargs or {})
        wp = random_passes(rng, 1, cfg.leader_position, depth_range=cfg.separation_range, **kw)
        k = int(wp.n_points[0])
        pattern = (wp.points[0, :k].copy(), wp.durations[0, : k - 1].copy(), wp.dwell[0, :k].copy())
        separation = float(cfg.leader_position[2] - pattern[0][0, 2])  # the first waypoint's depth
    vehicle = draw_vehicle_scales(rng, cfg.vehicle_spreads, 1)  # last: the draws above are an env's without it
    if cfg.mass_randomization is not None:
        vehicle = VehicleScales(mass=np.array([mass_scale]))
    elif vehicle is not None and vehicle.mass is not None:
        mass_scale = float(vehicle.mass[0])
    return Episode(sim_seed, separation, phase, scales, mass_scale, pattern, vehicle)


def nominal_episode(cfg: FollowerConfig) -> Episode:
    """A placeholder episode for construction (before the first reset draws one)."""
    pattern = None
    if cfg.reference == "passes":
        below = np.array(cfg.leader_position, float) - [0.0, 0.0, cfg.separation_range[0]]
        pattern = (below[None], np.zeros(0), np.zeros(1))
    n = len(cfg.field_scales)
    return Episode(0, cfg.separation_range[0], 0.0, (1.0,) * n, 1.0, pattern)


def episode_info(cfg: FollowerConfig, ep: Episode) -> dict[str, Any]:
    """The info of reset(): the episode's drawn parameters (plain Python numbers)."""
    info: dict[str, Any] = {"separation": ep.separation, "mass_scale": ep.mass_scale}
    for name, s in zip(cfg.field_scales, ep.field_scales):
        info[f"field_scale_{name}"] = s
    for name in ("inertia", "motor_lag"):  # the mass factor is mass_scale
        factors = getattr(ep.vehicle, name) if ep.vehicle is not None else None
        if factors is not None:
            info[f"{name}_scale"] = float(factors[0])
    return info


@functools.lru_cache(maxsize=1)
def _scene() -> Scene:
    """The two-vehicle scene, compiled once per process (read-only: physics copies on write)."""
    return build_scene()


# ----------------------------------------------------------------------------- the batched task


class StepOutcome(NamedTuple):
    """What a step of W worlds gives, from the true state at its end."""

    terminated: np.ndarray  # (W,) bool: the status is not OK
    reward: np.ndarray  # (W,): the sum of the reward terms in REWARD_TERMS order
    values: np.ndarray  # (len(INFO_KEYS) - 1, W) float64: INFO_KEYS' reward terms and errors (m, m/s; capped)
    status: np.ndarray  # (W,) int64 `downwash_core.status.Status` codes

    def info(self) -> dict[str, np.ndarray]:
        """INFO_KEYS -> (W,) arrays."""
        return dict(zip(INFO_KEYS, (*self.values, self.status)))

    def world_info(self, w: int) -> dict[str, float | int]:
        """INFO_KEYS -> world w's plain Python floats and status int (the single env's info)."""
        return dict(zip(INFO_KEYS, (*self.values[:, w].tolist(), int(self.status[w]))))


class FollowerWorlds(TaskWorlds):
    """W worlds of the follower task on the engine: per-world episodes, batched obs and reward."""

    obs_shape = (OBS_DIM,)

    def __init__(self, cfg: FollowerConfig, n_worlds: int, n_threads: int = 0):
        self.cfg = cfg
        scene = _scene()
        self.i_leader, self.i_follower = scene.leader, scene.follower
        self.leader = np.array(cfg.leader_position, dtype=float)  # (3,) m, where the leader hovers
        # field: the knobs once; per-world constants when randomised
        field = build_field(cfg.field)  # None, a registered name / spec string, or an object
        knobs = {k: float(getattr(cfg, k)) for k in FIELD_KNOBS if float(getattr(cfg, k)) != 0.0}
        self.base_field = dataclasses.replace(field, **knobs) if knobs else field
        self.scale_names = tuple(cfg.field_scales)
        self.ref_kwargs = dict(cfg.reference_kwargs or {})
        episodes = [nominal_episode(cfg)] * int(n_worlds)
        field_now = self._field(episodes)
        super().__init__(cfg, scene, [scene.follower], episodes, n_threads, field=field_now,
                         predictor=self._predictor(field_now))
        self.obs_low, self.obs_high = obs_bounds(self.bound)

    def new_episode(self, rng: np.random.Generator) -> Episode:
        return draw_episode(rng, self.cfg)

    # ---------------------------------------------------------------- per-world parameters
    def _field(self, episodes: Sequence[Episode]) -> Any:
        """The worlds' field: the base field, or with each world's constants scaled by its episode's factors.

        A `DownwashField` takes them as (W, 1, 1) array constants; any other field of float constants
        (`config.randomizable_constants`) is rebuilt per world and flown as `sim.fields.per_world.PerWorldFields`.
        """
        if not self.scale_names:
            return self.base_field
        base = {name: float(getattr(self.base_field, name)) for name in self.scale_names}
        if not isinstance(self.base_field, DownwashField):
            return PerWorldFields([
                dataclasses.replace(self.base_field, **{name: base[name] * s for name, s in zip(base, ep.field_scales)})
                for ep in episodes
            ])
        scales = np.array([ep.field_scales for ep in episodes])  # (W, n)
        values = {name: (base[name] * scales[:, i]).reshape(len(episodes), 1, 1) for i, name in enumerate(base)}
        return dataclasses.replace(self.base_field, **values)

    def _predictor(self, field: Any) -> Any:
        return predictor_of(self.cfg.predictor, lambda: OraclePredictor(field), self,
                            bandwidth_for(env_controller(self.cfg)))

    def _episodes_changed(self) -> None:
        if self.scale_names:
            self.sim.field = self._field(self.episodes)
            self.sim.predictor = self._predictor(self.sim.field)

    def _reference(self) -> Cached:
        """Both vehicles' references (W, V): the leader hovers, the follower flies the episode's path."""
        cfg, W, eps = self.cfg, self.W, self.episodes
        if cfg.reference == "passes":
            follower = Waypoints.from_patterns(
                [ep.pattern[0] for ep in eps], [ep.pattern[1] for ep in eps], [ep.pattern[2] for ep in eps]
            )
        else:
            sep = np.array([ep.separation for ep in eps])
            below = self.leader - sep[:, None] * np.array([0.0, 0.0, 1.0])  # (W, 3) m
            follower = make_reference(cfg.reference, below, W, **self.ref_kwargs)
        t0 = np.zeros(W)
        if cfg.random_phase and cfg.reference in ("lemniscate", "transect"):
            t0 = np.array([ep.phase for ep in eps]) * follower.period
        by_role = {self.i_leader: Hover(self.leader, n_worlds=W), self.i_follower: TimeShifted(follower, t0)}
        return Cached(stack([by_role[i] for i in range(len(by_role))]))

    # ---------------------------------------------------------------- step
    def check_actions(self, action: Any, shape: tuple[int, ...]) -> np.ndarray:
        """Validate (shape, finite), clip to [-1, 1] and scale by the bound: the action in m/s^2;
        ValueError before any stepping."""
        a = check_action("action", action, shape)
        a *= self.bound
        return a

    def step(self, actions: np.ndarray, stepping: np.ndarray | None = None) -> StepOutcome:
        """Advance the `stepping` worlds (default all) one controller period with (W, 3) actions (m/s^2).

        Worlds not stepping must be reset before their next step (their outcome is zero). Returns
        the `StepOutcome` of every world, from the true state at the end of the step (`task_terms`, compiled).
        """
        out = self.advance(actions[:, None], stepping)
        return StepOutcome(out.terminated, out.reward[:, 0], out.values[:, :, 0], out.status)

    # ---------------------------------------------------------------- observation (`observe`: the engine's)
    def _observe_into(self, rot: np.ndarray, ref: Any, out: np.ndarray) -> None:
        sim = self.sim
        observe_kernel(sim.pos_est, sim.vel_est, rot, ref.pos, ref.vel, ref.acc, self.i_leader, self.i_follower,
                        self.last_action[:, 0], self.obs_low, self.obs_high, out)

    def camera_targets(self, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The leader, the follower and the follower's reference (3,) m."""
        pos = self.sim.true_states().pos[w]  # (V, 3) m
        return pos[self.i_leader], pos[self.i_follower], self.sim.reference(self.sim.t).pos[w, self.i_follower]


# ----------------------------------------------------------------------------- observation


def observation(
    pos_est: np.ndarray, vel_est: np.ndarray, rot: np.ndarray, ref: Any, leader: int, follower: int,
    last_action: np.ndarray, low: np.ndarray, high: np.ndarray,
) -> np.ndarray:
    """(W, OBS_DIM): the readable observation in `downwash_envs.observation.OBSERVATION`'s layout, clipped to
    [low, high], NaN (only a diverged world's) read as 0; `FollowerWorlds` runs its compiled twin
    `observe_kernel`, which a test compares with this bit for bit.

    pos_est, vel_est: (W, V, 3) m, m/s estimated; rot: (W, V, 3, 3) true attitudes; ref: a
    RefSample of (W, V, ...) arrays; leader, follower: vehicle indices; last_action (W, 3) m/s^2.
    """
    L, F = leader, follower
    parts = {
        "dp": pos_est[:, F] - pos_est[:, L],
        "v_follower": vel_est[:, F],
        "v_leader": vel_est[:, L],
        "pos_error": pos_est[:, F] - ref.pos[:, F],
        "vel_error": vel_est[:, F] - ref.vel[:, F],
        "ref_acc": ref.acc[:, F],
        "follower_x_axis": rot[:, F, :, 0],
        "follower_z_axis": rot[:, F, :, 2],
        "leader_z_axis": rot[:, L, :, 2],
        "last_action": last_action,
    }
    o = np.clip(np.concatenate([parts[e.name] for e in OBSERVATION], axis=1), low, high)
    o[np.isnan(o)] = 0.0
    return o


# where each entry starts (numba freezes these globals into the kernel)
(_O_DP, _O_V_FOLLOWER, _O_V_LEADER, _O_POS_ERROR, _O_VEL_ERROR, _O_REF_ACC, _O_X_AXIS, _O_Z_AXIS, _O_LEADER_Z_AXIS,
 _O_LAST_ACTION) = (OBS_SLICES[name].start for name in (
    "dp", "v_follower", "v_leader", "pos_error", "vel_error", "ref_acc", "follower_x_axis", "follower_z_axis",
    "leader_z_axis", "last_action"))  # fmt: skip


@njit
def observe_kernel(pos_est, vel_est, rot, ref_pos, ref_vel, ref_acc, leader, follower, last_action, low, high, out):
    """Compiled `observation`, written into out (W, OBS_DIM) (a test checks the two bit for bit)."""
    L, F = leader, follower
    for w in range(out.shape[0]):
        o = out[w]
        for k in range(3):
            o[_O_DP + k] = pos_est[w, F, k] - pos_est[w, L, k]
            o[_O_V_FOLLOWER + k] = vel_est[w, F, k]
            o[_O_V_LEADER + k] = vel_est[w, L, k]
            o[_O_POS_ERROR + k] = pos_est[w, F, k] - ref_pos[w, F, k]
            o[_O_VEL_ERROR + k] = vel_est[w, F, k] - ref_vel[w, F, k]
            o[_O_REF_ACC + k] = ref_acc[w, F, k]
            o[_O_X_AXIS + k] = rot[w, F, k, 0]
            o[_O_Z_AXIS + k] = rot[w, F, k, 2]
            o[_O_LEADER_Z_AXIS + k] = rot[w, L, k, 2]
            o[_O_LAST_ACTION + k] = last_action[w, k]
        for j in range(o.size):
            v = o[j]
            if v != v:  # NaN
                o[j] = 0.0
            elif v < low[j]:
                o[j] = low[j]
            elif v > high[j]:
                o[j] = high[j]
