"""Ambient wind in the loop: off changes nothing, determinism, batches, drag, convection of the wakes."""

import numpy as np
import pytest

from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError
from downwash_core.geometry import quat_to_mat
from downwash_core.params import QUAD
from sim.estimation import MocapConfig, MocapKalmanFilter
from sim.field import DownwashField, pairwise_field
from sim.flight import fly
from sim.logs import ARRAY_SPECS
from sim.predictor import OraclePredictor
from sim.scene import build_scene
from sim.passes import wind_advance_kernel, wind_sense_kernel
from sim.simulator import WIND_STREAM, Simulator
from sim.wind import AIRFRAME, DrydenWind, drag_acceleration
from downwash_trajectories import Hover, Lemniscate, stack

LEADER = np.array([0.0, 0.0, 2.5])
GUSTY = DrydenWind(mean=(2.0, -1.0, 0.0), w20=6.0)


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _lemniscate(W, sep=0.6):
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, sep], n_worlds=W)])


def _same(a, b, names):
    for k in names:
        assert np.array_equal(a[k], b[k]), k


@pytest.mark.parametrize("fast", [True, False])
def test_wind_off_is_bit_identical_to_no_wind(scene, fast):
    oracle = OraclePredictor(DownwashField())
    base = fly(scene, _lemniscate(1), [4], 1.5, predictor=oracle, fast=fast)[0]
    for wind in (None, DrydenWind(), DrydenWind(altitude=10.0, min_airspeed=3.0)):
        log = fly(scene, _lemniscate(1), [4], 1.5, predictor=oracle, wind=wind, fast=fast)[0]
        assert set(log.arrays) == set(ARRAY_SPECS)  # no wind rows
        _same(log, base, ARRAY_SPECS)
    sim = Simulator(scene, _lemniscate(1), [4], wind=DrydenWind(), fast=fast)
    assert set(sim.tick()) == set(ARRAY_SPECS)


def test_determinism_and_streams(scene):
    a = fly(scene, _lemniscate(1), [7], 2.0, wind=GUSTY)[0]
    b = fly(scene, _lemniscate(1), [7], 2.0, wind=GUSTY)[0]
    _same(a, b, list(ARRAY_SPECS) + ["wind", "wind_acc"])
    c = fly(scene, _lemniscate(1), [8], 2.0, wind=GUSTY)[0]
    assert not np.array_equal(a["wind"], c["wind"])
    # the motion-capture noise is the same stream as without wind: the wind has its own generator
    still = fly(scene, _lemniscate(1), [7], 2.0)[0]
    np.testing.assert_array_equal(a["mocap_pos"][0], still["mocap_pos"][0])
    assert a.meta["wind"] == GUSTY.describe() and "wind" not in still.meta
    # one gust state per world, started stationary from default_rng([seed, WIND_STREAM])
    sim = Simulator(scene, _lemniscate(2), [7, 9], wind=GUSTY)
    for w, seed in enumerate([7, 9]):
        xi = np.random.default_rng([seed, WIND_STREAM]).standard_normal((3, 2))
        np.testing.assert_array_equal(sim.gust_state[w], GUSTY.stationary_state(xi))
    row = sim.tick()
    assert np.array_equal(row["wind"][:, 0], row["wind"][:, 1])  # shared by the vehicles of a world
    assert not np.array_equal(row["wind"][0], row["wind"][1])


@pytest.mark.parametrize("fast", [True, False])
def test_batched_equals_serial_with_wind(scene, fast):
    seeds = [3, 4, 5]
    names = list(ARRAY_SPECS) + ["wind", "wind_acc"]
    batched = fly(scene, _lemniscate(3), seeds, 1.5, wind=GUSTY, predictor=OraclePredictor(DownwashField()), fast=fast)
    for w, s in enumerate(seeds):
        single = fly(scene, _lemniscate(1), [s], 1.5, wind=GUSTY, predictor=OraclePredictor(DownwashField()), fast=fast)[0]
        _same(batched[w], single, names)


def test_logged_drag_is_the_drag_law_and_the_wind_is_mean_plus_gust(scene):
    log = fly(scene, _lemniscate(1), [2], 2.0, wind=GUSTY)[0]
    want = drag_acceleration(log["wind"], log["vel"], QUAD.mass, AIRFRAME.drag_coefficient,
                             AIRFRAME.reference_area, AIRFRAME.air_density)
    np.testing.assert_allclose(log["wind_acc"], want, rtol=1e-14, atol=1e-17)
    gust = log["wind"] - np.array(GUSTY.mean)
    assert 0.05 < np.abs(gust).max() < 5 * GUSTY.scales()["sigma_u"]
    calm = fly(scene, _lemniscate(1), [2], 1.0, wind=DrydenWind(mean=(2.0, -1.0, 0.0)))[0]
    assert np.array_equal(calm["wind"], np.broadcast_to([2.0, -1.0, 0.0], calm["wind"].shape))


def test_a_steady_wind_pushes_hovering_vehicles_downwind_by_the_lqr_offset(scene):
    """Constant drag d on a hovering vehicle: the LQR (no integral) settles at e = (d - Kv v_est) / Kp
    on its estimates, and the Kalman filter, which does not know d, is biased: in steady state
    its innovation is i = dt d / Lv, so p_est = p - (1 - Lp) i and v_est = dt d / 2 - Lp d / Lv."""
    follower = LEADER - [0.0, 0.0, 1.5] + [2.0, 0.0, 0.0]  # out of the wake anyway; the field is off too
    ref = stack([Hover(LEADER), Hover(follower)])
    log = fly(scene, ref, [0], 20.0, wind=DrydenWind(mean=(8.0, -4.0, 0.0)), field_enabled=np.array([False]))[0]
    d = log["wind_acc"][-1, :, :2]  # m/s^2, at rest: the drag of the mean wind
    still_air = AIRFRAME.gain(QUAD.mass) * np.hypot(8.0, 4.0) * np.array([8.0, -4.0])  # the vehicles barely move
    np.testing.assert_allclose(d, np.broadcast_to(still_air, d.shape), rtol=2e-3)
    K = FeedbackLinearisedLQR().K
    Kp, Kv = K[0, 0], K[0, 3]
    Lp, Lv = MocapKalmanFilter(0.01, MocapConfig()).gain
    dt = 0.01
    want = (d - Kv * (0.5 * dt * d - Lp * d / Lv)) / Kp + (1.0 - Lp) * dt * d / Lv
    offset = log["pos"][-200:, :, :2].mean(axis=0) - log["ref_pos"][-1, :, :2]
    np.testing.assert_allclose(offset, want, rtol=0.01)
    assert np.all(offset[:, 0] > 0.5) and np.all(offset[:, 1] < -0.25)  # downwind


def test_the_wind_convects_the_wake_galilean_invariance(scene):
    """A leader hovering in a uniform wind w sheds the wake of a leader flying at -w through still
    air: its skewed axis trails downwind, where the follower feels the on-axis force."""
    field = DownwashField(skew=0.3)
    wind = np.array([2.0, 0.0, 0.0])
    depth = 0.6
    downwind = LEADER + [0.3 * depth * 2.0, 0.0, -depth]  # skew s |w| downwind of the leader, at depth s
    ref = stack([Hover(LEADER), Hover(downwind)])
    in_wind = Simulator(scene, ref, [1], field=field, wind=DrydenWind(mean=tuple(wind)),
                        predictor=OraclePredictor(field)).tick()
    still = Simulator(scene, ref, [1], field=field)
    still.physics.qvel[:, still._vel_idx] = -wind  # both vehicles fly at -w through still air
    moving = still.tick()
    np.testing.assert_array_equal(in_wind["field_mean"], moving["field_mean"])
    # on the displaced axis: -k A(s) n with k = 1 / (1 + (|w| / leader_speed_scale)^2), nothing lateral
    A = field.strength / (1.0 + depth / field.strength_depth) ** 2
    k = 1.0 / (1.0 + (2.0 / field.leader_speed_scale) ** 2)
    np.testing.assert_allclose(in_wind["field_mean"][0, 1], [0.0, 0.0, -k * A], rtol=1e-9, atol=1e-9)
    hover = Simulator(scene, ref, [1], field=field).tick()
    assert abs(hover["field_mean"][0, 1, 2]) < 0.5 * k * A  # in still air the follower is off the axis
    # the oracle gets the same air-relative truth; every row's field is the field at v - u_air
    assert np.array_equal(in_wind["f_hat"], in_wind["field_mean"])
    log = fly(scene, ref, [1], 1.0, field=field, wind=GUSTY)[0]
    want = pairwise_field(field, log["pos"], log["vel"] - log["wind"], quat_to_mat(log["quat"]))
    np.testing.assert_allclose(log["field_mean"], want, rtol=1e-12, atol=1e-12)


def test_compiled_wind_passes_equal_the_readable_law():
    rng = np.random.default_rng(11)
    W, V, dt = 4, 3, 0.01
    wind = DrydenWind(mean=(3.0, 4.0, 0.5), w20=10.0)
    mean, sigma, length, axes, vmin = wind.kernel_constants()
    state = rng.normal(size=(W, 3, 2))
    vel = rng.normal(size=(W, V, 3)) * [3.0, 3.0, 0.5]
    vel[0] = mean  # airspeed 0: the floor
    air, vel_air, acc = (np.empty((W, V, 3)) for _ in range(3))
    masses = np.array([0.7, 0.0319, 2.064])  # kg, each vehicle its own drag gain (sim.vehicle_params)
    gain = np.array([AIRFRAME.gain(m) for m in masses])
    wind_sense_kernel(state, axes, mean, gain, vel, air, vel_air, acc)
    want_air = np.broadcast_to(wind.wind(state)[:, None], (W, V, 3))
    np.testing.assert_allclose(air, want_air, rtol=1e-15, atol=1e-15)
    assert np.array_equal(vel_air, vel - air)
    np.testing.assert_allclose(acc, AIRFRAME.acceleration(air, vel, masses), rtol=1e-15, atol=1e-17)
    noise = rng.normal(size=(W, 5, 3, 2))
    cursor = np.array([0, 4, 2, 1])
    want = wind.step(state, noise[np.arange(W), cursor], dt, wind.airspeed(vel.mean(axis=1)))
    wind_advance_kernel(state, noise, cursor, vel, dt, mean, sigma, length, vmin, np.empty((3, 2, 2)), np.empty((3, 2, 2)))
    np.testing.assert_allclose(state, want, rtol=1e-12, atol=1e-14)


def test_bad_wind_inputs(scene):
    with pytest.raises(ConfigError, match="wind"):
        Simulator(scene, _lemniscate(1), [0], wind="severe")
    sim = Simulator(scene, _lemniscate(1), [0], wind=GUSTY)
    with pytest.raises(AttributeError, match="wind"):
        sim.wind = DrydenWind()
