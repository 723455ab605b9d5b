"""The multi-rate loop: determinism, batched == serial, tracking, failures end flights cleanly."""

import numpy as np
import pytest

from downwash_trajectories import Hover, Lemniscate, stack
from sim.field import DownwashField
from sim.flight import fly
from sim.logs import ARRAY_SPECS, load_log, save_log
from sim.metrics import tracking_metrics
from sim.predictor import OraclePredictor
from sim.scene import build_scene
from downwash_core.status import Status
from sim.simulator import Simulator

STATUS_OK, STATUS_DIVERGED, STATUS_GROUND, STATUS_VEHICLE = Status.OK, Status.DIVERGED, Status.GROUND, Status.VEHICLE

LEADER = np.array([0.0, 0.0, 2.5])


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _lemniscate(W, sep=0.6):
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, sep], n_worlds=W)])


def test_same_seed_bit_identical_logs(scene, tmp_path):
    a = fly(scene, _lemniscate(1), [7], 3.0)[0]
    b = fly(scene, _lemniscate(1), [7], 3.0)[0]
    save_log(tmp_path / "a.npz", a)
    save_log(tmp_path / "b.npz", b)
    la, lb = load_log(tmp_path / "a.npz"), load_log(tmp_path / "b.npz")
    for k in ARRAY_SPECS:
        assert np.array_equal(la[k], lb[k]), k
    c = fly(scene, _lemniscate(1), [8], 3.0)[0]
    assert not np.array_equal(a["mocap_pos"], c["mocap_pos"])


def test_batched_equals_serial_flights(scene):
    """mujoco.batch.Batch worlds reproduce single MjData flights bit for bit (per-world noise)."""
    seeds = [3, 4, 5]
    batched = fly(scene, _lemniscate(3), seeds, 2.0, predictor=OraclePredictor(DownwashField()))
    for w, s in enumerate(seeds):
        single = fly(scene, _lemniscate(1), [s], 2.0, predictor=OraclePredictor(DownwashField()))[0]
        for k in ARRAY_SPECS:
            assert np.array_equal(batched[w][k], single[k]), (w, k)


def test_tracking_without_downwash_and_oracle_helps(scene):
    W = 3
    field_on = np.array([False, True, True])
    from sim.predictor import PerWorldPredictor, ZeroPredictor

    pred = PerWorldPredictor([ZeroPredictor(), OraclePredictor(DownwashField())], np.array([0, 0, 1]))
    logs = fly(scene, _lemniscate(W), [0, 0, 0], 8.0, predictor=pred, field_enabled=field_on)
    no_dw, base, oracle = (tracking_metrics(L)["pos_err_3d_mean"] for L in logs)
    assert no_dw < 0.03
    assert base > 2 * no_dw
    assert oracle < 0.5 * base
    # the leader hovers steadily in every world
    for L in logs:
        assert np.abs(L["pos"][:, 0] - LEADER).max() < 0.05
    # the field is logged: zero where off, the applied field = mean + turbulence
    assert np.all(logs[0]["field_mean"] == 0) and np.abs(logs[1]["field_mean"][:, 1]).max() > 1.0
    turb = logs[1]["field_applied"] - logs[1]["field_mean"]
    mag = np.linalg.norm(logs[1]["field_mean"], axis=-1, keepdims=True)
    assert np.abs(turb).max() > 0 and np.all(np.abs(turb) <= 0.6 * mag + 1e-12)


def test_predictor_runs_at_45_hz_and_is_held(scene):
    calls = []

    class Counting:
        def __call__(self, est, true):
            calls.append(1)
            return np.full_like(est.pos, 1e-3 * len(calls))  # tiny: must not disturb the flight

    L = fly(scene, _lemniscate(1), [0], 2.0, predictor=Counting())[0]
    assert len(calls) == pytest.approx(90, abs=2)  # 45 Hz over 2 s
    changes = np.count_nonzero(np.diff(L["f_hat"][:, 1, 0]))
    assert 80 <= changes <= 90  # held between updates; 50 Hz ticks see ~45 new values per s
    # compensation enters the command: u = a_ref - K (x_est - x_ref) - f_hat, row by row
    from controllers.lqr import ControllerState, FeedbackLinearisedLQR
    from downwash_core.state import RefSample

    zeros = np.zeros(L["yaw_est"].shape)  # the lemniscate's yaw and yaw rate
    ref = RefSample(L["ref_pos"], L["ref_vel"], L["ref_acc"], zeros, zeros)
    want = FeedbackLinearisedLQR()(ControllerState(L["pos_est"], L["vel_est"], L["yaw_est"]), ref, L["f_hat"])
    np.testing.assert_allclose(L["u_cmd"], want.acc, rtol=0, atol=1e-12)
    assert np.abs(L["f_hat"][:, 1]).max() > 0.05  # so the check above would see a missing - f_hat


def test_failures_end_their_world_only(scene):
    class NaNBeyondX:  # a field that breaks for followers at x > 5
        def __call__(self, p_a, v_a, R_a, p_b, v_b):
            out = DownwashField()(p_a, v_a, R_a, p_b, v_b)
            return np.where(p_b[..., :1] > 5.0, np.nan, out)

    W = 4
    follower = np.array([[0, 0, 1.9], [10, 0, 1.9], [0, 0, -1.0], [0, 0, 2.5]])  # ok, NaN, into ground, into leader
    leader = np.array([LEADER, LEADER, LEADER, LEADER - [0, 0, 0.0]])
    leader[3] = [0.0, 0.15, 2.5]  # starts inside the collision ellipsoid of the follower
    ref = stack([Hover(leader), Hover(follower)])
    logs = fly(scene, ref, list(range(W)), 4.0, field=NaNBeyondX())
    status = [L.meta["status"] for L in logs]
    assert status == [STATUS_OK, STATUS_DIVERGED, STATUS_GROUND, STATUS_VEHICLE]
    assert len(logs[0]) == 200 and all(len(L) < 200 for L in logs[1:])
    assert "world 1" in logs[1].meta["message"] and "diverged" in logs[1].meta["message"]
    for L in logs:
        assert np.isfinite(L["pos"]).all()  # rows up to the failure are kept, all finite


def test_bad_inputs(scene):
    with pytest.raises(ValueError, match="duration"):
        fly(scene, _lemniscate(1), [0], 0.0)
    with pytest.raises(ValueError, match="shorter than one controller period"):
        fly(scene, _lemniscate(1), [0], 0.005)
    with pytest.raises(ValueError, match="field_enabled"):
        Simulator(scene, _lemniscate(2), [0, 1], field_enabled=np.ones(3, bool))
    with pytest.raises(ValueError, match="seeds"):
        Simulator(scene, _lemniscate(1), [])


def test_fused_kernels_equal_the_readable_components(scene):
    """The compiled sense / actuate passes of one autopilot tick against quat_to_mat,
    perturb_quat (the motion-capture attitude), MocapKalmanFilter, the turbulence law and
    Autopilot, on random states (bit for bit where the arithmetic is the same)."""
    from downwash_core.geometry import perturb_quat, quat_to_mat, yaw_of
    from sim.passes import actuate_kernel, sense_kernel
    from sim.simulator import Sensed

    W, V = 3, scene.n_vehicles
    sim = Simulator(scene, _lemniscate(W), [1, 2, 3], field_enabled=np.array([True, False, True]))
    rng = np.random.default_rng(5)
    ph = sim.physics
    q = rng.normal(size=(W, V, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    ph.qpos[:, sim._pos_idx] = rng.normal(size=(W, V, 3))
    ph.qpos[:, sim._quat_idx] = q
    ph.qvel[:] = rng.normal(size=ph.qvel.shape)
    sim.pos_est[:], sim.vel_est[:] = rng.normal(size=(2, W, V, 3))
    prior_p, prior_v = sim.pos_est.copy(), sim.vel_est.copy()
    sim._cursor[:] = [0, 5, 9]
    cursor = sim._cursor.copy()
    noise = sim._noise[np.arange(W), cursor]  # (W, V, 9)

    kin, quat, rot, quat_est, rot_est, yaw, _ = Sensed.empty(W, V)
    sim.t[:], sim.next_prediction[:] = [0.0, 0.1, 0.2], [0.0, 0.2, 0.1]
    n_due = sense_kernel(*sim._sense_args, kin, quat, rot, quat_est, rot_est, yaw)
    pos, vel = ph.qpos[:, sim._pos_idx], ph.qvel[:, sim._vel_idx]
    mocap = pos + sim.cfg.mocap.position_noise * noise[..., :3]
    est = sim.kf.update(prior_p, prior_v, mocap)
    assert n_due == 2 and sim._due.tolist() == [True, False, True]
    assert np.array_equal(quat, q)
    np.testing.assert_allclose(rot, quat_to_mat(q), rtol=0, atol=1e-15)  # the readable one normalises first
    q_meas = perturb_quat(q, sim.cfg.mocap.attitude_noise * noise[..., 3:6])
    np.testing.assert_allclose(quat_est, q_meas, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rot_est, quat_to_mat(q_meas), rtol=0, atol=1e-14)
    np.testing.assert_allclose(yaw, yaw_of(rot_est), rtol=0, atol=1e-14)
    # the measured attitude differs from the truth by the motion-capture noise, ~0.002 rad
    angle = 2 * np.arccos(np.clip(np.abs(np.sum(quat_est * q, axis=-1)), 0, 1))
    assert np.all(angle > 0) and np.all(angle < 10 * sim.cfg.mocap.attitude_noise)
    for got, want in zip(kin, (pos, vel, mocap, *est)):
        assert np.array_equal(got, want)
    assert np.array_equal(sim.pos_est, est[0]) and np.array_equal(sim.vel_est, est[1])

    mean = rng.normal(size=(W, V, 3))
    mean_in, turb0 = mean.copy(), rng.normal(size=(W, V, 3))
    sim.turb[:] = turb0
    cmd_acc = rng.normal(size=(W, V, 3))
    yaw_rate = rng.normal(size=(W, V))
    thrust, rot_des = sim.controller.setpoint(cmd_acc, yaw)
    applied = np.empty((W, V, 3))
    sim.active[:] = [True, True, False]
    t0 = sim.t.copy()
    sim._rot_des[:], sim._yaw_rate_des[:], sim._thrust_acc[:] = rot_des, yaw_rate, thrust
    actuate_kernel(*sim._actuate_args, mean, applied, rot, cmd_acc)
    mean_want = mean_in * sim.field_enabled[:, None, None]
    turb = sim.turbulence.step(turb0, noise[..., 6:9], sim.cfg.rates.autopilot_dt)
    applied_want = sim.turbulence.apply(mean_want, turb)
    omega = ph.qvel[:, scene.qvel_adr[:, None] + 3 + np.arange(3)]
    rotors = sim.autopilot(rot, omega, rot_des, yaw_rate, thrust, sim._mass_believed)
    assert np.array_equal(mean, mean_want) and np.array_equal(sim.turb, turb)
    np.testing.assert_allclose(applied, applied_want, rtol=1e-15, atol=1e-15)  # |mean|: sqrt of a sum either way
    assert np.array_equal(ph.xfrc_applied[:, scene.body_ids, :3], sim.mass * applied)
    assert np.array_equal(ph.ctrl[:, scene.act_ids], rotors)
    pred = sim.kf.predict(est[0], est[1], cmd_acc)
    assert np.array_equal(sim.pos_est, pred[0]) and np.array_equal(sim.vel_est, pred[1])
    assert np.array_equal(sim.t, t0 + sim.cfg.rates.autopilot_dt * sim.active)
    assert np.array_equal(sim._cursor, cursor + 1)


def test_rows_are_fresh_and_never_written_again(scene):
    """fly() keeps rows as they come: a row's arrays must not change in later ticks."""
    sim = Simulator(scene, _lemniscate(2), [1, 2])
    first = sim.tick()
    kept = {k: v.copy() for k, v in first.items()}
    for _ in range(5):
        sim.tick()
    for k in ARRAY_SPECS:
        assert np.array_equal(first[k], kept[k]), k


def test_oracle_sees_the_truth_and_per_world_routing_keeps_each_predictor_to_its_worlds():
    """The oracle evaluates the field at the TRUE states whatever the estimates say; PerWorldPredictor
    hands each predictor only its own worlds, estimates and truth alike."""
    from downwash_core.state import VehicleStates
    from sim.field import pairwise_field
    from sim.predictor import PerWorldPredictor, ZeroPredictor

    rng = np.random.default_rng(2)
    W = 4
    true = VehicleStates(np.stack([np.tile(LEADER, (W, 1)), LEADER - [0.1, 0.0, 0.6] + 0.05 * rng.normal(size=(W, 3))], 1),
                         0.3 * rng.normal(size=(W, 2, 3)), np.broadcast_to(np.eye(3), (W, 2, 3, 3)).copy())
    estimated = VehicleStates(true.pos + [0.2, -0.1, 0.05], true.vel + 0.1, true.rot)
    field = DownwashField()
    want = pairwise_field(field, true.pos, true.vel, true.rot)
    assert np.abs(want).max() > 0.5 and not np.allclose(want, pairwise_field(field, estimated.pos, estimated.vel, estimated.rot))
    np.testing.assert_array_equal(OraclePredictor(field)(estimated, true), want)

    seen = []

    class Recording:
        def __call__(self, est, tru):
            seen.append((est.pos.copy(), tru.pos.copy()))
            return np.ones_like(est.pos)

    routed = PerWorldPredictor([ZeroPredictor(), Recording()], np.array([0, 1, 0, 1]))(estimated, true)
    assert np.array_equal(routed[[0, 2]], np.zeros((2, 2, 3))) and np.array_equal(routed[[1, 3]], np.ones((2, 2, 3)))
    (est_seen, true_seen), = seen
    assert np.array_equal(est_seen, estimated.pos[[1, 3]]) and np.array_equal(true_seen, true.pos[[1, 3]])


def test_a_predictor_that_observes_sees_each_ticks_row_of_its_own_worlds(scene):
    """``observe(t, vel_est, u_cmd)`` is called after every tick with the row's arrays (the rows the log
    keeps); a PerWorldPredictor hands each observer only its own worlds' rows, and has no ``observe``
    when none of its predictors has one."""
    from sim.predictor import PerWorldPredictor, ZeroPredictor

    seen = []

    class Watching(ZeroPredictor):
        def observe(self, t, vel_est, u_cmd):
            seen.append((t.copy(), vel_est.copy(), u_cmd.copy()))

    assert PerWorldPredictor([ZeroPredictor(), ZeroPredictor()], np.array([0, 1])).observe is None
    routed = PerWorldPredictor([ZeroPredictor(), Watching()], np.array([0, 1, 0, 1]))
    logs = fly(scene, _lemniscate(4), [0, 1, 2, 3], 0.2, predictor=routed)
    assert len(seen) == len(logs[1]) == 10
    for k, (t, vel_est, u_cmd) in enumerate(seen):
        for name, got in (("t", t), ("vel_est", vel_est), ("u_cmd", u_cmd)):
            np.testing.assert_array_equal(got, np.stack([logs[w][name][k] for w in (1, 3)]))


@pytest.mark.parametrize("fast", [True, False])
def test_a_tick_steps_without_mujocos_profiling_timer_and_gives_it_back(scene, fast):
    """The simulator turns the bindings' timer callback off while it steps (sim.physics.profiling_timer_off):
    a timer of the user's own is not called during a tick, and is called again by mj_step after it."""
    import mujoco

    ref = stack([Hover(LEADER, n_worlds=1), Hover(LEADER - [0, 0, 0.6], n_worlds=1)])
    sim = Simulator(scene, ref, [0], fast=fast)  # one world: a batch of MuJoCo's refuses a Python callback
    calls = []
    mujoco.set_mjcb_time(lambda: calls.append(1) or 0.0)
    try:
        sim.tick()
        assert (sim._plan is not None) == fast
        before = len(calls)
        for _ in range(3):
            sim.tick()
        assert len(calls) == before  # 30 physics steps per world, no clock read
        data = mujoco.MjData(scene.model)
        mujoco.mj_step(scene.model, data)
        assert len(calls) > before  # given back
    finally:
        mujoco.set_mjcb_time(None)  # the bindings' own timer again


def test_the_profiling_timer_switch_counts_its_entries():
    """Simulators in several threads: the callback comes back when the last one leaves, not the first."""
    import ctypes

    from sim.physics import _libmujoco_path, profiling_timer_off

    slot = ctypes.c_void_p.in_dll(ctypes.CDLL(_libmujoco_path()), "mjcb_time")
    original = slot.value
    switch = profiling_timer_off()
    switch.__enter__()
    switch.__enter__()  # a second simulator, another thread
    assert slot.value is None
    switch.__exit__(None, None, None)
    assert slot.value is None  # the other one still steps
    switch.__exit__(None, None, None)
    assert slot.value == original
