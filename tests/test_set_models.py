"""Models of sets: neighbour-set data from logs, the three models of sets, training, checkpoints
and the predictor in the loop."""

import copy
import functools

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from downwash_core import geometry
from downwash_core.errors import CheckpointError, ConfigError, DataError
from downwash_core.params import LEADER_POSITION
from downwash_core.provenance import differences
from downwash_core.state import VehicleStates
from downwash.checkpoint import Checkpoint, load_checkpoint, save_checkpoint, wrap_pairwise
from downwash.datasets import Dataset, concatenate, load_dataset, log_provenance
from downwash.labels import follower_acceleration, labels_from_log, smooth_command
from downwash.predictor import LearnedPredictor
from downwash.registry import SET_KINDS, make_model
from downwash.set_models import DeepSets, DeepSetsEquivariant, SummedPairwise
from downwash.train import TrainConfig, predict, rmse, save_trained, train_model
from sim.neighbours import NeighbourSet, gather_neighbours, select_neighbours
from sim.field import DownwashField, pairwise_field
from sim.flight import fly
from sim.logs import save_log
from sim.scene import build_scene
from test_checkpoint import trained_like  # tests/ is on sys.path under pytest
from test_features import random_rotations
from downwash_trajectories import Hover, Transect, stack
from conftest import restamp

LEADER = np.array(LEADER_POSITION)
LINEAR = {"type": "sim.aggregation.LinearSuperposition", "name": "linear"}


def as_checkpoint(model, neighbours, record):
    """A model of sets with what it was made for, as `load_checkpoint` returns it."""
    return Checkpoint(model, {**record, "neighbours": neighbours.describe()})


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Small torch ops on two busy cores ran 15-25x slower with two threads (see downwash.train)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _settings(n: int):
    """n examples, no deadline (torch warms up on the first call), no example database."""
    return settings(max_examples=n, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


# ------------------------------------------------------------------------------ flights


@pytest.fixture(scope="module")
def three_logs():
    """Two 3 s flights of a 3-vehicle stack: a hovering leader, one follower passing 0.5 m below
    it, another hovering 1.0 m below (beneath both wakes)."""
    scene = build_scene([("a", "leader"), ("b", "follower"), ("c", "follower")])
    ref = stack([Hover(LEADER, n_worlds=2), Transect(LEADER - [0, 0, 0.5], x_offset=[0.1, -0.1], n_worlds=2),
                 Hover(LEADER - [0.1, 0.05, 1.0], n_worlds=2)])
    logs = fly(scene, ref, [5, 6], 3.0)
    assert all(L.ok for L in logs)
    return logs


@pytest.fixture(scope="module")
def pair_log():
    """A 3 s two-vehicle flight: the follower passes 0.6 m below the hovering leader."""
    ref = stack([Hover(LEADER, n_worlds=1), Transect(LEADER - [0, 0, 0.6], x_offset=0.1)])
    return fly(build_scene(), ref, [2], 3.0)[0]


def test_two_vehicle_log_with_one_neighbour_gives_exactly_the_pair_formula(pair_log):
    """K = 1 on a two-vehicle log (the defaults): the follower's samples are the pair's, computed here
    the plain way from the leader's and the follower's columns, bit for bit."""
    log = pair_log
    f, l = int(log.meta["follower"]), int(log.meta["leader"])
    lab = labels_from_log(log)
    assert lab["mask"].all() and (lab["vehicle"] == f).all() and (lab["neighbour"] == l).all()
    rows, end = lab["row"], len(log)
    pos, vel = log["pos_est"][rows], log["vel_est"][rows]
    want_y = (follower_acceleration(log["t"][:end], log["mocap_pos"][:end, f]) - smooth_command(log["u_cmd"][:end, f]))[rows]
    assert np.array_equal(lab["y"], want_y)
    assert np.array_equal(lab["dp"][:, 0], pos[:, f] - pos[:, l])
    assert np.array_equal(lab["v_a"][:, 0], vel[:, l].astype(np.float64))
    assert np.array_equal(lab["v_b"], vel[:, f].astype(np.float64))
    assert np.array_equal(lab["R_a"][:, 0], geometry.quat_to_mat(log["quat_est"][rows, l].astype(np.float64)))
    ds = Dataset.from_labels(lab, NeighbourSet(1), flight=0, stage=0, provenance=log_provenance(log.meta))
    pairs = ds.pairs()
    assert np.array_equal(pairs.dp, lab["dp"][:, 0]) and np.array_equal(pairs.y, lab["y"])


def test_every_vehicle_gets_its_own_label_and_neighbours(three_logs, tmp_path):
    """Each target's label is labels_from_log's with that vehicle as the follower; K = 2 holds the
    other two; a radius drops the far one; the files load through load_dataset."""
    log = three_logs[0]
    swarm = labels_from_log(log, NeighbourSet(2), targets="all")
    for j in range(3):
        mine = swarm["vehicle"] == j
        rows = swarm["row"][mine]
        acc = follower_acceleration(log["t"], log["mocap_pos"][:, j]) - smooth_command(log["u_cmd"][:, j])
        assert np.array_equal(swarm["y"][mine], acc[rows])
        assert np.array_equal(swarm["v_b"][mine], log["vel_est"][rows, j].astype(np.float64))
        assert (np.sort(swarm["neighbour"][mine], axis=1) == sorted({0, 1, 2} - {j})).all()
    # a radius keeps the vehicles within it: at the end the top vehicle has the middle one
    # (~0.5 m) and not the bottom one (~1 m); earlier, on the way in from the spawn points, others
    near = labels_from_log(log, NeighbourSet(2, radius=0.8), targets=[0])
    dist = np.linalg.norm(log["pos_est"][near["row"], :, None] - log["pos_est"][near["row"], None], axis=-1)[:, 0]
    for k, i in enumerate((1, 2)):
        assert np.array_equal((near["neighbour"] == i).any(1), dist[:, i] <= 0.8)
    assert near["neighbour"][-1].tolist() == [1, -1] and near["mask"][-1].tolist() == [True, False]
    for i, L in enumerate(three_logs):
        save_log(tmp_path / f"flight_{i}.npz", L)
    ds = load_dataset(tmp_path, NeighbourSet(3), targets="all")
    assert ds.flights.tolist() == [0, 1] and ds.mask.shape[1] == 3 and (ds.mask.sum(1) == 2).all()
    assert ds.provenance["aggregation"] == LINEAR and ds.provenance["field"] == log.meta["field"]


def test_two_vehicle_data_joins_many_vehicle_data_of_any_one_law(pair_log, three_logs, tmp_path):
    """With two vehicles every aggregation law is the pairwise force: such a log records the law
    as None and joins 3-vehicle data of one law (whose record the result keeps); 3-vehicle data
    of two laws never mix; a log on disk joins the same log in memory (JSON lists vs tuples)."""
    ns = NeighbourSet(2)
    as_set = lambda L: Dataset.from_labels(labels_from_log(L, ns, targets="all"), ns, flight=0, stage=0,  # noqa: E731
                                                provenance=log_provenance(L.meta))
    pair, swarm = as_set(pair_log), as_set(three_logs[0])
    assert pair.provenance["aggregation"] is None and swarm.provenance["aggregation"] == LINEAR
    mixed = concatenate([pair, swarm])
    assert mixed.provenance == swarm.provenance and mixed.flights.tolist() == [0, 1]
    assert concatenate([pair, pair]).provenance["aggregation"] is None
    velocity = {"type": "sim.aggregation.VelocitySuperposition", "name": "velocity", "exponent": 2.0}
    other = Dataset.from_labels(labels_from_log(three_logs[1], ns, targets="all"), ns, flight=0, stage=0,
                                     provenance={**log_provenance(three_logs[1].meta), "aggregation": velocity})
    assert concatenate([pair, other]).provenance["aggregation"] == velocity
    with pytest.raises(DataError, match="(?s)other settings.*aggregation.name"):
        concatenate([pair, swarm, other])
    save_log(tmp_path / "f.npz", three_logs[0])
    assert concatenate([swarm, load_dataset(tmp_path / "f.npz", ns, targets="all")]).provenance == swarm.provenance
    # a model trained on two-vehicle data only was trained for no law in particular
    path = tmp_path / "pair_only.pt"
    save_checkpoint(path, copy.deepcopy(random_model("deepsets", 0)).float(), neighbours=ns, provenance=pair.provenance)
    assert load_checkpoint(path).record["aggregation"] is None
    with pytest.raises(CheckpointError, match="trained on two-vehicle flights only"):
        LearnedPredictor(path, expect_aggregation="linear")


@_settings(40)
@given(seed=st.integers(0, 2**31 - 1), V=st.integers(1, 6), K=st.integers(1, 7), radius=st.none() | st.floats(0.2, 3.0))
def test_neighbour_selection_matches_a_plain_loop(seed, V, K, radius):
    rng = np.random.default_rng(seed)
    pos = rng.normal(size=(3, V, 3))
    index, mask = select_neighbours(pos, NeighbourSet(K, radius))
    assert index.shape == mask.shape == (3, V, K)
    for w in range(3):
        for j in range(V):
            d = {i: np.linalg.norm(pos[w, j] - pos[w, i]) for i in range(V) if i != j}
            want = sorted((i for i in d if radius is None or d[i] <= radius), key=lambda i: (d[i], i))[:K]
            assert index[w, j, mask[w, j]].tolist() == want
            assert (index[w, j, ~mask[w, j]] == -1).all()


# ------------------------------------------------------------------------------ models


@functools.lru_cache(maxsize=None)
def random_model(kind, seed, pair_kind="equivariant_general"):
    """A float64 swarm model with random weights and random normalisation (cached: never modify it)."""
    if kind == "summed_pairwise":
        return SummedPairwise(trained_like(pair_kind, seed=seed)).double().eval()
    torch.manual_seed(seed)
    return randomised(make_model(kind).double(), seed).eval()


def randomised(model, seed):
    """`model` (changed in place) with its weights jittered and a random normalisation, from `seed`; its
    spectral norms settled."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g, dtype=p.dtype))
        for name, buf in model.named_buffers():
            if "." not in name:  # the normalisation buffers, not spectral-norm state
                buf.copy_(torch.rand(buf.shape, generator=g, dtype=buf.dtype) + 0.5)
    model.settle_spectral_norm()
    return model


def neighbour_batch(rng, B, K, max_tilt=0.5, p_mask=0.7):
    """Random padded neighbour sets (B, K, ...); neighbours mostly above the target."""
    dp = rng.normal(size=(B, K, 3)) * [0.5, 0.5, 0.4] + [0, 0, -0.8]
    v_a, v_b = rng.normal(size=(B, K, 3)) * 0.5, rng.normal(size=(B, 3)) * 0.8
    R_a = random_rotations(rng, B * K, max_tilt).reshape(B, K, 3, 3)
    mask = rng.random((B, K)) < p_mask
    return dp, v_a, v_b, R_a, mask


def run(model, dp, v_a, v_b, R_a, mask):
    with torch.no_grad():
        return model(dp, v_a, v_b, R_a, mask).numpy()


KINDS = list(SET_KINDS)


@pytest.mark.parametrize("kind", KINDS)
@_settings(25)
@given(seed=st.integers(0, 2**31 - 1), B=st.integers(1, 6), K=st.integers(1, 6))
def test_invariant_to_neighbour_order_and_padding(kind, seed, B, K):
    """A random permutation of the neighbours changes nothing; nor do extra masked slots holding
    anything (even NaN); a target whose slots are all masked gets exactly 0."""
    rng = np.random.default_rng(seed)
    model = random_model(kind, seed % 7)
    dp, v_a, v_b, R_a, mask = neighbour_batch(rng, B, K)
    out = run(model, dp, v_a, v_b, R_a, mask)
    assert np.isfinite(out).all()
    perm = np.stack([rng.permutation(K) for _ in range(B)])
    take = lambda a: np.take_along_axis(a, perm.reshape(B, K, *[1] * (a.ndim - 2)), 1)  # noqa: E731
    # torch's float64 products (MKL, in their kernel's order) pool the slots in another order: round-off of
    # widths <= 48, <= 7e-15 measured under torch's default, AVX2 and AVX-512 kernels (both checks): 1e-12 is 100x+
    np.testing.assert_allclose(run(model, take(dp), take(v_a), v_b, take(R_a), take(mask)), out, rtol=1e-12, atol=1e-12)
    extra = rng.integers(1, 4)
    junk = lambda a: np.concatenate([a, rng.normal(size=(B, extra, *a.shape[2:])) * 5], 1)  # noqa: E731
    dp2, v_a2, R_a2 = junk(dp), junk(v_a), junk(R_a)
    dp2[:, -1] = np.nan
    mask2 = np.concatenate([mask, np.zeros((B, extra), bool)], 1)
    np.testing.assert_allclose(run(model, dp2, v_a2, v_b, R_a2, mask2), out, rtol=1e-12, atol=1e-12)
    assert (out[~mask.any(1)] == 0).all()


def _rotate_z(rng, dp, v_a, v_b, R_a):
    Q = geometry.rotation_about_axis(np.array([0.0, 0.0, 1.0]), rng.uniform(-np.pi, np.pi))
    return Q, (dp @ Q.T, v_a @ Q.T, v_b @ Q.T, Q @ R_a)


@pytest.mark.parametrize("kind,pair_kind", [("deepsets_equivariant", None), ("summed_pairwise", "equivariant"),
                                            ("summed_pairwise", "equivariant_general")])
@_settings(25)
@given(seed=st.integers(0, 2**31 - 1), K=st.integers(1, 5))
def test_equivariant_under_a_rotation_of_everything_about_world_z(kind, pair_kind, seed, K):
    """F(Q x) = Q F(x) in float64 for a random rotation Q about world z of every position,
    velocity and attitude (tilted neighbours included), for random weights."""
    rng = np.random.default_rng(seed)
    model = random_model(kind, seed % 5, pair_kind)
    dp, v_a, v_b, R_a, mask = neighbour_batch(rng, 8, K, p_mask=0.8)
    out = run(model, dp, v_a, v_b, R_a, mask)
    Q, rotated = _rotate_z(rng, dp, v_a, v_b, R_a)
    scale = max(np.abs(out).max(), 1e-3)
    # Q and the rotated inputs are BLAS products, the model torch's (MKL): round-off only, 1.4e-14 measured
    # under every OpenBLAS and torch kernel, 1e-4 of the 1e-10 * scale allowed
    np.testing.assert_allclose(run(model, *rotated, mask), out @ Q.T, rtol=0, atol=1e-10 * scale)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plain_deep_sets_is_not_equivariant(seed):
    """The same check fails clearly for Neural-Swarm2's deep sets (raw world-frame inputs)."""
    rng = np.random.default_rng(seed)
    model = random_model("deepsets", seed)
    dp, v_a, v_b, R_a, mask = neighbour_batch(rng, 32, 3, p_mask=1.0)
    out = run(model, dp, v_a, v_b, R_a, mask)
    Q, rotated = _rotate_z(rng, dp, v_a, v_b, R_a)
    assert np.abs(run(model, *rotated, mask) - out @ Q.T).max() > 1e-2 * np.abs(out).max() > 0


def test_equivariant_deep_sets_sees_the_azimuth_between_two_wakes():
    """Carry one of two level neighbours around a still target (its invariants about its own axis
    unchanged): a pair sum keeps the vertical force (each term only turns about z); the
    equivariant deep sets change it, since their vector channels see where the other wake is."""
    rng = np.random.default_rng(3)
    dp, v_a, _, _, mask = neighbour_batch(rng, 1, 2, p_mask=1.0)
    R_a, v_b = np.broadcast_to(np.eye(3), (1, 2, 3, 3)).copy(), np.zeros((1, 3))
    spread = {}
    for kind in ("deepsets_equivariant", "summed_pairwise"):
        model = random_model(kind, 1)
        f_z = []
        for angle in np.linspace(0.0, 2 * np.pi, 7)[:-1]:
            Q = geometry.rotation_about_axis(np.array([0.0, 0.0, 1.0]), angle)
            dp2, v_a2 = dp.copy(), v_a.copy()
            dp2[:, 1], v_a2[:, 1] = dp[:, 1] @ Q.T, v_a[:, 1] @ Q.T
            f_z.append(run(model, dp2, v_a2, v_b, R_a @ np.eye(3), mask)[0, 2])
        spread[kind] = np.ptp(f_z) / max(np.abs(f_z).max(), 1e-9)
    # the neighbour turned by BLAS products (its bits the kernel's) moves a pair sum's f_z by round-off only:
    # 0 to 1.5e-16 relative measured under every OpenBLAS and torch kernel
    assert spread["summed_pairwise"] < 1e-12
    assert spread["deepsets_equivariant"] > 1e-2


# ------------------------------------------------------------------------------ summed pairwise in the loop


def _stacked_states(rng, W, V):
    pos = np.zeros((W, V, 3))
    pos[..., 2] = 3.0 - 0.5 * np.arange(V) + rng.normal(scale=0.05, size=(W, V))
    pos[..., :2] = rng.normal(scale=0.15, size=(W, V, 2))
    vel = rng.normal(scale=0.4, size=(W, V, 3))
    rot = random_rotations(rng, W * V, 0.3).reshape(W, V, 3, 3)
    return VehicleStates(pos, vel, rot)


@pytest.mark.parametrize("pair_kind", ["equivariant", "equivariant_general", "shallow", "deep"])
def test_summed_pairwise_equals_the_learned_predictors_sum(pair_kind):
    """With every other vehicle as a neighbour, summed_pairwise in the loop is LearnedPredictor's sum:
    to float64 rounding for a float64 pair model, to float32 rounding for a float32 one (the
    predictor computes in float64, the deep model's spectral normalisation included)."""
    rng = np.random.default_rng(4)
    states = _stacked_states(rng, 3, 4)
    pair = trained_like(pair_kind, seed=2)
    pair64 = copy.deepcopy(pair).double()
    if pair_kind == "deep":
        pair64.settle_spectral_norm()
    for model, rtol in ((pair64, 1e-10), (pair, 1e-5)):
        want = LearnedPredictor(model)(states, states)
        assert np.abs(want).max() > 0.1 and (want[:, 0] == 0).all()  # the top vehicle is below nobody
        for backend in LearnedPredictor.BACKENDS:
            got = LearnedPredictor(wrap_pairwise(model, NeighbourSet(3)), backend=backend)(states, states)
            # float64: the backends' products (compiled, `matmul_rows`, torch's MKL) sum in their own orders, ~1e-15
            # relative under every kernel, so 1e-10 is slack; float32: the float32 model's own rounding
            np.testing.assert_allclose(got, want, rtol=0, atol=rtol * np.abs(want).max())


@pytest.mark.parametrize("kind", KINDS)
@_settings(10)
@given(seed=st.integers(0, 2**31 - 1), B=st.integers(1, 40), K=st.integers(1, 5))
def test_numpy_twin_equals_the_torch_model(kind, seed, B, K):
    """The predictor's default NumPy path is the torch model to float64 rounding, padding and
    blocks of rows included (B up to 40 targets of 5 slots: more than one block of rows)."""
    rng = np.random.default_rng(seed)
    model = random_model(kind, seed % 3)
    batch = neighbour_batch(rng, B, K)
    want = run(model, *batch)
    # the twin's products (OpenBLAS for the deep sets, `matmul_rows` for the pair sum) against torch's MKL,
    # float64, widths <= 48, each in its own order: <= 7e-15 of max(|F|, 1) measured under every OpenBLAS and
    # torch kernel tried (both checks; tests/test_set_fused.py says more)
    np.testing.assert_allclose(model.numpy_forward()(*batch), want, rtol=0, atol=1e-12 * max(np.abs(want).max(), 1))
    states = _stacked_states(rng, 3, 4)
    ck = as_checkpoint(copy.deepcopy(model).float(), NeighbourSet(K), {"aggregation": LINEAR})
    a, *others = (LearnedPredictor(ck, backend=backend)(states, states) for backend in LearnedPredictor.BACKENDS)
    for b in others:  # compiled, numpy and torch agree
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(np.abs(b).max(), 1))


@pytest.mark.parametrize("kind", KINDS)
def test_predictor_uses_only_the_estimates_and_matches_the_training_inputs(kind, three_logs):
    """The predictor ignores `true` (true states that differ give the same output) and sees, from
    a log row's estimates, exactly the inputs the data set built for that row."""
    model = random_model(kind, 0)
    ns = NeighbourSet(2)
    pred = LearnedPredictor(as_checkpoint(model, ns, {"aggregation": LINEAR}))
    log = three_logs[1]
    rows = np.arange(20, 120, 7)
    est = VehicleStates(log["pos_est"][rows], log["vel_est"][rows], geometry.quat_to_mat(log["quat_est"][rows]))
    true = VehicleStates(log["pos"][rows] + 0.3, -log["vel"][rows], geometry.quat_to_mat(log["quat"][rows]))
    out = pred(est, true)
    assert out.shape == (rows.size, 3, 3) and out.dtype == np.float64
    assert np.array_equal(pred(est, est), out) and np.array_equal(pred(est, None), out)
    assert not np.allclose(pred(true, est), out)  # the states do matter
    data = Dataset.from_labels(labels_from_log(log, ns, targets="all"), ns, flight=0, stage=0)
    for v in range(3):
        sel = (data.vehicle == v) & np.isin(data.t, log["t"][rows])
        # torch (MKL) against the predictor's default path: float64 round-off, 3e-15 measured under every kernel
        np.testing.assert_allclose(predict(model, data.subset(sel)), out[:, v], rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------ training


def synthetic_set(n_flights=4, n=300, K=2, seed=0):
    """Random 3-vehicle stacks labelled with the true field, summed (flight = a block of samples)."""
    rng = np.random.default_rng(seed)
    ns = NeighbourSet(K)
    parts = []
    for f in range(n_flights):
        s = _stacked_states(rng, n, 3)
        y = pairwise_field(DownwashField(), s.pos, s.vel, s.rot)  # (n, 3, 3)
        index, mask = select_neighbours(s.pos, ns)
        g = gather_neighbours(s.pos, s.vel, s.rot, index, mask)
        flat = lambda a: a.reshape(n * 3, *a.shape[2:])  # noqa: E731
        labels = {"dp": flat(g["dp"]), "v_a": flat(g["v_a"]), "v_b": flat(g["v_b"]), "R_a": flat(g["R_a"]),
                  "mask": flat(mask), "neighbour": flat(index), "vehicle": np.tile(np.arange(3), n),
                  "y": flat(y), "t": np.repeat(np.arange(n) * 0.02, 3), "field_mean": flat(y)}
        parts.append(Dataset.from_labels(labels, ns, flight=0, stage=0,
                                              provenance={"field": "true", "aggregation": LINEAR}))
    return concatenate(parts)


TINY = TrainConfig(max_epochs=6, min_steps=0, batch_size=256, patience=6)


@pytest.mark.parametrize("kind", ["deepsets_equivariant", "deepsets"])
def test_training_is_deterministic_and_reduces_the_validation_error(kind):
    data = synthetic_set(n=200)
    train, val = data.select_flights([0, 1, 2]), data.select_flights([3])
    config = TrainConfig(max_epochs=20, min_steps=0, batch_size=256, patience=20)
    model, history = train_model(kind, train, val, config, seed=3)
    with torch.random.fork_rng():
        torch.manual_seed(3)
        untrained = make_model(kind)
    untrained.fit_normalization(untrained.encode(train.dp, train.v_a, train.v_b, train.R_a, train.mask),
                                torch.as_tensor(train.y, dtype=torch.float32))
    before = rmse(untrained.eval(), val)[0]
    after = rmse(model, val)[0]
    scale = np.sqrt(np.mean(val.y**2))
    # seeded: after / before 0.26 and 0.69, after / scale 0.43 and 0.60 for the two kinds
    assert after < 0.75 * before and after < 0.65 * scale, (before, after, scale)
    assert history["best_val_loss"] == pytest.approx(after**2, rel=1e-4)
    assert history["neighbours"] == NeighbourSet(2).describe() and history["provenance"]["aggregation"] == LINEAR
    # same seed: the same weights bit for bit; another seed: other weights
    small = data.select_flights([0, 1])
    a, _ = train_model(kind, small, val, TINY, seed=7)
    b, _ = train_model(kind, small, val, TINY, seed=7)
    c, _ = train_model(kind, small, val, TINY, seed=8)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)


def test_training_argument_errors():
    data = synthetic_set(n_flights=2, n=50)
    with pytest.raises(ConfigError, match="no training of its own.*wrap_pairwise"):
        train_model("summed_pairwise", data)
    with pytest.raises(ConfigError, match="model kind: unknown 'transformer'; allowed: shallow, deep"):
        train_model("transformer", data)
    other = synthetic_set(n_flights=1, n=50, K=3)
    with pytest.raises(DataError, match="neighbour set"):
        train_model("deepsets", data, other, TINY)
    with pytest.raises(DataError, match="neighbour set"):
        concatenate([data, other])
    odd = Dataset(**{k: getattr(data, k) for k in ("dp", "v_a", "v_b", "R_a", "mask", "neighbour", "vehicle", "y",
                                                        "flight", "stage", "t", "field_mean")},
                       neighbours=data.neighbours, provenance={"field": "other", "aggregation": LINEAR})
    with pytest.raises(DataError, match="field"):
        concatenate([data, odd])
    with pytest.raises(ConfigError, match="max_neighbours"):
        NeighbourSet(0)
    with pytest.raises(ConfigError, match="radius"):
        NeighbourSet(2, radius=-1.0)
    with pytest.raises(ConfigError, match="backend: expected one of"):
        LearnedPredictor(as_checkpoint(random_model("deepsets", 0), NeighbourSet(2), {"aggregation": LINEAR}),
                       backend="jax")
    with pytest.raises(ConfigError, match="latent: expected an integer in"):
        make_model("deepsets_equivariant", latent=0)
    with pytest.raises(ConfigError, match="feature_set: 'deepsets_equivariant' accepts"):
        make_model("deepsets_equivariant", feature_set="raw")
    with pytest.raises(TypeError, match="bad architecture arguments"):
        make_model("deepsets", feature_set="general")
    with pytest.raises(ConfigError, match="dp: expected"):
        random_model("deepsets", 0)(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3, 3)),
                                    np.ones(2, bool))


# ------------------------------------------------------------------------------ checkpoints


@pytest.mark.parametrize("kind,pair_kind", [(k, "equivariant_general") for k in KINDS] + [("summed_pairwise", "deep")])
def test_checkpoint_round_trip_and_what_it_records(tmp_path, kind, pair_kind):
    model = copy.deepcopy(random_model(kind, 1, pair_kind)).float()
    ns = NeighbourSet(3, radius=2.0)
    path = tmp_path / f"{kind}.pt"
    record = save_checkpoint(path, model, {"seed": 3}, neighbours=ns,
                             provenance={"field": {"type": "f", "k": 1.0}, "aggregation": "linear", "config": {"a": 1}})
    assert path.with_suffix(".json").is_file()
    loaded = load_checkpoint(path, expect_kind=kind, expect_neighbours=ns, expect_aggregation="linear")
    assert loaded.neighbours == ns and loaded.record == record
    assert record["aggregation"] == LINEAR and record["field"] == {"type": "f", "k": 1.0}
    assert record["neighbours"]["radius"] == 2.0 and record["model"]["kind"] == kind and record["seed"] == 3
    rng = np.random.default_rng(0)
    batch = neighbour_batch(rng, 16, 3)
    assert np.array_equal(run(loaded.model, *batch), run(model, *batch))
    states = _stacked_states(rng, 2, 4)
    in_memory = LearnedPredictor(as_checkpoint(model, ns, record))
    assert np.array_equal(LearnedPredictor(path)(states, states), in_memory(states, states))


def test_a_model_for_another_neighbour_set_or_law_stops_before_flight(tmp_path):
    pair_path = tmp_path / "pair.pt"
    save_checkpoint(pair_path, trained_like("equivariant"), {"provenance": {"field": {"type": "true"}}})
    wrapped = wrap_pairwise(pair_path, NeighbourSet(2))
    assert wrapped.record["field"] == {"type": "true"} and wrapped.record["aggregation"] == LINEAR
    path = tmp_path / "swarm.pt"
    save_checkpoint(path, wrapped.model, neighbours=wrapped.neighbours,
                    provenance={k: v for k, v in wrapped.record.items() if k not in ("model", "neighbours")})
    other_law = {"type": "sim.aggregation.Other", "name": "other"}
    with pytest.raises(CheckpointError, match=r"swarm.pt: trained for the neighbour set .*max_neighbours': 2"):
        load_checkpoint(path, expect_neighbours=NeighbourSet(3))
    other_law_error = '(?s)swarm.pt: trained for another aggregation law.*name: "linear" here, "other" asked for'
    with pytest.raises(CheckpointError, match=other_law_error):
        LearnedPredictor(path, expect_aggregation=other_law)
    with pytest.raises(CheckpointError, match="neighbour set"):
        LearnedPredictor(wrapped, expect_neighbours=NeighbourSet(2, radius=1.0))
    with pytest.raises(CheckpointError, match="aggregation law"):
        LearnedPredictor(wrapped, expect_aggregation=other_law)
    with pytest.raises(ConfigError, match="aggregation: unknown 'other'"):
        LearnedPredictor(wrapped, expect_aggregation="other")
    LearnedPredictor(path, expect_neighbours=NeighbourSet(2), expect_aggregation="linear")  # what it was made for
    with pytest.raises(CheckpointError, match="model kind is 'summed_pairwise', expected 'deepsets'"):
        load_checkpoint(path, expect_kind="deepsets")
    with pytest.raises(CheckpointError, match="swarm.pt: a 'summed_pairwise' model of sets, not a per-neighbour model"):
        wrap_pairwise(path)


def test_bad_checkpoint_files_raise_checkpoint_errors(tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    path = tmp_path / "m.pt"
    model = copy.deepcopy(random_model("deepsets", 0)).float()
    save_checkpoint(path, model, neighbours=NeighbourSet(2), provenance={"aggregation": "linear"})
    data = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="cut.pt: not a readable torch checkpoint"):
        load_checkpoint(tmp_path / "cut.pt")
    torch.save({"format": "downwash-swarm-model", "version": 1, "evil": DeepSets}, tmp_path / "evil.pt")
    with pytest.raises(CheckpointError, match="evil.pt: refused by the safe loader"):
        load_checkpoint(tmp_path / "evil.pt")
    payload = torch.load(path, weights_only=True)
    payload["state_dict"] = {k: v for k, v in payload["state_dict"].items() if not k.startswith("rho.0.")}
    torch.save(restamp(payload), tmp_path / "short.pt")
    with pytest.raises(CheckpointError, match="short.pt: weights do not match.*missing tensor 'rho.0"):
        load_checkpoint(tmp_path / "short.pt")


def test_trained_model_checkpoint_records_its_data(tmp_path, three_logs):
    """save_trained stores the neighbour set, the logs' field and aggregation law and the training record;
    the reloaded predictor flies (finite output) on the estimates."""
    ns = NeighbourSet(2)
    data = concatenate([Dataset.from_labels(labels_from_log(L, ns, targets="all"), ns, flight=0, stage=0,
                                                       provenance=log_provenance(L.meta)) for L in three_logs])
    model, history = train_model("deepsets_equivariant", data, None, TINY, seed=1)
    record = save_trained(tmp_path / "m.pt", model, history, data)
    assert record["field"] == three_logs[0].meta["field"] and record["aggregation"] == LINEAR
    assert record["neighbours"] == ns.describe() and record["training"]["seed"] == 1
    assert differences(record["provenance"]["config"], three_logs[0].meta["config"]) == []
    pred = LearnedPredictor(tmp_path / "m.pt", expect_neighbours=ns, expect_aggregation="linear")
    L = three_logs[0]
    est = VehicleStates(L["pos_est"][40:45], L["vel_est"][40:45], geometry.quat_to_mat(L["quat_est"][40:45]))
    assert np.isfinite(pred(est, est)).all()


def test_model_classes_are_registered():
    assert SET_KINDS == {"summed_pairwise": SummedPairwise, "deepsets_equivariant": DeepSetsEquivariant,
                                 "deepsets": DeepSets}


@pytest.mark.parametrize("backend", LearnedPredictor.BACKENDS)
def test_the_swarm_predictor_clamps_as_the_pair_predictor(backend):
    """The same bound as `LearnedPredictor(clamp=...)`: no vehicle's prediction exceeds it, and those
    below it pass unchanged."""
    rng = np.random.default_rng(7)
    states = _stacked_states(rng, 3, 4)
    pair = copy.deepcopy(trained_like("equivariant", seed=2)).double()
    free = LearnedPredictor(wrap_pairwise(pair, NeighbourSet(3)), backend=backend)(states, states)
    norm = np.linalg.norm(free, axis=-1)
    bound = float(np.median(norm[norm > 0]))  # some vehicles above it, some below
    got = LearnedPredictor(wrap_pairwise(pair, NeighbourSet(3)), backend=backend, clamp=bound)(states, states)
    assert np.all(np.linalg.norm(got, axis=-1) <= bound * (1 + 1e-12))
    np.testing.assert_array_equal(got[norm <= bound], free[norm <= bound])
    # the same float64 pair model summed by another path (compiled, `matmul_rows` or torch's MKL): ~1e-15
    # relative apart on any kernel (7e-6 of this tolerance measured)
    np.testing.assert_allclose(got, LearnedPredictor(pair, clamp=bound)(states, states), rtol=0, atol=1e-10 * bound)
    with pytest.raises(ConfigError, match="clamp"):
        LearnedPredictor(wrap_pairwise(pair, NeighbourSet(3)), clamp=float("nan"))


def test_the_swarm_collection_trains_the_shared_pair_models_under_their_folders_lock(tmp_path, monkeypatch):
    """Every law's collection trains the law-free pair models into one folder: each trains them holding that
    folder's lock (another process could not take it meanwhile), the models of its own data under its own."""
    import fcntl
    import os

    import downwash.swarm_collection as sc
    from downwash_core.locks import LOCK_NAME
    from sim.aggregation import make_aggregation

    pair_path = tmp_path / "equivariant.pt"
    save_checkpoint(pair_path, trained_like("equivariant"), {})
    pair_dir, swarm_dir = tmp_path / "pair_models", tmp_path / "swarm"

    def taken(folder):
        fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a descriptor of its own: as another process would
            return False
        except BlockingIOError:
            return True
        finally:
            os.close(fd)

    trained = {}

    def train(kind, data, path, cfg, kinds=False):
        trained[path] = taken(pair_dir if path.parent == pair_dir else swarm_dir)
        save_checkpoint(path, make_model(kind).eval(), {}, neighbours=cfg.neighbours,
                        provenance={"aggregation": None, "field": None})

    class Data:
        skipped = {}

        def __init__(self, *args, **kwargs):
            pass

        def __call__(self, *args, **kwargs):
            return None

    monkeypatch.setattr(sc, "fly_recorded", lambda *args, **kwargs: None)  # no flights, no data: the wiring only
    monkeypatch.setattr(sc, "CheckedLoader", Data)
    monkeypatch.setattr(sc, "concatenate", lambda parts: None)
    monkeypatch.setattr(sc, "rmse", lambda model, data: (0.0,))
    monkeypatch.setattr(sc, "_train", train)
    sc.collect_swarm(sc.SwarmCollectionConfig(quick=True), swarm_dir, tmp_path / "pair", pair_path, {}, None,
                     make_aggregation("linear"), pair_dir)
    pair = {path: held for path, held in trained.items() if path.parent == pair_dir}
    assert len(pair) == len(sc.TRAINABLE_SET_KINDS) and all(pair.values())
    assert not taken(pair_dir)  # let go after
    # the other models (the stages' and those of the swarm's own data) under the collection's own lock
    own = [held for path, held in trained.items() if path.is_relative_to(swarm_dir)]
    assert len(own) == len(trained) - len(pair) > 0 and all(own)


def test_the_swarm_collection_deploys_its_models_clamped(tmp_path, monkeypatch):
    """Its provenance records the clamp, and the deployed predictor applies it (it was never applied)."""
    import downwash.stages as stages
    import downwash.swarm_collection as sc
    from sim.aggregation import make_aggregation

    pair_path = tmp_path / "equivariant.pt"
    save_checkpoint(pair_path, trained_like("equivariant"), {})
    deployed = []

    class Flown(Exception):
        pass

    def fly_stage(stage, sdir, n_train, n_val, seconds, *, predictor, **settings):
        deployed.append(predictor)
        raise Flown

    monkeypatch.setattr(stages, "fly_stage", fly_stage)  # the one stage driver's flights
    cfg = sc.SwarmCollectionConfig(quick=True, clamp=2.5)
    with pytest.raises(Flown):
        sc.collect_swarm(cfg, tmp_path / "swarm", tmp_path / "pair", pair_path, {}, None, make_aggregation("linear"),
                         tmp_path / "pair_models")
    assert deployed[0].clamp == 2.5 and sc.swarm_provenance(cfg, None, {})["swarm"]["clamp"] == 2.5
