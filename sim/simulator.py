"""The multi-rate stepping loop: physics, autopilot, field, motion capture, controller, predictor.

Rates (core.params.Rates): physics 500 Hz; autopilot, downwash field and motion
capture on the 100 Hz autopilot grid; the LQR at 50 Hz; the predictor at 45 Hz,
evaluated at the first autopilot tick after each 1/45 s and held in between.

Everything is batched over worlds W and vehicles V. Each world draws its noise
(motion capture, turbulence) from its own generator, so a world's flight does not
depend on which other worlds share its batch: the batched loop equals a loop of
single flights bit for bit, which a test checks.

The loop is assembled from components, each injected and each with its config in
its own module: the outer-loop `controller` (`controllers.lqr.FeedbackLinearisedLQR`),
the `autopilot` (`controllers.autopilot.Autopilot`), the `turbulence`
(`sim.turbulence.OUTurbulence`), the downwash `field` (`sim.field.DownwashField` or
any object with its call signature) and the `predictor` (`sim.predictor`).

Each autopilot tick is two compiled passes over all worlds and vehicles around the
pluggable Python calls (predictor, field, reference): `_sense_kernel` (state, motion
capture, Kalman update) and `_actuate_kernel` (field and turbulence into
`xfrc_applied`, autopilot into `ctrl`, Kalman prediction, clocks); the 50 Hz command
is one more (the controller's `command_setpoint`). The math stays in its module
(`controllers.autopilot.rotor_thrusts`, `sim.estimation.kf_update` / `kf_predict`,
`sim.turbulence.OUTurbulence`); tests check the passes against the readable components.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from controllers.autopilot import Autopilot, rotor_thrusts
from controllers.lqr import ControllerState, FeedbackLinearisedLQR, Setpoint
from core.errors import ConfigError
from core.geometry import perturb_quat_into, quat_to_mat_fast, quat_to_rot
from core.jit import njit
from core.params import QUAD, RATES, QuadParams, Rates
from core.state import VehicleStates
from core.status import Status
from sim.estimation import MocapConfig, MocapKalmanFilter, kf_predict, kf_update
from sim.field import DownwashField, check_field, pairwise_field
from sim.physics import make_physics
from sim.predictor import Predictor, ZeroPredictor
from sim.scene import Scene
from sim.turbulence import OUTurbulence

__all__ = ["SimConfig", "Simulator"]

# Status codes as plain ints for the compiled status pass (numba freezes globals).
_OK, _DIVERGED, _GROUND, _VEHICLE = (int(s) for s in (Status.OK, Status.DIVERGED, Status.GROUND, Status.VEHICLE))


@dataclass(frozen=True)
class SimConfig:
    """The vehicle, the rates, the motion capture and the failure checks of a flight.

    The controller, autopilot, turbulence, field and predictor are components of the
    `Simulator`, each with its own settings.
    """

    rates: Rates = field(default_factory=lambda: RATES)
    quad: QuadParams = field(default_factory=lambda: QUAD)
    mocap: MocapConfig = field(default_factory=MocapConfig)
    ground_clearance: float = 0.03  # m, a vehicle centre below this height has hit the ground
    collision_radius_xy: float = 0.26  # m, vehicles closer than this laterally ...
    collision_radius_z: float = 0.08  # m, ... and vertically (ellipsoid) have collided
    max_distance: float = 100.0  # m, beyond this from the origin the flight has diverged
    noise_block: int = 256  # autopilot ticks of noise drawn per generator call

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class _Sensed(NamedTuple):
    """What one autopilot tick senses and applies, batched (W, V, ...); the first tick of a
    controller period writes into fresh arrays (they become the log row), later ones reuse."""

    kin: np.ndarray  # (5, W, V, 3): true position m, true velocity m/s, mocap position m, KF position m, KF velocity m/s
    quat: np.ndarray  # (W, V, 4) true attitude (w, x, y, z)
    rot: np.ndarray  # (W, V, 3, 3) true attitude, body to world
    quat_est: np.ndarray  # (W, V, 4) motion-capture attitude
    rot_est: np.ndarray  # (W, V, 3, 3) motion-capture attitude, body to world
    yaw: np.ndarray  # (W, V) rad, motion-capture heading
    applied: np.ndarray  # (W, V, 3) m/s^2, the field applied (mean + turbulence)

    @classmethod
    def empty(cls, W: int, V: int) -> "_Sensed":
        return cls(np.empty((5, W, V, 3)), np.empty((W, V, 4)), np.empty((W, V, 3, 3)), np.empty((W, V, 4)),
                   np.empty((W, V, 3, 3)), np.empty((W, V)), np.empty((W, V, 3)))


# columns of Simulator._layout (V, 7), the per-vehicle address table of the kernels
_QPOS, _QVEL, _BODY, _ACT = 0, 1, 2, 3  # free joint in qpos, in qvel, body id, 4 actuator ids

# The per-autopilot-tick work is two compiled passes over all worlds and vehicles, one
# before the (pluggable, Python) predictor and field calls and one after: as NumPy on
# these small arrays, per-call overhead cost several times MuJoCo's own step.


@njit
def _sense_kernel(
    qpos, qvel, layout, noise, cursor, sigma_p, sigma_att, gain_p, gain_v,
    pos_est, vel_est, t, next_prediction, due, kin, quat, rot, quat_est, rot_est, yaw_meas,
):
    """Read the true state, take the motion-capture sample and apply the Kalman update.

    The arguments before `kin` are the simulator's persistent buffers and constants,
    bound once (`Simulator._sense_args`); the last six are fresh each tick.

    qpos (W, nq), qvel (W, nv): live MuJoCo state; layout (V, 7): see Simulator._layout.
    noise (W, block, V, 9) standard normals read at each world's `cursor`: [0:3] mocap
    position, [3:6] mocap attitude (body-frame rotation vector), [6:9] turbulence.
    pos_est, vel_est (W, V, 3): the Kalman prior, updated in place to the posterior.
    Writes kin (5, W, V, 3) [true position m, true velocity m/s (world), mocap position m,
    posterior position m, posterior velocity m/s], quat (W, V, 4) (w, x, y, z) and
    rot (W, V, 3, 3) body to world (true), quat_est and rot_est (the mocap attitude,
    `core.geometry.perturb_quat` of the truth by sigma_att * noise), yaw_meas (W, V) rad
    (its heading), and due (W,) bool: the predictor is due (t >= next_prediction, 1 ns
    slack). Returns how many worlds are due.
    """
    W, V = pos_est.shape[0], pos_est.shape[1]
    n_due = 0
    for w in range(W):
        c = cursor[w]
        for i in range(V):
            a, b = layout[i, _QPOS], layout[i, _QVEL]
            for k in range(4):
                quat[w, i, k] = qpos[w, a + 3 + k]
            quat_to_rot(qpos[w, a + 3], qpos[w, a + 4], qpos[w, a + 5], qpos[w, a + 6], rot[w, i])
            q = quat_est[w, i]
            perturb_quat_into(
                quat[w, i, 0], quat[w, i, 1], quat[w, i, 2], quat[w, i, 3],
                sigma_att * noise[w, c, i, 3], sigma_att * noise[w, c, i, 4], sigma_att * noise[w, c, i, 5], q,
            )
            yaw_meas[w, i] = quat_to_rot(q[0], q[1], q[2], q[3], rot_est[w, i])
            for k in range(3):
                p = qpos[w, a + k]
                m = p + sigma_p * noise[w, c, i, k]
                kin[0, w, i, k] = p
                kin[1, w, i, k] = qvel[w, b + k]
                kin[2, w, i, k] = m
                pe, ve = kf_update(pos_est[w, i, k], vel_est[w, i, k], m, gain_p, gain_v)
                pos_est[w, i, k] = kin[3, w, i, k] = pe
                vel_est[w, i, k] = kin[4, w, i, k] = ve
        due[w] = t[w] >= next_prediction[w] - 1e-9
        n_due += due[w]
    return n_due


@njit
def _hold_kernel(f_hat, pred, due, next_prediction, period):
    """Take the new prediction (W, V, 3) m/s^2 where due (W,) and schedule the next (s), in place."""
    for w in range(f_hat.shape[0]):
        if due[w]:
            f_hat[w] = pred[w]
            next_prediction[w] = next_prediction[w] + period


@njit
def _actuate_kernel(
    field_on, noise, cursor, turb, decay, diffusion, intensity, mass, xfrc, layout,
    qvel, rot_des, yaw_rate_des, thrust_acc, mass_believed, ap_gain, max_thrust, ctrl,
    pos_est, vel_est, dt, t, active,
    mean, applied, rot, acc_cmd,
):
    """Apply the field, run the autopilot and the Kalman prediction, advance the clocks.

    mean (W, V, 3) m/s^2: mean field, zeroed in place where field_on (W,) is False.
    turb (W, V, 3): Ornstein-Uhlenbeck state, advanced in place with noise[w, cursor[w], :, 6:9]:
    turb = decay turb + diffusion xi; applied = mean + intensity |mean| turb (written to
    applied (W, V, 3) m/s^2, so the turbulence is zero outside the wake and scales with it),
    and mass * applied (N, world frame) into xfrc (W, nbody, 6) at each vehicle's body.
    Autopilot (controllers.autopilot.rotor_thrusts) on rot (W, V, 3, 3), body rates from
    qvel (W, nv), set-points rot_des (W, V, 3, 3), yaw_rate_des (W, V) rad/s,
    thrust_acc (W, V) m/s^2, mass_believed (W, V) kg -> rotor thrusts (N) into ctrl (W, nu).
    Addresses from layout (V, 7), see Simulator._layout. Kalman prediction of pos_est, vel_est (W, V, 3) over dt (s) with
    acc_cmd (W, V, 3) m/s^2, in place. Then t (W,) s advances by dt where active and
    every cursor by one.

    The arguments before `mean` are the simulator's persistent buffers and constants,
    bound once (`Simulator._actuate_args`); the last four are fresh each tick.
    """
    W, V = mean.shape[0], mean.shape[1]
    x = np.empty(14)
    out = np.empty(4)
    for w in range(W):
        c = cursor[w]
        for i in range(V):
            if not field_on[w]:
                for k in range(3):
                    mean[w, i, k] *= 0.0
            mag = np.sqrt(mean[w, i, 0] ** 2 + mean[w, i, 1] ** 2 + mean[w, i, 2] ** 2)
            for k in range(3):
                turb[w, i, k] = decay * turb[w, i, k] + diffusion * noise[w, c, i, 6 + k]
                applied[w, i, k] = mean[w, i, k] + intensity * mag * turb[w, i, k]
                xfrc[w, layout[i, _BODY], k] = mass * applied[w, i, k]
            b = layout[i, _QVEL] + 3
            rotor_thrusts(
                rot[w, i], qvel[w, b:b + 3], rot_des[w, i], yaw_rate_des[w, i], thrust_acc[w, i],
                mass_believed[w, i], ap_gain, max_thrust, x, out,
            )
            for k in range(4):
                ctrl[w, layout[i, _ACT + k]] = out[k]
            for k in range(3):
                pos_est[w, i, k], vel_est[w, i, k] = kf_predict(pos_est[w, i, k], vel_est[w, i, k], acc_cmd[w, i, k], dt)
        if active[w]:
            t[w] = t[w] + dt
        cursor[w] += 1


class Simulator:
    """W worlds of V vehicles flying the full stack; advance one controller tick at a time.

    reference: callable t (W,) -> RefSample with (W, V, ...) arrays (`trajectories.stack`).
    seeds: one int per world; a world's noise comes only from its own generator.
    config: `SimConfig` (vehicle, rates, motion capture, failure checks).
    Components (each defaults to the paper's):
      controller: the outer loop, `FeedbackLinearisedLQR(LQRConfig(...))` or any object
        with its `command_setpoint(state, ref, f_hat, out, residual, override, lookahead)`;
      autopilot: `Autopilot(quad, ...)` (its `gain` and `max_thrust` run compiled);
      turbulence: `OUTurbulence(intensity, time_constant)`;
      field: any object with the `DownwashField` call signature;
      predictor: `sim.predictor.Predictor`, evaluated at 45 Hz and held.
    field_enabled: (W,) bool, False for worlds flown without downwash.
    """

    def __init__(
        self,
        scene: Scene,
        reference: Callable,
        seeds: Sequence[int],
        *,
        config: SimConfig | None = None,
        controller: Any | None = None,
        autopilot: Autopilot | None = None,
        turbulence: OUTurbulence | None = None,
        field: Any | None = None,
        predictor: Predictor | None = None,
        field_enabled: np.ndarray | None = None,
        n_threads: int = 0,
    ):
        self.scene = scene
        self.cfg = cfg = config if config is not None else SimConfig()
        self.reference = reference
        self.controller = controller if controller is not None else FeedbackLinearisedLQR()
        self.autopilot = autopilot if autopilot is not None else Autopilot(cfg.quad)
        self.turbulence = turbulence if turbulence is not None else OUTurbulence()
        self.field = field if field is not None else DownwashField()
        self.predictor = predictor if predictor is not None else ZeroPredictor()
        seeds = [int(s) for s in seeds]
        W, V = len(seeds), scene.n_vehicles
        if W < 1:
            raise ConfigError("seeds: expected one seed per world, got none")
        self.W, self.V = W, V
        self.seeds = seeds
        self.field_enabled = np.ones(W, bool) if field_enabled is None else np.asarray(field_enabled, bool)
        if self.field_enabled.shape != (W,):
            raise ConfigError(f"field_enabled: expected shape ({W},), got {self.field_enabled.shape}")

        r = cfg.rates
        self.physics = make_physics(scene.model, W, n_threads)
        self.kf = MocapKalmanFilter(r.autopilot_dt, cfg.mocap)
        self.mass = cfg.quad.mass

        # index arrays, resolved once
        qa, va = scene.qpos_adr, scene.qvel_adr
        self._pos_idx = qa[:, None] + np.arange(3)
        self._quat_idx = qa[:, None] + 3 + np.arange(4)
        self._vel_idx = va[:, None] + np.arange(3)
        # per vehicle: qpos address, qvel address, body id, 4 actuator ids (columns _QPOS.._ACT)
        self._layout = np.concatenate(
            [np.stack([qa, va, scene.body_ids], axis=1), scene.act_ids], axis=1
        ).astype(np.int64)
        # scalars of the hot loop, as Python floats, looked up once
        self._ou_a, self._ou_b = self.turbulence.coefficients(r.autopilot_dt)
        self._prediction_period = 1.0 / r.predictor_hz  # s
        self._sigma_p, self._sigma_att = float(cfg.mocap.position_noise), float(cfg.mocap.attitude_noise)
        self._kf_gain_p, self._kf_gain_v = (float(g) for g in self.kf.gain)
        self._max_thrust = float(self.autopilot.max_thrust)
        self._turbulence_intensity = float(self.turbulence.intensity)

        # per-world state beyond MuJoCo's; pos_est, vel_est, turb, f_hat, t, tick_index and
        # next_prediction are updated in place, `sensed` replaced each autopilot tick (copy
        # its arrays to keep a value; the rows tick() returns are fresh already)
        self.t = np.zeros(W)  # s, time since each world's reset
        self.tick_index = np.zeros(W, np.int64)
        self.status = np.zeros(W, np.int64)
        self.message = [""] * W
        self.active = np.ones(W, bool)
        self.pos_est = np.zeros((W, V, 3))  # m, Kalman estimate (prior for the next sample)
        self.vel_est = np.zeros((W, V, 3))  # m/s
        self.sensed = _Sensed.empty(W, V)  # the latest autopilot tick's measurements and truth
        self.turb = np.zeros((W, V, 3))  # -, Ornstein-Uhlenbeck turbulence state
        self.f_hat = np.zeros((W, V, 3))  # m/s^2, held prediction
        self.next_prediction = np.zeros(W)  # s
        self._rngs: list[np.random.Generator] = [None] * W  # type: ignore[list-item]
        self._noise = np.zeros((W, cfg.noise_block, V, 9))  # per tick: mocap position, attitude, turbulence
        self._mass_believed = np.full((W, V), cfg.quad.mass)  # kg, the controller's model
        self._cursor = np.zeros(W, np.int64)
        self._cursor_max = 0  # max(self._cursor), kept as a Python int (no reduction per tick)
        self._due = np.zeros(W, bool)
        self._reused = _Sensed.empty(W, V)  # buffers of the second and later autopilot ticks
        self._rot_des = np.empty((W, V, 3, 3))  # body to world, set by the 50 Hz control
        self._yaw_rate_des = np.empty((W, V))  # rad/s
        self._thrust_acc = np.empty((W, V))  # m/s^2
        self._status_new = np.zeros(W, np.int64)
        self.row: dict[str, np.ndarray] = {}
        # The compiled passes' persistent arguments, bound once: every array here is only
        # ever updated in place, so each tick passes just the arrays that are fresh.
        self._sense_args = (
            self.physics.qpos, self.physics.qvel, self._layout, self._noise, self._cursor,
            self._sigma_p, self._sigma_att, self._kf_gain_p, self._kf_gain_v,
            self.pos_est, self.vel_est, self.t, self.next_prediction, self._due,
        )
        self._actuate_args = (
            self.field_enabled, self._noise, self._cursor, self.turb,
            self._ou_a, self._ou_b, self._turbulence_intensity, self.mass, self.physics.xfrc_applied, self._layout,
            self.physics.qvel, self._rot_des, self._yaw_rate_des, self._thrust_acc, self._mass_believed,
            self.autopilot.gain, self._max_thrust, self.physics.ctrl,
            self.pos_est, self.vel_est, cfg.rates.autopilot_dt, self.t, self.active,
        )
        self.reset(np.arange(W), seeds)
        if field is not None:  # once, before any step: a bad field is named, not found mid-batch
            start = self.true_states()
            check_field(field, start.pos, start.vel, start.rot, finite=False)

    # ------------------------------------------------------------------ state access
    def true_states(self) -> VehicleStates:
        qpos, qvel = self.physics.qpos, self.physics.qvel
        return VehicleStates(qpos[:, self._pos_idx], qvel[:, self._vel_idx], quat_to_mat_fast(qpos[:, self._quat_idx]))

    # ------------------------------------------------------------------ reset
    def reset(self, worlds: np.ndarray, seeds: Sequence[int] | None = None, reference: Callable | None = None) -> None:
        """Start the given worlds afresh at their reference's t = 0 state, hovering level."""
        worlds = np.asarray(worlds, dtype=np.int64)
        if reference is not None:
            self.reference = reference
        if seeds is not None:
            for w, s in zip(worlds, seeds):
                self.seeds[w] = int(s)
        ph = self.physics
        ph.reset(worlds)
        ref = self.reference(np.zeros(self.W))
        qpos, qvel = ph.qpos, ph.qvel
        for w in worlds:  # per-world python is fine here: resets are rare
            qpos[w, self._pos_idx] = ref.pos[w]
            half = 0.5 * ref.yaw[w]
            qpos[w, self._quat_idx] = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], axis=-1)
            qvel[w] = 0.0
            qvel[w, self._vel_idx] = ref.vel[w]
            ph.act[w] = self.cfg.quad.hover_rotor_thrust
            ph.ctrl[w] = self.cfg.quad.hover_rotor_thrust
            ph.xfrc_applied[w] = 0.0
            self._rngs[w] = np.random.default_rng(self.seeds[w])
            self._refill(w)
        self.t[worlds] = 0.0
        self.tick_index[worlds] = 0
        self.status[worlds] = Status.OK
        for w in worlds:
            self.message[w] = ""
        self.active[worlds] = True
        self.pos_est[worlds] = ref.pos[worlds]
        self.vel_est[worlds] = ref.vel[worlds]
        self.turb[worlds] = 0.0
        self.f_hat[worlds] = 0.0
        self.next_prediction[worlds] = 0.0
        self._cursor_max = int(self._cursor.max())

    def _refill(self, w: int) -> None:
        self._noise[w] = self._rngs[w].standard_normal(self._noise.shape[1:])
        self._cursor[w] = 0

    def _refill_used(self) -> None:
        """Refill the noise block of every world whose draws are used up (each from its own stream)."""
        for w in np.flatnonzero(self._cursor >= self._noise.shape[1]):
            self._refill(w)
        self._cursor_max = int(self._cursor.max())

    # ------------------------------------------------------------------ one controller tick
    def tick(self, residual: np.ndarray | None = None, override: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Advance every active world by one controller period; returns the tick's log row.

        residual: (W, V, 3) m/s^2 added to the LQR command (e.g. an RL compensation action).
        override: (W, V, 3) m/s^2 replacing the LQR acceleration where finite (NaN keeps LQR).
        The row describes the state at the start of the tick and the command applied during it;
        its arrays are fresh each tick and never written to afterwards.
        """
        r = self.cfg.rates
        ph, W, V = self.physics, self.W, self.V
        if residual is not None:
            residual = _as_batch(residual, (W, V, 3))
        if override is not None:
            override = _as_batch(override, (W, V, 3))
        row: dict[str, np.ndarray] = {}
        t_start = self.t.copy()
        for sub in range(r.autopilot_per_control):
            first = sub == 0
            if self._cursor_max >= self._noise.shape[1]:
                self._refill_used()
            sensed = _Sensed.empty(W, V) if first else self._reused  # the first tick's arrays become the row
            kin, quat, rot, quat_est, rot_est, yaw, applied = sensed
            pos, vel, mocap, pos_est, vel_est = kin
            # motion capture and Kalman update
            n_due = _sense_kernel(*self._sense_args, kin, quat, rot, quat_est, rot_est, yaw)
            self.sensed = sensed

            # predictor at 45 Hz, held: it sees what a lab measures, the truth only for oracles
            if n_due:
                pred = self.predictor(VehicleStates(pos_est, vel_est, rot_est), VehicleStates(pos, vel, rot))
                _hold_kernel(self.f_hat, _as_batch(pred, (W, V, 3)), self._due, self.next_prediction, self._prediction_period)

            # downwash field, applied as an external force until the next autopilot tick
            mean = pairwise_field(self.field, pos, vel, rot)

            if first:  # the LQR and feedback linearisation at 50 Hz
                ref = self.reference(self.t)
                cmd_acc = np.empty((W, V, 3))  # m/s^2, the command applied (row u_cmd)
                self.controller.command_setpoint(
                    ControllerState(pos_est, vel_est, yaw), ref, self.f_hat,
                    Setpoint(cmd_acc, self._yaw_rate_des, self._thrust_acc, self._rot_des),
                    residual, override, r.control_dt,
                )
                row = {
                    "t": t_start, "pos": pos, "vel": vel, "quat": quat,
                    "pos_est": pos_est, "vel_est": vel_est, "quat_est": quat_est, "yaw_est": yaw,
                    "mocap_pos": mocap, "ref_pos": ref.pos, "ref_vel": ref.vel, "ref_acc": ref.acc,
                    "u_cmd": cmd_acc, "f_hat": self.f_hat.copy(), "field_mean": mean, "field_applied": applied,
                }

            # field and turbulence into xfrc_applied, autopilot into ctrl, Kalman prediction, clocks
            _actuate_kernel(*self._actuate_args, mean, applied, rot, cmd_acc)
            self._cursor_max += 1
            diverged = ph.step(r.physics_per_autopilot, self.active)
        self._check(diverged)
        self.row = row
        return row

    def _check(self, diverged: np.ndarray) -> None:
        """Count the tick for active worlds; end those that diverged or collided (they keep their rows)."""
        cfg = self.cfg
        status = self._status_new
        n_ended = _status_kernel(
            self.physics.qpos, self._layout, self.physics.qvel, diverged, self.active, self.tick_index,
            cfg.max_distance, cfg.ground_clearance, cfg.collision_radius_xy, cfg.collision_radius_z, status,
        )
        if n_ended:
            for w in np.flatnonzero(status):
                self.status[w] = status[w]
                what = Status(int(status[w])).description
                self.message[w] = f"world {w} (seed {self.seeds[w]}): {what} at t = {self.t[w]:.2f} s"
                self.active[w] = False


def _as_batch(x: Any, shape: tuple[int, ...]) -> np.ndarray:
    """x as a float64 array of exactly `shape` (broadcast, read-only, only when it differs)."""
    x = np.asarray(x, dtype=np.float64)
    return x if x.shape == shape else np.broadcast_to(x, shape)


@njit
def _status_kernel(qpos, layout, qvel, diverged, active, tick_index, max_distance, ground, radius_xy, radius_z, status):
    """Count the tick of active worlds (tick_index (W,), in place) and write into status (W,)
    the `Status` codes of those that end now (OK elsewhere).

    qpos (W, nq): vehicle positions (m) at qpos[w, layout[i, _QPOS] + (0, 1, 2)];
    diverged (W,) bool from the physics. Returns how many worlds end.
    """
    W, V = qpos.shape[0], layout.shape[0]
    q_adr = layout[:, _QPOS]
    n_ended = 0
    for w in range(W):
        status[w] = _OK
        if not active[w]:
            continue
        tick_index[w] += 1
        bad = diverged[w]
        for j in range(qvel.shape[1]):
            bad = bad or not np.isfinite(qvel[w, j])
        for i in range(V):
            for k in range(3):
                bad = bad or not (abs(qpos[w, q_adr[i] + k]) <= max_distance)  # NaN fails too
        if bad:
            status[w] = _DIVERGED
        else:
            for i in range(V):
                if qpos[w, q_adr[i] + 2] < ground:
                    status[w] = _GROUND
        if status[w] == _OK:
            for i in range(V):
                for j in range(i + 1, V):
                    a, b = q_adr[i], q_adr[j]
                    dx, dy, dz = qpos[w, a] - qpos[w, b], qpos[w, a + 1] - qpos[w, b + 1], qpos[w, a + 2] - qpos[w, b + 2]
                    if (dx * dx + dy * dy) / radius_xy**2 + dz * dz / radius_z**2 < 1.0:
                        status[w] = _VEHICLE
        n_ended += status[w] != _OK
    return n_ended
