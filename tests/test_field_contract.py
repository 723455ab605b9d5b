"""The compiled-field contract (`sim.field_contract`): the docs' Gaussian jet with a compiled form flies the
fused tick, bit for bit as its readable path, over several worlds with resets and actions; its compiled law is
its NumPy law to rounding; a compiled form the kernel cannot read is refused before any flight."""

import sys

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from experiments.benchmark.recipes import docs_blocks
from downwash_trajectories import Hover, Lemniscate, stack
from sim.field import pairwise_field, pairwise_forces
from sim.field_contract import CompiledField, field_law
from sim.predictor import OraclePredictor
from sim.scene import build_scene
from sim.simulator import Simulator

LEADER = np.array([0.0, 0.0, 2.5])


@pytest.fixture(scope="module")
def recipe(tmp_path_factory):
    """The page's field and its compiled form, as the modules mypkg.fields and mypkg.compiled_fields (numba
    caches by file)."""
    blocks = docs_blocks("A new field")
    plain, compiled = blocks[1], blocks[3]
    assert plain.startswith("# mypkg/fields.py") and compiled.startswith("# mypkg/compiled_fields.py")
    root = tmp_path_factory.mktemp("recipe")
    (root / "mypkg").mkdir()
    (root / "mypkg" / "__init__.py").write_text("")
    (root / "mypkg" / "fields.py").write_text(plain)
    (root / "mypkg" / "compiled_fields.py").write_text(compiled)
    sys.path.insert(0, str(root))
    try:
        import mypkg.compiled_fields as module

        yield module
    finally:
        sys.path.remove(str(root))
        for name in ("mypkg.compiled_fields", "mypkg.fields", "mypkg"):
            sys.modules.pop(name, None)


def _stack_reference(W):
    """Three vehicles, each below the one before: the bottom one sums two wakes; the middle one flies a
    small figure-eight through the leader's wake."""
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, 0.5], 0.15, 0.08, n_worlds=W),
                  Hover(LEADER - [0.05, 0, 1.0], n_worlds=W)])


def _fly(field, W, n_ticks, fast, **kw):
    """The rows of a flight of W worlds: world 1 reset a third of the way, residual actions every other tick."""
    sim = Simulator(build_scene(["a", "b", "c"]), _stack_reference(W), list(range(W)), field=field, fast=fast, **kw)
    rng = np.random.default_rng(5)
    rows = []
    for k in range(n_ticks):
        if k == n_ticks // 3 and W > 1:
            sim.reset(np.array([1]))
        residual = rng.normal(0.0, 0.3, (W, 3, 3)) if k % 2 else None
        rows.append(dict(sim.tick(residual=residual)))
    return rows, sim


@pytest.mark.parametrize("W", [1, 12])  # 12: chunks of worlds on two threads, each its block of the C call
def test_the_recipe_flies_fused_as_readable(recipe, W):
    field = recipe.CompiledGaussianJet()
    fused, sim = _fly(field, W, 60, fast=True)
    assert sim._plan is not None, "the compiled field was expected to fly the fused tick"
    readable, other = _fly(field, W, 60, fast=False)
    for k, (x, y) in enumerate(zip(fused, readable)):
        for name in x:
            assert np.array_equal(x[name], y[name], equal_nan=True), (k, name)
    assert np.array_equal(sim.physics.qpos, other.physics.qpos)
    pushed = np.array([row["field_mean"][:, 2, 2] for row in fused])
    assert pushed.mean() < -1.0  # the bottom vehicle feels the wakes above it


def test_the_compiled_law_is_the_numpy_law(recipe):
    """The compiled sum and terms agree with the field's NumPy __call__ over broadcast pairs, to rounding,
    with each pair's scale as a factor on its push."""
    field = recipe.CompiledGaussianJet(strength=2.5, width=0.3)
    rng = np.random.default_rng(0)
    W, V = 6, 4
    pos = LEADER + rng.uniform(-0.3, 0.3, (W, V, 3)) - np.array([0, 0, 0.45])[None, None] * np.arange(V)[None, :, None]
    vel = rng.normal(0, 0.4, (W, V, 3))
    angles = rng.normal(0, 0.2, (W, V))
    rot = np.zeros((W, V, 3, 3))
    rot[..., 0, 0], rot[..., 0, 2], rot[..., 2, 0], rot[..., 2, 2] = (np.cos(angles), np.sin(angles),
                                                                      -np.sin(angles), np.cos(angles))
    rot[..., 1, 1] = 1.0

    def numpy_law(*args):  # the field as a plain callable: pairwise_field's broadcast evaluation of __call__
        return field(*args)

    want = pairwise_field(numpy_law, pos, vel, rot)
    got = pairwise_field(field, pos, vel, rot)  # the field's pairwise: the compiled sum
    assert np.abs(want).max() > 0.5
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    terms = recipe.JET.pair_forces(pos, vel, rot, field.params)
    np.testing.assert_allclose(terms, pairwise_forces(numpy_law, pos, vel, rot), rtol=1e-12, atol=1e-12)
    scale = rng.uniform(0.5, 2.0, (V, V))
    np.testing.assert_allclose(field.pairwise(pos, vel, rot, scale), (terms * scale[None, :, :, None]).sum(axis=1),
                               rtol=1e-12, atol=1e-12)


def test_a_wrong_params_array_is_refused_before_flight(recipe):
    jet = recipe.CompiledGaussianJet

    class Float32Params(jet):
        def compiled_field(self):
            good = super().compiled_field()
            return good._replace(params=good.params.astype(np.float32))

    class ShortParams(jet):
        def compiled_field(self):
            return CompiledField(recipe.JET.compiled(self.params).address, self.params[:2].copy(), 3)

    class NotCompiled(jet):
        def compiled_field(self):
            return (recipe.JET.function.address, self.params)

    for cls, match in ((Float32Params, "Float32Params.compiled_field.*C-contiguous float64 array of shape \\(3,\\)"),
                       (ShortParams, "ShortParams.compiled_field.*shape \\(3,\\)"),
                       (NotCompiled, "NotCompiled.compiled_field.*expected a sim.field_contract.CompiledField")):
        with pytest.raises(ConfigError, match=match):
            Simulator(build_scene(), stack([Hover(LEADER, n_worlds=1), Hover(LEADER - [0, 0, 0.6], n_worlds=1)]),
                      [0], field=cls(), fast=True)
    with pytest.raises(ConfigError, match=r"jet_pair reads a C-contiguous float64 array of shape \(3,\)"):
        recipe.JET.compiled(np.zeros(2))
    with pytest.raises(ConfigError, match=r"jet_pair reads"):  # the readable sum checks them too
        recipe.JET.pairwise(np.zeros((1, 2, 3)), np.zeros((1, 2, 3)), np.zeros((1, 2, 3, 3)), np.zeros(4))
    with pytest.raises(TypeError, match="numba.njit function"):
        field_law(lambda *args: None, 1)


def test_an_oracle_of_the_field_flies_fused_as_readable(recipe):
    """The oracle predictor of a compiled field runs its C function in the fused tick, at the predictor's rate."""
    jet = recipe.CompiledGaussianJet(strength=2.0)
    field = recipe.CompiledGaussianJet()
    fused, sim = _fly(field, 4, 30, fast=True, predictor=OraclePredictor(jet))
    assert sim._plan is not None and sim._plan.laws[1] is not None
    readable, _ = _fly(field, 4, 30, fast=False, predictor=OraclePredictor(jet))
    for k, (x, y) in enumerate(zip(fused, readable)):
        for name in x:
            assert np.array_equal(x[name], y[name], equal_nan=True), (k, name)
    assert np.array([row["f_hat"][:, 2, 2] for row in fused]).mean() < -0.5  # the oracle saw the wakes


def test_what_flies_the_readable_path(recipe):
    """Another aggregation law, an oracle of the field among per-world predictors and a scene of mixed kinds whose
    pairs each have a field of their own fly the readable path, and fly."""
    jet = recipe.CompiledGaussianJet()
    reference = stack([Hover(LEADER, n_worlds=2), Hover(LEADER - [0, 0, 0.6], n_worlds=2)])
    from sim.aggregation import make_aggregation
    from sim.predictor import PerWorldPredictor, ZeroPredictor

    cases = [dict(field=jet, aggregation=make_aggregation("velocity")),
             dict(field=jet, predictor=PerWorldPredictor([ZeroPredictor(), OraclePredictor(jet)], np.array([0, 1])))]
    for kw in cases:
        sim = Simulator(build_scene(), reference, [0, 1], **kw)
        assert sim._plan is None
        assert np.all(np.isfinite(sim.tick()["field_mean"]))

    class ByKinds(type(jet)):
        def for_kinds(self, leader, follower):
            return type(self)(strength=self.strength * leader.mass / follower.mass)

    mixed = build_scene(kinds=["x500", "paper_quad"])
    assert Simulator(mixed, reference, [0, 1], field=ByKinds())._plan is None  # each pair its own field

    class AsGiven(type(jet)):
        def for_kinds(self, leader, follower):
            return self

    sims = [Simulator(mixed, reference, [0, 1], field=AsGiven(), fast=fast) for fast in (True, False)]
    assert sims[0]._plan is not None  # every pair flies it as given: fused, the pairs' factors all 1.0
    assert np.array_equal(sims[0]._plan.arrays["field_fn_scale"], np.ones((2, 2)))
    assert not np.array_equal(sims[0].vehicle_params.field_scale, np.ones((2, 2)))  # (the paper field's are not)
    for _ in range(5):
        rows = [dict(sim.tick()) for sim in sims]
        assert all(np.array_equal(rows[0][k], rows[1][k], equal_nan=True) for k in rows[0])
