"""The field registry (sim/fields/registry.py): every registered field's contract, the spec
grammar of `--field` / `field=`, the envs and a short flight with each field."""

from __future__ import annotations

import json
import math
import textwrap

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial.transform import Rotation

from downwash_core.errors import ConfigError
from downwash_core.geometry import quat_to_mat
from downwash_core.provenance import describe
from downwash_core.status import Status
from experiments.common import load_field
from sim.field import DownwashField, check_field
from sim.fields import FIELDS, MomentumWake, make_field, register_field, resolve_field_spec
from sim.fields import registry as registry_module

# The symmetry each registered field claims (its registry line says the same in words).
# A field registered without a line here fails test_every_field_has_a_symmetry_test.
# "memory": a field with memory, not a law of the instant: its symmetries (vehicle order, batched = serial,
# the steady hover wake equal to momentum's) are tested in tests/test_shed_wake.py
SYMMETRY = {"so2": "so2", "so2-swirl": "so2", "momentum": "so2", "so2-c4": "c4", "so2-skew": "skew", "shed": "memory", "jet": "so2", "pybullet": "so2"}
NAMES = [name for name, law in SYMMETRY.items() if law != "memory"]
POS, VEL = 1e3, 100.0  # m, m/s: wide bounds of the random inputs


def test_every_field_has_a_symmetry_test():
    assert set(FIELDS) == set(SYMMETRY)
    assert list(FIELDS)[0] == "so2"


# ----------------------------------------------------------------------------- inputs


def _floats(bound):
    return st.floats(-bound, bound, allow_nan=False, allow_infinity=False)


@st.composite
def states(draw):
    """(p_a, v_a, R_a, p_b, v_b) batched over a drawn shape, followers anywhere or in the wake."""
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=2, max_side=3))
    vec = lambda b: draw(hnp.arrays(np.float64, shape + (3,), elements=_floats(b)))  # noqa: E731
    q = draw(hnp.arrays(np.float64, shape + (4,), elements=_floats(1.0)))
    q = np.where(np.linalg.norm(q, axis=-1, keepdims=True) > 1e-3, q, [1.0, 0.0, 0.0, 0.0])
    R_a = quat_to_mat(q)
    p_a = vec(POS)
    if draw(st.booleans()):
        p_b = vec(POS)
    else:  # near the wake: on its axis or a little off it, above or below
        depth = draw(st.floats(-1.0, 5.0))
        p_b = p_a - depth * R_a[..., :, 2] + draw(st.sampled_from([0.0, 1e-9, 0.3])) * R_a[..., :, 0]
    zero_v = draw(st.booleans())
    v_a, v_b = (np.zeros(shape + (3,)), np.zeros(shape + (3,))) if zero_v else (vec(VEL), vec(VEL))
    return p_a, v_a, R_a, p_b, v_b


def _random_pairs(seed, n=300, depth=(0.1, 2.5)):
    """n random pairs, followers inside the wake of a randomly tilted leader."""
    rng = np.random.default_rng(seed)
    R_a = Rotation.random(n, random_state=rng).as_matrix()
    body = np.column_stack([rng.normal(0, 0.3, n), rng.normal(0, 0.3, n), -rng.uniform(*depth, n)])
    p_a = rng.normal(0, 1, (n, 3))
    return {"p_a": p_a, "v_a": rng.normal(0, 0.5, (n, 3)), "R_a": R_a,
            "p_b": p_a + np.einsum("nij,nj->ni", R_a, body), "v_b": rng.normal(0, 0.6, (n, 3))}


def _call(field, x, **over):
    x = {**x, **over}
    return field(x["p_a"], x["v_a"], x["R_a"], x["p_b"], x["v_b"])


def _rotation_error(field, x, angle):
    """(n,) |F(H dp, H v_b) - H F(dp, v_b)|, H rotating about each leader's axis by `angle`."""
    H = x["R_a"] @ Rotation.from_euler("z", np.broadcast_to(angle, (len(x["p_a"]),))[:, None]).as_matrix() \
        @ np.swapaxes(x["R_a"], 1, 2)
    rot = lambda v: np.einsum("nij,nj->ni", H, v)  # noqa: E731
    F = _call(field, x)
    F_rot = _call(field, x, p_b=x["p_a"] + rot(x["p_b"] - x["p_a"]), v_b=rot(x["v_b"]))
    return np.linalg.norm(F_rot - rot(F), axis=-1)


# ----------------------------------------------------------------------------- every field


@pytest.mark.parametrize("name", NAMES)
@given(x=states())
@settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
def test_finite_and_shaped_for_wide_inputs(name, x):
    field = make_field(name)
    with np.errstate(divide="raise", over="raise", invalid="raise", under="ignore"):
        F = field(*x)
    assert F.shape == np.broadcast_shapes(x[0].shape, x[3].shape, x[2].shape[:-1]) and F.shape[-1] == 3
    assert np.all(np.isfinite(F))


@pytest.mark.parametrize("name", NAMES)
def test_broadcasts_over_leading_axes(name):
    field = make_field(name)
    x = _random_pairs(0, n=4)
    p_b = x["p_a"][:3][None] + np.array([0.05, 0.0, -0.8])  # (1, 3, 3)
    F = field(x["p_a"][:, None], x["v_a"][:, None], x["R_a"][:, None], p_b, np.zeros((1, 3, 3)))
    assert F.shape == (4, 3, 3)
    assert F[2, 1] == pytest.approx(field(x["p_a"][2], x["v_a"][2], x["R_a"][2], p_b[0, 1], np.zeros(3)))


@pytest.mark.parametrize("name", NAMES)
def test_exactly_zero_well_above_the_leader(name):
    x = _random_pairs(1, depth=(-5.0, -0.5))  # 0.5-5 m above the leader along its axis
    assert np.all(_call(make_field(name), x) == 0.0)


@pytest.mark.parametrize("name", NAMES)
def test_translation_invariant(name):
    field, x = make_field(name), _random_pairs(2)
    shift = np.random.default_rng(3).normal(0, 10, (len(x["p_a"]), 3))
    F = _call(field, x)
    assert _call(field, x, p_a=x["p_a"] + shift, p_b=x["p_b"] + shift) == pytest.approx(F, abs=1e-9 * np.abs(F).max())
    assert np.abs(F).max() > 0.1  # the wake is there


@pytest.mark.parametrize("name", NAMES)
def test_claimed_symmetry_about_the_leader_axis(name):
    field, x = make_field(name), _random_pairs(4)
    generic = np.random.default_rng(5).uniform(0.3, 2 * math.pi - 0.3, len(x["p_a"]))
    scale = np.abs(_call(field, x)).max()
    kind = SYMMETRY[name]
    # H (`_rotation_error`) is a BLAS product, orthogonal to a few eps with the kernel's bits: the round-off
    # it carries is ~2e-6 of the 1e-9 * scale allowed under every kernel, and a broken symmetry is > 0.05
    if kind == "so2":
        assert _rotation_error(field, x, generic).max() < 1e-9 * scale
    elif kind == "c4":  # quarter turns pass, a generic angle does not
        for k in (1, 2, 3):
            assert _rotation_error(field, x, k * math.pi / 2).max() < 1e-9 * scale
        assert _rotation_error(field, x, generic).max() > 0.05
    elif kind == "skew":  # equivariant while the leader moves only along its axis
        n = x["R_a"][:, :, 2]
        along = {**x, "v_a": np.einsum("ni,ni->n", x["v_a"], n)[:, None] * n}
        assert _rotation_error(field, along, generic).max() < 1e-9 * scale
        assert _rotation_error(field, x, generic).max() > 0.05


# ----------------------------------------------------------------------------- load_field


def test_names_and_the_default():
    assert load_field("") == DownwashField() == load_field("so2")
    assert describe(load_field("")) == describe(load_field("so2"))  # one law, one provenance
    assert load_field("so2-c4") == DownwashField(c4_amplitude=0.3)
    assert load_field("so2-swirl") == DownwashField(swirl=0.4)
    assert load_field("so2-skew") == DownwashField(skew=0.35)
    assert load_field("momentum") == MomentumWake()
    assert describe(load_field("so2-c4")) == describe(load_field("so2:c4_amplitude=0.3"))


def test_parameters_are_type_converted():
    f = load_field("so2:strength=8")
    assert f.strength == 8.0 and type(f.strength) is float
    m = load_field("momentum:thrust_scale=1.5,ring_points=4,drag=false")
    assert (m.thrust_scale, m.ring_points, m.drag) == (1.5, 4, False)
    assert type(m.ring_points) is int and m.drag is False
    assert load_field("momentum:rotors=0,drag=Yes").rotors is False
    assert load_field("so2-c4:c4_amplitude=0.5").c4_amplitude == 0.5  # overrides the preset
    assert resolve_field_spec(" momentum:thrust_scale = 2 ").thrust_scale == 2.0


@pytest.mark.parametrize("spec, match", [
    ("nope", r"unknown field 'nope'; registered: so2, so2-c4, so2-swirl, so2-skew, momentum, shed, jet, pybullet; or a MODULE:FACTORY"),
    ("so2:colour=1", r"field 'so2' has no parameter 'colour'; allowed: strength, .*skew"),
    ("momentum:thrust=2", r"no parameter 'thrust'; allowed: air_density, .*thrust_scale, .*drag"),
    ("momentum:ring_points=2.5", "ring_points.*expected an integer"),
    ("momentum:drag=maybe", "drag.*expected a bool"),
    ("so2:strength=fast", "strength.*expected a number"),
    ("so2:strength=inf", "strength.*finite"),
    ("so2:strength", "KEY=VALUE"),
    ("so2:strength=1,strength=2", "given twice"),
    ("momentum:air_density=0", "air_density"),
    ("momentum:make", "KEY=VALUE"),  # a registered name wins over a top-level module of that name
    ("mom:x=1", r"unknown field 'mom'.*registered: so2"),
    ("no_such_module:make", "cannot import"),
    ("sim.field:no_such_factory", "no callable 'no_such_factory'"),
    ("a:b:c", "MODULE:FACTORY"),
])
def test_bad_specs_name_what_is_allowed(spec, match):
    with pytest.raises(ConfigError, match=match):
        load_field(spec)


def test_module_factory_still_works(tmp_path, monkeypatch):
    assert load_field("sim.field:DownwashField") == DownwashField()
    (tmp_path / "my_field_pkg.py").write_text(textwrap.dedent("""
        from sim.fields import MomentumWake
        def make():
            return MomentumWake(thrust_scale=2.0)
        def broken():
            return lambda p_a, v_a, R_a, p_b, v_b: p_b * float("nan")
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    assert load_field("my_field_pkg:make") == MomentumWake(thrust_scale=2.0)
    with pytest.raises(ConfigError, match="non-finite"):
        load_field("my_field_pkg:broken")


@pytest.mark.parametrize("name", NAMES)
def test_every_resolved_field_passes_check_field_and_describes_stably(name):
    field = load_field(name)
    check_field(field)
    text = json.dumps(describe(field), sort_keys=True)
    assert "0x" not in text and text == json.dumps(describe(load_field(name)), sort_keys=True)


def test_register_field_checks_the_name():
    with pytest.raises(ConfigError, match="lowercase"):
        register_field("my.field", DownwashField, "x", "none")
    with pytest.raises(ConfigError, match="already registered"):
        register_field("so2", DownwashField, "x", "none")
    try:
        register_field("test-weak", DownwashField, "so2 at half strength", "SO(2)", {"strength": float},
                       {"strength": 5.3})
        assert load_field("test-weak") == DownwashField(strength=5.3)
        assert load_field("test-weak:strength=1").strength == 1.0
    finally:
        registry_module._REGISTRY.pop("test-weak", None)


def test_experiment_lists_the_fields(tmp_path, capsys):
    from experiments.fields import main

    main(["--out", str(tmp_path / "f"), "--quick", "--seed", "3"])
    r = json.loads((tmp_path / "f" / "results.json").read_text())
    assert [f["name"] for f in r["fields"]] == list(FIELDS)
    assert all(f["description"] and f["symmetry"] for f in r["fields"])
    assert r["fields"][1]["preset"] == {"c4_amplitude": 0.3}
    lines = capsys.readouterr().out.splitlines()
    for name in FIELDS:
        assert sum(line.startswith(name + " ") for line in lines) == 1
    with pytest.raises(SystemExit) as e:  # checked while parsing, before any import of the stack
        main(["--out", str(tmp_path / "g"), "--field", "nope"])
    assert e.value.code == 2 and "--field: unknown field 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "g").exists()


# ----------------------------------------------------------------------------- envs and flight


def test_envs_accept_a_field_name():
    from downwash_envs.config import build_field, make_config
    from downwash_envs.follower import DownwashFollowerEnv

    assert isinstance(build_field("momentum"), MomentumWake)
    assert make_config({"field": "so2-c4", "swirl": 0.2}).field == "so2-c4"  # knobs on a so2 name: fine
    with pytest.raises(ConfigError, match="DownwashField"):
        make_config({"field": "momentum", "swirl": 0.2})
    with pytest.raises(ConfigError, match="registered: so2"):
        make_config({"field": "nope"})
    with pytest.raises(ConfigError, match="thrust_scale"):
        make_config({"field": "momentum:thrust_scale=-1"})
    env = DownwashFollowerEnv(field="momentum", reference="hover", separation=0.8)
    try:
        obs, _ = env.reset(seed=0)
        assert isinstance(env.simulator.field, MomentumWake)
        for _ in range(10):
            obs, reward, terminated, truncated, _ = env.step(np.zeros(3, np.float32))
            assert np.all(np.isfinite(obs)) and np.isfinite(reward)
    finally:
        env.close()


@pytest.mark.parametrize("name", NAMES)
def test_short_flight_under_a_hovering_leader(name):
    from sim.flight import fly
    from sim.scene import build_scene
    from downwash_trajectories import Hover, stack

    leader = np.array([0.0, 0.0, 2.5])
    ref = stack([Hover(leader, n_worlds=1), Hover(leader - [0.05, 0.0, 0.7], n_worlds=1)])
    log = fly(build_scene(), ref, [0], 1.5, field=make_field(name))[0]
    assert log.meta["status"] == Status.OK, log.meta.get("message")
    assert np.all(np.isfinite(log["pos"])) and np.all(np.isfinite(log["field_mean"]))
    assert np.abs(log["field_mean"]).max() > 0.1  # the follower was in the wake
