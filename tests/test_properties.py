"""Property-based tests (hypothesis) of the field, the features, the labels and the checkpoint loader.

Each property is checked on inputs that hypothesis draws, in wide physical ranges
(positions within +/-50 m, velocities within +/-20 m/s, any rotation) and with the
edge cases drawn on purpose (follower exactly on the wake axis, zero lateral
velocity, coinciding vehicles). Every test runs with `database=None` (no example
database; hypothesis still caches constants under its self-ignored `.hypothesis/`).
"""

from __future__ import annotations

import builtins
import io
import json
import math
import os
import struct
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from downwash_core.errors import CheckpointError
from downwash_core.geometry import quat_to_mat
from downwash_core.status import Status
from downwash.checkpoint import load_checkpoint, save_checkpoint
from downwash.features import (
    FEATURE_SETS,
    HISTORY_LAGS,
    MEMORY_FEATURE_SETS,
    N_BASIS,
    equivariant_basis,
    invariant_features,
    model_inputs,
)
from test_checkpoint import trained_like  # tests/ is on sys.path under pytest
from downwash.labels import DEFAULT_POLYORDER, DEFAULT_WINDOW, FAIL_MARGIN_S, SAMPLE_SCHEMA, labels_from_log
from downwash.models import PAIRWISE_KINDS
from sim.field import DownwashField, pairwise_field
from sim.logs import ARRAY_SPECS, FlightLog
from conftest import restamp


def _settings(n: int):
    """n examples, no deadline (numba and torch warm up on the first call), no example database."""
    return settings(
        max_examples=n, deadline=None, database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


# ------------------------------------------------------------------------ strategies

POS_BOUND = 50.0  # m
VEL_BOUND = 20.0  # m/s
# the field's knobs at documented values: |c4| < 1 (class docstring), swirl and skew as in tests/test_field.py
KNOB_VALUES = {"c4_amplitude": 0.3, "swirl": 0.4, "skew": 0.35}
# exact rotations (identity, quarter and half turns): with these, "on the axis" means r = 0 exactly
SPECIAL_QUATS = [
    (1.0, 0.0, 0.0, 0.0),
    (0.0, 1.0, 0.0, 0.0),
    (0.0, 0.0, 0.0, 1.0),
    (math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)),
    (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0),
]


def _floats(bound: float):
    return st.floats(-bound, bound, allow_nan=False, allow_infinity=False)


def _vec(shape, bound: float):
    return hnp.arrays(np.float64, tuple(shape) + (3,), elements=_floats(bound))


@st.composite
def rotations(draw, shape=()):
    """Rotation matrices (*shape, 3, 3) from unit quaternions (random or exact special ones)."""
    def one():
        q = draw(st.one_of(st.sampled_from(SPECIAL_QUATS), st.tuples(*[_floats(1.0)] * 4)))
        q = np.array(q, dtype=np.float64)
        return q if np.linalg.norm(q) > 1e-3 else np.array([1.0, 0.0, 0.0, 0.0])

    quats = np.array([one() for _ in range(int(np.prod(shape, dtype=int)))]).reshape(tuple(shape) + (4,))
    return quat_to_mat(quats)


@st.composite
def pair_states(draw, shape=None, mode=None):
    """(p_a, v_a, R_a, p_b, v_b) of one leader-follower pair, batched over `shape`.

    mode of the follower's position: "free" (anywhere within +/-50 m), "wake" (within
    ~1 m of the wake axis, -0.5..5 m below the leader), "axis" (on the leader's axis:
    r = 0, exactly for the special rotations), "same" (dp = 0). The follower's velocity is free, axial (zero lateral
    velocity) or zero; so is the leader's.
    """
    if shape is None:
        shape = draw(hnp.array_shapes(min_dims=0, max_dims=2, max_side=3))
    shape = tuple(shape)
    mode = mode or draw(st.sampled_from(["free", "wake", "axis", "same"]))
    R_a = draw(rotations(shape))
    n = R_a[..., :, 2]
    p_a = draw(_vec(shape, POS_BOUND))
    if mode == "free":
        p_b = draw(_vec(shape, POS_BOUND))
    elif mode == "wake":
        body = np.stack(
            [draw(hnp.arrays(np.float64, shape, elements=_floats(1.0))),
             draw(hnp.arrays(np.float64, shape, elements=_floats(1.0))),
             -draw(hnp.arrays(np.float64, shape, elements=st.floats(-0.5, 5.0)))], axis=-1)
        p_b = p_a + np.einsum("...ij,...j->...i", R_a, body)
    elif mode == "axis":
        s = draw(hnp.arrays(np.float64, shape, elements=_floats(POS_BOUND)))
        p_b = p_a - s[..., None] * n
    else:
        p_b = p_a.copy()

    def velocity():
        kind = draw(st.sampled_from(["free", "axial", "zero"]))
        if kind == "free":
            return draw(_vec(shape, VEL_BOUND))
        if kind == "axial":
            return draw(hnp.arrays(np.float64, shape, elements=_floats(VEL_BOUND)))[..., None] * n
        return np.zeros(shape + (3,))

    return p_a, velocity(), R_a, p_b, velocity()


def _about_axis(R_a: np.ndarray, angle: float) -> np.ndarray:
    """H = R_a Rz(angle) R_a^T: the rotation by `angle` about the leader's axis n = R_a[:, 2]."""
    # BLAS products: H is orthogonal to ~3 eps with the kernel's last bits (exactly Rz for R_a = I, where every
    # sum has one nonzero term). The equivariance tests allow 1e-9 m/s^2; follower positions up to 50 m are
    # re-rounded (~7e-15 m) and the field's steepest slope is ~100 s^-2: ~1e-12, H's round-off less
    c, s = math.cos(angle), math.sin(angle)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R_a @ Rz @ np.swapaxes(R_a, -1, -2)


def _rotate(H: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", H, x)


def _equivariance_error(field, p_a, v_a, R_a, p_b, v_b, angle: float) -> np.ndarray:
    """|F(H dp, H v_b) - H F(dp, v_b)| (...,) with H the rotation by `angle` about the leader's axis."""
    H = _about_axis(R_a, angle)
    F = field(p_a, v_a, R_a, p_b, v_b)
    F_rot = field(p_a, v_a, R_a, p_a + _rotate(H, p_b - p_a), _rotate(H, v_b))
    return np.linalg.norm(F_rot - _rotate(H, F), axis=-1)


ANGLES = st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False)
FIELDS = {"default": DownwashField(), **{k: DownwashField(**{k: v}) for k, v in KNOB_VALUES.items()}}


# ------------------------------------------------------------------ the ground-truth field


@pytest.mark.parametrize("name", sorted(FIELDS))
@_settings(50)
@given(x=pair_states(), c4=st.floats(-0.99, 0.99), swirl=_floats(2.0), skew=st.floats(0.0, 2.0))
def test_field_is_finite_with_shape_and_warning_free(name, x, c4, swirl, skew):
    """Finite (..., 3) float64 output for any finite state, with the knob at its documented
    value and at a drawn one, and no divide/overflow/invalid floating-point event."""
    knob = {"c4_amplitude": c4, "swirl": swirl, "skew": skew}.get(name)
    fields = [FIELDS[name]] + ([DownwashField(**{name: knob})] if knob is not None else [])
    for field in fields:
        with np.errstate(divide="raise", over="raise", invalid="raise", under="ignore"):
            F = field(*x)
        assert F.shape == x[0].shape and F.dtype == np.float64
        assert np.isfinite(F).all(), F


def test_field_edge_cases_are_finite_and_exact():
    """The singular points, exactly: r = 0 below a level leader (at rest, and moving axially:
    zero lateral velocity) gives (0, 0, -A(s)) with no lateral part; dp = 0 gives exactly 0."""
    field = DownwashField()
    p_a, R = np.array([1.0, -2.0, 2.5]), np.eye(3)
    for v_b in ([0.0, 0.0, 0.0], [0.0, 0.0, -3.0]):  # at rest, and moving axially (zero lateral speed)
        F = field(p_a, np.zeros(3), R, p_a - [0.0, 0.0, 1.0], np.array(v_b))
        assert F[0] == 0.0 and F[1] == 0.0  # on the axis: no radial force
        assert F[2] == pytest.approx(-field.strength / (1 + 1 / field.strength_depth) ** 2, rel=1e-12)  # -A(1 m)
    assert np.array_equal(field(p_a, np.ones(3), R, p_a, np.ones(3)), np.zeros(3))  # dp = 0


@pytest.mark.parametrize("name", ["default", "swirl"])
@_settings(60)
@given(x=pair_states(mode="wake"), angle=ANGLES)
def test_field_so2_equivariant_about_the_leader_axis(name, x, angle):
    """Rotating dp and v_b about n rotates the output by the same rotation (default and swirl)."""
    err = _equivariance_error(FIELDS[name], *x, angle)
    assert np.all(err <= 1e-9), err.max()


@_settings(40)
@given(x=pair_states(mode="wake"), turns=st.integers(-4, 4))
def test_field_with_c4_keeps_quarter_turn_equivariance(x, turns):
    """The documented C4 symmetry of the c4 knob: quarter turns about n commute with it."""
    err = _equivariance_error(FIELDS["c4_amplitude"], *x, turns * math.pi / 2)
    assert np.all(err <= 1e-9), err.max()


@_settings(40)
@given(x=pair_states(mode="wake"), angle=ANGLES, w=_floats(VEL_BOUND))
def test_field_with_skew_is_equivariant_when_the_leader_moves_only_axially(x, angle, w):
    p_a, _, R_a, p_b, v_b = x
    v_a = w * R_a[..., :, 2]  # v_a,xy = 0: skew does nothing, so equivariance holds
    err = _equivariance_error(FIELDS["skew"], p_a, v_a, R_a, p_b, v_b, angle)
    assert np.all(err <= 1e-9), err.max()


def test_field_equivariance_check_fails_for_c4_and_skew():
    """The equivariance check catches a knob that breaks SO(2) symmetry, on inputs chosen to
    show it: a level leader, the follower 0.5 m below and one wake width (sigma = 0.16 m)
    out along the leader's body x axis, turned by 45 degrees (cos 4 theta from +1 to -1)."""
    p_a, R = np.zeros(3), np.eye(3)
    p_b = np.array([0.16, 0.0, -0.5])
    angle = math.pi / 4
    ok = _equivariance_error(FIELDS["default"], p_a, np.zeros(3), R, p_b, np.zeros(3), angle)
    assert ok < 1e-12  # the same inputs pass for the equivariant default field (R = I: H = Rz exactly, any kernel)
    broken = _equivariance_error(FIELDS["c4_amplitude"], p_a, np.zeros(3), R, p_b, np.zeros(3), angle)
    # down = A w G (1 + c4 taper cos 4 theta) with w = 1, G = exp(-1/2), taper = 1 / 1.0625 and
    # cos 4 theta = +1 before and -1 after the turn; the radial force is the same, so the error
    # is 2 c4 A G / 1.0625 = 1.03 m/s^2
    f = FIELDS["c4_amplitude"]
    A = f.strength / (1 + 0.5 / f.strength_depth) ** 2
    assert broken == pytest.approx(2 * 0.3 * A * math.exp(-0.5) / 1.0625, rel=1e-9)
    skewed = _equivariance_error(FIELDS["skew"], p_a, np.array([1.0, 0.0, 0.0]), R, p_b, np.zeros(3), angle)
    assert skewed > 0.1


@pytest.mark.parametrize("name", sorted(FIELDS))
@_settings(40)
@given(x=pair_states(), shift=_vec((), POS_BOUND))
def test_field_is_translation_invariant(name, x, shift):
    p_a, v_a, R_a, p_b, v_b = x
    F = FIELDS[name](p_a, v_a, R_a, p_b, v_b)
    F_shift = FIELDS[name](p_a + shift, v_a, R_a, p_b + shift, v_b)
    # both positions are rounded once more after the shift (|p| <= 100 m: ~1e-14 m), and the
    # field's steepest slope is ~A / sigma ~ 100 (m/s^2)/m
    np.testing.assert_allclose(F_shift, F, rtol=0, atol=1e-9)


@st.composite
def fleets(draw):
    """(pos, vel, rot) of W = 1..4 worlds with V = 2..5 vehicles, many in each other's wake."""
    W, V = draw(st.integers(1, 4)), draw(st.integers(2, 5))
    centre = draw(_vec((W, 1), POS_BOUND))
    if draw(st.booleans()):  # a column of vehicles within ~1 m of each other's axes
        offsets = np.stack(
            [draw(hnp.arrays(np.float64, (W, V), elements=_floats(0.6))),
             draw(hnp.arrays(np.float64, (W, V), elements=_floats(0.6))),
             draw(hnp.arrays(np.float64, (W, V), elements=st.floats(-4.0, 0.0)))], axis=-1)
    else:
        offsets = draw(_vec((W, V), POS_BOUND))
    vel = draw(_vec((W, V), VEL_BOUND)) * draw(st.sampled_from([0.0, 0.05, 1.0]))
    return centre + offsets, vel, draw(rotations((W, V)))


@pytest.mark.parametrize("name", sorted(FIELDS))
@_settings(40)
@given(fleet=fleets())
def test_compiled_pairwise_equals_the_broadcast_path(name, fleet):
    field = FIELDS[name]
    pos, vel, rot = fleet
    fast = field.pairwise(pos, vel, rot)
    assert fast is not None  # scalar constants: the compiled kernel is used
    slow = pairwise_field(lambda *args: field(*args), pos, vel, rot)  # no `pairwise`: broadcast path
    assert fast.shape == slow.shape == pos.shape
    np.testing.assert_allclose(fast, slow, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(pairwise_field(field, pos, vel, rot), fast)  # the dispatch takes it


# ------------------------------------------------------------------------- features


@st.composite
def feature_inputs(draw):
    """(dp, v_a, v_b, R_a) with the singular cases drawn on purpose: dp = 0, dp on the axis
    (r = 0, exactly for the special rotations), v_b = 0 or axial (zero lateral speed)."""
    p_a, v_a, R_a, p_b, v_b = draw(pair_states())
    return p_b - p_a, v_a, v_b, R_a


@pytest.mark.parametrize("feature_set", sorted(FEATURE_SETS))
@_settings(50)
@given(x=feature_inputs())
def test_model_inputs_finite_and_consistent_numpy(feature_set, x):
    dp, v_a, v_b, R_a = x
    hist = np.stack([v_a * lag for lag in HISTORY_LAGS], -2)  # a neighbour that moved at v_a
    feats, basis = model_inputs(feature_set, dp, v_a, v_b, R_a, hist)
    k = len(FEATURE_SETS[feature_set])
    assert feats.shape == dp.shape[:-1] + (k,) and np.isfinite(feats).all()
    if feature_set in MEMORY_FEATURE_SETS:  # the memoryless set's columns, then each lag's displacement
        base = feature_set.removesuffix("_memory")
        np.testing.assert_array_equal(feats[..., :len(FEATURE_SETS[base])], model_inputs(base, dp, v_a, v_b, R_a)[0])
        moved = hist if basis is None else np.einsum("...hj,...kj->...hk", hist, basis)
        np.testing.assert_allclose(feats[..., len(FEATURE_SETS[base]):], moved.reshape(*dp.shape[:-1], -1),
                                   rtol=1e-12, atol=1e-15)
        with pytest.raises(ValueError, match="history"):
            model_inputs(feature_set, dp, v_a, v_b, R_a)
        feats, feature_set = feats[..., :len(FEATURE_SETS[base])], base
    if feature_set == "raw":
        assert basis is None
        np.testing.assert_array_equal(feats, np.concatenate([dp, v_b], -1))
        return
    assert basis.shape == dp.shape[:-1] + (N_BASIS[feature_set], 3) and np.isfinite(basis).all()
    np.testing.assert_array_equal(feats, invariant_features(dp, v_a, v_b, R_a, feature_set))
    np.testing.assert_array_equal(basis, equivariant_basis(dp, R_a, feature_set))
    # cosines and sines lie in [-1, 1], lateral norms are non-negative, |r_hat| (and |t_hat|) at most 1
    names = FEATURE_SETS[feature_set]
    for j, name in enumerate(names):
        if name.startswith(("cos_", "sin_")):
            assert np.all(np.abs(feats[..., j]) <= 1.0), name
        if name.endswith("_lateral"):
            assert np.all(feats[..., j] >= 0.0), name
    assert np.all(np.linalg.norm(basis[..., 0, :], axis=-1) <= 1.0 + 1e-12)
    assert np.all(np.linalg.norm(basis[..., 2:, :], axis=-1) <= 1.0 + 1e-12)


@pytest.mark.parametrize("feature_set", ["5", "6"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@_settings(25)
@given(x=feature_inputs(), weights=hnp.arrays(np.float64, 12, elements=_floats(1.0)))
def test_features_and_gradients_finite_under_torch(feature_set, dtype, x, weights):
    """Values and gradients (w.r.t. dp, v_a, v_b and R_a) are finite, also at r = 0 and v = 0."""
    tensors = [torch.tensor(a, dtype=dtype, requires_grad=True) for a in x]
    feats, basis = model_inputs(feature_set, *tensors)
    k = feats.shape[-1]
    w = torch.tensor(weights, dtype=dtype)
    loss = (feats * w[:k]).sum() + (basis.reshape(basis.shape[:-2] + (6,)) * w[6:]).sum()
    loss.backward()
    assert torch.isfinite(feats).all() and torch.isfinite(basis).all()
    for name, t in zip(("dp", "v_a", "v_b", "R_a"), tensors):
        if name == "v_a" and feature_set == "5":
            assert t.grad is None  # set "5" does not use the leader's velocity
            continue
        assert t.grad is not None and torch.isfinite(t.grad).all(), name


def test_torch_gradients_finite_exactly_at_r_zero_and_v_zero():
    """The exact singular points (not just near them): r = 0, v_b = 0 and dp = 0."""
    for dp in ([0.0, 0.0, -1.0], [0.0, 0.0, 0.0]):
        tensors = [torch.tensor(a, dtype=torch.float64, requires_grad=True)
                   for a in (dp, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], np.eye(3))]
        feats, basis = model_inputs("6", *tensors)
        (feats.sum() + basis.sum()).backward()
        assert torch.isfinite(feats).all()
        for t in tensors:
            assert torch.isfinite(t.grad).all()


@pytest.mark.parametrize("feature_set", ["5", "6"])
@_settings(60)
@given(x=feature_inputs(), angle=ANGLES)
def test_features_invariant_and_basis_equivariant_about_the_leader_axis(feature_set, x, angle):
    dp, v_a, v_b, R_a = x
    H = _about_axis(R_a, angle)
    feats = invariant_features(dp, v_a, v_b, R_a, feature_set)
    feats_rot = invariant_features(_rotate(H, dp), v_a, _rotate(H, v_b), R_a, feature_set)
    np.testing.assert_allclose(feats_rot, feats, rtol=1e-9, atol=1e-9)
    basis = equivariant_basis(dp, R_a)
    basis_rot = equivariant_basis(_rotate(H, dp), R_a)
    np.testing.assert_allclose(basis_rot, np.einsum("...ij,...kj->...ki", H, basis), rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------- labels


def _blank_arrays(T: int, V: int) -> dict[str, np.ndarray]:
    """Zero arrays of the documented shapes for every name in ARRAY_SPECS."""
    return {
        name: np.zeros((T,) + tuple(V if d == "V" else d for d in trail))
        for name, (trail, _) in ARRAY_SPECS.items()
    }


# the attitude arrays of a log: quaternions (w, x, y, z) per vehicle, which must not be zero
QUAT_ARRAYS = [name for name, (trail, _) in ARRAY_SPECS.items() if trail == ("V", 4)]


def _poly(coef: np.ndarray, tau: np.ndarray, deriv: int = 0) -> np.ndarray:
    """sum_k coef[k] tau^k (coef (K, 3)), or its deriv-th derivative, at tau (T,) -> (T, 3)."""
    c = np.polynomial.polynomial.polyder(coef, deriv, axis=0) if deriv else coef
    return np.polynomial.polynomial.polyval(tau, c).T


@st.composite
def synthetic_logs(draw):
    """A two-vehicle log: follower on a random polynomial path (degree <= 4, in t - t_mid),
    under a random polynomial command (degree <= 2), a flight that ended OK or early, maybe a
    NaN in one of the inputs the labels use; returns (log, labels_from_log keywords, expected)."""
    dt = draw(st.sampled_from([0.01, 0.02, 0.05]))
    T = draw(st.integers(2, 300))
    leader = draw(st.sampled_from([0, 1]))
    follower = 1 - leader
    status = int(draw(st.sampled_from([Status.OK, Status.OK, Status.DIVERGED, Status.GROUND, Status.VEHICLE])))
    margin_rows = draw(st.one_of(st.none(), st.integers(0, 60)))  # None: the default FAIL_MARGIN_S
    t0 = draw(st.floats(0.0, 100.0))
    x_coef = draw(hnp.arrays(np.float64, (draw(st.integers(1, 5)), 3), elements=_floats(1.0)))  # m/s^k
    u_coef = draw(hnp.arrays(np.float64, (draw(st.integers(1, 3)), 3), elements=_floats(10.0)))  # m/s^(2+k)
    nan_at = draw(st.one_of(st.none(), st.tuples(
        st.integers(0, T - 1),
        st.sampled_from(["mocap_pos_f", "u_cmd_f", "pos_est_l", "pos_est_f", "vel_est_l", "vel_est_f", "attitude_l"]),
    )))

    quat = np.array(draw(st.one_of(st.sampled_from(SPECIAL_QUATS), st.tuples(*[_floats(1.0)] * 4))))
    assume(np.linalg.norm(quat) > 1e-3)

    tau = dt * (np.arange(T) - (T - 1) / 2)  # s, time from the middle of the flight (exactly uniform)
    arrays = _blank_arrays(T, 2)
    arrays["t"] = t0 + dt * np.arange(T)
    for name in QUAT_ARRAYS:  # every attitude array (true, estimated): both vehicles, constant
        arrays[name][:] = quat
    arrays["mocap_pos"][:, follower] = _poly(x_coef, tau)
    arrays["u_cmd"][:, follower] = _poly(u_coef, tau)
    for name in ("pos_est", "vel_est", "field_mean", "field_applied"):
        arrays[name][:] = draw(hnp.arrays(np.float64, (T, 2, 3), elements=_floats(10.0)))
    if nan_at is not None:
        row, which = nan_at
        name, who = which[:-2], {"l": leader, "f": follower}[which[-1]]
        for name in QUAT_ARRAYS if name == "attitude" else [name]:
            arrays[name][row, who, 0] = np.nan

    meta = {"leader": leader, "follower": follower, "status": status}
    kwargs = {}
    if margin_rows is None:
        margin_rows = FAIL_MARGIN_S / dt
        assert abs(margin_rows - round(margin_rows)) < 1e-9  # the drawn dt divide the default margin
        margin_rows = round(margin_rows)
    else:
        kwargs["fail_margin_s"] = margin_rows * dt

    # what the docstring promises: drop window // 2 rows at each end, the last fail_margin_s
    # of a failed flight, and every row from the first non-finite input on
    h = DEFAULT_WINDOW // 2
    end = T - (margin_rows if status != 0 else 0)
    if nan_at is not None:
        end = min(end, nan_at[0])
    rows = np.arange(h, end - h) if end >= DEFAULT_WINDOW else np.arange(0)
    # Savitzky-Golay (polyorder 4) is exact on the degree <= 4 path, so a = x''. The command
    # kernel K (c = [1, -2, 1] * K) has zero first moment and second moment
    # sum_j K_j j^2 = -1/6, forced by c being exact on t^4: K * (12 t^2 + 2) = 12 t^2.
    # So for a quadratic command, K * u = u - u'' dt^2 / 12.
    a = _poly(x_coef, tau, 2)
    u_smoothed = _poly(u_coef, tau) - _poly(u_coef, tau, 2) * dt**2 / 12
    expected = {"rows": rows, "y": (a - u_smoothed)[rows]}
    return FlightLog(arrays, meta), kwargs, expected


@_settings(80)
@given(case=synthetic_logs())
def test_labels_equal_exact_acceleration_minus_smoothed_command(case):
    """y = x'' - K * u on every kept row (1e-8 relative), the kept rows are exactly those the
    docstring leaves, every output is finite, and the inputs are the right vehicles' rows."""
    log, kwargs, expected = case
    assert DEFAULT_POLYORDER >= 4  # the exactness argument needs polyorder >= the path's degree
    lab = labels_from_log(log, **kwargs)
    rows = expected["rows"]
    assert set(lab) == set(SAMPLE_SCHEMA)
    np.testing.assert_array_equal(lab["row"], rows)
    for name, (shape, _) in SAMPLE_SCHEMA.items():
        assert lab[name].shape == (len(rows), *(1 if d == "K" else d for d in shape)), name  # the pair: K = 1
        assert np.isfinite(lab[name]).all(), name
    if not len(rows):
        return
    scale = 1.0 + np.abs(expected["y"]).max()
    np.testing.assert_allclose(lab["y"], expected["y"], rtol=0, atol=1e-8 * scale)
    leader, follower = log.meta["leader"], log.meta["follower"]
    pos, vel = log["pos_est"][rows], log["vel_est"][rows]
    assert lab["mask"].all() and (lab["neighbour"] == leader).all() and (lab["vehicle"] == follower).all()
    np.testing.assert_array_equal(lab["dp"][:, 0], pos[:, follower] - pos[:, leader])
    np.testing.assert_array_equal(lab["v_a"][:, 0], vel[:, leader])
    np.testing.assert_array_equal(lab["v_b"], vel[:, follower])
    np.testing.assert_array_equal(lab["t"], log["t"][rows])
    np.testing.assert_array_equal(lab["field_mean"], log["field_mean"][rows, follower])
    R_a = lab["R_a"][:, 0]  # a rotation, from the leader's (unnormalised) quaternion
    # a BLAS product of orthonormal rows: within 3 eps of exact on any kernel (~1e-15 against 1e-12)
    np.testing.assert_allclose(R_a @ np.swapaxes(R_a, -1, -2), np.broadcast_to(np.eye(3), R_a.shape), atol=1e-12)


# ----------------------------------------------------------------------- checkpoints


class _RunsOnLoad:
    """Pickles as a call of `func(*args)`: unpickling it would run that call."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return (self.func, self.args)


def _touch(path: str) -> None:
    Path(path).write_text("code from the checkpoint ran")


def _code_objects(sentinel: Path) -> list:
    """Objects whose unpickling would create `sentinel`, through three different callables."""
    return [_RunsOnLoad(_touch, str(sentinel)), _RunsOnLoad(builtins.open, str(sentinel), "w"),
            _RunsOnLoad(os.mkdir, str(sentinel))]


def _trained_like(kind: str, seed: int, dtype=torch.float32):
    """A model of `kind` with random weights and normalisation, as if trained, in `dtype`."""
    return trained_like(kind, seed=seed).to(dtype)


_VALID: dict[str, bytes] = {}


def _valid_checkpoint(kind: str) -> bytes:
    """The bytes of a valid checkpoint of `kind` (made once per kind)."""
    if kind not in _VALID:
        with tempfile.TemporaryDirectory() as d:
            save_checkpoint(Path(d) / "model.pt", _trained_like(kind, seed=0))
            _VALID[kind] = (Path(d) / "model.pt").read_bytes()
    return _VALID[kind]


def _load_or_checkpoint_error(path: Path):
    """Load `path`: a model, or None when CheckpointError was raised; any other exception propagates."""
    try:
        model, record = load_checkpoint(path)
    except CheckpointError:
        return None
    assert isinstance(model, tuple(PAIRWISE_KINDS.values())) and isinstance(record, dict)
    return model


def _load_bytes(data: bytes):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "model.pt"
        path.write_bytes(data)
        return _load_or_checkpoint_error(path)


def _torch_saved(obj) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def _zip(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, content in members.items():
            z.writestr(name, content)
    return buf.getvalue()


def _members(data: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        return {name: z.read(name) for name in z.namelist()}


@_settings(80)
@given(data=st.binary(max_size=4096))
@example(data=b"")
@example(data=b"PK\x03\x04" + bytes(100))  # a zip local-file header, then nothing
def test_bytes_without_a_zip_end_record_raise_checkpoint_error(data):
    """Any file that is not a zip archive (no end-of-central-directory signature) is refused."""
    assume(b"PK\x05\x06" not in data)
    assert _load_bytes(data) is None


@pytest.mark.parametrize("kind", sorted(PAIRWISE_KINDS))
@_settings(30)
@given(cut=st.floats(0.0, 1.0, exclude_max=True))
def test_truncated_checkpoints_raise_checkpoint_error(kind, cut):
    data = _valid_checkpoint(kind)
    assert _load_bytes(data[: int(cut * len(data))]) is None


# member names of this alphabet can never be torch's "<archive>/data.pkl"
_NAME = st.lists(st.sampled_from("abcefg/_.0123"), min_size=1, max_size=12).map("".join)


@_settings(40)
@given(members=st.dictionaries(_NAME, st.binary(max_size=256), max_size=6))
def test_zip_archives_with_random_members_raise_checkpoint_error(members):
    assert _load_bytes(_zip(members)) is None


@st.composite
def payloads_with_code(draw, sentinel: Path):
    """A torch.save'd payload holding an object whose unpickling would create `sentinel`:
    alone, or hidden in a valid checkpoint's payload (top level, state dict, nested list)."""
    obj = draw(st.sampled_from(_code_objects(sentinel)))
    kind = draw(st.sampled_from(sorted(PAIRWISE_KINDS)))
    where = draw(st.sampled_from(["alone", "meta_json", "extra_key", "state_dict", "nested"]))
    if where == "alone":
        return _torch_saved(obj)
    payload = torch.load(io.BytesIO(_valid_checkpoint(kind)), weights_only=True)
    if where == "meta_json":
        payload["meta_json"] = obj
    elif where == "extra_key":
        payload["extra"] = obj
    elif where == "state_dict":
        payload["state_dict"]["in_mean"] = obj
    else:
        payload["extra"] = [1, {"a": (2.0, [obj])}]
    return _torch_saved(payload)


def test_code_objects_would_run_under_an_unsafe_loader(tmp_path):
    """Positive control of the sentinel: each code object does create it when unpickled unsafely."""
    for i in range(3):
        sentinel = tmp_path / f"sentinel{i}"
        data = _torch_saved(_code_objects(sentinel)[i])
        torch.load(io.BytesIO(data), weights_only=False)
        assert sentinel.exists()


@_settings(30)
@given(data=st.data())
def test_checkpoints_holding_code_are_refused_without_running_it(data):
    with tempfile.TemporaryDirectory() as d:
        sentinel = Path(d) / "sentinel"
        path = Path(d) / "model.pt"
        path.write_bytes(data.draw(payloads_with_code(sentinel)))
        with pytest.raises(CheckpointError, match="refused by the safe loader"):
            load_checkpoint(path)
        assert not sentinel.exists()


@pytest.mark.parametrize("kind", sorted(PAIRWISE_KINDS))
@_settings(4)
@given(seed=st.integers(0, 2**31 - 1), double=st.booleans(),
       x=pair_states(shape=(16,), mode="wake"))
def test_round_trip_gives_identical_predictions(kind, seed, double, x):
    model = _trained_like(kind, seed, torch.float64 if double else torch.float32)
    p_a, v_a, R_a, p_b, v_b = x
    inputs = (p_b - p_a, v_a, v_b, R_a, np.stack([v_a * lag for lag in HISTORY_LAGS], -2))  # a steadily moving leader
    with tempfile.TemporaryDirectory() as d:
        save_checkpoint(Path(d) / "model.pt", model, {"seed": seed})
        loaded, record = load_checkpoint(Path(d) / "model.pt", expect_kind=kind)
    assert type(loaded) is type(model) and record["seed"] == seed
    with torch.no_grad():
        want, got = model(*inputs), loaded(*inputs)
    assert got.dtype == want.dtype and torch.equal(got, want)


# --- corrupt or mistyped files: only CheckpointError may come out (these found two loader bugs, now fixed) ---

_ZIP64_LOCATOR_ON_DISK_1 = (
    b"PK\x06\x07" + struct.pack("<IQI", 1, 0, 1)  # zip64 end-of-central-directory locator, disk 1
    + b"PK\x05\x06" + struct.pack("<HHHHIIH", 0, 0, 0, 0, 0, 0, 0)  # an empty end record
)


@st.composite
def corrupted_checkpoints(draw):
    """Recipe for a corrupted valid checkpoint: ("bytes", kind, [(offset, byte), ...]) changes
    bytes in place; ("member", kind, name, content) replaces one zip member; ("raw", data)."""
    kind = draw(st.sampled_from(sorted(PAIRWISE_KINDS)))
    if draw(st.booleans()):
        n = len(_valid_checkpoint(kind))
        return ("bytes", kind, draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=6)))
    name = draw(st.sampled_from(sorted(_members(_valid_checkpoint(kind)))))
    return ("member", kind, name, draw(st.binary(max_size=64)))


def _corrupt(recipe) -> bytes:
    if recipe[0] == "raw":
        return recipe[1]
    data = _valid_checkpoint(recipe[1])
    if recipe[0] == "bytes":
        b = bytearray(data)
        for offset, value in recipe[2]:
            b[offset] = value
        return bytes(b)
    members = _members(data)
    members[recipe[2]] = recipe[3]
    return _zip(members)


@_settings(40)
@given(recipe=corrupted_checkpoints())
@example(recipe=("member", "shallow", "archive/data.pkl", b"."))
@example(recipe=("member", "shallow", "archive/data.pkl", b"\x80\x02h\x00."))
@example(recipe=("raw", _ZIP64_LOCATOR_ON_DISK_1))
def test_corrupted_checkpoints_raise_only_checkpoint_error(recipe):
    _load_bytes(_corrupt(recipe))


@st.composite
def mistyped_payloads(draw):
    """A valid checkpoint's payload (plain containers only, so the safe loader accepts it)
    with one field of the metadata or state dict replaced by a wrong value: ("meta", kind,
    key path, value) or ("state", kind, tensor name, value)."""
    kind = draw(st.sampled_from(sorted(PAIRWISE_KINDS)))
    value = draw(st.one_of(
        st.none(), st.booleans(), st.integers(-3, 3), st.floats(-3.0, 3.0),  # small: `hidden` sizes a layer
        st.lists(st.integers(-3, 3), max_size=2), st.dictionaries(st.sampled_from("ab"), st.integers(-3, 3), max_size=1),
    ))
    if draw(st.booleans()):
        path = draw(st.sampled_from([("model", "kind"), ("model", "feature_set"), ("model", "architecture"),
                                     ("model", "architecture", "hidden"), ("model", "dtype"), ("model",)]))
        return ("meta", kind, path, value)
    return ("state", kind, draw(st.sampled_from(["in_mean", "in_std", "out_mean", "out_std"])), value)


def _mistyped_bytes(recipe) -> bytes:
    payload = torch.load(io.BytesIO(_valid_checkpoint(recipe[1])), weights_only=True)
    if recipe[0] == "meta":
        record = json.loads(payload["meta_json"])
        node = record
        for key in recipe[2][:-1]:
            node = node.setdefault(key, {}) if isinstance(node, dict) else node
        if isinstance(node, dict):
            node[recipe[2][-1]] = recipe[3]
        payload["meta_json"] = json.dumps(record)
    else:
        payload["state_dict"][recipe[2]] = recipe[3]
    return _torch_saved(restamp(payload))


@_settings(40)
@given(recipe=mistyped_payloads())
@example(recipe=("meta", "shallow", ("model", "kind"), [1]))
@example(recipe=("meta", "shallow", ("model", "architecture", "hidden"), -1))
@example(recipe=("state", "shallow", "in_mean", 1))
def test_mistyped_payload_fields_raise_only_checkpoint_error(recipe):
    _load_bytes(_mistyped_bytes(recipe))
