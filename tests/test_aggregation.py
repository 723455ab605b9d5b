"""Tests of the wake aggregation laws (sim/aggregation.py) and the per-pair forces (sim/field.py).

States are stacks of 2-8 vehicles drawn by hypothesis: consecutive vehicles 0.3-0.8 m
apart vertically, within 0.2 m laterally and tilted by at most 0.2 rad about each
axis, so every vehicle but the top one lies inside the wake of the one above it
(non-zero pair forces, asserted) and the shielding law is active; the vehicle order is
shuffled, so no law can rely on index order.
"""

from __future__ import annotations

import inspect
import json
import math
import pickle
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from downwash_core.errors import ConfigError
from sim import field as field_module
from sim.aggregation import (
    AGGREGATIONS,
    DEFAULT_AGGREGATION,
    LinearSuperposition,
    VelocitySuperposition,
    WakeShielding,
    make_aggregation,
    parse_aggregation_spec,
    wake_field,
)
from sim.field import DownwashField, pairwise_field, pairwise_forces
from sim.fields.momentum import MomentumWake

SO2 = DownwashField()
KNOBS = DownwashField(c4_amplitude=0.3, swirl=0.4, skew=0.35)
MOMENTUM = MomentumWake()
FIELDS = {"so2": SO2, "so2-knobs": KNOBS, "momentum": MOMENTUM}
SPECS = ["linear", "velocity", "velocity:exponent=0.8", "velocity:exponent=1.5", "shielding", "shielding:eta=1,radius=0.4,ramp=0.05"]
NONLINEAR = [s for s in SPECS if s != "linear"]


def _settings(n: int):
    """n examples, no deadline (numba compiles on first use), no example database."""
    return settings(max_examples=n, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _rotations(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(..., 3, 3) body-to-world Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def _floats(lo: float, hi: float):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


@st.composite
def stacks(draw, min_vehicles: int = 2, max_vehicles: int = 8, max_worlds: int = 2):
    """(pos (W, V, 3) m, vel (W, V, 3) m/s, rot (W, V, 3, 3)): a shuffled stack per world."""
    V = draw(st.integers(min_vehicles, max_vehicles))
    W = draw(st.integers(1, max_worlds))
    gaps = draw(hnp.arrays(np.float64, (W, V), elements=_floats(0.3, 0.8)))
    lateral = draw(hnp.arrays(np.float64, (W, V, 2), elements=_floats(-0.1, 0.1)))
    angles = draw(hnp.arrays(np.float64, (3, W, V), elements=_floats(-0.2, 0.2)))
    yaw = draw(hnp.arrays(np.float64, (W, V), elements=_floats(-math.pi, math.pi)))
    vel = draw(hnp.arrays(np.float64, (W, V, 3), elements=_floats(-1.0, 1.0)))
    order = np.array(draw(st.permutations(range(V))))
    pos = np.concatenate([lateral, (3.0 - np.cumsum(gaps, axis=1))[..., None]], axis=-1)
    rot = _rotations(angles[0], angles[1], yaw)
    return pos[:, order], vel[:, order], rot[:, order]


def _close(actual: np.ndarray, expected: np.ndarray, rel: float = 1e-12) -> None:
    """|actual - expected| <= rel (|expected| + max |expected|): relative, with an absolute floor."""
    scale = float(np.max(np.abs(expected), initial=0.0))
    np.testing.assert_allclose(actual, expected, rtol=rel, atol=rel * scale + 1e-300)


class _Readable:
    """A field without `pairwise`/`pair_forces`: forces the broadcast (readable) evaluation."""

    def __init__(self, field):
        self.field = field

    def __call__(self, *args):
        return self.field(*args)


# --------------------------------------------------------------------------- the linear law


@_settings(30)
@given(stacks())
def test_linear_is_pairwise_field_bit_for_bit(state):
    pos, vel, rot = state
    for field in (SO2, KNOBS, MOMENTUM, _Readable(SO2)):
        expected = pairwise_field(field, pos, vel, rot)
        for law in (None, LinearSuperposition(), make_aggregation("linear"), make_aggregation("")):
            np.testing.assert_array_equal(wake_field(field, pos, vel, rot, law), expected)
        # one world without the batch axis, and an extra batch axis
        np.testing.assert_array_equal(wake_field(field, pos[0], vel[0], rot[0]),
                                      pairwise_field(field, pos[0], vel[0], rot[0]))
        np.testing.assert_array_equal(wake_field(field, pos[None], vel[None], rot[None], LinearSuperposition()),
                                      pairwise_field(field, pos[None], vel[None], rot[None]))


# --------------------------------------------------------------------------- properties of every law


@pytest.mark.parametrize("field_name", ["so2", "so2-knobs", "momentum"])
@_settings(25)
@given(state=stacks(min_vehicles=3), data=st.data())
def test_every_law_is_invariant_to_vehicle_order(field_name, state, data):
    field = FIELDS[field_name]
    pos, vel, rot = state
    assert np.any(pairwise_forces(field, pos, vel, rot) != 0.0)  # followers really are in wakes
    perm = np.array(data.draw(st.permutations(range(pos.shape[1]))))
    for spec in SPECS:
        law = make_aggregation(spec)
        out = wake_field(field, pos, vel, rot, law)
        permuted = wake_field(field, pos[:, perm], vel[:, perm], rot[:, perm], law)
        _close(permuted, out[:, perm])


@pytest.mark.parametrize("field_name", ["so2", "so2-knobs", "momentum"])
@_settings(30)
@given(stacks(min_vehicles=2, max_vehicles=2, max_worlds=3))
def test_every_law_reduces_to_the_pairwise_force_for_two_vehicles(field_name, state):
    field = FIELDS[field_name]
    pos, vel, rot = state
    expected = pairwise_field(field, pos, vel, rot)
    assert np.all(np.any(expected != 0.0, axis=-1).sum(axis=-1) == 1)  # the lower one feels the upper one
    for spec in SPECS:
        law = make_aggregation(spec)
        for f in (field, _Readable(field)):  # the compiled and the broadcast pair forces
            out = wake_field(f, pos, vel, rot, law)
            if isinstance(law, WakeShielding):  # no third vehicle: the empty product is exactly 1
                np.testing.assert_array_equal(out, pairwise_field(f, pos, vel, rot))
            else:
                _close(out, expected, 1e-13)


@pytest.mark.parametrize("field_name", ["so2", "momentum"])
@_settings(20)
@given(
    n=st.integers(2, 6),
    pos=hnp.arrays(np.float64, (2, 6, 3), elements=_floats(-50.0, 50.0)),
    vel=hnp.arrays(np.float64, (2, 6, 3), elements=_floats(-20.0, 20.0)),
    angles=hnp.arrays(np.float64, (3, 2, 6), elements=_floats(-math.pi, math.pi)),
    same=st.booleans(),
)
def test_every_law_is_finite_for_any_finite_state(field_name, n, pos, vel, angles, same):
    """Wide ranges, any attitude, and (same=True) two distinct vehicles at one point."""
    pos, vel, rot = pos[:, :n].copy(), vel[:, :n], _rotations(*angles)[:, :n]
    if same:
        pos[:, 1] = pos[:, 0]
    for spec in SPECS:
        assert np.all(np.isfinite(wake_field(FIELDS[field_name], pos, vel, rot, make_aggregation(spec))))


# --------------------------------------------------------------------------- compiled against readable


@st.composite
def pair_forces_and_geometry(draw):
    """Random (W, V, V, 3) forces (diagonal 0, some pairs exactly 0) with a random stack."""
    pos, vel, rot = draw(stacks(min_vehicles=2))
    W, V = pos.shape[:2]
    forces = draw(hnp.arrays(np.float64, (W, V, V, 3), elements=_floats(-20.0, 20.0)))
    zero = draw(hnp.arrays(np.bool_, (W, V, V)))
    forces[zero | np.eye(V, dtype=bool)] = 0.0
    return forces, pos, rot


@_settings(60)
@given(pair_forces_and_geometry(), _floats(0.5, 3.0), _floats(0.0, 1.0), _floats(0.05, 1.0), _floats(0.01, 0.5))
def test_compiled_laws_match_their_readable_twins(case, exponent, eta, radius, ramp):
    forces, pos, rot = case
    for law in (VelocitySuperposition(exponent), WakeShielding(eta, radius, ramp), LinearSuperposition()):
        _close(law.combine(forces, pos, rot), law.combine_reference(forces, pos, rot))
    # a non-float64 input takes the readable path and agrees too
    law = WakeShielding(eta, radius, ramp)
    _close(law.combine(forces.tolist(), pos.tolist(), rot.tolist()), law.combine(forces, pos, rot))


@pytest.mark.parametrize("knobs", [{}, {"c4_amplitude": 0.3}, {"swirl": 0.4}, {"skew": 0.35},
                                   {"c4_amplitude": 0.3, "swirl": 0.4, "skew": 0.35}])
@_settings(25)
@given(stacks(min_vehicles=2))
def test_compiled_pair_forces_match_the_field_and_the_pairwise_kernel(knobs, state):
    field = DownwashField(**knobs)
    pos, vel, rot = state
    fast = field.pair_forces(pos, vel, rot)
    assert fast.shape == pos.shape[:2] + pos.shape[1:2] + (3,)
    assert np.all(fast[:, np.arange(pos.shape[1]), np.arange(pos.shape[1])] == 0.0)
    _close(fast, pairwise_forces(_Readable(field), pos, vel, rot), 1e-11)
    np.testing.assert_array_equal(pairwise_forces(field, pos, vel, rot), fast)
    _close(fast.sum(axis=1), field.pairwise(pos, vel, rot))
    # per-world constants: no compiled path, the broadcast evaluation instead
    assert DownwashField(strength=np.full((pos.shape[0], 1, 1), 10.6)).pair_forces(pos, vel, rot) is None


@pytest.mark.parametrize("spec", NONLINEAR)
@_settings(25)
@given(stacks(min_vehicles=3))
def test_the_hot_path_matches_the_readable_path(spec, state):
    """wake_field on (W, V, 3) with DownwashField (compiled pairs + compiled law) against all-NumPy."""
    pos, vel, rot = state
    law = make_aggregation(spec)
    readable = law.combine_reference(pairwise_forces(_Readable(SO2), pos, vel, rot), pos, rot)
    _close(wake_field(SO2, pos, vel, rot, law), readable, 1e-11)


def test_the_per_pair_kernel_is_the_pairwise_kernel_kept_apart():
    """The two compiled loops are one law: the same statements up to the output index (no drift)."""

    def body(fn) -> list[str]:
        src = inspect.getsource(fn.py_func)
        src = src[src.index('"""', src.index('"""') + 3) + 3:]  # after the docstring
        src = src.replace("out[w, i, j,", "out[w, j,").replace("np.zeros((W, V, V, 3))", "np.zeros((W, V, 3))")
        return [line.rstrip() for line in src.splitlines() if line.strip()]

    assert body(field_module._pair_forces_kernel) == body(field_module._pairwise_kernel)


# --------------------------------------------------------------------------- analytic cases


def _level_stack(depths: list[float], lateral: list[float] | None = None):
    """One world: level vehicles at rest at z = 3 - depth, x = lateral (m)."""
    V = len(depths)
    pos = np.zeros((1, V, 3))
    pos[0, :, 2] = 3.0 - np.asarray(depths)
    if lateral is not None:
        pos[0, :, 0] = lateral
    return pos, np.zeros((1, V, 3)), np.broadcast_to(np.eye(3), (1, V, 3, 3)).copy()


@pytest.mark.parametrize("field_name", ["so2", "momentum"])
@pytest.mark.parametrize("order", [(0, 1, 2), (2, 0, 1)])
def test_a_stack_of_three_is_not_a_pairwise_sum_under_the_nonlinear_laws(field_name, order):
    """Three level vehicles 0.5 m apart on one axis, in index order or shuffled: each law in closed form."""
    field = FIELDS[field_name]
    depths = np.array([0.0, 0.5, 1.0])[list(order)]
    pos, vel, rot = _level_stack(list(depths))
    top, mid, bottom = np.argsort(depths)
    f = pairwise_forces(field, pos, vel, rot)[0]
    f_top, f_mid = f[top, bottom], f[mid, bottom]  # on the bottom vehicle, from the top and the middle one
    assert f_top[2] < 0.0 and f_mid[2] < f_top[2] and np.allclose(f_top[:2], 0.0) and np.allclose(f_mid[:2], 0.0)
    linear = wake_field(field, pos, vel, rot)[0, bottom]
    np.testing.assert_allclose(linear, f_top + f_mid, rtol=1e-14)

    # velocity, p = 2: the equivalent speeds add, |F| = (sqrt|f_top| + sqrt|f_mid|)^2
    velocity = wake_field(field, pos, vel, rot, make_aggregation("velocity"))[0, bottom]
    expected = -((math.sqrt(-f_top[2]) + math.sqrt(-f_mid[2])) ** 2)
    np.testing.assert_allclose(velocity, [0.0, 0.0, expected], rtol=1e-12, atol=1e-12)
    assert velocity[2] < 1.3 * linear[2]  # at least 30 % stronger: the test can fail

    # shielding: the middle vehicle sits on the top one's axis, 0.5 m from both (> ramp): g = 1
    for eta in (0.5, 1.0):
        shielded = wake_field(field, pos, vel, rot, WakeShielding(eta=eta))[0, bottom]
        np.testing.assert_allclose(shielded, (1.0 - eta) * f_top + f_mid, rtol=1e-14)
        assert shielded[2] > linear[2] + 0.2 * eta * abs(f_top[2])
    # the middle vehicle is not shielded from anything, and the top one feels nothing
    for spec in NONLINEAR:
        out = wake_field(field, pos, vel, rot, make_aggregation(spec))[0]
        np.testing.assert_array_equal(out[top], 0.0)
        np.testing.assert_allclose(out[mid], f[top, mid], rtol=1e-13)


@pytest.mark.parametrize("exponent", [0.5, 0.8, 1.0, 1.5, 2.0, 3.0])
def test_velocity_law_on_equal_parallel_and_perpendicular_forces(exponent):
    """Two leaders, equal |f| on one follower: parallel gives 2^p f, perpendicular 2^((p-1)/2) (f1 + f2)."""
    law = VelocitySuperposition(exponent)
    f = np.array([0.3, -0.4, -1.2])  # m/s^2, |f| = 1.3
    forces = np.zeros((1, 3, 3, 3))
    forces[0, 0, 2] = forces[0, 1, 2] = f
    for combine in (law.combine, law.combine_reference):
        np.testing.assert_allclose(combine(forces)[0, 2], 2.0**exponent * f, rtol=1e-13)
        np.testing.assert_array_equal(combine(forces)[0, :2], 0.0)
    f1, f2 = np.array([0.0, 0.0, -2.0]), np.array([2.0, 0.0, 0.0])
    forces[0, 0, 2], forces[0, 1, 2] = f1, f2
    for combine in (law.combine, law.combine_reference):
        out = combine(forces)[0, 2]
        np.testing.assert_allclose(out, 2.0 ** ((exponent - 1.0) / 2.0) * (f1 + f2), rtol=1e-13)
        # norm of a vector is a BLAS dot: 3 positive terms, within ~2 eps relative on any kernel
        assert math.isclose(np.linalg.norm(out), 2.0 ** (exponent / 2.0) * 2.0, rel_tol=1e-13)
    # opposite equal forces cancel, as the velocities do
    forces[0, 0, 2], forces[0, 1, 2] = f, -f
    for combine in (law.combine, law.combine_reference):
        np.testing.assert_allclose(combine(forces)[0, 2], 0.0, atol=1e-15)


@_settings(40)
@given(pair_forces_and_geometry(), _floats(0.1, 10.0))
def test_velocity_law_is_linear_for_exponent_one_and_homogeneous(case, scale):
    forces, _, _ = case
    _close(VelocitySuperposition(1.0).combine(forces), forces.sum(axis=1))
    law = VelocitySuperposition(2.0)
    _close(law.combine(scale * forces), scale * law.combine(forces), 1e-11)


def test_shielding_weight_in_closed_form_and_continuous():
    """Leader at depth 0, shield at 0.5 m and 0.125 m off the axis, follower at 1 m."""
    law = WakeShielding(eta=0.8, radius=0.25, ramp=0.1)
    pos, _, rot = _level_stack([0.0, 0.5, 1.0], [0.0, 0.125, 0.0])
    factors = law.shielding_factors(pos, rot)[0]
    lateral = (1.0 - 0.125**2 / 0.25**2) ** 2  # 0.5625
    assert math.isclose(factors[0, 2], 1.0 - 0.8 * lateral, rel_tol=1e-14)
    # every other pair has no vehicle between: exactly 1
    mask = np.ones((3, 3), dtype=bool)
    mask[0, 2] = False
    np.testing.assert_array_equal(factors[mask], 1.0)
    # near the edge of the depth ramp (0.05 m below the leader): S(0.5) = 0.5
    pos_ramp, _, _ = _level_stack([0.0, 0.05, 1.0])
    assert math.isclose(law.shielding_factors(pos_ramp, rot)[0, 0, 2], 1.0 - 0.8 * 0.5, rel_tol=1e-14)
    # the shield moving out across the radius, or up across the leader's rotor plane: no jump
    for depth, offsets in ((0.5, (0.25 - 1e-6, 0.25 + 1e-6)), (None, (1e-7, -1e-7))):
        values = []
        for x in offsets:
            p, _, _ = _level_stack([0.0, 0.5, 1.0], [0.0, x, 0.0]) if depth else _level_stack([0.0, x, 1.0])
            values.append(law.shielding_factors(p, rot)[0, 0, 2])
        assert abs(values[0] - values[1]) < 1e-9
    # zero shielding is the linear law
    state = _level_stack([0.0, 0.5, 1.0, 1.4], [0.0, 0.05, -0.05, 0.02])
    _close(wake_field(SO2, *state, WakeShielding(eta=0.0)), pairwise_field(SO2, *state))


# --------------------------------------------------------------------------- selection, errors, provenance


def test_registry_default_and_specs():
    assert DEFAULT_AGGREGATION == "linear" and set(AGGREGATIONS) == {"linear", "velocity", "shielding"}
    assert make_aggregation("") == LinearSuperposition()
    assert make_aggregation(" velocity ") == VelocitySuperposition(2.0)
    assert make_aggregation("velocity:exponent=1.5") == VelocitySuperposition(exponent=1.5)
    assert make_aggregation("shielding:eta=0.8, radius=0.3") == WakeShielding(eta=0.8, radius=0.3)
    assert parse_aggregation_spec("shielding:ramp=0.2") == ("shielding", {"ramp": 0.2})
    for name, cls in AGGREGATIONS.items():
        law = make_aggregation(name)
        assert isinstance(law, cls) and law.name == name
        d = law.describe()
        assert d["name"] == name and d == make_aggregation(name).describe()
        json.dumps(d)
        assert pickle.loads(pickle.dumps(law)) == law
    assert VelocitySuperposition(1.5).describe() != VelocitySuperposition(2.0).describe()
    assert WakeShielding().describe()["eta"] == 0.5


@pytest.mark.parametrize("spec, match", [
    ("bogus", r"unknown 'bogus'; allowed: linear, velocity, shielding"),
    ("velocity:p=2", r"no parameter 'p'; allowed: exponent"),
    ("linear:eta=1", r"no parameter 'eta'; allowed: no parameters"),
    ("shielding:eta", r"KEY=VALUE, got 'eta'; allowed: eta, radius, ramp"),
    ("shielding:eta=1.5", r"eta: got 1.5; allowed \[0.0, 1.0\]"),
    ("shielding:radius=0", r"radius: got 0.0; allowed \(0.0, 10.0\] m"),
    ("velocity:exponent=0.4", r"exponent: got 0.4; allowed \[0.5, 3.0\]"),
    ("velocity:exponent=inf", r"must be finite"),
    ("velocity:exponent=two", r"expected a number"),
    ("shielding:eta=0.1,eta=0.2", r"'eta' given twice"),
])
def test_bad_specs_raise_config_error_naming_what_is_allowed(spec, match):
    with pytest.raises(ConfigError, match=match):
        make_aggregation(spec)


def test_bad_laws_and_states_raise_config_error():
    pos, vel, rot = _level_stack([0.0, 0.5])
    with pytest.raises(ConfigError, match="make_aggregation.*linear, velocity, shielding"):
        wake_field(SO2, pos, vel, rot, "velocity")
    with pytest.raises(ConfigError, match="expected a law object"):
        wake_field(SO2, pos, vel, rot, object())
    with pytest.raises(ConfigError, match=re.escape("aggregation: expected an aggregation spec NAME[:KEY=VALUE,...], "
                                                    "got NoneType")):
        make_aggregation(None)
    with pytest.raises(ConfigError, match=re.escape("eta: got -0.1")):
        WakeShielding(eta=-0.1)
    with pytest.raises(ConfigError, match=r"rot: expected \(\.\.\., 2, 3, 3\)"):
        wake_field(SO2, pos, vel, rot[:, :, :2], make_aggregation("velocity"))
