"""Labels from logs (synthetic flights with known truth) and data sets: loading, errors, splits, shortening."""

import numpy as np
import pytest
from scipy.signal import savgol_coeffs

from downwash.datasets import Dataset, concatenate, load_dataset, shorten_per_stage, split_by_flight
from downwash_core.geometry import quat_to_mat as quat_to_rotmat
from downwash.labels import (
    DEFAULT_POLYORDER,
    DEFAULT_WINDOW,
    command_kernel,
    follower_acceleration,
    label_noise_floor,
    labels_from_log,
    second_derivative_coeffs,
)
from sim.logs import ARRAY_SPECS, FlightLog, LogError, save_log
from downwash_core.params import RATES

DT = RATES.control_dt  # 50 Hz controller ticks
MOCAP_NOISE = 0.5e-3  # m, standard deviation per axis
HALF = DEFAULT_WINDOW // 2

# follower trajectory and force: sums of sinusoids (amplitude, frequency in Hz) per axis
X_TERMS = [(0.6, 0.11), (0.25, 0.37), (0.05, 0.8)]  # m
F_TERMS = [(0.5, 0.2), (0.3, 0.55)]  # m/s^2


def _sines(t, terms, phase, deriv=0):
    out = np.zeros((t.size, 3))
    for k, (amp, hz) in enumerate(terms):
        w = 2 * np.pi * hz
        arg = w * t[:, None] + phase[k]
        out += amp * w**deriv * [np.sin, np.cos, lambda a: -np.sin(a), lambda a: -np.cos(a)][deriv % 4](arg)
    return out


def make_log(T=3000, noise=MOCAP_NOISE, seed=0, status=0, stage=0, leader_quat=(1.0, 0.0, 0.0, 0.0), x_terms=X_TERMS):
    """A two-vehicle log: leader hovering at 2.5 m, follower on a smooth path with a known force f.

    u_cmd = a_true - f (the commanded acceleration that, plus f, gives the motion).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    px, pf = rng.uniform(0, 2 * np.pi, (len(x_terms), 3)), rng.uniform(0, 2 * np.pi, (len(F_TERMS), 3))
    x = _sines(t, x_terms, px) + [0.0, 0.0, 1.5]
    v = _sines(t, x_terms, px, 1)
    a = _sines(t, x_terms, px, 2)
    f = _sines(t, F_TERMS, pf)
    lead = np.tile([0.0, 0.0, 2.5], (T, 1))
    pos = np.stack([lead, x], axis=1)
    vel = np.stack([np.zeros((T, 3)), v], axis=1)
    zeros = np.zeros((T, 2, 3))
    arrays = {
        "t": t, "pos": pos, "vel": vel,
        # the truth is level; the motion-capture attitude is `leader_quat`: labels must use the estimate
        "quat": np.tile([1.0, 0.0, 0.0, 0.0], (T, 2, 1)),
        "quat_est": np.tile(np.array(leader_quat, dtype=float), (T, 2, 1)),
        "pos_est": pos + 1e-4 * rng.normal(size=pos.shape), "vel_est": vel + 1e-3 * rng.normal(size=vel.shape),
        "yaw_est": np.zeros((T, 2)), "mocap_pos": pos + noise * rng.normal(size=pos.shape),
        "ref_pos": pos, "ref_vel": vel, "ref_acc": zeros,
        "u_cmd": np.stack([np.zeros((T, 3)), a - f], axis=1), "f_hat": zeros,
        "field_mean": np.stack([np.zeros((T, 3)), f], axis=1), "field_applied": np.stack([np.zeros((T, 3)), f], axis=1),
    }  # fmt: skip
    assert set(arrays) == set(ARRAY_SPECS)
    meta = {"seed": seed, "config": {}, "vehicles": ["alpha", "bravo"], "status": status, "message": "",
            "leader": 0, "follower": 1, "stage": stage}  # fmt: skip
    return FlightLog(arrays, meta)


def label_error_bounds(window=DEFAULT_WINDOW, polyorder=DEFAULT_POLYORDER):
    """(noise std per axis, deterministic error bound), m/s^2, from the filters' responses.

    label - f = (S2[x] - x'') - (K[u] - u) with u = x'' - f. For a sinusoid of
    angular frequency w the symmetric filters scale it by G2(w) = sum c2_k cos(w k dt)
    (vs -w^2 for x'') and G0(w) = sum K_k cos(w k dt) (vs 1).
    """
    c2 = savgol_coeffs(window, polyorder, deriv=2, delta=DT, use="conv")
    K = command_kernel(window, polyorder)
    k2 = (np.arange(window) - window // 2) * DT
    k0 = (np.arange(window - 2) - (window - 2) // 2) * DT
    G2 = lambda w: np.sum(c2 * np.cos(w * k2))  # noqa: E731
    G0 = lambda w: np.sum(K * np.cos(w * k0))  # noqa: E731
    bound = 0.0
    for amp, hz in X_TERMS:
        w = 2 * np.pi * hz
        bound += amp * abs(G2(w) + w**2) + amp * w**2 * abs(G0(w) - 1)
    for amp, hz in F_TERMS:
        bound += amp * abs(G0(2 * np.pi * hz) - 1)
    return MOCAP_NOISE * np.linalg.norm(c2), bound


def _lstsq_tolerance(window: int, polyorder: int, c: np.ndarray) -> float:
    """How far scipy's LAPACK least-squares Savitzky-Golay coefficients `c` may lie from the exact ones
    on any CPU: cond(A) * eps * |c| (first order) for the window's Vandermonde rows A."""
    points = np.arange(window, dtype=float) - window // 2
    return np.linalg.cond(points ** np.arange(polyorder + 1)[:, None]) * np.finfo(float).eps * np.linalg.norm(c)


@pytest.mark.parametrize("window,polyorder", [(3, 2), (5, 2), (7, 3), (19, 4), (21, 6), (31, 5)])
def test_filter_coefficients_are_scipys_solved_exactly(window, polyorder):
    """The exact rationals, rounded once: scipy's LAPACK solve to its round-off, and the moments
    of a second derivative (sum c_i i^k = 2 for k = 2, else 0, up to polyorder) to float64's.

    scipy solves the least-squares system A c = b (A the window's Vandermonde rows, up to
    polyorder) with LAPACK, whose last bits depend on the CPU's kernels; a backward-stable solve
    is accurate to cond(A) * eps * |c| (first order), so that is the tolerance: 1.95e-11 for a
    window of 21 with order 6 (cond 8.0e5; one AVX2 machine was 1.4e-12 off), 1.8e-15 for 3 with 2.
    The exact check is the moments' below.
    """
    c = second_derivative_coeffs(window, polyorder)
    np.testing.assert_allclose(c, savgol_coeffs(window, polyorder, deriv=2, use="conv"), rtol=0,
                               atol=_lstsq_tolerance(window, polyorder, c))
    i = np.arange(window) - window // 2
    for k in range(polyorder + 1):
        scale = np.abs(c * i**k).sum()
        # a float sum of `window` exact products: at most window * eps * scale (<= 7e-15 * scale) off
        assert abs((c * i**k).sum() - (2.0 if k == 2 else 0.0)) <= 1e-14 * scale, k
    c[0] = 7.0  # a copy: the cached coefficients stay as they are
    assert second_derivative_coeffs(window, polyorder)[0] != 7.0


def test_savgol_differentiator_is_exact_on_polynomials():
    t = np.arange(200) * DT
    coef = np.array([[0.3, -1.0, 0.5, 0.2, -0.05], [1.0, 0.1, -0.4, 0.03, 0.01], [2.0, 0.0, 0.7, -0.2, 0.02]])
    x = np.stack([np.polynomial.polynomial.polyval(t, c) for c in coef], axis=-1)
    acc = np.stack([np.polynomial.polynomial.polyval(t, np.polynomial.polynomial.polyder(c, 2)) for c in coef], axis=-1)
    np.testing.assert_allclose(follower_acceleration(t, x), acc, atol=1e-7)  # degree 4 = polyorder, also at the ends
    np.testing.assert_allclose(follower_acceleration(t, x[:, None, :])[:, 0], acc, atol=1e-7)  # (T, V, 3)
    K = command_kernel()
    assert K.size == DEFAULT_WINDOW - 2 and K.sum() == pytest.approx(1.0) and np.allclose(K, K[::-1])
    c2 = savgol_coeffs(DEFAULT_WINDOW, DEFAULT_POLYORDER, deriv=2, use="conv")
    np.testing.assert_allclose(np.convolve([1.0, -2.0, 1.0], K), c2, rtol=0,
                               atol=_lstsq_tolerance(DEFAULT_WINDOW, DEFAULT_POLYORDER, c2))


def test_filter_argument_errors():
    t = np.arange(50) * DT
    with pytest.raises(ValueError, match="window: expected an odd integer >= 3"):
        follower_acceleration(t, np.zeros((50, 3)), window=10)
    with pytest.raises(ValueError, match=r"polyorder: expected an integer in \[2, window - 1\]"):
        follower_acceleration(t, np.zeros((50, 3)), window=5, polyorder=5)
    with pytest.raises(ValueError, match="shorter than the filter window 19"):
        follower_acceleration(t[:10], np.zeros((10, 3)))
    with pytest.raises(ValueError, match="t: samples must be uniformly spaced"):
        follower_acceleration(t**2, np.zeros((50, 3)))


def test_labels_recover_the_force_without_noise():
    log = make_log(noise=0.0)
    lab = labels_from_log(log)
    _, bound = label_error_bounds()
    rows = lab["row"]
    np.testing.assert_array_equal(rows, np.arange(HALF, 3000 - HALF))
    f = log["field_mean"][rows, 1]
    assert np.max(np.abs(lab["y"] - f)) <= bound + 1e-4, (np.max(np.abs(lab["y"] - f)), bound)
    assert bound < 0.02  # slow signals: the smoothing bias is small
    # inputs: estimated states, the leader's attitude
    assert lab["mask"].all() and (lab["neighbour"] == 0).all() and (lab["vehicle"] == 1).all()  # the pair: K = 1
    np.testing.assert_allclose(lab["dp"][:, 0], log["pos_est"][rows, 1] - log["pos_est"][rows, 0])
    np.testing.assert_allclose(lab["v_b"], log["vel_est"][rows, 1])
    np.testing.assert_allclose(lab["v_a"][:, 0], log["vel_est"][rows, 0])
    np.testing.assert_allclose(lab["R_a"][:, 0], np.broadcast_to(np.eye(3), (rows.size, 3, 3)))
    np.testing.assert_allclose(lab["t"], log["t"][rows])


def test_fast_commands_cancel_in_the_label():
    """The command is smoothed with the kernel the acceleration filter applies, so fast motion that
    the command explains (here 4 Hz, 1.3 m/s^2) barely leaks into the label."""
    fast = (0.002, 4.0)  # m, Hz
    lab = labels_from_log(make_log(noise=0.0, x_terms=X_TERMS + [fast]))
    _, bound = label_error_bounds()
    w = 2 * np.pi * fast[1]
    c2 = savgol_coeffs(DEFAULT_WINDOW, DEFAULT_POLYORDER, deriv=2, delta=DT, use="conv")
    K = command_kernel()
    G2 = np.sum(c2 * np.cos(w * (np.arange(DEFAULT_WINDOW) - HALF) * DT))
    G0 = np.sum(K * np.cos(w * (np.arange(DEFAULT_WINDOW - 2) - HALF + 1) * DT))
    # what is left: the second difference's own error, x'' (w dt)^2 / 12 through K (2 % here) ...
    leak_consistent = fast[0] * abs(G2 + w**2 * G0)
    # ... against what a raw (unsmoothed) command would leave (35 %)
    leak_raw = fast[0] * abs(G2 + w**2)
    assert leak_raw > 0.3 and leak_consistent < 0.03
    err = np.max(np.abs(lab["y"] - lab["field_mean"]))
    assert err <= bound + leak_consistent + 1e-4, (err, bound, leak_consistent)


def test_labels_recover_the_force_with_mocap_noise():
    sigma, bound = label_error_bounds()
    assert 0.05 < sigma < 0.1  # 0.5 mm at 50 Hz through the 19 / 4 filter: about 0.077 m/s^2
    err = []
    for seed in range(3):
        lab = labels_from_log(make_log(seed=seed))
        err.append(lab["y"] - lab["field_mean"])
    err = np.concatenate(err)
    rmse_axis = np.sqrt(np.mean(err**2, axis=0))
    # ~9000 samples, correlated over a window: a few hundred independent ones, so +-20 % is > 4 sigma
    assert np.all(rmse_axis > 0.8 * sigma) and np.all(rmse_axis < 1.2 * sigma + bound), (rmse_axis, sigma, bound)
    assert np.all(np.abs(err.mean(axis=0)) < 5 * sigma / np.sqrt(err.shape[0] / DEFAULT_WINDOW) + bound)
    floor = label_noise_floor([make_log(seed=s) for s in range(3)])
    assert floor["rmse"] == pytest.approx(np.sqrt(np.mean(err**2)))
    assert floor["rmse_mean"] == floor["rmse"]  # this log's applied field is the mean field
    assert len(floor["rmse_axis"]) == 3 and floor["n_samples"] == err.shape[0]


def test_labels_use_the_motion_capture_leader_attitude_not_the_truth():
    """R_a comes from quat_est (tilted here), never from the true quat (level here)."""
    q = np.array([np.cos(0.2), np.sin(0.2), 0.0, 0.0])  # 0.4 rad roll
    lab = labels_from_log(make_log(T=200, leader_quat=q))
    np.testing.assert_allclose(lab["R_a"][:, 0], np.broadcast_to(quat_to_rotmat(q), lab["R_a"][:, 0].shape))


def test_failed_flights_and_non_finite_rows_are_cut():
    ok = labels_from_log(make_log(T=600))
    failed = labels_from_log(make_log(T=600, status=2))
    margin = int(round(0.5 / DT))
    assert ok["row"][-1] == 600 - HALF - 1
    assert failed["row"][-1] == 600 - margin - HALF - 1
    log = make_log(T=600)
    log.arrays["mocap_pos"][400, 1, 0] = np.nan
    cut = labels_from_log(log)
    assert cut["row"][-1] == 400 - HALF - 1 and np.all(np.isfinite(cut["y"]))
    assert len(labels_from_log(make_log(T=15))["y"]) == 0  # shorter than one window
    with pytest.raises(ValueError, match=r"flight.npz: targets: expected distinct vehicle indices in \[0, 1\], got \[0, 0\]"):
        labels_from_log(make_log(T=100), source="flight.npz", targets=[0, 0])


def test_load_dataset_from_a_folder(tmp_path):
    for i, (stage, T) in enumerate([(0, 400), (0, 300), (1, 500), (2, 350)]):
        save_log(tmp_path / f"flight_{i:02d}.npz", make_log(T=T, seed=i, stage=stage))
    save_log(tmp_path / "flight_99.npz", make_log(T=10, seed=9))  # too short: skipped with a warning
    ds = load_dataset(tmp_path)
    assert ds.sources == tuple(str(tmp_path / f"flight_{i:02d}.npz") for i in (0, 1, 2, 3, 99))
    assert list(ds.flights) == [0, 1, 2, 3]
    n = [400, 300, 500, 350]
    for i in range(4):
        assert np.sum(ds.flight == i) == n[i] - 2 * HALF
    assert list(ds.stages) == [0, 1, 2]
    assert np.all(ds.stage[ds.flight == 2] == 1)
    assert ds.n_minutes == pytest.approx(len(ds) * DT / 60)
    assert ds.summary()["n_flights"] == 4
    one = load_dataset(tmp_path / "flight_02.npz", stage=5)
    assert np.all(one.stage == 5) and len(one) == 500 - 2 * HALF
    two = load_dataset([tmp_path / "flight_00.npz", tmp_path / "flight_01.npz"])
    assert list(two.flights) == [0, 1]


def test_load_dataset_errors_name_the_folder_or_file(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match=r"empty: empty folder, no .npz flight logs"):
        load_dataset(empty)
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "readme.txt").write_text("hello")
    with pytest.raises(ValueError, match=r"notes: no .npz flight logs among 1 entries \(e.g. 'readme.txt'\)"):
        load_dataset(notes)
    with pytest.raises(FileNotFoundError, match="missing: no such file or folder"):
        load_dataset(tmp_path / "missing")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    save_log(foreign / "a_good.npz", make_log(T=100))
    np.savez(foreign / "b_random.npz", x=np.arange(3))
    with pytest.raises(LogError, match=r"b_random.npz: not a flight log of this project"):
        load_dataset(foreign)
    text = tmp_path / "text"
    text.mkdir()
    (text / "fake.npz").write_text("this is not a zip file")
    with pytest.raises(LogError, match=r"fake.npz: not a readable .npz flight log"):
        load_dataset(text)
    with pytest.raises(LogError, match=r"b_random.npz"):
        load_dataset([foreign / "a_good.npz", foreign / "b_random.npz"])


def synthetic_dataset(flight_lengths_by_stage, seed=0):
    """A Dataset of flights with the given lengths (samples) per stage; t counts ticks from each flight's start."""
    parts = []
    rng = np.random.default_rng(seed)
    for stage, lengths in flight_lengths_by_stage.items():
        for n in lengths:
            lab = {k: rng.normal(size=(n, 3)) for k in ("dp", "v_a", "v_b", "y", "field_mean")}
            one = Dataset.from_pairs(lab["dp"], lab["v_a"], lab["v_b"], np.broadcast_to(np.eye(3), (n, 3, 3)),
                                     lab["y"], np.zeros(n, int), np.full(n, stage), np.arange(n) * DT + 1.0,
                                     lab["field_mean"], sources=[f"s{stage}_{n}"])
            parts.append(one)
    return concatenate(parts)


def test_concatenate_keeps_flights_distinct():
    a = synthetic_dataset({0: [10, 20]})
    b = synthetic_dataset({1: [5]})
    c = concatenate([a, b])
    assert list(c.flights) == [0, 1, 2] and c.sources == ("s0_10", "s0_20", "s1_5")
    sub = c.select_flights([2])
    assert len(sub) == 5 and sub.sources == c.sources and np.all(sub.stage == 1)
    with pytest.raises(ValueError, match=r"Dataset.dp: expected shape \(2, 1, 3\), got \(3, 1, 3\)"):
        Dataset.from_pairs(np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3, 3)), np.zeros((2, 3)),
                           np.zeros(3))


def test_shorten_per_stage_keeps_stage_proportions():
    ds = synthetic_dataset({0: [900, 600, 1500, 300], 1: [1200, 1200, 600], 2: [3000, 1500]})
    total = ds.n_minutes
    for minutes in (0.3 * total, 0.5, total / 3, total):
        short = shorten_per_stage(ds, minutes, np.random.default_rng(1))
        frac = minutes / total
        assert short.n_minutes == pytest.approx(minutes, abs=3 * DT / 60)
        for s in ds.stages:
            assert np.sum(short.stage == s) == round(frac * np.sum(ds.stage == s))
            partial = 0
            for f in np.unique(short.flight[short.stage == s]):
                kept, full = np.sum(short.flight == f), np.sum(ds.flight == f)
                if kept < full:
                    partial += 1
                    t = np.sort(short.t[short.flight == f])  # a contiguous prefix from the flight's start
                    np.testing.assert_allclose(t, ds.t[ds.flight == f][:kept])
            assert partial <= 1
    a = shorten_per_stage(ds, 1.0, np.random.default_rng(5))
    b = shorten_per_stage(ds, 1.0, np.random.default_rng(5))
    np.testing.assert_array_equal(a.flight, b.flight)
    with pytest.raises(ValueError, match=r"minutes: expected a value in \(0, 3.6\]"):
        shorten_per_stage(ds, 10.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"minutes: expected a value in"):
        shorten_per_stage(ds, 0.0, np.random.default_rng(0))


def test_split_by_flight_is_disjoint_and_covers_stages():
    ds = synthetic_dataset({0: [500, 400, 600, 300], 1: [700, 700], 2: [1000]})
    for seed in range(10):
        train, val = split_by_flight(ds, 0.25, np.random.default_rng(seed))
        assert set(train.flights).isdisjoint(val.flights)
        assert set(train.flights) | set(val.flights) == set(ds.flights)
        assert len(train) + len(val) == len(ds)
        assert {0, 1} <= set(val.stages)  # every stage that can spare a flight is validated
        assert 2 not in set(val.stages)  # the single stage-2 flight stays in training
        assert np.all(np.isin(train.flights, ds.flights))
    with pytest.raises(ValueError, match="need at least 2 flights"):
        split_by_flight(synthetic_dataset({0: [100]}), 0.2, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"val_fraction: expected a value in \(0, 1\), got 0"):
        split_by_flight(ds, 0, np.random.default_rng(0))


def test_a_non_finite_value_on_any_vehicle_cuts_every_targets_labels():
    """One finiteness rule over every vehicle: a NaN on the leader's command (which the follower's labels
    never read) cuts the follower's labels, with one neighbour or every vehicle as a target."""
    from downwash.labels import finite_rows, labels_from_log
    from sim.flight import fly
    from sim.neighbours import NeighbourSet
    from sim.scene import build_scene
    from downwash_trajectories import Hover, Lemniscate, stack

    leader = np.array([0.0, 0.0, 2.5])
    reference = stack([Hover(leader, n_worlds=1), Lemniscate(leader - [0, 0, 0.6], n_worlds=1)])
    log = fly(build_scene(), reference, [0], 3.0)[0]
    cut = 150
    log.arrays["u_cmd"][cut:, int(log.meta["leader"])] = np.nan
    assert finite_rows(log.arrays) == cut
    pair = labels_from_log(log)
    every = labels_from_log(log, NeighbourSet(3), targets="all")
    assert pair["row"].max() == cut - HALF - 1 and every["row"].max() == cut - HALF - 1
    follower = every["vehicle"] == int(log.meta["follower"])
    np.testing.assert_array_equal(pair["y"], every["y"][follower])
