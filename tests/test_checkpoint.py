"""Checkpoints: round trip, safe loading, mismatches named, atomic writes."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from downwash.checkpoint import CheckpointError, checkpoint_digest, load_checkpoint, save_checkpoint, sidecar_path
from downwash.models import DeepSNMLP
from downwash.registry import make_model
from downwash.predictor import LearnedPredictor
from downwash.train import TrainConfig
from sim.predictor import VehicleStates
from conftest import restamp


def trained_like(kind, feature_set=None, seed=0):
    """A model with random weights and normalisation (as if trained)."""
    torch.manual_seed(seed)
    model = make_model(kind, feature_set)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
        model.set_normalization(torch.rand(model.n_features) - 0.5, torch.rand(model.n_features) + 0.5,
                                torch.rand(model.n_outputs) - 0.5, torch.rand(model.n_outputs) + 0.5)  # fmt: skip
    if isinstance(model, DeepSNMLP):
        model.settle_spectral_norm()
    return model.eval()


def inputs(n=40, seed=1):
    rng = np.random.default_rng(seed)
    dp = rng.normal(size=(n, 3)) + [0, 0, -1]
    return dp, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3))


@pytest.mark.parametrize("kind,feature_set", [("equivariant", "5"), ("equivariant", "6"), ("shallow", None), ("deep", None)])
def test_round_trip_gives_identical_predictions(tmp_path, kind, feature_set):
    model = trained_like(kind, feature_set)
    meta = {"config": TrainConfig(seed=3), "data": {"n_samples": np.int64(100), "minutes": 1.5}, "seed": 3, "source": tmp_path}
    path = tmp_path / "model.pt"
    record = save_checkpoint(path, model, meta)
    loaded, meta2 = load_checkpoint(path, expect_kind=kind, expect_feature_set=model.feature_set)
    assert meta2 == record
    assert type(loaded) is type(model) and loaded.feature_set == model.feature_set and not loaded.training
    with torch.no_grad():
        assert torch.equal(loaded(*inputs()), model(*inputs()))
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    desc = meta2["model"]
    assert desc["kind"] == kind and desc["feature_set"] == model.feature_set
    assert desc["n_parameters"] == sum(p.numel() for p in model.parameters())
    assert desc["normalization"]["in_std"] == pytest.approx(model.in_std.tolist())
    assert meta2["config"]["seed"] == 3 and meta2["data"]["n_samples"] == 100 and meta2["source"] == str(tmp_path)
    sidecar = json.loads(sidecar_path(path).read_text())  # the human-readable copy, with the content's digest
    assert sidecar.pop("content_sha256") == checkpoint_digest(path) and sidecar == record


def test_float64_round_trip(tmp_path):
    model = trained_like("equivariant").double()
    save_checkpoint(tmp_path / "m.pt", model, {})
    loaded, meta = load_checkpoint(tmp_path / "m.pt")
    assert meta["model"]["dtype"] == "float64" and loaded.in_mean.dtype == torch.float64
    x = [torch.tensor(a) for a in inputs()]
    assert torch.equal(loaded(*x), model(*x))


def test_predictor_from_checkpoint(tmp_path):
    model = trained_like("equivariant")
    save_checkpoint(tmp_path / "m.pt", model, {})
    pred = LearnedPredictor.from_checkpoint(tmp_path / "m.pt", clamp=5.0, expect_kind="equivariant")
    states = VehicleStates(np.array([[[0, 0, 2.0], [0.1, 0, 1.2]]]), np.zeros((1, 2, 3)), np.broadcast_to(np.eye(3), (1, 2, 3, 3)))
    true = VehicleStates(states.pos + [0.3, 0.0, 0.1], states.vel + 0.2, states.rot)  # what it must not see
    ref = LearnedPredictor(model, clamp=5.0)(states, true)
    np.testing.assert_array_equal(pred(states, true), ref)
    assert np.abs(ref).max() > 0 and not np.allclose(ref, LearnedPredictor(model, clamp=5.0)(true, states))
    with pytest.raises(CheckpointError, match="model kind is 'equivariant', expected 'deep'"):
        LearnedPredictor.from_checkpoint(tmp_path / "m.pt", expect_kind="deep")


def _side_effect(path):  # what a malicious pickle would run on load
    Path(path).write_text("pwned")
    return {}


class Evil:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (_side_effect, (self.marker,))


def test_pickled_objects_are_refused_without_running_them(tmp_path):
    model = trained_like("shallow")
    path = tmp_path / "evil.pt"
    save_checkpoint(path, model, {})
    payload = torch.load(path, weights_only=True)
    marker = tmp_path / "marker"
    payload["extra"] = Evil(marker)
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match=r"evil.pt: refused by the safe loader \(weights_only=True\)"):
        load_checkpoint(path)
    assert not marker.exists()


def test_mismatches_are_named(tmp_path):
    path = tmp_path / "eq5.pt"
    save_checkpoint(path, trained_like("equivariant", "5"), {})
    with pytest.raises(CheckpointError, match=r"eq5.pt: model kind is 'equivariant', expected 'shallow'"):
        load_checkpoint(path, expect_kind="shallow")
    with pytest.raises(CheckpointError, match=r"eq5.pt: feature set is '5', expected '6'"):
        load_checkpoint(path, expect_feature_set="6")
    # tensor shapes that do not fit the architecture in the metadata
    payload = torch.load(path, weights_only=True)
    payload["state_dict"]["net.0.weight"] = torch.zeros(32, 6)
    torch.save(restamp(payload), tmp_path / "bad_shape.pt")
    with pytest.raises(CheckpointError, match=r"bad_shape.pt: .*tensor 'net.0.weight' has shape \(32, 6\), expected \(32, 5\)"):
        load_checkpoint(tmp_path / "bad_shape.pt")
    # metadata claiming another feature set than the weights were trained for
    meta = json.loads(payload["meta_json"])
    meta["model"]["feature_set"] = "6"
    payload["meta_json"] = json.dumps(meta)
    payload["state_dict"]["net.0.weight"] = torch.zeros(32, 5)
    torch.save(restamp(payload), tmp_path / "bad_meta.pt")
    with pytest.raises(CheckpointError, match=r"bad_meta.pt: weights do not match a 'equivariant' model with feature set '6'.*in_mean"):
        load_checkpoint(tmp_path / "bad_meta.pt")
    del payload["state_dict"]["out_std"]
    meta["model"]["feature_set"] = "5"
    payload["meta_json"] = json.dumps(meta)
    torch.save(restamp(payload), tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match=r"missing tensor 'out_std'"):
        load_checkpoint(tmp_path / "missing.pt")


def test_foreign_and_missing_files(tmp_path):
    with pytest.raises(CheckpointError, match=r"nothing.pt: no such checkpoint file"):
        load_checkpoint(tmp_path / "nothing.pt")
    (tmp_path / "text.pt").write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match=r"text.pt: not a readable torch checkpoint"):
        load_checkpoint(tmp_path / "text.pt")
    good = tmp_path / "good.pt"
    save_checkpoint(good, trained_like("shallow"), {})
    data = good.read_bytes()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"truncated.pt: not a readable torch checkpoint"):
        load_checkpoint(tmp_path / "truncated.pt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match=r"other.pt: not a 'downwash-model' checkpoint"):
        load_checkpoint(tmp_path / "other.pt")
    with pytest.raises(ValueError, match=r"meta: the keys \['model'\] are reserved"):
        save_checkpoint(tmp_path / "x.pt", trained_like("shallow"), {"model": 1})
    with pytest.raises(TypeError, match="not JSON serialisable"):
        save_checkpoint(tmp_path / "x.pt", trained_like("shallow"), {"obj": object()})


def test_atomic_write_leaves_no_temporary_files(tmp_path, monkeypatch):
    path = tmp_path / "model.pt"
    first = trained_like("equivariant", seed=0)
    save_checkpoint(path, first, {"n": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.json", "model.pt"]
    # a failure while replacing the file: the old checkpoint survives, no temporary file stays
    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, trained_like("equivariant", seed=1), {"n": 2})
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.json", "model.pt"]
    loaded, meta = load_checkpoint(path)
    assert meta["n"] == 1
    assert torch.equal(loaded.state_dict()["net.0.weight"], first.state_dict()["net.0.weight"])
