"""Ensemble training (`downwash.ensemble`): each member is exactly its own `train_model`.

Data sets are labelled by the true field (`sim.field.DownwashField`, as in
test_training). The claim under test is bit-identity with one intra-op thread:
every member's state dict and history equal those of `train_model` with the same
data and config, for ensembles of one and of several members of different sizes,
with early stopping per member.
"""

import dataclasses

import numpy as np
import pytest
import torch

from downwash_core.errors import ConfigError
from downwash.checkpoint import load_checkpoint, save_checkpoint
from downwash.ensemble import train_ensemble
from downwash.models import PAIRWISE_KINDS, DownwashModel
from downwash.train import TrainConfig, rmse, train_model
from test_training import field_dataset

# a few epochs of several batches each: a short last batch every epoch, and
# members with different batch counts and sizes (one smaller than a batch)
SMALL = TrainConfig(max_epochs=3, min_steps=0, batch_size=256, patience=3)
_PER_RUN = ("train_loss", "val_loss", "best_epoch", "best_val_loss", "epochs", "planned_epochs", "steps", "lr",
            "n_train", "n_val", "train_flights", "val_flights", "kind", "feature_set", "config")  # fmt: skip


def _data(n, seed, n_flights=5):
    return field_dataset(n, np.random.default_rng(seed), n_flights=n_flights)


def assert_same_training(got, expected):
    (model, history), (ref, ref_history) = got, expected
    assert isinstance(model, DownwashModel) and type(model) is type(ref) and not model.training
    state, ref_state = model.state_dict(), ref.state_dict()
    assert state.keys() == ref_state.keys()
    for key in ref_state:
        assert torch.equal(state[key], ref_state[key]), key
    for key in _PER_RUN:
        assert history[key] == ref_history[key], key


@pytest.mark.parametrize("kind", list(PAIRWISE_KINDS))
def test_each_member_is_bit_identical_to_its_own_train_model(kind):
    datasets = [_data(1500, 10), _data(230, 11, n_flights=4), _data(1100, 12)]
    seeds = [3, 4, 5]
    singles = [train_model(kind, d, None, dataclasses.replace(SMALL, seed=s)) for d, s in zip(datasets, seeds)]
    # an ensemble of one ...
    (one,) = train_ensemble(kind, datasets[:1], SMALL, seeds=seeds[:1])
    assert_same_training(one, singles[0])
    # ... and of three members of different sizes (the second has fewer rows than a batch)
    trio = train_ensemble(kind, datasets, [dataclasses.replace(SMALL, seed=s) for s in seeds])
    assert [h["member"] for _, h in trio] == [0, 1, 2] and {h["ensemble_size"] for _, h in trio} == {3}
    assert len({h["n_train"] for _, h in trio}) == 3
    for got, expected in zip(trio, singles):
        assert_same_training(got, expected)


def test_early_stopping_is_per_member():
    """Member 0 is validated on labels opposite to its training labels, so it stops
    early; member 1 trains its whole schedule. Both equal their own training."""
    config = TrainConfig(max_epochs=30, min_steps=0, batch_size=512, patience=4)
    train_a, train_b = _data(1500, 20), _data(1200, 21)
    val_a = dataclasses.replace(_data(600, 22), y=-_data(600, 22).y)
    val_b = _data(600, 23)
    got = train_ensemble("shallow", [train_a, train_b], config, val=[val_a, val_b], seeds=[1, 2])
    expected = [train_model("shallow", train_a, val_a, dataclasses.replace(config, seed=1)),
                train_model("shallow", train_b, val_b, dataclasses.replace(config, seed=2))]  # fmt: skip
    for g, e in zip(got, expected):
        assert_same_training(g, e)
    stopped, full = got[0][1], got[1][1]
    assert stopped["epochs"] < stopped["planned_epochs"] and stopped["best_epoch"] <= 1
    assert full["epochs"] == full["planned_epochs"] == 30
    assert stopped["steps"] < full["steps"]


@pytest.mark.parametrize("kind", ["shallow", "deep"])
def test_members_with_different_configs(kind):
    """Own batch size, learning rate, weight decay and schedule length per member:
    members stop at different steps and share Adam calls only while their rates agree."""
    data = [_data(1300, 80), _data(900, 81), _data(1000, 82)]
    configs = [dataclasses.replace(SMALL, seed=1),
               dataclasses.replace(SMALL, seed=2, batch_size=200, lr=1e-2, weight_decay=1e-4, max_epochs=5),
               dataclasses.replace(SMALL, seed=3, batch_size=1000, lr_final=0.1, max_epochs=2, min_steps=5)]  # fmt: skip
    got = train_ensemble(kind, data, configs)
    for g, d, c in zip(got, data, configs):
        assert_same_training(g, train_model(kind, d, None, c))
    assert len({h["steps"] for _, h in got}) == 3


def test_shared_validation_set_and_different_seeds():
    data, val = _data(1200, 30), _data(500, 31)
    got = train_ensemble("equivariant", [data, data], SMALL, val=val, seeds=[0, 1])
    assert_same_training(got[1], train_model("equivariant", data, val, dataclasses.replace(SMALL, seed=1)))
    # same data, different seeds: different initialisation and batch order, different models
    a, b = got[0][0].state_dict(), got[1][0].state_dict()
    assert not torch.equal(a["net.0.weight"], b["net.0.weight"])
    assert got[0][1]["train_loss"] != got[1][1]["train_loss"]


def test_members_are_ordinary_models(tmp_path):
    data, val = _data(1000, 40), _data(400, 41)
    (model, history), (deep, _) = (train_ensemble(kind, [data], SMALL, seeds=[2])[0] for kind in ("shallow", "deep"))
    ref, _ = train_model("shallow", data, None, dataclasses.replace(SMALL, seed=2))
    assert rmse(model, val)[0] == rmse(ref, val)[0]
    save_checkpoint(tmp_path / "m.pt", deep, {"training": {k: v for k, v in history.items() if "loss" not in k}})
    loaded, _ = load_checkpoint(tmp_path / "m.pt", expect_kind="deep")
    assert all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), deep.state_dict().values()))
    pairs = val.pairs()
    x = [np.asarray(a[:50], dtype=np.float64) for a in (pairs.dp, pairs.v_a, pairs.v_b, pairs.R_a)]
    pred = loaded.numpy_forward()(*x)
    with torch.no_grad():
        np.testing.assert_allclose(pred, deep(*x).double().numpy(), rtol=1e-4, atol=1e-5)  # all 50 are below


def test_global_rng_untouched():
    data = _data(500, 50, n_flights=4)
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    train_ensemble("shallow", [data, data], TrainConfig(max_epochs=1, min_steps=0), seeds=[0, 1])
    assert torch.equal(torch.rand(3), expected)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda d: train_ensemble("shallow", []), "datasets: empty list"),
        (lambda d: train_ensemble("shallow", d), "datasets: expected a list"),
        (lambda d: train_ensemble("huge", [d]), "model kind: unknown 'huge'; allowed: shallow, deep"),
        (lambda d: train_ensemble("deepsets", [d]), "model kind 'deepsets': an ensemble is of per-neighbour kinds"),
        (lambda d: train_ensemble("shallow", [d, d], [SMALL]), "configs: got 1 configs for 2 data sets"),
        (lambda d: train_ensemble("shallow", [d, d], ["fast", SMALL]), r"configs\[0\]: expected a TrainConfig"),
        (lambda d: train_ensemble("shallow", [d, d], seeds=[1]), "seeds: got 1 seeds for 2 data sets"),
        (lambda d: train_ensemble("shallow", [d], seeds=[-1]), r"seeds\[0\]: expected an int >= 0"),
        (lambda d: train_ensemble("shallow", [d, d], val=[d]), "val: got 1 validation sets for 2 data sets"),
        (lambda d: train_ensemble("shallow", [d, d], [SMALL, dataclasses.replace(SMALL, num_threads=2)]),
         "num_threads must be the same"),
        (lambda d: train_ensemble("shallow", [d, d], [SMALL, dataclasses.replace(SMALL, portable=False)]),
         "portable must be the same"),
    ],
)
def test_bad_input_raises_config_error(call, message):
    with pytest.raises(ConfigError, match=message):
        call(_data(300, 60, n_flights=3))


def test_bad_member_data_is_named():
    good, bad = _data(300, 70, n_flights=3), _data(300, 71, n_flights=3)
    bad = dataclasses.replace(bad, y=np.full_like(bad.y, np.nan))
    with pytest.raises(ValueError, match=r"datasets\[1\]\.y: contains non-finite"):
        train_ensemble("shallow", [good, bad])
