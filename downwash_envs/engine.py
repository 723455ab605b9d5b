"""The one engine both env tasks run on: W worlds of a tracking task on one `sim.simulator.Simulator`.

`TaskWorlds` holds what the follower task (`downwash_envs.task.FollowerWorlds`) and the
swarm task (`downwash_envs.swarm_task.SwarmWorlds`) share: the simulator at the task's
control rate (one `MjData` for W = 1, a `mujoco.batch.Batch` otherwise), the worlds'
episodes, the agents' commands, the reward and termination (`downwash_envs.reward`,
compiled), the vehicles' per-episode parameters, and the observation's cache. A task
supplies its scene and agents, its episodes, its references and its observation kernel
(the methods to override, at the end of the class). Everything per step is batched over
worlds; Python loops over worlds happen only at reset.

Also here: `check_action` (one action validated and clipped) and the per-episode vehicle
randomisation (`VehicleScales`, `draw_vehicle_scales`, `VehicleModel`).

Shapes: W worlds, V vehicles, A agents (the vehicles the actions command); positions m,
velocities m/s, accelerations and actions m/s^2, all world frame, z up.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, NamedTuple, Sequence

import mujoco
import numpy as np

from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.status import Status
from downwash_envs.config import FollowerConfig
from downwash_envs.reward import INFO_KEYS, task_constants, task_kernel
from sim.physics import Physics
from sim.scene import Scene
from sim.simulator import SimConfig, Simulator

__all__ = [
    "VehicleScales", "draw_vehicle_scales", "VehicleModel", "check_action", "control_sim_config", "BatchOutcome",
    "TaskWorlds",
]  # fmt: skip

_OK = int(Status.OK)


# ----------------------------------------------------------------------------- vehicle randomisation


class VehicleScales(NamedTuple):
    """One episode's factors on the agents' true vehicle parameters, (A,) each; None: nominal."""

    mass: np.ndarray | None = None  # the body's mass, its inertia with it
    inertia: np.ndarray | None = None  # a further factor on the inertia alone
    motor_lag: np.ndarray | None = None  # every rotor's first-order time constant


def draw_vehicle_scales(rng: np.random.Generator, spreads: Mapping[str, float], n_agents: int) -> VehicleScales | None:
    """Factors from U(1 - s, 1 + s), (n_agents,) per parameter of `spreads` (`FollowerConfig.vehicle_spreads`:
    drawn in `VEHICLE_RANDOMIZABLE` order); None (nothing drawn) when `spreads` is empty."""
    if not spreads:
        return None
    return VehicleScales(**{name: rng.uniform(1.0 - s, 1.0 + s, n_agents) for name, s in spreads.items()})


class VehicleModel:
    """Writes episodes' `VehicleScales` into the worlds' MuJoCo models: the agents' bodies and rotors.

    The mass goes through `Physics.set_body_mass` (which scales the inertia with it, and makes
    the worlds' models their own, so that the simulator steps each world by its own model);
    the inertia factor and the rotors' time constant (the actuators' first-order filter,
    dynprm[0]) are then written per world: through `mujoco.batch.Batch.expand` for a batch,
    into the model that `set_body_mass` copied for a single world. The controller keeps the
    nominal vehicle.
    """

    def __init__(self, scene: Scene, agent_index: np.ndarray, spreads: Mapping[str, float]):
        model = scene.model
        self.bodies = scene.body_ids[agent_index]  # (A,)
        self.rotors = scene.act_ids[agent_index]  # (A, 4) actuator ids
        self.mass = model.body_mass[self.bodies].copy()  # (A,) kg, nominal
        self.motor_lag = model.actuator_dynprm[self.rotors, 0].copy()  # (A, 4) s, nominal
        spread, dt = spreads.get("motor_lag", 0.0), float(model.opt.timestep)
        if spread and not np.all(self.motor_lag * (1.0 - spread) > dt):
            allowed = 1.0 - dt / float(self.motor_lag.min())
            raise ConfigError(f"randomize['motor_lag']: got {spread}; a motor time constant of "
                              f"{float(self.motor_lag.min())} s must stay above the physics step {dt} s: "
                              f"allowed [0, {allowed:.3g})")

    def apply(self, physics: Physics, worlds: np.ndarray, scales: Sequence[VehicleScales]) -> None:
        """Give `worlds` (n,) the vehicles of `scales` (one per world) before they are reset."""
        n, A = len(worlds), self.bodies.size

        def stacked(name: str) -> np.ndarray | None:  # (n, A), or None where not drawn
            first = getattr(scales[0], name)
            return None if first is None else np.array([getattr(s, name) for s in scales]).reshape(n, A)

        mass, inertia, lag = stacked("mass"), stacked("inertia"), stacked("motor_lag")
        physics.set_body_mass(worlds, self.bodies, self.mass * mass if mass is not None else np.tile(self.mass, (n, 1)))
        if inertia is None and lag is None:
            return
        batch = getattr(physics, "batch", None)
        if batch is not None:  # per-world model fields of the batch
            w = np.asarray(worlds)
            if inertia is not None:
                batch.expand("body_inertia")[np.ix_(w, self.bodies)] *= inertia[..., None]
            if lag is not None:
                dynprm = batch.expand("actuator_dynprm")
                dynprm[w[:, None, None], self.rotors[None], 0] = self.motor_lag * lag[..., None]
            batch.set_const(ids=w)
        else:  # one world: the model set_body_mass copied for it
            model = physics.model
            if inertia is not None:
                model.body_inertia[self.bodies] *= inertia[-1][:, None]
            if lag is not None:
                model.actuator_dynprm[self.rotors, 0] = self.motor_lag * lag[-1][:, None]
            mujoco.mj_setConst(model, physics.data)


# ----------------------------------------------------------------------------- actions


def check_action(label: str, action: Any, shape: tuple[int, ...]) -> np.ndarray:
    """`action` as a new float64 array of `shape`, clipped to [-1, 1] as np.clip clips; ValueError
    naming `label` when it is not a finite float array of that shape."""
    try:
        a = np.array(action, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{label}: expected a float array of shape {shape} in [-1, 1], got {action!r}") from None
    if a.shape != shape:
        raise ValueError(f"{label}: expected shape {shape} (world frame, in [-1, 1]), got {a.shape}")
    if not _clip_finite(a.reshape(-1), 1.0):
        raise ValueError(f"{label}: must be finite (in [-1, 1]), got {a.tolist()}")
    return a


@njit
def _clip_finite(a, bound):
    """Clip a (n,) to [-bound, bound] in place, as np.clip; False (a untouched) if a value is not finite."""
    for i in range(a.size):
        if not np.isfinite(a[i]):
            return False
    for i in range(a.size):
        a[i] = min(max(a[i], -bound), bound)
    return True


# ----------------------------------------------------------------------------- the engine


def control_sim_config(task: FollowerConfig) -> SimConfig:
    """The task's `SimConfig` with the controller (= env step) at `task.control_hz`."""
    base = task.sim_base
    per_control = int(round(1.0 / (base.rates.autopilot_dt * task.control_hz)))
    rates = dataclasses.replace(base.rates, autopilot_per_control=per_control)
    return dataclasses.replace(base, rates=rates)


def env_controller(task: FollowerConfig) -> Any:
    """The outer loop `task.controller` names, at the task's control rate (its integrators and filters
    advance by the env step): the LQR (`task.lqr`), the LQR with integral action, or a lab controller."""
    dt = 1.0 / task.control_hz
    if task.controller == "integral":
        from controllers.integral import IntegralLQR

        return IntegralLQR(task.lqr, dt=dt)
    if task.controller in ("mellinger", "pid"):
        from controllers.crazyflie import CrazyfliePID, MellingerController

        return MellingerController(dt=dt) if task.controller == "mellinger" else CrazyfliePID(dt=dt)
    if task.controller == "indi":
        from controllers.indi import INDIController

        return INDIController(dt=dt)
    return FeedbackLinearisedLQR(task.lqr)


class BatchOutcome(NamedTuple):
    """What a step of W worlds gives per agent, from the true state at its end. A world that
    did not step reports zeros (status OK, not terminated)."""

    terminated: np.ndarray  # (W,) bool: the status is not OK
    status: np.ndarray  # (W,) int64 `downwash_core.status.Status` codes
    values: np.ndarray  # (len(INFO_KEYS) - 1, W, A) float64: INFO_KEYS' reward terms and errors (m, m/s; capped)
    reward: np.ndarray  # (W, A): the sum of the reward terms in REWARD_TERMS order
    row: Any  # the simulator's tick row (`Simulator.tick`), None when no world stepped


class TaskWorlds:
    """W worlds of a tracking task on one `Simulator`: per-world episodes, batched step, reward and observation.

    task: the task options (a `FollowerConfig`: rates, action bound, reward weights, components);
    scene: the compiled scene; agent_index: (A,) the vehicles the actions command, in scene
    order; episodes: (W,) the worlds' starting episodes (placeholders until the first reset);
    field, predictor: the simulator's; sim_options: further `Simulator` keywords.
    """

    cfg: Any  # the task's whole config (`FollowerConfig`, `SwarmConfig`); set by the task
    obs_shape: tuple[int, ...]  # one world's observation shape; set by the task
    obs_low: np.ndarray  # (D,) its bounds, likewise
    obs_high: np.ndarray

    def __init__(self, task: FollowerConfig, scene: Scene, agent_index: Sequence[int], episodes: Sequence[Any],
                 n_threads: int, *, field: Any, predictor: Any, **sim_options: Any):
        self.task = task
        self.W = W = len(episodes)
        self.scene = scene
        self.agent_index = np.asarray(agent_index, dtype=np.int64)
        self.episodes = list(episodes)
        self.sim_config = control_sim_config(task)
        self.bound = task.bound
        self.vehicles = VehicleModel(scene, self.agent_index, task.vehicle_spreads)  # before any allocation
        self.sim = Simulator(
            scene, self._reference(), [0] * W, config=self.sim_config, field=field, predictor=predictor,
            controller=env_controller(task), turbulence=task.turbulence, n_threads=n_threads, **sim_options,
        )
        self.last_action = np.zeros((W, self.agent_index.size, 3))  # m/s^2, as applied (clipped)
        # the simulator's (W, V, 3) command, the agents' rows written each step: a residual on every
        # LQR, or (acceleration mode) an override whose NaN rows keep the other vehicles' LQR
        self._override = task.action_mode == "acceleration"
        self._command = np.full((W, self.sim.V, 3), np.nan if self._override else 0.0)
        self._obs_cache: tuple[np.ndarray, Any] | None = None  # attitudes and reference of the last step
        self._constants = task_constants(task, self.bound)

    # ---------------------------------------------------------------- reset
    def reset_worlds(self, worlds: Sequence[int], episodes: Sequence[Any]) -> None:
        """Start the given worlds on the given episodes (their reference's state at the start)."""
        worlds = np.asarray(worlds, dtype=np.int64)
        for w, ep in zip(worlds, episodes):
            self.episodes[w] = ep
        self._episodes_changed()
        if len(episodes) and episodes[0].vehicle is not None:
            self.vehicles.apply(self.sim.physics, worlds, [ep.vehicle for ep in episodes])
        self.sim.reset(worlds, seeds=[ep.sim_seed for ep in episodes], reference=self._reference())
        self.last_action[worlds] = 0.0
        self._obs_cache = None

    # ---------------------------------------------------------------- step
    def advance(self, actions: np.ndarray, stepping: np.ndarray | None = None) -> BatchOutcome:
        """Advance the `stepping` worlds (default all) one controller period with (W, A, 3) actions (m/s^2).

        Worlds not stepping must be reset before their next step; their outcome is zero.
        """
        sim = self.sim
        if stepping is not None and not stepping.all():
            sim.active &= stepping
        self._command[:, self.agent_index] = actions
        row = None
        if sim.active.any():
            row = sim.tick(override=self._command) if self._override else sim.tick(residual=self._command)
        true = sim.true_states()
        ref = sim.reference(sim.t)
        W, A = actions.shape[:2]
        status, values, reward = np.empty(W, np.int64), np.empty((len(INFO_KEYS) - 1, W, A)), np.empty((W, A))
        task_kernel(true.pos, true.vel, ref.pos, ref.vel, self.agent_index, actions, self.last_action, sim.status,
                    self._constants, status, values[:6], reward, values[6], values[7])
        if stepping is None:
            self.last_action[:] = actions
        else:
            self.last_action[stepping] = actions[stepping]
            idle = ~stepping
            status[idle], values[:, idle], reward[idle] = _OK, 0.0, 0.0
        self._obs_cache = (true.rot, ref)
        return BatchOutcome(status != _OK, status, values, reward, row)

    # ---------------------------------------------------------------- observation
    def observe(self, fresh: bool = True) -> np.ndarray:
        """(W, *obs_shape) float32, the task's layout, clipped to its bounds (NaN -> 0).

        fresh=False reuses the attitudes and reference of the last step (no reset since).
        """
        sim = self.sim
        if fresh or self._obs_cache is None:
            rot, ref = sim.true_states().rot, sim.reference(sim.t)
        else:
            rot, ref = self._obs_cache
        out = np.empty((self.W, *self.obs_shape))
        self._observe_into(rot, ref, out)
        return out.astype(np.float32)

    # ---------------------------------------------------------------- methods to override
    def new_episode(self, rng: np.random.Generator) -> Any:
        """One episode drawn from `rng` (with `sim_seed` and `vehicle` fields), the same draws in every env class."""
        raise NotImplementedError

    def _reference(self) -> Any:
        """Every vehicle's reference over the worlds (W, V), for `self.episodes`."""
        raise NotImplementedError

    def _episodes_changed(self) -> None:
        """`self.episodes` changed (before the worlds are reset): update per-world components."""

    def _observe_into(self, rot: np.ndarray, ref: Any, out: np.ndarray) -> None:
        """Write the observation (W, *obs_shape) into `out`; rot (W, V, 3, 3) true attitudes, ref a RefSample."""
        raise NotImplementedError

    def camera_targets(self, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World w's (3,) m points for the camera: two to frame, and a marker (NaN: none)."""
        raise NotImplementedError
