"""Off means off: a world flown without downwash never feels the field, even a field that is NaN
wherever it flies (a user's field can pass the check points and be NaN elsewhere)."""

import numpy as np
import pytest
import torch

from downwash.checkpoint import save_checkpoint
from downwash.guard import support_of
from downwash.conditions import CONDITIONS, fly_conditions, learned
from downwash.registry import make_model
from downwash_core.status import Status
from sim.field import check_field
from sim.fields.registry import resolve_field_spec
from sim.scene import build_scene
from downwash_trajectories import Hover, Lemniscate, stack

LEADER = np.array([0.0, 0.0, 2.5])
SEEDS = [0, 1]
# where `check_field` evaluates a field (followers, and leaders as the other vehicle of a pair)
CHECK_POINTS = np.array([[0.0, 0.0, 1.9], [0.25, 0.0, 1.7], [0.0, 0.0, 2.5], [0.1, -0.2, 2.4]])


class NaNAwayFromTheCheckPoints:
    """The default field at the check points, NaN everywhere else (every point of a flight)."""

    def __init__(self):
        self.inner = resolve_field_spec("so2")

    def __call__(self, p_a, v_a, R_a, p_b, v_b):
        out = np.asarray(self.inner(p_a, v_a, R_a, p_b, v_b), float)
        near = (np.linalg.norm(np.asarray(p_b)[..., None, :] - CHECK_POINTS, axis=-1) < 1e-3).any(-1)
        return np.where(near[..., None], out, np.nan)

    def describe(self):
        return {"name": "nan_away_from_check_points"}


_RNG = np.random.default_rng(0)  # pairs beneath a hovering leader: the support its guarded conditions read
_SUPPORT = support_of(np.column_stack([_RNG.uniform(-0.5, 0.5, (400, 2)), -_RNG.uniform(0.3, 1.5, 400)]),
                      _RNG.normal(size=(400, 3)) * 0.05, _RNG.normal(size=(400, 3)) * 0.5,
                      np.broadcast_to(np.eye(3), (400, 3, 3)))


def _checkpoints(tmp_path):
    paths = {}
    for kind in learned(CONDITIONS):
        torch.manual_seed(0)
        model = make_model(kind)
        model.set_normalization(torch.zeros(model.n_features), torch.ones(model.n_features),
                                torch.zeros(model.n_outputs), torch.ones(model.n_outputs))
        if hasattr(model, "settle_spectral_norm"):
            model.settle_spectral_norm()
        paths[kind] = tmp_path / f"{kind}.pt"
        save_checkpoint(paths[kind], model.eval(), {"data": {"support": _SUPPORT.describe()}})  # for the guarded
    return paths


def _fly(field, checkpoints):
    W = len(CONDITIONS) * len(SEEDS)
    reference = stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=W)])
    return fly_conditions(build_scene(), CONDITIONS, reference, SEEDS, 1.0, field, checkpoints)


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    checkpoints = _checkpoints(tmp_path_factory.mktemp("models"))
    return _fly(NaNAwayFromTheCheckPoints(), checkpoints), _fly(resolve_field_spec("so2"), checkpoints)


def test_the_field_passes_the_checks_and_is_nan_in_flight():
    field = NaNAwayFromTheCheckPoints()
    check_field(field)  # finite where it is checked
    p = np.array([0.0, 0.0, 2.5]), np.zeros(3), np.eye(3), np.array([0.0, 0.0, 1.8]), np.zeros(3)
    assert np.isnan(field(*p)).all()


def test_no_downwash_never_feels_a_nan_field(flights):
    nan_field, finite_field = flights
    for log, reference in zip(nan_field["no_downwash"], finite_field["no_downwash"]):
        assert log.ok, log.meta["message"]
        assert len(log) == len(reference)
        for name in log.arrays:  # the field off: the same flight whatever the field
            assert np.array_equal(log[name], reference[name], equal_nan=True), name


def test_conditions_with_the_field_on_end_as_diverged_not_as_a_crash(flights):
    nan_field, _ = flights
    for condition in CONDITIONS:
        if condition != "no_downwash":
            assert all(log.meta["status"] == Status.DIVERGED for log in nan_field[condition]), condition
