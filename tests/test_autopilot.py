"""Mixer and attitude autopilot: analytic wrench, saturation, closed-loop convergence."""

import mujoco
import numpy as np
import pytest

from controllers.autopilot import Autopilot, mixer_matrix
from controllers.lqr import attitude_setpoint
from downwash_core.params import GRAVITY, QUAD
from sim.scene import build_scene
from downwash_core.geometry import quat_to_mat_fast as quat_to_mat


def test_level_hover_gives_equal_hover_thrust():
    ap = Autopilot()
    R = np.broadcast_to(np.eye(3), (3, 3, 3)).copy()
    out = ap(R, np.zeros((3, 3)), R, np.zeros(3), np.full(3, GRAVITY))
    np.testing.assert_allclose(out, QUAD.hover_rotor_thrust, rtol=1e-12)


def test_wrench_matches_pd_law():
    """Unsaturated: M @ thrusts = [m T (b3d.b3), -kR e_R - kW (w - w_d)]."""
    rng = np.random.default_rng(0)
    ap = Autopilot()
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(rng.normal(scale=0.05, size=(20, 3))).as_matrix()
    Rd = Rotation.from_rotvec(rng.normal(scale=0.05, size=(20, 3))).as_matrix()
    w = rng.normal(scale=0.3, size=(20, 3))
    yr = rng.normal(scale=0.2, size=20)
    T = np.full(20, GRAVITY)
    rotors = ap(R, w, Rd, yr, T)
    assert (rotors > 0).all() and (rotors < QUAD.max_rotor_thrust).all()
    wrench = rotors @ mixer_matrix().T
    E = np.swapaxes(Rd, -1, -2) @ R
    S = E - np.swapaxes(E, -1, -2)
    eR = 0.5 * np.stack([S[:, 2, 1], S[:, 0, 2], S[:, 1, 0]], -1)
    wd = np.zeros_like(w)
    wd[:, 2] = yr
    np.testing.assert_allclose(wrench[:, 1:], -ap.kR * eR - ap.kW * (w - wd), atol=1e-12)
    np.testing.assert_allclose(wrench[:, 0], QUAD.mass * T * np.einsum("ni,ni->n", Rd[:, :, 2], R[:, :, 2]), atol=1e-12)


def test_saturation():
    ap = Autopilot()
    R = np.eye(3)[None]
    out = ap(R, np.zeros((1, 3)), R, np.zeros(1), np.array([100.0]))
    np.testing.assert_allclose(out, QUAD.max_rotor_thrust)
    out = ap(R, np.zeros((1, 3)), R, np.zeros(1), np.array([-5.0]))
    np.testing.assert_allclose(out, 0.0)


def test_attitude_step_converges_in_mujoco():
    """From level, a 10 degree roll set-point is reached in MuJoCo with the motor lag."""
    sc = build_scene(("solo",))
    d = mujoco.MjData(sc.model)
    d.qpos[2] = 2.0
    d.act[:] = QUAD.hover_rotor_thrust
    ap = Autopilot()
    thrust, Rd = attitude_setpoint(np.array([[0.0, -GRAVITY * np.tan(np.deg2rad(10)), 0.0]]), np.zeros(1))
    for _ in range(100):  # 1 s at the 100 Hz autopilot rate
        R = quat_to_mat(d.qpos[3:7][None])
        d.ctrl[:] = ap(R, d.qvel[3:6][None], Rd, np.zeros(1), thrust)[0]
        mujoco.mj_step(sc.model, d, nstep=5)
    R = quat_to_mat(d.qpos[3:7][None])[0]
    angle = np.degrees(np.arccos(np.clip(np.trace(Rd[0].T @ R) / 2 - 0.5, -1, 1)))
    assert angle < 0.5
    roll = np.degrees(np.arctan2(R[2, 1], R[2, 2]))
    assert roll == pytest.approx(10.0, abs=0.5)
