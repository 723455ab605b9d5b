"""The follower task, batched over worlds: episodes, observation, reward terms, termination.

`FollowerWorlds` runs W worlds of the task on one `sim.simulator.Simulator` (one
`MjData` for W = 1, a `mujoco.batch.Batch` otherwise). Everything per step is
batched over worlds; Python loops over worlds happen only at reset. The single and
the vector env both run it, and both draw episodes with `draw_episode`, which is
why the vector env equals a `SyncVectorEnv` of single envs step for step.

Shapes: W worlds, V vehicles (the scene's leader and follower); positions m,
velocities m/s, accelerations and actions m/s^2, all world frame, z up.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from controllers.lqr import FeedbackLinearisedLQR
from core.geometry import dot
from core.status import Status
from envs.config import FIELD_KNOBS, FollowerConfig, build_field
from envs.observation import OBS_DIM, OBS_SLICES, obs_bounds
from sim.predictor import OraclePredictor, ZeroPredictor
from sim.scene import Scene, build_scene
from sim.simulator import Simulator
from trajectories import Cached, Hover, TimeShifted, Waypoints, make_reference, random_passes, stack

__all__ = ["REWARD_TERMS", "total_reward", "ERROR_CAP", "Episode", "draw_episode", "nominal_episode", "episode_info", "FollowerWorlds"]

# Reward terms, summed in this order: reward = sum(info["reward_" + name] for name in REWARD_TERMS).
REWARD_TERMS = ("alive", "position", "velocity", "action", "action_rate", "termination")
_OK, _LEFT_BOX = int(Status.OK), int(Status.LEFT_BOX)  # plain ints: no enum conversion per step


def total_reward(info: dict) -> Any:
    """The reward: the sum of ``info["reward_<term>"]`` in REWARD_TERMS order (floats or (W,) arrays alike,
    so that every env class sums the same way, bit for bit)."""
    reward = 0.0
    for k in REWARD_TERMS:
        reward = reward + info[f"reward_{k}"]
    return reward
ERROR_CAP = 10.0  # m and m/s: position/velocity errors in the reward are capped (a diverged state is not finite)


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


def draw_episode(rng: np.random.Generator, cfg: FollowerConfig) -> Episode:
    """Draw one episode's parameters, always in the same order (seed, separation, phase, ...)."""
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
    return Episode(sim_seed, separation, phase, scales, mass_scale, pattern)


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
    return info


@functools.lru_cache(maxsize=1)
def _scene() -> Scene:
    """The two-vehicle scene, compiled once per process (read-only: physics copies on write)."""
    return build_scene()


# ----------------------------------------------------------------------------- the batched task


class FollowerWorlds:
    """W worlds of the follower task on one Simulator: per-world episodes, batched obs and reward."""

    def __init__(self, cfg: FollowerConfig, n_worlds: int, n_threads: int = 0):
        self.cfg = cfg
        self.W = W = int(n_worlds)
        self.scene = scene = _scene()
        self.i_leader, self.i_follower = scene.leader, scene.follower
        base = cfg.sim_base
        per_control = int(round(1.0 / (base.rates.autopilot_dt * cfg.control_hz)))
        rates = dataclasses.replace(base.rates, autopilot_per_control=per_control)
        self.sim_config = dataclasses.replace(base, rates=rates)
        self.leader = np.array(cfg.leader_position, dtype=float)  # (3,) m, where the leader hovers
        self.bound = cfg.bound
        self.residual_mode = cfg.action_mode == "residual"

        # field: the knobs once; per-world constants when randomised
        field = build_field(cfg.field)  # None, a registered name / spec string, or an object
        knobs = {k: float(getattr(cfg, k)) for k in FIELD_KNOBS if float(getattr(cfg, k)) != 0.0}
        self.base_field = dataclasses.replace(field, **knobs) if knobs else field
        self.scale_names = tuple(cfg.field_scales)
        self.episodes: list[Episode] = [nominal_episode(cfg)] * W

        self.ref_kwargs = dict(cfg.reference_kwargs or {})
        self.follower_body = np.array([scene.body_ids[self.i_follower]])
        self.nominal_mass = float(scene.model.body_mass[scene.body_ids[self.i_follower]])  # kg

        field_now = self._field()
        self.sim = Simulator(
            scene, self._reference(), [0] * W, config=self.sim_config, field=field_now,
            predictor=self._predictor(field_now), n_threads=n_threads,
            controller=FeedbackLinearisedLQR(cfg.lqr), turbulence=cfg.turbulence,
        )
        V = self.sim.V
        self.last_action = np.zeros((W, 3))  # m/s^2, as applied (clipped)
        # the simulator's (W, V, 3) command; NaN keeps the leader's LQR in acceleration mode
        self._command = np.zeros((W, V, 3)) if self.residual_mode else np.full((W, V, 3), np.nan)
        self._obs_cache: tuple[np.ndarray, Any] | None = None  # attitudes and reference of the last step
        self.obs_low, self.obs_high = obs_bounds(self.bound)

    # ---------------------------------------------------------------- per-world parameters
    def _field(self) -> Any:
        if not self.scale_names:
            return self.base_field
        scales = np.array([ep.field_scales for ep in self.episodes])  # (W, n)
        values = {
            name: (float(getattr(self.base_field, name)) * scales[:, i]).reshape(self.W, 1, 1)
            for i, name in enumerate(self.scale_names)
        }
        return dataclasses.replace(self.base_field, **values)

    def _predictor(self, field: Any) -> Any:
        return OraclePredictor(field) if self.cfg.predictor == "oracle" else ZeroPredictor()

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

    # ---------------------------------------------------------------- reset
    def reset_worlds(self, worlds: Sequence[int], episodes: Sequence[Episode]) -> None:
        """Start the given worlds on the given episodes (their reference's t = 0 state)."""
        worlds = np.asarray(worlds, dtype=np.int64)
        for w, ep in zip(worlds, episodes):
            self.episodes[w] = ep
        sim = self.sim
        if self.scale_names:
            sim.field = self._field()
            sim.predictor = self._predictor(sim.field)
        if self.cfg.mass_randomization is not None:
            # true follower mass = nominal x scale (inertia likewise); the controller keeps nominal
            scale = np.array([ep.mass_scale for ep in episodes])
            sim.physics.set_body_mass(worlds, self.follower_body, (self.nominal_mass * scale)[:, None])
        sim.reset(worlds, seeds=[ep.sim_seed for ep in episodes], reference=self._reference())
        self.last_action[worlds] = 0.0
        self._obs_cache = None

    # ---------------------------------------------------------------- step
    def check_actions(self, action: Any, shape: tuple[int, ...]) -> np.ndarray:
        """Validate (shape, finite) and clip to the bound; ValueError before any stepping."""
        try:
            a = np.array(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action: expected a float array of shape {shape} (m/s^2), got {action!r}") from None
        if a.shape != shape:
            raise ValueError(f"action: expected shape {shape} (m/s^2, world frame), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: must be finite (m/s^2), got {a.tolist()}")
        return np.clip(a, -self.bound, self.bound, out=a)

    def step(self, actions: np.ndarray, stepping: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Advance the `stepping` worlds (default all) one controller period with (W, 3) actions (m/s^2).

        Worlds not stepping must be reset before their next step. Returns (terminated (W,)
        bool, info), from the true state at the end of the step; info holds (W,) arrays:
        ``reward_<term>`` for each of REWARD_TERMS (the reward is their `total_reward`), ``position_error`` (m), ``velocity_error`` (m/s), both capped, and ``status``
        (int64 `Status` codes).
        """
        sim, F = self.sim, self.i_follower
        if stepping is not None and not stepping.all():
            sim.active &= stepping
        cmd = self._command
        cmd[:, F] = actions
        if sim.active.any():
            if self.residual_mode:
                sim.tick(residual=cmd)
            else:
                sim.tick(override=cmd)
        true = sim.true_states()
        ref = sim.reference(sim.t)
        pos_err = _capped_norm(true.pos[:, F] - ref.pos[:, F])
        vel_err = _capped_norm(true.vel[:, F] - ref.vel[:, F])
        left = ~(pos_err <= self.cfg.max_tracking_error)
        status = np.where(sim.status != _OK, sim.status, np.where(left, _LEFT_BOX, _OK))
        terminated = status != _OK

        c, b2 = self.cfg, self.bound * self.bound
        da = actions - self.last_action
        terms = {
            "alive": c.alive_reward * (~terminated),
            "position": -c.position_cost_weight * pos_err,
            "velocity": -c.velocity_cost_weight * vel_err,
            "action": -c.action_cost_weight * (_sumsq(actions) / b2),
            "action_rate": -c.action_rate_cost_weight * (_sumsq(da) / b2),
            "termination": -c.termination_penalty * terminated,
        }
        if stepping is None:
            self.last_action[:] = actions
        else:
            self.last_action[stepping] = actions[stepping]
        self._obs_cache = (true.rot, ref)
        info = {f"reward_{k}": terms[k] for k in REWARD_TERMS}
        info.update(position_error=pos_err, velocity_error=vel_err, status=status.astype(np.int64))
        return terminated, info

    # ---------------------------------------------------------------- observation
    def observe(self, fresh: bool = True) -> np.ndarray:
        """(W, OBS_DIM) float64, the layout of `envs.observation.OBSERVATION`, clipped to its bounds.

        fresh=False reuses the attitudes and reference of the last step (no reset since).
        """
        sim, L, F = self.sim, self.i_leader, self.i_follower
        if fresh or self._obs_cache is None:
            rot = sim.true_states().rot
            ref = sim.reference(sim.t)
        else:
            rot, ref = self._obs_cache
        pe, ve = sim.pos_est, sim.vel_est
        o = np.empty((self.W, OBS_DIM))
        s = OBS_SLICES
        o[:, s["dp"]] = pe[:, F] - pe[:, L]
        o[:, s["v_follower"]] = ve[:, F]
        o[:, s["v_leader"]] = ve[:, L]
        o[:, s["pos_error"]] = pe[:, F] - ref.pos[:, F]
        o[:, s["vel_error"]] = ve[:, F] - ref.vel[:, F]
        o[:, s["ref_acc"]] = ref.acc[:, F]
        o[:, s["follower_x_axis"]] = rot[:, F, :, 0]
        o[:, s["follower_z_axis"]] = rot[:, F, :, 2]
        o[:, s["leader_z_axis"]] = rot[:, L, :, 2]
        o[:, s["last_action"]] = self.last_action
        np.clip(o, self.obs_low, self.obs_high, out=o)
        nan = np.isnan(o)
        if nan.any():  # only a diverged world's state
            o[nan] = 0.0
        return o


def _sumsq(x: np.ndarray) -> np.ndarray:
    """(W, 3) -> (W,) sum of squares; `dot` sums each row in the same order whatever W, so
    batched and single worlds agree bit for bit."""
    return dot(x, x)


def _capped_norm(x: np.ndarray) -> np.ndarray:
    """(W, 3) -> (W,) Euclidean norm, non-finite or above ERROR_CAP replaced by the cap."""
    n = np.sqrt(_sumsq(x))
    return np.where(n <= ERROR_CAP, n, ERROR_CAP)
