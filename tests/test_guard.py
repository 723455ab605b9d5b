"""The guard on learned compensation (downwash.guard): support, scaling, rate limit, bound, the loop."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from downwash.checkpoint import Checkpoint
from downwash.conditions import GUARDED, data_variant, learned, make_predictor, parse_conditions
from downwash.datasets import Dataset
from downwash.features import FEATURE_SETS
from downwash.guard import GUARD_FEATURES, GuardedPredictor, Support, support_of
from downwash.guard_fused import DEN, EVIDENCE, FRACTION, GAIN, NUM
from downwash.support import SUPPORT_FEATURES, support_inputs
from downwash.predictor import LearnedPredictor
from downwash.registry import make_model
from downwash.set_models import SummedPairwise
from downwash_core.errors import ConfigError
from downwash_core.state import VehicleStates
from sim.predictor import GUARD_STATE_WIDTH, PerWorldPredictor, ZeroPredictor, is_stateful
from test_set_models import _one_torch_thread, randomised  # noqa: F401 (the fixture: one torch thread)

K = len(SUPPORT_FEATURES)


def _pairs(rng, n, leader_speed=0.05):
    """Training-like pairs: the target 0.4-1.2 m below a level, nearly hovering neighbour."""
    dp = np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), -rng.uniform(0.4, 1.2, n)])
    v_a = rng.normal(size=(n, 3)) * leader_speed
    v_b = rng.normal(size=(n, 3)) * 0.4
    return dp, v_a, v_b, np.broadcast_to(np.eye(3), (n, 3, 3))


@pytest.fixture(scope="module")
def support():
    return support_of(*_pairs(np.random.default_rng(0), 20000))


def _guard(support, seed=0, **options):
    torch.manual_seed(seed)
    model = randomised(make_model("equivariant_general").double(), seed).eval()
    return GuardedPredictor(LearnedPredictor(Checkpoint(SummedPairwise(model), {})), support, **options)


def _states(rng, W, leader_speed=0.05, scale=1.0):
    """W worlds of a leader and a follower 0.5-1 m below it (inside the support unless leader_speed
    or scale say otherwise)."""
    pos = np.zeros((W, 2, 3))
    pos[:, 0] = [0.0, 0.0, 2.0]
    pos[:, 1] = pos[:, 0] + np.column_stack([rng.uniform(-0.3, 0.3, (W, 2)) * scale, -rng.uniform(0.5, 1.0, W)])
    vel = np.zeros((W, 2, 3))
    vel[:, 0] = rng.normal(size=(W, 3)) * leader_speed
    vel[:, 1] = rng.normal(size=(W, 3)) * 0.2
    return VehicleStates(pos, vel, np.broadcast_to(np.eye(3), (W, 2, 3, 3)).copy())


def test_the_support_holds_the_training_pairs_and_round_trips(support):
    dp, v_a, v_b, R = _pairs(np.random.default_rng(1), 5000)
    x = support_inputs(dp, v_a, v_b, R)
    confidence = support.confidence(x)  # new pairs of the same kind: nearly all inside, the rest near it
    assert np.mean(confidence == 1.0) > 0.97 and np.mean(confidence) > 0.995
    again = Support.from_record(support.describe())
    assert all(np.array_equal(getattr(again, k), getattr(support, k)) for k in ("lo", "hi", "margin"))
    far = x.copy()
    far[:, FEATURE_SETS[GUARD_FEATURES].index("va_lateral")] = 5.0  # a leader moving at 5 m/s
    assert np.all(support.confidence(far) == 0.0)
    with pytest.raises(ConfigError, match="support lo"):
        Support(np.zeros(3), np.ones(K), np.ones(K))
    with pytest.raises(ConfigError, match="hi >= lo"):
        Support(np.ones(K), np.zeros(K), np.ones(K))


def test_the_guard_never_increases_a_prediction_and_bounds_it(support):
    """Inside, outside and between, with the monitor fed random forces (so the lateral and vertical
    gains differ): each part of the prediction is scaled by a fraction in [0, 1], never turned, and the
    whole is bounded."""
    rng = np.random.default_rng(2)
    guard = _guard(support, bound=0.5)
    raw_predictor = guard.predictor
    W = 16
    for k in range(30):
        states = _states(rng, W, leader_speed=rng.choice([0.05, 0.5, 3.0]), scale=rng.choice([1.0, 4.0]))
        raw = raw_predictor(states)
        out = guard(states)
        guard.observe(np.full(W, 0.02 * k), rng.normal(size=(W, 2, 3)) * 0.05, rng.normal(size=(W, 2, 3)))
        assert np.all(np.linalg.norm(out, axis=-1) <= np.linalg.norm(raw, axis=-1) + 1e-12)
        assert np.all(np.linalg.norm(out, axis=-1) <= 0.5 + 1e-12)
        lateral, vertical = out[..., :2], out[..., 2]
        assert np.all(np.linalg.norm(lateral, axis=-1) <= np.linalg.norm(raw[..., :2], axis=-1) + 1e-12)
        assert np.all(np.abs(vertical) <= np.abs(raw[..., 2]) + 1e-12) and np.all(vertical * raw[..., 2] >= 0)
        turned = lateral[..., 0] * raw[..., 1] - lateral[..., 1] * raw[..., 0]  # (2D cross product)
        np.testing.assert_allclose(turned, 0.0, atol=1e-12)  # scaled, never turned
        assert np.all((guard.applied >= 0) & (guard.applied <= 1))
    gains = guard._state[:, 1, GAIN:GAIN + 2]
    assert np.any(np.abs(gains[:, 0] - gains[:, 1]) > 0.1)  # (the parts were judged apart)


def test_inside_the_support_the_prediction_passes_unchanged_once_recovered(support):
    rng = np.random.default_rng(3)
    guard = _guard(support, bound=1e6)
    states = _states(rng, 32)
    assert np.all(guard.confidence(states) == 1.0)
    fractions = []
    for _ in range(10):  # the fraction rises by recovery / 45 Hz = 0.111 per call
        out = guard(states)
        fractions.append(guard.applied.copy())
    np.testing.assert_allclose(np.array(fractions)[:, :, 1].mean(1), np.minimum(np.arange(1, 11) * 5.0 / 45.0, 1.0))
    np.testing.assert_array_equal(out, guard.predictor(states))  # recovered: exactly the model's


def test_far_outside_the_support_nothing_is_applied_and_recovery_is_rate_limited(support):
    """With no evidence from the forces felt (nothing observed), far outside the support nothing is applied."""
    rng = np.random.default_rng(4)
    guard = _guard(support)
    inside, moving = _states(rng, 8), _states(rng, 8, leader_speed=4.0)
    for _ in range(12):
        guard(inside)
    assert np.all(guard.applied[:, 1] > 0.95)
    np.testing.assert_array_equal(guard(moving), 0.0)  # drops at once
    assert np.all(guard.applied[:, 1] == 0.0)  # (the leader, with nothing above it, has nothing to scale: 1)
    previous = guard.applied.copy()
    for _ in range(12):  # back inside: the fraction rises by at most recovery / 45 Hz per call
        guard(inside)
        assert np.all(guard.applied - previous <= 5.0 / 45.0 + 1e-12)
        previous = guard.applied.copy()


def test_vehicle_kinds_the_data_never_held_are_outside_the_support(support):
    """A model trained on paper quads has never met a heavier leader's wake or a lighter target, even at a
    familiar offset: in such a scene its guard applies nothing. Data holding those kinds puts them back inside."""
    from downwash.features import kind_descriptors

    rng = np.random.default_rng(9)
    states = _states(rng, 8)
    paper = _guard(support)
    assert paper.for_vehicles(["paper_quad", "paper_quad"]) is paper and np.all(paper.confidence(states) == 1.0)
    for kinds in (["x500", "paper_quad"], ["paper_quad", "crazyflie_2_1"]):
        guard = paper.for_vehicles(kinds)
        assert guard.vehicle_kinds == tuple(kinds) and guard.support is paper.support
        assert np.all(guard.confidence(states)[:, 1] == 0.0) and np.all(guard.confidence(states)[:, 0] == 1.0)
        for _ in range(12):
            np.testing.assert_array_equal(guard(states)[:, 1], 0.0)
    dp, v_a, v_b, R = _pairs(np.random.default_rng(0), 20000)
    heavy, paper_quad = kind_descriptors(["x500", "paper_quad"])
    kind_a = np.where(np.arange(20000)[:, None] % 2 == 0, heavy, paper_quad)  # half the pairs under a heavy leader
    mixed = support_of(dp, v_a, v_b, R, kind_a, np.zeros_like(kind_a))
    data = dataclasses.replace(Dataset.from_pairs(dp, v_a, v_b, R, np.zeros((20000, 3)), np.arange(20000) // 100),
                               kind_a=kind_a[:, None, :])  # what a checkpoint records: its data set's pairs' kinds
    assert all(np.array_equal(getattr(data.support(), k), getattr(mixed, k)) for k in ("lo", "hi", "margin"))
    assert data.summary()["support"] == mixed.describe()
    guard = _guard(mixed).for_vehicles(["x500", "paper_quad"])
    assert np.all(guard.confidence(states) == 1.0)
    assert np.all(guard.for_vehicles(["paper_quad", "crazyflie_2_1"]).confidence(states)[:, 1] == 0.0)
    with pytest.raises(ConfigError, match="told 3 vehicle kinds, flies 2"):
        _guard(support).for_vehicles(["x500"] * 3).confidence(states)


def test_due_worlds_and_resets(support):
    rng = np.random.default_rng(5)
    guard = _guard(support)
    states = _states(rng, 3)
    assert is_stateful(guard)
    for _ in range(3):
        guard(states, due=np.array([True, True, False]))
    applied = guard.applied.copy()
    guard.reset([0])
    guard(states, due=np.array([True, True, True]))
    np.testing.assert_allclose(guard.applied[:, 1], [5 / 45, applied[1, 1] + 5 / 45, 5 / 45])


def test_the_guard_needs_a_support():
    model = make_model("equivariant").double().eval()
    with pytest.raises(ConfigError, match="records no support"):
        GuardedPredictor(LearnedPredictor(Checkpoint(SummedPairwise(model), {})))
    with pytest.raises(ConfigError, match="recovery"):
        GuardedPredictor(LearnedPredictor(Checkpoint(SummedPairwise(model), {})), support_of(
            *_pairs(np.random.default_rng(0), 100)), recovery=0.0)
    small = support_of(*_pairs(np.random.default_rng(0), 100))
    for bad in ({"skeptic": 0.0}, {"skeptic": np.nan}, {"prior": np.inf}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            GuardedPredictor(LearnedPredictor(Checkpoint(SummedPairwise(model), {})), small, **bad)
    assert GuardedPredictor(LearnedPredictor(Checkpoint(SummedPairwise(model), {})), small, skeptic=np.inf).skeptic == np.inf


def test_a_trained_checkpoint_records_its_support_and_the_condition_flies_guarded(tmp_path):
    from downwash.train import TrainConfig, save_trained, train_model

    rng = np.random.default_rng(6)
    dp, v_a, v_b, R = _pairs(rng, 600)
    ds = Dataset.from_pairs(dp, v_a, v_b, R, rng.normal(size=(600, 3)) * 0.1, np.arange(600) * 3 // 600)
    model, history = train_model("equivariant", ds, None, TrainConfig(max_epochs=1, min_steps=0, batch_size=128))
    save_trained(tmp_path / "equivariant.pt", model, history, ds)
    guarded = make_predictor("equivariant" + GUARDED, None, {"equivariant": tmp_path / "equivariant.pt"})
    assert isinstance(guarded, GuardedPredictor)
    np.testing.assert_allclose(guarded.support.hi, support_of(dp, v_a, v_b, R).hi)
    assert parse_conditions("baseline,deep_guarded") == ["baseline", "deep_guarded"]
    assert learned(["oracle", "deep_guarded", "deep", "equivariant-outdoor_guarded"]) == ["deep", "equivariant"]
    assert data_variant("equivariant_guarded", "outdoor") == "equivariant-outdoor_guarded"
    assert data_variant("deep", "outdoor") == "deep-outdoor"
    from downwash.conditions import guard_record

    assert guard_record(["baseline", "deep"]) is None
    assert guard_record(["deep_guarded"]) == {"features": "general", "kinds": ["log_mass", "log_rotor_radius"],
                                              "support_quantile": 0.001, "margin": 0.25,
                                              "monitor_parts": ["lateral", "vertical"], "recovery": 5.0, "bound": 6.0,
                                              "monitor": 1.0, "prior": 1.0, "skeptic": 5.0, "fast_monitor": 0.2,
                                              "fast_prior": 3.0}


def test_the_loop_logs_the_applied_fraction(support):
    """The simulator logs the guard's applied fraction per tick and vehicle (NaN in worlds without a
    guard), and the held prediction is the guard's."""
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, Line, Offset, stack
    from sim.flight import fly
    from sim.scene import build_scene

    guard = _guard(support, 7, prior=1e12, fast_prior=1e12, skeptic=np.inf)  # (a monitor that trusts the random
    # model inside the support and gives it nothing outside: the support alone acts)
    routed = PerWorldPredictor([guard, ZeroPredictor()], np.array([0, 0, 1]))
    top = np.array(LEADER_POSITION)
    leader = Line(top - [1.5, 0, 0], (3.0, 0.0, 0.0), duration=1.0, n_worlds=3)  # fast: out of the support
    still = Hover(top, n_worlds=3)
    for ref, full in ((stack([still, Offset(still, (0.0, 0.1, -0.6))]), True),
                      (stack([leader, Offset(leader, (0.0, 0.1, -0.6))]), False)):
        logs = fly(build_scene(), ref, [1, 2, 3], 1.0, predictor=routed)
        a = logs[0]["applied"]
        assert a.shape == (len(logs[0]), 2) and np.all(np.isnan(logs[2]["applied"]))
        if full:
            assert a[-1, 1] > 1.0 - 1e-9 and a[0, 1] < 0.2  # recovered from the reset's zero
        else:
            assert np.all(a[:, 1] == 0.0) and np.all(logs[0]["f_hat"] == 0.0)


def test_the_metrics_count_ticks_at_full_partial_and_no_compensation():
    from sim.logs import FlightLog
    from sim.metrics import compensation_shares

    applied = np.array([[1.0, 1.0], [1.0, 0.5], [1.0, 0.0], [1.0, 1.0]])  # vehicle 0 leads: not counted
    log = FlightLog({"applied": applied}, {"roles": ["leader", "follower"], "follower": 1})
    assert compensation_shares([log]) == {"full": 0.5, "partial": 0.25, "none": 0.25}
    assert compensation_shares([FlightLog({}, {"follower": 1})]) is None
    nan = FlightLog({"applied": np.full((3, 2), np.nan)}, {"follower": 1})  # worlds of another predictor
    assert compensation_shares([nan]) is None


def test_the_staged_collection_deploys_its_stage_models_guarded_on_request(tmp_path):
    """--guard-stages: each stage model flies clamped and behind the guard; off (the paper's protocol), the
    collection's provenance, and so its folders' key, is what it was."""
    from downwash.staged import CollectionConfig, deployed_predictor, provenance
    from downwash.train import TrainConfig, save_trained, train_model
    from experiments.common import parse_args
    from experiments.staged_collection import StagedArgs
    from sim.field import DownwashField

    rng = np.random.default_rng(8)
    dp, v_a, v_b, R = _pairs(rng, 600)
    ds = Dataset.from_pairs(dp, v_a, v_b, R, rng.normal(size=(600, 3)) * 0.1, np.arange(600) * 3 // 600)
    model, history = train_model("equivariant", ds, None, TrainConfig(max_epochs=1, min_steps=0, batch_size=128))
    save_trained(tmp_path / "equivariant.pt", model, history, ds)
    assert isinstance(deployed_predictor(None, 6.0, True), ZeroPredictor)
    plain = deployed_predictor(tmp_path / "equivariant.pt", 2.5, False)
    guarded = deployed_predictor(tmp_path / "equivariant.pt", 2.5, True)
    assert isinstance(plain, LearnedPredictor) and plain.clamp == 2.5
    assert isinstance(guarded, GuardedPredictor) and guarded.predictor.clamp == 2.5
    np.testing.assert_array_equal(guarded.support.hi, ds.support().hi)
    field = DownwashField()
    off, on = provenance(CollectionConfig(), field), provenance(CollectionConfig(guard=True), field)
    assert "guard" not in off["collection"] and on["collection"]["guard"]["bound"] == 6.0
    assert parse_args(StagedArgs, "staged_collection", ["--guard-stages"], "").guard_stages is True


@pytest.mark.parametrize("neighbours", [1, 3])
def test_the_compiled_pass_is_its_numpy_reference_bit_for_bit(support, neighbours):
    """`downwash.guard_fused.guard_into`, which every call runs, against `GuardedPredictor.reference`
    (the NumPy support check, rate limit and bound): random stacks of vehicles of random kinds, inside,
    near and far outside the support, random due worlds and fractions, predictions above the bound."""
    from downwash.checkpoint import wrap_pairwise
    from downwash.guard_fused import guard_into
    from downwash.predictor import LearnedPredictor
    from sim.neighbours import NeighbourSet

    rng = np.random.default_rng(10 + neighbours)
    model = randomised(make_model("equivariant_general").double(), 1).eval()
    base = GuardedPredictor(LearnedPredictor(wrap_pairwise(model, NeighbourSet(neighbours))), support)
    seen, kinds_seen = [], []
    for trial in range(8):
        W, V = 60, 4
        kinds = [["paper_quad", "x500", "crazyflie_2_1"][k] for k in rng.integers(0, 3, V)] if trial % 2 else None
        guard = base if kinds is None else base.for_vehicles(kinds)
        pos = np.zeros((W, V, 3))
        pos[..., 2] = 2.0 + np.arange(V)[::-1] * rng.uniform(0.3, 1.3, (W, 1))  # a stack: vehicle 0 on top
        pos[..., :2] = rng.normal(size=(W, V, 2)) * rng.choice([0.1, 0.4, 1.0], (W, 1, 1))
        vel = rng.normal(size=(W, V, 3)) * rng.choice([0.05, 0.3, 2.0], (W, 1, 1))
        tilt = rng.normal(size=(W, V, 3)) * 0.2
        rot = np.array([[np.eye(3) + np.cross(np.eye(3), t) for t in w] for w in tilt])  # (not quite rotations)
        states = VehicleStates(pos, vel, rot)
        raw = rng.normal(size=(W, V, 3)) * rng.choice([0.5, 10.0], (W, 1, 1))
        state = rng.normal(size=(W, V, GUARD_STATE_WIDTH))  # (the raw prediction before: overwritten where due)
        state[..., FRACTION:FRACTION + 2] = rng.uniform(0, 1, (W, V, 2))  # the fractions
        state[..., GAIN:GAIN + 2] = np.where(rng.uniform(size=(W, V, 2)) < 0.5, 1.0, rng.uniform(0, 1, (W, V, 2)))
        state[..., EVIDENCE] = np.where(rng.uniform(size=(W, V)) < 0.5, 0.0, rng.uniform(0, 1, (W, V)))
        due = rng.uniform(size=W) < 0.7
        want_out, want_state, want_applied = guard.reference(states, raw, state, due)
        out, got_state, got_applied = raw.copy(), state.copy(), np.full((W, V), -1.0)
        guard_into(pos, vel, rot, due.view(np.uint8), out, got_state, got_applied, *guard._pack)
        np.testing.assert_array_equal(out, want_out)
        np.testing.assert_array_equal(got_state, want_state)
        np.testing.assert_array_equal(got_state[~due], state[~due])
        np.testing.assert_array_equal(got_applied[due], want_applied[due])
        assert np.all(got_applied[~due] == -1.0)  # only the due worlds' applied fraction is written
        seen.append(guard.confidence(states).ravel())
        kinds_seen.append(guard.kind_confidence(states).ravel())
    seen, kinds_seen = np.concatenate(seen), np.concatenate(kinds_seen)
    assert np.mean(seen == 1.0) > 0.05 and np.mean(seen == 0.0) > 0.05 and np.mean((seen > 0) & (seen < 1)) > 0.01
    assert np.mean(kinds_seen == 0.0) > 0.05 and np.mean((kinds_seen == 1.0) & (seen < 1)) > 0.05


def _observe_forces(guard, states, scale, rng, seconds=2.0, noise=1.0, dt=0.02):
    """Ticks of a flight at constant states in which each vehicle feels `scale` times the model's
    prediction plus motion-capture-like noise (m/s^2): the rows the monitor reads after each tick."""
    W, V = states.pos.shape[:2]
    vel, u = np.zeros((W, V, 3)), rng.normal(size=(W, V, 3))  # (any command: the force is what is left)
    for k in range(int(seconds / dt)):
        raw = guard.predictor(states)
        guard(states)
        guard.observe(np.full(W, k * dt), vel, u)
        vel = vel + (u + scale * raw + rng.normal(size=(W, V, 3)) * noise) * dt


@pytest.mark.parametrize("scale", [(-1.0, -1.0), (0.0, 0.0), (1 / 3, 1 / 3), (0.5, 0.5), (1.0, 1.0), (2.0, 2.0),
                                   (0.0, 1.0), (1.0, -1.0), (1 / 3, 2.0)])
def test_the_monitor_scales_a_model_to_the_forces_felt(support, scale):
    """Inside its support, a model that predicts 3x (2x) the force felt is applied at a third (half), one
    that is right in full, one that points the wrong way or at nothing not at all: the monitor's gain of
    each part of the prediction (lateral, vertical; the forces felt are `scale` (lateral, vertical) times
    it) is the least-squares scale of that part against the forces felt, clipped to [0, 1], and the
    motion-capture noise in those forces (1 m/s^2 per axis) does not bias it. (The one-second sums: the fast
    ones' prior is put out of reach here; they are the next test's.)"""
    rng = np.random.default_rng(11)
    guard = _guard(support, 3, bound=1e6, fast_prior=1e12)
    states = _states(rng, 16)
    assert np.all(guard.confidence(states) == 1.0)
    _observe_forces(guard, states, np.array(scale)[[0, 0, 1]], rng)
    raw = guard.predictor(states)
    gain = guard._state[:, 1, GAIN:GAIN + 2]
    want = np.clip(scale, 0.0, 1.0)
    strength = np.column_stack([np.linalg.norm(raw[:, 1, :2], axis=-1), np.abs(raw[:, 1, 2])])
    judged = strength > 0.5  # (the parts in which the random model predicts forces worth judging)
    assert np.mean(judged) > 0.6
    assert np.all((np.abs(gain - want) < 0.08 + 0.2 / strength)[judged]), (gain, want)
    out = guard(states)
    np.testing.assert_allclose(out[:, 1], raw[:, 1] * gain[:, [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(guard.applied[:, 1], np.linalg.norm(out[:, 1], axis=-1) / np.linalg.norm(raw[:, 1], axis=-1),
                               rtol=1e-12)


def test_the_fast_monitor_turns_a_model_down_within_a_fifth_of_a_second(support):
    """A model right for two seconds (applied nearly in full through 1 m/s^2 of noise per axis) that then
    predicts three times the force felt (a neighbour passing close) is turned down to under 0.7 within
    0.2 s by the fast sums; the one-second sums alone, still holding the earlier agreement, apply over
    0.8 of it. Each gain is the lower of the two scales, so the fast monitor never raises one."""
    rng = np.random.default_rng(12)
    states = _states(rng, 16)
    gains = {}
    for fast in (0.2, 1.0):  # (1.0: the fast sums are the slow ones, with their prior: the one-second monitor alone)
        guard = _guard(support, 3, bound=1e6, fast_monitor=fast, **({} if fast < 1.0 else {"fast_prior": 1.0}))
        _observe_forces(guard, states, 1.0, np.random.default_rng(5))
        right = guard._state[:, 1, GAIN:GAIN + 2].copy()
        _observe_forces(guard, states, 1 / 3, np.random.default_rng(6), seconds=0.2)
        gains[fast] = guard._state[:, 1, GAIN:GAIN + 2]
        strength = np.column_stack([np.linalg.norm(guard.predictor(states)[:, 1, :2], axis=-1),
                                    np.abs(guard.predictor(states)[:, 1, 2])])
        judged = strength > 1.0
        assert np.mean(judged) > 0.4 and np.median(right[judged]) > 0.9, right  # right: (nearly) in full before
    assert np.all(gains[0.2] <= gains[1.0])
    assert np.median(gains[0.2][judged]) < 0.7 < 0.8 < np.median(gains[1.0][judged]), gains


def test_the_monitor_starts_afresh_and_skips_ticks_it_cannot_judge(support):
    """A reset world's monitor has seen nothing (gain 1, its prior's trust); an ended world (its clock
    stopped) or a non-finite row adds no evidence; a world's gain depends on its own forces only."""
    rng = np.random.default_rng(12)
    guard = _guard(support, 3, bound=1e6)
    states = _states(rng, 4)
    _observe_forces(guard, states, 0.0, rng)
    gains = guard._state[:, 1, GAIN:GAIN + 2]
    assert np.all(gains.min(-1) < 0.2)
    guard.reset([0])
    assert np.all(guard._state[0, 1, GAIN:GAIN + 2] == 1.0) and np.all(guard._state[1:, 1, GAIN:GAIN + 2] == gains[1:])
    W, V = 4, 2
    guard(states)
    guard.observe(np.full(W, 5.0), np.zeros((W, V, 3)), np.zeros((W, V, 3)))  # the reset world's first tick
    before = guard._state[:, :, GAIN:GAIN + 2].copy()
    guard(states)
    stopped = np.array([5.0, 5.0, np.nan, 5.02])  # world 1: its clock did not move; 2: a NaN row
    vel = np.full((W, V, 3), 3.0)  # (a huge felt force in every world)
    vel[3] = np.nan
    guard.observe(stopped, vel, np.zeros((W, V, 3)))
    np.testing.assert_array_equal(guard._state[1:, :, GAIN:GAIN + 2], before[1:])
    assert np.all(guard._state[0, 1, GAIN:GAIN + 2] == 1.0)  # world 0: its first force is judged at its next tick


@pytest.mark.parametrize("scale", [-1.0, 0.0, 1.0])
def test_outside_the_support_only_the_forces_felt_give_a_model_authority(support, scale):
    """A leader moving at 4 m/s, far outside a hovering leader's support: nothing is applied until the
    forces felt agree with the model. Then its authority is the monitor's evidence, sum f.r / (sum |r|^2 +
    skeptic): a right model earns most of it within two seconds, one that points the wrong way or at
    nothing earns none (to the noise's reach). A vehicle kind the data never held gets nothing, whatever
    the evidence."""
    rng = np.random.default_rng(14)
    guard = _guard(support, 3, bound=1e6)
    states = _states(rng, 16, leader_speed=4.0)
    assert np.all(guard.confidence(states)[:, 1] == 0.0) and np.all(guard.kind_confidence(states) == 1.0)
    np.testing.assert_array_equal(guard(states)[:, 1], 0.0)  # no evidence yet
    _observe_forces(guard, states, scale, rng)
    evidence = guard._state[:, 1, EVIDENCE]
    sums = guard._seen[:, 1]
    np.testing.assert_allclose(evidence, np.clip(sums[:, NUM:NUM + 2].sum(-1) / (sums[:, DEN:DEN + 2].sum(-1) + guard.skeptic),
                                                 0, 1), rtol=1e-12)  # (one sum over both parts)
    out = guard(states)
    raw = guard.predictor(states)
    strength = np.linalg.norm(raw[:, 1], axis=-1)
    if scale == 1.0:
        assert np.all(evidence[strength > 1.0] > 0.8) and np.all(evidence > 0.3), (evidence, strength)
        fraction = np.minimum(evidence[:, None], guard._state[:, 1, GAIN:GAIN + 2])
        np.testing.assert_allclose(out[:, 1], raw[:, 1] * fraction[:, [0, 0, 1]], atol=1e-12)
    elif scale == -1.0:
        np.testing.assert_array_equal(out[:, 1], 0.0)
    else:
        # (the noise's reach: the evidence's spread is about 0.12 / |r|; 16 worlds)
        assert np.all(guard.applied[:, 1] < 0.4 / np.maximum(strength, 0.5)), (guard.applied[:, 1], strength)
    heavy = guard.for_vehicles(["x500", "paper_quad"])  # the same flight under a kind of leader the data never held
    assert np.all(heavy.kind_confidence(states)[:, 1] == 0.0)
    _observe_forces(heavy, _states(rng, 16), 1.0, rng)  # inside the continuous support, and right
    assert np.all(heavy._state[:, 1, EVIDENCE] > 0.3)
    np.testing.assert_array_equal(heavy(_states(rng, 16))[:, 1], 0.0)


class _ScaledOracle:
    """A model inside its support that is wrong by a factor: `scale` times the true mean field."""

    def __init__(self, field, scale):
        from sim.neighbours import NeighbourSet
        from sim.predictor import OraclePredictor

        self.oracle, self.scale, self.neighbours = OraclePredictor(field), scale, NeighbourSet(1)

    def __call__(self, estimated, true):
        return self.scale * self.oracle(estimated, true)

    def for_vehicles(self, kinds):
        return self


def test_in_flight_the_monitor_turns_a_wrong_model_down_and_a_right_one_on(support):
    """The closed loop, a follower hovering 0.6 m below its leader, inside the support: a model predicting
    three times the true mean field lifts the follower into its leader; behind the guard it settles near
    a third and flies far better than no model; the true mean field itself keeps its gain near 1."""
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, Offset, stack
    from sim.field import DownwashField
    from sim.flight import fly
    from sim.scene import build_scene

    field = DownwashField()
    top = np.array(LEADER_POSITION)
    conditions = [ZeroPredictor(), _ScaledOracle(field, 3.0), GuardedPredictor(_ScaledOracle(field, 3.0), support),
                  GuardedPredictor(_ScaledOracle(field, 1.0), support)]
    K = 3
    still = Hover(top, n_worlds=K * len(conditions))
    logs = fly(build_scene(), stack([still, Offset(still, (0.0, 0.05, -0.6))]), list(range(K * len(conditions))), 6.0,
               field=field, predictor=PerWorldPredictor(conditions, np.repeat(np.arange(len(conditions)), K)))
    flights = [logs[i * K:(i + 1) * K] for i in range(len(conditions))]
    assert all(L.meta["status"] == 3 for L in flights[1])  # three times the force, unguarded: into the leader
    assert all(len(L) == 300 for i in (0, 2, 3) for L in flights[i])
    error = [np.mean([np.linalg.norm(L["pos"][150:, 1] - L["ref_pos"][150:, 1], axis=-1).mean() for L in flights[i]])
             for i in (0, 2, 3)]
    applied = [np.mean([L["applied"][150:, 1].mean() for L in flights[i]]) for i in (2, 3)]
    assert abs(applied[0] - 1 / 3) < 0.05 and error[1] < 0.3 * error[0], (error, applied)
    assert applied[1] > 0.95 and error[2] < 0.3 * error[0], (error, applied)


class _SidewaysOracle(_ScaledOracle):
    """A model inside its support that is right about the push down and wrong sideways: the true mean
    field plus a steady 1.5 m/s^2 along x wherever the field acts."""

    def __call__(self, estimated, true):
        out = self.oracle(estimated, true)
        out[..., 0] += 1.5 * (np.linalg.norm(out, axis=-1) > 0)
        return out


def test_in_flight_the_monitor_keeps_the_part_of_a_model_that_is_right(support):
    """The closed loop of the test above with a model right vertically and wrong sideways: unguarded the
    follower drifts sideways; behind the guard the lateral part is turned down (the forces felt sideways
    do not follow it) while the vertical part stays on, so the follower flies its height as with the
    true field and its lateral track as with no model."""
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, Offset, stack
    from sim.field import DownwashField
    from sim.flight import fly
    from sim.scene import build_scene

    field = DownwashField()
    conditions = [ZeroPredictor(), _ScaledOracle(field, 1.0), _SidewaysOracle(field, 1.0),
                  GuardedPredictor(_SidewaysOracle(field, 1.0), support)]
    K = 3
    still = Hover(np.array(LEADER_POSITION), n_worlds=K * len(conditions))
    logs = fly(build_scene(), stack([still, Offset(still, (0.0, 0.05, -0.6))]), list(range(K * len(conditions))), 6.0,
               field=field, predictor=PerWorldPredictor(conditions, np.repeat(np.arange(len(conditions)), K)))
    assert all(L.meta["status"] == 0 for L in logs)

    def error(i, axes):
        return np.mean([np.linalg.norm(L["pos"][150:, 1, axes] - L["ref_pos"][150:, 1, axes], axis=-1).mean()
                        for L in logs[i * K:(i + 1) * K]])

    baseline, truth, sideways, guarded = range(4)
    lateral, vertical = slice(0, 2), slice(2, 3)
    assert error(sideways, lateral) > 3 * error(baseline, lateral)  # (the lateral part misleads)
    assert error(guarded, lateral) < 1.5 * error(baseline, lateral)
    assert error(guarded, vertical) < 0.5 * error(baseline, vertical)
    assert error(guarded, vertical) < error(truth, vertical) + 0.3 * (error(baseline, vertical) - error(truth, vertical))


def test_the_compiled_monitor_is_its_numpy_reference(support):
    """`downwash.guard_fused.monitor_into`, which ``observe`` runs, against ``monitor_reference``: random
    rows and sums, worlds whose last tick is unseen (NaN), stopped clocks and non-finite rows. To float64
    rounding (exp is the CPU's own in each), every other operation in the same order."""
    from downwash.guard_fused import MONITOR_WIDTH

    rng = np.random.default_rng(13)
    guard = _guard(support, 3)
    W, V = 40, 3
    guard._arrays(W, V)
    for trial in range(6):
        state = rng.normal(size=(W, V, GUARD_STATE_WIDTH))
        seen = rng.normal(size=(W, V, MONITOR_WIDTH)) * rng.choice([0.1, 10.0], (W, 1, 1))
        seen[..., DEN:DEN + 2] = np.abs(seen[..., DEN:DEN + 2])  # (the sums of |r|^2 are positive)
        seen_t = np.where(rng.uniform(size=W) < 0.2, np.nan, rng.uniform(0, 5, W))
        t = seen_t + rng.choice([0.02, 0.0, -1.0, 0.5], W, p=[0.7, 0.1, 0.1, 0.1])
        t[np.isnan(t)] = 1.0
        vel, u = rng.normal(size=(W, V, 3)), rng.normal(size=(W, V, 3))
        vel[rng.uniform(size=(W, V, 3)) < 0.02] = np.nan
        want_state, want_seen, want_t = guard.monitor_reference(t, vel, u, state, seen, seen_t)
        guard._state[...], guard._seen[...], guard._seen_t[...] = state, seen, seen_t
        guard.observe(t, vel, u)
        np.testing.assert_allclose(guard._state, want_state, rtol=1e-13, atol=1e-300)
        np.testing.assert_allclose(guard._seen, want_seen, rtol=1e-13, atol=1e-300)
        np.testing.assert_array_equal(guard._seen_t, want_t)
        judged = (t - seen_t > 0)[:, None] & np.isfinite(vel).all(-1)
        assert judged.mean() > 0.4 and (~judged).mean() > 0.1  # (about 0.53 and 0.47)
        np.testing.assert_array_equal(guard._seen[~judged][:, :2], seen[~judged][:, :2])  # unjudged: sums unchanged
