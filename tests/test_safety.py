"""The CBF safety filter (`sim.safety`): each pair's barrier is its collision ellipsoid inflated (its h'' derived
right), the barriers hold after one control period in random stacks of mixed kinds, it keeps a stack apart in
closed loop (also under a wrong model), its estimate measures the force felt at the observer's rate and resets
with the worlds, it takes the more restrictive of f_hat and the estimate, it leaves a command with no active
barrier alone bit for bit, its compiled and readable paths agree (and give the QP's optimum; the estimate bit
for bit), the fused tick runs it as the readable path does (its estimates shared), and bad settings are named."""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.optimize import nnls

from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, QUAD, RATES
from downwash_core.state import VehicleStates
from downwash_core.vehicles import as_params, get_vehicle
from downwash_trajectories import Hover, Lemniscate, Line, stack
from sim.flight import fly
from sim.observer import DEFAULT_BANDWIDTH
from sim.presets import make_preset
from sim.safety import (STATE_WIDTH, TOLERANCE, SafetyConfig, SafetyFilter, barrier_radii, cbf_filter_kernel,
                        constraint_rows, estimate_step, realised, record_step)
from sim.scene import build_scene
from sim.simulator import SimConfig, Simulator
from sim.vehicle_params import collision_radii

CFG = SafetyConfig()
L1 = CFG.poles[0]  # 1/s, the slower pole: the safe set is h >= 0, h' + L1 h >= 0
DT = RATES.control_dt
FAST = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SIM = SimConfig()
CRAZYFLIE = as_params(get_vehicle("crazyflie_2_1"))
KINDS = (QUAD, CRAZYFLIE)


def make_filter(quads, config=CFG, **kwargs):
    """The filter for these vehicles with the simulator's own per-pair ellipsoids (`SimConfig`'s radii)."""
    xy, z = collision_radii(quads, SIM.collision_radius_xy, SIM.collision_radius_z)
    return SafetyFilter(config, quads, xy, z, **kwargs)


def radii(filt, V):
    n = len(filt.params) - V
    return filt.params[n - 2 * V * V:n - V * V].reshape(V, V), filt.params[n - V * V:n].reshape(V, V)


def ellipsoid(a, c, dp, dv, da):
    """q, q', q'' of q = sqrt(dp.M dp), M = diag(1/a^2, 1/a^2, 1/c^2), from the chain rule (module doc)."""
    m = np.array([1 / a**2, 1 / a**2, 1 / c**2])
    q = math.sqrt(dp @ (m * dp))
    qd = dp @ (m * dv) / q
    return q, qd, (dv @ (m * dv) + dp @ (m * da) - qd * qd) / q


def fresh_state(W, V, estimate=None):
    """A state with nothing measured (the estimate then counts as it is)."""
    state = np.zeros((W, V, STATE_WIDTH))
    if estimate is not None:
        state[..., 0:3] = estimate
    return state


@pytest.fixture(scope="module")
def scene():
    return build_scene()


BRAKING = 3.5  # m/s^2, the most a drawn stack's pair may ask of the box beyond its drifts (see `stacks`)


@st.composite
def stacks(draw):
    """One world of a vertical stack of 2 or 3 vehicles of the kinds (paper quads, Crazyflies; W = 1): each pair
    outside its inflated ellipsoid and closing no faster than the safe set (h' + l1 h >= 0) and the actuator
    limits allow (`BRAKING`), any relative lateral velocity, commands inside the actuator box, a small predicted
    force and a small estimate."""
    V = draw(st.integers(2, 3))
    unit = st.floats(0.0, 1.0)
    quads = [KINDS[draw(st.integers(0, 1))] for _ in range(V)]
    filt = make_filter(quads)
    a, c = radii(filt, V)
    pos, vel = np.zeros((1, V, 3)), np.zeros((1, V, 3))
    pos[0, :, :2] = 0.1 * (2.0 * np.array([[draw(unit) for _ in range(2)] for _ in range(V)]) - 1.0)
    vel[0, :, :2] = 0.5 * (2.0 * np.array([[draw(unit) for _ in range(2)] for _ in range(V)]) - 1.0)
    pos[0, 0, 2], vel[0, V - 1, 2] = 1.5 + draw(unit), 2.0 * draw(unit) - 1.0
    for i in range(1, V):  # i - 1 above i, by at least the bound's own height (so q > inflation)
        pos[0, i, 2] = pos[0, i - 1, 2] - c[i - 1, i] * (CFG.inflation + 1e-3 + 3.0 * draw(unit))
    for i in range(V - 2, -1, -1):  # the upper one's vertical speed: q' drawn in [-fastest, 1]
        dp, dv = pos[0, i] - pos[0, i + 1], vel[0, i] - vel[0, i + 1]
        m = np.array([1 / a[i, i + 1] ** 2, 1 / a[i, i + 1] ** 2, 1 / c[i, i + 1] ** 2])
        q = math.sqrt(dp @ (m * dp))
        h = q - CFG.inflation
        # the fastest closing: inside the safe set (l1 h), and within the actuator limits: the braking the barrier
        # then asks, about c (k1 |q'| - k0 h) m/s^2, at most BRAKING, so that a stack's pairs together (the top's
        # climb and the bottom's descent, 3.6 + 7.4 m/s^2 for Crazyflies) can give it, drifts included
        fastest = min(L1 * h, (BRAKING / c[i, i + 1] + CFG.k0 * h) / CFG.k1)
        qd = -fastest + (1.0 + fastest) * draw(unit)
        dv[2] = (qd * q - m[0] * dp[0] * dv[0] - m[1] * dp[1] * dv[1]) / (m[2] * dp[2])
        vel[0, i, 2] = vel[0, i + 1, 2] + dv[2]
    frac = np.array([[draw(unit) for _ in range(3)] for _ in range(V)])
    u = (filt.lower + frac * (filt.upper - filt.lower))[None]
    f_hat, estimate = np.zeros((1, V, 3)), np.zeros((1, V, 3))
    f_hat[0, :, 2] = [draw(st.floats(-0.5, 0.5)) for _ in range(V)]
    estimate[0] = [[draw(st.floats(-0.5, 0.5)) for _ in range(3)] for _ in range(V)]
    return filt, pos, vel, u, f_hat, estimate


@FAST
@given(stacks())
def test_after_the_filter_one_control_period_keeps_every_pair_outside_its_inflated_ellipsoid(case):
    """The issue's property, on the ellipsoids: from random stacked states within the actuator limits, the filtered
    commands meet every pair's barrier under both drifts (f_hat and the estimate: it takes the more restrictive),
    and one control period of constant acceleration under either keeps every pair outside its bound."""
    filt, pos, vel, u, f_hat, estimate = case
    V = pos.shape[1]
    out = filt(pos, vel, u, f_hat, fresh_state(1, V, estimate))
    assert filt.filter_into(pos, vel, f_hat, u.copy(), fresh_state(1, V, estimate))[1] == 0, "feasible: none unmet"
    assert np.all(out >= np.minimum(filt.lower, u)) and np.all(out <= np.maximum(filt.upper, u))
    a, c = radii(filt, V)
    for drift in (f_hat, estimate):
        acc = out + drift  # the model's acceleration under this drift
        for i in range(V):
            for j in range(i + 1, V):
                dp, dv, da = pos[0, i] - pos[0, j], vel[0, i] - vel[0, j], acc[0, i] - acc[0, j]
                q, qd, qdd = ellipsoid(a[i, j], c[i, j], dp, dv, da)
                h = q - CFG.inflation
                assert h >= 0.0 and qd + L1 * h >= -1e-9, "(drawn in the safe set)"
                assert (qdd + CFG.k1 * qd + CFG.k0 * h) * c[i, j] >= -1e-7, "the barrier condition"
                for t in np.linspace(0.0, DT, 5):  # the exact motion over one control period
                    q_t, _, _ = ellipsoid(a[i, j], c[i, j], dp + dv * t + 0.5 * da * t * t, dv, da)
                    assert q_t >= CFG.inflation


@FAST
@given(st.integers(0, 2**32 - 1), st.integers(0, 1), st.integers(0, 1))
def test_the_pair_row_is_the_ellipsoids_second_derivative_linear_in_the_commands(seed, ki, kj):
    """h'' = (g / q) n.(u_i - u_j + f_i - f_j) + (dv.M dv - q'^2) / q, derived in the module doc: the row's slack,
    scaled by g / q, is h'' + k1 h' + k0 h of the exact motion (finite differences of q along it)."""
    rng = np.random.default_rng(seed)
    quads = [KINDS[ki], KINDS[kj]]
    filt = make_filter(quads)
    a, c = radii(filt, 2)
    pos = np.array([[[0.0, 0.0, 1.5]], [[0.0, 0.0, 1.0]]]).reshape(1, 2, 3) + rng.normal(0.0, 0.1, (1, 2, 3))
    vel, u = rng.normal(0.0, 0.5, (1, 2, 3)), rng.normal(0.0, 1.0, (1, 2, 3))
    A, b = constraint_rows(filt.params, filt.lower, filt.upper, pos, vel, np.zeros_like(u), u)
    slack = A[0, 0] @ u[0].reshape(-1) - b[0, 0]
    dp, dv, da = pos[0, 0] - pos[0, 1], vel[0, 0] - vel[0, 1], u[0, 0] - u[0, 1]
    m = np.array([1 / a[0, 1] ** 2, 1 / a[0, 1] ** 2, 1 / c[0, 1] ** 2])
    q_of = lambda t: math.sqrt((dp + dv * t + 0.5 * da * t * t) @ (m * (dp + dv * t + 0.5 * da * t * t)))
    eps = 1e-4
    q, qd, qdd = q_of(0.0), (q_of(eps) - q_of(-eps)) / (2 * eps), (q_of(eps) - 2 * q_of(0.0) + q_of(-eps)) / eps**2
    g_over_q = np.linalg.norm(m * dp) / q
    expected = qdd + CFG.k1 * qd + CFG.k0 * (q - CFG.inflation)
    assert slack * g_over_q == pytest.approx(expected, rel=1e-4, abs=1e-4 * (1 + abs(qdd)))
    assert np.linalg.norm(A[0, 0]) == pytest.approx(math.sqrt(2.0))  # (unit normals: the row is in m/s^2)


@FAST
@given(st.integers(1, 4), st.integers(1, 3), st.integers(0, 2**32 - 1), st.floats(0.2, 1.5), st.booleans())
def test_compiled_equals_readable_and_both_give_the_qps_optimum(W, V, seed, spread, mixed):
    """Random clusters (many barriers active, commands partly outside the box) with an estimate measured the tick
    before: the estimate and the velocities it records are the same bits on both paths; in every world where the
    readable filter meets every barrier the compiled one does too, its commands equal the NumPy ones and are the
    least-squares optimum (feasible; u - u_nom a non-negative combination of the normals of the barriers it meets
    with equality: the KKT conditions, checked with scipy's NNLS). (Where barriers are left unmet, infeasible within
    the box, there is no optimum to agree on: the paths' rounding may then leave different ones unmet; both stay
    within the box widened to the nominal commands.)"""
    rng = np.random.default_rng(seed)
    quads = [KINDS[int(k)] for k in rng.integers(0, 2 if mixed else 1, V)]
    filt = make_filter(quads)
    pos = rng.normal(0.0, spread * 0.3, (W, V, 3)) + [0.0, 0.0, 1.0]
    vel, u, f_hat = rng.normal(0.0, 1.0, (W, V, 3)), rng.normal(0.0, 4.0, (W, V, 3)), rng.normal(0.0, 0.5, (W, V, 3))
    state = fresh_state(W, V)
    state[..., 3:6], state[..., 6:9] = vel + rng.normal(0.0, 0.02, (W, V, 3)), rng.normal(0.0, 2.0, (W, V, 3))
    state[..., 0:3], state[..., 9] = rng.normal(0.0, 1.0, (W, V, 3)), rng.random((W, V)) < 0.8
    compiled = state.copy()
    out = filt(pos, vel, u, f_hat, compiled)  # (all worlds in one call)
    measured = state.copy()
    estimate_step(filt.params, vel, measured)
    A, b = constraint_rows(filt.params, filt.lower, filt.upper, pos, vel, f_hat, u, measured[..., 0:3])
    for w in range(W):
        one = slice(w, w + 1)
        readable = state[one].copy()
        ref, unmet = filt.reference(pos[one], vel[one], u[one], f_hat[one], readable)
        assert np.array_equal(compiled[one][..., [0, 1, 2, 3, 4, 5, 9]], readable[..., [0, 1, 2, 3, 4, 5, 9]])
        assert np.all(out[w] >= np.minimum(filt.lower, u[w])) and np.all(out[w] <= np.maximum(filt.upper, u[w]))
        assert np.all(ref >= np.minimum(filt.lower, u[one])) and np.all(ref <= np.maximum(filt.upper, u[one]))
        if unmet:
            continue
        assert filt.filter_into(pos[one], vel[one], f_hat[one], u[one].copy(), state[one].copy())[1] == 0
        np.testing.assert_allclose(out[w], ref[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(compiled[w, :, 6:9], readable[0, :, 6:9], rtol=1e-9, atol=1e-9)
        x, x0 = out[w].reshape(-1), u[w].reshape(-1)
        slack = A[w] @ x - b[w]
        assert slack.min() >= -1e-7
        tight = slack < 1e-7
        if tight.any():
            _, residual = nnls(A[w][tight].T, x - x0)
            assert residual < 1e-6
        else:
            assert np.array_equal(x, x0)


@FAST
@given(st.integers(1, 3), st.integers(1, 4), st.integers(0, 2**32 - 1), st.floats(0.1, 40.0))
def test_the_estimate_and_what_it_records_are_the_kernels_bits(W, V, seed, scale):
    """Where no barrier acts (vehicles far apart), the compiled filter's state is `estimate_step` then
    `record_step` (`realised`: the tilt cone, the floor, the full thrust) bit for bit, commands of any size."""
    rng = np.random.default_rng(seed)
    quads = [KINDS[int(k)] for k in rng.integers(0, 2, V)]
    filt = make_filter(quads)
    vel, u = rng.normal(0.0, 0.1, (W, V, 3)), rng.normal(0.0, scale, (W, V, 3))
    pos = np.zeros((W, V, 3))
    pos[..., 2] = (np.arange(V) + 1.0) * (10.0 + 2.0 * np.abs(u).max())  # far apart, far up: every barrier slack
    state = fresh_state(W, V, rng.normal(0.0, 1.0, (W, V, 3)))
    state[..., 3:6], state[..., 6:9] = rng.normal(0.0, 0.1, (W, V, 3)), rng.normal(0.0, scale, (W, V, 3))
    state[..., 9] = 1.0
    compiled, readable = state.copy(), state.copy()
    same = u.copy()
    assert filt.filter_into(pos, vel, np.zeros((W, V, 3)), same, compiled) == (0, 0) and np.array_equal(same, u)
    estimate_step(filt.params, vel, readable)
    record_step(filt.params, vel, u, readable)
    assert np.array_equal(compiled, readable)
    got = realised(filt.params, u)
    f = got + [0.0, 0.0, GRAVITY]
    top = np.array([q.thrust_to_weight * GRAVITY for q in quads])
    assert np.all(np.linalg.norm(f, axis=-1) <= top * (1 + 1e-12))
    assert np.all(np.hypot(f[..., 0], f[..., 1]) <= math.tan(filt.max_tilt) * f[..., 2] * (1 + 1e-12) + 1e-12)
    small = (np.linalg.norm(u + [0.0, 0.0, GRAVITY], axis=-1) < 0.5 * top) & (u[..., 2] + GRAVITY > filt.min_vertical) \
        & (np.hypot(u[..., 0], u[..., 1]) < math.tan(filt.max_tilt) * (u[..., 2] + GRAVITY))
    assert np.array_equal(got[small], u[small])  # (a command within the limits is itself)


def test_the_estimate_measures_a_constant_force_at_the_observers_rate_and_resets_with_its_worlds():
    """A constant force F on every vehicle, the commands realised: after n calls (the first only records) the
    estimate is F (1 - exp(-bandwidth (n - 1) dt)), `sim.observer`'s law with its DEFAULT_BANDWIDTH; `reset` clears
    the worlds named and leaves the others."""
    assert CFG.bandwidth == DEFAULT_BANDWIDTH
    W, V = 3, 2
    filt = make_filter([QUAD] * V, n_worlds=W)
    pos = np.zeros((W, V, 3))
    pos[..., 2] = [5.0, 3.0]
    vel = np.zeros((W, V, 3))
    force = np.array([0.3, -0.2, -1.5])
    for n in range(1, 31):
        u = np.tile([0.1, -0.1, 0.4], (W, V, 1))
        filt.filter_into(pos, vel, np.zeros((W, V, 3)), u)
        vel = vel + (u + force) * DT
        expected = force * (1.0 - math.exp(-DEFAULT_BANDWIDTH * (n - 1) * DT))
        np.testing.assert_allclose(filt.state[..., 0:3], np.broadcast_to(expected, (W, V, 3)), rtol=1e-9, atol=1e-12)
    kept = filt.state[[0, 2]].copy()
    filt.reset([1])
    assert not filt.state[1].any() and np.array_equal(filt.state[[0, 2]], kept)
    filt.reset()
    assert not filt.state.any()


def test_each_barrier_takes_the_more_restrictive_of_f_hat_and_the_estimate():
    """Two paper quads stacked near the bound, the model predicting no force: an estimate pushing the upper one down
    (towards the lower) changes the filtered commands; one pushing it up (apart) changes nothing, bit for bit; and
    with the roles swapped (the model pushing them together, the estimate not) the model's counts."""
    filt = make_filter([QUAD, QUAD])
    c = radii(filt, 2)[1][0, 1]
    pos = np.array([[[0.0, 0.0, 1.5], [0.0, 0.0, 1.5 - c * (CFG.inflation + 0.3)]]])
    vel, u, none = np.zeros((1, 2, 3)), np.zeros((1, 2, 3)), np.zeros((1, 2, 3))
    push = np.zeros((1, 2, 3))
    push[0, 0, 2] = -6.0  # on the upper vehicle, downwards: towards the lower one
    base = filt(pos, vel, u, none, fresh_state(1, 2))
    assert np.array_equal(base, u)  # (nothing acts without a force)
    towards = filt(pos, vel, u, none, fresh_state(1, 2, push))
    assert towards[0, 0, 2] - towards[0, 1, 2] > 0.5  # the filter pulls them apart
    assert np.array_equal(filt(pos, vel, u, none, fresh_state(1, 2, -push)), base)
    assert np.array_equal(filt(pos, vel, u, push, fresh_state(1, 2)), towards)  # (the model's push counts alike)
    assert np.array_equal(filt(pos, vel, u, push, fresh_state(1, 2, -push)), towards)


def test_a_command_with_no_active_barrier_is_returned_unchanged_bit_for_bit():
    rng = np.random.default_rng(5)
    W, V = 32, 3
    filt = make_filter([QUAD] * V, n_worlds=W)
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


BOUND = CFG.inflation * SIM.collision_radius_z  # m, two paper quads straight above each other: the vertical bound


def _gaps(sim, n_ticks):
    return np.array([np.array(row["pos"][:, 0, 2] - row["pos"][:, 1, 2]) for row in
                     (sim.tick() for _ in range(n_ticks))])


def test_closed_loop_the_filter_keeps_the_stack_apart_and_without_it_they_collide(scene):
    """Without wake (the gap is the commands' doing alone): the upper vehicle descends at 0.5 m/s from 0.6 m
    above the lower one (inside the safe set: h' + l1 h >= 0). Over 2 s the true gap never falls below the bound
    (the inflated ellipsoid straight above) with the filter; without it the vehicles collide."""
    W = 3
    gaps = {}
    for safety in (None, CFG):
        sim = Simulator(scene, _descend(W), [1, 2, 3], safety=safety, field_enabled=np.zeros(W, bool))
        gaps[safety is not None] = _gaps(sim, 100)
        assert (sim.status == 0).all() == (safety is not None), sim.message
    assert gaps[True].min() >= BOUND
    assert gaps[True][-1].max() < BOUND + 0.05  # (held near the bound, not far away)
    assert gaps[False].min() < SIM.collision_radius_z


class _WrongModel:
    """A model that predicts the lower vehicle pushed down hard where nothing pushes it: the controller's
    compensation then drives it up into the vehicle above."""

    def __call__(self, estimated: VehicleStates, true: VehicleStates | None = None) -> np.ndarray:
        out = np.zeros(estimated.pos.shape)
        out[:, 1, 2] = -8.0
        return out


def test_a_wrong_model_does_not_close_the_stack_the_estimate_holds_the_barrier(scene):
    """The model predicts a push the lower vehicle does not feel: trusting it, a barrier would let the climb the
    compensation causes close the stack. With the filter's estimate the gap stays near the bound and they never
    collide; without the filter they do."""
    W = 2
    ref = stack([Hover([0.0, 0.0, 2.5], n_worlds=W), Hover([0.0, 0.0, 1.9], n_worlds=W)])
    gaps = {}
    for safety in (None, CFG):
        sim = Simulator(scene, ref, [3, 4], safety=safety, predictor=_WrongModel(), field_enabled=np.zeros(W, bool))
        gaps[safety is not None] = _gaps(sim, 100)
        assert (sim.status == 0).all() == (safety is not None), sim.message
    assert gaps[True].min() >= BOUND - 0.02  # (the estimate's lag: within 2 cm of the bound, far from a collision)
    assert gaps[False].min() < SIM.collision_radius_z


@pytest.mark.parametrize("W, n_threads", [(1, 1), (16, 2)])
def test_the_fused_tick_runs_the_filter_as_the_readable_path(scene, W, n_threads):
    """A flight where the filter acts (with the field, actions, a residual, a reset of some worlds midway) takes the
    fused path and flies the readable path's rows bit for bit, the filter's estimates too (one array, by address);
    its logs name the filter's settings."""
    rows, sims = [], []
    for fast in (True, False):
        sim = Simulator(scene, _descend(W), list(range(W)), safety=CFG, fast=fast, n_threads=n_threads)
        assert (sim._plan is not None) == fast
        flown = []
        for k in range(60):
            if k == 30:
                sim.reset(np.arange(0, W, 3))
                assert not sim._safety_filter.state[np.arange(0, W, 3)].any()
            flown.append(dict(sim.tick(residual=np.full((W, 2, 3), 0.1) if k % 7 == 3 else None)))
        rows.append(flown)
        sims.append(sim)
    for a, b in zip(*rows):
        for name in a:
            assert np.array_equal(a[name], b[name], equal_nan=True), name
    assert np.array_equal(sims[0].physics.qpos, sims[1].physics.qpos)
    assert np.array_equal(sims[0]._safety_filter.state, sims[1]._safety_filter.state)
    assert sims[0]._safety_filter.state[..., 9].all()  # (every world measured since its reset)
    assert min(row["pos"][:, 0, 2].min() - row["pos"][:, 1, 2].max() for row in rows[0]) >= BOUND - 0.01
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
    rows = [[dict(sim.tick()) for _ in range(60)] for sim in sims]
    assert rows[0][-1]["ref_pos"][:, 0, 2].max() - 1.9 < BOUND - 0.05  # (the references close in: it acts)
    for a, b in zip(*rows):
        for name in ("pos", "quat", "u_cmd"):
            np.testing.assert_allclose(a[name], b[name], rtol=0, atol=1e-7, err_msg=name)
    assert min(row["pos"][:, 0, 2].min() - row["pos"][:, 1, 2].max() for row in rows[0]) >= BOUND


@FAST
@given(st.floats(1.0, 4.0), st.floats(0.01, 0.3), st.floats(0.02, 0.3), st.floats(0.5, 4.0), st.integers(0, 2**32 - 1))
def test_a_capped_margin_is_the_pairs_own_inflation_and_an_uncapped_one_keeps_its_radii(inflation, max_margin, c,
                                                                                        aspect, seed):
    """`barrier_radii`: where (inflation - 1) c exceeds max_margin the scaled radii give the same constraint rows as
    the pair's own inflation 1 + max_margin / c on its collision radii (so the surface lies max_margin beyond the
    ellipsoid); elsewhere the radii pass bit for bit."""
    xy, z = np.full((2, 2), aspect * c), np.full((2, 2), c)
    capped = SafetyConfig(inflation=inflation, max_margin=max_margin)
    bx, bz = barrier_radii(capped, xy, z)
    if (inflation - 1.0) * c <= max_margin:
        assert np.array_equal(bx, xy) and np.array_equal(bz, z)
        return
    assert bz[0, 1] < c and math.isclose(bz[0, 1] / c, bx[0, 1] / (aspect * c), rel_tol=1e-12)
    own = SafetyConfig(inflation=1.0 + max_margin / c, max_margin=100.0)
    quads = [QUAD, QUAD]
    rng = np.random.default_rng(seed)
    pos = np.array([[[0.0, 0.0, 1.5], [0.0, 0.0, 1.5 - c * (1.2 + max_margin / c)]]]) + 0.02 * rng.normal(size=(1, 2, 3))
    vel, f_hat, u = rng.normal(size=(1, 2, 3)), rng.normal(size=(1, 2, 3)), rng.normal(size=(1, 2, 3))
    rows = [constraint_rows(f.params, f.lower, f.upper, pos, vel, f_hat, u)
            for f in (SafetyFilter(cfg, quads, xy, z) for cfg in (capped, own))]
    np.testing.assert_allclose(rows[0][0], rows[1][0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(rows[0][1], rows[1][1], rtol=1e-9, atol=1e-9)


def test_the_filter_reads_each_pairs_ellipsoid_from_the_simulators_vehicles():
    """The simulator hands the filter its per-pair radii (`sim.vehicle_params`, kinds and `SimConfig` included), the
    control period and one row of estimates per world."""
    preset = make_preset("stack3").with_kinds(["crazyflie_2_1", "paper_quad", "crazyflie_2_1"])
    scene, ref = preset.scene(), preset.reference(2)
    config = SimConfig(collision_radius_xy=0.3, collision_radius_z=0.1)
    sim = Simulator(scene, ref, [0, 1], safety=CFG, config=config)
    filt = sim._safety_filter
    a, c = radii(filt, 3)
    barrier = barrier_radii(CFG, sim.vehicle_params.collision_xy, sim.vehicle_params.collision_z)
    assert np.array_equal(a, barrier[0]) and np.array_equal(c, barrier[1])
    off = ~np.eye(3, dtype=bool)  # each pair's margin, 1.5 c, is under max_margin: the radii pass as they are
    assert np.array_equal(a[off], sim.vehicle_params.collision_xy[off])
    assert a[0, 2] < a[0, 1] < 0.3 and filt.state.shape == (2, 3, STATE_WIDTH) and filt.params[5] == DT


@pytest.mark.parametrize("kwargs, named", [
    ({"inflation": 0.5}, "inflation"), ({"inflation": float("nan")}, "inflation"),
    ({"inflation": float("inf")}, "inflation"), ({"ground_clearance": -1.0}, "ground_clearance"),
    ({"max_margin": 0.0}, "max_margin"),
    ({"k0": 0.0}, "k0"), ({"k1": "fast"}, "k1"), ({"k0": 9.0, "k1": 5.0}, "k1"), ({"bandwidth": 0.0}, "bandwidth"),
    ({"bandwidth": True}, "bandwidth"), ({"thrust_fraction": 1.5}, "thrust_fraction"),
    ({"thrust_fraction": True}, "thrust_fraction"),
])
def test_bad_settings_are_named_with_their_allowed_range(kwargs, named):
    with pytest.raises(ConfigError, match=f"SafetyConfig.{named}: .*allowed"):
        SafetyConfig(**kwargs)


def test_a_box_in_which_a_vehicle_cannot_hover_bad_radii_and_a_wrong_type_are_named(scene):
    with pytest.raises(ConfigError, match=r"SafetyConfig.thrust_fraction: .*allowed \("):
        make_filter([CRAZYFLIE], SafetyConfig(thrust_fraction=0.6))
    make_filter([CRAZYFLIE])  # (0.9 of it: it can)
    with pytest.raises(ConfigError, match=r"collision radii as \(2, 2\)"):
        SafetyFilter(CFG, [QUAD, QUAD], np.ones((3, 3)), np.ones((3, 3)))
    with pytest.raises(ConfigError, match="radii must be finite and > 0"):
        SafetyFilter(CFG, [QUAD, QUAD], np.zeros((2, 2)), np.ones((2, 2)))
    with pytest.raises(ConfigError, match="safety: expected a sim.safety.SafetyConfig"):
        Simulator(scene, _descend(1), [0], safety={"inflation": 2.0})
    with pytest.raises(ConfigError, match="the estimate's state has shape"):
        make_filter([QUAD, QUAD], n_worlds=2).filter_into(*np.zeros((4, 3, 2, 3)))
    assert math.isclose(sum(CFG.poles), CFG.k1) and math.isclose(CFG.poles[0] * CFG.poles[1], CFG.k0)
    assert TOLERANCE > 0 and cbf_filter_kernel is not None
