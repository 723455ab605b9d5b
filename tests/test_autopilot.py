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
    # the collective row is LAPACK's inverse of the 4x4 mixer (cond 62.5): ~cond * eps = 1.4e-14 on any kernel
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
    # the mixer's inverse (LAPACK, cond 62.5) and 4-term BLAS products: any kernel is within ~cond * eps *
    # |thrust| ~ 1e-14 (N, N m) of exact, under the 1e-12 floor (rtol 1e-7 covers the nonzero entries)
    np.testing.assert_allclose(wrench[:, 1:], -ap.kR * eR - ap.kW * (w - wd), atol=1e-12)
    np.testing.assert_allclose(wrench[:, 0], QUAD.mass * T * np.einsum("ni,ni->n", Rd[:, :, 2], R[:, :, 2]), atol=1e-12)


def test_saturation():
    ap = Autopilot()
    R = np.eye(3)[None]
    out = ap(R, np.zeros((1, 3)), R, np.zeros(1), np.array([100.0]))
    np.testing.assert_allclose(out, QUAD.max_rotor_thrust)
    out = ap(R, np.zeros((1, 3)), R, np.zeros(1), np.array([-5.0]))
    np.testing.assert_allclose(out, 0.0)


def _readable_rotor_thrusts(ap, R, w, Rd, yr, T):
    """The autopilot in plain linear algebra: the PD wrench through the inverse mixer, then
    attitude first (every demand less the largest one's excess), clipped to [0, max]."""
    E = np.swapaxes(Rd, -1, -2) @ R
    S = E - np.swapaxes(E, -1, -2)
    eR = 0.5 * np.stack([S[:, 2, 1], S[:, 0, 2], S[:, 1, 0]], -1)
    wd = np.zeros_like(w)
    wd[:, 2] = yr
    b3 = np.maximum(np.einsum("ni,ni->n", Rd[:, :, 2], R[:, :, 2]), 0.5)
    wrench = np.concatenate([(QUAD.mass * T * b3)[:, None], -ap.kR * eR - ap.kW * (w - wd)], axis=1)
    demand = wrench @ np.linalg.inv(mixer_matrix()).T
    excess = np.maximum(demand.max(axis=1) - QUAD.max_rotor_thrust, 0.0)
    return np.clip(demand - excess[:, None], 0.0, QUAD.max_rotor_thrust), demand


def test_saturation_gives_up_thrust_not_attitude():
    """Over random attitudes, rates and collective demands up to 3 g: the compiled mixer is its
    readable form; where a rotor saturates, the torques are the unsaturated PD torques as long as
    no rotor is driven to zero, and only the collective thrust falls short."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    n = 400
    ap = Autopilot()
    R = Rotation.from_rotvec(rng.normal(scale=0.3, size=(n, 3))).as_matrix()
    Rd = Rotation.from_rotvec(rng.normal(scale=0.3, size=(n, 3))).as_matrix()
    w = rng.normal(scale=1.0, size=(n, 3))
    yr = rng.normal(scale=0.5, size=n)
    T = rng.uniform(0.0, 3.0 * GRAVITY, size=n)
    rotors = ap(R, w, Rd, yr, T)
    expected, demand = _readable_rotor_thrusts(ap, R, w, Rd, yr, T)
    # both go through the same LAPACK inverse of the mixer (cond 62.5) and then BLAS / compiled sums of 4-14
    # terms in their own orders: ~cond * eps * 4 N ~ 6e-14 apart on any kernel (measured 4e-15)
    np.testing.assert_allclose(rotors, expected, rtol=1e-12, atol=1e-12)
    saturated = (demand.max(axis=1) > QUAD.max_rotor_thrust) & (demand.min(axis=1) - (
        demand.max(axis=1) - QUAD.max_rotor_thrust) > 0)
    assert saturated.sum() > 50  # (the draw exercises the rule)
    kept = rotors[saturated] @ mixer_matrix().T
    wanted = demand[saturated] @ mixer_matrix().T
    # 4-term BLAS products of thrusts <= 4 N with |mixer| <= 1: within 4 eps * 16 ~ 1e-14 of exact on any kernel
    np.testing.assert_allclose(kept[:, 1:], wanted[:, 1:], atol=1e-12)
    assert (kept[:, 0] < wanted[:, 0]).all()
    np.testing.assert_allclose(rotors[saturated].max(axis=1), QUAD.max_rotor_thrust)


@pytest.mark.parametrize("climb_g", [0.0, 2.0])
def test_attitude_step_converges_in_mujoco(climb_g):
    """From level, a 10 degree roll set-point is reached in MuJoCo with the motor lag, also while
    the collective demand (hover plus climb_g g) saturates the rotors: attitude comes first."""
    sc = build_scene(("solo",))
    d = mujoco.MjData(sc.model)
    d.qpos[2] = 2.0
    d.act[:] = QUAD.hover_rotor_thrust
    ap = Autopilot()
    thrust, Rd = attitude_setpoint(np.array([[0.0, -(1 + climb_g) * GRAVITY * np.tan(np.deg2rad(10)),
                                                             climb_g * GRAVITY]]),
                                   np.zeros(1))
    assert (climb_g == 0.0) == bool(thrust[0] * QUAD.mass / 4 < QUAD.max_rotor_thrust)
    for _ in range(100):  # 1 s at the 100 Hz autopilot rate
        R = quat_to_mat(d.qpos[3:7][None])
        d.ctrl[:] = ap(R, d.qvel[3:6][None], Rd, np.zeros(1), thrust)[0]
        mujoco.mj_step(sc.model, d, nstep=5)
    R = quat_to_mat(d.qpos[3:7][None])[0]
    angle = np.degrees(np.arccos(np.clip(np.trace(Rd[0].T @ R) / 2 - 0.5, -1, 1)))
    assert angle < 0.5
    roll = np.degrees(np.arctan2(R[2, 1], R[2, 2]))
    assert roll == pytest.approx(10.0, abs=0.5)
