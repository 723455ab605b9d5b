"""Domain randomisation of any field of float constants (`field_randomization`), per world per episode.

A `DownwashField` takes per-world constants as arrays; `MomentumWake`, `JetWake`, `PybulletDownwash` (and
their `fitted:` subclasses) are rebuilt per world and flown through `sim.fields.per_world.PerWorldFields`.
Each world's force must be that of the field rebuilt with its own drawn constant, evaluated alone.
"""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_core.geometry import quat_to_mat
from downwash_core.params import QUAD
from downwash_core.vehicles import get_vehicle
from downwash_envs import DownwashFollowerVectorEnv
from downwash_envs.config import FIELD_RANDOMIZABLE, FollowerConfig, build_field, randomizable_constants
from downwash.field_fit import PairStates, bootstrap_fit, field_forces, randomization_ranges, write_fitted
from sim.field import DownwashField, pairwise_field, pairwise_forces
from sim.fields.per_world import PerWorldFields
from sim.fields.registry import make_field
from sim.vehicle_params import pair_field

THRUST = {"thrust_scale": (0.8, 1.2)}


def _states(rng: np.random.Generator, W: int, V: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """pos, vel (W, V, 3) m, m/s and rot (W, V, 3, 3): a follower 0.3-1.0 m below a leader, near its axis."""
    pos = np.zeros((W, V, 3))
    pos[:, 0] = [0.0, 0.0, 2.5]
    pos[:, 1:] = pos[:, :1] + np.concatenate([rng.uniform(-0.15, 0.15, (W, V - 1, 2)),
                                              -rng.uniform(0.3, 1.0, (W, V - 1, 1))], axis=-1)
    q = np.concatenate([np.ones((W, V, 1)), rng.normal(0.0, 0.03, (W, V, 3))], axis=-1)
    return pos, rng.normal(0.0, 0.3, (W, V, 3)), quat_to_mat(q)


def _rebuilt(env: DownwashFollowerVectorEnv, infos: dict) -> list:
    """Each world's field, rebuilt from the base field with the factors its reset info reports."""
    worlds = env._worlds
    return [dataclasses.replace(worlds.base_field, **{
        name: float(getattr(worlds.base_field, name)) * float(infos[f"field_scale_{name}"][w])
        for name in worlds.scale_names}) for w in range(worlds.W)]


# ----------------------------------------------------------------------------- per-world draws


@pytest.mark.parametrize("name", ["momentum", "jet"])
def test_each_world_draws_its_constant_within_the_range_reproducibly(name):
    env = DownwashFollowerVectorEnv(4, field=name, field_randomization=THRUST)
    _, infos = env.reset(seed=11)
    factors = infos["field_scale_thrust_scale"]
    assert np.all((factors >= 0.8) & (factors <= 1.2)) and len(set(factors.tolist())) == 4
    field = env._worlds.sim.field
    assert isinstance(field, PerWorldFields) and len(field) == 4
    base = float(env._worlds.base_field.thrust_scale)
    assert [f.thrust_scale for f in field.fields] == [base * s for s in factors]  # exactly the drawn factor
    assert all(type(f) is type(env._worlds.base_field) for f in field.fields)
    # the other constants are the base field's
    others = [k for k in randomizable_constants(env._worlds.base_field) if k != "thrust_scale"]
    assert all(getattr(f, k) == getattr(env._worlds.base_field, k) for f in field.fields for k in others)
    # the same seed, the same draws; another seed, others; a new episode, new ones
    again = DownwashFollowerVectorEnv(4, field=name, field_randomization=THRUST)
    assert np.array_equal(again.reset(seed=11)[1]["field_scale_thrust_scale"], factors)
    assert not np.array_equal(again.reset(seed=12)[1]["field_scale_thrust_scale"], factors)
    new = env.reset(seed=13)[1]["field_scale_thrust_scale"]
    assert [f.thrust_scale for f in env._worlds.sim.field.fields] == [base * s for s in new]
    for e in (env, again):
        e.close()


def test_so2_keeps_array_constants_and_its_draws():
    """The so2 field still takes its per-world constants as (W, 1, 1) arrays (not one field per world),
    drawn in FollowerConfig.field_scales order: the golden digests (tests/test_env.py) stay as recorded."""
    env = DownwashFollowerVectorEnv(3, field_randomization="default")
    _, infos = env.reset(seed=7)
    field = env._worlds.sim.field
    assert type(field) is DownwashField and np.shape(field.strength) == (3, 1, 1)
    assert np.array_equal(field.strength[:, 0, 0], 10.6 * infos["field_scale_strength"])
    assert tuple(env._worlds.scale_names) == ("strength", "width0", "width_slope")  # sorted: the draw order
    env.close()


# ----------------------------------------------------------------------------- world w flies field w


@pytest.mark.parametrize("name", ["momentum", "jet", "pybullet"])
def test_world_force_is_that_of_its_rebuilt_field(name):
    constant = {"momentum": "thrust_scale", "jet": "thrust_scale", "pybullet": "dw_coeff_1"}[name]
    env = DownwashFollowerVectorEnv(3, field=name, field_randomization={constant: (0.5, 1.5)}, predictor="oracle")
    _, infos = env.reset(seed=3)
    sim, rebuilt = env._worlds.sim, _rebuilt(env, infos)
    assert sim.predictor.field is sim.field  # the oracle flies the worlds' fields too
    pos, vel, rot = _states(np.random.default_rng(0), 3)
    pos, vel, rot = (np.repeat(x[:1], 3, axis=0) for x in (pos, vel, rot))  # one state in every world
    batched = pairwise_field(sim.field, pos, vel, rot)  # PerWorldFields.pairwise: the loop over worlds
    for w, field in enumerate(rebuilt):
        alone = field(pos[w, 0], vel[w, 0], rot[w, 0], pos[w, 1], vel[w, 1])  # the readable law, one pair
        np.testing.assert_array_equal(batched[w, 1], alone)
        np.testing.assert_array_equal(batched[w, 0], 0.0)  # the leader is above: no wake
    assert len({tuple(batched[w, 1]) for w in range(3)}) == 3  # the constants matter
    # the broadcast call (as KindPairs and pairwise_forces make it) and pair_forces agree with it
    leaders = (pos[:, :, None], vel[:, :, None], rot[:, :, None])
    called = sim.field(*leaders, pos[:, None], vel[:, None])
    forces = sim.field.pair_forces(pos, vel, rot)
    np.testing.assert_array_equal(forces[:, 0, 1], called[:, 0, 1])
    np.testing.assert_array_equal(forces.sum(axis=1), batched)
    # the simulator takes the readable path (no compiled form) and steps
    env.step(np.zeros((3, 3), np.float32))
    assert sim._plan is None and np.all(np.isfinite(sim.true_states().pos))
    env.close()


def test_a_degenerate_range_flies_exactly_the_field_with_that_constant():
    """thrust_scale x U(0.8, 0.8) draws 0.8 exactly and one more uniform, after the episode's other draws
    (lemniscate: nothing after it), so the worlds fly bit for bit as with momentum:thrust_scale=0.8."""
    runs = []
    for opts in (dict(field="momentum", field_randomization={"thrust_scale": (0.8, 0.8)}),
                 dict(field="momentum:thrust_scale=0.8")):
        env = DownwashFollowerVectorEnv(2, **opts)
        obs, _ = env.reset(seed=5)
        trace = [obs]
        for k in range(5):
            trace.append(env.step(np.full((2, 3), 0.1 * k, np.float32))[0])
        runs.append(np.array(trace))
        env.close()
    np.testing.assert_array_equal(runs[0], runs[1])


def test_per_world_fields_match_array_constants_of_so2():
    """PerWorldFields of scalar DownwashFields (each on its compiled kernel) against one DownwashField
    with (W, 1, 1) array constants (the NumPy law): the same forces to rounding."""
    rng = np.random.default_rng(4)
    scales = rng.uniform(0.7, 1.3, 5)
    arrays = DownwashField(strength=10.6 * scales.reshape(5, 1, 1), width0=0.1 * scales.reshape(5, 1, 1))
    per_world = PerWorldFields([DownwashField(strength=10.6 * s, width0=0.1 * s) for s in scales])
    pos, vel, rot = _states(rng, 5, V=3)
    np.testing.assert_allclose(pairwise_field(per_world, pos, vel, rot), pairwise_field(arrays, pos, vel, rot),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(pairwise_forces(per_world, pos, vel, rot), pairwise_forces(arrays, pos, vel, rot),
                               rtol=1e-12, atol=1e-12)


def test_per_world_fields_interface_and_errors():
    fields = [make_field("momentum", thrust_scale=s) for s in (0.9, 1.1)]
    pw = PerWorldFields(fields)
    assert pw.describe()["fields"][1]["thrust_scale"] == 1.1 and "PerWorldFields" in pw.describe()["type"]
    assert pickle.loads(pickle.dumps(pw)).fields == pw.fields
    pos, vel, rot = _states(np.random.default_rng(1), 2)
    # inputs with a world axis of 1 (or none) serve every world
    one = pw(pos[:1, 0], vel[:1, 0], rot[:1, 0], pos[:1, 1], vel[:1, 1])
    assert one.shape == (2, 3)
    np.testing.assert_array_equal(one[1], fields[1](pos[0, 0], vel[0, 0], rot[0, 0], pos[0, 1], vel[0, 1]))
    thrust = np.array([0.2, 0.4])  # N per world, a keyword array sliced as the states
    out = pw(pos[:, 0], vel[:, 0], rot[:, 0], pos[:, 1], vel[:, 1], thrust=thrust)
    np.testing.assert_array_equal(out[1], fields[1](pos[1, 0], vel[1, 0], rot[1, 0], pos[1, 1], vel[1, 1], thrust=0.4))
    # kinds: each world's field paired (sim.vehicle_params.pair_field), itself for two paper quads
    assert pair_field(pw, QUAD, QUAD) is pw
    crazyflie = get_vehicle("crazyflie_2_1")
    paired = pair_field(pw, crazyflie, QUAD)
    assert paired is not pw and paired.fields == tuple(pair_field(f, crazyflie, QUAD) for f in fields)
    with pytest.raises(ConfigError, match="one field per world, got none"):
        PerWorldFields([])
    with pytest.raises(ConfigError, match=r"fields\[1\] is a float"):
        PerWorldFields([fields[0], 1.0])
    with pytest.raises(ConfigError, match=r"fields\[0\] \(ShedWake\) has memory"):
        PerWorldFields([make_field("shed")])
    with pytest.raises(ConfigError, match="2 worlds' fields, states of 3 worlds"):
        pw.pairwise(*_states(np.random.default_rng(2), 3))
    with pytest.raises(ConfigError, match="batched over 2 worlds"):
        pw(pos[0, 0], vel[0, 0], rot[0, 0], pos[0, 1], vel[0, 1])  # no world axis at all


# ----------------------------------------------------------------------------- a field fitted to flights


def _fit_states(seed: int, n_flights: int = 4, per_flight: int = 80) -> PairStates:
    """Synthetic labels of a known momentum wake (thrust_scale 0.7, spreading_rate 0.12) plus noise,
    followers 0.15-1.4 m below a leader (as tests/test_field_fit.py's synthetic_states, one kind)."""
    rng = np.random.default_rng(seed)
    n = n_flights * per_flight
    p_a = rng.uniform(-1, 1, (n, 3)) + [0, 0, 2.0]
    depth, radius, angle = rng.uniform(0.15, 1.4, n), 0.4 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 7, n)
    p_b = p_a + np.stack([radius * np.cos(angle), radius * np.sin(angle), -depth], axis=1)
    q = np.concatenate([np.ones((n, 1)), rng.normal(0.0, 0.04, (n, 3))], axis=1)
    kind = "crazyflie_2_1"
    states = PairStates(
        p_a=p_a, v_a=rng.normal(0, 0.2, (n, 3)), R_a=quat_to_mat(q), p_b=p_b, v_b=rng.normal(0, 0.3, (n, 3)),
        y=np.zeros((n, 3)), kind_a=np.zeros(n, int), kind_b=np.zeros(n, int),
        flight=np.repeat(np.arange(n_flights), per_flight), row=np.tile(np.arange(per_flight), n_flights),
        vehicle=np.zeros(n, int), types=np.full(n, "S2S"), kinds=(kind,),
        flight_names=tuple(f"f{i}" for i in range(n_flights)),
        flight_digests=tuple(f"{i:064x}" for i in range(n_flights)), selection={"synthetic": seed})
    y = field_forces(make_field("momentum", thrust_scale=0.7, spreading_rate=0.12), states)
    return dataclasses.replace(states, y=y + rng.normal(0, 0.05, (n, 3)))


def test_a_fitted_field_is_randomised_over_its_intervals(tmp_path):
    fit = bootstrap_fit("momentum", _fit_states(seed=21), n_boot=10)
    path = write_fitted(tmp_path / "momentum.json", fit)
    ranges = randomization_ranges(fit, spec=f"fitted:{path}")
    # the absolute intervals as factors on the fitted values: what randomization_ranges gives
    factors = {p: (lo / fit.params[p], hi / fit.params[p]) for p, (lo, hi) in ranges["absolute"].items()}
    assert ranges["field_randomization"].keys() == factors.keys()  # (approx per pair: newer pytest takes no nesting)
    assert all(ranges["field_randomization"][p] == pytest.approx(f) for p, f in factors.items())
    env = DownwashFollowerVectorEnv(3, field=ranges["field"], field_randomization=factors)
    _, infos = env.reset(seed=2)
    fields = env._worlds.sim.field.fields
    for f in fields:  # the fitted class (its data's digest in its provenance), constants inside the intervals
        assert f.describe()["fitted"]["data_digest"] == fit.data_digest
        for p, (lo, hi) in ranges["absolute"].items():
            assert lo * (1 - 1e-12) <= getattr(f, p) <= hi * (1 + 1e-12)
    assert len({f.thrust_scale for f in fields}) == 3
    pos, vel, rot = _states(np.random.default_rng(6), 3)
    batched = pairwise_field(env._worlds.sim.field, pos, vel, rot)
    for w, field in enumerate(_rebuilt(env, infos)):
        assert field == fields[w]
        np.testing.assert_array_equal(batched[w, 1], field(pos[w, 0], vel[w, 0], rot[w, 0], pos[w, 1], vel[w, 1]))
    env.step(np.zeros((3, 3), np.float32))
    env.close()


# ----------------------------------------------------------------------------- bad input


def test_randomizable_constants_are_the_float_dataclass_fields():
    assert randomizable_constants(build_field(None)) == FIELD_RANDOMIZABLE
    momentum = randomizable_constants(build_field("momentum"))
    assert "thrust_scale" in momentum and not {"n_rotors", "ring_points", "rotors", "drag"} & set(momentum)
    assert "dw_coeff_3" in randomizable_constants(build_field("pybullet"))  # negative constants scale too
    assert "mirror_width" not in randomizable_constants(build_field("pybullet"))
    assert randomizable_constants(build_field("shed")) == ()  # a wake with memory
    assert randomizable_constants(lambda *a: np.zeros(3)) == ()


_BAD = [
    (dict(field="momentum", field_randomization={"colour": (0.9, 1.1)}),
     r"field_randomization: \['colour'\]: not among MomentumWake's .*float constants; "
     r"allowed: air_density, .*thrust_scale"),
    (dict(field="momentum", field_randomization={"n_rotors": (0.9, 1.1)}),
     r"\['n_rotors'\]: not among MomentumWake's .*; allowed: (?!.*n_rotors)"),
    (dict(field="momentum", field_randomization={"drag": (0.9, 1.1)}), r"\['drag'\]: not among MomentumWake's"),
    (dict(field="jet", field_randomization={"thrust_scale": (0.05, 1.0)}),
     r"field_randomization\['thrust_scale'\]: .*0.1 <= low <= high <= 5.0"),
    (dict(field="jet", field_randomization={"thrust_scale": (1.2, 0.8)}), r"field_randomization\['thrust_scale'\]"),
    (dict(field="pybullet", field_randomization={"dw_coeff_1": (0.9, 6.0)}), r"field_randomization\['dw_coeff_1'\]"),
    (dict(field="momentum", field_randomization={"thrust_scale": ("0.8", 1.2)}), r"thrust_scale'\]: .*a str"),
    (dict(field="momentum", field_randomization="default"),
     r"'default' scales so2's constants; for a MomentumWake give .*thrust_scale"),
    (dict(field="momentum:thrust_scale=4", field_randomization={"thrust_scale": (1.0, 3.0)}),
     r"field_randomization\['thrust_scale'\]: factor 3 makes thrust_scale = 12, which MomentumWake refuses"),
    (dict(field="momentum", field_randomization={"virtual_origin": (0.9, 1.1)}),
     r"MomentumWake.virtual_origin is 0, which no factor changes"),
    (dict(field="shed", field_randomization=THRUST), r"needs a field of float dataclass constants .*got ShedWake"),
    (dict(field=lambda p_a, v_a, R_a, p_b, v_b: np.zeros(np.broadcast_shapes(p_a.shape, p_b.shape)),
          field_randomization={"strength": (0.9, 1.1)}), r"needs a field of float dataclass constants .*got function"),
    (dict(field_randomization={"fade_start": (0.9, 1.1)}),
     r"\['fade_start'\]: not among DownwashField's .*; allowed: strength"),
    (dict(field_randomization=["strength"]), r"field_randomization: got \['strength'\] \(a list\); allowed: None"),
    (dict(field_randomization="wide"), r"field_randomization: got 'wide' \(a str\); allowed: None, 'default'"),
]


@pytest.mark.parametrize("opts, match", _BAD, ids=[str(m[:40]) for _, m in _BAD])
def test_bad_field_randomization_is_refused_at_construction(opts, match):
    with pytest.raises(ConfigError, match=match):
        FollowerConfig(**opts)


def test_good_ranges_on_each_field_family_are_accepted():
    FollowerConfig(field="pybullet", field_randomization={"dw_coeff_3": (0.5, 2.0), "min_width": (0.8, 1.2)})
    FollowerConfig(field="jet", field_randomization={"decay_constant": (0.9, 1.1), "virtual_origin": (0.9, 1.1)})
    FollowerConfig(field="so2:strength=8", field_randomization={"strength": (0.5, 1.5)})
