"""Tests for controllers.references: analytic derivatives, geometry, batching, errors."""

from __future__ import annotations

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_trajectories import (
    Cached,
    Circle,
    Line,
    Offset,
    Relative,
    SPEED_RANGE,
    Hover,
    Lemniscate,
    RefSample,
    Reference,
    Transect,
    Waypoints,
    TimeShifted,
    random_passes,
    stack,
)

LEADER = np.array([0.3, -0.2, 2.5])  # m


# ----------------------------------------------------------------------------- helpers


def min_jerk_scalar(tau: float) -> tuple[float, float, float]:
    """s, ds/dtau, d2s/dtau2 of the quintic, written out independently."""
    return (
        10 * tau**3 - 15 * tau**4 + 6 * tau**5,
        30 * tau**2 - 60 * tau**3 + 30 * tau**4,
        60 * tau - 180 * tau**2 + 120 * tau**3,
    )


def slow_waypoints(points, durations, dwell, t: float):
    """Plain-Python evaluation of one world's pattern at one time."""
    points = [np.asarray(p, float) for p in points]
    clock = 0.0
    for k, p in enumerate(points):
        if t < clock + dwell[k]:
            return p, np.zeros(3), np.zeros(3)
        clock += dwell[k]
        if k == len(points) - 1:
            break
        T = durations[k]
        if t < clock + T:
            tau = max((t - clock) / T, 0.0)
            s, ds, dds = min_jerk_scalar(tau)
            d = points[k + 1] - p
            return p + s * d, ds / T * d, dds / T**2 * d
        clock += T
    return points[-1], np.zeros(3), np.zeros(3)


def assert_fd_derivatives(ref: Reference, t: np.ndarray | float, h: float = 1e-5) -> None:
    """vel == d pos / dt and acc == d vel / dt by central differences."""
    t = np.asarray(t, float)
    lo, mid, hi = ref(t - h), ref(t), ref(t + h)
    fd_vel = (hi.pos - lo.pos) / (2 * h)
    fd_acc = (hi.vel - lo.vel) / (2 * h)
    fd_yaw_rate = (hi.yaw - lo.yaw) / (2 * h)
    np.testing.assert_allclose(mid.vel, fd_vel, atol=1e-6, rtol=1e-6)
    np.testing.assert_allclose(mid.acc, fd_acc, atol=1e-4, rtol=1e-5)
    np.testing.assert_allclose(mid.yaw_rate, fd_yaw_rate, atol=1e-6)


def check_sample_shapes(s: RefSample, w: int) -> None:
    assert s.pos.shape == s.vel.shape == s.acc.shape == (w, 3)
    assert s.yaw.shape == s.yaw_rate.shape == (w,)
    for a in s:
        assert np.all(np.isfinite(a))


# ----------------------------------------------------------------------------- derivatives


def _all_refs() -> dict[str, Reference]:
    w = 5
    rng = np.random.default_rng(7)
    centers = LEADER + rng.normal(scale=0.5, size=(w, 3))
    return {
        "hover": Hover(centers),
        "lemniscate": Lemniscate(
            centers, half_length=rng.uniform(0.5, 1.5, w), half_width=0.4, period=rng.uniform(8, 25, w)
        ),
        "transect": Transect(centers, x_offset=rng.uniform(-0.3, 0.3, w), half_length=1.2, period=[6, 9, 12, 15, 18]),
        "waypoints": Waypoints(
            rng.uniform(-1, 1, size=(w, 4, 3)), rng.uniform(0.5, 3, size=(w, 3)), rng.uniform(0, 1, size=(w, 4))
        ),
        "passes_seed0": random_passes(np.random.default_rng(0), w, LEADER),
        "passes_seed1": random_passes(np.random.default_rng(1), w, centers, duration=30.0, hover_prob=0.5),
        "passes_seed2": random_passes(
            np.random.default_rng(2), w, LEADER, depth_range=(0.5, 0.7), speed_range=(0.9, 1.0)
        ),
        "line": Line(centers, rng.uniform(-3, 3, size=(w, 3))),
        "circle": Circle(centers, radius=rng.uniform(0.5, 4, w), speed=[0.5, -1.0, 2.0, -3.0, 1.2],
                         phase=rng.uniform(0, 6, w)),
        "offset_circle": Offset(Circle(LEADER, radius=2.0, speed=2.5, n_worlds=w), [0.0, 0.0, -0.6]),
        # collection passes flown beneath a leader on a line: the derivatives of both add
        "relative_passes": Relative(Line(centers, rng.uniform(-3, 3, size=(w, 3))),
                                    random_passes(np.random.default_rng(3), w, LEADER, depth_range=(0.5, 0.7)), LEADER),
    }


@pytest.mark.parametrize("name", list(_all_refs()))
def test_analytic_derivatives_match_finite_differences(name):
    ref = _all_refs()[name]
    w = ref.n_worlds
    rng = np.random.default_rng(123)
    end = float(np.max(ref.duration)) if np.max(ref.duration) > 0 else 10.0
    for _ in range(40):
        t_world = rng.uniform(-1.0, end + 2.0, size=w)  # per-world times, also before/after
        check_sample_shapes(ref(t_world), w)
        assert_fd_derivatives(ref, t_world)
        assert_fd_derivatives(ref, float(rng.uniform(0.0, end)))  # shared time


def test_fd_check_catches_a_wrong_derivative():
    """The derivative check itself must be able to fail."""

    class Wrong:
        n_worlds = 1
        duration = 1.0

        def __call__(self, t):
            t = np.full(1, float(t)) if np.ndim(t) == 0 else np.asarray(t, float)
            pos = np.stack([np.sin(t), t**2, 0 * t], axis=1)
            vel = np.stack([np.cos(t), 2 * t, 0 * t], axis=1)
            acc = np.stack([np.sin(t), 2 + 0 * t, 0 * t], axis=1)  # sign error in x
            return RefSample(pos, vel, acc, 0 * t, 0 * t)

    with pytest.raises(AssertionError):
        assert_fd_derivatives(Wrong(), 0.7)


@pytest.mark.parametrize("name", list(_all_refs()))
def test_shared_time_equals_per_world_time(name):
    ref = _all_refs()[name]
    for t in (0.0, 3.21, 17.5, 100.0):
        a, b = ref(t), ref(np.full(ref.n_worlds, t))
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("name", list(_all_refs()))
def test_per_world_time_equals_world_by_world_sampling(name):
    ref = _all_refs()[name]
    ts = np.linspace(0.3, 25.0, ref.n_worlds)
    batched = ref(ts)
    for i, ti in enumerate(ts):
        single = ref(ti)
        for x, y in zip(batched, single):
            np.testing.assert_allclose(x[i], y[i], atol=1e-12)


# ----------------------------------------------------------------------------- hover


def test_hover_holds_points_with_zero_derivatives():
    ref = Hover([1.0, 2.0, 3.0], n_worlds=3)
    s = ref(np.array([0.0, 5.0, 1e4]))
    check_sample_shapes(s, 3)
    np.testing.assert_array_equal(s.pos, np.tile([1.0, 2.0, 3.0], (3, 1)))
    assert not s.vel.any() and not s.acc.any() and not s.yaw.any() and not s.yaw_rate.any()
    assert Hover(np.zeros((4, 3))).n_worlds == 4


# ----------------------------------------------------------------------------- lemniscate


def test_lemniscate_starts_at_tip_and_crosses_centre_at_quarter_periods():
    a, b, T = 1.3, 0.45, 16.0
    ref = Lemniscate(LEADER - [0, 0, 0.6], half_length=a, half_width=b, period=T)
    c = LEADER - [0, 0, 0.6]
    np.testing.assert_allclose(ref(0.0).pos[0], c + [a, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ref(T / 2).pos[0], c - [a, 0, 0], atol=1e-12)
    for tc in (T / 4, 3 * T / 4):
        np.testing.assert_allclose(ref(tc).pos[0], c, atol=1e-12)
        assert np.linalg.norm(ref(tc).vel[0]) > 0.1  # passes through, does not stop
    # The crossing is visited only at those two times in a period.
    ts = np.linspace(0, T, 4001)
    d = np.array([np.linalg.norm(ref(t).pos[0] - c) for t in ts])
    near = ts[d < 1e-3]
    assert np.all(np.minimum(abs(near - T / 4), abs(near - 3 * T / 4)) < 0.01)
    assert ref.duration == T


def test_lemniscate_shape_periodicity_and_constant_height():
    a, b, T = 1.0, 0.5, 20.0
    ref = Lemniscate(np.zeros(3), a, b, T, n_worlds=2)
    ts = np.linspace(0, T, 2001)
    pos = np.array([ref(t).pos[0] for t in ts])
    np.testing.assert_allclose(pos[:, 2], 0.0)
    np.testing.assert_allclose(np.abs(pos[:, 0]).max(), a, rtol=1e-6)
    np.testing.assert_allclose(np.abs(pos[:, 1]).max(), b, rtol=1e-4)
    rng = np.random.default_rng(0)
    for t in rng.uniform(0, 3 * T, 10):
        for x, y in zip(ref(t), ref(t + T)):
            np.testing.assert_allclose(x, y, atol=1e-9)


def test_lemniscate_per_world_parameters():
    centers = np.array([[0, 0, 1.0], [5, 5, 2.0]])
    ref = Lemniscate(centers, half_length=[1.0, 2.0], period=[10.0, 40.0])
    assert ref.n_worlds == 2
    np.testing.assert_array_equal(ref.duration, [10.0, 40.0])
    s = ref(np.array([2.5, 10.0]))  # each world at its own T / 4
    np.testing.assert_allclose(s.pos, centers, atol=1e-12)
    np.testing.assert_allclose(ref(0.0).pos, centers + [[1.0, 0, 0], [2.0, 0, 0]])


# ----------------------------------------------------------------------------- transect


def test_transect_geometry_and_peak_speed_at_centre():
    L, T = 1.2, 12.0
    c = LEADER - [0, 0, 0.6]
    ref = Transect(c, x_offset=0.2, half_length=L, period=T)
    ts = np.linspace(0, T, 6001)
    s = [ref(t) for t in ts]
    pos = np.array([x.pos[0] for x in s])
    speed = np.array([np.linalg.norm(x.vel[0]) for x in s])
    np.testing.assert_allclose(pos[:, 0], c[0] + 0.2)
    np.testing.assert_allclose(pos[:, 2], c[2])
    np.testing.assert_allclose(pos[:, 1].min(), c[1] - L, atol=1e-9)
    np.testing.assert_allclose(pos[:, 1].max(), c[1] + L, atol=1e-9)
    i = np.argmax(speed)
    assert abs(pos[i, 1] - c[1]) < 1e-2
    np.testing.assert_allclose(speed.max(), 2 * np.pi * L / T, rtol=1e-6)
    np.testing.assert_allclose(ref(T / 4).pos[0], c + [0.2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ref(0.0).vel[0], 0.0, atol=1e-12)


# ----------------------------------------------------------------------------- waypoints


def _patterns(seed: int, n: int):
    rng = np.random.default_rng(seed)
    pts, durs, dwells = [], [], []
    for _ in range(n):
        k = int(rng.integers(1, 7))
        pts.append(rng.uniform(-2, 2, size=(k, 3)))
        durs.append(rng.uniform(0.3, 4.0, size=k - 1))
        dw = rng.uniform(0.0, 2.0, size=k)
        dw[rng.uniform(size=k) < 0.3] = 0.0
        dwells.append(dw)
    return pts, durs, dwells


def test_waypoints_pass_through_each_point_at_its_time_and_hold_the_last():
    pts, durs, dwells = _patterns(3, 8)
    ref = Waypoints.from_patterns(pts, durs, dwells)
    assert ref.n_worlds == 8
    for w in range(8):
        k = len(pts[w])
        assert ref.n_points[w] == k
        expected_arrival = np.concatenate([[0.0], np.cumsum(dwells[w][:-1] + durs[w])])
        np.testing.assert_allclose(ref.arrival_times[w, :k], expected_arrival)
        assert np.all(np.isnan(ref.arrival_times[w, k:]))
        np.testing.assert_allclose(ref.duration[w], np.sum(dwells[w]) + np.sum(durs[w]))
    for k in range(ref.points.shape[1]):
        t = np.nan_to_num(ref.arrival_times[:, k], nan=1e3)
        for tt in (t, t + 0.5 * np.nan_to_num(ref.dwell[:, k])):  # arrival and mid-dwell
            s = ref(tt)
            has = k < ref.n_points
            np.testing.assert_allclose(s.pos[has], ref.points[has, k], atol=1e-12)
            np.testing.assert_allclose(s.vel[has], 0.0, atol=1e-12)
            np.testing.assert_allclose(s.acc[has], 0.0, atol=1e-12)
    last = np.array([p[-1] for p in pts])
    for extra in (0.0, 1.0, 1e3):
        s = ref(ref.duration + extra)
        np.testing.assert_allclose(s.pos, last, atol=1e-12)
        assert not s.vel.any() and not s.acc.any()
    first = np.array([p[0] for p in pts])
    np.testing.assert_allclose(ref(-5.0).pos, first)


def test_waypoints_batched_equals_slow_per_world_evaluation():
    pts, durs, dwells = _patterns(11, 12)
    ref = Waypoints.from_patterns(pts, durs, dwells)
    rng = np.random.default_rng(5)
    for _ in range(30):
        t = rng.uniform(-1.0, ref.duration.max() + 1.0, size=ref.n_worlds)
        s = ref(t)
        for w in range(ref.n_worlds):
            p, v, a = slow_waypoints(pts[w], durs[w], dwells[w], t[w])
            np.testing.assert_allclose(s.pos[w], p, atol=1e-12)
            np.testing.assert_allclose(s.vel[w], v, atol=1e-12)
            np.testing.assert_allclose(s.acc[w], a, atol=1e-12)
            single = Waypoints(pts[w], durs[w], dwells[w])(t[w])
            np.testing.assert_allclose(s.pos[w], single.pos[0], atol=1e-12)
            np.testing.assert_allclose(s.acc[w], single.acc[0], atol=1e-12)


def test_waypoints_min_jerk_peak_speed_and_shared_pattern():
    ref = Waypoints([[0, 0, 1.0], [2.0, 0, 1.0]], [4.0], dwell=0.0, n_worlds=3)
    assert ref.n_worlds == 3
    s = ref(2.0)  # mid-move: peak speed 1.875 * d / T
    np.testing.assert_allclose(s.vel, np.tile([1.875 * 2.0 / 4.0, 0, 0], (3, 1)))
    np.testing.assert_allclose(s.pos, np.tile([1.0, 0, 1.0], (3, 1)))
    np.testing.assert_allclose(s.acc, 0.0, atol=1e-12)


# ----------------------------------------------------------------------------- random passes


def _pass_moves(ref: Waypoints):
    """(world, start point, end point, duration) of every move tagged 'pass'."""
    w_idx, k_idx = np.nonzero(ref.move_tags == "pass")
    return w_idx, ref.points[w_idx, k_idx], ref.points[w_idx, k_idx + 1], ref.durations[w_idx, k_idx]


def test_random_passes_deterministic_per_seed_and_only_through_the_generator():
    a = random_passes(np.random.default_rng(42), 6, LEADER)
    np.random.seed(0)  # the global RNG must not matter
    b = random_passes(np.random.default_rng(42), 6, LEADER)
    np.random.seed(99)
    np.random.random(10)
    c = random_passes(np.random.default_rng(43), 6, LEADER)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.durations, b.durations)
    np.testing.assert_array_equal(a.dwell, b.dwell)
    np.testing.assert_array_equal(a.move_tags, b.move_tags)
    ts = np.linspace(0, 60, 50)
    for t in ts:
        for x, y in zip(a(t), b(t)):
            np.testing.assert_array_equal(x, y)
    assert a.points.shape != c.points.shape or not np.allclose(a.points, c.points, equal_nan=True)


def test_random_passes_waypoints_in_depth_range_and_pattern_length():
    for seed, depth in [(0, (1.35, 1.75)), (1, (0.45, 0.55)), (2, (0.9, 1.2))]:
        centers = LEADER + np.random.default_rng(seed).normal(size=(16, 3))
        ref = random_passes(np.random.default_rng(seed), 16, centers, depth_range=depth, duration=45.0)
        valid = ~np.isnan(ref.points[..., 0])
        sep = (centers[:, None, 2] - ref.points[..., 2])[valid]
        assert sep.min() >= depth[0] - 1e-12 and sep.max() <= depth[1] + 1e-12
        assert np.all(ref.duration >= 45.0)
        assert np.all(ref.duration < 45.0 + 40.0)  # "about" the asked length
        horiz = np.linalg.norm(ref.points[..., :2] - centers[:, None, :2], axis=-1)[valid]
        assert horiz.max() <= np.hypot(0.6, 1.0) + 1e-9


def test_random_passes_speeds_within_range():
    lo, hi = 0.2, 0.8
    ref = random_passes(np.random.default_rng(5), 24, LEADER, speed_range=(lo, hi), hover_prob=0.3)
    w_idx, p0, p1, dur = _pass_moves(ref)
    peak = 1.875 * np.linalg.norm(p1 - p0, axis=1) / dur
    assert peak.min() >= lo - 1e-9 and peak.max() <= hi + 1e-9
    assert peak.max() - peak.min() > 0.3 * (hi - lo)  # drawn, not constant
    # Dense sampling of the whole pattern (passes, repositioning, hovers).
    ts = np.arange(0.0, ref.duration.max() + 1.0, 0.02)
    speed = np.array([np.linalg.norm(ref(t).vel, axis=1) for t in ts])  # (T, W)
    assert speed.max() <= hi + 1e-6
    # Each pass reaches its drawn peak speed.
    arrive = ref.arrival_times[w_idx, np.nonzero(ref.move_tags == "pass")[1] + 1]
    for w, t_end, d, pk in zip(w_idx, arrive, dur, peak):
        tt = np.linspace(t_end - d, t_end, 401)
        v = np.array([np.linalg.norm(ref(t).vel[w]) for t in tt])
        np.testing.assert_allclose(v.max(), pk, rtol=1e-4)


def test_random_passes_headings_and_offsets():
    center = LEADER
    ref = random_passes(np.random.default_rng(9), 32, center, max_offset=0.6, pass_half_length=1.0)
    w_idx, p0, p1, _ = _pass_moves(ref)
    assert len(w_idx) > 60
    d = (p1 - p0)[:, :2]
    heading = np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi)
    counts = np.histogram(heading, bins=12, range=(0, 2 * np.pi))[0]
    assert np.all(counts > 0), counts
    # Horizontal closest approach of each straight pass to the wake axis.
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    r0 = p0[:, :2] - center[:2]
    s = np.clip(-(r0 * u).sum(1), 0.0, np.linalg.norm(d, axis=1))
    closest = np.linalg.norm(r0 + s[:, None] * u, axis=1)
    assert np.all(closest <= 0.6 + 1e-9)
    assert np.sum(closest < 0.05) >= 2  # some right through the wake
    assert np.sum(closest > 0.3) >= 10  # some beside it
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 2.0, rtol=1e-12)


def test_random_passes_hovers_and_segments():
    ref = random_passes(
        np.random.default_rng(4),
        8,
        LEADER,
        n_segments=10,
        hover_prob=0.5,
        hover_radius=0.8,
        hover_time_range=(2.0, 4.0),
    )
    n_items = (ref.move_tags == "pass").sum(1) + (np.nan_to_num(ref.dwell) > 0).sum(1)
    np.testing.assert_array_equal(n_items, 10)
    hov = np.nan_to_num(ref.dwell) > 0
    assert hov.sum() > 10
    assert np.all((ref.dwell[hov] >= 2.0) & (ref.dwell[hov] <= 4.0))
    r = np.linalg.norm(ref.points[hov][:, :2] - LEADER[:2], axis=1)
    assert r.max() <= 0.8 + 1e-12
    only_passes = random_passes(np.random.default_rng(4), 4, LEADER, hover_prob=0.0, duration=20.0)
    assert np.all(np.nan_to_num(only_passes.dwell) == 0.0)
    start = random_passes(np.random.default_rng(4), 3, LEADER, start=[0.0, 0.0, 1.0], duration=10.0)
    np.testing.assert_allclose(start(0.0).pos, np.tile([0.0, 0.0, 1.0], (3, 1)))
    assert np.all(start.move_tags[:, 0] == "reposition")


# ----------------------------------------------------------------------------- stack


def test_stack_shapes_and_values():
    w = 4
    leader = Hover(LEADER, n_worlds=w)
    follower = Lemniscate(LEADER - [0, 0, 0.6], n_worlds=w, period=[10, 12, 14, 16])
    third = random_passes(np.random.default_rng(0), w, LEADER)
    both = stack([leader, follower, third])
    assert both.n_worlds == w and both.n_vehicles == 3
    np.testing.assert_allclose(both.duration, np.maximum(third.duration, [10, 12, 14, 16]))
    t = np.array([0.5, 1.5, 7.0, 30.0])
    s = both(t)
    assert s.pos.shape == s.vel.shape == s.acc.shape == (w, 3, 3)
    assert s.yaw.shape == s.yaw_rate.shape == (w, 3)
    for v, ref in enumerate([leader, follower, third]):
        single = ref(t)
        for x, y in zip(s, single):
            np.testing.assert_array_equal(x[:, v], y)
    assert_fd_derivatives(both, t)


def test_stack_fill_writes_the_sample_into_kept_storage():
    """`fill` (the simulator's fused tick samples through it) equals a call, overwriting whatever
    the storage held, and checks the times as a call does."""
    w = 4
    both = stack([Hover(LEADER, n_worlds=w), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=w, period=[10, 12, 14, 16]),
                  random_passes(np.random.default_rng(1), w, LEADER)])
    vec, ang = np.full((3, w, 3, 3), np.nan), np.full((2, w, 3), np.nan)
    for t in (np.array([0.5, 1.5, 7.0, 30.0]), 3.25):
        both.fill(t, vec, ang)
        for x, y in zip((*vec, *ang), both(t)):
            np.testing.assert_array_equal(x, y)
    with pytest.raises(ConfigError, match="t: expected"):
        both.fill(np.zeros(3), vec, ang)


def test_stack_rejects_mismatched_world_counts():
    with pytest.raises(ValueError, match="same n_worlds"):
        stack([Hover(LEADER, n_worlds=2), Hover(LEADER, n_worlds=3)])
    with pytest.raises(ValueError, match="refs"):
        stack([])


# ----------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize("speed_range", [(0.05, 1.0), (0.1, 1.5), (0.8, 0.2), (-1.0, 0.5), (0.2,)])
def test_random_passes_rejects_speeds_out_of_range(speed_range):
    with pytest.raises(ValueError, match=r"speed_range: .*allowed 0\.1-1\.0 m/s"):
        random_passes(np.random.default_rng(0), 2, LEADER, speed_range=speed_range)


def test_speed_range_constant_matches_design():
    assert SPEED_RANGE == (0.1, 1.0)


@pytest.mark.parametrize("depth_range", [(0.0, 1.0), (-0.5, 1.0), (1.75, 1.35), (np.nan, 1.0)])
def test_random_passes_rejects_bad_depth_range(depth_range):
    with pytest.raises(ValueError, match="depth_range: .*allowed > 0"):
        random_passes(np.random.default_rng(0), 2, LEADER, depth_range=depth_range)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(duration=0.0), "duration: must be finite and > 0 s"),
        (dict(duration=-3.0), "duration"),
        (dict(n_segments=0), "n_segments"),
        (dict(hover_prob=1.5), "hover_prob: .*allowed 0-1"),
        (dict(max_offset=-0.1), "max_offset"),
        (dict(pass_half_length=0.0), "pass_half_length"),
        (dict(reposition_speed=2.0), r"reposition_speed: .*allowed 0\.1-1\.0 m/s"),
        (dict(hover_time_range=(3.0, 1.0)), "hover_time_range"),
        (dict(start=[0.0, 1.0]), r"start: expected shape \(W, 3\) or \(3,\)"),
        (dict(start=np.zeros((3, 3))), r"start: expected shape \(2, 3\) or \(3,\)"),
    ],
)
def test_random_passes_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        random_passes(np.random.default_rng(0), 2, LEADER, **kwargs)


def test_random_passes_rejects_bad_world_count_center_and_rng():
    with pytest.raises(ValueError, match="n_worlds"):
        random_passes(np.random.default_rng(0), 0, LEADER)
    with pytest.raises(ValueError, match=r"center: expected shape \(3, 3\) or \(3,\)"):
        random_passes(np.random.default_rng(0), 3, np.zeros((2, 3)))
    with pytest.raises(TypeError, match="rng"):
        random_passes(0, 3, LEADER)


@pytest.mark.parametrize("period", [0.0, -1.0, np.inf, [10.0, 0.0]])
def test_periodic_references_reject_bad_periods(period):
    with pytest.raises(ValueError, match="period: must be finite and > 0 s"):
        Lemniscate(LEADER, period=period)
    with pytest.raises(ValueError, match="period: must be finite and > 0 s"):
        Transect(LEADER, period=period)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Hover([1.0, 2.0]), r"points: expected shape \(W, 3\) or \(3,\)"),
        (lambda: Hover(np.zeros((2, 4))), r"points: expected shape \(W, 3\) or \(3,\)"),
        (lambda: Hover([0, 0, np.nan]), "points: must be finite"),
        (lambda: Hover(np.zeros((2, 3)), n_worlds=3), "n_worlds: got 3 but points is batched over 2"),
        (lambda: Hover(LEADER, n_worlds=0), "n_worlds"),
        (lambda: Lemniscate(np.zeros((3, 3)), half_length=[1.0, 2.0]), "disagree on the number of worlds"),
        (lambda: Lemniscate(LEADER, half_length=-1.0), "half_length: must be finite and > 0 m"),
        (lambda: Lemniscate(LEADER, half_width=0.0), "half_width"),
        (lambda: Lemniscate([0.0, 0.0]), r"center: expected shape \(W, 3\) or \(3,\)"),
        (lambda: Transect(LEADER, half_length=0.0), "half_length"),
        (lambda: Transect(LEADER, x_offset=np.nan), "x_offset"),
        (lambda: Waypoints(np.zeros((3, 2)), [1.0, 1.0]), r"points: expected shape \(W, K, 3\) or \(K, 3\)"),
        (lambda: Waypoints(np.zeros((3, 3)), [1.0]), r"durations: expected shape \(W, 2\) or \(2,\)"),
        (lambda: Waypoints(np.zeros((3, 3)), [1.0, 0.0]), "durations: every move needs a finite duration > 0 s"),
        (lambda: Waypoints(np.zeros((3, 3)), [1.0, 1.0], dwell=-1.0), "dwell: every dwell must be finite and >= 0 s"),
        (lambda: Waypoints(np.zeros((3, 3)), [1.0, 1.0], dwell=[1.0, 2.0]), r"dwell: expected a float or shape"),
        (
            lambda: Waypoints([[[0, 0, 0], [np.nan] * 3, [1, 1, 1]]], [[1.0, 1.0]]),
            "points: NaN padding must be trailing",
        ),
        (lambda: Waypoints([[0, 0, np.nan], [1, 1, 1]], [1.0]), "some but not all coordinates NaN"),
        (lambda: Waypoints.from_patterns([np.zeros((2, 3))], [[1.0, 2.0]]), r"durations\[0\]: expected shape \(1,\)"),
        (lambda: Waypoints.from_patterns([np.zeros((2, 3))], [[1.0]], [[1.0]]), r"dwell\[0\]: expected a float or"),
        (lambda: Waypoints.from_patterns([np.zeros((2, 3))], [[1.0]], [1.0, 2.0]), "dwell: expected a float or 1"),
    ],
)
def test_constructors_reject_bad_inputs(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_sampling_rejects_wrong_time_shape():
    for ref in _all_refs().values():
        with pytest.raises(ValueError, match=r"t: expected a float or shape \(5,\)"):
            ref(np.zeros(3))


@pytest.mark.parametrize(
    "make",
    [
        lambda: Hover(LEADER, yaw=1.0),
        lambda: Lemniscate(LEADER, radius=1.0),
        lambda: Transect(LEADER, y_offset=0.2),
        lambda: Waypoints(np.zeros((2, 3)), [1.0], speed=1.0),
        lambda: random_passes(np.random.default_rng(0), 2, LEADER, speeds=(0.1, 0.5)),
    ],
)
def test_unknown_keywords_raise_type_error(make):
    with pytest.raises(TypeError):
        make()


def test_mixed_routes_worlds_to_their_references():
    from downwash_trajectories import Mixed

    lem = Lemniscate(np.zeros(3), n_worlds=2)
    hov = Hover(np.array([[1.0, 2.0, 3.0]]))
    mixed = Mixed([(lem, [0, 2]), (hov, [1])])
    t = np.array([1.5, 7.0, 3.0])
    s = mixed(t)
    np.testing.assert_array_equal(s.pos[[0, 2]], lem(t[[0, 2]]).pos)
    np.testing.assert_array_equal(s.pos[1], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(s.vel[1], 0.0)
    with pytest.raises(ValueError, match="exactly one"):
        Mixed([(lem, [0, 1]), (hov, [1])])
    with pytest.raises(ValueError, match="n_worlds=2"):
        Mixed([(lem, [0]), (hov, [1])])


def test_stack_fills_in_place_exactly_like_sampling_each_reference():
    """StackedReference's in-place fill of built-in references equals sampling them one by one."""
    rng = np.random.default_rng(2)
    W = 4
    refs = [
        Hover(rng.normal(size=(W, 3))),
        Lemniscate(rng.normal(size=(W, 3)), rng.uniform(0.5, 2, W), rng.uniform(0.2, 1, W), rng.uniform(5, 30, W)),
        Transect(rng.normal(size=(W, 3)), rng.normal(size=W), rng.uniform(0.5, 2, W), rng.uniform(5, 30, W)),
        # shifted by a per-world phase: in place through the inner reference, at t + t0
        TimeShifted(Lemniscate(rng.normal(size=(W, 3)), 1.0, 0.5, 10.0, n_worlds=W), rng.uniform(0, 10, W)),
    ]
    assert hasattr(refs[-1], "sample_into")

    class Opaque:  # a Reference without the in-place fill: sampled and copied
        def __init__(self, ref):
            self.ref, self.n_worlds, self.duration = ref, ref.n_worlds, ref.duration

        def __call__(self, t):
            return self.ref(t)

    for t in (rng.uniform(-5, 50, W), 3.3):
        fast, slow = stack(refs)(t), stack([Opaque(r) for r in refs])(t)
        for v, ref in enumerate(refs):
            for a, b, c in zip(fast, slow, ref(t)):
                assert np.array_equal(a[:, v], c) and np.array_equal(b[:, v], c)


def test_moving_leader_references_have_the_speed_and_geometry_asked_for():
    """Circle: constant speed |v| = speed, centripetal |a| = speed^2 / radius, radius kept, the sign
    of speed sets the turn; Line: pos = start + v t; Offset keeps velocity and shifts position."""
    t = np.linspace(0.0, 20.0, 7)
    c = Circle([1.0, -1.0, 3.0], radius=2.5, speed=-2.0, n_worlds=7)
    s = c(t)
    np.testing.assert_allclose(np.linalg.norm(s.vel, axis=1), 2.0, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(s.acc, axis=1), 4.0 / 2.5, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(s.pos[:, :2] - [1.0, -1.0], axis=1), 2.5, rtol=1e-12)
    rel = s.pos[:, :2] - [1.0, -1.0]
    assert np.all(rel[:, 0] * s.vel[:, 1] - rel[:, 1] * s.vel[:, 0] < 0)  # clockwise for a negative speed
    assert c.duration == pytest.approx(2 * np.pi * 2.5 / 2.0)
    line = Line([0.0, 0.0, 2.5], [1.5, -0.5, 0.0], n_worlds=7)
    np.testing.assert_allclose(line(t).pos, [0.0, 0.0, 2.5] + t[:, None] * [1.5, -0.5, 0.0])
    below = Offset(c, [0.0, 0.0, -0.6])(t)
    np.testing.assert_allclose(below.pos, s.pos - [0, 0, 0.6])
    assert np.array_equal(below.vel, s.vel) and np.array_equal(below.acc, s.acc)
    with pytest.raises(ValueError, match="speed: must be non-zero"):
        Circle([0, 0, 2.5], speed=0.0)
    with pytest.raises(ValueError, match=r"offset: expected 3 finite numbers"):
        Offset(c, [0.0, 0.6])


def test_cached_reuses_a_sample_only_for_the_same_times():
    """Cached returns its last sample for bit-identical times, and samples afresh otherwise, even when
    the caller changed its times array in place (the simulator's clock)."""
    lem = Lemniscate(np.zeros((3, 3)), 1.0, 0.5, 10.0, n_worlds=3)
    cached = Cached(lem)
    t = np.array([0.0, 1.0, 2.0])
    first = cached(t)
    assert cached(t.copy()) is first
    t[1] = 1.5  # in place
    second = cached(t)
    assert second is not first
    for a, b in zip(second, lem(t)):
        np.testing.assert_array_equal(a, b)
    assert cached(3.0) is not second and np.array_equal(cached(3.0).pos, lem(3.0).pos)


def test_a_relative_pattern_is_the_pattern_moved_with_its_base():
    w = 3
    base = Line(LEADER, [1.5, 0.0, 0.0], n_worlds=w)
    pattern = random_passes(np.random.default_rng(4), w, LEADER, depth_range=(0.5, 0.7))
    ref = Relative(base, pattern, LEADER)
    t = np.array([0.0, 2.5, 7.0])
    got, b, p = ref(t), base(t), pattern(t)
    np.testing.assert_array_equal(got.pos, b.pos + (p.pos - LEADER))
    np.testing.assert_array_equal(got.vel, b.vel + p.vel)
    np.testing.assert_array_equal(got.yaw, p.yaw)
    with pytest.raises(ConfigError, match="origin"):
        Relative(base, pattern, [0.0, 1.0])
    with pytest.raises(ConfigError, match="the same n_worlds"):
        Relative(Line(LEADER, [1.0, 0.0, 0.0], n_worlds=2), pattern, LEADER)
