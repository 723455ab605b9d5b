"""Models that read the vehicle kinds: data, equivariance, the three backends, the scene binding, learning."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from downwash.checkpoint import Checkpoint
from downwash.datasets import Dataset, aggregation_record
from downwash.features import KIND_FEATURES, kind_descriptors
from downwash.labels import labels_from_log
from downwash.predictor import LearnedPredictor
from downwash.registry import make_model
from downwash.train import TrainConfig, rmse, train_model
from downwash_core.errors import ConfigError
from downwash_core.state import VehicleStates
from downwash_core.vehicles import CRAZYFLIE_2_1, PAPER_QUAD, X500
from sim.flight import fly
from sim.neighbours import NeighbourSet
from sim.presets import make_preset
from sim.simulator import Simulator
from test_set_models import _one_torch_thread, neighbour_batch, randomised  # noqa: F401 (the fixture: one torch thread)

D = len(KIND_FEATURES)
SETS = ("deepsets_equivariant", "deepsets")
MIXED = ("x500", "paper_quad", "crazyflie_2_1", "paper_quad")


def _kind_model(kind: str, seed: int = 0):
    torch.manual_seed(seed)
    return randomised(make_model(kind, kinds=True).double(), seed).eval()


def _checkpoint(model, K: int = 3) -> Checkpoint:
    return Checkpoint(model, {"neighbours": NeighbourSet(K).describe(), "aggregation": aggregation_record("linear")})


def _states(rng, W: int, V: int) -> VehicleStates:
    from downwash_core.geometry import quat_to_mat

    q = rng.normal(size=(W, V, 4))
    q[..., 0] += 4.0  # near level
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    pos = rng.normal(scale=0.6, size=(W, V, 3))
    return VehicleStates(pos, rng.normal(scale=0.5, size=(W, V, 3)), quat_to_mat(q))


# ----------------------------------------------------------------------------- the descriptors


def test_kind_descriptors_are_log_ratios_to_the_paper_quad():
    d = kind_descriptors(["paper_quad", X500, "crazyflie_2_1"])
    assert d.shape == (3, D)
    np.testing.assert_array_equal(d[0], 0.0)
    assert d[1, 0] == pytest.approx(math.log(X500.mass / PAPER_QUAD.mass))
    assert d[2, 1] == pytest.approx(math.log(CRAZYFLIE_2_1.rotor_radius / PAPER_QUAD.rotor_radius))
    assert d[1, 0] > 0 > d[2, 0]  # heavier and lighter than the paper quad


def test_an_unknown_kind_is_refused_by_name():
    with pytest.raises(ConfigError, match="no_such_drone.*allowed"):
        kind_descriptors(["paper_quad", "no_such_drone"])


# ----------------------------------------------------------------------------- labels carry the kinds


def test_labels_of_a_mixed_flight_carry_each_vehicles_kind():
    preset = make_preset("crazyflie_stack")
    (log,) = fly(preset.scene(), preset.reference(1), [3], duration=1.0)
    assert log.meta["kinds"] == list(preset.kinds)
    lab = labels_from_log(log, NeighbourSet(2))
    table = kind_descriptors(preset.kinds)
    assert len(lab["y"]) > 0
    np.testing.assert_array_equal(lab["kind_b"], table[lab["vehicle"]])
    real = lab["mask"]
    np.testing.assert_array_equal(lab["kind_a"][real], table[lab["neighbour"][real]])
    np.testing.assert_array_equal(lab["kind_a"][~real], 0.0)


def test_a_paper_quad_log_and_a_dataset_without_kinds_read_zeros():
    n = 5
    ds = Dataset.from_pairs(np.ones((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)),
                            np.zeros((n, 3)), np.arange(n))
    assert ds.kind_a.shape == (n, 1, D) and ds.kind_b.shape == (n, D)
    assert not ds.kind_a.any() and not ds.kind_b.any()


# ----------------------------------------------------------------------------- symmetries


@pytest.mark.parametrize("seed", range(4))
def test_the_equivariant_model_with_kinds_stays_equivariant_and_order_invariant(seed):
    rng = np.random.default_rng(seed)
    model = _kind_model("deepsets_equivariant", seed)
    B, K = 16, 3
    dp, v_a, v_b, R_a, mask = neighbour_batch(rng, B, K)
    kind_a = rng.normal(size=(B, K, D))
    kind_b = rng.normal(size=(B, D))
    f = model.numpy_forward()
    out = f(dp, v_a, v_b, R_a, mask, kind_a, kind_b)
    a = rng.uniform(-np.pi, np.pi)
    Q = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    rotated = f(dp @ Q.T, v_a @ Q.T, v_b @ Q.T, Q @ R_a, mask, kind_a, kind_b)
    # the twin's BLAS products (and the rotations') sum in their kernel's order: round-off only, 4e-15 measured
    # under every OpenBLAS kernel here and for the shuffle below, against 1e-9
    np.testing.assert_allclose(rotated, out @ Q.T, atol=1e-9)
    perm = rng.permutation(K)  # the kinds travel with their neighbours
    shuffled = f(dp[:, perm], v_a[:, perm], v_b, R_a[:, perm], mask[:, perm], kind_a[:, perm], kind_b)
    np.testing.assert_allclose(shuffled, out, atol=1e-9)
    assert not np.allclose(f(dp, v_a, v_b, R_a, mask, kind_a * 0.0, kind_b), out)  # the kinds are read


@pytest.mark.parametrize("kind", SETS)
def test_bad_kind_shapes_are_refused_before_any_work(kind):
    rng = np.random.default_rng(0)
    model = _kind_model(kind)
    dp, v_a, v_b, R_a, mask = neighbour_batch(rng, 4, 2)
    with pytest.raises(ConfigError, match="kind_a, kind_b: expected"):
        model(dp, v_a, v_b, R_a, mask, np.zeros((4, 2, D + 1)), np.zeros((4, D)))
    with pytest.raises(ConfigError, match="kinds: expected True or False"):
        make_model(kind, kinds="yes")


# ----------------------------------------------------------------------------- the backends and the scene


@pytest.mark.parametrize("kind", SETS)
def test_the_three_backends_agree_with_kinds(kind):
    rng = np.random.default_rng(1)
    states = _states(rng, 3, len(MIXED))
    checkpoint = _checkpoint(_kind_model(kind))
    out = {b: LearnedPredictor(checkpoint, backend=b, vehicle_kinds=MIXED)(states) for b in ("compiled", "numpy", "torch")}
    scale = np.abs(out["torch"]).max()
    for b in ("compiled", "numpy"):
        # compiled loops / NumPy's BLAS against torch's MKL, float64: each in its own order, 5e-15 measured
        # under every OpenBLAS and torch kernel, ~1e-4 of 1e-11 * scale
        np.testing.assert_allclose(out[b], out["torch"], rtol=0, atol=1e-11 * scale)
    # the kinds matter, and a table of paper quads is the unbound model
    blind = LearnedPredictor(checkpoint)(states)
    assert np.abs(blind - out["compiled"]).max() > 1e-3 * scale
    paper = LearnedPredictor(checkpoint, vehicle_kinds=["paper_quad"] * len(MIXED))(states)
    np.testing.assert_array_equal(paper, blind)


def test_a_predictor_told_another_vehicle_count_refuses_the_states():
    rng = np.random.default_rng(2)
    pred = LearnedPredictor(_checkpoint(_kind_model("deepsets_equivariant")), vehicle_kinds=MIXED[:3])
    with pytest.raises(ConfigError, match="3 vehicle kinds, the states hold 4"):
        pred(_states(rng, 1, 4))


def test_a_kind_blind_model_ignores_the_scene():
    pred = LearnedPredictor(_checkpoint(randomised(make_model("deepsets_equivariant").double(), 0).eval()))
    assert pred.for_vehicles(MIXED) is pred


@pytest.mark.parametrize("W", [1, 8])
def test_the_simulator_tells_the_model_its_scene_and_both_paths_agree(W):
    preset = make_preset("crazyflie_stack")
    checkpoint = _checkpoint(_kind_model("deepsets_equivariant"))
    rows = []
    for fast in (True, False):
        sim = Simulator(preset.scene(), preset.reference(W), list(range(W)), fast=fast,
                        predictor=LearnedPredictor(checkpoint, clamp=0.5))
        assert (sim._plan is not None) == fast
        assert sim._scene_predictor.vehicle_kinds == tuple(preset.kinds)
        rows.append([sim.tick()["f_hat"] for _ in range(20)])
    told = LearnedPredictor(checkpoint, clamp=0.5, vehicle_kinds=preset.kinds)
    assert np.abs(rows[0][-1]).max() > 0.01  # the model pushes: the comparison is not of zeros
    for a, b in zip(*rows):
        # both flights run the compiled pass (the default backend: no BLAS), so they are equal to the bit
        # (measured); the 1e-9 is for float64 round-off carried through 20 ticks of closed loop
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert told.describe()["vehicle_kinds"] == list(preset.kinds)


# ----------------------------------------------------------------------------- learning


def _synthetic_kinds_data(rng, n: int, flights: int) -> Dataset:
    """Two neighbours above a target; each pushes down by exp(its log mass) / exp(the target's), a
    smooth bump in the lateral distance: a law a kind-blind model cannot represent."""
    B, K = n, 2
    dp, v_a, v_b, R_a, mask = neighbour_batch(rng, B, K, max_tilt=0.1, p_mask=1.0)
    dp[..., 2] = rng.uniform(0.3, 1.0, size=(B, K))  # targets below their neighbours
    table = kind_descriptors(["paper_quad", "x500", "crazyflie_2_1"])
    kind_a = table[rng.integers(0, 3, size=(B, K))]
    kind_b = table[rng.integers(0, 3, size=B)]
    r2 = (dp[..., :2] ** 2).sum(-1)
    push = np.exp(kind_a[..., 0] - kind_b[:, None, 0]) * np.exp(-r2 / 0.05)  # (B, K)
    y = np.zeros((B, 3))
    y[:, 2] = -(push * mask).sum(1)
    return Dataset(dp=dp, v_a=v_a, v_b=v_b, R_a=R_a, mask=mask, neighbour=np.zeros((B, K), np.int64),
                   vehicle=np.ones(B, np.int64), y=y, flight=rng.integers(0, flights, size=B), stage=np.zeros(B, np.int64),
                   t=np.zeros(B), field_mean=np.full((B, 3), np.nan), kind_a=kind_a, kind_b=kind_b,
                   neighbours=NeighbourSet(K))


def test_a_model_that_reads_the_kinds_learns_what_a_blind_one_cannot():
    rng = np.random.default_rng(0)
    train, val = _synthetic_kinds_data(rng, 4000, 8), _synthetic_kinds_data(rng, 1000, 2)
    config = TrainConfig(max_epochs=40, min_steps=400, batch_size=256, patience=40)
    errors = {}
    for kinds in (False, True):
        model, _ = train_model("deepsets_equivariant", train, val, config, kinds=kinds)
        errors[kinds] = rmse(model, val)[0]
    spread = float(np.sqrt(np.mean(val.y**2)))
    assert errors[True] < 0.5 * errors[False], (errors, spread)
    assert errors[True] < 0.3 * spread
