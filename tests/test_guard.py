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
from downwash.support import SUPPORT_FEATURES, support_inputs
from downwash.predictor import LearnedPredictor
from downwash.registry import make_model
from downwash.set_models import SummedPairwise
from downwash_core.errors import ConfigError
from downwash_core.state import VehicleStates
from sim.predictor import PerWorldPredictor, ZeroPredictor, is_stateful
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
    rng = np.random.default_rng(2)
    guard = _guard(support, bound=0.5)
    raw_predictor = guard.predictor
    for k in range(30):  # inside, outside and between
        states = _states(rng, 16, leader_speed=rng.choice([0.05, 0.5, 3.0]), scale=rng.choice([1.0, 4.0]))
        raw = raw_predictor(states)
        out = guard(states)
        assert np.all(np.linalg.norm(out, axis=-1) <= np.linalg.norm(raw, axis=-1) + 1e-12)
        assert np.all(np.linalg.norm(out, axis=-1) <= 0.5 + 1e-12)
        np.testing.assert_allclose(np.cross(out, raw), 0.0, atol=1e-12)  # scaled, never turned
        assert np.all((guard.applied >= 0) & (guard.applied <= 1))


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
                                              "recovery": 5.0, "bound": 6.0}


def test_the_loop_logs_the_applied_fraction(support):
    """The simulator logs the guard's applied fraction per tick and vehicle (NaN in worlds without a
    guard), and the held prediction is the guard's."""
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, Line, Offset, stack
    from sim.flight import fly
    from sim.scene import build_scene

    guard = _guard(support, 7)
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
            assert a[-1, 1] == 1.0 and a[0, 1] < 0.2  # recovered from the reset's zero
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
    seen = []
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
        fraction = rng.uniform(0, 1, (W, V))
        due = rng.uniform(size=W) < 0.7
        want_out, want_fraction, want_applied = guard.reference(states, raw, fraction, due)
        out, got_fraction, got_applied = raw.copy(), fraction.copy(), np.full((W, V), -1.0)
        guard_into(pos, vel, rot, due.view(np.uint8), out, got_fraction, got_applied, *guard._pack)
        np.testing.assert_array_equal(out, want_out)
        np.testing.assert_array_equal(got_fraction, want_fraction)
        np.testing.assert_array_equal(got_applied[due], want_applied[due])
        assert np.all(got_applied[~due] == -1.0)  # only the due worlds' applied fraction is written
        seen.append(guard.confidence(states).ravel())
    seen = np.concatenate(seen)
    assert np.mean(seen == 1.0) > 0.05 and np.mean(seen == 0.0) > 0.05 and np.mean((seen > 0) & (seen < 1)) > 0.01
