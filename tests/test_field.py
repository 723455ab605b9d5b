"""Tests of the ground-truth downwash field (sim/field.py)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sim.field import DownwashField, pairwise_field

DEFAULT = DownwashField()
KNOBS = {"c4_amplitude": 0.3, "swirl": 0.4, "skew": 0.35}
LEVEL = np.eye(3)
ZERO3 = np.zeros(3)


# --------------------------------------------------------------------------- helpers


def _states(rng: np.random.Generator, n: int, *, tilt: bool = True) -> dict[str, np.ndarray]:
    """n random leader/follower states, followers mostly inside the wake.

    The follower sits at depth -0.2..2 m along the leader's axis and up to ~0.8 m
    to the side of it; velocities up to ~1 m/s.
    """
    if tilt:
        R_a = Rotation.random(n, random_state=rng).as_matrix()
    else:
        yaw = rng.uniform(-np.pi, np.pi, n)
        R_a = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    body = np.column_stack(
        [rng.normal(0.0, 0.3, n), rng.normal(0.0, 0.3, n), -rng.uniform(-0.2, 2.0, n)]
    )
    p_a = rng.normal(0.0, 1.0, (n, 3))
    return {
        "p_a": p_a,
        "v_a": rng.normal(0.0, 0.5, (n, 3)),
        "R_a": R_a,
        "p_b": p_a + np.einsum("nij,nj->ni", R_a, body),
        "v_b": rng.normal(0.0, 0.6, (n, 3)),
    }


def _about_axis(R_a: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations H = R_a Rz(angle) R_a^T about each leader's axis n."""
    Rz = Rotation.from_euler("z", np.asarray(angle)[:, None]).as_matrix()
    return R_a @ Rz @ np.swapaxes(R_a, -1, -2)


def _equivariance_error(field, x: dict[str, np.ndarray], angle: np.ndarray) -> np.ndarray:
    """(n,) |F(H x) - H F(x)| with H rotating dp and v_b about the leader's axis."""
    # H is a BLAS product (orthogonal to a few eps, its last bits the kernel's): the round-off it carries into
    # this error is <= 1.1e-14 m/s^2 in every test here under every OpenBLAS kernel, 1 % of the 1e-12 allowed
    H = _about_axis(x["R_a"], angle)
    dp = x["p_b"] - x["p_a"]
    F = field(x["p_a"], x["v_a"], x["R_a"], x["p_b"], x["v_b"])
    F_rot = field(
        x["p_a"],
        x["v_a"],
        x["R_a"],
        x["p_a"] + np.einsum("nij,nj->ni", H, dp),
        np.einsum("nij,nj->ni", H, x["v_b"]),
    )
    return np.linalg.norm(F_rot - np.einsum("nij,nj->ni", H, F), axis=-1)


def _call(field, x: dict[str, np.ndarray]) -> np.ndarray:
    return field(x["p_a"], x["v_a"], x["R_a"], x["p_b"], x["v_b"])


def _dot(a, b) -> float:
    return sum(ai * bi for ai, bi in zip(a, b))


def _reference(field: DownwashField, p_a, v_a, R_a, p_b, v_b) -> list[float]:
    """The law of sim.field for one pair, in plain Python floats."""
    c = field
    n = [R_a[i][2] for i in range(3)]
    x_a = [R_a[i][0] for i in range(3)]
    y_a = [R_a[i][1] for i in range(3)]
    dp = [p_b[i] - p_a[i] for i in range(3)]
    s = -_dot(dp, n)
    r_vec = [dp[i] + s * n[i] for i in range(3)]
    va_n = _dot(v_a, n)
    va_xy = [v_a[i] - va_n * n[i] for i in range(3)]
    s_pos = max(s, 0.0)
    if c.skew:
        r_vec = [r_vec[i] + c.skew * s_pos * va_xy[i] for i in range(3)]
    r = math.sqrt(_dot(r_vec, r_vec))
    sigma = c.width0 + c.width_slope * s_pos
    A = c.strength / (1.0 + s_pos / c.strength_depth) ** 2
    if s <= c.fade_start:
        w = 0.0
    elif s >= c.fade_end:
        w = 1.0
    else:
        t = (s - c.fade_start) / (c.fade_end - c.fade_start)
        w = 3.0 * t**2 - 2.0 * t**3
    rho = r / sigma
    G = math.exp(-0.5 * rho**2)
    vb_n = _dot(v_b, n)
    vxy = [v_b[i] - vb_n * n[i] for i in range(3)]
    q = math.sqrt(_dot(vxy, vxy))
    v_r = _dot(vxy, r_vec) / r if r > 0.0 else 0.0
    k = 1.0 / (1.0 + _dot(va_xy, va_xy) / c.leader_speed_scale**2)
    down = A * w * G * (1.0 - c.approach_gain * math.tanh(v_r / c.approach_speed) * rho)
    if c.c4_amplitude:
        theta = math.atan2(_dot(r_vec, y_a), _dot(r_vec, x_a))
        taper = rho**4 / (rho**4 + 0.5**4)
        down *= 1.0 + c.c4_amplitude * math.cos(4.0 * theta) * taper
    radial = (
        c.radial_gain
        * A
        * w
        * G
        * (rho**2 - c.radial_offset * (1.0 + c.radial_speed_gain * q / c.radial_speed))
    )
    F = [k * (radial * r_vec[i] / sigma - down * n[i]) for i in range(3)]
    if c.swirl:
        cross = [
            n[1] * r_vec[2] - n[2] * r_vec[1],
            n[2] * r_vec[0] - n[0] * r_vec[2],
            n[0] * r_vec[1] - n[1] * r_vec[0],
        ]
        F = [F[i] + k * c.swirl * A * w * G * rho * cross[i] / sigma for i in range(3)]
    return F


def _on_axis_strength(s: float) -> float:
    return 10.6 / (1.0 + s / 0.57) ** 2


# --------------------------------------------------------------------------- the law


@pytest.mark.parametrize("s, expected", [(0.5, 3.0), (1.0, 1.4), (1.5, 0.8)])
def test_on_axis_magnitude_matches_spec(s: float, expected: float) -> None:
    p_a = np.array([0.3, -0.2, 2.0])
    F = DEFAULT(p_a, ZERO3, LEVEL, p_a - [0.0, 0.0, s], ZERO3)
    # At rest directly below a level leader: pushed straight down (-z) by A(s).
    np.testing.assert_allclose(F, [0.0, 0.0, -_on_axis_strength(s)], rtol=1e-14, atol=1e-15)
    assert F[2] == pytest.approx(-expected, abs=0.05)


def test_on_axis_force_of_a_tilted_leader_points_along_minus_its_axis() -> None:
    R_a = Rotation.from_euler("xyz", [0.4, -0.3, 1.0]).as_matrix()
    n = R_a[:, 2]
    F = DEFAULT(ZERO3, ZERO3, R_a, -1.0 * n, ZERO3)
    np.testing.assert_allclose(F, -_on_axis_strength(1.0) * n, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("knobs", [{}, KNOBS], ids=["default", "knobs_on"])
def test_batched_field_matches_scalar_reference(knobs: dict[str, float]) -> None:
    field = DownwashField(**knobs)
    x = _states(np.random.default_rng(1), 300)
    F = _call(field, x)
    ref = np.array(
        [
            _reference(field, *(x[k][i].tolist() for k in ("p_a", "v_a", "R_a", "p_b", "v_b")))
            for i in range(300)
        ]
    )
    assert np.abs(ref).max() > 1.0  # the samples do reach the wake
    np.testing.assert_allclose(F, ref, rtol=1e-11, atol=1e-12)


def test_field_is_translation_invariant() -> None:
    x = _states(np.random.default_rng(2), 100)
    shift = np.array([3.0, -1.0, 0.5])
    F = _call(DEFAULT, x)
    F_shift = DEFAULT(x["p_a"] + shift, x["v_a"], x["R_a"], x["p_b"] + shift, x["v_b"])
    np.testing.assert_allclose(F_shift, F, atol=1e-12)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_so2_equivariance_about_leader_axis(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = _states(rng, 500)
    err = _equivariance_error(DEFAULT, x, rng.uniform(-np.pi, np.pi, 500))
    assert np.abs(_call(DEFAULT, x)).max() > 1.0
    assert err.max() < 1e-12


def test_equivariance_check_fails_for_a_rotation_not_about_the_axis() -> None:
    # The test above can fail: rotating about world x instead of n breaks it.
    rng = np.random.default_rng(6)
    x = _states(rng, 200, tilt=False)
    H = Rotation.from_euler("x", rng.uniform(0.3, 1.0, (200, 1))).as_matrix()
    F = _call(DEFAULT, x)
    F_rot = DEFAULT(
        x["p_a"],
        x["v_a"],
        x["R_a"],
        x["p_a"] + np.einsum("nij,nj->ni", H, x["p_b"] - x["p_a"]),
        np.einsum("nij,nj->ni", H, x["v_b"]),
    )
    assert np.linalg.norm(F_rot - np.einsum("nij,nj->ni", H, F), axis=-1).max() > 0.1


def test_exactly_zero_at_and_above_the_leader() -> None:
    rng = np.random.default_rng(7)
    n_samples = 400
    field = DownwashField(**KNOBS)
    R_a = Rotation.random(n_samples, random_state=rng).as_matrix()
    s = rng.uniform(-1.5, 0.05, n_samples)
    s[:3] = [0.05, 0.0, -1e-9]  # at the fade start, level with the leader, just above
    body = np.column_stack([rng.normal(0, 0.3, n_samples), rng.normal(0, 0.3, n_samples), -s])
    body[3] = 0.0  # dp = 0
    p_a = rng.normal(0.0, 1.0, (n_samples, 3))
    p_b = p_a + np.einsum("nij,nj->ni", R_a, body)
    v_a, v_b = rng.normal(0.0, 1.0, (2, n_samples, 3))
    with np.errstate(all="raise"):
        for f in (DEFAULT, field):
            F = f(p_a, v_a, R_a, p_b, v_b)
            assert np.all(F == 0.0)
    # ... and just past the fade start the force is on.
    F = DEFAULT(ZERO3, ZERO3, LEVEL, np.array([0.0, 0.0, -0.06]), ZERO3)
    assert F[2] < 0.0


@pytest.mark.parametrize("knobs", [{}, KNOBS], ids=["default", "knobs_on"])
def test_finite_and_warning_free_at_singular_points(knobs: dict[str, float]) -> None:
    field = DownwashField(**knobs)
    R_a = Rotation.from_euler("xyz", [0.2, -0.1, 0.7]).as_matrix()
    n = R_a[:, 2]
    cases = [
        # (dp, v_a, v_b)
        (-0.5 * n, ZERO3, ZERO3),  # r = 0, all at rest
        (-0.5 * n, ZERO3, np.array([0.3, -0.2, 0.5])),  # r = 0, moving follower
        (-0.5 * n, np.array([0.4, 0.1, 0.0]), 0.7 * n),  # r = 0, vxy = 0
        (-0.8 * n + 0.1 * R_a[:, 0], ZERO3, 0.7 * n),  # r > 0, vxy = 0
        (-0.8 * n + 0.1 * R_a[:, 0], ZERO3, ZERO3),  # r > 0, v_b = 0
        (ZERO3, ZERO3, ZERO3),  # dp = 0
        (-0.15 * n, 0.3 * n, ZERO3),  # inside the fade, v_a along the axis
    ]
    with np.errstate(all="raise"):
        for dp, v_a, v_b in cases:
            F = field(ZERO3, v_a, R_a, dp, v_b)
            assert F.shape == (3,)
            assert np.all(np.isfinite(F))
        batched = field(
            ZERO3,
            np.array([c[1] for c in cases]),
            R_a,
            np.array([c[0] for c in cases]),
            np.array([c[2] for c in cases]),
        )
    assert np.all(np.isfinite(batched))


def test_no_divide_overflow_or_invalid_anywhere() -> None:
    # Far outside the wake G may underflow to 0 (NumPy ignores underflow by default);
    # nothing else may happen, including for huge offsets and speeds.
    rng = np.random.default_rng(8)
    n_samples = 1000
    scale = 10.0 ** rng.uniform(-6, 3, (n_samples, 1))
    x = {
        "p_a": rng.normal(0, 1, (n_samples, 3)),
        "v_a": rng.normal(0, 1, (n_samples, 3)) * scale,
        "R_a": Rotation.random(n_samples, random_state=rng).as_matrix(),
        "v_b": rng.normal(0, 1, (n_samples, 3)) * scale[::-1],
    }
    x["p_b"] = x["p_a"] + rng.normal(0, 1, (n_samples, 3)) * scale
    with np.errstate(divide="raise", over="raise", invalid="raise", under="ignore"):
        for f in (DEFAULT, DownwashField(**KNOBS)):
            assert np.all(np.isfinite(_call(f, x)))


# --------------------------------------------------------------------------- features


def _level_state(dp, v_b, v_a=ZERO3):
    return ZERO3, np.asarray(v_a, float), LEVEL, np.asarray(dp, float), np.asarray(v_b, float)


def test_leader_lateral_motion_weakens_the_wake_by_k() -> None:
    dp = [0.12, -0.05, -0.9]
    v_b = [0.2, 0.1, -0.1]
    F0 = DEFAULT(*_level_state(dp, v_b))
    norms = []
    for speed in (0.0, 0.5, 1.0, 2.0, 4.0):
        v_a = speed * np.array([0.6, 0.8, 0.0]) + [0.0, 0.0, 0.7]  # a climb does not count
        F = DEFAULT(*_level_state(dp, v_b, v_a))
        k = 1.0 / (1.0 + (speed / 2.0) ** 2)
        np.testing.assert_allclose(F, k * F0, rtol=1e-13, atol=1e-15)
        norms.append(np.linalg.norm(F))
    assert np.all(np.diff(norms) < 0.0)
    assert norms[3] == pytest.approx(0.5 * norms[0])


def test_approach_pushes_harder_and_retreat_pulls_up() -> None:
    s = 1.0
    sigma = 0.10 + 0.12 * s
    dp = [sigma, 0.0, -s]  # rho = 1 on the +x side of the axis
    rest = DEFAULT(*_level_state(dp, ZERO3))[2]
    approach = DEFAULT(*_level_state(dp, [-0.5, 0.0, 0.0]))[2]  # v_r < 0
    retreat = DEFAULT(*_level_state(dp, [0.5, 0.0, 0.0]))[2]  # v_r > 0
    assert approach < rest < 0.0  # a stronger downward push
    assert retreat > 0.0  # 1 - 1.5 tanh(1) < 0: pulled up
    # On the axis (rho = 0) the direction of travel does not matter.
    on_axis = [DEFAULT(*_level_state([0, 0, -s], [v, 0, 0]))[2] for v in (-0.5, 0.0, 0.5)]
    np.testing.assert_allclose(on_axis, on_axis[0], rtol=1e-14)


def test_radial_force_inward_under_the_leader_and_outward_beyond() -> None:
    s = 0.8
    sigma = 0.10 + 0.12 * s
    for rho, sign in ((0.5, -1.0), (0.9, -1.0), (1.2, 1.0), (2.0, 1.0)):
        for azimuth in (0.0, 2.0, 4.0):
            u = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
            F = DEFAULT(*_level_state(rho * sigma * u + [0, 0, -s], ZERO3))
            lateral = F[:2] @ u[:2]
            assert sign * lateral > 0.0, (rho, azimuth)
            # radial: no tangential component
            assert abs(F[0] * u[1] - F[1] * u[0]) < 1e-15


def test_inward_region_grows_with_follower_speed() -> None:
    s = 0.8
    sigma = 0.10 + 0.12 * s
    dp = [1.2 * sigma, 0.0, -s]  # rho^2 = 1.44: outward at rest
    at_rest = DEFAULT(*_level_state(dp, ZERO3))
    tangential = DEFAULT(*_level_state(dp, [0.0, 0.5, 0.0]))  # q = 0.5, v_r = 0
    assert at_rest[0] > 0.0
    assert tangential[0] < 0.0  # 1.44 < 1 + 0.5 * 0.5 / 0.5 = 1.5: now inward
    assert tangential[2] == pytest.approx(at_rest[2], rel=1e-14)  # v_r = 0: same push


def test_per_world_constants_broadcast_over_the_batch() -> None:
    rng = np.random.default_rng(9)
    W = 5
    x = _states(rng, W)
    strength = np.array([5.0, 10.6, 12.0, 20.0, 0.0])
    width0 = np.array([0.08, 0.10, 0.12, 0.09, 0.11])
    skew = np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    F = _call(DownwashField(strength=strength), x)
    np.testing.assert_allclose(F, (strength / 10.6)[:, None] * _call(DEFAULT, x), atol=1e-13)
    F = _call(DownwashField(strength=strength, width0=width0, skew=skew), x)
    for w in range(W):
        one = {k: v[w] for k, v in x.items()}
        scalar_field = DownwashField(
            strength=float(strength[w]), width0=float(width0[w]), skew=float(skew[w])
        )
        np.testing.assert_allclose(F[w], _call(scalar_field, one), rtol=1e-13, atol=1e-14)


def test_field_pickles() -> None:
    field = DownwashField(strength=np.array([9.0, 11.0]), swirl=0.2)
    x = _states(np.random.default_rng(10), 2)
    clone = pickle.loads(pickle.dumps(field))
    np.testing.assert_array_equal(_call(clone, x), _call(field, x))


# --------------------------------------------------------------------------- knobs


def test_knobs_off_by_default_and_zero_is_identical_to_default() -> None:
    assert DEFAULT.c4_amplitude == DEFAULT.swirl == DEFAULT.skew == 0.0
    x = _states(np.random.default_rng(11), 300)
    F = _call(DEFAULT, x)
    explicit = DownwashField(c4_amplitude=0.0, swirl=0.0, skew=0.0)
    np.testing.assert_array_equal(_call(explicit, x), F)
    # Zero as arrays takes the knobs' code paths, which must then change nothing
    # (up to rounding: the skew path computes |v_a,xy|^2 another way).
    as_arrays = DownwashField(c4_amplitude=np.zeros(300), swirl=np.zeros(300), skew=np.zeros(300))
    np.testing.assert_allclose(_call(as_arrays, x), F, rtol=1e-12, atol=1e-14)


def test_c4_breaks_so2_equivariance_keeps_c4_and_the_axis() -> None:
    rng = np.random.default_rng(12)
    x = _states(rng, 400)
    angle = rng.uniform(0.2, 1.3, 400)  # never a quarter turn
    field = DownwashField(c4_amplitude=0.3)
    assert _equivariance_error(DEFAULT, x, angle).max() < 1e-12
    assert _equivariance_error(field, x, angle).max() > 0.05
    quarter = rng.integers(-2, 3, 400) * (np.pi / 2)
    assert _equivariance_error(field, x, quarter).max() < 1e-12
    # On the axis the modulation vanishes.
    R_a = Rotation.from_euler("xyz", [0.3, 0.1, 0.9]).as_matrix()
    dp = -0.7 * R_a[:, 2]
    np.testing.assert_allclose(
        field(ZERO3, ZERO3, R_a, dp, ZERO3), DEFAULT(ZERO3, ZERO3, R_a, dp, ZERO3), rtol=1e-14
    )


def test_c4_follows_the_leader_yaw() -> None:
    # The lobes are fixed to the leader's body: yawing leader and follower together
    # leaves the vertical force unchanged; yawing only the leader by 45 deg flips it.
    field = DownwashField(c4_amplitude=0.5)
    dp = np.array([0.15, 0.0, -0.6])
    Rz = Rotation.from_euler("z", 0.7).as_matrix()
    base = field(ZERO3, ZERO3, LEVEL, dp, ZERO3)
    together = field(ZERO3, ZERO3, Rz, Rz @ dp, ZERO3)
    np.testing.assert_allclose(together, Rz @ base, atol=1e-14)
    default = DEFAULT(ZERO3, ZERO3, LEVEL, dp, ZERO3)
    yawed = field(ZERO3, ZERO3, Rotation.from_euler("z", np.pi / 4).as_matrix(), dp, ZERO3)
    assert base[2] < default[2] < yawed[2] < 0.0  # theta = 0: cos 4 theta = 1; 45 deg: -1


def test_swirl_is_tangential_and_keeps_equivariance() -> None:
    rng = np.random.default_rng(13)
    x = _states(rng, 400)
    angle = rng.uniform(-np.pi, np.pi, 400)
    field = DownwashField(swirl=0.4)
    assert _equivariance_error(field, x, angle).max() < 1e-12
    n = x["R_a"][:, :, 2]
    dp = x["p_b"] - x["p_a"]
    r_vec = dp - np.sum(dp * n, axis=-1, keepdims=True) * n
    tangent = np.cross(n, r_vec)
    tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
    assert np.abs(np.sum(_call(DEFAULT, x) * tangent, axis=-1)).max() < 1e-12
    swirl_part = np.sum(_call(field, x) * tangent, axis=-1)
    assert np.abs(swirl_part).max() > 0.1
    # Only the tangential direction changed.
    diff = _call(field, x) - _call(DEFAULT, x)
    np.testing.assert_allclose(diff, swirl_part[:, None] * tangent, atol=1e-12)


def test_skew_breaks_equivariance_only_when_the_leader_moves_sideways() -> None:
    rng = np.random.default_rng(14)
    x = _states(rng, 400)
    angle = rng.uniform(0.2, 3.0, 400)
    field = DownwashField(skew=0.35)
    assert _equivariance_error(field, x, angle).max() > 0.05
    n = x["R_a"][:, :, 2]
    for v_a in (np.zeros((400, 3)), rng.normal(0, 1, (400, 1)) * n):  # at rest, along n
        still = dict(x, v_a=v_a)
        assert _equivariance_error(field, still, angle).max() < 1e-12
        np.testing.assert_allclose(_call(field, still), _call(DEFAULT, still), atol=1e-13)


def test_skew_trails_the_wake_behind_the_moving_leader() -> None:
    field = DownwashField(skew=0.3)
    v_a = np.array([1.0, 0.0, 0.0])
    s = 1.0
    # The wake axis at depth s sits at -skew s v_a: straight down there, no lateral force.
    F = field(*_level_state([-0.3 * s, 0.0, -s], ZERO3, v_a))
    k = 1.0 / (1.0 + (1.0 / 2.0) ** 2)
    np.testing.assert_allclose(F, [0.0, 0.0, -k * _on_axis_strength(s)], atol=1e-14)
    # Under the leader itself the follower is now off the wake axis: weaker push.
    assert field(*_level_state([0.0, 0.0, -s], ZERO3, v_a))[2] > F[2]


# --------------------------------------------------------------------------- pairwise


def _fleet(rng: np.random.Generator, W: int, V: int):
    """W worlds of V vehicles stacked ~0.6 m apart in height, near one column."""
    pos = np.zeros((W, V, 3))
    pos[..., 2] = 2.5 - 0.6 * np.arange(V)
    pos[..., :2] = rng.normal(0.0, 0.1, (W, V, 2))
    vel = rng.normal(0.0, 0.4, (W, V, 3))
    rot = Rotation.from_euler("xyz", rng.normal(0, 0.15, (W * V, 3))).as_matrix()
    return pos, vel, rot.reshape(W, V, 3, 3)


def test_pairwise_two_vehicles_is_the_two_directed_pairs() -> None:
    pos, vel, rot = _fleet(np.random.default_rng(15), 6, 2)
    F = pairwise_field(DEFAULT, pos, vel, rot)
    assert F.shape == (6, 2, 3)
    on_lower = DEFAULT(pos[:, 0], vel[:, 0], rot[:, 0], pos[:, 1], vel[:, 1])
    on_upper = DEFAULT(pos[:, 1], vel[:, 1], rot[:, 1], pos[:, 0], vel[:, 0])
    np.testing.assert_allclose(F[:, 1], on_lower, rtol=0, atol=1e-13)  # compiled path vs broadcast law
    np.testing.assert_allclose(F[:, 0], on_upper, rtol=0, atol=1e-13)
    assert np.all(F[:, 0] == 0.0)  # nothing acts on the upper one
    F = pairwise_field(DEFAULT, pos, np.zeros_like(vel), rot)
    assert np.all(F[:, 1, 2] < -0.1)  # at rest the lower vehicle is pushed down


@pytest.mark.parametrize("field", [DEFAULT, DownwashField(**KNOBS)], ids=["default", "knobs"])
def test_pairwise_three_vehicles_equals_the_double_loop(field: DownwashField) -> None:
    pos, vel, rot = _fleet(np.random.default_rng(16), 4, 3)
    F = pairwise_field(field, pos, vel, rot)
    expected = np.zeros_like(F)
    for w in range(4):
        for j in range(3):
            for i in range(3):
                if i != j:
                    expected[w, j] += field(pos[w, i], vel[w, i], rot[w, i], pos[w, j], vel[w, j])
    assert np.abs(expected[:, 2]).max() > 0.5  # the bottom vehicle feels both above it
    np.testing.assert_allclose(F, expected, rtol=1e-13, atol=1e-14)


def test_pairwise_with_a_single_unbatched_fleet() -> None:
    pos, vel, rot = _fleet(np.random.default_rng(17), 1, 3)
    np.testing.assert_allclose(
        pairwise_field(DEFAULT, pos[0], vel[0], rot[0]), pairwise_field(DEFAULT, pos, vel, rot)[0], rtol=0, atol=1e-13
    )


def test_pairwise_accepts_any_field_with_the_signature() -> None:
    class InverseSquare:
        """A pluggable field that is not finite at dp = 0 (the ignored diagonal)."""

        def __call__(self, p_a, v_a, R_a, p_b, v_b):
            dp = p_b - p_a
            with np.errstate(divide="ignore", invalid="ignore"):
                return dp / np.linalg.norm(dp, axis=-1, keepdims=True) ** 3

    pos, vel, rot = _fleet(np.random.default_rng(18), 3, 3)
    F = pairwise_field(InverseSquare(), pos, vel, rot)
    expected = np.zeros_like(F)
    for i in range(3):
        for j in range(3):
            if i != j:
                d = pos[:, j] - pos[:, i]
                expected[:, j] += d / np.linalg.norm(d, axis=-1, keepdims=True) ** 3
    np.testing.assert_allclose(F, expected, rtol=1e-13)
    # A plain function works too.
    F = pairwise_field(lambda p_a, v_a, R_a, p_b, v_b: v_a + 0.0 * p_b, pos, vel, rot)
    np.testing.assert_allclose(F, vel.sum(axis=1, keepdims=True) - vel, rtol=1e-13)


def test_pairwise_per_world_constants() -> None:
    pos, vel, rot = _fleet(np.random.default_rng(19), 3, 2)
    strength = np.array([5.0, 10.6, 15.0])
    F = pairwise_field(DownwashField(strength=strength[:, None, None]), pos, vel, rot)
    np.testing.assert_allclose(
        F, (strength / 10.6)[:, None, None] * pairwise_field(DEFAULT, pos, vel, rot), atol=1e-13
    )


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "pos_shape, vel_shape, rot_shape, match",
    [
        ((2, 4), (2, 4), (2, 3, 3), r"pos: expected \(\.\.\., V, 3\) but found \(2, 4\)"),
        ((3,), (3,), (3, 3), r"pos: expected \(\.\.\., V, 3\) but found \(3,\)"),
        ((5, 2, 3), (5, 3, 3), (5, 2, 3, 3), r"vel: expected \(\.\.\., 2, 3\)"),
        ((5, 2, 3), (5, 2, 3), (5, 2, 3), r"rot: expected \(\.\.\., 2, 3, 3\)"),
        ((5, 2, 3), (4, 2, 3), (5, 2, 3, 3), r"batch shapes do not broadcast"),
    ],
)
def test_pairwise_rejects_bad_shapes(pos_shape, vel_shape, rot_shape, match) -> None:
    with pytest.raises(ValueError, match=match):
        pairwise_field(DEFAULT, np.zeros(pos_shape), np.zeros(vel_shape), np.zeros(rot_shape))


def test_field_validate_names_the_bad_argument() -> None:
    good = dict(p_a=ZERO3, v_a=ZERO3, R_a=LEVEL, p_b=ZERO3, v_b=ZERO3)
    DEFAULT(**good, validate=True)
    with pytest.raises(ValueError, match=r"p_b: expected \(\.\.\., 3\) but found \(2,\)"):
        DEFAULT(**dict(good, p_b=np.zeros(2)), validate=True)
    with pytest.raises(ValueError, match=r"R_a: expected \(\.\.\., 3, 3\) but found \(3,\)"):
        DEFAULT(**dict(good, R_a=np.zeros(3)), validate=True)
    with pytest.raises(ValueError, match=r"batch shapes do not broadcast: .*v_a \(4,\)"):
        DEFAULT(**dict(good, p_a=np.zeros((5, 3)), v_a=np.zeros((4, 3))), validate=True)


@pytest.mark.parametrize(
    "knobs", [{}, {"c4_amplitude": 0.3}, {"swirl": 0.5}, {"skew": 0.4}, {"c4_amplitude": 0.3, "swirl": 0.5, "skew": 0.4}]
)
def test_compiled_pairwise_matches_broadcast_evaluation(knobs):
    """DownwashField.pairwise (compiled, the loop's hot path) == the NumPy broadcast law."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    W, V = 300, 3
    pos = rng.normal(size=(W, V, 3)) * [0.4, 0.4, 0.8]
    vel = rng.normal(size=(W, V, 3))
    rot = Rotation.random(W * V, random_state=6).as_matrix().reshape(W, V, 3, 3)
    field = DownwashField(**knobs)
    fast = field.pairwise(pos, vel, rot)
    slow = pairwise_field(lambda *a: field(*a), pos, vel, rot)  # a plain callable: no fast path
    assert np.abs(slow).max() > 1.0  # the samples do reach the wake
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(pairwise_field(field, pos, vel, rot), fast)
    # per-world constants decline the compiled path and still work through broadcasting
    per_world = DownwashField(strength=np.full((W, 1, 1), 10.6), **knobs)
    assert per_world.pairwise(pos, vel, rot) is None
    np.testing.assert_allclose(pairwise_field(per_world, pos, vel, rot), slow, atol=1e-12)
