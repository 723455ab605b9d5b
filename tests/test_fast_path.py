"""The fused compiled tick equals the readable path bit for bit, and falls back where it must."""

import copy
import dataclasses

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from downwash_core.params import RATES
from downwash.guard_fused import FRACTION, GAIN
from downwash.predictor import LearnedPredictor
from sim.aggregation import make_aggregation
from sim.field import DownwashField
from sim.fields.momentum import MomentumWake
from sim.physics import mj_step_address
from sim.predictor import OraclePredictor, PerWorldPredictor, ZeroPredictor
from sim.scene import build_scene
from sim.fused_abi import STEP_CALLER, STEP_ROWS, STEP_SERIAL
from sim.plan import _chunk_sizes
from sim.rows import Row
from sim.simulator import SimConfig, Simulator
from sim.wind import DrydenWind
from test_checkpoint import trained_like  # tests/ is on sys.path under pytest
from downwash_trajectories import Hover, Lemniscate, stack

LEADER = np.array([0.0, 0.0, 2.5])


@pytest.fixture(scope="module")
def scene():
    return build_scene()


@pytest.fixture(scope="module")
def models():
    return {"equivariant": trained_like("equivariant", "5"), "general": trained_like("equivariant_general", seed=3),
            "shallow": trained_like("shallow"), "deep": trained_like("deep")}


def _lemniscate(W, sep=0.6):
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, sep], n_worlds=W)])


def _fly_both(scene, W, n_ticks, actions=None, **components):
    """The rows of the fused and the readable path, and the two simulators."""
    out = []
    for fast in (True, False):
        sim = Simulator(scene, _lemniscate(W), list(range(10, 10 + W)), fast=fast, **components)
        assert (sim._plan is not None) == fast, "the fused path was expected to apply"
        rows = []
        for k in range(n_ticks):
            kw = actions(k) if actions is not None else {}
            rows.append(dict(sim.tick(**kw)))
        out.append((rows, sim))
    return out


def _assert_same(fused, readable):
    (rows_f, sim_f), (rows_r, sim_r) = fused, readable
    assert len(rows_f) == len(rows_r)
    for k, (a, b) in enumerate(zip(rows_f, rows_r)):
        assert a.keys() == b.keys()
        for name in a:
            assert np.array_equal(a[name], b[name], equal_nan=True), (k, name)
    for name in ("t", "tick_index", "status", "active", "pos_est", "vel_est", "turb", "gust_state", "f_hat"):
        assert np.array_equal(getattr(sim_f, name), getattr(sim_r, name), equal_nan=True), name
    assert sim_f.message == sim_r.message
    assert np.array_equal(sim_f.physics.qpos, sim_r.physics.qpos, equal_nan=True)
    assert np.array_equal(sim_f.physics.ctrl, sim_r.physics.ctrl, equal_nan=True)


@pytest.mark.parametrize("W", [1, 16])  # 16: chunks of worlds on two threads, offsets into the tables
def test_fused_equals_readable_with_a_predictor_per_world(scene, models, W):
    """A `PerWorldPredictor` of zero, oracle and compiled learned predictors (the experiments' one
    batch of many conditions) flies the fused path, world by world as the readable path."""
    predictors = [ZeroPredictor(), OraclePredictor(DownwashField()), LearnedPredictor(models["equivariant"], clamp=6.0),
                  LearnedPredictor(models["deep"]), LearnedPredictor(models["general"])]
    assignment = np.arange(W) % len(predictors) if W > 1 else np.array([2])
    pred = PerWorldPredictor(predictors, assignment)
    _assert_same(*_fly_both(scene, W, 60, field=DownwashField(swirl=0.2), predictor=pred))


@pytest.mark.parametrize("W", [1, 3])
@pytest.mark.parametrize("predictor", ["zero", "oracle", "equivariant", "equivariant_general", "shallow", "deep"])
def test_fused_equals_readable(scene, models, W, predictor):
    field = DownwashField(swirl=0.2, skew=0.1)
    pred = {
        "zero": lambda: ZeroPredictor(), "oracle": lambda: OraclePredictor(DownwashField()),
        "equivariant": lambda: LearnedPredictor(models["equivariant"], clamp=6.0),
        "equivariant_general": lambda: LearnedPredictor(models["general"]),
        "shallow": lambda: LearnedPredictor(models["shallow"], clamp=4.0),
        "deep": lambda: LearnedPredictor(models["deep"]),
    }[predictor]()
    _assert_same(*_fly_both(scene, W, 60, field=field, predictor=pred, field_enabled=np.arange(W) % 2 == 0))


@pytest.mark.parametrize("W", [1, 2])
def test_fused_equals_readable_with_wind_actions_refills_and_other_rates(scene, models, W):
    rng = np.random.default_rng(0)
    residual = rng.normal(size=(80, W, 2, 3))
    override = np.where(rng.random((80, W, 2, 3)) < 0.5, np.nan, rng.normal(size=(80, W, 2, 3)))

    def actions(k):  # residual, override, both or none, by turns
        return [{}, {"residual": residual[k]}, {"override": override[k]}, {"residual": residual[k], "override": override[k]}][k % 4]

    # a noise block of 3 autopilot ticks runs out in the middle of a controller tick of 4
    config = SimConfig(noise_block=3, rates=dataclasses.replace(RATES, autopilot_per_control=4))
    wind = DrydenWind(mean=(1.5, 0.5, 0.0), w20=8.0)
    pred = LearnedPredictor(models["equivariant"], clamp=6.0)
    _assert_same(*_fly_both(scene, W, 80, actions, config=config, wind=wind, predictor=pred))


def test_threads_and_models_of_their_own(scene, models):
    """A batch large enough for one chunk of worlds per thread, and a batch whose worlds have
    models of their own (the batch steps them): both equal the readable path."""
    wind = DrydenWind(mean=(1.0, 0.0, 0.0), w20=5.0)
    fused, readable = _fly_both(scene, 33, 30, wind=wind, predictor=LearnedPredictor(models["equivariant"]), n_threads=2)
    plan = fused[1]._plan
    assert plan.stepping == STEP_ROWS and plan.n_threads == 2  # chunks of worlds, large first, on two threads
    bounds = plan.chunks[1, :, :2]
    assert np.array_equal(np.diff(bounds, axis=1)[:, 0], [8, 8, 4, 4, 2, 2, 2, 3]) and bounds[0, 0] == 0
    assert np.array_equal(bounds[1:, 0], bounds[:-1, 1]) and bounds[-1, 1] == 33
    _assert_same(fused, readable)
    out = []
    for fast in (True, False):
        sim = Simulator(scene, _lemniscate(3), [0, 1, 2], fast=fast, predictor=OraclePredictor(DownwashField()))
        sim.physics.set_body_mass(np.array([1]), scene.body_ids[1:], np.array([[0.9]]))
        rows = [dict(sim.tick()) for _ in range(30)]
        assert fast == (sim._plan is not None) and (not fast or sim._plan.stepping == STEP_CALLER)
        out.append((rows, sim))
    _assert_same(*out)
    assert Simulator(scene, _lemniscate(1), [0])._plan.stepping == STEP_SERIAL


def test_fused_equals_readable_when_worlds_end(scene):
    """Worlds that hit the ground, collide or diverge end alike on both paths, the others fly on."""
    W = 3
    follower = np.array([[0, 0, 1.9], [0, 0, -1.0], [0, 0, 2.5]])  # ok, into the ground, into the leader
    leader = np.array([LEADER, LEADER, [0.0, 0.15, 2.5]])
    out = []
    for fast in (True, False):
        sim = Simulator(scene, stack([Hover(leader), Hover(follower)]), [0, 1, 2], fast=fast)
        out.append(([dict(sim.tick()) for _ in range(60)], sim))
    _assert_same(*out)
    assert out[0][1].status.tolist() == [0, 2, 3]
    for fast in (True, False):  # worlds that diverge (the physics reports it), alone and in a batch
        for W in (1, 3):
            sim = Simulator(scene, _lemniscate(W), list(range(W)), fast=fast)
            sim.physics.qvel[0] = 1e12
            sim.tick()
            assert sim.status.tolist() == [1] + [0] * (W - 1) and sim.active.tolist() == [False] + [True] * (W - 1)


def test_the_fused_path_rebinds_when_components_change(scene, models):
    """Replacing a component, or the serial physics copying its model, rebinds; the flight stays
    bit-identical to the readable path doing the same."""
    out = []
    for fast in (True, False):
        sim = Simulator(scene, _lemniscate(1), [5], fast=fast)
        rows = [dict(sim.tick()) for _ in range(10)]
        sim.predictor = LearnedPredictor(models["equivariant"])
        sim.field = DownwashField(strength=8.0)
        rows += [dict(sim.tick()) for _ in range(10)]
        sim.physics.set_body_mass(np.array([0]), scene.body_ids[1:], np.array([[0.8]]))
        rows += [dict(sim.tick()) for _ in range(10)]
        assert (sim._plan is not None) == fast
        out.append((rows, sim))
    _assert_same(*out)
    sim = out[0][1]
    sim.fast = False
    sim.tick()
    assert sim._plan is None


@pytest.mark.parametrize("W", [1, 16])  # 16: chunks of worlds on two threads, offsets into the guard's state
def test_fused_equals_readable_with_a_guard(scene, models, W):
    """A guard around a compiled model flies the fused path, its pass after the model (`downwash.guard_fused`):
    the same rows, its applied fraction included, the same state (the monitor's gains included), partial
    fractions on the way; a world's reset restarts its fraction on both paths."""
    from downwash.guard import GuardedPredictor
    from downwash.support import support_of

    rng = np.random.default_rng(0)
    n = 4000  # a support the lemniscate leaves and re-enters: the follower +-1 m, the support +-0.75 m
    dp = np.column_stack([rng.uniform(-0.75, 0.75, (n, 2)), -rng.uniform(0.45, 0.75, n)])
    support = support_of(dp, rng.normal(size=(n, 3)) * 0.1, rng.normal(size=(n, 3)) * 0.6,
                         np.broadcast_to(np.eye(3), (n, 3, 3)))
    guard = GuardedPredictor(LearnedPredictor(models["equivariant"], clamp=6.0), support)
    fused, readable = (Simulator(scene, _lemniscate(W), list(range(10, 10 + W)), fast=fast,
                                 field=DownwashField(swirl=0.2), predictor=copy.deepcopy(guard))
                       for fast in (True, False))  # (a guard of its own for each simulator: it keeps state)
    rows = [[dict(sim.tick()) for _ in range(60)] for sim in (fused, readable)]
    _assert_same((rows[0], fused), (rows[1], readable))
    applied = np.array([r["applied"][:, 1] for r in rows[0]])
    assert np.mean((applied > 0) & (applied < 1)) > 0.2 and np.max(applied) > 0.5
    assert np.min(fused._scene_predictor._state[:, 1, GAIN:GAIN + 2]) < 0.9  # the monitor's gains (random weights: the forces disagree)
    assert fused._plan.guard is not None and fused._plan.monitors and readable._plan is None  # (its monitor in the kernel)
    assert np.shares_memory(fused._plan.arrays["guard_state"], fused._scene_predictor._state)
    np.testing.assert_array_equal(fused._scene_predictor._state, readable._scene_predictor._state)  # gains included
    for name in ("_seen", "_seen_t"):  # the monitor's memory: observed once per tick on both paths, the same bits
        np.testing.assert_array_equal(getattr(fused._scene_predictor, name), getattr(readable._scene_predictor, name))
    for sim in (fused, readable):
        sim.reset(np.array([0]))
    fresh = fused._scene_predictor._state[0]
    assert np.all(fresh[:, FRACTION:FRACTION + 2] == 0.0) and np.all(fresh[:, GAIN:GAIN + 2] == 1)
    rows = [[dict(sim.tick()) for _ in range(5)] for sim in (fused, readable)]
    _assert_same((rows[0], fused), (rows[1], readable))
    memory = GuardedPredictor(LearnedPredictor(trained_like("equivariant_memory", "general_memory")), support)
    assert Simulator(scene, _lemniscate(W), list(range(W)), predictor=memory)._plan is None  # (a model with state)
    # guards among the predictors of a PerWorldPredictor (the experiments' batches of conditions): each its worlds
    other = GuardedPredictor(LearnedPredictor(models["general"]), support)
    assignment = (np.arange(W) + 1) % 4  # (one world: the guard's)
    pred = PerWorldPredictor([ZeroPredictor(), guard, LearnedPredictor(models["deep"]), other], assignment)
    fused, readable = (Simulator(scene, _lemniscate(W), list(range(10, 10 + W)), fast=fast,
                                 field=DownwashField(swirl=0.2), predictor=copy.deepcopy(pred))
                       for fast in (True, False))
    assert fused._plan is not None and readable._plan is None
    rows = [[dict(sim.tick()) for _ in range(40)] for sim in (fused, readable)]
    _assert_same((rows[0], fused), (rows[1], readable))
    applied = rows[0][-1]["applied"]
    guarded = np.isin(assignment, [1, 3])
    assert np.all(np.isnan(applied[~guarded])) and np.all(np.isfinite(applied[guarded]))
    for sim in (fused, readable):
        sim.reset(np.arange(W)[::3])
    rows = [[dict(sim.tick()) for _ in range(5)] for sim in (fused, readable)]
    _assert_same((rows[0], fused), (rows[1], readable))
    with_memory = PerWorldPredictor([guard, memory], np.arange(W) % 2)
    assert Simulator(scene, _lemniscate(W), list(range(W)), predictor=with_memory)._plan is None


def test_components_without_a_compiled_form_take_the_readable_path(scene, models):
    W = 2
    cases = [
        dict(field=MomentumWake()),
        dict(predictor=PerWorldPredictor([ZeroPredictor(), LearnedPredictor(models["equivariant"], backend="numpy")],
                                         np.array([0, 1]))),
        dict(predictor=LearnedPredictor(models["equivariant"], backend="numpy")),
        dict(predictor=OraclePredictor(MomentumWake())),
        dict(aggregation=make_aggregation("velocity")),
        dict(field=dataclasses.replace(DownwashField(), strength=np.full((W, 1, 1), 9.0))),
    ]
    for components in cases:
        sim = Simulator(scene, _lemniscate(W), [0, 1], **components)
        assert sim._plan is None, components
        assert isinstance(sim.tick(), dict)
    sim = Simulator(scene, _lemniscate(W), [0, 1], aggregation=make_aggregation("linear"))
    assert sim._plan is not None and isinstance(sim.tick(), Row)


def test_rows_are_views_of_one_flat_array_and_mj_step_is_found(scene):
    sim = Simulator(scene, _lemniscate(1), [0])
    row = sim.tick()
    assert isinstance(row, Row) and set(row) == set(dict(row)) and len(row) == 16
    for name in row:
        assert np.shares_memory(row[name], row.flat)
    kept = row.flat.copy()
    sim.tick()
    assert np.array_equal(row.flat, kept)  # never written again
    assert isinstance(mj_step_address(), int)


@pytest.mark.parametrize("W", [1, 3])
def test_true_states_are_the_readable_indexing(scene, W):
    from downwash_core.geometry import quat_to_mat_fast

    sim = Simulator(scene, _lemniscate(W), list(range(W)))
    for _ in range(5):
        sim.tick()
    qpos, qvel = sim.physics.qpos, sim.physics.qvel
    got = sim.true_states()
    assert np.array_equal(got.pos, qpos[:, sim._pos_idx]) and np.array_equal(got.vel, qvel[:, sim._vel_idx])
    assert np.array_equal(got.rot, quat_to_mat_fast(qpos[:, sim._quat_idx]))


def test_fly_logs_are_the_same_on_both_paths(scene, models):
    """`sim.flight.fly` stacks the fused path's rows at once; the logs equal the readable path's."""
    from sim.flight import fly

    wind = DrydenWind(mean=(0.0, 1.0, 0.0), w20=4.0)
    kw = dict(predictor=LearnedPredictor(models["shallow"]), wind=wind)
    fused = fly(scene, _lemniscate(2), [3, 4], 1.0, **kw)
    readable = fly(scene, _lemniscate(2), [3, 4], 1.0, fast=False, **kw)
    for a, b in zip(fused, readable):
        assert a.arrays.keys() == b.arrays.keys() and {"wind", "wind_acc"} <= set(a.arrays)
        for name in a.arrays:
            assert a[name].shape == b[name].shape and np.array_equal(a[name], b[name]), name
        assert {k: v for k, v in a.meta.items() if k != "code"} == {k: v for k, v in b.meta.items() if k != "code"}


@given(st.integers(1, 600), st.integers(1, 8), st.integers(1, 16))
def test_chunks_cover_every_world_once_largest_first(n_worlds, n_threads, smallest):
    """Guided chunks: they add up to the batch, none below the smallest size (unless the batch is),
    and sizes never grow except the last, which absorbs a remainder below the smallest size."""
    sizes = _chunk_sizes(n_worlds, n_threads, smallest)
    assert sum(sizes) == n_worlds and all(s >= min(smallest, n_worlds) for s in sizes)
    assert all(a >= b for a, b in zip(sizes[:-2], sizes[1:-1]))
    assert sizes[-1] < 2 * max(smallest, sizes[-2] if len(sizes) > 1 else 0) or len(sizes) == 1
    if n_threads == 1:
        assert sizes == [n_worlds]
