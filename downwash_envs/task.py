"""The follower task, batched over worlds: episodes, observation, reward terms, termination.

`FollowerWorlds` runs W worlds of the task on one `sim.simulator.Simulator` (one
`MjData` for W = 1, a `mujoco.batch.Batch` otherwise). Everything per step is
batched over worlds; Python loops over worlds happen only at reset. The single and
the vector env both run it, and both draw episodes with `draw_episode`, which is
why the vector env equals a `SyncVectorEnv` of single envs step for step.

The reward and termination are `task_terms` (readable) and its compiled twin
`task_kernel`, written for A agents so that the swarm env (`downwash_envs.swarm`, every
follower an agent) runs the same code; here the one agent is the follower. The
observation is `observation` and its compiled twin `_observe_kernel`.

Shapes: W worlds, V vehicles (the scene's leader and follower); positions m,
velocities m/s, accelerations and actions m/s^2, all world frame, z up.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np

from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.jit import njit
from downwash_core.status import Status
from downwash_envs.config import FIELD_KNOBS, FollowerConfig, build_field
from downwash_envs.observation import OBS_DIM, OBS_SLICES, OBSERVATION, obs_bounds
from sim.predictor import OraclePredictor, ZeroPredictor
from sim.scene import Scene, build_scene
from sim.simulator import Simulator
from downwash_trajectories import Cached, Hover, TimeShifted, Waypoints, make_reference, random_passes, stack

__all__ = [
    "REWARD_TERMS", "INFO_KEYS", "ERROR_CAP", "Episode", "draw_episode", "nominal_episode", "episode_info",
    "task_constants", "task_terms", "task_kernel", "squared_norm", "observation", "StepOutcome", "FollowerWorlds",
]  # fmt: skip

# Reward terms, summed in this order: reward = sum(info["reward_" + name] for name in REWARD_TERMS).
REWARD_TERMS = ("alive", "position", "velocity", "action", "action_rate", "termination")
# A step's info, in this order: the reward terms, the errors (m, m/s; true state, capped), the status code.
INFO_KEYS = (*(f"reward_{k}" for k in REWARD_TERMS), "position_error", "velocity_error", "status")
_OK, _LEFT_BOX = int(Status.OK), int(Status.LEFT_BOX)  # plain ints: no enum conversion per step

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
        self._agents = np.array([self.i_follower])  # the task's one agent, for `task_kernel`
        self._constants = task_constants(cfg, self.bound)

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
        """Validate (shape, finite), clip to [-1, 1] and scale by the bound: the action in m/s^2;
        ValueError before any stepping."""
        try:
            a = np.array(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action: expected a float array of shape {shape} in [-1, 1], got {action!r}") from None
        if a.shape != shape:
            raise ValueError(f"action: expected shape {shape} (world frame, in [-1, 1]), got {a.shape}")
        if not _clip_finite(a.reshape(-1), 1.0):
            raise ValueError(f"action: must be finite (in [-1, 1]), got {a.tolist()}")
        a *= self.bound
        return a

    def step(self, actions: np.ndarray, stepping: np.ndarray | None = None) -> StepOutcome:
        """Advance the `stepping` worlds (default all) one controller period with (W, 3) actions (m/s^2).

        Worlds not stepping must be reset before their next step. Returns the `StepOutcome`
        of every world, from the true state at the end of the step (`task_terms`, compiled).
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
        W = self.W
        status, values, reward = np.empty(W, np.int64), np.empty((len(INFO_KEYS) - 1, W, 1)), np.empty((W, 1))
        task_kernel(true.pos, true.vel, ref.pos, ref.vel, self._agents, actions[:, None], self.last_action[:, None],
                    sim.status, self._constants, status, values[:6], reward, values[6], values[7])
        if stepping is None:
            self.last_action[:] = actions
        else:
            self.last_action[stepping] = actions[stepping]
        self._obs_cache = (true.rot, ref)
        return StepOutcome(status != _OK, reward[:, 0], values[:, :, 0], status)

    # ---------------------------------------------------------------- observation
    def observe(self, fresh: bool = True) -> np.ndarray:
        """(W, OBS_DIM) float32, the layout of `downwash_envs.observation.OBSERVATION`, clipped to its bounds.

        fresh=False reuses the attitudes and reference of the last step (no reset since).
        """
        sim = self.sim
        if fresh or self._obs_cache is None:
            rot = sim.true_states().rot
            ref = sim.reference(sim.t)
        else:
            rot, ref = self._obs_cache
        o = np.empty((self.W, OBS_DIM))
        _observe_kernel(sim.pos_est, sim.vel_est, rot, ref.pos, ref.vel, ref.acc, self.i_leader, self.i_follower,
                        self.last_action, self.obs_low, self.obs_high, o)
        return o.astype(np.float32)


# ----------------------------------------------------------------------------- reward, termination, observation


def task_constants(task: FollowerConfig, bound: float) -> np.ndarray:
    """(8,) float64: max_tracking_error (m), the six reward weights in REWARD_TERMS order (the
    costs negated, so that each term is weight * value), and bound^2 (m^2/s^4)."""
    return np.array([
        task.max_tracking_error, task.alive_reward, -task.position_cost_weight, -task.velocity_cost_weight,
        -task.action_cost_weight, -task.action_rate_cost_weight, -task.termination_penalty, bound * bound,
    ])  # fmt: skip


def task_terms(
    true_pos: np.ndarray, true_vel: np.ndarray, ref_pos: np.ndarray, ref_vel: np.ndarray, agents: np.ndarray,
    actions: np.ndarray, last_action: np.ndarray, sim_status: np.ndarray, constants: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The readable reward and termination of a step (the envs run its compiled twin `task_kernel`).

    true_pos, true_vel, ref_pos, ref_vel: (W, V, 3) m, m/s at the end of the step; agents (A,);
    actions, last_action: (W, A, 3) m/s^2 (this step's, the previous); sim_status: (W,) the
    simulator's `Status` codes; constants: `task_constants`. Returns status (W,) int64 (the
    simulator's, else LEFT_BOX when any agent is farther than max_tracking_error from its
    reference, else OK), terms (6, W, A) in REWARD_TERMS order, reward (W, A) (their sum in
    that order), position and velocity errors (W, A), capped
    at ERROR_CAP (non-finite: the cap). The world's end is every agent's.
    """
    max_err, alive, w_p, w_v, w_a, w_da, w_end, b2 = constants
    pos_err = _capped(np.sqrt(squared_norm(true_pos[:, agents] - ref_pos[:, agents])))
    vel_err = _capped(np.sqrt(squared_norm(true_vel[:, agents] - ref_vel[:, agents])))
    left = ~np.all(pos_err <= max_err, axis=1)
    status = np.where(sim_status != _OK, sim_status, np.where(left, _LEFT_BOX, _OK)).astype(np.int64)
    ended = np.repeat((status != _OK)[:, None], len(agents), axis=1).astype(np.float64)  # (W, A) 1.0 / 0.0
    terms = np.stack([
        alive * (1.0 - ended), w_p * pos_err, w_v * vel_err, w_a * (squared_norm(actions) / b2),
        w_da * (squared_norm(actions - last_action) / b2), w_end * ended,
    ])  # fmt: skip
    reward = np.zeros(pos_err.shape)
    for term in terms:
        reward = reward + term
    return status, terms, reward, pos_err, vel_err


def _capped(n: np.ndarray) -> np.ndarray:
    return np.where(n <= ERROR_CAP, n, ERROR_CAP)


@njit
def _capped_distance(x, y):
    """|x - y| of two (3,) vectors, summed x, y, z left to right; non-finite or above ERROR_CAP: the cap."""
    dx, dy, dz = x[0] - y[0], x[1] - y[1], x[2] - y[2]
    e = np.sqrt(dx * dx + dy * dy + dz * dz)
    return e if e <= ERROR_CAP else ERROR_CAP


@njit
def task_kernel(true_pos, true_vel, ref_pos, ref_vel, agents, actions, last_action, sim_status, constants,
                 status, terms, reward, pos_err, vel_err):
    """Compiled `task_terms`, written into status (W,), terms (6, W, A), reward, pos_err, vel_err (W, A)."""
    W, A = pos_err.shape
    max_err, alive, w_p, w_v = constants[0], constants[1], constants[2], constants[3]
    w_a, w_da, w_end, b2 = constants[4], constants[5], constants[6], constants[7]
    for w in range(W):
        inside = True
        for i in range(A):
            a = agents[i]
            pos_err[w, i] = _capped_distance(true_pos[w, a], ref_pos[w, a])
            vel_err[w, i] = _capped_distance(true_vel[w, a], ref_vel[w, a])
            inside = inside and pos_err[w, i] <= max_err
        if sim_status[w] != _OK:
            status[w] = sim_status[w]
        elif not inside:
            status[w] = _LEFT_BOX
        else:
            status[w] = _OK
        ended = 1.0 if status[w] != _OK else 0.0
        for i in range(A):
            ax, ay, az = actions[w, i, 0], actions[w, i, 1], actions[w, i, 2]
            dx, dy, dz = ax - last_action[w, i, 0], ay - last_action[w, i, 1], az - last_action[w, i, 2]
            terms[0, w, i] = alive * (1.0 - ended)
            terms[1, w, i] = w_p * pos_err[w, i]
            terms[2, w, i] = w_v * vel_err[w, i]
            terms[3, w, i] = w_a * ((ax * ax + ay * ay + az * az) / b2)
            terms[4, w, i] = w_da * ((dx * dx + dy * dy + dz * dz) / b2)
            terms[5, w, i] = w_end * ended
            r = 0.0
            for k in range(6):
                r = r + terms[k, w, i]
            reward[w, i] = r


def squared_norm(x: np.ndarray) -> np.ndarray:
    """(..., 3) -> (...) squared norm, summed x, y, z left to right (as the compiled kernels)."""
    return x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1] + x[..., 2] * x[..., 2]


def observation(
    pos_est: np.ndarray, vel_est: np.ndarray, rot: np.ndarray, ref: Any, leader: int, follower: int,
    last_action: np.ndarray, low: np.ndarray, high: np.ndarray,
) -> np.ndarray:
    """(W, OBS_DIM): the readable observation in `downwash_envs.observation.OBSERVATION`'s layout, clipped to
    [low, high], NaN (only a diverged world's) read as 0; `FollowerWorlds` runs its compiled twin
    `_observe_kernel`, which a test compares with this bit for bit.

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


@njit
def _clip_finite(a, bound):
    """Clip a (n,) to [-bound, bound] in place, as np.clip; False (a untouched) if a value is not finite."""
    for i in range(a.size):
        if not np.isfinite(a[i]):
            return False
    for i in range(a.size):
        a[i] = min(max(a[i], -bound), bound)
    return True


# where each entry starts (numba freezes these globals into the kernel)
(_O_DP, _O_V_FOLLOWER, _O_V_LEADER, _O_POS_ERROR, _O_VEL_ERROR, _O_REF_ACC, _O_X_AXIS, _O_Z_AXIS, _O_LEADER_Z_AXIS,
 _O_LAST_ACTION) = (OBS_SLICES[name].start for name in (
    "dp", "v_follower", "v_leader", "pos_error", "vel_error", "ref_acc", "follower_x_axis", "follower_z_axis",
    "leader_z_axis", "last_action"))  # fmt: skip


@njit
def _observe_kernel(pos_est, vel_est, rot, ref_pos, ref_vel, ref_acc, leader, follower, last_action, low, high, out):
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
