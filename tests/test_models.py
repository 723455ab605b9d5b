"""Models: parameter counts, the paper's equivariance theorem, spectral norms, errors, the predictor."""

import numpy as np
import pytest
import torch

from downwash_core import geometry
from downwash import features as F
from downwash.features import HISTORY_LAGS
from downwash.models import PAIRWISE_KINDS, DeepSNMLP, EquivariantModel, ShallowMLP, count_parameters
from downwash.registry import make_model
from downwash.predictor import LearnedPredictor
from downwash.train import TrainConfig, train_model
from downwash.datasets import Dataset
from sim.field import DownwashField
from sim.predictor import Predictor, VehicleStates
from test_features import random_rotations  # tests/ is on sys.path under pytest




def randomise(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """A float64 copy with random weights AND random normalisation (so that is tested too)."""
    g = torch.Generator().manual_seed(seed)
    model = model.double()
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * 0.5)
        k, m = model.n_features, model.n_outputs
        model.set_normalization(
            torch.randn(k, generator=g, dtype=torch.float64),
            torch.rand(k, generator=g, dtype=torch.float64) + 0.5,
            torch.randn(m, generator=g, dtype=torch.float64),
            torch.rand(m, generator=g, dtype=torch.float64) + 0.5,
        )
    return model.eval()


def equivariance_error(model, rng, n=256, max_tilt=0.0):
    """max |F(H dp, v_a, H v_b, R_a) - H F(dp, v_a, v_b, R_a)| over random states and angles about n."""
    dp = rng.normal(size=(n, 3)) * [0.6, 0.6, 0.5] + [0, 0, -1.0]
    v_a = rng.normal(size=(n, 3)) * 0.3
    v_b = rng.normal(size=(n, 3)) * 0.6
    R_a = random_rotations(rng, n, max_tilt)
    H = geometry.rotation_about_axis(R_a[:, :, 2], rng.uniform(-np.pi, np.pi, n))
    rot = lambda v: np.einsum("nij,nj->ni", H, v)  # noqa: E731
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        out = model(t(dp), t(v_a), t(v_b), t(R_a)).numpy()
        out_rot = model(t(rot(dp)), t(v_a), t(rot(v_b)), t(R_a)).numpy()
    assert np.isfinite(out).all()
    return float(np.max(np.abs(out_rot - rot(out)))), float(np.max(np.abs(out)))


def test_parameter_counts():
    assert count_parameters(make_model("equivariant")) == 258
    assert count_parameters(make_model("equivariant", "5")) == 258
    assert count_parameters(make_model("equivariant", "6")) == 290
    assert count_parameters(make_model("shallow")) == 323
    n_deep = count_parameters(make_model("deep"))
    assert 9000 <= n_deep <= 10000
    assert n_deep == 9583  # the paper's count, widths 6-40x6-25-3
    assert sum(isinstance(m, torch.nn.Module) and hasattr(m, "effective_weight") for m in make_model("deep").net) == 8


def test_registry_and_attributes():
    assert list(PAIRWISE_KINDS) == ["shallow", "deep", "equivariant", "equivariant_general", "equivariant_memory",
                                    "deep_memory"]
    for kind, cls in PAIRWISE_KINDS.items():
        m = make_model(kind)
        assert isinstance(m, cls) and m.kind == kind
        assert m.feature_set == {"equivariant": "5", "equivariant_general": "general", "equivariant_memory":
                                 "general_memory", "deep_memory": "raw_memory"}.get(kind, "raw")
        assert m.in_mean.dtype == torch.float32
        assert {"in_mean", "in_std", "out_mean", "out_std"} <= set(m.state_dict())


@pytest.mark.parametrize("feature_set", ["5", "6"])
@pytest.mark.parametrize("max_tilt", [0.0, 0.7])
def test_equivariant_model_is_equivariant(feature_set, max_tilt):
    """The paper's theorem 1, for several weight initialisations, a level and a tilted leader."""
    rng = np.random.default_rng(0)
    for seed in range(4):
        model = randomise(EquivariantModel(feature_set), seed)
        err, scale = equivariance_error(model, rng, max_tilt=max_tilt)
        assert scale > 0.1  # a non-trivial output
        # torch's MLP (MKL products, in their kernel's order) on rotated inputs: the round-off of two evaluations,
        # ~width * eps * |W| |h|; 1.7e-14 measured under torch's default, AVX2 and AVX-512 kernels: 1e-10 is 6000x
        assert err < 1e-10, (seed, err)


@pytest.mark.parametrize("kind", ["shallow", "deep"])
def test_baselines_are_not_equivariant(kind):
    rng = np.random.default_rng(1)
    for seed in range(3):
        model = randomise(make_model(kind), seed)
        if isinstance(model, DeepSNMLP):
            model.settle_spectral_norm()
        err, scale = equivariance_error(model, rng)
        assert err > 1e-2 * scale and err > 1e-3, (seed, err, scale)


def test_float64_forward_and_shapes():
    for kind in PAIRWISE_KINDS:
        model = make_model(kind).double()
        x = torch.zeros(4, 7, 3, dtype=torch.float64)
        R = torch.eye(3, dtype=torch.float64).expand(4, 7, 3, 3)
        hist = torch.zeros(4, 7, len(HISTORY_LAGS), 3, dtype=torch.float64) if model.memory else None
        out = model(x, x, x, R, hist)
        assert out.shape == (4, 7, 3) and out.dtype == torch.float64
        out32 = make_model(kind)(np.zeros((5, 3)), np.zeros((5, 3)), np.zeros((5, 3)), np.broadcast_to(np.eye(3), (5, 3, 3)),
                                 None if hist is None else np.zeros((5, len(HISTORY_LAGS), 3)))
        assert out32.shape == (5, 3) and out32.dtype == torch.float32


def test_equivariant_model_safe_on_axis_and_at_rest():
    model = randomise(EquivariantModel("6"), 3)
    dp = torch.tensor([[0.0, 0.0, -0.7], [0.0, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    v = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    R = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    out = model(dp, v, v, R)
    assert torch.isfinite(out).all()
    assert torch.allclose(out[:, :2], torch.zeros(2, 2, dtype=torch.float64))  # no lateral force on the axis
    out.sum().backward()
    assert torch.isfinite(dp.grad).all() and torch.isfinite(v.grad).all()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


def small_field_data(n=3000, seed=0):
    """Samples below a level leader labelled by the true field, in 6 flights."""
    rng = np.random.default_rng(seed)
    dp = np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)), -rng.uniform(0.3, 1.6, n)])
    v_a, v_b = rng.normal(size=(n, 3)) * 0.05, rng.normal(size=(n, 3)) * 0.5
    R = np.broadcast_to(np.eye(3), (n, 3, 3))
    y = DownwashField()(np.zeros(3), v_a, R, dp, v_b)
    return Dataset.from_pairs(dp, v_a, v_b, R, y, np.arange(n) * 6 // n, field_mean=y)


def test_deep_spectral_norms_bounded_after_training():
    ds = small_field_data()
    model, _ = train_model("deep", ds, None, TrainConfig(max_epochs=3, min_steps=0, batch_size=256))
    norms = [float(torch.linalg.matrix_norm(layer.effective_weight().detach(), ord=2)) for layer in model.spectral_layers()]
    assert len(norms) == 8
    assert max(norms) <= 2.0 + 1e-4, norms
    assert min(norms) >= 2.0 - 1e-3, norms  # torch's normalisation makes the bound tight


def test_deep_spectral_norm_settles_from_a_poor_estimate():
    model = make_model("deep")
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    x = torch.randn(64, 3)
    R = torch.eye(3).expand(64, 3, 3)
    for _ in range(5):
        loss = model(x, x, x, R).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.settle_spectral_norm()
    model.eval()
    for layer in model.spectral_layers():
        assert float(torch.linalg.matrix_norm(layer.effective_weight().detach(), ord=2)) <= 2.0 + 1e-4


def test_bad_kind_and_feature_set():
    with pytest.raises(ValueError, match=r"model kind: unknown 'mlp'; allowed: shallow, deep, equivariant, equivariant_general, equivariant_memory, deep_memory, summed_pairwise, deepsets_equivariant, deepsets"):
        make_model("mlp")
    with pytest.raises(ValueError, match=r"feature_set: model kind 'shallow' accepts \['raw'\], got '6'"):
        make_model("shallow", "6")
    with pytest.raises(ValueError, match=r"feature_set: model kind 'equivariant' accepts \['5', '6'\], got '7'"):
        make_model("equivariant", "7")
    with pytest.raises(ValueError, match=r"'deep' accepts \['raw'\], got '5'"):
        make_model("deep", "5")
    with pytest.raises(TypeError, match="bad architecture arguments"):
        make_model("shallow", width=3)
    with pytest.raises(ValueError, match=r"in_std: must be positive"):
        ShallowMLP().set_normalization(torch.zeros(6), torch.zeros(6), torch.zeros(3), torch.ones(3))
    with pytest.raises(ValueError, match=r"out_mean: expected shape \(2,\)"):
        EquivariantModel().set_normalization(torch.zeros(5), torch.ones(5), torch.zeros(3), torch.ones(2))


def test_folded_numpy_layers_match_the_torch_model():
    rng = np.random.default_rng(4)
    dp = rng.normal(size=(50, 3))
    va, vb = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    R = random_rotations(rng, 50, 0.5)
    hist = rng.normal(size=(50, len(HISTORY_LAGS), 3)) * 0.3
    for kind in PAIRWISE_KINDS:
        model = randomise(make_model(kind), 7)
        if isinstance(model, DeepSNMLP):
            model.settle_spectral_norm()
        x, basis = F.model_inputs(model.feature_set, dp, va, vb, R, hist)
        h = x
        layers = model.folded_layers()
        for w, b in layers[:-1]:
            h = np.maximum(h @ w.T + b, 0.0)
        out = h @ layers[-1][0].T + layers[-1][1]
        if basis is not None:
            out = F.assemble(out, basis)
        with torch.no_grad():
            ref = model(dp, va, vb, R, hist).numpy()
        # NumPy's BLAS against torch's MKL products (widths <= 40, float64): each sums in its kernel's order,
        # ~width * eps * |W| |h| ~ 1e-14 apart (1.9e-14 measured under every OpenBLAS and torch kernel)
        np.testing.assert_allclose(out, ref, rtol=1e-10, atol=1e-10)


def reference_prediction(model, states: VehicleStates) -> np.ndarray:
    """A plain loop over worlds and ordered pairs (the slow reference)."""
    W, V = states.pos.shape[:2]
    out = np.zeros((W, V, 3))
    for w in range(W):
        for j in range(V):
            for i in range(V):
                if i == j:
                    continue
                dp = states.pos[w, j] - states.pos[w, i]
                if -(dp @ states.rot[w, i][:, 2]) <= 0:
                    continue
                with torch.no_grad():
                    out[w, j] += model(dp, states.vel[w, i], states.vel[w, j], states.rot[w, i]).double().numpy()
    return out


def random_vehicle_states(rng, W, V):
    pos = rng.normal(size=(W, V, 3)) * [0.4, 0.4, 0.8] + [0, 0, 2.0]
    vel = rng.normal(size=(W, V, 3)) * 0.5
    rot = random_rotations(rng, W * V, 0.3).reshape(W, V, 3, 3)
    return VehicleStates(pos, vel, rot)


@pytest.mark.parametrize("backend", ["compiled", "numpy", "torch"])
@pytest.mark.parametrize("kind", ["equivariant", "shallow", "deep"])
def test_predictor_matches_a_per_pair_loop(kind, backend):
    rng = np.random.default_rng(5)
    model = randomise(make_model(kind), 11)
    if isinstance(model, DeepSNMLP):
        model.settle_spectral_norm()
    model = model.float().train()
    predictor = LearnedPredictor(model, backend=backend)
    assert isinstance(predictor, Predictor)
    for W, V in [(3, 3), (4, 2), (1, 2), (2, 1)]:
        # the estimates differ from the truth: a learned model must see only the estimates
        estimated, true = random_vehicle_states(rng, W, V), random_vehicle_states(rng, W, V)
        out = predictor(estimated, true)
        assert out.shape == (W, V, 3) and out.dtype == np.float64
        np.testing.assert_allclose(out, reference_prediction(model, estimated), rtol=1e-4, atol=1e-4)
        if V > 1:
            assert not np.allclose(out, reference_prediction(model, true), rtol=1e-4, atol=1e-4)
    # a follower above its leader gets nothing from it (estimated above, true below); the original model is untouched
    states = VehicleStates(np.array([[[0, 0, 1.0], [0, 0, 2.0]]]), np.zeros((1, 2, 3)), np.broadcast_to(np.eye(3), (1, 2, 3, 3)))
    true = VehicleStates(states.pos[:, ::-1].copy(), states.vel, states.rot)
    out = predictor(states, true)
    assert np.all(out[0, 1] == 0.0) and np.any(out[0, 0] != 0.0)
    # the predictor froze a copy: the original is still in training mode with gradients on
    assert model.training and all(p.requires_grad for p in model.parameters())
    assert predictor.model is not model and not predictor.model.training


def test_predictor_clamp_and_errors():
    rng = np.random.default_rng(6)
    model = randomise(make_model("shallow"), 2).float()
    states, true = random_vehicle_states(rng, 8, 3), random_vehicle_states(rng, 8, 3)
    free = LearnedPredictor(model)(states, true)
    clamped = LearnedPredictor(model, clamp=0.1)(states, true)
    norm_free, norm_clamped = np.linalg.norm(free, axis=-1), np.linalg.norm(clamped, axis=-1)
    assert np.all(norm_clamped <= 0.1 + 1e-12) and np.any(norm_free > 0.1)
    small = norm_free <= 0.1
    np.testing.assert_allclose(clamped[small], free[small])
    with pytest.raises(ValueError, match="clamp: expected None or a finite magnitude > 0"):
        LearnedPredictor(model, clamp=-1.0)
    with pytest.raises(ValueError, match=r"backend: expected one of \['compiled', 'numpy', 'torch'\], got 'jax'"):
        LearnedPredictor(model, backend="jax")
    with pytest.raises(TypeError, match="model: expected a per-neighbour model, a Checkpoint or a path, got Linear"):
        LearnedPredictor(torch.nn.Linear(3, 3))


@pytest.mark.parametrize("feature_set", ["5", "6", "raw"])
@pytest.mark.parametrize("clamp", [None, 0.2])
def test_compiled_predictor_equals_the_readable_one(feature_set, clamp):
    """The one-pass compiled predictor against the NumPy path (features, folded layers, basis,
    depth gate, clamp) to float64 rounding, for every feature set, with followers above and
    below their leaders, tilted leaders and 2-5 vehicles."""
    rng = np.random.default_rng(8)
    kind = "shallow" if feature_set == "raw" else "equivariant"
    models = [randomise(make_model(kind, feature_set), 4)]
    if feature_set == "raw":
        deep = randomise(make_model("deep"), 5)
        deep.settle_spectral_norm()
        models.append(deep)
    for model in models:
        fast = LearnedPredictor(model, clamp=clamp, backend="compiled")
        slow = LearnedPredictor(model, clamp=clamp, backend="numpy")
        for W, V in [(1, 2), (3, 2), (2, 3), (2, 5)]:
            states = random_vehicle_states(rng, W, V)
            got, want = fast(states), slow(states)
            assert np.abs(want).max() > 0
            # no BLAS on either side (the compiled loops and `matmul_rows`, both written out): the same on every
            # CPU, apart only where the two sum or assemble in another order (1.8e-15 measured)
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kind", sorted(PAIRWISE_KINDS))
@pytest.mark.parametrize("bad", [0, -1, False, True, 5000, "32", 2.5, None, "shape"])
def test_bad_layer_widths_raise_config_error_naming_hidden(kind, bad):
    """Widths are integers (not bools) in [1, MAX_WIDTH]: one for a one-hidden-layer model, a
    sequence for a deep one ("shape": the other form). A width of 0 used to build a zero-width
    layer, and torch only warned."""
    from downwash_core.errors import ConfigError

    deep = issubclass(PAIRWISE_KINDS[kind], DeepSNMLP)
    if bad == "shape":
        bad = 32 if deep else [32]
    elif deep:
        bad = [40, bad]
    with pytest.raises(ConfigError, match="hidden"):
        make_model(kind, hidden=bad)


@pytest.mark.parametrize("name", ["phi_hidden", "rho_hidden"])
@pytest.mark.parametrize("bad", [[0], [32, False], 32, "32"])
def test_bad_set_model_widths_raise_config_error_naming_them(name, bad):
    from downwash_core.errors import ConfigError

    with pytest.raises(ConfigError, match=name):
        make_model("deepsets_equivariant", **{name: bad})
