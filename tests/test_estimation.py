"""Kalman filter: steady-state gain is the limit of the time-varying filter; it tracks."""

import numpy as np

from sim.estimation import (
    MocapConfig, MocapKalmanFilter, kalman_gain_sequence, kf_predict, kf_update, steady_state_gain,
)


def test_steady_state_gain_is_limit_of_time_varying_filter():
    dt = 0.01
    seq = kalman_gain_sequence(dt, 2000)
    # rtol: the steady-state gain is rounded to float32 precision (downwash_core.numerics), 2^-24 = 6e-8;
    # that rounding is 0.27 of rtol here, the same bits under every kernel (tests/test_numerics.py), and
    # the recursion (BLAS 2x2 products) and the raw DARE gain agree to 2e-13 relative under every kernel
    np.testing.assert_allclose(seq[-1], steady_state_gain(dt), rtol=2.0**-24)
    assert 0 < seq[-1][0] < 1 and seq[-1][1] > 0


def test_tracks_constant_acceleration_without_bias():
    rng = np.random.default_rng(0)
    dt = 0.01
    kf = MocapKalmanFilter(dt)
    a = np.array([[0.5, -0.2, 0.1]])
    p_true, v_true = np.zeros((1, 3)), np.array([[1.0, 0.0, -0.5]])
    p, v = np.zeros((1, 3)), np.zeros((1, 3))
    errs = []
    for k in range(1000):
        meas = p_true + 0.0005 * rng.normal(size=(1, 3))
        p, v = kf.update(p, v, meas)
        errs.append(np.concatenate([(p - p_true)[0], (v - v_true)[0]]))
        p, v = kf.predict(p, v, a)
        p_true, v_true = p_true + dt * v_true + 0.5 * dt * dt * a, v_true + dt * a
    e = np.array(errs[200:])
    assert np.abs(e[:, :3]).mean() < 0.0005  # better than the raw measurement noise
    assert np.abs(e[:, 3:]).mean() < 0.05
    assert np.abs(e.mean(axis=0)).max() < 0.01  # unbiased


def test_bad_config():
    import pytest

    with pytest.raises(ValueError, match="position_noise"):
        MocapConfig(position_noise=-1.0)


def test_compiled_scalar_steps_equal_the_filter_bit_for_bit():
    """kf_predict / kf_update (the simulator's compiled loop) against MocapKalmanFilter."""
    kf = MocapKalmanFilter(0.01)
    rng = np.random.default_rng(0)
    pos, vel, acc, meas = rng.normal(size=(4, 50, 3)) * [[[1.0]], [[0.5]], [[3.0]], [[1.0]]]
    p_ref, v_ref = kf.predict(pos, vel, acc)
    p_upd, v_upd = kf.update(pos, vel, meas)
    g_p, g_v = (float(g) for g in kf.gain)
    for idx in np.ndindex(pos.shape):
        assert kf_predict(pos[idx], vel[idx], acc[idx], kf.dt) == (p_ref[idx], v_ref[idx])
        assert kf_update(pos[idx], vel[idx], meas[idx], g_p, g_v) == (p_upd[idx], v_upd[idx])
