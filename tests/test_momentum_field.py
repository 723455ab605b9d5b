"""Tests of the physics-based `momentum` field (sim/fields/momentum.py): analytic answers.

Each check recomputes its expectation by hand from the textbook formula (momentum
theory, the self-similar round jet), not from the module's internals.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, QUAD
from downwash_core.provenance import describe
from sim.field import DownwashField
from sim.fields import MomentumWake, rotor_thrust_ratio

WAKE = MomentumWake()
RHO = 1.225  # kg/m^3
HOVER_THRUST = QUAD.mass * GRAVITY  # N
DISK_AREA = 4 * math.pi * QUAD.rotor_radius**2  # m^2, four rotors
V_H = math.sqrt(HOVER_THRUST / (2 * RHO * DISK_AREA))  # m/s, hover induced velocity
D0 = math.sqrt(2) * 2 * QUAD.rotor_radius  # m, vena contracta of the equivalent disk (radius 2 R)
LEVEL, ZERO3 = np.eye(3), np.zeros(3)
LEADER = np.array([0.0, 0.0, 2.5])


def _below(s, x=0.0, y=0.0):
    return LEADER + np.array([x, y, -s])


def _tau_by_hand(c: float) -> float:
    """Momentum theory at constant power: the positive real root of tau^3 + c tau - 1 = 0."""
    roots = np.roots([1.0, 0.0, c, -1.0])
    return max(r.real for r in roots if abs(r.imag) < 1e-9 and r.real > 0)


# ------------------------------------------------------------------ rotor model


def test_thrust_ratio_hand_computed_case():
    # a rotor in a stream descending at its own hover induced velocity (c = 1):
    # (1 + x)^2 x = 1 -> x = 0.46557, T/T_h = (1 + x) x = 0.68233
    x = brentq(lambda x: (1 + x) ** 2 * x - 1, 0.0, 1.0)
    assert rotor_thrust_ratio(1.0) == pytest.approx((1 + x) * x, rel=1e-12)
    assert rotor_thrust_ratio(1.0) == pytest.approx(0.6823278, abs=1e-7)


@pytest.mark.parametrize("c", [-1e4, -50.0, -5.0, -1.8899, -1.88, -1.0, -0.3, 0.0, 0.2, 0.5, 0.7, 1.0, 3.0, 40.0, 1e5])
def test_thrust_ratio_is_the_root_of_the_cubic(c):
    # np.roots is LAPACK's eigenvalues of the balanced companion matrix; the positive root is simple, its
    # relative condition sum |a_k tau^k| / |tau p'(tau)| is <= 2 for every real c, so any kernel is within
    # a few eps of it (8e-16 measured under every kernel): rel 1e-9 leaves a factor of a million
    assert rotor_thrust_ratio(c) == pytest.approx(_tau_by_hand(c), rel=1e-9)


def test_thrust_ratio_small_climb_slope_and_limits():
    eps = 1e-6
    slope = (rotor_thrust_ratio(eps) - rotor_thrust_ratio(-eps)) / (2 * eps)
    assert slope == pytest.approx(-1.0 / 3.0, rel=1e-6)  # dT/T_h = -V_c / (3 v_h)
    assert rotor_thrust_ratio(1e8) == pytest.approx(1e-8, rel=1e-6)
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        assert np.all(np.isfinite(rotor_thrust_ratio(np.array([-1e300, -1.0, 0.0, 1e300]))))


# ------------------------------------------------------------------ the wake


def test_hover_induced_velocity_near_the_disk_and_contraction_to_twice_it():
    U0, b0, _, _ = WAKE.centreline(1e-7, HOVER_THRUST)
    assert U0 == pytest.approx(V_H, rel=1e-5)  # momentum theory at the disk
    assert b0 == pytest.approx(2 * QUAD.rotor_radius, rel=1e-5)  # the equivalent disk's radius
    s = np.linspace(0.0, 2.0, 2001)
    U = WAKE.centreline(s, HOVER_THRUST)[0]
    assert U.max() <= 2 * V_H and U.max() > 0.95 * 2 * V_H  # the vena contracta's 2 v_h
    U_near, b_near, _, _ = WAKE.centreline(3 * 2 * QUAD.rotor_radius, HOVER_THRUST)
    assert U_near > 0.95 * 2 * V_H and b_near < 2 * QUAD.rotor_radius  # contracted
    # continuity across the contraction: the flux U b^2 is conserved (within the join's 5 %)
    assert U_near * b_near**2 == pytest.approx(U0 * b0**2, rel=0.05)


@pytest.mark.parametrize("origin", [0.0, 0.3])
def test_far_field_centreline_decays_like_B_U_d_over_x(origin):
    wake = MomentumWake(virtual_origin=origin)
    for s in (3.0, 4.0, 6.0):
        U = wake.centreline(s, HOVER_THRUST)[0]
        assert U == pytest.approx(5.8 * (2 * V_H) * D0 / (s - origin), rel=2e-3)


def _half_width(wake, s):
    axial = lambda r: -wake.wind(LEADER, LEVEL, _below(s, x=r))[2]  # noqa: E731
    U_c = axial(0.0)
    return brentq(lambda r: axial(r) - 0.5 * U_c, 1e-4, 5.0, xtol=1e-12)


def test_half_width_grows_linearly_with_slope_S():
    b2, b4 = _half_width(WAKE, 2.0), _half_width(WAKE, 4.0)
    assert (b4 - b2) / 2.0 == pytest.approx(0.094, rel=5e-3)
    assert b4 == pytest.approx(0.094 * 4.0, rel=2e-3)


def test_more_thrust_more_flow_with_the_square_root():
    U1 = WAKE.centreline(1.0, HOVER_THRUST)[0]
    U2 = WAKE.centreline(1.0, 4 * HOVER_THRUST)[0]
    assert U2 == pytest.approx(2 * U1, rel=1e-12)  # v_h ~ sqrt(T); shape set by the geometry


def test_wake_velocity_is_divergence_free():
    """Continuity: div u = 0 (central differences) inside and outside the jet, near and far."""
    h = 1e-5
    for s, r in [(0.2, 0.0), (0.2, 0.05), (0.6, 0.1), (1.0, 0.03), (2.0, 0.2), (2.0, 0.8), (4.0, 0.5)]:
        p = _below(s, x=r * 0.6, y=r * 0.8)
        div = 0.0
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            div += (WAKE.wind(LEADER, LEVEL, p + e)[i] - WAKE.wind(LEADER, LEVEL, p - e)[i]) / (2 * h)
        U_c, b, _, _ = WAKE.centreline(s, HOVER_THRUST)
        assert abs(div) < 1e-5 * U_c / b, (s, r, div)


def test_entrainment_draws_air_in_and_the_contraction_pulls_inward():
    for s, r in [(1.0, 0.5), (2.0, 0.6), (3.0, 1.5)]:  # outside the far-field jet: inflow
        u = WAKE.wind(LEADER, LEVEL, _below(s, x=r))
        assert u[0] < 0.0
    u = WAKE.wind(LEADER, LEVEL, _below(0.05, x=0.03))  # inside the contracting slipstream
    assert u[0] < 0.0 and u[2] < 0.0
    u = WAKE.wind(LEADER, LEVEL, _below(2.0, x=0.05))  # inside the spreading far-field jet: outflow
    assert u[0] > 0.0


def test_zero_at_and_above_the_rotor_plane_and_faded_in_below():
    rng = np.random.default_rng(0)
    R_a = Rotation.random(200, random_state=rng).as_matrix()
    n = R_a[..., :, 2]
    lateral = rng.normal(0, 0.5, (200, 3))
    lateral -= np.einsum("ni,ni->n", lateral, n)[:, None] * n
    height = rng.uniform(0.0, 3.0, 200)  # m above the rotor plane along n
    height[:2] = [0.0, 1e-12]
    dp = lateral + height[:, None] * n
    v_b = rng.normal(0, 2, (200, 3))
    with np.errstate(divide="raise", over="raise", invalid="raise"):
        F = WAKE(ZERO3, ZERO3, R_a, dp, v_b)
    assert np.all(F == 0.0)
    assert np.all(WAKE(ZERO3, ZERO3, LEVEL, np.array([0.0, 0.0, 0.0]), ZERO3) == 0.0)  # dp = 0
    assert WAKE(ZERO3, ZERO3, LEVEL, np.array([0.0, 0.0, -0.01]), ZERO3)[2] < 0.0


# ------------------------------------------------------------------ the force on the follower


def test_follower_thrust_loss_matches_momentum_theory_hand_case():
    """On the axis 3 m below (far field), a point follower (arm 0) at rest, rotors only."""
    wake = MomentumWake(follower_arm=0.0, drag=False)
    s = 3.0
    U = 5.8 * (2 * V_H) * D0 / s  # m/s, B U_J d0 / x by hand
    c = U / V_H  # the follower is the same vehicle: its v_h is the leader's
    expected = GRAVITY * (_tau_by_hand(c) - 1.0)
    F = wake(LEADER, ZERO3, LEVEL, _below(s), ZERO3)
    assert F[:2] == pytest.approx([0.0, 0.0], abs=1e-15)
    assert F[2] == pytest.approx(expected, rel=3e-3)
    # a follower climbing at 1 m/s: only the wake's share (its own climb loss subtracted)
    v = np.array([0.0, 0.0, 1.0])
    F = wake(LEADER, ZERO3, LEVEL, _below(s), v)
    expected = GRAVITY * (_tau_by_hand(c + 1.0 / V_H) - _tau_by_hand(1.0 / V_H))
    assert F[2] == pytest.approx(expected, rel=3e-3)


def test_drag_pushes_with_the_wake_and_pulls_into_the_entrainment():
    drag_only = MomentumWake(rotors=False)
    k = RHO * 1.0 * 0.01 / (2 * QUAD.mass)  # 1/m, rho C_d A / (2 m)
    U = -WAKE.wind(LEADER, LEVEL, _below(1.0))[2]
    F = drag_only(LEADER, ZERO3, LEVEL, _below(1.0), ZERO3)
    assert F[2] == pytest.approx(-k * U * U, rel=1e-12)  # down, quadratic in the stream
    both = WAKE(LEADER, ZERO3, LEVEL, _below(1.0), ZERO3)
    rotors = MomentumWake(drag=False)(LEADER, ZERO3, LEVEL, _below(1.0), ZERO3)
    assert both[2] == pytest.approx(rotors[2] + F[2], rel=1e-12) and both[2] < rotors[2] < 0
    side = drag_only(LEADER, ZERO3, LEVEL, _below(2.0, x=0.7), ZERO3)
    assert side[0] < 0.0  # drawn toward the axis by the inflow
    # a follower falling with the stream feels no relative wind; what remains is the
    # still-air drag it no longer gets: downward too
    v = WAKE.wind(LEADER, LEVEL, _below(1.0))
    F = drag_only(LEADER, ZERO3, LEVEL, _below(1.0), v)
    # norm of a vector is a BLAS dot: 3 positive terms, within ~2 eps relative of the drag's own |v| on any kernel
    assert F == pytest.approx(k * np.linalg.norm(v) * v, rel=1e-12)


@pytest.mark.parametrize("s", [0.5, 1.0, 1.5])
def test_leader_at_one_and_a_half_times_thrust_pushes_harder(s):
    base = WAKE(LEADER, ZERO3, LEVEL, _below(s, x=0.05), ZERO3)
    strong = WAKE(LEADER, ZERO3, LEVEL, _below(s, x=0.05), ZERO3, thrust=1.5 * HOVER_THRUST)
    scaled = MomentumWake(thrust_scale=1.5)(LEADER, ZERO3, LEVEL, _below(s, x=0.05), ZERO3)
    assert strong[2] < base[2] < 0.0
    assert scaled == pytest.approx(strong, rel=1e-12)


def test_thrust_estimate_holds_altitude_at_the_leader_tilt():
    tilt = Rotation.from_euler("x", 0.3).as_matrix()
    assert WAKE.leader_thrust(LEVEL) == pytest.approx(HOVER_THRUST)
    assert WAKE.leader_thrust(tilt) == pytest.approx(HOVER_THRUST / math.cos(0.3))
    upside_down = Rotation.from_euler("x", math.pi).as_matrix()
    assert WAKE.leader_thrust(upside_down) == pytest.approx(2 * HOVER_THRUST)  # capped
    assert np.all(WAKE(LEADER, ZERO3, LEVEL, _below(1.0), ZERO3, thrust=0.0) == 0.0)


def test_magnitudes_below_a_hovering_leader_against_so2():
    """Recorded in docs/fields.md; not tuned to the so2 field (see there why they differ)."""
    so2 = DownwashField()
    rows = []
    for s in (0.5, 1.0, 1.5):
        F = WAKE(LEADER, ZERO3, LEVEL, _below(s), ZERO3)
        G = so2(LEADER, ZERO3, LEVEL, _below(s), ZERO3)
        rows.append((s, F[2], G[2]))
    print("\n".join(f"s = {s} m: momentum {f:.2f}, so2 {g:.2f} m/s^2" for s, f, g in rows))
    down = [-f for _, f, _ in rows]
    assert down[0] > down[1] > down[2] > 1.0 and down[0] < 10.0  # downward, decaying, O(g/2)
    for (_, f, g) in rows:
        assert 1.0 < f / g < 5.0


# ------------------------------------------------------------------ contract


def test_equivariance_reflection_and_independence_of_the_leader_velocity():
    rng = np.random.default_rng(3)
    n_s = 300
    R_a = Rotation.random(n_s, random_state=rng).as_matrix()
    body = np.column_stack([rng.normal(0, 0.3, n_s), rng.normal(0, 0.3, n_s), -rng.uniform(0.1, 2.5, n_s)])
    dp = np.einsum("nij,nj->ni", R_a, body)
    v_b, v_a = rng.normal(0, 1, (2, n_s, 3))
    F = WAKE(ZERO3, v_a, R_a, dp, v_b)
    H = R_a @ Rotation.from_euler("z", rng.uniform(-np.pi, np.pi, (n_s, 1))).as_matrix() @ np.swapaxes(R_a, 1, 2)
    F_rot = WAKE(ZERO3, v_a, R_a, np.einsum("nij,nj->ni", H, dp), np.einsum("nij,nj->ni", H, v_b))
    # H and M are BLAS products (orthogonal to a few eps, their bits the kernel's); |F| <= 10.5 m/s^2, and the
    # round-off they carry through the wake is 6e-15-7e-15 under every kernel: 1e-10 is 1e4x that, and below
    # any real asymmetry (both checks)
    assert np.abs(F_rot - np.einsum("nij,nj->ni", H, F)).max() < 1e-10
    M = R_a @ np.diag([1.0, -1.0, 1.0]) @ np.swapaxes(R_a, 1, 2)  # mirror through a plane containing n
    F_mir = WAKE(ZERO3, v_a, R_a, np.einsum("nij,nj->ni", M, dp), np.einsum("nij,nj->ni", M, v_b))
    assert np.abs(F_mir - np.einsum("nij,nj->ni", M, F)).max() < 1e-10
    assert np.array_equal(WAKE(ZERO3, 5 * v_a, R_a, dp, v_b), F)


def test_bad_parameters_are_named():
    for kwargs, match in [({"air_density": 0.0}, "air_density"), ({"ring_points": 0}, "ring_points"),
                          ({"spreading_rate": -0.1}, "spreading_rate"), ({"drag": "yes"}, "drag"),
                          ({"thrust_scale": float("nan")}, "thrust_scale")]:
        with pytest.raises(ConfigError, match=match):
            MomentumWake(**kwargs)


def test_describe_is_stable_and_complete():
    d = describe(MomentumWake(thrust_scale=1.2, drag=False))
    assert d["name"] == "momentum" and d["type"].endswith("MomentumWake")
    assert d["thrust_scale"] == 1.2 and d["drag"] is False and d["spreading_rate"] == 0.094
    text = json.dumps(d, sort_keys=True)
    assert "0x" not in text and text == json.dumps(describe(MomentumWake(thrust_scale=1.2, drag=False)), sort_keys=True)
