"""The generalised equivariant model: a tangential output channel and the leader's velocity as input."""

import numpy as np
import pytest
import torch

from downwash_core import geometry
from downwash_core.state import VehicleStates
from downwash.datasets import Dataset
from downwash.models import EquivariantModel, GeneralEquivariantModel, count_parameters
from downwash.predictor import LearnedPredictor
from downwash.train import TrainConfig, rmse, train_model
from sim.field import DownwashField
from test_features import random_rotations  # tests/ is on sys.path under pytest
from test_models import randomise


def _states(rng, n, max_tilt):
    dp = rng.normal(size=(n, 3)) * [0.6, 0.6, 0.5] + [0, 0, -1.0]
    return dp, rng.normal(size=(n, 3)) * 0.8, rng.normal(size=(n, 3)) * 0.6, random_rotations(rng, n, max_tilt)


def _apply(model, dp, v_a, v_b, R_a):
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        return model(t(dp), t(v_a), t(v_b), t(R_a)).numpy()


def test_parameter_count():
    assert count_parameters(GeneralEquivariantModel()) == 10 * 32 + 32 + 32 * 3 + 3 == 451


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("max_tilt", [0.0, 0.7])
def test_equivariant_when_the_whole_configuration_rotates_about_the_leader_axis(seed, max_tilt):
    """F(H dp, H v_a, H v_b) = H F(dp, v_a, v_b) for rotations H about n, in float64, for random
    weights and tilted leaders; rotating dp and v_b but NOT v_a breaks it (the model reads the
    leader's velocity direction, which a skewed wake needs)."""
    rng = np.random.default_rng(seed)
    model = randomise(GeneralEquivariantModel().double(), seed)
    dp, v_a, v_b, R_a = _states(rng, 256, max_tilt)
    H = geometry.rotation_about_axis(R_a[:, :, 2], rng.uniform(-np.pi, np.pi, 256))
    rot = lambda v: np.einsum("nij,nj->ni", H, v)  # noqa: E731
    out = _apply(model, dp, v_a, v_b, R_a)
    scale = np.abs(out).max()
    assert scale > 0.1 and np.isfinite(out).all()
    # torch's MLP (MKL products, their kernel's order) on rotated inputs: round-off only, <= 1.7e-5 of the
    # 1e-10 * scale allowed under torch's default, AVX2 and AVX-512 and every OpenBLAS kernel
    assert np.abs(_apply(model, rot(dp), rot(v_a), rot(v_b), R_a) - rot(out)).max() < 1e-10 * scale
    assert np.abs(_apply(model, rot(dp), v_a, rot(v_b), R_a) - rot(out)).max() > 1e-3 * scale


def test_it_tells_left_from_right_where_the_paper_model_cannot():
    """Mirroring the configuration in a plane through the axis changes the generalised model's
    output beyond the mirror image (the signed angles and t_hat); the paper's model is mirror-symmetric."""
    rng = np.random.default_rng(5)
    dp, v_a, v_b, _ = _states(rng, 128, 0.0)
    R_a = np.broadcast_to(np.eye(3), (128, 3, 3)).copy()
    M = np.diag([1.0, -1.0, 1.0])  # mirror y -> -y, a plane through the (world z) axis
    for cls, symmetric in ((EquivariantModel, True), (GeneralEquivariantModel, False)):
        model = randomise(cls().double(), 3)
        out = _apply(model, dp, v_a, v_b, R_a)
        mirrored = _apply(model, dp @ M, v_a @ M, v_b @ M, R_a)
        err = np.abs(mirrored - out @ M).max()
        # @ M (diagonal, +-1) is exact in any BLAS kernel, so a symmetric model's err is 0 (measured); a broken
        # symmetry is far above 1e-10 of the output
        assert (err < 1e-10 * np.abs(out).max()) == symmetric, (cls.__name__, err)


def test_compiled_predictor_equals_the_readable_one_for_the_general_model():
    rng = np.random.default_rng(9)
    model = randomise(GeneralEquivariantModel(), 4)
    for W, V in [(1, 2), (3, 3), (2, 5)]:
        pos, vel = rng.normal(size=(W, V, 3)), rng.normal(size=(W, V, 3))
        rot = random_rotations(rng, W * V, 0.4).reshape(W, V, 3, 3)
        states = VehicleStates(pos, vel, rot)
        fast = LearnedPredictor(model, clamp=3.0, backend="compiled")(states)
        slow = LearnedPredictor(model, clamp=3.0, backend="numpy")(states)
        assert np.abs(slow).max() > 0
        # no BLAS on either side (compiled loops, `matmul_rows`): the same on every CPU, apart only where the
        # two sum in another order (4e-16 measured)
        np.testing.assert_allclose(fast, slow, rtol=1e-10, atol=1e-12)


def _field_dataset(field, n, seed):
    """Samples of a field where flights go, the leader moving sideways at up to 1 m/s."""
    rng = np.random.default_rng(seed)
    dp = np.stack([rng.uniform(-0.8, 0.8, n), rng.uniform(-0.8, 0.8, n), -rng.uniform(0.4, 1.6, n)], axis=1)
    v_b = rng.uniform(-1, 1, (n, 3)) * [1, 1, 0.3]
    v_a = rng.uniform(-1, 1, (n, 3)) * [1, 1, 0.0]
    R_a = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    y = field(np.zeros((n, 3)), v_a, R_a, dp, v_b)
    flight = np.arange(n) // 500
    return Dataset.from_pairs(dp, v_a, v_b, R_a, y, flight, t=(np.arange(n) % 500) * 0.02, field_mean=y)


@pytest.mark.parametrize("knob", [{"swirl": 0.4}, {"skew": 0.35}])
def test_it_learns_swirl_and_skewed_wakes_that_the_paper_model_cannot(knob):
    """Trained on the same samples of the so2-swirl or so2-skew truth, the generalised model's
    validation RMSE is well below the paper model's, which has no tangential channel and no
    leader-velocity direction."""
    field = DownwashField(**knob)
    train, val = _field_dataset(field, 12000, 0), _field_dataset(field, 4000, 1)
    cfg = TrainConfig(seed=0, max_epochs=40, min_steps=600)
    general, _ = train_model("equivariant_general", train, None, cfg)
    paper, _ = train_model("equivariant", train, None, cfg)
    e_general, e_paper = rmse(general, val)[0], rmse(paper, val)[0]
    assert e_general < 0.7 * e_paper, (e_general, e_paper)
