"""Model inputs: invariance, the NED mapping, safety at r = 0 and v = 0, one formula for NumPy and torch."""

import mujoco
import numpy as np
import pytest
import torch

from downwash_core import geometry
from downwash import features as F

# Our z-up world (x, y, z up) and a FLU body; the paper's NED world and FRD body.
# C maps one to the other (a proper rotation by pi about x).
C = np.diag([1.0, -1.0, -1.0])


def random_rotations(rng, n, max_tilt):
    """Body-to-world rotations with random yaw and a random tilt of up to max_tilt rad."""
    axis = rng.normal(size=(n, 3))
    axis[:, 2] = 0.0
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    tilt = geometry.rotation_about_axis(axis, rng.uniform(0, max_tilt, n))
    yaw = geometry.rotation_about_axis(np.tile([0.0, 0.0, 1.0], (n, 1)), rng.uniform(-np.pi, np.pi, n))
    return tilt @ yaw


def random_states(rng, n, max_tilt=0.6):
    dp = rng.normal(size=(n, 3))
    v_a = rng.normal(size=(n, 3))
    v_b = rng.normal(size=(n, 3))
    return dp, v_a, v_b, random_rotations(rng, n, max_tilt)


def test_rotations_are_proper():
    R = random_rotations(np.random.default_rng(0), 50, 1.0)
    # BLAS/LAPACK on orthonormal matrices: 3-term sums within 3 eps of exact on any kernel, det's LU within
    # a few eps (cond(R) = 1): ~1e-15 against 1e-12
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.mark.parametrize("feature_set", ["5", "6"])
@pytest.mark.parametrize("max_tilt", [0.0, 0.8])
def test_features_invariant_under_rotation_about_leader_axis(feature_set, max_tilt):
    rng = np.random.default_rng(1)
    dp, v_a, v_b, R_a = random_states(rng, 200, max_tilt)
    n = R_a[:, :, 2]
    H = geometry.rotation_about_axis(n, rng.uniform(-np.pi, np.pi, 200))
    rot = lambda v: np.einsum("nij,nj->ni", H, v)  # noqa: E731
    h = F.invariant_features(dp, v_a, v_b, R_a, feature_set)
    # the paper's action rotates dp and v_b; |P v_a| is invariant if v_a is rotated too
    np.testing.assert_allclose(F.invariant_features(rot(dp), v_a, rot(v_b), R_a, feature_set), h, rtol=0, atol=1e-12)
    np.testing.assert_allclose(F.invariant_features(rot(dp), rot(v_a), rot(v_b), R_a, feature_set), h, rtol=0, atol=1e-12)
    # ... while a rotation about another axis changes them (the test can fail)
    G = geometry.rotation_about_axis(np.tile([1.0, 0.0, 0.0], (200, 1)), np.full(200, 0.7))
    moved = F.invariant_features(np.einsum("nij,nj->ni", G, dp), v_a, v_b, R_a, feature_set)
    assert np.max(np.abs(moved - h)) > 0.1
    # the output basis rotates with the state: r_hat -> H r_hat, d -> d
    B = F.equivariant_basis(dp, R_a)
    B_rot = F.equivariant_basis(rot(dp), R_a)
    np.testing.assert_allclose(B_rot[:, 0], rot(B[:, 0]), atol=1e-12)
    np.testing.assert_allclose(B_rot[:, 1], B[:, 1], atol=1e-12)


def test_ned_mapping_level_leader():
    """A follower 1 m directly below a level leader has depth +1; positive f2 pushes it down (-z)."""
    R = np.eye(3)
    dp = np.array([0.0, 0.0, -1.0])
    v_b = np.array([0.3, 0.0, -0.5])  # moving down at 0.5 m/s
    h = F.invariant_features(dp, np.zeros(3), v_b, R, "5")
    names = F.FEATURE_SETS["5"]
    assert h[names.index("depth")] == pytest.approx(1.0)
    assert h[names.index("vb_axial_down")] == pytest.approx(0.5)
    assert h[names.index("r_lateral")] == 0.0
    assert h[names.index("vb_lateral")] == pytest.approx(0.3)
    assert F.depth(dp, R) == pytest.approx(1.0)
    assert F.depth(-dp, R) == pytest.approx(-1.0)  # above the leader: negative
    B = F.equivariant_basis(dp, R)
    np.testing.assert_allclose(F.assemble(np.array([0.0, 2.0]), B), [0.0, 0.0, -2.0])  # toward the ground
    # off axis: r_hat points from the wake axis to the follower
    B = F.equivariant_basis(np.array([0.5, 0.0, -1.0]), R)
    np.testing.assert_allclose(F.assemble(np.array([1.0, 0.0]), B), [1.0, 0.0, 0.0], atol=1e-5)


def test_features_match_the_papers_ned_formulas():
    """Depth, axial speed and the output map equal the paper's eq. 4-5 written in NED / FRD."""
    rng = np.random.default_rng(2)
    dp, v_a, v_b, R_a = random_states(rng, 100, 0.8)
    R_MA = C @ np.swapaxes(R_a, -1, -2) @ C  # paper's R_M^A: NED inertial -> FRD body
    dp_ned, vb_ned = dp @ C, v_b @ C  # C is symmetric
    body_dp = np.einsum("nij,nj->ni", R_MA, dp_ned)
    body_vb = np.einsum("nij,nj->ni", R_MA, vb_ned)
    h = F.invariant_features(dp, v_a, v_b, R_a, "5")
    np.testing.assert_allclose(h[:, 3], body_dp[:, 2], atol=1e-12)  # [R dp]_3
    np.testing.assert_allclose(h[:, 4], body_vb[:, 2], atol=1e-12)  # [R v_b]_3
    np.testing.assert_allclose(h[:, 1], np.hypot(body_dp[:, 0], body_dp[:, 1]), atol=1e-12)
    np.testing.assert_allclose(h[:, 2], np.hypot(body_vb[:, 0], body_vb[:, 1]), atol=1e-12)
    r, q = h[:, 1], h[:, 2]
    dot = np.einsum("ni,ni->n", body_dp[:, :2], body_vb[:, :2])
    # the cosine, softened by R_EPS and V_EPS exactly as documented
    np.testing.assert_allclose(h[:, 0], dot / np.sqrt((r**2 + F.R_EPS**2) * (q**2 + F.V_EPS**2)), atol=1e-12)
    np.testing.assert_allclose(h[:, 0], dot / (r * q), atol=(F.R_EPS / r.min()) ** 2 + (F.V_EPS / q.min()) ** 2)
    # eq. 5: F = R^T (f1 [cos phi, sin phi], f2) in NED, phi the polar angle in the body plane
    f = rng.normal(size=(100, 2))
    phi = np.arctan2(body_dp[:, 1], body_dp[:, 0])
    soft = r / np.sqrt(r**2 + F.R_EPS**2)  # r_hat is softened on the axis
    F_body = np.column_stack([f[:, 0] * soft * np.cos(phi), f[:, 0] * soft * np.sin(phi), f[:, 1]])
    F_world = np.einsum("nji,nj->ni", R_MA, F_body) @ C  # back to NED inertial, then to our world
    np.testing.assert_allclose(F.assemble(f, F.equivariant_basis(dp, R_a)), F_world, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_safe_at_zero_offset_and_zero_speed(dtype):
    """r = 0 (on the axis), v = 0 and dp = 0: finite features, basis and gradients."""
    R = torch.tensor(random_rotations(np.random.default_rng(3), 1, 0.5)[0], dtype=dtype)
    n = R[:, 2]
    cases = [(-0.8 * n, torch.zeros(3, dtype=dtype)), (torch.zeros(3, dtype=dtype), torch.zeros(3, dtype=dtype)),
             (-0.8 * n, 0.4 * n), (torch.tensor([0.3, 0, -1.0], dtype=dtype), torch.tensor([1e-30, 0, 0], dtype=dtype))]  # fmt: skip
    for dp0, vb0 in cases:
        dp = dp0.clone().requires_grad_(True)
        v_b = vb0.clone().requires_grad_(True)
        v_a = torch.zeros(3, dtype=dtype, requires_grad=True)
        h = F.invariant_features(dp, v_a, v_b, R, "6")
        B = F.equivariant_basis(dp, R)
        assert torch.isfinite(h).all() and torch.isfinite(B).all()
        assert abs(float(h.detach()[0])) < 1e-6  # the cosine is defined 0 when either vector vanishes
        (h.sum() + B.sum()).backward()
        for g in (dp.grad, v_b.grad, v_a.grad):
            assert torch.isfinite(g).all(), g


def test_numpy_and_torch_give_the_same_numbers():
    rng = np.random.default_rng(4)
    args = random_states(rng, 64, 0.7)
    for fs in ("5", "6", "raw"):
        x_np, b_np = F.model_inputs(fs, *args)
        x_t, b_t = F.model_inputs(fs, *(torch.tensor(a) for a in args))
        assert isinstance(x_np, np.ndarray) and isinstance(x_t, torch.Tensor)
        # the same elementwise steps in both libraries (dot written out: no BLAS, no reductions); they part
        # only where one rounds a step its own way: an ulp or two of O(1) values (2e-16 measured under
        # torch's default, AVX2 and AVX-512 kernels), far under 1e-14
        np.testing.assert_allclose(x_t.numpy(), x_np, rtol=0, atol=1e-14)
        if b_np is not None:
            np.testing.assert_allclose(b_t.numpy(), b_np, rtol=0, atol=1e-14)
    raw = F.raw_features(args[0], args[2])
    np.testing.assert_array_equal(raw, np.concatenate([args[0], args[2]], axis=-1))


def test_cosine_feature_is_the_cosine_away_from_zero():
    dp = np.array([1.0, 0.0, -1.0])
    for angle in np.linspace(-np.pi, np.pi, 9):
        v_b = 0.7 * np.array([np.cos(angle), np.sin(angle), 0.0])
        c = F.invariant_features(dp, np.zeros(3), v_b, np.eye(3))[0]
        assert c == pytest.approx(np.cos(angle), abs=1e-5)


def test_unknown_feature_set_raises():
    z = np.zeros(3)
    with pytest.raises(ValueError, match=r"feature_set.*'7'"):
        F.invariant_features(z, z, z, np.eye(3), "7")
    with pytest.raises(ValueError, match=r"feature_set.*'bad'"):
        F.model_inputs("bad", z, z, z, np.eye(3))


def test_quat_to_rotmat_matches_mujoco():
    rng = np.random.default_rng(5)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    ref = np.empty((20, 9))
    for i in range(20):
        mujoco.mju_quat2Mat(ref[i], q[i])
    np.testing.assert_allclose(geometry.quat_to_mat(q), ref.reshape(20, 3, 3), atol=1e-12)
    np.testing.assert_allclose(geometry.quat_to_mat(np.array([1.0, 0, 0, 0])), np.eye(3))
