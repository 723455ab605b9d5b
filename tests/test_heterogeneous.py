"""Vehicles of any kind: each vehicle's numbers through the loop, wakes that scale with their pair, the
mixed presets, and a scene of paper quads that flies bit for bit as before kinds existed."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controllers.autopilot import Autopilot
from downwash_core.errors import ConfigError
from downwash.guard_fused import FRACTION
from downwash_core.params import GRAVITY, QUAD
from downwash_core.status import Status
from downwash_core.vehicles import (CRAZYFLIE_2_1, PAPER_QUAD, VEHICLE_NAMES, VEHICLES, X500, airframe_area_scale,
                                    momentum_wake_kwargs, size_scale, so2_pair_scale, so2_strength_scale)
from downwash_trajectories import Hover, Lemniscate, stack
from sim.aggregation import make_aggregation
from sim.field import DownwashField, pairwise_field
from sim.fields.momentum import MomentumWake
from sim.flight import fly
from sim.metrics import tracking_metrics
from sim.predictor import OraclePredictor, PerWorldPredictor, ZeroPredictor
from sim.presets import make_preset
from sim.scene import build_scene, check_clearance
from sim.simulator import SimConfig, Simulator
from test_fast_path import _assert_same  # tests/ is on sys.path under pytest
from sim.vehicle_params import KindPairs, VehicleParams, collision_radii, pair_field, scene_field
from sim.wind import AIRFRAME, DrydenWind

LEADER = np.array([0.0, 0.0, 2.5])
MIXED = ("x500", "paper_quad", "crazyflie_2_1")  # top to bottom: every pair's factor differs from 1


def _mixed_reference(W: int, spacing: float = 0.6):
    """A hovering top vehicle and two beneath it on lemniscates through its axis."""
    return stack([Hover(LEADER, n_worlds=W),
                  Lemniscate(LEADER - [0, 0, spacing], half_length=0.3, half_width=0.15, period=10.0, n_worlds=W),
                  Lemniscate(LEADER - [0, 0, 2 * spacing], half_length=0.25, half_width=0.1, period=8.0, n_worlds=W)])


@pytest.fixture(scope="module")
def mixed():
    return build_scene(("alpha", "bravo", "charlie"), kinds=MIXED)


def _fly_both(scene, W, n_ticks, **components):
    """The rows of the fused and the readable path, and the two simulators."""
    out = []
    for fast in (True, False):
        sim = Simulator(scene, _mixed_reference(W), list(range(20, 20 + W)), fast=fast, **components)
        assert (sim._plan is not None) == fast, "the fused path was expected to apply"
        out.append(([dict(sim.tick()) for _ in range(n_ticks)], sim))
    return out


# ----------------------------------------------------------------------------- the two paths agree


@pytest.mark.parametrize("W", [1, 8])  # 8: a batch, in chunks on two threads on the fused path
def test_mixed_scene_fused_equals_readable(mixed, W):
    """Per-vehicle masses, drag, autopilot tables and per-pair wakes, with wind and an oracle predictor
    in some worlds: the fused tick flies the readable path's bits."""
    pred = PerWorldPredictor([ZeroPredictor(), OraclePredictor(DownwashField())], np.arange(W) % 2)
    wind = DrydenWind.preset("light", mean=(1.0, 0.5, 0.0))
    fused, readable = _fly_both(mixed, W, 60, predictor=pred, wind=wind, n_threads=2)
    _assert_same(fused, readable)
    rows, sim = fused
    field = np.stack([r["field_mean"] for r in rows])
    assert np.abs(field[..., 1:, 2]).max() > 0.1  # the wakes act on the vehicles below
    rel = rows[-1]["wind"] - rows[-1]["vel"]  # each vehicle's drag with its own gain
    want = sim.vehicle_params.drag_gain[:, None] * np.linalg.norm(rel, axis=-1, keepdims=True) * rel
    np.testing.assert_allclose(rows[-1]["wind_acc"], want, rtol=1e-12, atol=1e-15)


def test_a_guard_in_a_mixed_scene_flies_the_fused_path_with_its_state_where_the_scene_binds_it(mixed):
    """A guard among the conditions of a batch, in a scene of vehicle kinds: the scene tells it the kinds
    (a guard of its own), and the fused tick advances that guard's state, as the readable path does."""
    import copy

    from downwash.guard import GuardedPredictor
    from downwash.predictor import LearnedPredictor
    from downwash.registry import make_model
    from downwash.support import SUPPORT_FEATURES, Support

    F = len(SUPPORT_FEATURES)
    support = Support(np.full(F, -8.0), np.full(F, 8.0), np.full(F, 0.5))  # (every kind inside it)
    guard = GuardedPredictor(LearnedPredictor(make_model("equivariant_general")), support,
                             prior=1e12, fast_prior=1e12)  # (a monitor that trusts the untrained model:
    # the support alone acts)
    pred = PerWorldPredictor([ZeroPredictor(), guard], np.arange(4) % 2)
    sims = [Simulator(mixed, _mixed_reference(4), [20, 21, 22, 23], fast=fast, predictor=copy.deepcopy(pred))
            for fast in (True, False)]
    rows = [[dict(sim.tick()) for _ in range(30)] for sim in sims]
    for a, b in zip(*rows):
        for name in a:
            assert np.array_equal(a[name], b[name], equal_nan=True), name
    bound = sims[0]._scene_predictor.predictors[1]
    assert bound is not sims[0].predictor.predictors[1] and bound.vehicle_kinds == tuple(k.name for k in mixed.kinds)
    fractions = bound._state[..., FRACTION:FRACTION + 2]
    assert sims[0]._plan is not None and np.all(fractions.max(-1) > 0)  # its state advanced on the fused path
    assert np.all(bound._seen_t > 0)  # and its monitor watched the flight
    assert np.all(np.isnan(rows[0][-1]["applied"][::2])) and np.all(rows[0][-1]["applied"][1::2] > 0)


def test_mixed_scene_fused_equals_readable_with_the_oracle_and_no_wind(mixed):
    _assert_same(*_fly_both(mixed, 1, 40, predictor=OraclePredictor(DownwashField(swirl=0.2)),
                            field=DownwashField(swirl=0.2)))


def test_the_oracle_predicts_what_the_scene_feels(mixed):
    """An oracle in a mixed scene scales each pair as the truth does: at the first tick (held from
    the first autopilot tick, no wind) its prediction is the mean field, on both paths."""
    for fast in (True, False):
        sim = Simulator(mixed, _mixed_reference(2), [1, 2], predictor=OraclePredictor(DownwashField()), fast=fast)
        row = sim.tick()
        assert np.array_equal(row["f_hat"], row["field_mean"])
        sim.tick()
        assert np.abs(sim.f_hat[:, 1:, 2]).max() > 0.0


def test_mixed_scene_batched_equals_serial():
    """mixed_formation under the non-linear velocity law (the pair forces scaled per pair) with wind:
    world k of a batch of 3 is, bit for bit, the flight of seed k alone."""
    p = make_preset("mixed_formation")
    kw = dict(aggregation=make_aggregation("velocity"), wind=DrydenWind.preset("light", mean=(1.0, 0.0, 0.0)))
    batch = fly(p.scene(), p.reference(3), [5, 6, 7], 1.0, **kw)
    for k, seed in enumerate([5, 6, 7]):
        alone = fly(p.scene(), p.reference(1), [seed], 1.0, **kw)[0]
        for name, array in alone.arrays.items():
            np.testing.assert_array_equal(batch[k][name], array, err_msg=name)
    assert np.abs(batch[0]["field_mean"][:, 1:]).max() > 0.05


# ----------------------------------------------------------------------------- each vehicle's numbers


def test_each_vehicle_flies_its_own_numbers(mixed):
    sim = Simulator(mixed, _mixed_reference(2), [0, 1])
    vp = sim.vehicle_params
    assert vp.names == MIXED
    np.testing.assert_array_equal(vp.mass, [X500.mass, QUAD.mass, CRAZYFLIE_2_1.mass])
    np.testing.assert_array_equal(sim._mass_believed, np.tile(vp.mass, (2, 1)))
    for i, kind in enumerate((X500, PAPER_QUAD, CRAZYFLIE_2_1)):
        np.testing.assert_array_equal(sim._ap_gain[i], Autopilot(kind).gain)
        assert sim._max_thrust[i] == kind.max_rotor_thrust
        area = AIRFRAME.reference_area * (kind.arm_length / QUAD.arm_length) ** 2
        assert vp.drag_gain[i] == pytest.approx(1.225 * 1.0 * area / (2 * kind.mass), rel=1e-14)
        # every rotor at its kind's hover thrust at reset
        np.testing.assert_array_equal(sim.physics.ctrl[:, mixed.act_ids[i]], kind.hover_rotor_thrust)
        np.testing.assert_array_equal(sim.physics.act[:, mixed.act_ids[i]], kind.hover_rotor_thrust)
    assert vp.drag_gain[1] == AIRFRAME.gain(QUAD.mass)  # the paper quad's, exactly


@pytest.mark.parametrize("name", VEHICLE_NAMES)
def test_each_kind_hovers_alone_on_its_own_hover_thrust(name):
    """One vehicle of each kind, default SimConfig: it starts at its own hover thrust and holds its point."""
    kind = VEHICLES[name]
    scene = build_scene(["solo"], kinds=name)
    sim = Simulator(scene, stack([Hover([0.5, -0.3, 1.5], n_worlds=2)]), [3, 4])
    np.testing.assert_array_equal(sim.physics.ctrl, kind.hover_rotor_thrust)
    for _ in range(150):  # 3 s
        sim.tick()
    assert sim.active.all()
    pos = sim.true_states().pos[:, 0]
    assert np.abs(pos - [0.5, -0.3, 1.5]).max() < 0.01
    # the rotors hold the weight: thrust at hover within the noise, well inside the kind's limit
    np.testing.assert_allclose(sim.physics.ctrl.mean(), kind.hover_rotor_thrust, rtol=0.05)
    assert sim.physics.ctrl.max() < kind.max_rotor_thrust


def test_collision_ellipsoid_scales_with_the_pair():
    """An X500 and a paper quad 0.45 m apart at one height collide (their radius 0.52 m), two paper quads
    0.45 m apart do not (0.26 m); check_clearance refuses such a start with the pair's radii."""
    xy, z = collision_radii((X500.params, QUAD), 0.26, 0.08)
    assert xy[1, 1] == 0.26 and z[1, 1] == 0.08  # two paper quads: SimConfig's, exactly
    assert xy[0, 1] == pytest.approx(0.26 * (size_scale(X500) + 1.0) / 2) and xy[0, 1] == xy[1, 0] > 0.5
    ref = stack([Hover(LEADER, n_worlds=1), Hover(LEADER + [0.45, 0, 0], n_worlds=1)])
    for kinds, status in ((("x500", "paper_quad"), Status.VEHICLE), (None, Status.OK)):
        sim = Simulator(build_scene(kinds=kinds), ref, [0], field_enabled=np.zeros(1, bool))
        sim.tick()
        assert sim.status[0] == status, kinds
    with pytest.raises(ConfigError, match="start inside each other"):
        check_clearance(ref(np.zeros(1)).pos, ["a", "b"], xy, z)


# ----------------------------------------------------------------------------- wakes between kinds


def test_pair_scaling_is_exactly_one_for_a_pair_of_one_kind():
    for kind in VEHICLES.values():
        assert so2_pair_scale(kind, kind) == 1.0
    assert airframe_area_scale(PAPER_QUAD) == 1.0 and size_scale(PAPER_QUAD) == 1.0
    so2, momentum = DownwashField(), MomentumWake()
    assert pair_field(so2, QUAD, QUAD) is so2 and pair_field(momentum, PAPER_QUAD, PAPER_QUAD) is momentum
    assert pair_field(so2, CRAZYFLIE_2_1, CRAZYFLIE_2_1) is so2  # the paper's law: the same pair, the same push
    vp = VehicleParams.of(build_scene(), SimConfig())
    assert scene_field(so2, vp) is so2 and scene_field(momentum, vp) is momentum
    assert np.array_equal(vp.field_scale, np.ones((2, 2)))


def test_the_documented_so2_pair_law_by_hand():
    """scale = (m_l / m_f) min(1, A_f / A_l); a paper-quad follower under a larger-disc leader gets the
    stated disc-loading scaling, under a smaller one the thrust ratio."""
    for a in VEHICLES.values():
        for b in VEHICLES.values():
            by_hand = a.mass / b.mass * min(1.0, (b.rotor_radius / a.rotor_radius) ** 2)
            assert so2_pair_scale(a, b) == pytest.approx(by_hand, rel=1e-13)
    assert so2_pair_scale(X500, PAPER_QUAD) == pytest.approx(so2_strength_scale(X500), rel=1e-13)
    assert so2_pair_scale(CRAZYFLIE_2_1, PAPER_QUAD) == pytest.approx(so2_strength_scale(CRAZYFLIE_2_1, basis="thrust"))
    assert so2_pair_scale(X500, CRAZYFLIE_2_1) == pytest.approx(1.841, abs=1e-3)
    assert so2_pair_scale(PAPER_QUAD, CRAZYFLIE_2_1) == pytest.approx(7.606, abs=1e-3)


def _first_field(scene, positions, field):
    """The simulator's mean field at the first tick, the vehicles hovering level at `positions` (V, 3)."""
    ref = stack([Hover(p, n_worlds=1) for p in positions])
    sim = Simulator(scene, ref, [0], field=field, turbulence=None)
    return sim.tick()["field_mean"][0]


def test_a_crazyflie_under_an_x500_feels_the_documented_scaling():
    """Through the simulator, a follower straight below a leader: the paper's law times so2_pair_scale.
    A Crazyflie under an X500 feels 1.84 the paper pair's push, 7.6 times what a paper quad feels under
    the same X500; under a paper quad (whose 0.04 m rotors load their discs 4x as heavily as the X500's)
    it feels 7.6 the pair's."""
    depth = 0.8
    positions = [LEADER, LEADER - [0, 0, depth]]
    base = DownwashField()(LEADER, np.zeros(3), np.eye(3), positions[1], np.zeros(3))
    felt = {}
    for leader in ("x500", "paper_quad"):
        for follower in ("crazyflie_2_1", "paper_quad"):
            got = _first_field(build_scene(kinds=[leader, follower]), positions, DownwashField())[1]
            scale = so2_pair_scale(VEHICLES[leader], VEHICLES[follower])
            np.testing.assert_allclose(got, scale * base, rtol=1e-12, atol=1e-15)
            felt[leader, follower] = -got[2]
    assert felt["x500", "crazyflie_2_1"] > 7 * felt["x500", "paper_quad"] > 0
    assert felt["x500", "crazyflie_2_1"] == pytest.approx(1.841 * felt["paper_quad", "paper_quad"], rel=1e-3)
    assert felt["paper_quad", "crazyflie_2_1"] == pytest.approx(7.606 * felt["paper_quad", "paper_quad"], rel=1e-3)


def test_momentum_pairs_take_each_vehicles_numbers():
    """Under momentum each pair is the field of its kinds (momentum_wake_kwargs, the follower's drag area
    scaled: momentum_drag_area_scale); a Crazyflie's rotors (v_h 4.3 m/s) lose more thrust in an X500's stream than a paper quad's
    (11.8 m/s): it is pushed several times as hard."""
    field = MomentumWake()
    paired = pair_field(field, X500, CRAZYFLIE_2_1)
    assert paired == MomentumWake(**momentum_wake_kwargs(X500, CRAZYFLIE_2_1),
                                  drag_area=field.drag_area * airframe_area_scale(CRAZYFLIE_2_1))  # all of it in the wake
    big = pair_field(field, PAPER_QUAD, X500)  # an X500's airframe under a paper quad's narrow jet: capped
    assert big.drag_area == pytest.approx(0.01 * (X500.arm_length / 0.09) ** 2 * (0.04 / X500.rotor_radius) ** 2)
    depth = 0.8
    positions = [LEADER, LEADER - [0, 0, depth]]
    felt = {}
    for follower in ("crazyflie_2_1", "paper_quad"):
        got = _first_field(build_scene(kinds=["x500", follower]), positions, field)[1]
        want = pair_field(field, X500, VEHICLES[follower])(LEADER, np.zeros(3), np.eye(3), positions[1], np.zeros(3))
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
        felt[follower] = -got[2]
    # rotors alone, by hand: the X500's near-wake axis speed over each follower's hover induced velocity
    U = pair_field(field, X500, PAPER_QUAD).centreline(depth, X500.mass * GRAVITY)[0]
    assert felt["crazyflie_2_1"] > 3 * felt["paper_quad"] > 0 and 9.0 < U < 12.0


# docs/fields.md, "Vehicles of other kinds": a follower at rest on the axis of a hovering leader, z (m/s^2)
DOCUMENTED_PUSH = {  # (leader, follower): {(field, depth m): z}
    ("paper_quad", "paper_quad"): {("so2", 0.5): -3.01, ("so2", 1.0): -1.40, ("momentum", 0.5): -5.91,
                                   ("momentum", 1.0): -4.12},
    ("paper_quad", "crazyflie_2_1"): {("so2", 0.5): -22.9, ("so2", 1.0): -10.6, ("momentum", 0.5): -31.0,
                                      ("momentum", 1.0): -17.6, ("momentum", 2.0): -7.84},
    ("x500", "crazyflie_2_1"): {("so2", 0.5): -5.54, ("so2", 1.0): -2.57, ("momentum", 0.5): -12.0,
                                ("momentum", 1.0): -12.6, ("momentum", 2.0): -11.2},
    ("x500", "paper_quad"): {("so2", 0.5): -0.73, ("so2", 1.0): -0.34, ("momentum", 0.5): -3.54,
                             ("momentum", 1.0): -3.71},
    ("paper_quad", "x500"): {("so2", 0.5): -1.02, ("so2", 1.0): -0.47, ("momentum", 0.5): -1.09,
                             ("momentum", 1.0): -1.02},
}


def test_the_documented_pushes_between_kinds():
    """The table of docs/fields.md, from the pair fields; far below (2 m) the X500's still contracting jet
    pushes a Crazyflie harder than the paper quad's decayed one (momentum), never under so2 (0.242)."""
    fields = {"so2": DownwashField(), "momentum": MomentumWake()}
    for (leader, follower), values in DOCUMENTED_PUSH.items():
        for (name, depth), z in values.items():
            f = pair_field(fields[name], VEHICLES[leader], VEHICLES[follower])
            got = f(LEADER, np.zeros(3), np.eye(3), LEADER - [0, 0, depth], np.zeros(3))
            assert got[2] == pytest.approx(z, abs=0.006 if abs(z) < 10 else 0.06), (leader, follower, name, depth)
            np.testing.assert_allclose(got[:2], 0.0, atol=1e-12)
    push = DOCUMENTED_PUSH
    assert push["x500", "crazyflie_2_1"]["momentum", 2.0] < push["paper_quad", "crazyflie_2_1"]["momentum", 2.0]
    assert push["x500", "crazyflie_2_1"]["so2", 1.0] > push["paper_quad", "crazyflie_2_1"]["so2", 1.0]


def test_kind_pairs_broadcast_evaluation_matches_the_compiled_one(mixed):
    """KindPairs of a DownwashField with per-world constants (no compiled form) takes each pair's field
    on the broadcast pair batch: the compiled per-pair kernel's numbers, to rounding."""
    vp = VehicleParams.of(mixed, SimConfig())
    rng = np.random.default_rng(0)
    pos = LEADER + rng.normal(scale=0.3, size=(4, 3, 3)) - np.array([0, 0, 0.5]) * np.arange(3)[:, None]
    vel = rng.normal(scale=0.3, size=(4, 3, 3))
    rot = np.broadcast_to(np.eye(3), (4, 3, 3, 3)).copy()
    compiled = pairwise_field(KindPairs(DownwashField(), vp), pos, vel, rot)
    per_world = DownwashField(strength=np.full((4, 1, 1), DownwashField().strength))
    broadcast = pairwise_field(KindPairs(per_world, vp), pos, vel, rot)
    np.testing.assert_allclose(broadcast, compiled, rtol=1e-12, atol=1e-13)
    assert np.abs(compiled).max() > 0.1


def test_a_field_without_kind_scaling_is_refused_in_a_mixed_scene_and_for_kinds_is_used(mixed):
    class Mine:
        def __call__(self, p_a, v_a, R_a, p_b, v_b):
            return np.zeros(np.broadcast_shapes(p_a.shape, p_b.shape))

    with pytest.raises(ConfigError, match=r"field Mine: no scaling for a x500 leader and a x500 follower; .*"
                                          r"DownwashField, .*MomentumWake, or a field with for_kinds"):
        Simulator(mixed, _mixed_reference(1), [0], field=Mine())
    pair = stack([Hover(LEADER, n_worlds=1), Hover(LEADER - [0, 0, 0.6], n_worlds=1)])
    assert Simulator(build_scene(), pair, [0], field=Mine())._scene_field is not None  # paper quads: as given

    class Scaled(Mine):
        def for_kinds(self, leader, follower):
            return self

    sim = Simulator(mixed, _mixed_reference(1), [0], field=Scaled())
    sim.tick()
    assert sim.active.all()


# ----------------------------------------------------------------------------- a scene of paper quads


def test_a_scene_of_paper_quads_is_bit_identical_whatever_says_so():
    """No kinds, kinds='paper_quad', a Scene without kinds and SimConfig(quad=QUAD): the same flight, bit
    for bit, with the fields flown as given (no wrapper, factors exactly 1.0)."""
    ref = stack([Hover(LEADER, n_worlds=2), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=2)])
    default = build_scene()
    scenes = [default, build_scene(kinds="paper_quad"), dataclasses.replace(default, kinds=())]
    logs = []
    for scene, config in zip(scenes + [default], [None, None, SimConfig(quad=QUAD), SimConfig(quad=QUAD)]):
        sim = Simulator(scene, ref, [1, 2], config=config)
        assert sim._scene_field is sim.field and sim._scene_predictor is sim.predictor
        assert sim.vehicle_params.names == ("paper_quad", "paper_quad")
        logs.append(fly(scene, ref, [1, 2], 1.0, config=config, predictor=OraclePredictor(DownwashField())))
    for other in logs[1:]:
        for a, b in zip(logs[0], other):
            for name in a.arrays:
                np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert "kinds" not in logs[0][0].meta and "kinds" not in logs[0][0].meta["scene"]


# ----------------------------------------------------------------------------- presets, logs, names


@pytest.mark.parametrize("spec, field", [("heavy_over_light", "so2"), ("heavy_over_light", "momentum"),
                                         ("crazyflie_stack", "so2"), ("mixed_formation", "so2")])
def test_mixed_presets_start_clear_and_fly_stably(spec, field):
    """Baseline controller, the field: no crash over the preset's duration, finite, tracking bounded (the
    baseline's error on the paper pair is 0.34 m mean, 0.56 m at most)."""
    from sim.fields.registry import make_field

    p = make_preset(spec)
    assert p.kinds and p.n_vehicles == len(p.kinds)
    names = [n for n, _ in p.vehicles]
    xy, z = p.collision_radii()
    ref = p.reference(2)
    for t in np.linspace(0.0, p.duration, 201):  # the references keep apart by the pairs' ellipsoids
        pos = ref(np.full(2, t)).pos
        check_clearance(pos, names, xy, z)
        assert pos[..., 2].min() >= 0.5
    logs = fly(p.scene(), ref, [11, 12], p.duration, field=make_field(field))
    for log in logs:
        assert log.meta["status_name"] == "ok", log.meta["message"]
        assert len(log) == round(p.duration / 0.02)
        assert all(np.isfinite(a).all() for a in log.arrays.values())
        err = np.linalg.norm(log["pos"] - log["ref_pos"], axis=-1)
        assert err.max() < 1.2 and err.mean() < 0.4, (err.max(0), err.mean(0))
        assert log["pos"][..., 2].min() > 0.3
    assert np.abs(logs[0]["field_mean"][:, 1:, 2]).max() > 0.3  # the wakes reach the vehicles below


def test_a_mixed_flight_log_names_the_kinds_and_its_metrics_work_per_vehicle():
    p = make_preset("heavy_over_light")
    log = fly(p.scene(), p.reference(1), [3], 0.5)[0]
    assert log.meta["kinds"] == ["x500", "paper_quad"]
    assert [k["name"] for k in log.meta["scene"]["kinds"]] == ["x500", "paper_quad"]
    assert log.meta["scene"]["kinds"][0]["mass"] == X500.mass
    for vehicle in (0, 1):
        metrics = tracking_metrics(log, vehicle)
        assert all(math.isfinite(v) for v in metrics.values())


def test_bad_kind_names_are_refused_naming_the_allowed_ones():
    allowed = "allowed: paper_quad, crazyflie_2_1, x500, crazyflie_large"
    with pytest.raises(ConfigError, match=f"vehicle: unknown 'hexa'; {allowed}"):
        build_scene(kinds=["x500", "hexa"])
    with pytest.raises(ConfigError, match=f"vehicle: unknown 'cf2'; {allowed}"):
        make_preset("pair").with_kinds(["cf2", "x500"])
    with pytest.raises(ConfigError, match=f"vehicle: unknown 'X500'; {allowed}"):
        VehicleParams.of(build_scene(kinds=["X500", "x500"]), SimConfig())
    with pytest.raises(ConfigError, match="allowed: pair, .*heavy_over_light, crazyflie_stack, mixed_formation"):
        make_preset("heavy")
    with pytest.raises(ConfigError, match="separation: allowed 0.6-2.0 m"):
        make_preset("heavy_over_light:separation=0.3")
