"""The one registry type and spec grammar (downwash_core/registry.py): registration and its refusals,
lookup, typed parameters and their round trips, every error, listings, and the registries moved
onto it (fields, models, vehicles, presets, sensors) keeping their public names."""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError
from downwash_core.registry import Entry, Registry, UnknownNameError, convert_value, format_spec, infer_params, \
    param_type, type_name


def widget(size: int = 3, gain: float = 1.5, loud: bool = False, label: str = "w",
           mean: tuple[float, ...] = (0.0, 0.0), corner: tuple[int, int] = (1, 2)):
    """A widget: its arguments, back."""
    if gain < 0:
        raise ConfigError(f"gain: allowed >= 0, got {gain}")
    return {"size": size, "gain": gain, "loud": loud, "label": label, "mean": mean, "corner": corner}


@pytest.fixture
def reg():
    r = Registry("widget", hint="see the widget docs")
    r.register("plain", widget, "a widget with every parameter")
    r.register("fixed", widget, "a widget of one size", params={"gain": float}, preset={"gain": 2.5})
    r.register("bare", lambda: "bare", "a widget without parameters")
    return r


# ----------------------------------------------------------------------------- registering
def test_register_infers_typed_parameters_and_defaults(reg):
    e = reg.entry("plain")
    assert dict(e.params) == {"size": int, "gain": float, "loud": bool, "label": str, "mean": tuple[float, ...],
                              "corner": tuple[int, int]}
    assert dict(e.defaults) == {"size": 3, "gain": 1.5, "loud": False, "label": "w", "mean": (0.0, 0.0),
                                "corner": (1, 2)}
    assert e.kind == "widget" and e.plugin is None and e.description == "a widget with every parameter"
    assert reg.entry("fixed").params == {"gain": float} and reg.entry("fixed").preset == {"gain": 2.5}


@pytest.mark.parametrize("name, factory, kw, match", [
    ("Bad", widget, {}, r"widget name 'Bad': use lowercase letters, digits, '-' and '_' \(no '.' or ':'\)"),
    ("a.b", widget, {}, "use lowercase"),
    ("a:b", widget, {}, "use lowercase"),
    (3, widget, {}, "widget name 3: use lowercase"),
    ("plain", widget, {}, "widget name 'plain' is already registered"),
    ("new", 42, {}, "widget 'new': factory must be callable, got int"),
    ("new", widget, {"description": "two\nlines"}, "description: expected one line"),
    ("new", widget, {"params": {"size": list}}, r"parameter 'size': .* is not a type of the grammar"),
    ("new", widget, {"params": {"mean": tuple[float, int]}}, "is not a type of the grammar"),
    ("new", widget, {"params": {"not an id": int}}, "is not a type of the grammar"),
    ("new", widget, {"params": {"size": int}, "preset": {"gain": 1.0}},
     r"preset \['gain'\] of no parameter; allowed: size"),
])
def test_register_refuses_what_it_cannot_hold(reg, name, factory, kw, match):
    with pytest.raises(ConfigError, match=match):
        reg.register(name, factory, **{"description": "one line", **kw})
    assert "new" not in reg


def test_reserved_names_and_a_name_pattern_of_its_own():
    r = Registry("thing", name_pattern=r"[a-z]+", name_rule="lower case letters", reserved={"fitted": "the grammar's"})
    with pytest.raises(ConfigError, match="^thing name 'fitted' is the grammar's$"):
        r.register("fitted", widget)
    with pytest.raises(ConfigError, match="thing name 'a_b': use lower case letters"):
        r.register("a_b", widget)


def test_a_registry_of_objects_returns_the_objects():
    r = Registry("kind", objects=True)
    marker = object()
    r.register("one", None, "an object", obj=marker, params={})
    r.register("cls", dict, "a class: the object is the factory", params={})
    assert r["one"] is marker and r.get("one") is marker and r.make("one") is marker
    assert r["cls"] is dict and list(r.values()) == [marker, dict] and r.entry("one").obj is marker


# ----------------------------------------------------------------------------- lookup
def test_lookup_as_a_mapping(reg):
    assert list(reg) == ["plain", "fixed", "bare"] == list(reg.names()) and len(reg) == 3
    assert "plain" in reg and "nope" not in reg and 3 not in reg and ["x"] not in reg
    assert isinstance(reg["plain"], Entry) and reg.get("nope") is None and reg.get("nope", 1) == 1
    assert [e.name for e in reg.entries()] == ["plain", "fixed", "bare"]
    assert reg.peek("plain") is reg["plain"] and reg.peek("nope") is None


def test_an_unknown_name_names_the_allowed_ones_and_is_a_key_error(reg):
    with pytest.raises(UnknownNameError) as e:
        reg["nope"]
    assert str(e.value) == "widget: unknown 'nope'; allowed: plain, fixed, bare; see the widget docs"
    assert isinstance(e.value, ConfigError) and isinstance(e.value, KeyError) and isinstance(e.value, ValueError)
    with pytest.raises(ConfigError, match=r"^--w: unknown 'nope'"):
        reg.entry("nope", label="--w")
    with pytest.raises(ConfigError, match="allowed: none registered"):
        Registry("empty")["x"]


def test_pop_removes_an_entry(reg):
    assert reg.pop("bare").name == "bare" and "bare" not in reg
    assert reg.pop("bare", None) is None
    with pytest.raises(KeyError, match="unknown 'bare'"):
        reg.pop("bare")


# ----------------------------------------------------------------------------- specs
def test_a_spec_gives_typed_values(reg):
    name, params = reg.parse(" plain:size=4, gain = 2,loud=Yes,label=big,mean=1,2,3,corner=5,6 ")
    assert name == "plain" and params == {"size": 4, "gain": 2.0, "loud": True, "label": "big",
                                          "mean": (1.0, 2.0, 3.0), "corner": (5, 6)}
    assert type(params["gain"]) is float and type(params["size"]) is int
    assert reg.parse("plain") == ("plain", {}) and reg.parse("plain:") == ("plain", {})
    assert reg.parse("plain:mean=") == ("plain", {"mean": ()})
    assert reg.resolve("fixed") == widget(gain=2.5) and reg.resolve("fixed:gain=3").get("gain") == 3.0
    assert reg.make("plain", size=5)["size"] == 5


def test_the_empty_spec_is_the_default():
    r = Registry("widget", default="plain")
    r.register("plain", widget)
    assert r.parse("") == ("plain", {}) and r.parse("  ") == ("plain", {})


@pytest.mark.parametrize("spec, match", [
    ("nope", r"^widget: unknown 'nope'; allowed: plain, fixed, bare; see the widget docs$"),
    ("nope:size=1", r"^widget: unknown 'nope' in 'nope:size=1'; allowed: plain"),
    ("", r"^widget: unknown ''"),
    ("plain:size", r"^widget: 'plain:size': widget 'plain': parameters are KEY=VALUE, got 'size'; allowed: size, gain"),
    ("plain:colour=1", r"^widget: 'plain:colour=1': widget 'plain' has no parameter 'colour'; allowed: size, gain, "
                       r"loud, label, mean, corner$"),
    ("bare:x=1", r"widget 'bare' has no parameter 'x'; allowed: no parameters$"),
    ("plain:size=1,size=2", r"^widget: 'plain:size=1,size=2': parameter 'size' given twice$"),
    ("plain:size=2.5", r"widget 'plain' parameter size='2.5': expected an integer$"),
    ("plain:gain=fast", r"parameter gain='fast': expected a number$"),
    ("plain:gain=inf", r"parameter gain='inf': must be finite$"),
    ("plain:gain=nan", r"parameter gain='nan': must be finite$"),
    ("plain:loud=maybe", r"parameter loud='maybe': expected a bool \(true/1/yes/on or false/0/no/off\)$"),
    ("plain:mean=1,x", r"parameter mean='1,x': expected a comma list of numbers; 'x': expected a number$"),
    ("plain:corner=1,2,3", r"parameter corner='1,2,3': expected 2 integers, comma-separated, got 3$"),
    ("plain:size=1,2", r"parameters are KEY=VALUE, got '2'"),  # only a tuple goes on after a comma
    ("plain:gain=-1", r"^widget: 'plain:gain=-1': gain: allowed >= 0, got -1.0$"),  # the factory's own, with the spec
])
def test_every_bad_spec_is_one_error_naming_the_spec_and_what_is_allowed(reg, spec, match):
    with pytest.raises(ConfigError, match=match):
        reg.resolve(spec)


def test_a_spec_that_is_no_string_and_a_label(reg):
    with pytest.raises(ConfigError, match="^--widget: expected a widget spec NAME"):
        reg.parse(3, label="--widget")
    with pytest.raises(ConfigError, match=r"^--widget: 'plain:size=x': widget 'plain' parameter size='x'"):
        reg.parse("plain:size=x", label="--widget")


def test_make_refuses_unknown_parameters(reg):
    with pytest.raises(ConfigError, match=r"widget 'fixed' has no parameter\(s\) \['size'\]; allowed: gain"):
        reg.make("fixed", size=3)


_VALUES = {int: st.integers(-10**6, 10**6), float: st.floats(allow_nan=False, allow_infinity=False),
           bool: st.booleans(), str: st.text("abcxyz_-./ ", min_size=1).map(str.strip).filter(bool),
           tuple[float, ...]: st.tuples(st.floats(-1e9, 1e9)) | st.tuples(st.floats(-1e9, 1e9), st.floats(-1, 1)),
           tuple[int, int]: st.tuples(st.integers(), st.integers())}


@settings(max_examples=200, deadline=None)
@given(st.fixed_dictionaries({}, optional={"size": _VALUES[int], "gain": _VALUES[float], "loud": _VALUES[bool],
                                           "label": _VALUES[str], "mean": _VALUES[tuple[float, ...]],
                                           "corner": _VALUES[tuple[int, int]]}))
def test_format_spec_and_parse_round_trip(params):
    r = Registry("widget")
    r.register("plain", widget)
    spec = format_spec("plain", params)
    assert r.parse(spec) == ("plain", params)
    assert format_spec(*r.parse(spec)) == spec


@pytest.mark.parametrize("value", [float("nan"), float("inf"), "a,b", "a=b", " padded", None, object(), ("x,y",)])
def test_format_spec_refuses_what_the_grammar_cannot_read_back(value):
    with pytest.raises(ConfigError, match="format_spec: key="):
        format_spec("w", {"key": value})


@pytest.mark.parametrize("text, kind, value", [
    ("7", int, 7), (" 7 ", float, 7.0), ("1e-3", float, 1e-3), ("OFF", bool, False), ("on", bool, True),
    ("x=y", str, "x=y"), ("1, 2", tuple[int, ...], (1, 2)), ("", tuple[str, ...], ()),
    ("a,b", tuple[str, str], ("a", "b")), ("0,1,yes", tuple[bool, ...], (False, True, True)),
])
def test_convert_value(text, kind, value):
    out = convert_value(text, kind)
    assert out == value and type(out) is type(value)


# ----------------------------------------------------------------------------- types
def test_param_types_from_annotations_and_defaults():
    assert param_type(int) is int and param_type(Optional[float]) is float and param_type(str | None) is str
    assert param_type(float | np.ndarray) is float  # one arm of the grammar
    assert param_type(int | str) is None and param_type(np.ndarray) is None and param_type(dict) is None
    assert param_type(Sequence[int]) == tuple[int, ...] and param_type(list[float]) == tuple[float, ...]
    assert param_type(tuple[int, int]) == tuple[int, int] and param_type(tuple[int, str]) is None
    assert param_type("unresolved", 2) is int and param_type("unresolved", (1.0, 2.0)) == tuple[float, ...]
    assert param_type("unresolved", (1, "a")) is None and param_type("unresolved") is None
    assert [type_name(t) for t in (int, tuple[float, ...], tuple[int, int])] == ["int", "tuple[float, ...]",
                                                                                 "tuple[int, int]"]


def test_infer_params_of_a_dataclass_a_class_and_a_function():
    @dataclasses.dataclass(frozen=True)
    class Law:
        strength: float = 2.0
        rings: int = 4
        table: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2))  # no type of the grammar
        _private: float = 1.0

    class Model:
        def __init__(self, feature_set: str | None = None, hidden: Sequence[int] = (32,), other: object = None):
            pass

    params, defaults = infer_params(Law)
    assert params == {"strength": float, "rings": int} and defaults["strength"] == 2.0 and "table" in defaults
    assert infer_params(Model) == ({"feature_set": str, "hidden": tuple[int, ...]},
                                   {"feature_set": None, "hidden": (32,), "other": None})
    assert infer_params(lambda a, *args, b=1.5, **kw: None) == ({"b": float}, {"b": 1.5})
    assert infer_params(len) == ({}, {})  # a builtin: no signature


def test_listing_describes_each_entry(reg):
    @dataclasses.dataclass(frozen=True)
    class Noted(Entry):
        note: str = ""

    r = Registry("widget", entry_type=Noted)
    r.register("fixed", widget, "a widget of one gain", params={"gain": float, "mean": tuple[float, ...]},
               preset={"gain": 2.5}, note="extra")
    (d,) = r.listing()
    assert d == {"name": "fixed", "description": "a widget of one gain", "note": "extra", "plugin": None,
                 "params": {"gain": {"type": "float", "default": 2.5}, "mean": {"type": "tuple[float, ...]",
                                                                                "default": (0.0, 0.0)}},
                 "preset": {"gain": 2.5}}


# ----------------------------------------------------------------------------- the registries on it
def test_the_registries_are_registries_with_their_public_names():
    from downwash.registry import MODEL_KINDS, make_model
    from downwash_core.vehicles import PAPER_QUAD, VEHICLES, get_vehicle, register_vehicle
    from sim.fields.registry import FIELDS, make_field
    from sim.presets import PRESETS, make_preset, parse_preset_spec
    from sim.sensors import SENSORS, make_sensor

    for r in (FIELDS, MODEL_KINDS, VEHICLES, PRESETS, SENSORS):
        assert isinstance(r, Registry) and r.group in ("fields", "models", "vehicles", "presets", "sensors")
    assert VEHICLES["paper_quad"] is PAPER_QUAD and get_vehicle("paper_quad") is PAPER_QUAD
    assert MODEL_KINDS["equivariant"] is type(make_model("equivariant"))
    assert make_field("so2", strength=3.0).strength == 3.0
    assert parse_preset_spec("stack:n=5") == ("stack", {"n": 5}) and make_preset("stack:n=5").n_vehicles == 5
    assert make_sensor("mocap_biased", position_bias=0.001).position_bias == 0.001
    assert FIELDS.entry("so2").defaults["strength"] == FIELDS["so2"].make().strength  # the listing's defaults
    with pytest.raises(ConfigError, match="register_vehicle: expected a VehicleKind, got str"):
        register_vehicle("x500")
    with pytest.raises(ConfigError, match="vehicle name 'paper_quad' is already registered"):
        register_vehicle(PAPER_QUAD)


def test_register_vehicle_adds_a_kind_that_scenes_take():
    from downwash_core.vehicles import PAPER_QUAD, VEHICLES, get_vehicle, register_vehicle
    from sim.presets import make_preset

    kind = dataclasses.replace(PAPER_QUAD, name="test_heavy_quad", mass=0.8, description="a heavier paper quad",
                               source="a test: the paper quad at 0.8 kg")
    try:
        assert register_vehicle(kind) is kind and get_vehicle("test_heavy_quad") is kind
        assert list(VEHICLES)[-1] == "test_heavy_quad"
        assert make_preset("pair").with_kinds(["paper_quad", "test_heavy_quad"]).kinds == ("paper_quad",
                                                                                           "test_heavy_quad")
    finally:
        VEHICLES.pop("test_heavy_quad", None)
