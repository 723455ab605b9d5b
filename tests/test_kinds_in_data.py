"""Whether a model's training data held the scene's vehicle kinds: what a results entry's kinds_in_data says."""

from __future__ import annotations

import numpy as np
import torch

from downwash.checkpoint import save_checkpoint
from downwash.conditions import kinds_in_data
from downwash.features import kind_descriptors
from downwash.registry import make_model
from downwash.support import SUPPORT_FEATURES, Support

N_KIND = 2 * kind_descriptors(["paper_quad"]).shape[1]


def _support(kinds):
    """A support whose kind columns span exactly these kinds' descriptors (the other features: [-1, 1])."""
    d = kind_descriptors(kinds)
    lo, hi = -np.ones(len(SUPPORT_FEATURES)), np.ones(len(SUPPORT_FEATURES))
    lo[-N_KIND:] = np.tile(d.min(axis=0), 2)
    hi[-N_KIND:] = np.tile(d.max(axis=0), 2)
    return Support(lo, hi, np.full(len(SUPPORT_FEATURES), 0.1))


def test_the_support_holds_only_the_kinds_of_its_data():
    quads = _support(["paper_quad"])
    assert quads.holds_kinds(kind_descriptors(["paper_quad", "paper_quad", "paper_quad"]))
    assert not quads.holds_kinds(kind_descriptors(["paper_quad", "crazyflie_2_1"]))
    mixed = _support(["paper_quad", "crazyflie_2_1"])
    assert mixed.holds_kinds(kind_descriptors(["crazyflie_2_1", "paper_quad"]))
    assert mixed.holds_kinds(kind_descriptors(["crazyflie_2_1"]))
    assert not mixed.holds_kinds(kind_descriptors(["x500", "paper_quad"]))


def test_each_learned_condition_is_judged_from_its_checkpoint(tmp_path):
    torch.manual_seed(0)
    model = make_model("equivariant")
    model.set_normalization(torch.zeros(model.n_features), torch.ones(model.n_features),
                            torch.zeros(model.n_outputs), torch.ones(model.n_outputs))
    save_checkpoint(tmp_path / "with.pt", model.eval(), {"data": {"support": _support(["paper_quad"]).describe()}})
    save_checkpoint(tmp_path / "without.pt", model.eval(), {})
    checkpoints = {"equivariant": tmp_path / "with.pt", "equivariant-old": tmp_path / "without.pt"}
    conditions = ["baseline", "dob", "integral", "equivariant", "equivariant_guarded", "equivariant_dob", "equivariant-old"]
    assert kinds_in_data(conditions, checkpoints, ["paper_quad", "paper_quad"]) == {
        "equivariant": True, "equivariant_guarded": True, "equivariant_dob": True, "equivariant-old": False}
    assert kinds_in_data(["equivariant"], checkpoints, ["crazyflie_2_1", "paper_quad"]) == {"equivariant": False}
