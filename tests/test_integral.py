"""The LQR with integral action (`controllers.integral`): its gain, its integral, anti-windup, a removed sag."""

from __future__ import annotations

import control
import numpy as np
import pytest

from controllers.integral import DEFAULT_QI, IntegralLQR, integral_lqr_gain
from controllers.lqr import ControllerState, FeedbackLinearisedLQR, LQRConfig, Setpoint
from downwash_core.errors import ConfigError
from downwash_core.params import RATES
from downwash_core.state import RefSample


def _ref(W, V, pos=0.0):
    z = np.zeros((W, V, 3))
    return RefSample(z + pos, z.copy(), z.copy(), np.zeros((W, V)), np.zeros((W, V)))


def _state(W, V, pos):
    return ControllerState(np.broadcast_to(np.asarray(pos, float), (W, V, 3)).copy(), np.zeros((W, V, 3)),
                           np.zeros((W, V)))


def _command(ctl, state, ref, f_hat=None, **kw):
    W, V = state.pos.shape[:2]
    out = Setpoint.empty(W, V)
    ctl.command_setpoint(state, ref, np.zeros((W, V, 3)) if f_hat is None else f_hat, out, **kw)
    return out


def test_the_gain_is_python_controls_on_the_augmented_system_and_stabilises_it():
    K_i, K = integral_lqr_gain()
    A = np.zeros((10, 10))
    A[0:3, 3:6], A[3:6, 6:9] = np.eye(3), np.eye(3)
    B = np.zeros((10, 4))
    B[6:9, 0:3], B[9, 3] = np.eye(3), 1.0
    Q = np.diag([*DEFAULT_QI, *np.diag(np.diag([1.0, 1.0, 8.0, 0.01, 0.01, 0.1, 1.0]))])
    K_full, _, _ = control.lqr(A, B, Q, np.diag([0.8, 0.8, 0.8, 1.0]))
    np.testing.assert_allclose(np.hstack([np.vstack([K_i, np.zeros((1, 3))]), K]), K_full, rtol=1e-6, atol=1e-9)
    assert np.all(np.linalg.eigvals(A - B @ K_full).real < 0)
    assert np.all(np.diag(K_i) > 0) and np.allclose(K_i, np.diag(np.diag(K_i)))  # decoupled axes


def test_with_no_integral_it_commands_what_the_lqr_with_its_gain_does():
    ctl = IntegralLQR()
    state, ref = _state(2, 3, [0.1, -0.2, 0.05]), _ref(2, 3)
    f_hat = np.full((2, 3, 3), 0.3)
    got = _command(ctl, state, ref, f_hat)
    want = _command(FeedbackLinearisedLQR(ctl.config, gain=ctl.K), state, ref, f_hat)
    for a, b in zip(got, want):
        assert np.array_equal(a, b)


def test_the_integral_is_the_sum_of_the_errors_and_acts_through_k_i():
    ctl = IntegralLQR()
    e = np.array([0.01, -0.02, 0.03])
    state, ref = _state(1, 1, e), _ref(1, 1)
    for _ in range(10):
        _command(ctl, state, ref)
    np.testing.assert_allclose(ctl.integral[0, 0], 10 * e * RATES.control_dt, rtol=1e-12)
    out = _command(ctl, state, ref)
    plain = _command(FeedbackLinearisedLQR(ctl.config, gain=ctl.K), state, ref)
    np.testing.assert_allclose(out.acc[0, 0], plain.acc[0, 0] - ctl.K_i @ (10 * e * RATES.control_dt), rtol=1e-12)


def test_no_windup_where_the_actuators_cannot_follow_and_a_bounded_authority():
    ctl = IntegralLQR(max_integral_acc=2.0)
    # 50 m to the side: the tilt limit cuts the command, so the vehicle's integral does not move
    state = ControllerState(np.array([[[50.0, 0.0, 0.0], [0.01, 0.0, 0.0]]]), np.zeros((1, 2, 3)), np.zeros((1, 2)))
    for _ in range(20):
        _command(ctl, state, _ref(1, 2))
    assert np.all(ctl.integral[0, 0] == 0)
    assert ctl.integral[0, 1, 0] > 0
    # an override freezes it too
    ctl.reset()
    _command(ctl, _state(1, 1, [0.1, 0, 0]), _ref(1, 1), override=np.zeros((1, 1, 3)))
    assert np.all(ctl.integral == 0)
    # a long steady error: the integral's command stops at the bound
    for _ in range(5000):
        _command(ctl, _state(1, 1, [0.0, 0.0, -0.5]), _ref(1, 1))
    assert abs(ctl.K_i[2, 2] * ctl.integral[0, 0, 2]) == pytest.approx(2.0, rel=1e-12)


def test_reset_clears_only_its_worlds():
    ctl = IntegralLQR()
    for _ in range(5):
        _command(ctl, _state(3, 1, [0.0, 0.0, 0.1]), _ref(3, 1))
    ctl.reset([1])
    assert np.all(ctl.integral[1] == 0) and np.all(ctl.integral[[0, 2], 0, 2] > 0)


@pytest.mark.parametrize("bad", [dict(qi=(1.0, 1.0)), dict(qi=(1.0, 0.0, 1.0)), dict(dt=0.0), dict(dt=float("nan")),
                                 dict(max_integral_acc=-1.0)])
def test_bad_settings_are_refused(bad):
    with pytest.raises(ConfigError):
        IntegralLQR(**bad)


def test_it_describes_itself():
    d = IntegralLQR(LQRConfig(max_tilt_deg=30.0)).describe()
    assert d["type"] == "IntegralLQR" and d["max_tilt_deg"] == 30.0 and d["qi"] == list(DEFAULT_QI)


class _ConstantPush:
    """Pushes every vehicle below its leader down by `push` m/s^2."""

    def __init__(self, push):
        self.push = push

    def __call__(self, p_a, v_a, R_a, p_b, v_b):
        below = (np.asarray(p_b)[..., 2] < np.asarray(p_a)[..., 2])[..., None]
        shape = np.broadcast_shapes(np.shape(p_a), np.shape(p_b))
        return np.where(below, np.array([0.0, 0.0, -self.push]), 0.0) * np.ones(shape)


def test_in_the_loop_it_removes_the_steady_sag_the_lqr_keeps():
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, stack
    from sim.flight import fly
    from sim.scene import build_scene

    leader = np.array(LEADER_POSITION)
    ref = stack([Hover(leader, n_worlds=1), Hover(leader - [0, 0, 0.6], n_worlds=1)])
    scene, field = build_scene(), _ConstantPush(1.5)
    plain = fly(scene, ref, [0], 10.0, field=field)[0]
    integral = fly(scene, ref, [0], 10.0, field=field, controller=IntegralLQR())[0]
    assert plain.ok and integral.ok
    tail = slice(-100, None)  # the last 2 s
    sag = [np.mean(L["pos"][tail, 1, 2] - L["ref_pos"][tail, 1, 2]) for L in (plain, integral)]
    assert sag[0] < -0.05 and abs(sag[1]) < 0.1 * abs(sag[0])


def test_per_world_controllers_fly_each_group_as_alone():
    """PerWorldController of the LQR and the integral LQR: each group's commands and state are what
    its controller gives its worlds alone, bit for bit; resets reach the right rows."""
    from controllers.per_world import PerWorldController

    rng = np.random.default_rng(3)
    W, V = 5, 2
    assignment = np.array([1, 0, 1, 1, 0])
    routed = PerWorldController([FeedbackLinearisedLQR(), IntegralLQR()], assignment)
    alone = [FeedbackLinearisedLQR(), IntegralLQR()]
    for _ in range(4):
        state = ControllerState(rng.normal(size=(W, V, 3)) * 0.1, rng.normal(size=(W, V, 3)) * 0.1,
                                rng.normal(size=(W, V)) * 0.1)
        ref, f_hat = _ref(W, V), rng.normal(size=(W, V, 3))
        out = _command(routed, state, ref, f_hat)
        for i, ctl in enumerate(alone):
            w = np.flatnonzero(assignment == i)
            part = _command(ctl, ControllerState(*(a[w] for a in state)), RefSample(*(a[w] for a in ref)), f_hat[w])
            for a, b in zip(out, part):
                assert np.array_equal(a[w], b)
    np.testing.assert_array_equal(routed.controllers[1].integral, alone[1].integral)
    routed.reset([2])  # world 2 is row 1 of the integral LQR's group
    assert np.all(routed.controllers[1].integral[1] == 0) and np.any(routed.controllers[1].integral[[0, 2]] != 0)
    with pytest.raises(ConfigError, match="assignment"):
        PerWorldController([FeedbackLinearisedLQR()], [0, 1])
