"""The compiled-sensor contract (`sim.sensor_contract`): a sensor outside the family of `sim.sensors` (dropouts:
a lost measurement is held at the last one) flies the fused tick bit for bit as the readable path, with resets,
actions and chunks of worlds; when it keeps a sample it measures the plain sensor's noise exactly, it loses samples
at its stated rate, and a compiled form the sense pass cannot read is refused before any flight."""

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_core.geometry import perturb_quat_into
from downwash_core.jit import njit
from downwash_trajectories import Hover, Lemniscate, stack
from sim.flight import fly
from sim.logs import ARRAY_SPECS
from sim.scene import build_scene
from sim.sensor_contract import (SENSOR_STATE_STREAM, CompiledSensorLaw, checked_sensor_law, episode_state,
                                 sensor_law)
from sim.sensors import MocapConfig, check_sensor, draw_episode_offset
from sim.simulator import SimConfig, Simulator

LEADER = np.array([0.0, 0.0, 2.5])
MINSTD = 2147483647.0  # the loss stream: x <- 48271 x mod (2^31 - 1), exact in float64


@njit
def dropout_sample(p, q, xi, offset, state, params, m, q_m):
    """state: [loss stream, has a measurement, last position (3), last attitude (4)]; params: the stds, the loss."""
    position_std, attitude_std, loss = params[0], params[1], params[2]
    state[0] = (48271.0 * state[0]) % MINSTD
    if state[1] != 0.0 and state[0] / MINSTD < loss:  # lost: the last measurement, held
        for k in range(3):
            m[k] = state[2 + k]
        for k in range(4):
            q_m[k] = state[5 + k]
        return
    for k in range(3):  # kept: the plain sensor's law on the sample's draws
        m[k] = p[k] + position_std * xi[k] + offset[k]
    perturb_quat_into(q[0], q[1], q[2], q[3], attitude_std * xi[3], attitude_std * xi[4], attitude_std * xi[5], q_m)
    state[1] = 1.0
    for k in range(3):
        state[2 + k] = m[k]
    for k in range(4):
        state[5 + k] = q_m[k]


DROPOUT = sensor_law(dropout_sample, state_width=9, n_params=3)


@dataclass(frozen=True)
class DropoutMocap(MocapConfig):
    """Motion capture that loses each sample with probability `loss` and holds the last one instead."""

    loss: float = 0.1

    name: ClassVar[str] = "mocap_dropout"
    RANGES: ClassVar = {**MocapConfig.RANGES, "loss": (0.0, 0.99, "-")}

    def episode_state(self, rng, n_vehicles):
        state = np.zeros((n_vehicles, 9))
        state[:, 0] = rng.integers(1, 2**31 - 1, n_vehicles)  # each vehicle's loss stream, seeded at reset
        return state

    def compiled_sensor(self, W, V):
        params = np.array([self.position_noise, self.attitude_noise, self.loss])
        return DROPOUT.compiled(params, np.zeros((W, V, 9)))


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _reference(W):
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=W)])


def _fly(scene, sensor, W, n_ticks, fast):
    """The rows of a flight of W worlds, one world reset a third of the way, random actions on some ticks."""
    sim = Simulator(scene, _reference(W), list(range(W)), config=SimConfig(mocap=sensor), fast=fast,
                    n_threads=2 if W > 1 else 1)
    rng = np.random.default_rng(3)
    rows = []
    for k in range(n_ticks):
        if k == n_ticks // 3:
            sim.reset(np.array([min(1, W - 1)]))
        residual = rng.normal(0.0, 0.3, (W, 2, 3)) if k % 2 else None
        override = np.where(rng.random((W, 2, 3)) < 0.2, rng.normal(0.0, 0.5, (W, 2, 3)), np.nan)
        rows.append(dict(sim.tick(residual=residual, override=override if k % 3 == 0 else None)))
    return rows, sim


@pytest.mark.parametrize("W", [1, 12])  # 12: chunks of worlds on two threads, offsets into the sensor's state
def test_dropouts_fly_the_fused_tick_as_the_readable_path(scene, W):
    sensor = DropoutMocap(loss=0.3)
    (fused, sim_f), (readable, sim_r) = (_fly(scene, sensor, W, 60, fast) for fast in (True, False))
    assert sim_f._plan is not None and sim_r._plan is None
    for k, (x, y) in enumerate(zip(fused, readable)):
        for name in x:
            assert np.array_equal(x[name], y[name], equal_nan=True), (k, name)
    assert np.array_equal(sim_f.physics.qpos, sim_r.physics.qpos)
    state_f, state_r = sim_f._sensor_law.state, sim_r._sensor_law.state  # each simulator its own memory
    assert state_f is not state_r and np.array_equal(state_f, state_r) and np.all(state_f[..., 1] == 1.0)


def _same_logs(a, b):
    for la, lb in zip(a, b, strict=True):
        for k in ARRAY_SPECS:
            assert np.array_equal(la[k], lb[k]), k


@pytest.mark.parametrize("fast", [True, False], ids=["fused", "readable"])
def test_without_losses_the_law_flies_the_plain_sensor_bit_for_bit(scene, fast):
    """The loss stream is the sensor's own (its state, seeded at reset), not the noise blocks: a law that keeps
    every sample measures what `mocap` measures, and flies its flight, to the bit."""
    plain = fly(scene, _reference(2), [3, 4], 1.0, fast=fast)
    _same_logs(plain, fly(scene, _reference(2), [3, 4], 1.0, config=SimConfig(mocap=DropoutMocap(loss=0.0)),
                          fast=fast))


def _noise_of_world(seed, n_ticks, V, block=256):
    """The standard normals (n_ticks, V, 9) world `seed` draws, autopilot tick by tick (`Simulator._refill`)."""
    rng = np.random.default_rng(seed)
    blocks = [rng.standard_normal((block, V, 9)) for _ in range(-(-n_ticks // block))]
    return np.concatenate(blocks)[:n_ticks]


def _within_binomial(lost, trials, p):
    """Whether `lost` of `trials` Bernoulli(p) draws is within 4 standard deviations of n p."""
    return abs(lost - trials * p) <= 4 * np.sqrt(trials * p * (1 - p))


def test_the_law_loses_samples_at_its_rate_and_holds_the_last_measurement():
    """One sample after another through the law's loop (what its C function runs): a kept sample is the plain
    sensor's measurement of the same draws, a lost one the previous measurement, and the losses (after each
    vehicle's first sample, which is always kept) are Bernoulli(loss) within a binomial bound."""
    sensor, plain = DropoutMocap(loss=0.25, attitude_noise=0.01), MocapConfig(attitude_noise=0.01)
    W, V, T = 2000, 2, 8
    rng = np.random.default_rng(0)
    state = np.stack([episode_state(sensor, seed, V, 9) for seed in range(W)])
    params = sensor.compiled_sensor(W, V).params
    offset = np.zeros((W, V, 3))
    previous, lost_total = None, 0
    for t in range(T):
        pos = rng.normal(size=(W, V, 3))
        quat = rng.normal(size=(W, V, 4))
        quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
        normals = rng.standard_normal((W, V, 6))
        m, q_m = DROPOUT.measure(pos, quat, normals, offset, state, params)
        want_m, want_q = plain.measure(pos, quat, normals, offset)
        kept = np.all(m == want_m, axis=-1)
        # the attitude: NumPy's sin/cos or the kernel's (tests/test_sensors.py)
        np.testing.assert_allclose(q_m[kept], want_q[kept], rtol=0, atol=1e-15)
        if previous is None:
            assert kept.all()
        else:
            held = np.all(m == previous[0], axis=-1) & np.all(q_m == previous[1], axis=-1)
            assert np.all(kept | held) and not np.any(kept & held)  # one or the other, never both
            lost_total += int((~kept).sum())
        previous = (m, q_m)
    assert _within_binomial(lost_total, W * V * (T - 1), sensor.loss)
    # the stream is the sensor's own: seeded from the world's sensor-state stream, never from its noise
    assert np.array_equal(episode_state(sensor, 5, V, 9)[:, 0],
                          np.random.default_rng([5, SENSOR_STATE_STREAM]).integers(1, 2**31 - 1, V))


def test_a_flight_keeps_each_sample_or_holds_one_at_the_stated_rate(scene):
    """In the log (each controller tick's first sample), a kept measurement is the plain sensor's law of the
    world's own draws; the share of the others is the loss rate, within a binomial bound."""
    sensor, seeds = DropoutMocap(loss=0.3), [11, 12]
    logs = fly(scene, _reference(2), seeds, 6.0, config=SimConfig(mocap=sensor))
    per_control = SimConfig().rates.autopilot_per_control
    lost, trials = 0, 0
    for log, seed in zip(logs, seeds):
        T, V = len(log), log["pos"].shape[1]
        normals = _noise_of_world(seed, T * per_control, V)[::per_control, :, :6]
        want, _ = sensor.measure(log["pos"], log["quat"], normals, draw_episode_offset(sensor, seed, V))
        kept = np.all(log["mocap_pos"] == want, axis=-1)[1:]  # (the first sample is always kept)
        lost, trials = lost + int((~kept).sum()), trials + kept.size
        assert np.abs(log["mocap_pos"] - log["pos"]).max() < 0.05  # a held sample is a recent one
    assert _within_binomial(lost, trials, sensor.loss) and lost > 0


class _Refused(DropoutMocap):
    """A dropout sensor whose compiled form is replaced by `form(W, V)` (the test's)."""

    form = None

    def compiled_sensor(self, W, V):
        return type(self).form(W, V)


def _good(W, V):
    return DROPOUT.compiled(np.zeros(3), np.zeros((W, V, 9)))


@pytest.mark.parametrize("form, match", [
    (lambda W, V: tuple(_good(W, V)), r"_Refused.compiled_sensor\(\): expected a sim.sensor_contract.CompiledSensorLaw"),
    (lambda W, V: _good(W, V)._replace(params=np.zeros(3, np.int64)), r"its params must be a C-contiguous float64"),
    (lambda W, V: _good(W, V)._replace(state=np.zeros((W + 1, V, 9))), r"its state must be .* shape \(W, V, S\) = "
                                                                       r"\(2, 2, S\), got ndarray float64 \(3, 2, 9\)"),
    (lambda W, V: _good(W, V)._replace(state=np.zeros((9, V, W)).T), r"its state must be a writeable C-contiguous"),
    (lambda W, V: _good(W, V)._replace(address=0), r"its address must be a C function's"),
])
def test_a_compiled_form_the_sense_pass_cannot_read_is_refused_before_any_flight(scene, form, match, monkeypatch):
    monkeypatch.setattr(_Refused, "form", staticmethod(form))
    with pytest.raises(ConfigError, match=match):
        Simulator(scene, _reference(2), [0, 1], config=SimConfig(mocap=_Refused()))


def test_a_bad_episode_state_and_a_sensor_with_no_law_are_refused(scene):
    class WrongState(DropoutMocap):
        def episode_state(self, rng, n_vehicles):
            return np.zeros((n_vehicles, 3))

    with pytest.raises(ConfigError, match=r"WrongState.episode_state: expected finite \(2, 9\)"):
        Simulator(scene, _reference(1), [0], config=SimConfig(mocap=WrongState()))

    class NoLaw:  # neither the family's interface nor a compiled law
        measurement_noise, process_accel_noise = 0.0005, 2.0

        def episode_offset(self, rng, n_vehicles):
            return np.zeros((n_vehicles, 3))

        def describe(self):
            return {"type": "NoLaw"}

    with pytest.raises(ConfigError, match=r"SimConfig.mocap: a sensor needs compiled, measure"):
        check_sensor(NoLaw())
    with pytest.raises(ConfigError, match=r"shape \(n_params,\) = \(3,\)"):
        checked_sensor_law(CompiledSensorLaw(1, np.zeros(2), np.zeros((1, 2, 9))), "x", 1, 2, DROPOUT)
    with pytest.raises(TypeError, match=r"sensor_law: sample must be a numba.njit function"):
        sensor_law(dropout_sample.py_func, 9, 3)
