"""The compiled scene agrees with the one parameter source; bad XML fails clearly."""

import mujoco
import numpy as np
import pytest

from downwash_core.errors import DataError
from downwash_core.params import GRAVITY, QUAD, RATES
from sim.scene import QUAD_XML, build_scene


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def test_vehicle_parameters_match_params(scene):
    m = scene.model
    for b in scene.body_ids:
        assert m.body_mass[b] == pytest.approx(QUAD.mass, abs=1e-12)
        np.testing.assert_allclose(m.body_inertia[b], QUAD.inertia, atol=1e-12)
    # the geoms carry no mass: the vehicle's total is its body's
    assert m.body_subtreemass[scene.body_ids].tolist() == pytest.approx([QUAD.mass] * scene.n_vehicles)
    for v, acts in enumerate(scene.act_ids):
        for k, a in enumerate(acts):
            site = m.actuator_trnid[a, 0]
            np.testing.assert_allclose(m.site_pos[site], QUAD.rotor_positions[k], atol=1e-5)
            assert np.linalg.norm(m.site_pos[site][:2]) == pytest.approx(QUAD.arm_length, abs=1e-5)
            np.testing.assert_allclose(m.actuator_ctrlrange[a], [0.0, QUAD.max_rotor_thrust], atol=1e-4)
            assert m.actuator_dynprm[a, 0] == pytest.approx(QUAD.motor_time_constant)
            assert m.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_FILTER
            np.testing.assert_allclose(m.actuator_gear[a], [0, 0, 1, 0, 0, QUAD.rotor_spin[k] * QUAD.yaw_moment_coeff])


def test_scene_options_and_names(scene):
    m = scene.model
    assert m.opt.timestep == RATES.physics_dt
    np.testing.assert_allclose(m.opt.gravity, [0, 0, -GRAVITY])
    assert scene.vehicles == ("alpha", "bravo")
    assert m.body(scene.body_ids[1]).name == "bravo/quad"
    assert m.camera("overview").id >= 0
    # thrust-to-weight and longest diagonal as in the paper's vehicle (section 5.C)
    assert 4 * QUAD.max_rotor_thrust / QUAD.weight == pytest.approx(2.3, rel=1e-3)
    assert QUAD.diagonal == pytest.approx(0.26, abs=0.005)


def test_hover_thrust_balances_gravity(scene):
    """Four rotors at hover thrust hold a level vehicle still (no drift after 0.5 s)."""
    d = mujoco.MjData(scene.model)
    d.qpos[scene.qpos_adr[:, None] + np.arange(3)] = [[0, 0, 2.0], [1, 0, 2.0]]
    d.act[:] = d.ctrl[:] = QUAD.hover_rotor_thrust
    for _ in range(250):
        mujoco.mj_step(scene.model, d)
    z = d.qpos[scene.qpos_adr + 2]
    np.testing.assert_allclose(z, 2.0, atol=1e-6)


def test_n_vehicles_scene():
    s = build_scene(("a", "b", "c"))
    assert s.n_vehicles == 3 and s.act_ids.shape == (3, 4)
    assert len(set(s.qpos_adr.tolist())) == 3


def test_missing_and_malformed_xml(tmp_path):
    with pytest.raises(DataError, match="not found"):
        build_scene(quad_xml=tmp_path / "nope.xml")
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><body name='quad'>")
    with pytest.raises(ValueError, match="malformed"):
        build_scene(quad_xml=bad)
    no_rotor = tmp_path / "norotor.xml"
    no_rotor.write_text(QUAD_XML.read_text().replace('name="rotor3" site', 'name="rotorX" site'))
    with pytest.raises(ValueError, match="rotor3"):
        build_scene(quad_xml=no_rotor)
    with pytest.raises(ValueError, match="distinct"):
        build_scene(("a", "a"))


def test_contacts_are_off_and_collisions_are_detected_geometrically(scene):
    """Contact dynamics are disabled (flights end at a collision, see test_simulator)."""
    assert scene.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
