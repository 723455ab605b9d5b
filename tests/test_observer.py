"""The disturbance observer (`sim.observer`): its estimate's rate, its residual form, its resets, in the loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError
from downwash_core.state import VehicleStates
from sim.observer import DEFAULT_BANDWIDTH, DisturbanceObserver

DT = 0.02  # s, the controller period


def _states(W: int, V: int) -> VehicleStates:
    return VehicleStates(np.zeros((W, V, 3)), np.zeros((W, V, 3)), np.broadcast_to(np.eye(3), (W, V, 3, 3)).copy())


class _Constant:
    """An inner predictor that always predicts `value`."""

    def __init__(self, value):
        self.value = np.asarray(value, dtype=np.float64)

    def __call__(self, estimated, true=None):
        return np.broadcast_to(self.value, estimated.pos.shape).copy()


def _fly_synthetic(obs, disturbance, n, W=2, V=1, seed=0):
    """n ticks of a double integrator pushed by `disturbance` under random commands, the observer called
    and told each tick as the simulator does (a due call at the tick's start, observe after it)."""
    rng = np.random.default_rng(seed)
    vel = np.zeros((W, V, 3))
    out = []
    for k in range(n):
        out.append(obs(_states(W, V), _states(W, V), due=np.ones(W, bool)))
        u = rng.normal(size=(W, V, 3))
        obs.observe(np.full(W, k * DT), vel.copy(), u)
        vel = vel + (u + disturbance) * DT
    return out


@settings(max_examples=25, deadline=None)
@given(st.floats(0.5, 30.0), st.lists(st.floats(-5, 5), min_size=3, max_size=3), st.integers(2, 60))
def test_the_estimate_of_a_constant_disturbance_rises_at_the_stated_rate(bandwidth, d, n):
    """After n ticks (n - 1 measurements), d_hat = d (1 - exp(-bandwidth dt)^(n - 1)), whatever the commands."""
    d = np.array(d)
    obs = DisturbanceObserver(bandwidth=bandwidth, bound=None)
    _fly_synthetic(obs, d, n)
    expected = d * (1.0 - math.exp(-bandwidth * DT) ** (n - 1))
    np.testing.assert_allclose(obs.estimate, np.broadcast_to(expected, obs.estimate.shape), atol=1e-9)


def test_with_a_model_inside_it_estimates_what_the_model_missed():
    d, model = np.array([0.2, -0.1, -1.5]), np.array([0.0, 0.0, -1.0])
    obs = DisturbanceObserver(_Constant(model), bandwidth=10.0, bound=None)
    out = _fly_synthetic(obs, d, 200)
    np.testing.assert_allclose(obs.estimate[0, 0], d - model, atol=1e-9)  # the residual, not the whole
    np.testing.assert_allclose(out[-1][0, 0], d, atol=1e-9)  # the model plus the residual: the whole


def test_the_bound_caps_what_is_applied_not_what_is_estimated():
    obs = DisturbanceObserver(bandwidth=50.0, bound=1.0)
    out = _fly_synthetic(obs, np.array([0.0, 0.0, -8.0]), 100)
    assert np.linalg.norm(obs.estimate[0, 0]) == pytest.approx(8.0, rel=1e-6)
    assert np.linalg.norm(out[-1][0, 0]) == pytest.approx(1.0, rel=1e-12)


def test_reset_forgets_only_its_worlds_and_the_next_tick_is_not_measured():
    obs = DisturbanceObserver(bandwidth=20.0, bound=None)
    _fly_synthetic(obs, np.array([0.0, 0.0, -1.0]), 50, W=3)
    before = obs.estimate.copy()
    obs.reset([1])
    assert np.all(obs.estimate[1] == 0) and np.array_equal(obs.estimate[[0, 2]], before[[0, 2]])
    # the first tick after a reset has nothing to difference against: the estimate stays 0
    obs(_states(3, 1), _states(3, 1), due=np.ones(3, bool))
    obs.observe(np.full(3, 10.0), np.full((3, 1, 3), 7.0), np.zeros((3, 1, 3)))
    assert np.all(obs.estimate[1] == 0)


def test_a_non_finite_measurement_leaves_the_estimate():
    obs = DisturbanceObserver(bandwidth=20.0, bound=None)
    _fly_synthetic(obs, np.array([0.0, 0.0, -1.0]), 20, W=1)
    before = obs.estimate.copy()
    obs(_states(1, 1), _states(1, 1), due=np.ones(1, bool))
    obs.observe(np.full(1, 20 * DT), np.full((1, 1, 3), np.nan), np.zeros((1, 1, 3)))
    assert np.array_equal(obs.estimate, before)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan, True, "4"])
def test_bad_bandwidths_are_refused(bad):
    with pytest.raises(ConfigError, match="bandwidth"):
        DisturbanceObserver(bandwidth=bad)


def test_it_describes_itself_for_provenance():
    assert DisturbanceObserver().describe() == {"type": "DisturbanceObserver", "bandwidth": DEFAULT_BANDWIDTH,
                                                "bound": 20.0, "inner": "ZeroPredictor"}


class _ConstantPush:
    """A field that pushes every vehicle below its leader down by `push` m/s^2, wherever it is."""

    def __init__(self, push: float):
        self.push = push

    def __call__(self, p_a, v_a, R_a, p_b, v_b):
        below = (np.asarray(p_b)[..., 2] < np.asarray(p_a)[..., 2])[..., None]
        return np.where(below, np.array([0.0, 0.0, -self.push]), 0.0) * np.ones(np.broadcast_shapes(np.shape(p_a), np.shape(p_b)))


def test_in_the_loop_it_removes_a_steady_sag():
    """A hover beneath the leader in a constant push: the LQR sags by push / k_p; with the observer the
    sag is gone within a few time constants."""
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, stack
    from sim.flight import fly
    from sim.scene import build_scene

    leader = np.array(LEADER_POSITION)
    ref = stack([Hover(leader, n_worlds=1), Hover(leader - [0, 0, 0.6], n_worlds=1)])
    field = _ConstantPush(1.5)
    scene = build_scene()
    plain = fly(scene, ref, [0], 6.0, field=field)[0]
    observed = fly(scene, ref, [0], 6.0, field=field, predictor=DisturbanceObserver())[0]
    assert plain.ok and observed.ok
    tail = slice(-100, None)  # the last 2 s
    sag_plain = np.mean(plain["pos"][tail, 1, 2] - plain["ref_pos"][tail, 1, 2])
    sag_observed = np.mean(observed["pos"][tail, 1, 2] - observed["ref_pos"][tail, 1, 2])
    assert sag_plain < -0.05  # the LQR alone sags (no integral action)
    assert abs(sag_observed) < 0.1 * abs(sag_plain)
    f_hat = observed["f_hat"][tail, 1, 2]
    assert np.mean(f_hat) == pytest.approx(-1.5, abs=0.1)  # the observer's estimate is the push
