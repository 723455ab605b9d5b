"""The models' compiled passes (`downwash.set_fused`): the NumPy twin's neighbour sets and
forces, one compiled function per kind, and swarm flights on the simulator's fused path.

Tolerance. The compiled pass and the NumPy twin (`LearnedPredictor(backend="numpy")`) compute the
same float64 expressions in another order: the twin's networks are BLAS products (their own
summation order, FMA on some CPUs) and the pair force is assembled as the pair kernel assembles
it (``f1 px / r`` where the twin has ``f1 (px / r)``). Measured differences are a few ulps of the
largest output (at most 3e-15 of max(|F|, 1) over 900 random cases of every kind; 60-95 % of the
components bit-equal); the tests allow `TOL` = 1e-12 of it, the bound the
twin and the torch model are held to (tests/test_set_models.py), while a wrong weight, slot or
neighbour moves the output by far more. NaN appears in the same places in both. The neighbour
selection itself is compared exactly (indices and mask). Flights: the fused tick and the readable
path call the same kernel, so their flights are compared bit for bit (as tests/test_fast_path.py
does for the pair predictor).
"""

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

import downwash.predictor as predictor_module
from downwash_core.errors import ConfigError
from downwash_core.state import VehicleStates
from downwash.set_fused import COMPILED_KINDS
from sim.neighbours import select_into
from downwash.predictor import LearnedPredictor
from downwash.registry import SET_KINDS, make_model
from downwash.set_models import SummedPairwise
from sim.neighbours import NeighbourSet, select_neighbours
from sim.predictor import PerWorldPredictor
from sim.presets import make_preset
from sim.simulator import Simulator
from test_checkpoint import trained_like  # tests/ is on sys.path under pytest
from test_fast_path import _assert_same
from test_features import random_rotations
from test_set_models import _one_torch_thread, _settings, as_checkpoint, randomised  # noqa: F401 (an autouse fixture)

TOL = 1e-12  # of max(|F|, 1): see the module docstring (<= 1.6e-3 of it measured under Prescott to SkylakeX OpenBLAS)
LINEAR = {"type": "sim.aggregation.LinearSuperposition", "name": "linear"}
KINDS = list(SET_KINDS)
PAIR_KINDS = [("equivariant", "5"), ("equivariant", "6"), ("equivariant_general", None), ("shallow", None),
              ("deep", None)]


_MODELS: dict = {}


def random_model(kind: str, seed: int = 0, **architecture):
    """A model with random weights and normalisation (cached: never modify it); summed_pairwise
    wraps a random pair model of `PAIR_KINDS[seed % 5]`; float32 unless `double=True`."""
    key = (kind, seed, tuple(sorted(architecture.items())))
    if key not in _MODELS:
        double = architecture.pop("double", False)
        if kind == "summed_pairwise":
            pair_kind, feature_set = PAIR_KINDS[seed % len(PAIR_KINDS)]
            model = SummedPairwise(trained_like(pair_kind, feature_set, seed=seed))
        else:
            torch.manual_seed(seed)
            model = randomised(make_model(kind, **architecture), seed)
        _MODELS[key] = (model.double() if double else model).eval()
    return _MODELS[key]


def random_states(rng, W: int, V: int, grid: bool, n_nan: int) -> VehicleStates:
    """A vertical stack of V vehicles in W worlds, tilted and moving. grid: positions on a 0.25 m grid
    (many exactly equal distances); n_nan: that many worlds with one diverged (all-NaN) vehicle."""
    if grid:
        pos = rng.integers(-2, 3, size=(W, V, 3)) * 0.25
        pos[..., 2] += 3.0 - 0.5 * np.arange(V)
    else:
        pos = rng.normal(scale=0.3, size=(W, V, 3))
        pos[..., 2] += 3.0 - 0.45 * np.arange(V)
    vel = rng.normal(scale=0.5, size=(W, V, 3))
    rot = random_rotations(rng, W * V, 0.4).reshape(W, V, 3, 3)
    for w in rng.permutation(W)[:n_nan]:
        i = rng.integers(V)
        pos[w, i], vel[w, i], rot[w, i] = np.nan, np.nan, np.nan
    return VehicleStates(pos, vel, rot)


def _predictors(model, ns, clamp):
    ck = as_checkpoint(model, ns, {"aggregation": LINEAR})
    return LearnedPredictor(ck, clamp=clamp), LearnedPredictor(ck, backend="numpy", clamp=clamp)


def _assert_close(got, want):
    scale = max(np.nanmax(np.abs(want), initial=0.0), 1.0)
    np.testing.assert_allclose(got, want, rtol=0, atol=TOL * scale, equal_nan=True)


# ------------------------------------------------------------------------------ the neighbour set


@_settings(60)
@given(seed=st.integers(0, 2**31 - 1), V=st.integers(1, 8), K=st.integers(1, 9), grid=st.booleans(),
       radius=st.sampled_from([None, 0.3, 0.6, 1.0]), n_nan=st.integers(0, 2))
def test_selection_is_select_neighbours(seed, V, K, grid, radius, n_nan):
    """Indices and mask exactly those of `sim.neighbours.select_neighbours`: ties (the grid) by vehicle
    index, NaN vehicles in no set, the radius, fewer vehicles than slots."""
    rng = np.random.default_rng(seed)
    states = random_states(rng, 3, V, grid, n_nan)
    ns = NeighbourSet(K, radius)
    index, mask = select_neighbours(states.pos, ns)
    radius2 = np.inf if radius is None else radius**2
    key, idx = np.empty(max(V - 1, 1)), np.empty(max(V - 1, 1), np.int64)
    for w in range(3):
        for j in range(V):
            n = select_into(states.pos, w, j, radius2, K, key, idx)
            assert mask[w, j].sum() == n and mask[w, j, :n].all()
            assert np.array_equal(idx[:n], index[w, j, :n])


def test_exact_ties_go_to_the_lower_vehicle_index():
    """Four vehicles at exactly the same distance from vehicle 0, two slots: vehicles 1 and 2."""
    pos = np.array([[[0.0, 0, 0], [0, 0, 1], [1, 0, 0], [0, -1, 0], [-1, 0, 0]]])
    key, idx = np.empty(4), np.empty(4, np.int64)
    assert select_into(pos, 0, 0, np.inf, 2, key, idx) == 2 and list(idx[:2]) == [1, 2]
    assert select_neighbours(pos, NeighbourSet(2))[0][0, 0].tolist() == [1, 2]


# ------------------------------------------------------------------------------ the models


@pytest.mark.parametrize("kind", KINDS)
@_settings(30)
@given(seed=st.integers(0, 2**31 - 1), W=st.integers(1, 4), V=st.integers(2, 8), K=st.integers(1, 9),
       grid=st.booleans(), radius=st.sampled_from([None, 0.35, 0.7]), n_nan=st.integers(0, 2), clamp=st.booleans(),
       double=st.booleans())
def test_compiled_equals_the_numpy_twin(kind, seed, W, V, K, grid, radius, n_nan, clamp, double):
    """Every kind, random weights (float32 and float64 models), random states with exact distance ties,
    diverged vehicles, a radius that drops some and sets with fewer vehicles than slots, with and
    without the clamp: the compiled pass is the NumPy twin to `TOL`."""
    rng = np.random.default_rng(seed)
    model = random_model(kind, seed % 5, double=double)
    states = random_states(rng, W, V, grid, min(n_nan, W))
    ns = NeighbourSet(K, radius)
    bound = None
    if clamp:  # a bound some vehicles exceed
        free = _predictors(model, ns, None)[1](states, states)
        norm = np.linalg.norm(free, axis=-1)
        bound = float(np.median(norm[norm > 0])) if (norm > 0).any() else 1.0
    compiled, numpy_twin = _predictors(model, ns, bound)
    want = numpy_twin(states, states)
    got = compiled(states, states)
    _assert_close(got, want)
    if bound is not None:
        assert np.all(np.linalg.norm(got, axis=-1)[np.isfinite(got).all(-1)] <= bound * (1 + 1e-12))
    # the C function writes the same as the kernel
    out = np.full_like(got, -7.0)
    abi = compiled.compiled()
    _call_c(abi, states, out)
    assert np.array_equal(out, got, equal_nan=True)


def _call_c(abi, states, out):
    """Call a `CompiledPredictor` through ctypes, as the fused tick calls it."""
    import ctypes

    f = ctypes.CFUNCTYPE(None, *[ctypes.c_int64] * 2, *[ctypes.c_void_p] * 9)(abi.address)
    pos, vel, rot = (np.ascontiguousarray(a, dtype=np.float64) for a in (states.pos, states.vel, states.rot))
    W, V = pos.shape[:2]
    f(W, V, pos.ctypes.data, vel.ctypes.data, rot.ctypes.data, pos.ctypes.data, vel.ctypes.data, rot.ctypes.data,
      abi.params.ctypes.data, abi.iparams.ctypes.data, out.ctypes.data)


@pytest.mark.parametrize("kind", KINDS)
def test_a_diverged_vehicle_and_a_lone_one_get_zero(kind):
    """A NaN vehicle is nobody's neighbour and has none; a vehicle beyond the radius of all others gets 0."""
    rng = np.random.default_rng(5)
    states = random_states(rng, 2, 4, False, 0)
    states.pos[0, 1], states.vel[0, 1], states.rot[0, 1] = np.nan, np.nan, np.nan
    states.pos[1, 3] += [10.0, 0.0, 0.0]
    compiled, numpy_twin = _predictors(random_model(kind, 2), NeighbourSet(3, radius=2.0), None)
    got = compiled(states, states)
    assert np.isfinite(got).all() and (got[0, 1] == 0).all() and (got[1, 3] == 0).all()
    _assert_close(got, numpy_twin(states, states))


def test_one_compiled_function_per_kind_for_every_model():
    """Models of one kind with other architectures, feature sets, pair kinds, neighbour sets and clamps
    share one C function and one kernel signature: a model is data, never a recompilation."""
    rng = np.random.default_rng(0)
    states = {V: random_states(rng, 2, V, False, 0) for V in (2, 5)}
    models = {
        "summed_pairwise": [random_model("summed_pairwise", s) for s in range(5)],
        "deepsets_equivariant": [random_model("deepsets_equivariant", 0),
                                 random_model("deepsets_equivariant", 1, feature_set="5", phi_hidden=(16,), latent=4,
                                              vectors=2, rho_hidden=(8, 8)),
                                 random_model("deepsets_equivariant", 2, feature_set="6", double=True)],
        "deepsets": [random_model("deepsets", 0), random_model("deepsets", 1, phi_hidden=(16,), latent=8,
                                                              rho_hidden=(12,))],
    }
    for kind, ms in models.items():
        addresses = set()
        for m in ms:
            for ns, clamp in ((NeighbourSet(4), None), (NeighbourSet(1, radius=0.5), 2.0)):
                compiled, numpy_twin = _predictors(m, ns, clamp)
                addresses.add(compiled.compiled().address)
                for s in states.values():
                    _assert_close(compiled(s, s), numpy_twin(s, s))
        assert addresses == {COMPILED_KINDS[kind].address}, kind
        assert len(COMPILED_KINDS[kind].kernel.signatures) == 1, (kind, COMPILED_KINDS[kind].kernel.signatures)


def test_the_default_backend_is_compiled_where_the_kind_has_one(monkeypatch):
    ck = as_checkpoint(random_model("deepsets", 0), NeighbourSet(2), {"aggregation": LINEAR})
    assert LearnedPredictor(ck).backend == "compiled" and LearnedPredictor(ck).compiled() is not None
    for backend in ("numpy", "torch"):
        assert LearnedPredictor(ck, backend=backend).compiled() is None
    monkeypatch.delitem(predictor_module.COMPILED_KINDS, "deepsets")  # a kind without a compiled form
    assert LearnedPredictor(ck).backend == "numpy"
    with pytest.raises(ConfigError, match="no compiled form"):
        LearnedPredictor(ck, backend="compiled")


# ------------------------------------------------------------------------------ in the loop


def _fly_both(preset, W, n_ticks, predictor):
    """(rows, simulator) of the fused and the readable path."""
    out = []
    scene = preset.scene()
    for fast in (True, False):
        sim = Simulator(scene, preset.reference(W), list(range(10, 10 + W)), predictor=predictor, fast=fast)
        assert (sim._plan is not None) == fast, "the fused path was expected to apply"
        out.append(([dict(sim.tick()) for _ in range(n_ticks)], sim))
    return out


@pytest.mark.parametrize("W", [1, 3])
@pytest.mark.parametrize("kind", KINDS)
def test_a_formation_flies_the_fused_path_as_the_readable_one(kind, W):
    """formation5 with a model of sets: the fused tick (its C function) and the readable path (the same
    kernel through `__call__`) give the same flight bit for bit, and the model acts on it."""
    preset = make_preset("formation5")
    pred = LearnedPredictor(as_checkpoint(random_model(kind, 1), NeighbourSet(4), {"aggregation": LINEAR}), clamp=3.0)
    fused, readable = _fly_both(preset, W, 60, pred)
    _assert_same(fused, readable)
    assert np.abs(fused[1].f_hat).max() > 1e-3 and fused[1].active.all()


@pytest.mark.parametrize("kind", KINDS)
def test_the_fused_flight_follows_the_numpy_twins(kind):
    """The fused flight with the compiled pass and the readable flight with the NumPy twin differ
    only by the twin's rounding, carried through 1.2 s of closed loop (well below a micrometre)."""
    preset = make_preset("formation5")
    ck = as_checkpoint(random_model(kind, 3), NeighbourSet(4, radius=1.5), {"aggregation": LINEAR})
    sims = []
    for fast, backend in ((True, "compiled"), (False, "numpy")):
        pred = LearnedPredictor(ck, backend=backend, clamp=1.0)
        sim = Simulator(preset.scene(), preset.reference(2), [4, 5], predictor=pred, fast=fast)
        assert (sim._plan is not None) == fast
        for _ in range(60):
            sim.tick()
        sims.append(sim)
    assert np.abs(sims[0].f_hat).max() > 1e-3 and sims[0].active.all() and sims[1].active.all()
    # the twin's products (OpenBLAS's order for the deep sets) against the compiled pass, over 60 ticks:
    # <= 1.5e-15 measured under every OpenBLAS and torch kernel (both checks), far under 1e-9
    np.testing.assert_allclose(sims[0].f_hat, sims[1].f_hat, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sims[0].pos_est, sims[1].pos_est, rtol=0, atol=1e-9)


def test_a_batch_of_swarm_models_per_world_flies_the_fused_path():
    """One batch, a model of each kind (and two of one kind) world by world (`PerWorldPredictor`): each
    world calls its kind's C function with its model's constants, as the readable path routes them."""
    ns = NeighbourSet(4)
    predictors = [LearnedPredictor(as_checkpoint(random_model(kind, seed), ns, {"aggregation": LINEAR}), clamp=3.0)
                  for kind, seed in (("summed_pairwise", 2), ("deepsets_equivariant", 1), ("deepsets", 1),
                                     ("deepsets_equivariant", 4))]
    W = 6
    pred = PerWorldPredictor(predictors, np.arange(W) % len(predictors))
    _assert_same(*_fly_both(make_preset("formation5"), W, 40, pred))
