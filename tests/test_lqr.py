"""LQR gain against analytic answers and scipy's Riccati solution; feedback linearisation."""

import control
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.lqr import (
    DEFAULT_Q, DEFAULT_R, ControllerState, FeedbackLinearisedLQR, LQRConfig, Setpoint, attitude_setpoint,
    double_integrator, lqr_gain, wrap_angle,
)
from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY
from downwash_core.state import RefSample


# The gain is rounded to float32 precision so that every CPU gets its bits (downwash_core.numerics):
# half a float32 step, relative. LAPACK's own error (the Riccati solve, ~1e-15 relative here) is far
# below it, and the rounded bits are the same under every OpenBLAS kernel (tests/test_numerics.py).
F32 = 2.0**-24


def test_scalar_integrator_gain_is_sqrt_q_over_r():
    # yaw channel: xdot = u, cost q x^2 + r u^2 -> K = sqrt(q r) / r
    K = lqr_gain()
    q, r = DEFAULT_Q[6, 6], DEFAULT_R[3, 3]
    assert K[3, 6] == pytest.approx(np.sqrt(q * r) / r, rel=F32)


def test_double_integrator_gains_analytic():
    # per axis: kp = sqrt(qp / r), kv = sqrt(qv / r + 2 kp)
    K = lqr_gain()
    for axis in range(3):
        qp, qv, r = DEFAULT_Q[axis, axis], DEFAULT_Q[axis + 3, axis + 3], DEFAULT_R[axis, axis]
        kp = np.sqrt(qp / r)
        assert K[axis, axis] == pytest.approx(kp, rel=F32)
        assert K[axis, axis + 3] == pytest.approx(np.sqrt(qv / r + 2 * kp), rel=F32)
    # the decoupled axes: every other entry is exactly zero (the solve's round-off removed)
    mask = np.zeros_like(K, bool)
    for axis in range(3):
        mask[axis, [axis, axis + 3]] = True
    mask[3, 6] = True
    assert np.all(K[~mask] == 0.0)


def test_matches_scipy_riccati_and_is_stable():
    rng = np.random.default_rng(0)
    A, B = double_integrator()
    for _ in range(3):
        M = rng.normal(size=(7, 7))
        Q = M @ M.T + 0.1 * np.eye(7)
        N = rng.normal(size=(4, 4))
        R = N @ N.T + 0.5 * np.eye(4)
        P = scipy.linalg.solve_continuous_are(A, B, Q, R)
        # python-control (without slycot) makes its gain with this same scipy CARE and solve: the raw gain
        # equals the right side bit for bit on any CPU (slycot's SB02MD would differ by ~cond * eps, ~1e-14
        # here); what is left is lqr_gain's float32 rounding, <= 2^-24 = 6.0e-8 relative (0.45 of rtol)
        np.testing.assert_allclose(lqr_gain(Q, R), np.linalg.solve(R, B.T @ P), rtol=1e-7, atol=1e-9)
        assert np.linalg.eigvals(A - B @ lqr_gain(Q, R)).real.max() < 0


def test_rollout_cost_matches_riccati():
    """The closed-loop cost from x0 equals x0' P x0 (continuous LQR, no cross term)."""
    A, B = double_integrator()
    K = lqr_gain()
    P = scipy.linalg.solve_continuous_are(A, B, DEFAULT_Q, DEFAULT_R)
    x0 = np.array([0.3, -0.2, 0.1, 0.0, 0.1, 0.0, 0.2])
    sys = control.ss(A - B @ K, np.zeros((7, 1)), np.eye(7), 0)
    t = np.linspace(0, 60, 60001)
    x = control.initial_response(sys, t, x0).states
    u = -K @ x
    stage = np.einsum("it,ij,jt->t", x, DEFAULT_Q, x) + np.einsum("it,ij,jt->t", u, DEFAULT_R, u)
    cost = np.trapezoid(stage, t)
    assert cost == pytest.approx(x0 @ P @ x0, rel=1e-4)


def test_command_law_batched():
    lqr = FeedbackLinearisedLQR()
    rng = np.random.default_rng(1)
    shape = (4, 2)
    p, v, pr, vr, ar, fh = (rng.normal(size=shape + (3,)) for _ in range(6))
    yaw, yr, yrr = (rng.normal(size=shape) for _ in range(3))
    cmd = lqr(ControllerState(p, v, yaw), RefSample(pr, vr, ar, yr, yrr), fh)
    x = np.concatenate([p - pr, v - vr, wrap_angle(yaw - yr)[..., None]], -1)
    fb = np.einsum("ij,...j->...i", lqr.K, x)
    np.testing.assert_allclose(cmd.acc, ar - fb[..., :3] - fh, atol=1e-12)
    np.testing.assert_allclose(cmd.yaw_rate, yrr - fb[..., 3], atol=1e-12)


def test_bad_weights():
    with pytest.raises(ValueError, match=r"Q: expected \(7, 7\) but found \(6, 6\)"):
        lqr_gain(np.eye(6), DEFAULT_R)
    with pytest.raises(ValueError, match="R: must be positive definite"):
        lqr_gain(DEFAULT_Q, np.diag([1, 1, 1, 0.0]))
    with pytest.raises(ValueError, match="Q: must be symmetric"):
        lqr_gain(DEFAULT_Q + np.triu(np.ones((7, 7)), 1), DEFAULT_R)


def test_attitude_setpoint():
    rng = np.random.default_rng(2)
    acc = rng.normal(scale=2.0, size=(50, 3))
    yaw = rng.uniform(-np.pi, np.pi, 50)
    thrust, R = attitude_setpoint(acc, yaw)
    # BLAS/LAPACK on an orthonormal R: any kernel's 3-term sums are within 3 eps of exact (|rows| = 1),
    # det's LU within a few eps (cond(R) = 1): ~1e-15 against 1e-12
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # thrust vector realises the commanded acceleration when inside the limits
    f = thrust[:, None] * R[:, :, 2] - [0, 0, GRAVITY]
    tilt = np.arccos(R[:, 2, 2])
    ok = tilt < np.deg2rad(34.9)
    np.testing.assert_allclose(f[ok], acc[ok], atol=1e-9)
    # heading (Lee et al.): c1 = (cos yaw, sin yaw, 0) lies in the b1-b3 plane, on b1's side
    c1 = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], -1)
    np.testing.assert_allclose(np.einsum("ni,ni->n", R[:, :, 1], c1), 0.0, atol=1e-12)
    assert (np.einsum("ni,ni->n", R[:, :, 0], c1) > 0).all()
    # a huge lateral command is tilt-limited
    t2, R2 = attitude_setpoint(np.array([[50.0, 0, 0]]), np.zeros(1))
    assert np.degrees(np.arccos(R2[0, 2, 2])) == pytest.approx(35.0)


@pytest.mark.parametrize("extra", ["none", "residual", "override"])
def test_compiled_command_setpoint_equals_command_then_setpoint(extra):
    """The simulator's one-pass kernel against __call__ followed by attitude_setpoint."""
    rng = np.random.default_rng(1)
    W, V = 5, 2
    lqr = FeedbackLinearisedLQR()
    pos, vel, ref_pos, ref_vel, ref_acc, f_hat = (rng.normal(size=(W, V, 3)) for _ in range(6))
    yaw, ref_yaw, ref_yaw_rate = (rng.uniform(-4, 4, size=(W, V)) for _ in range(3))
    residual = rng.normal(size=(W, V, 3)) if extra == "residual" else None
    override = None
    if extra == "override":
        override = np.where(rng.uniform(size=(W, V, 3)) < 0.5, rng.normal(size=(W, V, 3)), np.nan)
    lookahead, max_tilt = 0.02, lqr.max_tilt

    ref = RefSample(ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate)
    cmd = lqr(ControllerState(pos, vel, yaw), ref, f_hat)
    acc = cmd.acc
    if residual is not None:
        acc = acc + residual
    if override is not None:
        acc = np.where(np.isfinite(override), override, acc)
    thrust, rot = lqr.setpoint(acc, yaw + cmd.yaw_rate * lookahead)
    assert max_tilt == np.deg2rad(35.0)

    out = Setpoint.empty(W, V)
    lqr.command_setpoint(ControllerState(pos, vel, yaw), ref, f_hat, out, residual, override, lookahead)
    # K (x - x_ref) may be summed in another order than NumPy's matmul: rounding only
    for got, want in zip(out, (acc, cmd.yaw_rate, thrust, rot)):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    if override is not None:
        finite = np.isfinite(override)
        assert np.array_equal(out[0][finite], override[finite])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.5, 80.0), min_size=3, max_size=3), st.lists(st.floats(1.0, 3.0), min_size=3, max_size=3))
def test_pd_matched_weights_give_that_pd_gain(kp, damping):
    """LQRConfig.from_pd: python-control's gain of the weights is the PD law asked for, on every axis
    (kd = damping * sqrt(2 kp), at least the least damping an LQR gain can have)."""
    kd = [z * np.sqrt(2.0 * p) for p, z in zip(kp, damping)]
    cfg = LQRConfig.from_pd(kp, kd)
    K = lqr_gain(np.diag(cfg.q), np.diag(cfg.r))
    # 1e-6: the Riccati solve's accuracy (measured 2e-8 relative on these weights), on any CPU's LAPACK
    np.testing.assert_allclose(np.diag(K[:3, :3]), kp, rtol=1e-6)
    np.testing.assert_allclose(np.diag(K[:3, 3:6]), kd, rtol=1e-6)
    assert K[3, 6] == pytest.approx(lqr_gain()[3, 6])  # yaw as the default's


def test_pd_matched_weights_refuse_what_no_lqr_gives():
    with pytest.raises(ConfigError, match=r"kd\^2 >= 2 kp"):
        LQRConfig.from_pd((10.0, 10.0, 10.0), (1.0, 10.0, 10.0))
    with pytest.raises(ConfigError, match="expected 3 finite kp > 0"):
        LQRConfig.from_pd((10.0, 10.0), (5.0, 5.0))
