"""The multi-rate stepping loop: physics, autopilot, field, motion capture, controller, predictor.

Rates (sim.params.Rates): physics 500 Hz; autopilot, downwash field and motion
capture on the 100 Hz autopilot grid; the LQR at 50 Hz; the predictor at 45 Hz,
evaluated at the first autopilot tick after each 1/45 s and held in between.

Everything is batched over worlds W and vehicles V. Each world draws its noise
(motion capture, turbulence) from its own generator, so a world's flight does not
depend on which other worlds share its batch: the batched loop equals a loop of
single flights bit for bit, which a test checks.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from controllers.autopilot import Autopilot
from controllers.lqr import DEFAULT_Q, DEFAULT_R, FeedbackLinearisedLQR, attitude_setpoint
from sim.estimation import MocapConfig, MocapKalmanFilter
from sim.field import DownwashField, pairwise_field
from sim.jit import njit
from sim.params import QUAD, RATES, QuadParams, Rates
from sim.physics import make_physics
from sim.predictor import Predictor, VehicleStates, ZeroPredictor
from sim.scene import Scene

__all__ = ["SimConfig", "Simulator", "quat_to_mat", "yaw_of", "STATUS_OK", "STATUS_DIVERGED", "STATUS_GROUND", "STATUS_VEHICLE"]

STATUS_OK, STATUS_DIVERGED, STATUS_GROUND, STATUS_VEHICLE = 0, 1, 2, 3


@dataclass(frozen=True)
class SimConfig:
    """Everything about a flight but its reference, field object, predictor and seed."""

    rates: Rates = field(default_factory=lambda: RATES)
    quad: QuadParams = field(default_factory=lambda: QUAD)
    mocap: MocapConfig = field(default_factory=MocapConfig)
    turbulence_intensity: float = 0.10  # -, turbulence std as a fraction of the local mean force
    turbulence_time_constant: float = 0.05  # s, Ornstein-Uhlenbeck correlation time
    lqr_q: tuple[float, ...] = tuple(np.diag(DEFAULT_Q))  # diagonal of Q
    lqr_r: tuple[float, ...] = tuple(np.diag(DEFAULT_R))  # diagonal of R
    max_tilt_deg: float = 35.0  # deg, tilt limit of feedback linearisation
    ground_clearance: float = 0.03  # m, a vehicle centre below this height has hit the ground
    collision_radius_xy: float = 0.26  # m, vehicles closer than this laterally ...
    collision_radius_z: float = 0.08  # m, ... and vertically (ellipsoid) have collided
    max_distance: float = 100.0  # m, beyond this from the origin the flight has diverged
    noise_block: int = 256  # autopilot ticks of noise drawn per generator call

    def __post_init__(self):
        if len(self.lqr_q) != 7 or len(self.lqr_r) != 4:
            raise ValueError(f"lqr_q/lqr_r: expected 7 and 4 diagonal entries, got {len(self.lqr_q)} and {len(self.lqr_r)}")
        if not 0.0 <= self.turbulence_intensity <= 1.0:
            raise ValueError(f"turbulence_intensity: allowed 0-1, got {self.turbulence_intensity}")
        if self.turbulence_time_constant <= 0:
            raise ValueError(f"turbulence_time_constant: must be > 0 s, got {self.turbulence_time_constant}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices (body to world)."""
    return _attitude_kernel(q.reshape(-1, 4).astype(float, copy=False))[0].reshape(q.shape[:-1] + (3, 3))


def yaw_of(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) body-to-world rotations -> (...,) heading (rad), Z-Y-X convention."""
    return np.arctan2(rot[..., 1, 0], rot[..., 0, 0])


@njit
def _attitude_kernel(q):
    """Flat (n, 4) quaternions -> rotation matrices (n, 3, 3) and headings (n,) rad."""
    n = q.shape[0]
    R = np.empty((n, 3, 3))
    yaw = np.empty(n)
    for i in range(n):
        w, x, y, z = q[i, 0], q[i, 1], q[i, 2], q[i, 3]
        R[i, 0, 0], R[i, 0, 1], R[i, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
        R[i, 1, 0], R[i, 1, 1], R[i, 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        R[i, 2, 0], R[i, 2, 1], R[i, 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
        yaw[i] = np.arctan2(R[i, 1, 0], R[i, 0, 0])
    return R, yaw


@njit
def _wake_force_kernel(mean, turb, xi, decay, diffusion, intensity):
    """Advance the Ornstein-Uhlenbeck turbulence (in place) and return the applied field.

    mean, turb, xi: flat (n, 3); applied = mean + intensity |mean| turb, so the
    turbulence is zero where the wake is and scales with the local mean force.
    """
    applied = np.empty_like(mean)
    for i in range(mean.shape[0]):
        mag = np.sqrt(mean[i, 0] ** 2 + mean[i, 1] ** 2 + mean[i, 2] ** 2)
        for k in range(3):
            turb[i, k] = decay * turb[i, k] + diffusion * xi[i, k]
            applied[i, k] = mean[i, k] + intensity * mag * turb[i, k]
    return applied


class Simulator:
    """W worlds of V vehicles flying the full stack; advance one controller tick at a time.

    reference: callable t (W,) -> RefSample with (W, V, ...) arrays (controllers.references.stack).
    field: any object with the DownwashField call signature.
    predictor: sim.predictor.Predictor, evaluated at 45 Hz and held.
    seeds: one int per world; a world's noise comes only from its own generator.
    field_enabled: (W,) bool, False for worlds flown without downwash.
    """

    def __init__(
        self,
        scene: Scene,
        reference: Callable,
        seeds: Sequence[int],
        *,
        config: SimConfig | None = None,
        field: Any | None = None,
        predictor: Predictor | None = None,
        field_enabled: np.ndarray | None = None,
        n_threads: int = 0,
    ):
        self.scene = scene
        self.cfg = cfg = config if config is not None else SimConfig()
        self.reference = reference
        self.field = field if field is not None else DownwashField()
        self.predictor = predictor if predictor is not None else ZeroPredictor()
        seeds = [int(s) for s in seeds]
        W, V = len(seeds), scene.n_vehicles
        if W < 1:
            raise ValueError("seeds: expected one seed per world, got none")
        self.W, self.V = W, V
        self.seeds = seeds
        self.field_enabled = np.ones(W, bool) if field_enabled is None else np.asarray(field_enabled, bool)
        if self.field_enabled.shape != (W,):
            raise ValueError(f"field_enabled: expected shape ({W},), got {self.field_enabled.shape}")

        r = cfg.rates
        self.physics = make_physics(scene.model, W, n_threads)
        self.lqr = FeedbackLinearisedLQR(np.diag(cfg.lqr_q), np.diag(cfg.lqr_r))
        self.autopilot = Autopilot(cfg.quad)
        self.kf = MocapKalmanFilter(r.autopilot_dt, cfg.mocap)
        self.max_tilt = np.deg2rad(cfg.max_tilt_deg)
        self.mass = cfg.quad.mass

        # index arrays, resolved once
        qa, va = scene.qpos_adr, scene.qvel_adr
        self._q_idx = qa[:, None] + np.arange(7)
        self._dq_idx = va[:, None] + np.arange(6)
        self._pos_idx = qa[:, None] + np.arange(3)
        self._quat_idx = qa[:, None] + 3 + np.arange(4)
        self._vel_idx = va[:, None] + np.arange(3)
        self._omega_idx = va[:, None] + 3 + np.arange(3)
        self._act_idx = scene.act_ids.ravel()
        self._body_ids = scene.body_ids
        self._ou_a = np.exp(-r.autopilot_dt / cfg.turbulence_time_constant)
        self._ou_b = np.sqrt(1.0 - self._ou_a**2)

        # per-world state beyond MuJoCo's
        self.t = np.zeros(W)  # s, time since each world's reset
        self.tick_index = np.zeros(W, np.int64)
        self.status = np.zeros(W, np.int64)
        self.message = [""] * W
        self.active = np.ones(W, bool)
        self.pos_est = np.zeros((W, V, 3))
        self.vel_est = np.zeros((W, V, 3))
        self.yaw_meas = np.zeros((W, V))
        self.mocap_pos = np.zeros((W, V, 3))
        self.turb = np.zeros((W, V, 3))
        self.f_hat = np.zeros((W, V, 3))
        self.next_prediction = np.zeros(W)
        self._rngs: list[np.random.Generator] = [None] * W  # type: ignore[list-item]
        self._noise = np.zeros((W, cfg.noise_block, V, 7))  # per tick: mocap xyz, yaw, turbulence xyz
        self._all_fields_on = bool(self.field_enabled.all())
        self._mass_believed = np.full((W, V), cfg.quad.mass)  # kg, the controller's model
        self._cursor = np.zeros(W, np.int64)
        self._world_index = np.arange(W)
        self.row: dict[str, np.ndarray] = {}
        self.reset(np.arange(W), seeds)

    # ------------------------------------------------------------------ state access
    def true_states(self) -> VehicleStates:
        qpos, qvel = self.physics.qpos, self.physics.qvel
        return VehicleStates(qpos[:, self._pos_idx], qvel[:, self._vel_idx], quat_to_mat(qpos[:, self._quat_idx]))

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
        self.status[worlds] = STATUS_OK
        for w in worlds:
            self.message[w] = ""
        self.active[worlds] = True
        self.pos_est[worlds] = ref.pos[worlds]
        self.vel_est[worlds] = ref.vel[worlds]
        self.turb[worlds] = 0.0
        self.f_hat[worlds] = 0.0
        self.next_prediction[worlds] = 0.0

    def _refill(self, w: int) -> None:
        self._noise[w] = self._rngs[w].standard_normal(self._noise.shape[1:])
        self._cursor[w] = 0

    def _draw(self) -> np.ndarray:
        """(W, V, 7) standard normals for this autopilot tick, from each world's own stream."""
        if self._cursor.max() >= self._noise.shape[1]:
            for w in np.flatnonzero(self._cursor >= self._noise.shape[1]):
                self._refill(w)
        out = self._noise[self._world_index, self._cursor]
        self._cursor += 1
        return out

    # ------------------------------------------------------------------ one controller tick
    def tick(self, residual: np.ndarray | None = None, override: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Advance every active world by one controller period; returns the tick's log row.

        residual: (W, V, 3) m/s^2 added to the LQR command (e.g. an RL compensation action).
        override: (W, V, 3) m/s^2 replacing the LQR acceleration where finite (NaN keeps LQR).
        The row describes the state at the start of the tick and the command applied during it.
        """
        cfg, r = self.cfg, self.cfg.rates
        ph, W, V = self.physics, self.W, self.V
        sigma_p, sigma_yaw = cfg.mocap.position_noise, cfg.mocap.yaw_noise
        row: dict[str, np.ndarray] = {}
        dt_active = r.autopilot_dt * self.active
        for sub in range(r.autopilot_per_control):
            q = ph.qpos[:, self._q_idx]  # (W, V, 7): position, quaternion
            dq = ph.qvel[:, self._dq_idx]  # (W, V, 6): linear velocity (world), angular (body)
            pos, vel = q[..., :3], dq[..., :3]
            rot, yaw = _attitude_kernel(q[..., 3:].reshape(-1, 4))
            rot = rot.reshape(W, V, 3, 3)

            # motion capture and Kalman update
            noise = self._draw()  # (W, V, 7)
            mocap = pos + sigma_p * noise[..., :3]
            self.yaw_meas = yaw.reshape(W, V) + sigma_yaw * noise[..., 3]
            self.pos_est, self.vel_est = self.kf.update(self.pos_est, self.vel_est, mocap)

            # predictor at 45 Hz, held
            due = self.t >= self.next_prediction - 1e-9
            if due.any():
                est = VehicleStates(self.pos_est, self.vel_est, rot)
                pred = self.predictor(est, VehicleStates(pos, vel, rot))
                self.f_hat = np.where(due[:, None, None], pred, self.f_hat)
                self.next_prediction = np.where(due, self.next_prediction + 1.0 / r.predictor_hz, self.next_prediction)

            # downwash field, applied as an external force until the next autopilot tick
            mean = pairwise_field(self.field, pos, vel, rot)
            if not self._all_fields_on:
                mean *= self.field_enabled[:, None, None]
            applied = _wake_force_kernel(
                mean.reshape(-1, 3), self.turb.reshape(-1, 3), noise[..., 4:].reshape(-1, 3),
                self._ou_a, self._ou_b, cfg.turbulence_intensity,
            ).reshape(W, V, 3)
            ph.xfrc_applied[:, self._body_ids, :3] = self.mass * applied

            if sub == 0:  # the LQR and feedback linearisation at 50 Hz
                ref = self.reference(self.t)
                cmd = self.lqr(
                    self.pos_est, self.vel_est, self.yaw_meas,
                    ref.pos, ref.vel, ref.acc, ref.yaw, ref.yaw_rate, self.f_hat,
                )
                cmd_acc, yaw_rate = cmd.acc, cmd.yaw_rate
                if residual is not None:
                    cmd_acc = cmd_acc + residual
                if override is not None:
                    cmd_acc = np.where(np.isfinite(override), override, cmd_acc)
                thrust, rot_des = attitude_setpoint(cmd_acc, self.yaw_meas + yaw_rate * r.control_dt, self.max_tilt)
                row = {
                    "t": self.t, "pos": pos, "vel": vel, "quat": q[..., 3:],
                    "pos_est": self.pos_est, "vel_est": self.vel_est, "yaw_est": self.yaw_meas,
                    "mocap_pos": mocap, "ref_pos": ref.pos, "ref_vel": ref.vel, "ref_acc": ref.acc,
                    "u_cmd": cmd_acc, "f_hat": self.f_hat, "field_mean": mean, "field_applied": applied,
                }

            rotors = self.autopilot(rot, dq[..., 3:], rot_des, yaw_rate, thrust, self._mass_believed)
            ph.ctrl[:, self._act_idx] = rotors.reshape(W, -1)
            diverged = ph.step(r.physics_per_autopilot, self.active)
            self.pos_est, self.vel_est = self.kf.predict(self.pos_est, self.vel_est, cmd_acc)
            self.t = self.t + dt_active
        self.tick_index += self.active
        self._check(diverged)
        self.row = row
        return row

    def _check(self, diverged: np.ndarray) -> None:
        """End worlds that diverged or collided; they keep their rows and stop stepping."""
        cfg = self.cfg
        status = _status_kernel(
            self.physics.qpos[:, self._pos_idx], self.physics.qvel, diverged, self.active,
            cfg.max_distance, cfg.ground_clearance, cfg.collision_radius_xy, cfg.collision_radius_z,
        )
        if status.any():
            what = {STATUS_DIVERGED: "diverged (NaN, runaway state or MuJoCo instability warning)",
                    STATUS_GROUND: "hit the ground", STATUS_VEHICLE: "vehicles collided"}
            for w in np.flatnonzero(status):
                self.status[w] = status[w]
                self.message[w] = f"world {w} (seed {self.seeds[w]}): {what[status[w]]} at t = {self.t[w]:.2f} s"
                self.active[w] = False


@njit
def _status_kernel(pos, qvel, diverged, active, max_distance, ground, radius_xy, radius_z):
    """(W,) status codes for active worlds that end now: diverged, ground or vehicle collision."""
    W, V = pos.shape[0], pos.shape[1]
    status = np.zeros(W, np.int64)
    for w in range(W):
        if not active[w]:
            continue
        bad = diverged[w]
        for j in range(qvel.shape[1]):
            bad = bad or not np.isfinite(qvel[w, j])
        for i in range(V):
            for k in range(3):
                bad = bad or not (abs(pos[w, i, k]) <= max_distance)  # NaN fails too
        if bad:
            status[w] = STATUS_DIVERGED
            continue
        for i in range(V):
            if pos[w, i, 2] < ground:
                status[w] = STATUS_GROUND
        if status[w]:
            continue
        for i in range(V):
            for j in range(i + 1, V):
                dx, dy, dz = pos[w, i, 0] - pos[w, j, 0], pos[w, i, 1] - pos[w, j, 1], pos[w, i, 2] - pos[w, j, 2]
                if (dx * dx + dy * dy) / radius_xy**2 + dz * dz / radius_z**2 < 1.0:
                    status[w] = STATUS_VEHICLE
    return status
