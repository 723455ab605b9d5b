"""The `jet` (sim/fields/jet.py) and `pybullet` (sim/fields/pybullet_law.py) fields: analytic values
recomputed by hand from the published laws, properties over random geometry, the registry spec and a
short flight with each."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from downwash_core.errors import ConfigError
from downwash_core.geometry import dot
from downwash_core.params import GRAVITY, QUAD
from downwash_core.provenance import describe
from downwash_core.status import Status
from downwash_core.vehicles import get_vehicle, so2_pair_scale
from sim.field import check_field
from sim.fields import FIELDS, JetWake, MomentumWake, PybulletDownwash, make_field, resolve_field_spec
from sim.vehicle_params import pair_field

RHO = 1.225  # kg/m^3
HOVER_THRUST = QUAD.mass * GRAVITY  # N, the paper quad's
U_H = math.sqrt(HOVER_THRUST / (2 * RHO * 4 * math.pi * QUAD.rotor_radius**2))  # m/s, Bauersfeld Eq. 1
L_MOTOR = 2 * QUAD.arm_length  # m, the paper quad's distance between opposite motors
B_D, S_JET, S0 = 10.11, 0.07668, -5.817  # Bauersfeld et al. 2024, Eq. 9
A_PROFILE = math.sqrt(2) - 1  # -, Eq. 3: U = U_c (1 + a xi^2)^-2
LEVEL, ZERO3 = np.eye(3), np.zeros(3)
LEADER = np.array([0.0, 0.0, 2.5])
JET, PYB = JetWake(), PybulletDownwash()


def _below(s, x=0.0, y=0.0):
    return LEADER + np.array([x, y, -s])


def _jet_speed_by_hand(s, r):
    """Bauersfeld et al.'s far-field jet (Eqs. 2-4, 6, 9) for the paper quad in a hover, m/s."""
    x = s / L_MOTOR - S0
    U_c, b = B_D * U_H / x, S_JET * L_MOTOR * x
    return U_c / (1 + A_PROFILE * (r / b) ** 2) ** 2


def _tau_by_hand(c: float) -> float:
    """Momentum theory at constant power: the positive real root of tau^3 + c tau - 1 = 0."""
    return max(r.real for r in np.roots([1.0, 0.0, c, -1.0]) if abs(r.imag) < 1e-9 and r.real > 0)


def _pybullet_force_by_hand(dz, dxy, c1=2267.18, c2=0.16, c3=-0.11, r=0.0231348):
    """gym-pybullet-drones' BaseAviary._downwash (N, the downward magnitude), written out from its formula."""
    alpha = c1 * (r / (4 * dz)) ** 2
    beta = c2 * dz + c3
    return alpha * math.exp(-0.5 * (dxy / beta) ** 2)


# ----------------------------------------------------------------------------- jet: the wake


def test_jet_hover_induced_velocity_is_momentum_theory():
    assert U_H == pytest.approx(11.8069, abs=1e-4)
    assert JET.hover_induced_velocity(HOVER_THRUST) == pytest.approx(U_H, rel=1e-14)
    assert JET.hover_induced_velocity(1.5 * HOVER_THRUST) == pytest.approx(math.sqrt(1.5) * U_H, rel=1e-14)


@pytest.mark.parametrize("s", [0.1, 0.45, 1.0, 2.0, 5.0])
def test_jet_centreline_decays_as_one_over_the_distance_from_the_virtual_origin(s):
    U_c, b = JET.centreline(s, HOVER_THRUST)
    assert U_c == pytest.approx(B_D * U_H / (s / L_MOTOR - S0), rel=1e-13)
    # U_c (s - s0 l) is constant: a 1/(s - s0 l) decay from a virtual origin 5.817 motor distances above the rotor plane
    assert U_c * (s - S0 * L_MOTOR) == pytest.approx(B_D * U_H * L_MOTOR, rel=1e-13)
    assert JET.speed(s, 0.0, HOVER_THRUST) == pytest.approx(U_c, rel=1e-14)  # below the fade, on the axis


def test_jet_landmarks_of_the_paper_law():
    U0, _ = JET.centreline(0.0, HOVER_THRUST)
    U25, _ = JET.centreline(2.5 * L_MOTOR, HOVER_THRUST)  # where the paper finds the flow jet-like
    assert U0 / U_H == pytest.approx(B_D / 5.817, rel=1e-12) and U0 / U_H == pytest.approx(1.738, abs=1e-3)
    assert U25 / U_H == pytest.approx(1.2156, abs=1e-4)


def test_jet_half_width_grows_linearly_and_halves_the_speed():
    s = np.linspace(0.2, 3.0, 15)
    U_c, b = JET.centreline(s, HOVER_THRUST)
    assert b == pytest.approx(S_JET * (s - S0 * L_MOTOR), rel=1e-13)
    assert np.diff(b) / np.diff(s) == pytest.approx(np.full(14, S_JET), rel=1e-9)  # slope S
    assert JET.speed(s, b * b, HOVER_THRUST) == pytest.approx(U_c / 2, rel=1e-13)  # b is the half-width


@pytest.mark.parametrize("s, r", [(0.5, 0.0), (0.5, 0.1), (1.0, 0.2), (1.5, 0.05), (2.0, 0.6)])
def test_jet_velocity_matches_the_paper_formula(s, r):
    u = JET.wind(LEADER, LEVEL, _below(s, r * 0.6, r * 0.8))
    assert u[:2] == pytest.approx([0.0, 0.0], abs=1e-15)  # axial only: the paper models the mean speed
    assert -u[2] == pytest.approx(_jet_speed_by_hand(s, r), rel=1e-12)


def test_jet_is_zero_at_and_above_the_rotor_plane_and_faded_in_below():
    for s in (0.0, -0.01, -0.5, -1.047, -2.0, -50.0):  # (the virtual origin, -5.817 l = -1.047 m, included)
        assert JET.speed(s, 0.0, HOVER_THRUST) == 0.0
        assert np.all(JET(LEADER, ZERO3, LEVEL, _below(s), ZERO3) == 0.0)
    s = np.linspace(0.0, JET.fade_depth, 50)
    speed = JET.speed(s, 0.0, HOVER_THRUST)
    assert np.all(np.diff(speed) > 0) and speed[-1] == pytest.approx(JET.centreline(JET.fade_depth, HOVER_THRUST)[0])


def test_jet_speed_cap_keeps_a_virtual_origin_below_the_plane_finite():
    jet = JetWake(virtual_origin=2.0)  # the origin 0.36 m below the plane: the bare law is singular there
    s = np.linspace(-1.0, 2.0, 301)
    U_c, b = jet.centreline(s, HOVER_THRUST)
    assert np.all(np.isfinite(U_c)) and np.all(U_c <= 2 * U_H * (1 + 1e-15)) and np.all(b > 0)
    far = 1.5  # beyond the cap, the law itself
    assert jet.centreline(far, HOVER_THRUST)[0] == pytest.approx(B_D * U_H / (far / L_MOTOR - 2.0), rel=1e-13)
    # with the paper's constants the cap never acts at or below the rotor plane
    assert np.all(JET.centreline(np.linspace(0, 5, 50), HOVER_THRUST)[0] < 2 * U_H)


def test_jet_thrust_estimate_and_keyword():
    tilted = Rotation.from_euler("x", 30, degrees=True).as_matrix()
    p_b = LEADER - 0.8 * tilted[:, 2]
    T_est = HOVER_THRUST / math.cos(math.radians(30))
    assert JET(LEADER, ZERO3, tilted, p_b, ZERO3) == pytest.approx(JET(LEADER, ZERO3, tilted, p_b, ZERO3, thrust=T_est))
    weak, strong = (JET(LEADER, ZERO3, LEVEL, _below(0.8), ZERO3, thrust=k * HOVER_THRUST)[2] for k in (1.0, 1.5))
    assert strong < weak < 0


# ----------------------------------------------------------------------------- jet: the follower


def test_jet_follower_rotors_lose_thrust_as_momentum_theory_says():
    s = 0.9
    jet = JetWake(drag=False)
    v_hf = math.sqrt(HOVER_THRUST / (2 * RHO * 4 * math.pi * QUAD.rotor_radius**2))  # the follower's own v_h
    # on the axis every rotor of the ring is at r = arm
    c = _jet_speed_by_hand(s, QUAD.arm_length) / v_hf
    expected = GRAVITY * (_tau_by_hand(c) - 1.0)
    assert jet(LEADER, ZERO3, LEVEL, _below(s), ZERO3) == pytest.approx([0.0, 0.0, expected], rel=1e-9, abs=1e-12)


def test_jet_follower_drag_is_the_airframe_law_in_the_jet():
    s = 1.2
    jet = JetWake(rotors=False)
    gain = RHO * jet.drag_coefficient * jet.drag_area / (2 * QUAD.mass)  # 1/m
    U = _jet_speed_by_hand(s, 0.0)
    assert jet(LEADER, ZERO3, LEVEL, _below(s), ZERO3) == pytest.approx([0.0, 0.0, -gain * U * U], rel=1e-12)
    v_b = np.array([0.3, 0.0, -0.5])  # moving: the wake's share, drag(u - v) - drag(-v)
    rel_w, rel_0 = np.array([0.0, 0.0, -U]) - v_b, -v_b
    expected = gain * (np.linalg.norm(rel_w) * rel_w - np.linalg.norm(rel_0) * rel_0)
    assert jet(LEADER, ZERO3, LEVEL, _below(s), v_b) == pytest.approx(expected, rel=1e-12)


def test_jet_magnitudes_below_a_hovering_leader():
    """The numbers of docs/fields.md's table (z, m/s^2, follower at rest), from this law, not tuned."""
    depths = (0.5, 1.0, 1.5, 2.0)
    on_axis = [JET(LEADER, ZERO3, LEVEL, _below(s), ZERO3)[2] for s in depths]
    off_axis = [JET(LEADER, ZERO3, LEVEL, _below(s, 0.2), ZERO3)[2] for s in depths]
    assert on_axis == pytest.approx([-4.129, -3.168, -2.565, -2.147], abs=1e-3)
    assert off_axis == pytest.approx([-0.976, -1.177, -1.256, -1.258], abs=1e-3)
    U_c, b = JET.centreline(np.array(depths), HOVER_THRUST)
    assert U_c == pytest.approx([13.89, 10.50, 8.44, 7.05], abs=0.01) and b == pytest.approx(
        [0.1186, 0.1570, 0.1953, 0.2336], abs=1e-4)


def test_pybullet_magnitudes_below_a_leader():
    """The numbers of docs/fields.md's `pybullet` table (m/s^2, m)."""
    depths = np.array([0.5, 1.0, 1.5, 2.0])
    assert PYB.width(depths) == pytest.approx([0.030, 0.0515, 0.1301, 0.2100], abs=1e-4)
    on_axis = [PYB(LEADER, ZERO3, LEVEL, _below(s), ZERO3)[2] for s in depths]
    off_axis = [PYB(LEADER, ZERO3, LEVEL, _below(s, 0.2), ZERO3)[2] for s in depths]
    assert on_axis == pytest.approx([-9.814, -2.809, -1.248, -0.702], abs=1e-3)
    assert off_axis == pytest.approx([-0.0, -0.0015, -0.383, -0.446], abs=1e-3)


def test_jet_shares_momentums_follower_constants_and_defaults():
    momentum = MomentumWake()
    own = {"motor_distance", "decay_constant", "spreading_rate", "virtual_origin"}  # the paper's, in its units
    shared = [f.name for f in dataclasses.fields(JetWake) if f.name not in own]
    assert len(shared) == 14 and all(getattr(JET, k) == getattr(momentum, k) for k in shared)
    jet_own = [JET.decay_constant, JET.spreading_rate, JET.virtual_origin]
    assert jet_own != [momentum.decay_constant, momentum.spreading_rate, momentum.virtual_origin]
    assert JET.motor_distance == pytest.approx(0.18)


# ----------------------------------------------------------------------------- pybullet: the law


@pytest.mark.parametrize("dz, dxy", [(1.0, 0.05), (1.5, 0.1), (0.9, 0.0), (2.0, 0.3), (3.0, 0.5)])
def test_pybullet_law_at_hand_computed_points(dz, dxy):
    F = _pybullet_force_by_hand(dz, dxy)  # N on the 0.027 kg Crazyflie
    a = PYB(LEADER, ZERO3, LEVEL, _below(dz, dxy * 0.6, -dxy * 0.8), ZERO3)
    # beta is wide here (>= 0.034 m, w0 = 0.030 m enters as (w0 / beta)^4 / 4 <= 15 %): a few % at most
    beta = 0.16 * dz - 0.11
    tol = (0.030 / beta) ** 4 / 4 * (dxy / beta) ** 2 + 1e-12
    assert a[:2] == pytest.approx([0.0, 0.0], abs=1e-15)
    assert -a[2] * 0.027 == pytest.approx(F, rel=max(tol, 1e-12))


def test_pybullet_hand_value_at_one_metre():
    # alpha = 2267.18 (0.0231348 / 4)^2 = 0.07584 N; beta = 0.05 m; at 0.05 m off the axis exp(-0.5)
    alpha = 2267.18 * (0.0231348 / 4) ** 2
    assert alpha == pytest.approx(0.0758399, abs=1e-7)
    a = PYB(LEADER, ZERO3, LEVEL, _below(1.0, 0.05), ZERO3)[2]
    w_eff = (0.05**4 + 0.03**4) ** 0.25  # the width floor's share
    assert a == pytest.approx(-alpha * math.exp(-0.5 * (0.05 / w_eff) ** 2) / 0.027, rel=1e-12)
    assert PYB(LEADER, ZERO3, LEVEL, _below(1.0), ZERO3)[2] == pytest.approx(-alpha / 0.027, rel=1e-13)  # -2.809


def test_pybullet_width_where_beta_is_not_positive():
    dz = np.linspace(0.0, 0.6875, 30)  # beta = 0.16 dz - 0.11 <= 0
    assert PYB.width(dz) == pytest.approx(np.full(30, 0.030), rel=1e-15)
    deep = np.linspace(0.7, 5.0, 50)
    assert np.all(np.diff(PYB.width(np.r_[dz, deep])) >= 0)  # monotone: the wake never narrows downstream
    beta = 0.16 * 4.0 - 0.11
    assert PYB.width(4.0) == pytest.approx(beta, rel=(0.03 / beta) ** 4)  # the law's own width where it is wide
    mirror = PybulletDownwash(mirror_width=True)  # gym-pybullet-drones' |beta|
    assert mirror.width(0.1) == pytest.approx(abs(0.16 * 0.1 - 0.11), rel=(0.03 / 0.094) ** 4)
    assert mirror.width(0.6875) == pytest.approx(0.030, rel=1e-15)  # where gym-pybullet-drones divides by 0
    a = mirror(LEADER, ZERO3, LEVEL, _below(0.6875), ZERO3)
    assert np.all(np.isfinite(a)) and a[2] < 0


def test_pybullet_near_depth_caps_the_push_at_the_crazyflies_weight():
    assert PYB(LEADER, ZERO3, LEVEL, _below(0.535), ZERO3)[2] == pytest.approx(-GRAVITY, rel=1e-3)
    capped = [PYB(LEADER, ZERO3, LEVEL, _below(s), ZERO3)[2] for s in (0.05, 0.2, 0.4, 0.535)]
    assert capped == pytest.approx([capped[-1]] * 4, rel=1e-14)
    beyond = PYB(LEADER, ZERO3, LEVEL, _below(0.6), ZERO3)[2] * 0.027
    assert -beyond == pytest.approx(_pybullet_force_by_hand(0.6, 0.0), rel=1e-14)  # the law itself beyond


def test_pybullet_is_zero_at_and_above_the_leader_and_continuous_below():
    for s in (0.0, -1e-9, -0.3, -5.0):
        assert np.all(PYB(LEADER, ZERO3, LEVEL, _below(s, 0.01), ZERO3) == 0.0)
    s = np.linspace(0.0, PYB.fade_depth, 40)
    push = PYB.push(s, 0.0)
    assert push[0] == 0.0 and np.all(np.diff(push) > 0) and np.max(np.diff(push)) < 0.1 * push[-1]


def test_pybullet_pushes_along_the_leaders_axis():
    R = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    n = R[:, 2]
    a = PYB(LEADER, ZERO3, R, LEADER - 1.2 * n, ZERO3)
    assert a == pytest.approx(-_pybullet_force_by_hand(1.2, 0.0) / 0.027 * n, rel=1e-13)


def test_pybullet_other_kinds_scale_as_so2():
    cf, x500 = get_vehicle("crazyflie_2_1"), get_vehicle("x500")
    assert pair_field(PYB, QUAD, QUAD) is PYB and pair_field(PYB, cf, cf) is PYB  # one kind: the same acceleration
    paired = pair_field(PYB, QUAD, cf)
    assert paired.dw_coeff_1 == pytest.approx(2267.18 * so2_pair_scale(QUAD, cf)) and so2_pair_scale(QUAD, cf) > 7
    p_b = _below(1.0, 0.02)
    ratio = paired(LEADER, ZERO3, LEVEL, p_b, ZERO3)[2] / PYB(LEADER, ZERO3, LEVEL, p_b, ZERO3)[2]
    assert ratio == pytest.approx(so2_pair_scale(QUAD, cf), rel=1e-13)
    assert pair_field(PYB, x500, QUAD).dw_coeff_1 < 2267.18


def test_jet_other_kinds_take_the_leaders_motor_distance():
    cf = get_vehicle("crazyflie_2_1")
    assert pair_field(JET, QUAD, QUAD) is JET
    cf_pair = pair_field(JET, cf, cf)
    assert cf_pair.motor_distance == pytest.approx(2 * cf.arm_length) and cf_pair.leader_mass == cf.mass
    assert (cf_pair.decay_constant, cf_pair.spreading_rate, cf_pair.virtual_origin) == (B_D, S_JET, S0)
    T = cf.mass * GRAVITY  # the law in the Crazyflie's own units
    uh = math.sqrt(T / (2 * RHO * 4 * math.pi * cf.rotor_radius**2))
    assert cf_pair.centreline(0.5, T)[0] == pytest.approx(B_D * uh / (0.5 / (2 * cf.arm_length) - S0), rel=1e-13)


@pytest.mark.parametrize("cls, kwargs, match", [
    (JetWake, {"motor_distance": 0.0}, "motor_distance"),
    (JetWake, {"spreading_rate": -0.1}, "spreading_rate"),
    (JetWake, {"decay_constant": float("nan")}, "decay_constant"),
    (JetWake, {"air_density": 0.0}, "air_density"),  # shared: checked by MomentumWake under the same name
    (PybulletDownwash, {"min_width": 0.0}, "min_width"),
    (PybulletDownwash, {"follower_mass": -1.0}, "follower_mass"),
    (PybulletDownwash, {"near_depth": float("inf")}, "near_depth"),
    (PybulletDownwash, {"mirror_width": "yes"}, "mirror_width"),
])
def test_bad_parameters_are_named(cls, kwargs, match):
    with pytest.raises(ConfigError, match=match):
        cls(**kwargs)


# ----------------------------------------------------------------------------- properties


def _floats(lo, hi):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


@st.composite
def pairs(draw, n=4):
    """n pairs: a randomly tilted leader anywhere, followers below, above, on or off its axis."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    R_a = Rotation.random(n, random_state=rng).as_matrix()
    scale = draw(st.sampled_from([1e-9, 0.05, 1.0, 30.0]))
    depth = draw(_floats(-3, 6)) * rng.uniform(0, 1, n)  # m, along -n: mostly below (s > 0), some above
    body = np.column_stack([rng.normal(0, scale, n), rng.normal(0, scale, n), -depth])
    p_a = rng.normal(0, 100, (n, 3))
    v = lambda: rng.normal(0, draw(st.sampled_from([0.0, 1.0, 50.0])), (n, 3))  # noqa: E731
    return p_a, v(), R_a, p_a + np.einsum("nij,nj->ni", R_a, body), v()


FIELD_OBJECTS = {"jet": JET, "pybullet": PYB, "pybullet-mirror": PybulletDownwash(mirror_width=True),
                 "jet-origin-below": JetWake(virtual_origin=3.0)}


@pytest.mark.parametrize("name", FIELD_OBJECTS)
@given(x=pairs())
@settings(max_examples=40, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
def test_finite_shaped_and_zero_above_the_leader(name, x):
    field = FIELD_OBJECTS[name]
    p_a, v_a, R_a, p_b, v_b = x
    with np.errstate(divide="raise", over="raise", invalid="raise", under="ignore"):
        F = field(p_a, v_a, R_a, p_b, v_b)
    assert F.shape == (4, 3) and np.all(np.isfinite(F))
    above = dot(p_b - p_a, R_a[:, :, 2]) >= 0  # s <= 0, in the fields' own arithmetic (bit for bit)
    assert np.all(F[above] == 0.0)


@pytest.mark.parametrize("name", FIELD_OBJECTS)
@given(x=pairs(), angle=_floats(0.0, 2 * math.pi), flip=st.booleans())
@settings(max_examples=40, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
def test_equivariant_under_rotations_and_reflections_about_the_leader_axis(name, x, angle, flip):
    field = FIELD_OBJECTS[name]
    p_a, v_a, R_a, p_b, v_b = x
    local = Rotation.from_euler("z", angle).as_matrix() @ (np.diag([1.0, -1.0, 1.0]) if flip else np.eye(3))
    H = R_a @ local @ np.swapaxes(R_a, 1, 2)  # about each leader's axis n
    act = lambda v: np.einsum("nij,nj->ni", H, v)  # noqa: E731
    F = field(p_a, v_a, R_a, p_b, v_b)
    F_h = field(p_a, v_a, R_a, p_a + act(p_b - p_a), act(v_b))
    assert F_h == pytest.approx(act(F), abs=1e-9 * max(1.0, np.abs(F).max()))


def test_the_wrong_axis_breaks_the_symmetry():
    """The equivariance check can fail: rotating about world x (not the leader's axis) moves the field."""
    rng = np.random.default_rng(7)
    p_a = rng.normal(0, 1, (50, 3))
    p_b = p_a + np.column_stack([rng.normal(0, 0.05, 50), rng.normal(0, 0.05, 50), -rng.uniform(0.8, 1.5, 50)])
    H = Rotation.from_euler("x", 0.4).as_matrix()
    for field in (JET, PYB):
        F = field(p_a, ZERO3, LEVEL, p_b, ZERO3)
        F_h = field(p_a, ZERO3, LEVEL, p_a + (p_b - p_a) @ H.T, ZERO3)
        assert np.abs(F_h - F @ H.T).max() > 0.1


@pytest.mark.parametrize("name", FIELD_OBJECTS)
def test_batched_equals_one_by_one(name):
    field = FIELD_OBJECTS[name]
    rng = np.random.default_rng(11)
    n = 40
    R_a = Rotation.random(n, random_state=rng).as_matrix()
    p_a = rng.normal(0, 1, (n, 3))
    body = np.column_stack([rng.normal(0, 0.15, n), rng.normal(0, 0.15, n), -rng.uniform(-0.5, 2.5, n)])
    p_b, v_a, v_b = p_a + np.einsum("nij,nj->ni", R_a, body), rng.normal(0, 0.5, (n, 3)), rng.normal(0, 0.7, (n, 3))
    batched = field(p_a, v_a, R_a, p_b, v_b)
    single = np.array([field(p_a[i], v_a[i], R_a[i], p_b[i], v_b[i]) for i in range(n)])
    assert np.array_equal(batched, single)
    grid = field(p_a[:5, None], v_a[:5, None], R_a[:5, None], p_b[None, :7], v_b[None, :7])  # (5, 7) broadcast
    assert grid.shape == (5, 7, 3) and np.array_equal(grid[3, 6], field(p_a[3], v_a[3], R_a[3], p_b[6], v_b[6]))
    assert np.abs(batched).max() > 0.1  # the wake is there


# ----------------------------------------------------------------------------- registry and flight


def test_registered_with_their_parameters_and_lines():
    for name, cls in (("jet", JetWake), ("pybullet", PybulletDownwash)):
        entry = FIELDS[name]
        assert entry.factory is cls and entry.description and entry.symmetry.startswith("SO(2)")
        assert set(entry.params) == {f.name for f in dataclasses.fields(cls)}
        assert make_field(name) == cls()


def test_specs_parse_and_convert():
    j = resolve_field_spec("jet:decay_constant=9.5,virtual_origin=-4,ring_points=4,drag=false")
    assert (j.decay_constant, j.virtual_origin, j.ring_points, j.drag) == (9.5, -4.0, 4, False)
    assert type(j.ring_points) is int and type(j.virtual_origin) is float
    p = resolve_field_spec(" pybullet:dw_coeff_1 = 1000, mirror_width=yes ")
    assert (p.dw_coeff_1, p.mirror_width) == (1000.0, True)
    with pytest.raises(ConfigError, match="field 'pybullet' has no parameter 'alpha'; allowed: dw_coeff_1"):
        resolve_field_spec("pybullet:alpha=1")
    with pytest.raises(ConfigError, match="spreading_rate"):
        resolve_field_spec("jet:spreading_rate=0")


@pytest.mark.parametrize("name", ["jet", "pybullet"])
def test_checked_and_described_stably(name):
    field = make_field(name)
    check_field(field, name=name)
    d = describe(field)
    assert d["name"] == name and "0x" not in json.dumps(d)
    assert json.dumps(d, sort_keys=True) == json.dumps(describe(make_field(name)), sort_keys=True)
    changed = make_field(name, **({"spreading_rate": 0.09} if name == "jet" else {"dw_coeff_2": 0.2}))
    assert describe(changed) != d  # a fitted parameter is in the provenance


@pytest.mark.parametrize("name", ["jet", "pybullet"])
def test_short_flight_under_a_hovering_leader(name):
    from downwash_trajectories import Hover, stack
    from sim.flight import fly
    from sim.scene import build_scene

    ref = stack([Hover(LEADER, n_worlds=1), Hover(LEADER - [0.05, 0.0, 0.7], n_worlds=1)])
    log = fly(build_scene(), ref, [0], 1.0, field=make_field(name))[0]
    assert log.meta["status"] == Status.OK, log.meta.get("message")
    assert np.all(np.isfinite(log["pos"])) and np.all(np.isfinite(log["field_mean"]))
    assert np.abs(log["field_mean"][:, 1]).max() > 1.0  # the follower was in the wake
    assert np.abs(log["field_mean"][:, 0]).max() == 0.0  # and the leader, above it, felt nothing
