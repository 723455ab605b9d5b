"""Vehicle kinds: the registry, each kind's physics, scenes of mixed kinds, the wake scaling."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, QUAD, QuadParams
from downwash_core.vehicles import (CRAZYFLIE_2_1, DEFAULT_VEHICLE, PAPER_QUAD, VEHICLE_NAMES, VEHICLES,
                                    X500, VehicleKind, get_vehicle, hover_induced_velocity, momentum_wake_kwargs,
                                    so2_strength_scale)
from sim.scene import build_scene, resolve_kinds

ROOT = Path(__file__).resolve().parents[1]
KINDS = list(VEHICLES.values())
MIXED_PRESETS = ("heavy_over_light", "crazyflie_stack", "mixed_formation")


# ----------------------------------------------------------------------------- the registry


def test_registry_names_and_lookups():
    assert VEHICLE_NAMES == ("paper_quad", "crazyflie_2_1", "x500", "crazyflie_large") == tuple(VEHICLES)
    assert DEFAULT_VEHICLE == "paper_quad"
    for name, kind in VEHICLES.items():
        assert kind.name == name and get_vehicle(name) is kind and get_vehicle(kind) is kind
    assert get_vehicle(" x500 ") is X500
    with pytest.raises(TypeError):
        VEHICLES["mine"] = PAPER_QUAD  # read-only


@pytest.mark.parametrize("bad", ["crazyflie", "", None, 3, "PAPER_QUAD"])
def test_unknown_vehicle_names_the_allowed_ones(bad):
    with pytest.raises(ConfigError, match=r"vehicle: unknown .*; allowed: paper_quad, crazyflie_2_1, x500, crazyflie_large"):
        get_vehicle(bad)


def test_static_copies_match_the_registry():
    from experiments import vehicles as experiment

    assert experiment.VEHICLE_NAMES == VEHICLE_NAMES


def test_paper_quad_is_quad_bit_for_bit():
    for f in dataclasses.fields(QuadParams):
        assert getattr(PAPER_QUAD, f.name) is getattr(QUAD, f.name), f.name  # the same float objects
    assert PAPER_QUAD.params == QUAD
    for prop in ("weight", "max_rotor_thrust", "hover_rotor_thrust", "diagonal"):
        assert getattr(PAPER_QUAD, prop) == getattr(QUAD, prop), prop


# ----------------------------------------------------------------------------- each kind's physics


@pytest.mark.parametrize("kind", KINDS, ids=VEHICLE_NAMES)
def test_each_kind_is_physically_sane(kind):
    assert 0 < kind.hover_rotor_thrust < kind.max_rotor_thrust  # it can hover, with margin to steer
    assert 1.2 < kind.thrust_to_weight < 5
    assert kind.max_rotor_thrust == pytest.approx(kind.thrust_to_weight * kind.mass * GRAVITY / 4, rel=1e-15)
    ixx, iyy, izz = kind.inertia
    assert ixx + iyy >= izz and iyy < izz  # a flat X quadrotor: yaw has the largest moment
    assert 2 * kind.rotor_radius <= kind.arm_length * math.sqrt(2)  # neighbouring discs do not overlap
    assert 0.005 < kind.motor_time_constant < 0.2
    assert 0 < kind.yaw_moment_coeff < 0.05
    # every number sourced: a summary line, then a line naming each field
    assert kind.source.strip() and kind.short_source and len(kind.source.strip().splitlines()) >= 6
    for f in ("mass", "arm_length", "inertia", "rotor_radius", "thrust_to_weight", "motor_time_constant",
              "yaw_moment_coeff"):
        assert f in kind.source, f"{kind.name}: {f} not in the source"
    assert set(kind.estimated) <= {f.name for f in dataclasses.fields(QuadParams)}
    record = kind.describe()
    json.dumps(record)  # results.json ready
    assert record["name"] == kind.name and record["source"] == kind.source


def test_crazyflie_numbers_from_drone_models():
    cf = CRAZYFLIE_2_1
    assert 0.027 <= cf.mass <= 0.034
    assert cf.mass == 0.0319 and cf.max_rotor_thrust == pytest.approx(0.12, rel=1e-12)
    assert cf.arm_length == pytest.approx(0.046, abs=1e-4)  # 92 mm motor to motor
    np.testing.assert_allclose(cf.params.rotor_positions[0], [0.03253, 0.03253, 0.0], rtol=1e-12)
    assert cf.inertia == (16.8e-6, 16.8e-6, 29.8e-6)
    np.testing.assert_allclose(cf.inertia, (16.571710e-6, 16.655602e-6, 29.261652e-6), rtol=0.02)  # Foerster 2015
    assert cf.motor_time_constant == 0.0858607 and cf.yaw_moment_coeff == pytest.approx(0.00735, rel=1e-3)
    assert "drone-models" in cf.source and "cf2x_L250" in cf.source and "Foerster 2015" in cf.source


def test_thrust_maps_of_the_logged_crazyflies():
    """The Neural-Swarm data set's thrust maps: the polynomial by hand at one point, the large frame's
    thrust-to-weight from its map at full PWM on a full battery, and only kinds with a map describe one."""
    small, large = VEHICLES["crazyflie_2_1"], VEHICLES["crazyflie_large"]
    m = small.thrust_map
    p, v = 40000 / 65536, 3.9 / 4.2
    grams = m.c00 + m.c10 * p + m.c01 * v + m.c20 * p * p + m.c11 * p * v
    np.testing.assert_allclose(m.thrust(np.full((2, 4), 40000.0), np.full(2, 3.9)), grams * 1e-3 * GRAVITY, rtol=1e-14)
    full = float(large.thrust_map.thrust(65535.0, 4.2)[0])
    assert large.thrust_to_weight == pytest.approx(4 * full / (0.067 * GRAVITY), rel=1e-12) and large.mass == 0.067
    assert {"arm_length", "rotor_radius", "inertia"} <= set(large.estimated)
    assert large.describe()["thrust_map"]["source"].endswith("the large frame")
    assert "thrust_map" not in PAPER_QUAD.describe() and "thrust_map" not in X500.describe()


def test_x500_numbers_from_px4_model():
    x = X500
    assert 1.5 <= x.mass <= 2.5 and x.mass == pytest.approx(2.0 + 4 * 0.016076923076923075, rel=1e-15)
    assert x.arm_length == pytest.approx(0.246, abs=1e-3) and x.max_rotor_thrust == pytest.approx(8.54858, rel=1e-12)
    assert x.inertia[0] > 0.02166666666666667 and x.inertia[2] > 0.04  # the rotors add to the base link's
    np.testing.assert_allclose(x.inertia, (0.02389, 0.02389, 0.04400), rtol=1e-3)
    assert {"inertia", "motor_time_constant"} <= set(x.estimated) and "estimated" in x.source
    assert "PX4-gazebo-models" in x.source


# ----------------------------------------------------------------------------- checks on construction


def _kind(**change):
    values = {f.name: getattr(PAPER_QUAD, f.name) for f in dataclasses.fields(VehicleKind)}
    values.update({"name": "mine", **change})
    return VehicleKind(**values)


@pytest.mark.parametrize("change, words", [
    ({"mass": -1.0}, "mass: expected a finite number > 0"),
    ({"mass": float("nan")}, "mass: expected a finite number > 0"),
    ({"mass": True}, "mass: expected a finite number > 0"),
    ({"arm_length": 0.0}, "arm_length: expected a finite number > 0"),
    ({"rotor_radius": float("inf")}, "rotor_radius: expected a finite number > 0"),
    ({"motor_time_constant": "0.03"}, "motor_time_constant: expected a finite number > 0"),
    ({"motor_time_constant": 2.0}, "motor_time_constant: got 2.0; allowed (0, 1) s"),
    ({"thrust_to_weight": 1.0}, "thrust_to_weight: got 1.0; allowed > 1"),
    ({"thrust_to_weight": 0.8}, "thrust_to_weight: got 0.8; allowed > 1"),
    ({"inertia": (1e-3, 1e-3)}, "inertia: expected 3 numbers"),
    ({"inertia": (1e-3, 1e-3, -1e-3)}, "inertia z: expected a finite number > 0"),
    ({"inertia": (1e-3, 1e-3, 3e-3)}, "triangle inequality"),
    ({"rotor_radius": 0.07}, "neighbouring rotors"),
    ({"source": "  "}, "source: expected where the numbers come from"),
    ({"estimated": ("colour",)}, "estimated: unknown fields ['colour']"),
    ({"name": "Big Quad"}, "vehicle name: expected lower case"),
])
def test_bad_numbers_are_refused_naming_them(change, words):
    with pytest.raises(ConfigError) as e:
        _kind(**change)
    assert words in str(e.value), str(e.value)
    if "name" not in change:
        assert str(e.value).startswith("vehicle 'mine': ")


def test_inertia_list_becomes_a_tuple():
    assert _kind(inertia=[1e-3, 1e-3, 2e-3]).inertia == (1e-3, 1e-3, 2e-3)


# ----------------------------------------------------------------------------- scenes


def _model_bytes(model) -> bytes:
    buf = np.zeros(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buf)
    return buf.tobytes()


def _scene_xml(monkeypatch, **kwargs) -> str:
    """The MJCF of the scene `build_scene(**kwargs)` compiles (captured at compile)."""
    captured = []
    compile_ = mujoco.MjSpec.compile

    def capture(spec, *a, **k):
        captured.append(spec.to_xml())
        return compile_(spec, *a, **k)

    with monkeypatch.context() as m:
        m.setattr(mujoco.MjSpec, "compile", capture)
        build_scene(**kwargs)
    return captured[-1]


def test_default_scene_is_unchanged(monkeypatch):
    """No kinds, kinds='paper_quad' and one paper_quad per vehicle: the same MJCF, byte for byte, with the
    vehicle file's numbers as written (not rewritten from QUAD: its ctrlrange stays the file's 3.9485)."""
    xml = _scene_xml(monkeypatch)
    assert xml == _scene_xml(monkeypatch, kinds="paper_quad")
    assert xml == _scene_xml(monkeypatch, kinds=[PAPER_QUAD, "paper_quad"])
    assert 'ctrlrange="0 3.9485"' in xml and 'mass="0.7"' in xml and "3.94852" not in xml
    default = build_scene()
    assert _model_bytes(default.model) == _model_bytes(build_scene(kinds=["paper_quad", "paper_quad"]).model)
    assert default.kinds == (PAPER_QUAD, PAPER_QUAD)
    assert "kinds" not in default.describe()  # provenance as before kinds existed
    assert set(default.describe()) == {"vehicles", "roles", "quad_xml_sha256", "timestep"}


@pytest.fixture(scope="module")
def mixed():
    return build_scene(("alpha", "bravo", "charlie"), kinds=["x500", "paper_quad", "crazyflie_2_1"])


def test_scene_of_mixed_kinds_carries_each_kinds_numbers(mixed):
    m = mixed.model
    for v, kind in enumerate((X500, PAPER_QUAD, CRAZYFLIE_2_1)):
        assert mixed.kinds[v] is kind
        b = mixed.body_ids[v]
        assert m.body_mass[b] == pytest.approx(kind.mass, rel=1e-12)
        assert m.body_subtreemass[b] == pytest.approx(kind.mass, rel=1e-12)  # the geoms carry no mass
        np.testing.assert_allclose(m.body_inertia[b], kind.inertia, rtol=1e-12)
        for k, a in enumerate(mixed.act_ids[v]):
            site = m.actuator_trnid[a, 0]
            np.testing.assert_allclose(m.site_pos[site], kind.params.rotor_positions[k], atol=1e-5)
            np.testing.assert_allclose(m.actuator_ctrlrange[a], [0.0, kind.max_rotor_thrust], rtol=1e-4, atol=1e-12)
            np.testing.assert_allclose(m.actuator_actrange[a], [0.0, kind.max_rotor_thrust], rtol=1e-4, atol=1e-12)
            assert m.actuator_dynprm[a, 0] == pytest.approx(kind.motor_time_constant)
            assert m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_FILTER
            np.testing.assert_allclose(m.actuator_gear[a], [0, 0, 1, 0, 0, QUAD.rotor_spin[k] * kind.yaw_moment_coeff],
                                       rtol=1e-12)
        prefix = mixed.vehicles[v]
        assert m.geom(f"{prefix}/prop0").size[0] == pytest.approx(kind.rotor_radius)
    names = [n for n, _ in zip(mixed.vehicles, mixed.roles)]
    assert mixed.describe()["kinds"][0]["name"] == "x500" and len(mixed.describe()["kinds"]) == len(names)


def test_every_kind_hovers_at_its_hover_thrust(mixed):
    """Each vehicle at its own hover thrust holds still: mass, rotor sites and actuators agree."""
    d = mujoco.MjData(mixed.model)
    d.qpos[mixed.qpos_adr[:, None] + np.arange(3)] = [[0, 0, 2.0], [2, 0, 2.0], [4, 0, 2.0]]
    for v, kind in enumerate(mixed.kinds):
        d.act[mixed.act_ids[v]] = d.ctrl[mixed.act_ids[v]] = kind.hover_rotor_thrust
    for _ in range(250):
        mujoco.mj_step(mixed.model, d)
    np.testing.assert_allclose(d.qpos[mixed.qpos_adr + 2], 2.0, atol=1e-6)
    np.testing.assert_allclose(d.qvel[mixed.qvel_adr[:, None] + np.arange(6)], 0.0, atol=1e-6)


def test_rotor_commands_are_clipped_at_each_kinds_limit(mixed):
    """Every rotor commanded the paper quad's hover thrust: the Crazyflie's rotors settle at their
    0.12 N limit and it climbs at (T/W - 1) g; the others' limits are above the command."""
    d = mujoco.MjData(mixed.model)
    d.qpos[mixed.qpos_adr[:, None] + np.arange(3)] = [[0, 0, 2.0], [2, 0, 2.0], [4, 0, 2.0]]
    d.ctrl[:] = QUAD.hover_rotor_thrust
    for _ in range(int(1.0 / mixed.model.opt.timestep)):  # 1 s, > 11 motor time constants of the slowest
        mujoco.mj_step(mixed.model, d)
    cf = 2
    np.testing.assert_allclose(d.act[mixed.act_ids[cf]], CRAZYFLIE_2_1.max_rotor_thrust, rtol=1e-4)
    np.testing.assert_allclose(d.act[mixed.act_ids[:2]], QUAD.hover_rotor_thrust, rtol=1e-4)
    d.act[mixed.act_ids[cf]] = CRAZYFLIE_2_1.max_rotor_thrust
    mujoco.mj_forward(mixed.model, d)
    assert d.qacc[mixed.qvel_adr[cf] + 2] == pytest.approx((CRAZYFLIE_2_1.thrust_to_weight - 1) * GRAVITY, rel=1e-9)


def test_kinds_argument_is_checked():
    with pytest.raises(ConfigError, match=r"kinds: expected one per vehicle \(2\), got 3"):
        build_scene(kinds=["x500", "x500", "x500"])
    with pytest.raises(ConfigError, match="vehicle: unknown 'hexa'"):
        build_scene(kinds=["x500", "hexa"])
    with pytest.raises(ConfigError, match="kinds: expected a vehicle name"):
        resolve_kinds(3, 2)
    assert resolve_kinds(None, 3) == (PAPER_QUAD,) * 3 and resolve_kinds(X500, 2) == (X500, X500)
    fast = _kind(motor_time_constant=0.001)
    with pytest.raises(ConfigError, match="motor_time_constant 0.001 s: allowed above the physics step"):
        build_scene(kinds=fast)


def test_a_custom_kind_builds_without_registering():
    big = _kind(mass=1.4, inertia=(5e-3, 5e-3, 9e-3))
    scene = build_scene(kinds=[PAPER_QUAD, big])
    assert scene.model.body_mass[scene.body_ids].tolist() == pytest.approx([0.7, 1.4])


def test_presets_take_kinds_without_changing_the_built_in_ones():
    from sim.presets import PRESETS, make_preset

    for name in PRESETS:
        preset = make_preset("stack:n=5" if name == "stack" else name)
        if name in MIXED_PRESETS:  # the presets of other kinds name them
            assert preset.kinds and preset.describe()["kinds"] == list(preset.kinds)
            continue
        assert preset.kinds == () and "kinds" not in preset.describe()
        assert preset.with_kinds("paper_quad") == preset
    stack = make_preset("stack3").with_kinds(["x500", "paper_quad", "crazyflie_2_1"])
    assert stack.kinds == ("x500", "paper_quad", "crazyflie_2_1") and stack.describe()["kinds"] == list(stack.kinds)
    scene = stack.scene()
    assert scene.model.body_mass[scene.body_ids].tolist() == pytest.approx([X500.mass, 0.7, 0.0319])
    with pytest.raises(ConfigError, match=r"kinds: expected one per vehicle \(3\)"):
        make_preset("stack3").with_kinds(["x500"])
    with pytest.raises(ConfigError, match="a preset takes registered vehicle names"):
        make_preset("pair").with_kinds(_kind())


# ----------------------------------------------------------------------------- wake scaling


@pytest.mark.parametrize("kind", KINDS, ids=VEHICLE_NAMES)
def test_hover_induced_velocity_by_hand(kind):
    by_hand = math.sqrt(kind.mass * 9.81 / (2 * 1.225 * 4 * math.pi * kind.rotor_radius**2))
    assert hover_induced_velocity(kind) == pytest.approx(by_hand, rel=1e-14)
    assert kind.hover_induced_velocity() == hover_induced_velocity(kind.name)
    assert kind.disc_loading == pytest.approx(kind.mass * 9.81 / (4 * math.pi * kind.rotor_radius**2), rel=1e-14)
    with pytest.raises(ConfigError, match="air_density"):
        hover_induced_velocity(kind, 0.0)


def test_hover_induced_velocities():
    assert hover_induced_velocity("paper_quad") == pytest.approx(11.8, abs=0.05)  # docs/fields.md
    assert hover_induced_velocity("crazyflie_2_1") == pytest.approx(4.28, abs=0.01)
    assert hover_induced_velocity("x500") == pytest.approx(5.81, abs=0.01)


@pytest.mark.parametrize("kind", KINDS, ids=VEHICLE_NAMES)
def test_so2_strength_scale_by_hand(kind):
    disc = (kind.mass / kind.rotor_radius**2) / (0.70 / 0.04**2)  # (m g / n pi r^2) over the paper quad's
    assert so2_strength_scale(kind) == pytest.approx(disc, rel=1e-13)
    assert so2_strength_scale(kind, basis="thrust") == pytest.approx(kind.mass / 0.70, rel=1e-14)
    assert so2_strength_scale(kind, reference=kind) == 1.0
    # = the ratio of the induced velocities squared
    assert so2_strength_scale(kind) == pytest.approx((hover_induced_velocity(kind) / hover_induced_velocity(PAPER_QUAD)) ** 2)
    with pytest.raises(ConfigError, match="basis: unknown 'area'; allowed: disc_loading, thrust"):
        so2_strength_scale(kind, basis="area")


def test_so2_field_scaled_pushes_in_proportion():
    """The paper's law with strength x scale: the push below a hovering leader scales by the factor."""
    from sim.field import DownwashField

    base = DownwashField()
    scale = so2_strength_scale("crazyflie_2_1")
    scaled = DownwashField(strength=base.strength * scale)
    p_a, v, R = np.array([0.0, 0.0, 2.5]), np.zeros(3), np.eye(3)
    for s in (0.5, 1.0, 1.5):
        p_b = p_a - [0.05, 0.0, s]
        np.testing.assert_allclose(scaled(p_a, v, R, p_b, v), scale * base(p_a, v, R, p_b, v), rtol=1e-12)


def test_momentum_wake_for_other_kinds_by_hand():
    from sim.fields.momentum import MomentumWake

    assert MomentumWake(**momentum_wake_kwargs("paper_quad")) == MomentumWake()  # the field's defaults
    assert MomentumWake(**momentum_wake_kwargs("paper_quad", "paper_quad")) == MomentumWake()
    for leader in KINDS:
        for follower in KINDS:
            wake = MomentumWake(**momentum_wake_kwargs(leader, follower))
            T = leader.mass * GRAVITY
            U0, b0, _, _ = wake.centreline(0.0, T)  # at the rotor plane the axis speed is v_h
            assert U0 == pytest.approx(math.sqrt(T / (2 * 1.225 * 4 * math.pi * leader.rotor_radius**2)), rel=1e-12)
            assert b0 == pytest.approx(2 * leader.rotor_radius, rel=1e-5)  # the equivalent disc's radius
            assert wake.leader_thrust(np.eye(3)) == pytest.approx(T)
            assert wake.vh_follower == pytest.approx(hover_induced_velocity(follower), rel=1e-12)
            assert (wake.follower_mass, wake.follower_arm) == (follower.mass, follower.arm_length)


# ----------------------------------------------------------------------------- the listing


def test_vehicles_listing_runs_quick(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run([sys.executable, "-m", "experiments.vehicles", "--quick", "--out", "o"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in VEHICLE_NAMES:
        assert name in proc.stdout
    assert "v_h m/s" in proc.stdout and "drone-models" in proc.stdout
    results = json.loads((tmp_path / "o" / "results.json").read_text())
    assert [v["name"] for v in results["vehicles"]] == list(VEHICLE_NAMES)
    cf = results["vehicles"][1]
    assert cf["mass"] == 0.0319 and cf["hover_induced_velocity"] == pytest.approx(4.281, abs=1e-3)
    assert results["args"]["quick"] is True


def test_vehicles_listing_options(tmp_path):
    from experiments.vehicles import main

    results = main(["--only", "x500", "--out", str(tmp_path / "x")])
    assert [v["name"] for v in results["vehicles"]] == ["x500"]
    with pytest.raises(ConfigError, match=r"--only: unknown vehicle kinds \['cf'\]; allowed: paper_quad"):
        main(["--only", "cf", "--out", str(tmp_path / "y")])
    with pytest.raises(ConfigError, match="--field"):
        main(["--field", "so2", "--out", str(tmp_path / "z")])
    assert not (tmp_path / "y").exists() and not (tmp_path / "z").exists()


def test_the_simulator_flies_each_kind_with_its_numbers_and_refuses_a_contradicting_sim_config():
    """A Crazyflie stack flies with the Crazyflie's numbers from its kinds, bit for bit as with
    SimConfig(quad=<the kind>) (which agrees); a SimConfig.quad that contradicts the kinds is refused."""
    from sim.scene import build_scene
    from sim.simulator import SimConfig, Simulator
    from downwash_core.vehicles import CRAZYFLIE_2_1
    from downwash_trajectories import Hover, stack

    leader = np.array([0.0, 0.0, 1.5])
    reference = stack([Hover(leader, n_worlds=2), Hover(leader - [0, 0, 0.25], n_worlds=2)])
    scene = build_scene(kinds="crazyflie_2_1")
    with pytest.raises(ConfigError, match=r"SimConfig.quad: .*crazyflie_2_1.*each vehicle flies its own kind"):
        Simulator(build_scene(), reference, [0, 1], config=SimConfig(quad=CRAZYFLIE_2_1.params))
    off = np.zeros(2, bool)  # no downwash: the vehicle's own numbers alone (test_heterogeneous flies the wakes)
    sims = [Simulator(scene, reference, [0, 1], field_enabled=off, **kw)
            for kw in ({}, {"config": SimConfig(quad=CRAZYFLIE_2_1.params)})]
    for sim in sims:
        np.testing.assert_array_equal(sim.vehicle_params.mass, CRAZYFLIE_2_1.mass)
        for _ in range(100):
            sim.tick()
        assert sim.active.all()
        assert np.abs(sim.physics.qpos[:, sim._pos_idx[1]] - (leader - [0, 0, 0.25])).max() < 0.1
    np.testing.assert_array_equal(sims[0].physics.qpos, sims[1].physics.qpos)
