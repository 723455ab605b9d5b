"""Tests of the wake with memory (sim/fields/shed.py): the steady state against the momentum law,
the transport delay and the wind's drift against quadrature, and the batch contracts.

Expectations come from `MomentumWake` (the steady law the shed wake must reproduce) and from
integrating ds / (kappa U_c(s)) by scipy's quad, not from the module's table or search.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.spatial.transform import Rotation

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, QUAD
from downwash_core.vehicles import get_vehicle
from sim.fields import MomentumWake
from sim.fields import momentum, shed_kernels
from sim.fields.shed import ShedWake, WakeState
from sim.fields.shed_centreline import nearest_segments, nearest_segments_numpy
from sim.vehicle_params import pair_field

HOVER = QUAD.mass * GRAVITY  # N, the paper quad's hover thrust
TOP = np.array([0.0, 0.0, 2.5])  # m, the leader
ASIDE = np.array([3.0, 0.0, 2.5])  # m, a vehicle out of every wake while the wake is built


def _level(W, V):
    return np.broadcast_to(np.eye(3), (W, V, 3, 3)).copy()


def _delay(wake: ShedWake, s: float, thrust: float = HOVER) -> float:
    """s, the time an element takes to reach depth s: int_0^s ds' / (kappa U_c(s')), by quadrature."""
    speed = lambda x: wake.convection * wake.law.centreline(x, thrust)[0]
    return quad(lambda x: 1.0 / speed(x), 0.0, s, limit=200)[0]


def _hover(wake, pos, seconds, dt, **kw):
    """A wake of vehicles held still at pos (W, V, 3), level, for `seconds`."""
    W, V, _ = pos.shape
    state = wake.initial_state(W, V)
    vel, rot = np.zeros((W, V, 3)), _level(W, V)
    for _ in range(int(round(seconds / dt))):
        wake.step(state, dt, pos, vel, rot, **kw)
    return state


def _centre_x(wake, state, pos, depths, xs):
    """m, per depth below the leader (vehicle 0 of world 0): the x of the strongest downward air along a line in x."""
    pts = np.array([[x, 0.0, TOP[2] - s] for s in depths for x in xs])[None]
    u_z = wake.air_velocity(state, pos, _level(*pos.shape[:2]), pts)[0, 0, :, 2].reshape(len(depths), len(xs))
    return xs[np.argmin(u_z, axis=1)]


# ------------------------------------------------------------------ 1. the steady state is the momentum law


@pytest.mark.parametrize("dt", [0.01, 0.004, 0.025])  # one shedding a step, some steps none, several a step
def test_steady_wake_of_a_hovering_leader_is_the_momentum_law(dt):
    wake, law = ShedWake(), MomentumWake()
    pos = np.array([[TOP, ASIDE], [TOP, ASIDE]])  # W = 2 worlds
    thrust = np.full((2, 2), HOVER)
    state = _hover(wake, pos, wake.max_age + 0.5, dt, thrust=thrust)
    vel, rot = np.zeros((2, 2, 3)), _level(2, 2)
    for depth in (0.3, 0.6, 1.0, 1.5):
        probe = pos.copy()
        probe[0, 1] = TOP + [0.0, 0.0, -depth]  # world 0: on the axis
        probe[1, 1] = TOP + [0.1, 0.0, -depth]  # world 1: 0.1 m off it
        got = wake.forces(state, probe, vel, rot)
        want = law(probe[:, 0], vel[:, 0], rot[:, 0], probe[:, 1], vel[:, 1])
        # measured (dt = 0.01), z in m/s^2, shed / momentum: on the axis -6.196 / -5.579 / -4.115 / -2.963 at
        # 0.3 / 0.6 / 1.0 / 1.5 m, 0.1 m off -1.649 / -1.847 / -2.148 / -2.091, the same to 5e-16 relative:
        # a straight wake has s = depth exactly, so the tolerance is rounding (the law's own error is not at stake)
        np.testing.assert_allclose(got[:, 0, 1], want, rtol=1e-9, atol=1e-12)
        assert np.all(got[:, 1, 0] == 0.0)  # the leader is above the follower's rotor plane
        assert np.all(got[:, [0, 1], [0, 1]] == 0.0)  # no vehicle feels its own wake
    assert want[0, 2] < -2.0 and want[1, 2] < -2.0  # the comparison is not of two zeros


def test_steady_wakes_of_two_kinds_are_the_pair_laws():
    """Each element carries its own kind's jet, each target its own rotors and airframe: an X500 over a
    Crazyflie (world 0) and the Crazyflie over the X500 (world 1) are the momentum law of that ordered pair."""
    x500, cf = get_vehicle("x500"), get_vehicle("crazyflie_2_1")
    wake = ShedWake().for_vehicles([x500, "crazyflie_2_1"])
    assert wake.vehicles == ("x500", "crazyflie_2_1")
    pos = np.array([[TOP, ASIDE], [ASIDE, TOP]])
    state = _hover(wake, pos, wake.max_age + 0.3, 0.01)
    vel, rot = np.zeros((2, 2, 3)), _level(2, 2)
    for depth in (0.5, 1.0):
        probe = pos.copy()
        probe[0, 1] = TOP + [0.05, 0.0, -depth]
        probe[1, 0] = TOP + [0.05, 0.0, -depth]
        got = wake.forces(state, probe, vel, rot)
        want_0 = pair_field(MomentumWake(), x500, cf)(TOP, vel[0, 0], rot[0, 0], probe[0, 1], vel[0, 1])
        want_1 = pair_field(MomentumWake(), cf, x500)(TOP, vel[1, 1], rot[1, 1], probe[1, 0], vel[1, 0])
        np.testing.assert_allclose(got[0, 0, 1], want_0, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(got[1, 1, 0], want_1, rtol=1e-9, atol=1e-12)
        assert want_0[2] < -5.0 and abs(want_1[2]) > 1e-3  # X500 > Crazyflie: -12 m/s^2 at 1 m (docs/fields.md)


# ------------------------------------------------------------------ 2. transport delay, 3. wind


def test_elements_travel_by_the_quadrature_of_the_centreline_speed():
    wake = ShedWake()
    state = _hover(wake, TOP[None, None], wake.max_age + 0.1, 0.01, thrust=np.full((1, 1), HOVER))
    depth, age = state.depth[state.valid], state.age[state.valid]
    assert depth.size == wake.n_elements == 80 and depth.max() > 3.0  # the default reaches past 3 m
    for s, a in zip(depth[age > 0], age[age > 0]):
        assert _delay(wake, s) == pytest.approx(a, rel=1e-5)


def test_a_jump_of_the_leader_reaches_each_depth_after_the_transport_delay():
    """The leader jumps 0.5 m sideways; the wake's centreline at depth s follows when the first element
    shed at the new place gets there: one shedding period after the jump plus int ds / (kappa U_c)."""
    wake, dt = ShedWake(rate_hz=400.0, max_age=0.3), 0.0025  # a fine clock: the delay quantised by 2.5 ms
    pos = TOP[None, None].copy()
    state = _hover(wake, pos, 0.35, dt)
    pos = pos + [0.5, 0.0, 0.0]
    depths, xs = (0.6, 1.5), np.linspace(-0.25, 0.75, 201)
    arrived = {}
    for i in range(1, 120):
        wake.step(state, dt, pos, np.zeros((1, 1, 3)), _level(1, 1))
        for s, x in zip(depths, _centre_x(wake, state, pos, depths, xs)):
            if s not in arrived and x > 0.25:
                arrived[s] = i * dt
    np.testing.assert_allclose(_centre_x(wake, state, pos, depths, xs), 0.5, atol=0.006)  # all moved over
    for s in depths:
        predicted = 1.0 / wake.rate_hz + _delay(wake, s)
        # measured 0.0600 s against 0.0592 at 0.6 m, 0.1850 against 0.1871 at 1.5 m: within one period
        assert arrived[s] == pytest.approx(predicted, abs=1.0 / wake.rate_hz), (s, arrived[s], predicted)
    assert arrived[1.5] > 2.5 * arrived[0.6]  # the far wake is slow: the delay grows ~ s^2


def test_wind_carries_the_steady_wake_downwind_by_the_wind_times_the_delay():
    wake = ShedWake()
    wind = np.array([[2.0, 0.0, 0.0]])  # m/s
    state = _hover(wake, TOP[None, None], wake.max_age + 0.5, 0.01, wind=wind)
    depths = (0.6, 1.0, 1.5)
    found = _centre_x(wake, state, TOP[None, None], depths, np.linspace(-0.1, 1.0, 1101))
    # measured 0.113 / 0.203 / 0.365 m against 0.113 / 0.205 / 0.369 (the polyline's chords cut the curve)
    np.testing.assert_allclose(found, [2.0 * _delay(wake, s) for s in depths], rtol=0.03, atol=0.002)
    still = _hover(wake, TOP[None, None], wake.max_age + 0.5, 0.01)
    np.testing.assert_array_equal(state.depth, still.depth)  # the wind moves elements, not their depth


# ------------------------------------------------------------------ 4. order, 5. batch


def _flight(wake, W, V, steps, dt, perm=None, reset_at=None, worlds=None):
    """A deterministic flight of a stack of V vehicles in W worlds: moving, tilted, in wind. Returns the
    state and the forces at the end; `perm` reorders the vehicles, `worlds` picks worlds of the W."""
    rng = np.random.default_rng(7)
    base = TOP + np.stack([rng.normal(0, 0.05, V), rng.normal(0, 0.05, V), -0.55 * np.arange(V)], -1)  # (V, 3)
    phase = rng.uniform(0, 2 * np.pi, (W, V))
    tilt = rng.normal(0, 0.08, (W, V, 2))
    wind = rng.normal(0, 0.5, (W, 3))
    perm = np.arange(V) if perm is None else np.asarray(perm)
    worlds = np.arange(W) if worlds is None else np.asarray(worlds)
    state = wake.initial_state(len(worlds), V)
    for step in range(steps + 1):
        t = step * dt
        pos = base[None] + 0.2 * np.stack([np.cos(t + phase), np.sin(t + phase), 0 * phase], -1)
        vel = 0.2 * np.stack([-np.sin(t + phase), np.cos(t + phase), 0 * phase], -1)
        rot = Rotation.from_rotvec(np.concatenate([tilt, 0 * tilt[..., :1]], -1).reshape(-1, 3)).as_matrix()
        rot = rot.reshape(W, V, 3, 3)
        pos, vel, rot, w_ = pos[worlds][:, perm], vel[worlds][:, perm], rot[worlds][:, perm], wind[worlds]
        if step == steps:
            return state, wake.forces(state, pos, vel, rot, wind=w_)
        if reset_at is not None and step == reset_at:
            wake.reset(state, np.isin(worlds, [1]))
        wake.step(state, dt, pos, vel, rot, wind=w_)


@pytest.mark.parametrize("kinds", [(), ("x500", "paper_quad", "crazyflie_2_1")])
def test_permuting_the_vehicles_permutes_the_forces(kinds):
    perm = [2, 0, 1]
    wake = ShedWake(vehicles=kinds)
    _, forces = _flight(wake, 2, 3, 40, 0.01)
    wake_p = wake.for_vehicles([kinds[i] for i in perm]) if kinds else wake
    _, forces_p = _flight(wake_p, 2, 3, 40, 0.01, perm=perm)
    np.testing.assert_array_equal(forces_p, forces[:, perm][:, :, perm])
    assert np.abs(forces[:, 0, 1, 2]).min() > 0.05  # vehicle 1 flies in vehicle 0's wake: a real comparison
    assert np.all(forces[:, 1, 0] == 0.0)  # and vehicle 0 above vehicle 1's rotor plane


def test_worlds_stepped_together_equal_each_world_stepped_alone():
    """Bit for bit, with steps longer than the shedding period (one or two sheddings a step) and world 1
    reset midway, so that the worlds' clocks and rings differ."""
    wake = ShedWake()
    together, forces = _flight(wake, 3, 3, 30, 0.013, reset_at=12)
    assert not np.array_equal(together.clock[0], together.clock[1])
    for w in range(3):
        alone, forces_w = _flight(wake, 3, 3, 30, 0.013, reset_at=12, worlds=[w])
        np.testing.assert_array_equal(forces_w[0], forces[w])
        for name in ("pos", "axis", "depth", "thrust", "age", "valid", "cursor", "clock"):
            np.testing.assert_array_equal(getattr(alone, name)[0], getattr(together, name)[w], err_msg=name)
    assert np.abs(forces).max() > 0.1


def test_compiled_search_equals_its_numpy_reference():
    wake = ShedWake(max_age=0.2)
    state, _ = _flight(wake, 3, 3, 35, 0.013, reset_at=25)  # world 1's ring partly filled
    rng = np.random.default_rng(3)
    points = TOP + rng.normal(0, 0.4, (3, 50, 3)) - [0, 0, 0.8]
    origin = TOP + rng.normal(0, 0.05, (3, 3, 3))
    newest = (state.cursor - 1) % state.shape[2]
    args = (points, origin, state.pos, state.valid, state.age, newest)
    for got, want in zip(nearest_segments(*args), nearest_segments_numpy(*args)):
        np.testing.assert_array_equal(got, want)


def _random_flight(rng, wake, W, V, steps):
    """Random steps of a random stack (tilted, moving, thrust given or estimated, wind or none, dt shorter or
    longer than the shedding period, some worlds reset midway), yielding each step's arguments."""
    base = TOP + np.stack([rng.normal(0, 0.1, V), rng.normal(0, 0.1, V), -0.45 * np.arange(V)], -1)
    wind = rng.normal(0, 1.0, (W, 3)) if rng.random() < 0.5 else None
    for i in range(steps):
        dt = float(rng.choice([0.002, 0.004, 0.01, 0.013, 0.027, 0.3]) if i else 0.01)
        pos = base + rng.normal(0, 0.05, (W, V, 3))
        vel = rng.normal(0, 0.5, (W, V, 3))
        rot = Rotation.from_rotvec(rng.normal(0, 0.3, (W * V, 3))).as_matrix().reshape(W, V, 3, 3)
        thrust = rng.uniform(0.0, 25.0, (W, V)) if rng.random() < 0.3 else None
        yield i, dt, pos, vel, rot, thrust, wind


def test_compiled_step_and_forces_equal_their_numpy_reference():
    """The compiled passes (the default) against `_step_reference` / `_forces_reference` on random states: W 1-4,
    V 1-5, kinds mixed, wind on and off, tilted vehicles, rings empty, partly filled (a reset) and wrapped, dt
    from a fifth of the shedding period to 30 of them. The state is carried bit for bit (only sqrt and
    arithmetic, in the reference's order), and so are the forces: the reference takes pow, sinh, asinh, cbrt
    and acos from the C library, as the kernels do (`downwash_core.libm`; NumPy's own differ on AVX-512)."""
    rng = np.random.default_rng(11)
    kinds = ["paper_quad", "x500", "crazyflie_2_1"]
    compared = 0
    for trial in range(24):
        W, V = int(rng.integers(1, 5)), int(rng.integers(1, 6))
        wake = ShedWake(max_age=float(rng.choice([0.05, 0.3, 0.8])))
        if trial % 3:
            wake = wake.for_vehicles(list(rng.choice(kinds, V)))
        fast, slow = wake.initial_state(W, V), wake.initial_state(W, V)
        for i, dt, pos, vel, rot, thrust, wind in _random_flight(rng, wake, W, V, int(rng.integers(1, 50))):
            if i == 20:
                for state in (fast, slow):
                    wake.reset(state, [W - 1])  # a partly filled ring beside full ones
            wake.step(fast, dt, pos, vel, rot, thrust, wind)
            wake.step(slow, dt, pos, vel, rot, thrust, wind, compiled=False)
            for name in ("pos", "axis", "depth", "thrust", "age", "valid", "cursor", "clock"):
                np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
            got = wake.forces(fast, pos, vel, rot, wind)
            want = wake.forces(slow, pos, vel, rot, wind, compiled=False)
            np.testing.assert_array_equal(got, want)
            compared += int(np.count_nonzero(want))
    assert compared > 2000  # pairs in a wake, not zeros


def test_compiled_twins_equal_the_momentum_law():
    """The kernels' scalar twins of `MomentumWake.centreline`, `induced_velocity`, `follower_response` and
    `rotor_thrust_ratio` against the NumPy originals on random inputs (bits on an AVX2 CPU, 1e-12 allowed:
    NumPy's SIMD transcendental functions elsewhere)."""
    rng = np.random.default_rng(12)
    laws = [MomentumWake(), MomentumWake(virtual_origin=0.3, ring_points=5, rotors=False),
            MomentumWake(virtual_origin=-0.2, ring_points=12, drag=False),
            pair_field(MomentumWake(), get_vehicle("x500"), get_vehicle("crazyflie_2_1"))]
    c = np.concatenate([rng.normal(0, 2, 400), rng.lognormal(0, 3, 100), -rng.lognormal(0, 3, 100),
                        [0.0, 0.5, momentum.C_STAR, -1.0, 1e-300, 1e300, -1e300]])
    want = momentum.rotor_thrust_ratio(c)
    got = [shed_kernels.rotor_thrust_ratio(x, momentum.C_STAR, momentum.C_SMALL) for x in c]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    for law in laws:
        jet = shed_kernels.pair_constants(law, GRAVITY, momentum.PROFILE_A, momentum.BLEND, momentum.C_STAR,
                                          momentum.C_SMALL)
        s = np.concatenate([rng.uniform(-0.2, 4.0, 200), [0.0, 1e-9, law.fade_depth, 50.0]])
        T, r2 = rng.uniform(-1.0, 30.0, s.size), rng.uniform(0.0, 0.3, s.size) * (rng.random(s.size) < 0.9)
        cl = law.centreline(s, T)
        for i in range(s.size):
            np.testing.assert_allclose(shed_kernels.centreline(s[i], T[i], jet), [x[i] for x in cl], rtol=1e-12)
            axial, radial = law.induced_velocity(s[i], r2[i], T[i])
            np.testing.assert_allclose(shed_kernels.velocity(s[i], r2[i], T[i], jet), (axial, radial), rtol=1e-12)
        M, K = 50, law.ring_points
        n = Rotation.from_rotvec(rng.normal(0, 0.4, (M, 3))).as_matrix()[..., 2]
        v_b, air, ring = rng.normal(0, 1, (M, 3)), rng.normal(0, 3, (M, 3)), rng.normal(0, 3, (M, K))
        want = law.follower_response(n, v_b, ring, air)
        got = np.zeros((M, 3))
        for i in range(M):
            shed_kernels.follower_response(n[i], v_b[i], ring[i].copy(), air[i], jet, got[i])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)


def test_the_compiled_travel_table_lookup_is_numpys_interp():
    """The step's lookup s = G^-1 (bisection within a bucket of the table) against np.interp, bit for bit: on and
    beside every table row, between rows, below and above the table, for each kind's table."""
    wake = ShedWake(vehicles=("paper_quad", "x500", "crazyflie_2_1"))
    c, rng = wake._compiled, np.random.default_rng(13)
    for k in range(3):
        xp, fp = c["table_x"][k], c["table_s"][k]
        x = np.concatenate([xp, np.nextafter(xp, -np.inf), np.nextafter(xp, np.inf), 0.5 * (xp[1:] + xp[:-1]),
                            rng.uniform(0.0, 1.0, 5000) ** 6 * xp[-1] * 1.1, [-1.0, -0.0, 1e-300, 2 * xp[-1], 1e300]])
        got = np.empty_like(x)
        shed_kernels._interp(x, xp, fp, c["table_slope"][k], c["table_start"][k], c["emin"], got)
        np.testing.assert_array_equal(got, np.interp(x, xp, fp))


def test_the_compiled_passes_reject_what_is_not_finite_before_touching_the_state():
    wake = ShedWake()
    pos, vel, rot = np.array([[TOP, TOP - [0, 0, 0.5]]]), np.zeros((1, 2, 3)), _level(1, 2)
    state = _hover(wake, pos, 0.3, 0.01)
    before = {k: v.copy() for k, v in vars(state).items()}
    nan = lambda x: np.where(np.ones_like(x, bool), np.nan, x)
    calls = [("pos", lambda: wake.step(state, 0.01, nan(pos), vel, rot)),
             ("vel", lambda: wake.step(state, 0.01, pos, nan(vel), rot)),
             ("rot", lambda: wake.step(state, 0.01, pos, vel, nan(rot))),
             ("thrust", lambda: wake.step(state, 0.01, pos, vel, rot, thrust=np.full((1, 2), np.inf))),
             ("wind", lambda: wake.step(state, 0.01, pos, vel, rot, wind=np.full((1, 3), np.nan))),
             ("vel", lambda: wake.forces(state, pos, nan(vel), rot)),
             ("wind", lambda: wake.forces(state, pos, vel, rot, wind=np.full((1, 3), np.nan)))]
    for name, call in calls:
        with pytest.raises(ConfigError, match=f"{name}: must be finite"):
            call()
    for k, v in vars(state).items():
        np.testing.assert_array_equal(v, before[k], err_msg=k)


# ------------------------------------------------------------------ 6. provenance


def test_describe_is_stable_json_and_tells_every_constant_apart():
    base = ShedWake().describe()
    text = json.dumps(base)
    assert "0x" not in text and base["name"] == "shed" and base["type"] == "sim.fields.shed.ShedWake"
    assert base["law"] == MomentumWake().describe()
    assert base == ShedWake(rate_hz=100, max_age=0.8, convection=0.5).describe()  # ints read as the floats
    assert json.loads(text) == base
    variants = [dict(rate_hz=50.0), dict(max_age=1.0), dict(convection=0.6), dict(vehicles=("x500",)),
                dict(law=MomentumWake(spreading_rate=0.1))]
    described = [json.dumps(ShedWake(**kw).describe(), sort_keys=True) for kw in variants]
    assert len(set(described + [json.dumps(base, sort_keys=True)])) == len(variants) + 1


# ------------------------------------------------------------------ 7. bad input


@pytest.mark.parametrize("kw, match", [
    (dict(rate_hz=0.0), "rate_hz"), (dict(rate_hz=-5.0), "rate_hz"), (dict(rate_hz="fast"), "rate_hz"),
    (dict(max_age=0.0), "max_age"), (dict(max_age=float("nan")), "max_age"),
    (dict(rate_hz=1e4, max_age=60.0), "max_age"),  # a ring of 600 000 elements
    (dict(convection=0.0), "convection"), (dict(convection=3.0), "convection"),
    (dict(law="momentum"), "law"), (dict(vehicles="x500"), "vehicles"), (dict(vehicles=("boat",)), "vehicle"),
])
def test_bad_constants_raise_naming_the_constant(kw, match):
    with pytest.raises(ConfigError, match=match):
        ShedWake(**kw)


def test_bad_shapes_raise_naming_the_argument_and_the_expected_shape():
    wake = ShedWake()
    state = wake.initial_state(2, 2)
    pos, vel, rot = np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), _level(2, 2)
    bad = [
        (lambda: wake.step(state, 0.01, np.zeros((2, 3)), vel, rot), r"pos: expected \(W, V, 3\) = \(2, 2, 3\)"),
        (lambda: wake.step(state, 0.01, pos, np.zeros((2, 3, 3)), rot), r"vel: expected \(W, V, 3\) = \(2, 2, 3\)"),
        (lambda: wake.step(state, 0.01, pos, vel, np.eye(3)), r"rot: expected \(W, V, 3, 3\) = \(2, 2, 3, 3\)"),
        (lambda: wake.step(state, 0.01, pos, vel, rot, thrust=np.ones(2)), r"thrust: expected \(W, V\) = \(2, 2\)"),
        (lambda: wake.step(state, 0.01, pos, vel, rot, wind=np.ones(3)), r"wind: expected \(W, 3\) = \(2, 3\)"),
        (lambda: wake.step(state, 0.0, pos, vel, rot), "dt"),
        (lambda: wake.step(state, 0.01, pos + np.nan, vel, rot), "pos: must be finite"),
        (lambda: wake.forces(state, np.zeros((1, 2, 3)), vel, rot), r"pos: expected \(W, V, 3\) = \(2, 2, 3\)"),
        (lambda: wake.forces(state, pos, vel, rot, wind=np.ones((2, 2))), r"wind: expected \(W, 3\)"),
        (lambda: wake.forces(ShedWake(max_age=0.5).initial_state(2, 2), pos, vel, rot), "state"),
        (lambda: wake.forces("wake", pos, vel, rot), "state"),
        (lambda: wake.air_velocity(state, pos, rot, np.zeros((2, 3))), r"points: expected \(W, P, 3\)"),
        (lambda: ShedWake(vehicles=("x500",)).initial_state(2, 2), "vehicles"),
        (lambda: wake.initial_state(0, 2), "n_worlds"),
    ]
    for call, match in bad:
        with pytest.raises(ConfigError, match=match):
            call()


# ------------------------------------------------------------------ 8. age and emptiness


def test_elements_older_than_max_age_are_dropped():
    wake = ShedWake(max_age=0.055)  # N = 6 elements
    assert wake.n_elements == 6
    state = _hover(wake, TOP[None, None], 0.2, 0.01)
    np.testing.assert_allclose(np.sort(state.age[state.valid]), np.arange(6) * 0.01, atol=1e-12)
    moved = TOP[None, None] + [1.0, 0.0, 0.0]
    wake.step(state, 0.2, moved, np.zeros((1, 1, 3)), _level(1, 1))  # one long step, the leader elsewhere
    assert state.valid.sum() == 6 and state.age[state.valid].max() <= 0.055
    np.testing.assert_allclose(state.pos[state.valid][:, 0], 1.0)  # nothing shed before the step is left
    # a wake that is gone does not push: 3 m down, past the reach of a 0.1 s wake (~1 m)
    short = ShedWake(max_age=0.1)
    pos = np.array([[TOP, TOP - [0.0, 0.0, 3.0]]])
    state = _hover(short, pos, 0.5, 0.01)
    far = short.forces(state, pos, np.zeros((1, 2, 3)), _level(1, 2))[0, 0, 1]
    steady = MomentumWake()(pos[0, 0], np.zeros(3), np.eye(3), pos[0, 1], np.zeros(3))
    assert steady[2] < -1.0 and np.abs(far).max() < 1e-3


def test_an_empty_wake_and_the_air_above_a_rotor_plane_give_exactly_zero():
    wake = ShedWake()
    rng = np.random.default_rng(0)
    pos, vel = rng.normal(0, 0.3, (2, 3, 3)), rng.normal(0, 1.0, (2, 3, 3))
    state = wake.initial_state(2, 3)
    assert np.all(wake.forces(state, pos, vel, _level(2, 3)) == 0.0)
    assert np.all(wake.air_velocity(state, pos, _level(2, 3), rng.normal(0, 1, (2, 7, 3))) == 0.0)
    state = _hover(wake, np.array([[TOP, ASIDE]]), 0.5, 0.01)
    wake.reset(state)
    assert np.all(wake.forces(state, np.array([[TOP, TOP - [0, 0, 0.5]]]), vel[:1, :2], _level(1, 2)) == 0.0)
    state = _hover(wake, np.array([[TOP, ASIDE]]), 0.5, 0.01)
    above = np.array([[TOP, TOP + [0.05, 0.0, 0.3]]])
    assert np.all(wake.forces(state, above, vel[:1, :2], _level(1, 2)) == 0.0)
    assert isinstance(state, WakeState) and state.shape == (1, 2, wake.n_elements)
