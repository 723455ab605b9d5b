"""The conditions a control engineer tries first: `integral`, `dob` and a model with the observer on its residual."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from controllers.integral import IntegralLQR
from controllers.lqr import FeedbackLinearisedLQR, LQRConfig
from downwash.checkpoint import save_checkpoint
from downwash.conditions import (CONDITIONS, OBSERVED, data_variant, fly_conditions, learned, condition_controller,
                                 make_predictor, parse_conditions)
from downwash.registry import make_model
from downwash_core.errors import ConfigError
from sim.fields.registry import resolve_field_spec
from sim.observer import DisturbanceObserver
from sim.scene import build_scene
from downwash_trajectories import Hover, Lemniscate, stack

LEADER = np.array([0.0, 0.0, 2.5])
SEEDS = [0, 1]


def _checkpoint(tmp_path):
    torch.manual_seed(0)
    model = make_model("equivariant")
    model.set_normalization(torch.zeros(model.n_features), torch.ones(model.n_features),
                            torch.zeros(model.n_outputs), torch.ones(model.n_outputs))
    path = tmp_path / "equivariant.pt"
    save_checkpoint(path, model.eval(), {})
    return {"equivariant": path}


def _fly(conditions, checkpoints, duration=3.0, follower=Lemniscate, **components):
    """The leader hovers; the follower flies `follower` (a reference class) 0.6 m below it."""
    W = len(conditions) * len(SEEDS)
    reference = stack([Hover(LEADER, n_worlds=W), follower(LEADER - [0, 0, 0.6], n_worlds=W)])
    return fly_conditions(build_scene(), conditions, reference, SEEDS, duration, resolve_field_spec("so2"),
                          checkpoints, **components)


def test_the_names_parse_and_map_to_their_components(tmp_path):
    assert {"integral", "dob", "equivariant_dob", "deep_dob"} <= set(CONDITIONS)
    assert parse_conditions("baseline,integral,dob,equivariant_dob") == ["baseline", "integral", "dob", "equivariant_dob"]
    assert learned(["integral", "dob", "equivariant_dob", "deep"]) == ["equivariant", "deep"]
    assert data_variant("equivariant" + OBSERVED, "outdoor") == "equivariant-outdoor_dob"
    checkpoints = _checkpoint(tmp_path)
    assert isinstance(make_predictor("dob", None, {}), DisturbanceObserver)
    observed = make_predictor("equivariant_dob", None, checkpoints)
    assert isinstance(observed, DisturbanceObserver) and type(observed.inner).__name__ == "LearnedPredictor"
    lqr = FeedbackLinearisedLQR(LQRConfig(max_tilt_deg=30.0))
    integral = condition_controller("integral", lqr)
    assert isinstance(integral, IntegralLQR) and integral.config == lqr.config
    assert condition_controller("baseline", lqr) is lqr and condition_controller("dob") is None
    with pytest.raises(ConfigError, match="integral"):
        condition_controller("integral", object())


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    checkpoints = _checkpoint(tmp_path_factory.mktemp("models"))
    mixed = _fly(["baseline", "integral", "oracle", "dob", "equivariant", "equivariant_dob"], checkpoints)
    alone = _fly(["baseline", "oracle", "equivariant"], checkpoints)
    under = _fly(["baseline", "integral", "dob"], checkpoints, follower=Hover)  # held in the wake
    return mixed, alone, under


def test_splitting_the_batch_changes_no_bit_of_the_fused_conditions(flights):
    mixed, alone, _ = flights
    for c in ("baseline", "oracle", "equivariant"):
        for a, b in zip(mixed[c], alone[c]):
            for key in ("pos", "u_cmd", "f_hat", "field_mean"):
                assert np.array_equal(a[key], b[key]), (c, key)


def test_the_observer_and_the_integral_act_and_fly(flights):
    mixed, _, under = flights
    for c in ("integral", "dob", "equivariant_dob"):
        assert all(L.ok for L in mixed[c]), c
        assert all(L.meta["condition"] == c for L in mixed[c])
    # held 0.6 m under the leader: the observer's prediction is the steady wake the follower feels (tau 0.125 s,
    # so settled after 2 s), the integral LQR predicts nothing
    tail = slice(-50, None)
    for L in under["dob"]:
        felt = np.mean(L["field_mean"][tail, 1, 2])
        assert felt < -0.5  # a wake worth estimating
        assert abs(np.mean(L["f_hat"][tail, 1, 2]) - felt) < 0.1 * abs(felt), (np.mean(L["f_hat"][tail, 1, 2]), felt)
    assert all(np.all(L["f_hat"] == 0) for L in under["integral"])
    # both hold the follower closer to its point than the baseline, which sags in the wake
    err = {c: np.mean([np.mean(np.abs(L["pos"][tail, 1, 2] - L["ref_pos"][tail, 1, 2])) for L in under[c]])
           for c in ("baseline", "integral", "dob")}
    assert err["dob"] < 0.5 * err["baseline"] and err["integral"] < err["baseline"], err


def test_integral_needs_the_lqr(tmp_path):
    with pytest.raises(ConfigError, match="integral"):
        _fly(["baseline", "integral"], {}, duration=0.1, controller=IntegralLQR())
