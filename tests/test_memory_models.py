"""Models with memory: the neighbour's history as an input, in the labels, the models and the loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from downwash.checkpoint import Checkpoint, wrap_pairwise
from downwash.datasets import Dataset, concatenate
from downwash.features import HISTORY_LAGS
from downwash.labels import labels_from_log
from downwash.predictor import LearnedPredictor
from downwash.registry import make_model
from downwash.set_models import SummedPairwise
from downwash.train import TrainConfig, rmse, train_model
from downwash_core import geometry
from downwash_core.errors import ConfigError
from downwash_core.params import LEADER_POSITION
from downwash_core.state import VehicleStates
from downwash_trajectories import Line, Offset, stack
from sim.flight import fly
from sim.predictor import PerWorldPredictor, ZeroPredictor, is_stateful
from sim.scene import build_scene
from sim.simulator import Simulator
from test_models import random_rotations
from test_set_models import _one_torch_thread, neighbour_batch, randomised  # noqa: F401 (the fixture: one torch thread)

H = len(HISTORY_LAGS)
LAG_CALLS = [3, 6, 9, 12]  # each lag in calls at 45 Hz
MEMORY_KINDS = ("equivariant_memory", "deep_memory")


def _model(kind: str, seed: int = 0):
    torch.manual_seed(seed)
    return randomised(make_model(kind).double(), seed).eval()


def _moving_pair_logs(speed: float, seconds: float, seeds=(3,), predictor=None):
    """The leader on a line along +x at `speed`, the follower 0.6 m below and 0.1 m beside it."""
    W = len(seeds)
    leader = Line(np.array(LEADER_POSITION) - [0.5 * speed * seconds, 0, 0], (speed, 0.0, 0.0), duration=seconds,
                  n_worlds=W)
    return fly(build_scene(), stack([leader, Offset(leader, (0.0, 0.1, -0.6))]), list(seeds), seconds,
               predictor=predictor)


# ----------------------------------------------------------------------------- the model


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_equivariant_model_with_memory_stays_equivariant(seed):
    """Rotating the whole configuration about the leader's axis, its history included, rotates the
    force (torch model and its NumPy twin), for a tilted leader; ignoring the history's rotation
    breaks it, so the history is read."""
    rng = np.random.default_rng(seed)
    model = _model("equivariant_memory", seed)
    n = 128
    dp = rng.normal(size=(n, 3)) * [0.5, 0.5, 0.3] + [0, 0, -0.8]
    v_a, v_b = rng.normal(size=(n, 3)) * 0.8, rng.normal(size=(n, 3)) * 0.6
    R_a = random_rotations(rng, n, 0.6)
    hist = rng.normal(size=(n, H, 3)) * 0.3
    Q = geometry.rotation_about_axis(R_a[:, :, 2], rng.uniform(-np.pi, np.pi, n))
    rot = lambda v: np.einsum("nij,n...j->n...i", Q, v)  # noqa: E731
    twin = model.numpy_forward()
    with torch.no_grad():
        out = model(dp, v_a, v_b, R_a, hist).numpy()
        turned = model(rot(dp), rot(v_a), rot(v_b), R_a, rot(hist)).numpy()
        unturned_history = model(rot(dp), rot(v_a), rot(v_b), R_a, hist).numpy()
    assert np.max(np.abs(out)) > 0.1
    # torch's products (MKL, in its kernel's order) and the twin's (`matmul_rows`) on rotated inputs:
    # round-off only, 1.3e-14 measured under every OpenBLAS and torch kernel (both checks), against 1e-10
    np.testing.assert_allclose(turned, rot(out), atol=1e-10)
    below = -np.einsum("ni,ni->n", dp, R_a[:, :, 2]) > 0  # the twin's depth gate
    np.testing.assert_allclose(twin(rot(dp), rot(v_a), rot(v_b), R_a, rot(hist))[below], rot(out)[below], atol=1e-10)
    assert np.max(np.abs(unturned_history - rot(out))) > 1e-3


def test_the_deep_model_with_memory_is_not_equivariant():
    rng = np.random.default_rng(5)
    model = _model("deep_memory", 5)
    n = 64
    dp = rng.normal(size=(n, 3)) * 0.4 + [0, 0, -0.8]
    v_a, v_b, hist = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, H, 3)) * 0.3
    Q = geometry.rotation_about_axis(np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, 1.0))
    rot = lambda v: np.einsum("nij,n...j->n...i", Q, v)  # noqa: E731
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    with torch.no_grad():
        err = model(rot(dp), rot(v_a), rot(v_b), R, rot(hist)).numpy() - rot(model(dp, v_a, v_b, R, hist).numpy())
    assert np.max(np.abs(err)) > 1e-3


@pytest.mark.parametrize("kind", MEMORY_KINDS)
def test_a_model_with_memory_refuses_to_run_without_its_history(kind):
    model = _model(kind)
    x = np.zeros((2, 3))
    with pytest.raises(ValueError, match="history"):
        model(x, x, x, np.broadcast_to(np.eye(3), (2, 3, 3)))
    with pytest.raises(ValueError, match=r"hist: expected shape \(\.\.\., 4, 3\)"):
        model(x, x, x, np.broadcast_to(np.eye(3), (2, 3, 3)), np.zeros((2, 3, 3)))


@pytest.mark.parametrize("kind", MEMORY_KINDS)
def test_summed_model_with_memory_numpy_twin_equals_torch(kind):
    """Over padded neighbour sets, each slot with its own history."""
    rng = np.random.default_rng(1)
    summed = SummedPairwise(_model(kind, 1))
    dp, v_a, v_b, R_a, mask = neighbour_batch(rng, 40, 3)
    hist = rng.normal(size=(40, 3, H, 3)) * 0.3
    with torch.no_grad():
        want = summed(dp, v_a, v_b, R_a, mask, hist=hist).numpy()
    got = summed.numpy_forward()(dp, v_a, v_b, R_a, mask, None, None, hist)
    # the twin's written-out products (`matmul_rows`) against torch's MKL, float64 (outputs ~1): 5e-15
    # measured under every OpenBLAS and torch kernel (both checks), 200x under 1e-12
    np.testing.assert_allclose(got, want, atol=1e-12)
    hist[~mask] = 99.0  # padding is never read
    np.testing.assert_allclose(summed.numpy_forward()(dp, v_a, v_b, R_a, mask, None, None, hist), want, atol=1e-12)


def test_memory_learns_what_the_present_cannot_tell():
    """A law that depends on where the neighbour was 0.13 s ago: the model with memory learns it, the
    memoryless generalised model cannot (its inputs do not hold it)."""
    rng = np.random.default_rng(0)
    n = 4000
    dp = np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), -rng.uniform(0.4, 1.2, n)])
    v_a, v_b = rng.normal(size=(n, 3)) * 0.3, rng.normal(size=(n, 3)) * 0.3
    hist = rng.normal(size=(n, H, 3)) * 0.3  # independent of the present
    y = -2.0 * hist[:, 1] + [0.0, 0.0, -1.0]  # pushed away from where the neighbour was: equivariant
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    ds = Dataset.from_pairs(dp, v_a, v_b, R, y, np.arange(n) * 8 // n, hist=hist)
    train, val = ds.select_flights(range(6)), ds.select_flights([6, 7])
    cfg = TrainConfig(max_epochs=40, min_steps=0, batch_size=256, seed=0)
    with_memory, _ = train_model("equivariant_memory", train, None, cfg)
    without, _ = train_model("equivariant_general", train, None, cfg)
    spread = float(np.sqrt(np.mean((val.y - val.y.mean(0)) ** 2)))
    assert rmse(with_memory, val)[0] < 0.25 * spread
    assert rmse(without, val)[0] > 0.8 * spread


# ----------------------------------------------------------------------------- the data


def test_labels_hold_the_neighbours_displacement_over_each_lag():
    """A leader on a line at 1.5 m/s: after the longest lag, each displacement is the speed times
    the lag (the estimates' noise aside); before it, the flight's start stands in for the past."""
    log = _moving_pair_logs(1.5, 4.0)[0]
    lab = labels_from_log(log)
    assert lab["hist"].shape == (len(lab["y"]), 1, H, 3)
    late = lab["t"] > 1.0  # the leader has reached its speed
    want = np.array([[1.5 * lag, 0.0, 0.0] for lag in HISTORY_LAGS])
    np.testing.assert_allclose(lab["hist"][late, 0], np.broadcast_to(want, (late.sum(), H, 3)), atol=0.02)
    # each row's displacement is the leader's estimated position now minus then, between rows
    r = lab["row"][late][10]
    t, pos = log["t"], log["pos_est"][:, 0]
    then = np.array([np.interp(t[r] - lag, t, pos[:, 0]) for lag in HISTORY_LAGS])
    np.testing.assert_allclose(lab["hist"][late][10, 0, :, 0], pos[r, 0] - then, atol=1e-9)


def test_datasets_carry_the_history_through_pairs_and_concatenation():
    rng = np.random.default_rng(2)
    n = 10
    hist = rng.normal(size=(n, H, 3))
    ds = Dataset.from_pairs(rng.normal(size=(n, 3)), np.zeros((n, 3)), np.zeros((n, 3)),
                            np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3)), np.zeros(n, np.int64), hist=hist)
    both = concatenate([ds, ds])
    np.testing.assert_array_equal(both.pairs().hist, np.concatenate([hist, hist]))
    np.testing.assert_array_equal(both.subset(np.arange(3, 7)).hist[:, 0], hist[3:7])
    plain = Dataset.from_pairs(ds.dp[:, 0], ds.v_a[:, 0], ds.v_b, ds.R_a[:, 0], ds.y, ds.flight)
    np.testing.assert_array_equal(plain.hist, 0.0)  # no history given: a neighbour that did not move


# ----------------------------------------------------------------------------- the loop


def _states_moving(base, step, k):
    """States of 2 worlds x 3 vehicles at call k: every vehicle moved k steps."""
    pos = base + k * step
    return VehicleStates(pos, np.zeros_like(pos), np.broadcast_to(np.eye(3), (*pos.shape[:2], 3, 3)).copy())


def test_the_predictor_remembers_its_calls_and_forgets_at_reset():
    """Each call's history is the neighbours' positions 3, 6, 9, 12 calls back (the first call's
    before that), per world: a world not due does not advance, a reset world starts afresh."""
    rng = np.random.default_rng(3)
    model = _model("equivariant_memory", 3)
    pred = LearnedPredictor(model)
    twin = SummedPairwise(model).numpy_forward()
    assert is_stateful(pred) and pred.backend == "numpy"
    base = np.array([[[0.0, 0.0, 2.0], [0.1, 0.05, 1.4], [-0.2, 0.1, 0.8]]] * 2) + rng.normal(size=(2, 3, 3)) * 0.01
    step = np.array([0.02, -0.01, 0.0])

    def expected(calls_so_far):  # the twin on the history the predictor should hold, per world
        out = []
        for w, k in enumerate(calls_so_far):
            moved = np.array([min(k, m) * step for m in LAG_CALLS])  # (H, 3), the same for every vehicle
            pos = base[w] + k * step
            dp = pos[:, None] - pos[None, :]  # (target, neighbour, 3)
            V = len(pos)
            f = twin(dp.reshape(V * V, 1, 3), np.zeros((V * V, 1, 3)), np.zeros((V * V, 3)),
                     np.broadcast_to(np.eye(3), (V * V, 1, 3, 3)), ~np.eye(V, dtype=bool).reshape(V * V, 1), None,
                     None, np.broadcast_to(moved, (V * V, 1, H, 3)))
            out.append(f.reshape(V, V, 3).sum(1))
        return np.stack(out)

    for k in range(15):
        got = pred(_states_moving(base, step, k))
        # the same twin (no BLAS: `matmul_rows`) on histories formed two ways: 1.8e-15 apart (measured,
        # the same under every OpenBLAS kernel; here and after the reset below)
        np.testing.assert_allclose(got, expected([k, k]), atol=1e-12)
    # world 1 is not due for three calls: its history stays, world 0's moves on
    for k in range(15, 18):
        pred(_states_moving(base, step, k), due=np.array([True, False]))
    got = pred(_states_moving(base, step, 18))
    assert not np.allclose(got[1], expected([18, 18])[1])
    pred.reset([0])
    got = pred(_states_moving(base, step, 0))
    np.testing.assert_allclose(got[0], expected([0, 0])[0], atol=1e-12)  # world 0 forgot its past


def test_the_history_lags_must_be_whole_calls():
    with pytest.raises(ConfigError, match="predictor_hz"):
        LearnedPredictor(_model("equivariant_memory"), predictor_hz=50.0)
    with pytest.raises(ConfigError, match="no compiled form"):
        LearnedPredictor(_model("deep_memory"), backend="compiled")


def test_the_loop_flies_a_model_with_memory_readably_and_resets_it():
    """The simulator takes the readable path for a predictor with state, tells it which worlds are due,
    and resets it with the worlds: a second flight after a reset is the first one, bit for bit, and
    the same model in a PerWorldPredictor beside a zero predictor flies the same."""
    model = _model("equivariant_memory", 4)
    pred = LearnedPredictor(Checkpoint(SummedPairwise(model), {}))
    first = _moving_pair_logs(1.0, 1.5, seeds=(5, 6), predictor=pred)
    again = _moving_pair_logs(1.0, 1.5, seeds=(5, 6), predictor=pred)  # the same predictor object, reset by fly
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a["f_hat"], b["f_hat"])
    assert np.abs(first[0]["f_hat"]).max() > 0.01
    routed = PerWorldPredictor([LearnedPredictor(wrap_pairwise(model)), ZeroPredictor()], np.array([0, 1]))
    mixed = _moving_pair_logs(1.0, 1.5, seeds=(5, 6), predictor=routed)
    np.testing.assert_array_equal(mixed[0]["f_hat"], first[0]["f_hat"])
    np.testing.assert_array_equal(mixed[1]["f_hat"], 0.0)
    scene = build_scene()
    leader = Line(np.array(LEADER_POSITION), (1.0, 0.0, 0.0), duration=2.0, n_worlds=1)
    sim = Simulator(scene, stack([leader, Offset(leader, (0.0, 0.1, -0.6))]), [1], predictor=pred)
    sim.tick()
    assert sim._plan is None  # a stateful predictor flies the readable path
