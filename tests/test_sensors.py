"""The sensor as a component (`sim.sensors`): the readable law against the compiled pass, each noise
model against its analytic statistics, determinism, batched = serial, errors, and the default sensor
flying exactly the flights of before sensors were components."""

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_core.geometry import quat_multiply
from downwash_core.provenance import describe
from downwash_trajectories import Hover, Lemniscate, stack
from sim.estimation import MocapKalmanFilter, steady_state_gain
from sim.flight import fly
from sim.logs import ARRAY_SPECS
from sim.scene import build_scene
from sim.sensors import (SENSOR_STREAM, SENSORS, BiasedMocap, CompiledSensor, MocapConfig, check_sensor,
                         draw_episode_offset, make_sensor, resolve_sensor_spec)
from sim.simulator import SimConfig, Simulator

LEADER = np.array([0.0, 0.0, 2.5])
# what logs and collection keys have recorded for the motion capture since before sensors were components
LEGACY_RECORD = {"position_noise": 0.0005, "attitude_noise": 0.002, "process_accel_noise": 2.0}
BIASED = BiasedMocap(position_bias=0.01)  # 1 cm: plain to see against 0.5 mm of white noise


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _lemniscate(W):
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=W)])


def _same_logs(a, b):
    for la, lb in zip(a, b, strict=True):
        for k in ARRAY_SPECS:
            assert np.array_equal(la[k], lb[k]), k


def _rotvec(q):
    """The rotation vector (..., 3) rad of unit quaternions (..., 4) (w, x, y, z)."""
    q = q * np.sign(q[..., :1])  # the short way round
    v = q[..., 1:]
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return 2 * np.arctan2(norm, q[..., :1]) * v / np.maximum(norm, 1e-300)


# ----------------------------------------------------------------------------- the default is today's
def test_the_default_sensor_is_todays_motion_capture_with_its_record():
    assert SimConfig().mocap == MocapConfig() == make_sensor() == make_sensor("mocap") == resolve_sensor_spec("")
    assert SimConfig().to_dict()["mocap"] == LEGACY_RECORD  # logs' "config"
    assert describe(SimConfig())["mocap"] == {"type": "sim.estimation.MocapConfig", **LEGACY_RECORD}  # collection keys
    assert list(SENSORS)[:2] == ["mocap", "mocap_biased"]
    assert MocapConfig().compiled() == CompiledSensor(0.0005, 0.002)


def test_the_explicit_default_and_a_zero_offset_fly_the_default_flight_bit_for_bit(scene):
    """No sensor given, the `mocap` entry, and `mocap_biased` with no bias: one flight (the offset pass
    adds exactly nothing, and the offsets' stream leaves the white draws alone). tests/test_golden.py
    pins that flight to the numbers recorded before sensors were components."""
    seeds = [3, 4]
    default = fly(scene, _lemniscate(2), seeds, 1.0)
    _same_logs(default, fly(scene, _lemniscate(2), seeds, 1.0, config=SimConfig(mocap=make_sensor("mocap"))))
    _same_logs(default, fly(scene, _lemniscate(2), seeds, 1.0, config=SimConfig(mocap=BiasedMocap(position_bias=0.0))))
    assert default[0].meta["config"]["mocap"] == LEGACY_RECORD


# ----------------------------------------------------------------------------- readable law = compiled pass
def _noise_of_world(seed, n_ticks, V, block=256):
    """The standard normals (n_ticks, V, 9) world `seed` draws, autopilot tick by tick (`Simulator._refill`)."""
    rng = np.random.default_rng(seed)
    blocks = [rng.standard_normal((block, V, 9)) for _ in range(-(-n_ticks // block))]
    return np.concatenate(blocks)[:n_ticks]


@pytest.mark.parametrize("sensor", [MocapConfig(), BIASED], ids=["mocap", "mocap_biased"])
@pytest.mark.parametrize("fast", [True, False], ids=["fused", "readable"])
def test_a_flight_measures_what_the_readable_law_says(scene, sensor, fast):
    """Each tick's mocap position and attitude in the log equal `sensor.measure` of the true state, the
    world's own draws and its episode's offsets (3 s: the noise blocks are refilled on the way)."""
    seeds = [11, 12]
    logs = fly(scene, _lemniscate(2), seeds, 3.0, config=SimConfig(mocap=sensor), fast=fast)
    per_control = SimConfig().rates.autopilot_per_control
    for log, seed in zip(logs, seeds):
        T, V = len(log), log["pos"].shape[1]
        normals = _noise_of_world(seed, T * per_control, V)[::per_control, :, :6]  # each row's first sub-tick
        offset = draw_episode_offset(sensor, seed, V)
        pos, quat = sensor.measure(log["pos"], log["quat"], normals, offset)
        assert np.array_equal(log["mocap_pos"], pos)
        # NumPy's float64 sin/cos do not depend on its SIMD loops (downwash_core.libm): equal to the bit here
        # with its AVX-512 loops and with only its baseline ones (NPY_DISABLE_CPU_FEATURES), measured
        np.testing.assert_allclose(log["quat_est"], quat, rtol=0, atol=1e-15)  # sin/cos: NumPy's or the kernel's


def test_the_fused_and_the_readable_path_fly_the_same_biased_flights(scene):
    """Also batched on two threads: each chunk of worlds reads its own worlds' offsets."""
    config = SimConfig(mocap=BIASED)
    seeds = list(range(20, 28))
    fused = fly(scene, _lemniscate(8), seeds, 1.0, config=config, n_threads=2)
    readable = fly(scene, _lemniscate(8), seeds, 1.0, config=config, n_threads=2, fast=False)
    _same_logs(fused, readable)


def test_batched_biased_flights_equal_serial_ones(scene):
    config = SimConfig(mocap=BIASED)
    seeds = [5, 6, 7, 8]
    batched = fly(scene, _lemniscate(4), seeds, 1.0, config=config, n_threads=2)
    for w, seed in enumerate(seeds):
        _same_logs([batched[w]], fly(scene, _lemniscate(1), [seed], 1.0, config=config))


def test_a_seed_flies_the_same_biased_flight_and_another_seed_another_offset(scene):
    config = SimConfig(mocap=BIASED)
    a, b = (fly(scene, _lemniscate(1), [9], 1.0, config=config)[0] for _ in range(2))
    _same_logs([a], [b])
    sim = Simulator(scene, _lemniscate(2), [9, 10], config=config)
    first = sim.mocap_offset.copy()
    assert np.array_equal(first[0], draw_episode_offset(BIASED, 9, sim.V))
    assert not np.array_equal(first[0], first[1])
    for _ in range(3):
        sim.tick()
    assert np.array_equal(sim.mocap_offset, first)  # constant through the episode
    sim.reset(np.array([1]), seeds=[11])
    assert np.array_equal(sim.mocap_offset[0], first[0])
    assert np.array_equal(sim.mocap_offset[1], draw_episode_offset(BIASED, 11, sim.V))


# ----------------------------------------------------------------------------- statistics
@pytest.mark.parametrize("sensor", [MocapConfig(), BiasedMocap(position_noise=0.001, attitude_noise=0.01)],
                         ids=["mocap", "mocap_biased"])
def test_the_white_noise_has_the_stated_standard_deviations(sensor):
    """Position error and attitude error (as a body-frame rotation vector) per axis: zero mean, the stated
    std; 3 x 20000 draws each, so the sample std is within 4 % (8 standard errors) of the truth."""
    rng = np.random.default_rng(0)
    W, V = 10000, 2
    pos = rng.normal(size=(W, V, 3))
    quat = rng.normal(size=(W, V, 4))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    offset = draw_episode_offset(sensor, 1, V)
    measured, measured_quat = sensor.measure(pos, quat, rng.standard_normal((W, V, 6)), offset)
    white = (measured - offset - pos).reshape(-1, 3)
    attitude = _rotvec(quat_multiply(quat * [1, -1, -1, -1], measured_quat)).reshape(-1, 3)  # q^-1 q_m, body frame
    for err, std in ((white, sensor.position_noise), (attitude, sensor.attitude_noise)):
        np.testing.assert_allclose(err.std(axis=0), std, rtol=0.04)
        assert np.all(np.abs(err.mean(axis=0)) < 4 * std / np.sqrt(len(err)))


def test_the_episode_offsets_are_gaussian_with_the_stated_std_and_independent():
    """Over 3000 episodes (seeds): per axis zero mean and std position_bias (within 4 %), uncorrelated
    between vehicles and axes; `mocap` has none."""
    sensor = BiasedMocap(position_bias=0.003)
    offsets = np.stack([draw_episode_offset(sensor, seed, 2) for seed in range(3000)]).reshape(3000, 6)
    np.testing.assert_allclose(offsets.std(axis=0), 0.003, rtol=0.04)
    assert np.all(np.abs(offsets.mean(axis=0)) < 4 * 0.003 / np.sqrt(3000))
    corr = np.corrcoef(offsets.T) - np.eye(6)
    assert np.abs(corr).max() < 4 / np.sqrt(3000)
    assert np.array_equal(draw_episode_offset(MocapConfig(), 5, 2), np.zeros((2, 3)))
    # the offsets' own stream: the white draws of the world's main generator are untouched
    assert np.array_equal(draw_episode_offset(sensor, 7, 2), 0.003 * np.random.default_rng([7, SENSOR_STREAM])
                          .standard_normal((2, 3)))


def test_a_biased_vehicle_hovers_displaced_by_minus_its_offset(scene):
    """The filter cannot see the offset, so the controller holds the measured position on the
    reference: the true hover moves by -offset (same seed, so the same white noise). Without the
    downwash, which would push the displaced follower differently."""
    reference = stack([Hover(LEADER, n_worlds=1), Hover(LEADER - [0, 0, 0.6], n_worlds=1)])
    off = np.array([False])
    plain = fly(scene, reference, [2], 6.0, field_enabled=off)[0]
    biased = fly(scene, reference, [2], 6.0, config=SimConfig(mocap=BIASED), field_enabled=off)[0]
    offset = draw_episode_offset(BIASED, 2, 2)
    assert np.abs(offset).max() > 0.005
    shift = biased["pos"][-100:].mean(axis=0) - plain["pos"][-100:].mean(axis=0)  # (V, 3), the last 2 s
    np.testing.assert_allclose(shift, -offset, rtol=0, atol=0.0003)  # 0.06 mm seen
    assert biased.meta["config"]["mocap"] == {"type": "sim.sensors.BiasedMocap", **LEGACY_RECORD, "position_bias": 0.01}


def test_the_kalman_filter_takes_its_measurement_noise_from_the_sensor(scene):
    dt = 0.01
    noisy = BiasedMocap(position_noise=0.003)
    assert np.array_equal(MocapKalmanFilter(dt, noisy).gain, steady_state_gain(dt, MocapConfig(position_noise=0.003)))
    assert not np.array_equal(MocapKalmanFilter(dt, noisy).gain, MocapKalmanFilter(dt).gain)
    sim = Simulator(scene, _lemniscate(1), [0], config=SimConfig(mocap=noisy))
    assert np.array_equal(sim.kf.gain, MocapKalmanFilter(dt, noisy).gain) and sim.sensor is noisy


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("make, match", [
    (lambda: MocapConfig(position_noise=-1e-3), r"mocap position_noise: allowed 0.0 to 0.1 m, got -0.001"),
    (lambda: MocapConfig(attitude_noise=float("nan")), r"mocap attitude_noise: allowed 0.0 to 0.5 rad, got nan"),
    (lambda: BiasedMocap(position_bias=0.2), r"mocap_biased position_bias: allowed 0.0 to 0.05 m, got 0.2"),
    (lambda: make_sensor("vicon"), r"sensor: unknown 'vicon'; allowed: mocap, mocap_biased"),
    (lambda: make_sensor("mocap", position_bias=0.1),
     r"sensor 'mocap' has no parameter\(s\) \['position_bias'\]; allowed: "),
    (lambda: resolve_sensor_spec("mocap_biased:position_bias=-1"), r"sensor: 'mocap_biased:position_bias=-1': "
                                                                   r"mocap_biased position_bias: allowed 0.0 to 0.05 m"),
    (lambda: resolve_sensor_spec("mocap_biased:position_bias"), r"parameters are KEY=VALUE"),
    (lambda: resolve_sensor_spec("mocap:position_noise=lots"), r"position_noise='lots': expected a number"),
    (lambda: check_sensor(object()), r"SimConfig.mocap: a sensor needs measurement_noise, .*got object"),
])
def test_a_bad_setting_names_the_option_and_what_is_allowed(make, match):
    with pytest.raises(ConfigError, match=match):
        make()


def test_the_simulator_refuses_what_is_no_sensor_of_the_family(scene):
    class Wrong(MocapConfig):
        def episode_offset(self, rng, n_vehicles):
            return np.zeros(3)

    with pytest.raises(ConfigError, match=r"SimConfig.mocap: a sensor needs"):
        Simulator(scene, _lemniscate(1), [0], config=SimConfig(mocap="mocap"))
    with pytest.raises(ConfigError, match=r"Wrong.episode_offset: expected finite \(2, 3\) m"):
        Simulator(scene, _lemniscate(1), [0], config=SimConfig(mocap=Wrong()))
