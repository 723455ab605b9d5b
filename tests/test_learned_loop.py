"""Labels from real simulated flights, and a learned model in the control loop."""

import numpy as np
import pytest

from downwash_trajectories import Hover, Transect, stack
from downwash.datasets import Dataset
from downwash.labels import PAIR, label_noise_floor, labels_from_log
from downwash.predictor import LearnedPredictor
from downwash.train import TrainConfig, rmse, train_model
from sim.field import DownwashField
from sim.flight import fly
from downwash_core.params import LEADER_POSITION
from sim.scene import build_scene

LEADER = np.array(LEADER_POSITION)


@pytest.fixture(scope="module")
def scene():
    return build_scene()


@pytest.fixture(scope="module")
def passes_logs(scene):
    """Three 24 s transects 0.6 m below the leader (baseline controller): two 0.1 m beside its
    axis (different noise), one right through it."""
    ref = stack([Hover(LEADER, n_worlds=3), Transect(LEADER - [0, 0, 0.6], x_offset=[0.1, 0.1, 0.0], n_worlds=3)])
    logs = fly(scene, ref, [11, 12, 13], 24.0)
    assert all(L.ok for L in logs)
    return logs


def _flight_labels(logs):
    """The labelled samples of simulated flights, one flight id each: nothing synthetic."""
    from downwash.datasets import concatenate

    return concatenate([Dataset.from_labels(labels_from_log(L), PAIR, flight=i, stage=0) for i, L in enumerate(logs)])


def test_labels_equal_the_true_field_within_the_noise_floor(passes_logs):
    """f = a - u from motion capture recovers the logged field; the floor function reports the error."""
    lab = labels_from_log(passes_logs[0])
    truth = lab["field_mean"]
    err = lab["y"] - truth
    rms_truth = np.sqrt(np.mean(truth**2))
    rms_err = np.sqrt(np.mean(err**2))
    assert rms_truth > 0.3  # the flight did pass through the wake (RMS over the whole flight, ~0.4)
    assert rms_err < 0.15 and rms_err < 0.3 * rms_truth  # labels carry the field, not noise
    floor = label_noise_floor(passes_logs)
    all_err = np.concatenate([labels_from_log(L)["y"] - labels_from_log(L)["field_mean"] for L in passes_logs])
    # the same labels (their LAPACK-made end rows are dropped) and the same NumPy sums on the same machine:
    # equal to the bit (measured), whatever the kernel
    assert floor["rmse_mean"] == pytest.approx(np.sqrt(np.mean(all_err**2)), rel=1e-12)
    # the vertical (largest) component is tracked sample by sample
    assert np.corrcoef(lab["y"][:, 2], truth[:, 2])[0, 1] > 0.95


def test_labels_are_the_full_downwash_when_a_model_compensates(scene):
    """With the oracle compensating, u includes -f_hat, and the label is still the full field."""
    from sim.predictor import OraclePredictor

    ref = stack([Hover(LEADER, n_worlds=1), Transect(LEADER - [0, 0, 0.6], x_offset=0.1)])
    L = fly(scene, ref, [3], 12.0, predictor=OraclePredictor(DownwashField()))[0]
    lab = labels_from_log(L)
    truth = lab["field_mean"]
    assert np.abs(L["f_hat"][:, 1]).max() > 0.5  # the model did act
    residual = truth - L["f_hat"][lab["row"], 1]  # what a label that forgot the compensation would be near
    rms = lambda x: np.sqrt(np.mean(x**2))  # noqa: E731
    assert rms(lab["y"] - truth) < 0.4 * rms(truth)
    assert rms(lab["y"] - residual) > 2 * rms(lab["y"] - truth)


def test_hover_under_the_leader_with_the_model_compensating_stays_bounded(scene, passes_logs):
    """An equivariant model trained on flight labels only, in the 45 Hz slot: a hover 0.6 m below
    the leader, at a spot none of the training flights held, stays close and bounded.

    The training flights: the transects, and hovers near the axis at 0.55-0.7 m flown with
    the oracle compensating (as the staged collection flies with a model), whose labels
    are the full downwash."""
    from sim.predictor import OraclePredictor

    spots = np.array([[0.0, 0.0, 0.55], [0.1, 0.0, 0.6], [0.0, -0.1, 0.65], [-0.1, 0.05, 0.7]])
    hovers = fly(scene, stack([Hover(LEADER, n_worlds=4), Hover(LEADER - spots * [-1, -1, 1], n_worlds=4)]),
                 [21, 22, 23, 24], 10.0, predictor=OraclePredictor(DownwashField()))
    model, _ = train_model("equivariant", _flight_labels([*passes_logs, *hovers]), None,
                           TrainConfig(seed=0, max_epochs=20, min_steps=400))
    W = 2
    ref = stack([Hover(LEADER, n_worlds=W), Hover(LEADER - [0.05, 0.0, 0.6], n_worlds=W)])
    from sim.predictor import PerWorldPredictor, ZeroPredictor

    pred = PerWorldPredictor([ZeroPredictor(), LearnedPredictor(model, clamp=6.0)], np.array([0, 1]))
    base, learned = fly(scene, ref, [0, 0], 10.0, predictor=pred)
    assert base.ok and learned.ok
    err = lambda L: np.linalg.norm(L["pos"][:, 1] - L["ref_pos"][:, 1], axis=1)  # noqa: E731
    assert err(base)[-250:].mean() > 0.3  # the baseline sags ~0.4 m below its set-point
    assert err(learned)[-250:].mean() < 0.3 * err(base)[-250:].mean()
    assert err(learned).max() < 0.3
    # bounded: the error does not grow over the flight (no slow divergence or growing oscillation)
    assert err(learned)[-100:].max() <= 1.5 * err(learned)[100:300].max() + 0.02


def test_trained_model_fits_real_flight_labels(passes_logs):
    """The equivariant model trained on two simulated flights' labels (and nothing else) predicts a
    third flight, flown with other noise, within a small margin of that flight's label-noise floor."""
    train = _flight_labels([passes_logs[0], passes_logs[2]])
    val = _flight_labels([passes_logs[1]])
    model, _ = train_model("equivariant", train, None, TrainConfig(seed=0, max_epochs=20, min_steps=400))
    val_rmse, _ = rmse(model, val)
    floor = label_noise_floor(passes_logs[1:2])["rmse_mean"]
    assert val_rmse < 2.0 * floor + 0.05
    untrained_rmse = float(np.sqrt(np.mean(val.y**2)))  # predicting zero
    assert val_rmse < 0.3 * untrained_rmse
