"""The compiled passes of one autopilot tick, shared by both paths of the loop.

The readable path (`sim.simulator.Simulator`, `fast=False` or a component without a
compiled form) runs each autopilot tick as these passes around the pluggable Python
calls (predictor, field, reference, controller); the fused kernel (`sim.fused`) calls
the very same passes inside one compiled call. As NumPy on these small arrays,
per-call overhead cost several times MuJoCo's own step.

- `sense_kernel`: the true state, the sensor's sample (`sim.sensors`), the Kalman update;
  `sense_law_kernel` the same with a sensor's compiled law (`sim.sensor_contract`) for the sample;
- `wind_sense_kernel`, `wind_advance_kernel`, `wind_force_kernel`: the air velocity
  at each vehicle and its drag, the next gust state, the drag into `xfrc_applied`;
- `hold_kernel`: the 45 Hz prediction, held;
- `actuate_kernel`: field and turbulence into `xfrc_applied`, the autopilot into
  `ctrl`, the Kalman prediction, the clocks;
- `status_kernel`: after a controller tick, which worlds diverged or collided;
- `true_states_kernel`: the true states, for `Simulator.true_states`.

The math stays in its module (`controllers.autopilot.rotor_thrusts`, `sim.sensors`,
`sim.estimation.kf_update` / `kf_predict`, `sim.turbulence.OUTurbulence`, `sim.wind`);
tests check the passes against the readable components. Every pass loops over the
flattened (W, V) batch and reads the vehicles' MuJoCo addresses from the simulator's
per-vehicle table `layout` (V, 7), whose columns are `_QPOS`, `_QVEL`, `_BODY`, `_ACT`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from controllers.autopilot import rotor_thrusts
from downwash_core.geometry import perturb_quat_into, quat_to_rot
from downwash_core.jit import njit, njit_inline
from downwash_core.status import Status
from sim.estimation import kf_predict, kf_update
from sim.fused_abi import call_sensor
from sim.wind import coefficients_into, drag_gain_speed, gust_into, gust_step_into

# Status codes as plain ints for the compiled status pass (numba freezes globals).
_OK, _DIVERGED, _GROUND, _VEHICLE = (int(s) for s in (Status.OK, Status.DIVERGED, Status.GROUND, Status.VEHICLE))

# columns of Simulator._layout (V, 7), the per-vehicle address table of the kernels
_QPOS, _QVEL, _BODY, _ACT = 0, 1, 2, 3  # free joint in qpos, in qvel, body id, 4 actuator ids


class Sensed(NamedTuple):
    """What one autopilot tick senses and applies, batched (W, V, ...): the outputs of `sense_kernel`
    and `actuate_kernel`. On the readable path the first tick of a controller period writes into
    fresh arrays (they become the log row), later ones reuse."""

    kin: np.ndarray  # (5, W, V, 3): true position m, true velocity m/s, mocap position m, KF position, KF velocity m/s
    quat: np.ndarray  # (W, V, 4) true attitude (w, x, y, z)
    rot: np.ndarray  # (W, V, 3, 3) true attitude, body to world
    quat_est: np.ndarray  # (W, V, 4) motion-capture attitude
    rot_est: np.ndarray  # (W, V, 3, 3) motion-capture attitude, body to world
    yaw: np.ndarray  # (W, V) rad, motion-capture heading
    applied: np.ndarray  # (W, V, 3) m/s^2, the field applied (mean + turbulence)

    @classmethod
    def empty(cls, W: int, V: int) -> "Sensed":
        return cls(np.empty((5, W, V, 3)), np.empty((W, V, 4)), np.empty((W, V, 3, 3)), np.empty((W, V, 4)),
                   np.empty((W, V, 3, 3)), np.empty((W, V)), np.empty((W, V, 3)))


@njit_inline
def read_truth(qpos, qvel, layout, w, i, kin, quat, rot):
    """Vehicle i of world w's true state from MuJoCo's: position and velocity into kin[0], kin[1]
    (W, V, 3 each), attitude into quat (w, x, y, z) and rot (body to world): both sensing passes' first step."""
    a, b = layout[i, _QPOS], layout[i, _QVEL]
    for k in range(4):
        quat[w, i, k] = qpos[w, a + 3 + k]
    quat_to_rot(qpos[w, a + 3], qpos[w, a + 4], qpos[w, a + 5], qpos[w, a + 6], rot[w, i])
    for k in range(3):
        kin[0, w, i, k] = qpos[w, a + k]
        kin[1, w, i, k] = qvel[w, b + k]


@njit
def sense_kernel(
    qpos, qvel, layout, noise, cursor, sigma_p, sigma_att, offset, gain_p, gain_v,
    pos_est, vel_est, t, next_prediction, due, kin, quat, rot, quat_est, rot_est, yaw_meas,
):
    """Read the true state, take the sensor's sample and apply the Kalman update.

    The arguments before `kin` are the simulator's persistent buffers and constants,
    bound once (`Simulator._sense_args`); the last six are fresh each tick.

    qpos (W, nq), qvel (W, nv): live MuJoCo state; layout (V, 7): see Simulator._layout.
    noise (W, block, V, 9) standard normals read at each world's `cursor`: [0:3] mocap
    position, [3:6] mocap attitude (body-frame rotation vector), [6:9] turbulence.
    sigma_p (m), sigma_att (rad): the sensor's `compiled()` stds; offset (W, V, 3) m: its
    per-episode position offsets (`sim.sensors`, whose `measure` is this law, in this order).
    pos_est, vel_est (W, V, 3): the Kalman prior, updated in place to the posterior.
    Writes kin (5, W, V, 3) [true position m, true velocity m/s (world), mocap position m,
    posterior position m, posterior velocity m/s], quat (W, V, 4) (w, x, y, z) and
    rot (W, V, 3, 3) body to world (true), quat_est and rot_est (the mocap attitude,
    `downwash_core.geometry.perturb_quat` of the truth by sigma_att * noise), yaw_meas (W, V) rad
    (its heading), and due (W,) bool: the predictor is due (t >= next_prediction, 1 ns
    slack). Returns how many worlds are due.
    """
    W, V = pos_est.shape[0], pos_est.shape[1]
    n_due = 0
    for w in range(W):
        c = cursor[w]
        for i in range(V):
            read_truth(qpos, qvel, layout, w, i, kin, quat, rot)
            q = quat_est[w, i]
            perturb_quat_into(
                quat[w, i, 0], quat[w, i, 1], quat[w, i, 2], quat[w, i, 3],
                sigma_att * noise[w, c, i, 3], sigma_att * noise[w, c, i, 4], sigma_att * noise[w, c, i, 5], q,
            )
            yaw_meas[w, i] = quat_to_rot(q[0], q[1], q[2], q[3], rot_est[w, i])
            for k in range(3):
                m = kin[0, w, i, k] + sigma_p * noise[w, c, i, k] + offset[w, i, k]  # (p + white) + offset: 0 adds nothing
                kin[2, w, i, k] = m
                pe, ve = kf_update(pos_est[w, i, k], vel_est[w, i, k], m, gain_p, gain_v)
                pos_est[w, i, k] = kin[3, w, i, k] = pe
                vel_est[w, i, k] = kin[4, w, i, k] = ve
        due[w] = t[w] >= next_prediction[w] - 1e-9
        n_due += due[w]
    return n_due


@njit
def sense_law_kernel(
    qpos, qvel, layout, noise, cursor, law_fn, law_params, law_state, offset, gain_p, gain_v,
    pos_est, vel_est, t, next_prediction, due, kin, quat, rot, quat_est, rot_est, yaw_meas,
):
    """`sense_kernel` with the sample taken by a sensor's compiled law (`sim.sensor_contract`).

    law_fn: the address of its C function of `SENSOR_SIGNATURE`; law_params, law_state: the addresses
    of its constants and of these worlds' first row of its state (W, V, S). The law maps the true
    positions kin[0] and attitudes quat, the sample's normals (columns 0:6 of each world's noise
    block at its cursor, gathered (W, V, 6)) and offset (W, V, 3) m into the measurement kin[2] and
    quat_est; the rest is `sense_kernel`'s, in its order. Every array is C-contiguous over these
    worlds (a chunk of whole worlds of the fused tick, or all of them). Returns how many worlds are due.
    """
    W, V = pos_est.shape[0], pos_est.shape[1]
    normals = np.empty((W, V, 6))
    for w in range(W):
        c = cursor[w]
        for i in range(V):
            read_truth(qpos, qvel, layout, w, i, kin, quat, rot)
            for k in range(6):
                normals[w, i, k] = noise[w, c, i, k]
    measured, truth = kin[2], kin[0]
    call_sensor(law_fn, W, V, truth.ctypes.data, quat.ctypes.data, normals.ctypes.data, offset.ctypes.data, law_state,
                law_params, measured.ctypes.data, quat_est.ctypes.data)
    n_due = 0
    for w in range(W):
        for i in range(V):
            q = quat_est[w, i]
            yaw_meas[w, i] = quat_to_rot(q[0], q[1], q[2], q[3], rot_est[w, i])
            for k in range(3):
                pe, ve = kf_update(pos_est[w, i, k], vel_est[w, i, k], kin[2, w, i, k], gain_p, gain_v)
                pos_est[w, i, k] = kin[3, w, i, k] = pe
                vel_est[w, i, k] = kin[4, w, i, k] = ve
        due[w] = t[w] >= next_prediction[w] - 1e-9
        n_due += due[w]
    return n_due


@njit
def true_states_kernel(qpos, qvel, layout, pos, vel, rot):
    """pos, vel (W, V, 3) and rot (W, V, 3, 3) from qpos (W, nq), qvel (W, nv) at the addresses of
    layout (V, 7); the attitude as `downwash_core.geometry.quat_to_mat_fast` (no normalisation)."""
    for w in range(pos.shape[0]):
        for i in range(pos.shape[1]):
            a, b = layout[i, _QPOS], layout[i, _QVEL]
            for k in range(3):
                pos[w, i, k] = qpos[w, a + k]
                vel[w, i, k] = qvel[w, b + k]
            quat_to_rot(qpos[w, a + 3], qpos[w, a + 4], qpos[w, a + 5], qpos[w, a + 6], rot[w, i])


@njit
def hold_kernel(f_hat, pred, due, next_prediction, period):
    """Take the new prediction (W, V, 3) m/s^2 where due (W,) and schedule the next (s), in place."""
    for w in range(f_hat.shape[0]):
        if due[w]:
            for i in range(f_hat.shape[1]):
                for k in range(3):
                    f_hat[w, i, k] = pred[w, i, k]
            next_prediction[w] = next_prediction[w] + period


@njit
def actuate_kernel(
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
    and mass[i] * applied (N, world frame; mass (V,) kg, each vehicle's) into xfrc (W, nbody, 6)
    at each vehicle's body.
    Autopilot (controllers.autopilot.rotor_thrusts) on rot (W, V, 3, 3), body rates from
    qvel (W, nv), set-points rot_des (W, V, 3, 3), yaw_rate_des (W, V) rad/s,
    thrust_acc (W, V) m/s^2, mass_believed (W, V) kg, each vehicle's tables ap_gain (V, 14, 4)
    and max_thrust (V,) N (`Autopilot.tables`) -> rotor thrusts (N) into ctrl (W, nu).
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
                    mean[w, i, k] = 0.0  # assigned: a field that is NaN here is off all the same
            mag = np.sqrt(mean[w, i, 0] ** 2 + mean[w, i, 1] ** 2 + mean[w, i, 2] ** 2)
            for k in range(3):
                turb[w, i, k] = decay * turb[w, i, k] + diffusion * noise[w, c, i, 6 + k]
                applied[w, i, k] = mean[w, i, k] + intensity * mag * turb[w, i, k]
                xfrc[w, layout[i, _BODY], k] = mass[i] * applied[w, i, k]
            b = layout[i, _QVEL] + 3
            rotor_thrusts(
                rot[w, i], qvel[w, b:b + 3], rot_des[w, i], yaw_rate_des[w, i], thrust_acc[w, i],
                mass_believed[w, i], ap_gain[i], max_thrust[i], x, out,
            )
            for k in range(4):
                ctrl[w, layout[i, _ACT + k]] = out[k]
            for k in range(3):
                pos_est[w, i, k], vel_est[w, i, k] = kf_predict(pos_est[w, i, k], vel_est[w, i, k], acc_cmd[w, i, k], dt)
        if active[w]:
            t[w] = t[w] + dt
        cursor[w] += 1


@njit
def wind_sense_kernel(state, axes, mean, gain, vel, air, vel_air, wind_acc):
    """The wind at every vehicle from each world's gust state state (W, 3, 2) m/s.

    axes (3, 3), mean (3,) m/s: `DrydenWind.kernel_constants`; gain (V,) 1/m: each vehicle's
    rho C_d A / (2 m) (`sim.vehicle_params`).
    vel (W, V, 3) m/s true velocities. Writes air (W, V, 3) m/s (mean + gust, the same at
    every vehicle of a world), vel_air = vel - air and wind_acc (W, V, 3) m/s^2, the
    drag `sim.wind.drag_acceleration(air, vel, ...)`.
    """
    W, V = vel.shape[0], vel.shape[1]
    gust = np.empty(3)
    for w in range(W):
        gust_into(state[w], axes, gust)
        for i in range(V):
            for k in range(3):
                air[w, i, k] = mean[k] + gust[k]
                vel_air[w, i, k] = vel[w, i, k] - air[w, i, k]
            rx, ry, rz = air[w, i, 0] - vel[w, i, 0], air[w, i, 1] - vel[w, i, 1], air[w, i, 2] - vel[w, i, 2]
            f = drag_gain_speed(rx, ry, rz, gain[i])
            wind_acc[w, i, 0], wind_acc[w, i, 1], wind_acc[w, i, 2] = f * rx, f * ry, f * rz


@njit
def wind_advance_kernel(state, noise, cursor, vel, dt, mean, sigma, length, min_airspeed, A, B):
    """Advance each world's gust state (W, 3, 2) one autopilot tick of dt (s), in place.

    The time scales come from the airspeed |mean_i v_i - mean wind| (floored at
    min_airspeed, m/s) of the world's mean vehicle velocity, vel (W, V, 3) m/s; the draws
    are noise[w, cursor[w]] (3, 2) of the world's wind block (W, block, 3, 2). sigma (3,)
    m/s, length (3,) m: `DrydenWind.kernel_constants`; A, B (3, 2, 2) scratch.
    """
    W, V = vel.shape[0], vel.shape[1]
    for w in range(W):
        mx, my, mz = 0.0, 0.0, 0.0
        for i in range(V):
            mx, my, mz = mx + vel[w, i, 0], my + vel[w, i, 1], mz + vel[w, i, 2]
        mx, my, mz = mx / V - mean[0], my / V - mean[1], mz / V - mean[2]
        airspeed = math.hypot(math.hypot(mx, my), mz)
        coefficients_into(dt, airspeed, sigma, length, min_airspeed, A, B)
        gust_step_into(state[w], noise[w, cursor[w]], A, B)


@njit
def wind_force_kernel(xfrc, layout, mass, wind_acc):
    """Add the wind drag mass[i] * wind_acc (W, V, 3) m/s^2 (N, world frame; mass (V,) kg) to xfrc (W, nbody, 6)."""
    for w in range(wind_acc.shape[0]):
        for i in range(wind_acc.shape[1]):
            b = layout[i, _BODY]
            for k in range(3):
                xfrc[w, b, k] = xfrc[w, b, k] + mass[i] * wind_acc[w, i, k]


@njit
def status_kernel(qpos, layout, qvel, diverged, active, tick_index, max_distance, ground, radius_xy, radius_z, status):
    """Count the tick of active worlds (tick_index (W,), in place) and write into status (W,)
    the `Status` codes of those that end now (OK elsewhere).

    qpos (W, nq): vehicle positions (m) at qpos[w, layout[i, _QPOS] + (0, 1, 2)];
    diverged (W,) bool from the physics; radius_xy, radius_z (V, V) m: each pair's collision
    ellipsoid (`sim.vehicle_params.collision_radii`). Returns how many worlds end.
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
                    if (dx * dx + dy * dy) / radius_xy[i, j] ** 2 + dz * dz / radius_z[i, j] ** 2 < 1.0:
                        status[w] = _VEHICLE
        n_ended += status[w] != _OK
    return n_ended
