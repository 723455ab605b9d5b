"""The CBF safety filter (`sim.safety`): its barriers hold after one control period, it keeps a stack apart in
closed loop, it leaves a command with no active barrier alone bit for bit, its compiled and readable paths
agree (and give the QP's optimum), the fused tick runs it as the readable path does, and bad settings are named."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls

from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError
from downwash_core.params import QUAD, RATES
from downwash_core.vehicles import get_vehicle
from downwash_trajectories import Hover, Lemniscate, Line, stack
from sim.flight import fly
from sim.safety import TOLERANCE, SafetyConfig, SafetyFilter, constraint_rows
from sim.scene import build_scene
from sim.simulator import Simulator

CFG = SafetyConfig()
L1 = CFG.poles[0]  # 1/s, the slower pole: the safe set is h >= 0, h' + L1 h >= 0
DT = RATES.control_dt
FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def scene():
    return build_scene()


@st.composite
def stacks(draw, active=True):
    """One world of a vertical stack of 2 or 3 paper quads (W = 1): gaps above the bound, closing no faster
    than the safe set allows (h' + l1 h >= 0), commands inside the actuator box, a small predicted force."""
    V = draw(st.integers(2, 3))
    unit = st.floats(0.0, 1.0)
    filt = SafetyFilter(CFG, [QUAD] * V)
    pos, vel = np.zeros((1, V, 3)), np.zeros((1, V, 3))
    pos[0, 0, 2], vel[0, V - 1, 2] = 1.5 + draw(unit), 2.0 * draw(unit) - 1.0
    for i in range(1, V):
        pos[0, i, 2] = pos[0, i - 1, 2] - CFG.vertical_gap - 1e-3 - 0.6 * draw(unit)
    for i in range(V - 2, -1, -1):  # the upper one's speed relative to the one below
        h = pos[0, i, 2] - pos[0, i + 1, 2] - CFG.vertical_gap
        vel[0, i, 2] = vel[0, i + 1, 2] + (-L1 * h + (1.0 + L1 * h) * draw(unit))
    pos[0, :, :2] = 0.1 * (2.0 * np.array([[draw(unit) for _ in range(2)] for _ in range(V)]) - 1.0)
    frac = np.array([[draw(unit) for _ in range(3)] for _ in range(V)])
    u = (filt.lower + frac * (filt.upper - filt.lower))[None]
    f_hat = np.zeros((1, V, 3))
    f_hat[0, :, 2] = [draw(st.floats(-0.5, 0.5)) for _ in range(V)]
    return filt, pos, vel, u, f_hat


@FAST
@given(stacks())
def test_after_the_filter_one_control_period_keeps_every_stacked_pair_above_its_bound(case):
    filt, pos, vel, u, f_hat = case
    out = filt(pos, vel, u, f_hat)
    assert filt.filter_into(pos, vel, f_hat, u.copy())[1] == 0, "feasible within the box: no barrier left unmet"
    assert np.all(out >= np.minimum(filt.lower, u) - 1e-12) and np.all(out <= np.maximum(filt.upper, u) + 1e-12)
    acc = out + f_hat  # the model's acceleration
    V = pos.shape[1]
    for i in range(V):
        for j in range(i + 1, V):  # i above j
            h = pos[0, i, 2] - pos[0, j, 2] - CFG.vertical_gap
            hd, hdd = vel[0, i, 2] - vel[0, j, 2], acc[0, i, 2] - acc[0, j, 2]
            assert hdd + CFG.k1 * hd + CFG.k0 * h >= -1e-7, "the barrier condition"
            # the closed-form prediction over one control period at constant acceleration stays in h >= 0
            # (from h >= 0, h' + l1 h >= 0 and the barrier: h(dt) >= h (1 - l1 dt + (l1 dt)^2 / 2) > 0)
            assert h + hd * DT + 0.5 * hdd * DT * DT >= 0.0


@FAST
@given(st.integers(1, 4), st.integers(1, 3), st.integers(0, 2**32 - 1), st.floats(0.2, 1.5))
def test_compiled_equals_readable_and_both_give_the_qps_optimum(W, V, seed, spread):
    """Random clusters (many barriers active, commands partly outside the box): the compiled filter equals the
    NumPy one, and its output is the least-squares optimum (feasible; u - u_nom a non-negative combination of
    the normals of the barriers it meets with equality: the KKT conditions, checked with scipy's NNLS)."""
    rng = np.random.default_rng(seed)
    filt = SafetyFilter(CFG, [QUAD] * V)
    pos = rng.normal(0.0, spread * 0.3, (W, V, 3)) + [0.0, 0.0, 1.0]
    vel, u, f_hat = rng.normal(0.0, 1.0, (W, V, 3)), rng.normal(0.0, 4.0, (W, V, 3)), rng.normal(0.0, 0.5, (W, V, 3))
    out = filt(pos, vel, u, f_hat)
    ref, unmet = filt.reference(pos, vel, u, f_hat)
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-9)
    assert filt.filter_into(pos, vel, f_hat, u.copy())[1] == unmet
    if unmet:
        return
    A, b = constraint_rows(CFG, filt.lower, filt.upper, pos, vel, f_hat, u)
    for w in range(W):
        x, x0 = out[w].reshape(-1), u[w].reshape(-1)
        slack = A[w] @ x - b[w]
        assert slack.min() >= -1e-7
        tight = slack < 1e-7
        if tight.any():
            lam, residual = nnls(A[w][tight].T, x - x0)
            assert residual < 1e-6
        else:
            assert np.array_equal(x, x0)


def test_a_command_with_no_active_barrier_is_returned_unchanged_bit_for_bit():
    rng = np.random.default_rng(5)
    W, V = 32, 3
    filt = SafetyFilter(CFG, [QUAD] * V)
    pos = np.zeros((W, V, 3))
    pos[..., 2] = [3.0, 2.0, 1.0]  # 1 m apart, hovering, commands small: every barrier is slack
    pos[..., :2] = rng.normal(0.0, 0.05, (W, V, 2))
    vel, u = rng.normal(0.0, 0.05, (W, V, 3)), rng.normal(0.0, 0.3, (W, V, 3))
    u[0, 0] = [1e3, -1e3, 1e3]  # far outside the box, no barrier violated: not clipped either
    same = u.copy()
    assert filt.filter_into(pos, vel, np.zeros((W, V, 3)), same) == (0, 0)
    assert np.array_equal(same, u)
    ref, _ = filt.reference(pos, vel, u)
    assert np.array_equal(ref, u)


def _descend(W, v=-0.5):
    """The upper vehicle commanded straight down onto the lower one (0.6 m below), which hovers."""
    return stack([Line([0.0, 0.0, 2.5], [0.0, 0.0, v], n_worlds=W), Hover([0.0, 0.0, 1.9], n_worlds=W)])


def _gaps(sim, n_ticks):
    return np.array([np.array(row["pos"][:, 0, 2] - row["pos"][:, 1, 2]) for row in
                     (sim.tick() for _ in range(n_ticks))])


def test_closed_loop_the_filter_keeps_the_stack_apart_and_without_it_they_collide(scene):
    """Without wake (the gap is the commands' doing alone): the upper vehicle descends at 0.5 m/s from 0.6 m
    above the lower one (inside the safe set: h' + l1 h >= 0). Over 2 s the true gap never falls below the bound
    with the filter; without it the vehicles collide."""
    W = 3
    gaps = {}
    for safety in (None, CFG):
        sim = Simulator(scene, _descend(W), [1, 2, 3], safety=safety, field_enabled=np.zeros(W, bool))
        gaps[safety is not None] = _gaps(sim, 100)
        assert (sim.status == 0).all() == (safety is not None), sim.message
    assert gaps[True].min() >= CFG.vertical_gap
    assert gaps[True][-1].max() < CFG.vertical_gap + 0.05  # (held near the bound, not far away)
    assert gaps[False].min() < CFG.vertical_gap


@pytest.mark.parametrize("W, n_threads", [(1, 1), (16, 2)])
def test_the_fused_tick_runs_the_filter_as_the_readable_path(scene, W, n_threads):
    """A flight where the filter acts (with the field, actions, a residual) takes the fused path and flies the
    readable path's rows bit for bit; its logs name the filter's settings."""
    rows, sims = [], []
    for fast in (True, False):
        sim = Simulator(scene, _descend(W), list(range(W)), safety=CFG, fast=fast, n_threads=n_threads)
        assert (sim._plan is not None) == fast
        rows.append([dict(sim.tick(residual=np.full((W, 2, 3), 0.1) if k % 7 == 3 else None)) for k in range(60)])
        sims.append(sim)
    for a, b in zip(*rows):
        for name in a:
            assert np.array_equal(a[name], b[name], equal_nan=True), name
    assert np.array_equal(sims[0].physics.qpos, sims[1].physics.qpos)
    assert min(row["pos"][:, 0, 2].min() - row["pos"][:, 1, 2].max() for row in rows[0]) >= CFG.vertical_gap - 0.01
    logs = fly(scene, _descend(1), [0], 0.1, safety=CFG)
    assert logs[0].meta["safety"] == CFG.describe()
    assert "safety" not in fly(scene, _descend(1), [0], 0.1)[0].meta


def test_a_flight_where_no_barrier_is_active_is_todays_flight(scene):
    """The pair's lemniscate 0.6 m beneath a hovering leader activates nothing: with the filter on it flies
    bit for bit as without it (the filter writes nothing when no barrier is active)."""
    W = 2
    ref = stack([Hover([0.0, 0.0, 2.5], n_worlds=W), Lemniscate([0.0, 0.0, 1.9], n_worlds=W)])
    sims = [Simulator(scene, ref, [4, 5], safety=s) for s in (None, CFG)]
    rows = [[dict(sim.tick()) for _ in range(50)] for sim in sims]
    for a, b in zip(*rows):
        for name in a:
            assert np.array_equal(a[name], b[name]), name


def test_another_controller_gets_feedback_linearisation_again_towards_its_own_heading(scene):
    """A controller the filter does not know (here an LQR subclass, flown on the readable path) gets
    `attitude_setpoint` on the filtered commands, towards the heading of its own set-point: the same flight, up to
    rounding, as the LQR's own step run again (the exact path)."""
    class Other(FeedbackLinearisedLQR):
        pass

    sims = [Simulator(scene, _descend(2), [7, 8], safety=CFG, controller=c, fast=False)
            for c in (Other(), FeedbackLinearisedLQR())]  # (headings: the estimates' noise and the LQR's yaw rate)
    rows = [[dict(sim.tick()) for _ in range(40)] for sim in sims]
    assert rows[0][-1]["ref_pos"][:, 0, 2].max() - 1.9 < CFG.vertical_gap - 0.05  # (the references close in: it acts)
    for a, b in zip(*rows):
        for name in ("pos", "quat", "u_cmd"):
            np.testing.assert_allclose(a[name], b[name], rtol=0, atol=1e-7, err_msg=name)
    assert min(row["pos"][:, 0, 2].min() - row["pos"][:, 1, 2].max() for row in rows[0]) >= CFG.vertical_gap


@pytest.mark.parametrize("kwargs, named", [
    ({"vertical_gap": 0.0}, "vertical_gap"), ({"vertical_gap": -0.1}, "vertical_gap"),
    ({"stack_radius": float("nan")}, "stack_radius"), ({"min_distance": float("inf")}, "min_distance"),
    ({"ground_clearance": -1.0}, "ground_clearance"), ({"k0": 0.0}, "k0"), ({"k1": "fast"}, "k1"),
    ({"k0": 9.0, "k1": 5.0}, "k1"), ({"thrust_fraction": 1.5}, "thrust_fraction"),
    ({"thrust_fraction": True}, "thrust_fraction"),
])
def test_bad_settings_are_named_with_their_allowed_range(kwargs, named):
    with pytest.raises(ConfigError, match=f"SafetyConfig.{named}: .*allowed"):
        SafetyConfig(**kwargs)


def test_a_box_in_which_a_vehicle_cannot_hover_and_a_wrong_type_are_named(scene):
    weak = get_vehicle("crazyflie_2_1")  # thrust-to-weight 1.53
    with pytest.raises(ConfigError, match=r"SafetyConfig.thrust_fraction: .*allowed \("):
        SafetyFilter(SafetyConfig(thrust_fraction=0.6), [weak])
    SafetyFilter(SafetyConfig(), [weak])  # (0.9 of it: it can)
    with pytest.raises(ConfigError, match="safety: expected a sim.safety.SafetyConfig"):
        Simulator(scene, _descend(1), [0], safety={"vertical_gap": 0.3})
    assert math.isclose(sum(CFG.poles), CFG.k1) and math.isclose(CFG.poles[0] * CFG.poles[1], CFG.k0)
    assert TOLERANCE > 0
