"""Named ground-truth fields and the one grammar that selects a field from a string.

A field spec (the experiments' `--field`, the envs' `field=` string) is one of::

    ""                       the default field, `so2`
    NAME                     a registered field:              so2, momentum
    NAME:KEY=VALUE[,...]     a registered field with parameters: so2:strength=8,
                             momentum:thrust_scale=1.2,drag=false
    fitted:PATH              a registered field with the constants fitted to real flights,
                             the JSON `downwash.field_fit.write_fitted` writes (with the
                             digest of the data it was fitted to; sim.fields.fitted)
    MODULE:FACTORY           an import path: MODULE.FACTORY() returns the field
                             object (no parameters):          mypkg.fields:make

The part before the first ':' is looked up in the registry first. A registered name
takes only KEY=VALUE parameters after its colon; anything else that contains a ':'
is an import path, which takes no '=' after its colon. Registered names contain no
'.', so a dotted module path is never taken for one; a top-level module that shares
a registered name (say a module `momentum`) must be reached through its package
path. Parameter values are converted to the parameter's type (float; int; bool:
true/false/1/0/yes/no/on/off): the one spec grammar of `downwash_core.registry`, whose
`Registry` `FIELDS` is. An unknown name or parameter, a bad value, or an import that
fails raises ConfigError naming what is allowed, before any work.

The `so2*` entries return a plain `sim.field.DownwashField`, so that the same law with
the same constants has the same provenance (and pipeline key) however it is spelled:
`so2-c4` and `so2:c4_amplitude=0.3` name one collection. `register_field` adds a
user's field under a name, and a plugin adds one through the entry-point group
`downwash_testbed.plugins` (`downwash_core.registry`).
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from downwash_core.errors import ConfigError
from downwash_core.registry import Entry, Registry
from sim.field import DownwashField
from sim.fields.jet import JetWake
from sim.fields.momentum import MomentumWake
from sim.fields.pybullet_law import PybulletDownwash
from sim.fields.shed import ShedWake

__all__ = ["FieldEntry", "FIELDS", "DEFAULT_FIELD", "register_field", "make_field", "parse_field_spec",
           "resolve_field_spec", "field_parameters"]

DEFAULT_FIELD = "so2"


@dataclass(frozen=True)
class FieldEntry(Entry):
    """One registered field (a `downwash_core.registry.Entry`): factory(**params) -> field object;
    params {parameter: float | int | bool} that the factory accepts; preset: the parameters the
    entry fixes unless overridden (shown by the listing); symmetry: one line, what the law keeps."""

    symmetry: str = ""


def field_parameters(cls: type) -> dict[str, type]:
    """{name: float | int | bool} of a dataclass's public fields, from their annotations."""
    out: dict[str, type] = {}
    for f in dataclasses.fields(cls):
        text = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
        out[f.name] = bool if text.startswith("bool") else int if text.startswith("int") else float
    return out


# the fields by name, in registration order (plugins' last); registered names contain no '.', so a
# dotted module path is never taken for one
FIELDS = Registry("field", group="fields", entry_type=FieldEntry, default=DEFAULT_FIELD,
                  reserved={"fitted": "the spec grammar's (fitted:PATH)"},
                  description="ground-truth downwash fields (--field NAME[:KEY=VALUE,...])")
_REGISTRY = FIELDS  # its former name (tests remove what they register with _REGISTRY.pop)


@FIELDS.adder
def register_field(name: str, factory: Callable[..., Any], description: str, symmetry: str,
                   params: Mapping[str, type] | None = None, preset: Mapping[str, Any] | None = None,
                   defaults: Mapping[str, Any] | None = None) -> FieldEntry:
    """Register `factory` under `name` (lowercase letters, digits, '-', '_'; not yet taken); params:
    {name: type} a spec may set (default: the factory's typed fields or keyword parameters,
    `downwash_core.registry.infer_params`); defaults: the factory's values (read from it unless
    given), for the listing."""
    return FIELDS.register(name, factory, description, params=params, preset=preset, defaults=defaults,
                           symmetry=symmetry)


def make_field(name: str, **params: Any) -> Any:
    """The registered field `name` built with typed `params`, e.g. make_field("momentum", thrust_scale=1.5)."""
    return FIELDS.make(name, **params)


def parse_field_spec(spec: str, label: str = "field") -> tuple[str, str, Any]:
    """("name", NAME, {typed params}) for a registered field, ("fitted", PATH, None) for a fitted
    one, or ("import", MODULE, FACTORY).

    ConfigError (prefixed with `label`) for an unknown name or parameter, a malformed
    parameter list, or a malformed import path; nothing is imported or built here.
    """
    if not isinstance(spec, str):
        raise ConfigError(f"{label}: expected a field spec string, got {type(spec).__name__}")
    spec = spec.strip() or DEFAULT_FIELD
    head, colon, tail = spec.partition(":")
    if head == "fitted" and colon:  # fitted:PATH, a fitted field's JSON (sim.fields.fitted)
        if not tail.strip():
            raise ConfigError(f"{label}: {spec!r}: expected fitted:PATH, the JSON of downwash.field_fit.write_fitted")
        return "fitted", tail.strip(), None
    if head in FIELDS:
        return "name", head, FIELDS.entry(head).parse_params(tail if colon else "", spec, label)
    registered = ", ".join(FIELDS)
    if not colon:
        raise ConfigError(f"{label}: unknown field {spec!r}; registered: {registered}; or a MODULE:FACTORY "
                          "import path (e.g. mypkg.fields:make_field)")
    if "=" in tail:
        raise ConfigError(f"{label}: unknown field {head!r} in {spec!r}; registered: {registered} "
                          "(a MODULE:FACTORY import path takes no KEY=VALUE parameters)")
    if tail.count(":") or not head or not tail:
        raise ConfigError(f"{label}: expected a registered field ({registered}) or MODULE:FACTORY "
                          f"(e.g. mypkg.fields:make_field), got {spec!r}")
    return "import", head, tail


def resolve_field_spec(spec: str, label: str = "field") -> Any:
    """The field object a spec names (see the module docstring); ConfigError otherwise.

    Checks only what the spec itself says; callers check the object's outputs
    (`sim.field.check_field`) and provenance.
    """
    kind, target, detail = parse_field_spec(spec, label)
    if kind == "fitted":
        from sim.fields.fitted import resolve_fitted_spec  # it builds on this registry

        return resolve_fitted_spec(target, label)
    if kind == "name":
        try:
            return FIELDS.entry(target).make(**detail)
        except ConfigError as e:  # a value the field's constructor rejects: say which spec
            raise ConfigError(f"{label}: {spec.strip() or DEFAULT_FIELD!r}: {e}") from e
    module_name, factory_name = target, detail
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise ConfigError(f"{label}: cannot import module {module_name!r}: {e}") from e
    factory = getattr(module, factory_name, None)
    if not callable(factory):
        raise ConfigError(f"{label}: {module_name!r} has no callable {factory_name!r}")
    obj = factory()
    if not callable(obj):
        raise ConfigError(f"{label}: {spec} returned {type(obj).__name__}, which is not callable as "
                          "field(p_a, v_a, R_a, p_b, v_b)")
    return obj


# ----------------------------------------------------------------------------- built-in fields
_SO2_PARAMS = field_parameters(DownwashField)
_SO2_SYMMETRY = "SO(2) and reflections about the leader axis; translation"
# Knob strengths of the presets: each large enough to matter against the turbulence
# (10 % of the local force) and the models' validation error, yet inside what the
# envs accept (|c4| < 1). c4 0.3: +/-30 % lobes of the push off the axis, the order
# of a four-rotor wake's imprint near the vehicle. swirl 0.4: a tangential force of
# 0.4 rho^2 times the push, as large as the radial one at the wake's edge (rho ~ 1).
# skew 0.35 s/m: about 1 / (downwash speed ~3 m/s); at 1 m/s leader speed the wake
# 1 m down trails by 0.35 m, 1.6 sigma of its width.
register_field(
    "so2", DownwashField,
    "the paper's synthetic downwash (sim.field.DownwashField); the default",
    _SO2_SYMMETRY, _SO2_PARAMS)
register_field(
    "so2-c4", DownwashField,
    "so2 with a four-lobe (rotor-imprint) modulation of the push with the leader's yaw, c4_amplitude 0.3",
    "C4 (quarter turns) about the leader axis only; translation", _SO2_PARAMS, {"c4_amplitude": 0.3})
register_field(
    "so2-swirl", DownwashField,
    "so2 with a tangential (swirling) lateral force, swirl 0.4",
    "SO(2) about the leader axis, not reflections (chiral); translation", _SO2_PARAMS, {"swirl": 0.4})
register_field(
    "so2-skew", DownwashField,
    "so2 with the wake trailing a laterally moving leader, skew 0.35 s/m",
    "SO(2) about the leader axis only while the leader does not move sideways; translation",
    _SO2_PARAMS, {"skew": 0.35})
_SHED_OWN = {"rate_hz": float, "max_age": float, "convection": float}


def _shed_wake(**params: Any) -> ShedWake:
    """`ShedWake` with its own constants, the others those of its momentum jet."""
    own = {k: params.pop(k) for k in list(params) if k in _SHED_OWN}
    return ShedWake(law=MomentumWake(**params), **own)


register_field(
    "momentum", MomentumWake,
    "physics wake: momentum-theory jet (Pope/Hussein constants), acting on the follower's rotors and airframe",
    _SO2_SYMMETRY, field_parameters(MomentumWake))
register_field(
    "shed", _shed_wake,
    "a wake with memory: the momentum jet shed by the rotors, carried down by its own speed and the wind",
    "as momentum below a leader hovering in still air; none once its wake trails (it moves, tilts or the wind blows)",
    {**field_parameters(MomentumWake), **_SHED_OWN},
    defaults={**dataclasses.asdict(MomentumWake()),
              **{f.name: f.default for f in dataclasses.fields(ShedWake) if f.name in _SHED_OWN}})
register_field(
    "jet", JetWake,
    "Bauersfeld et al.'s turbulent jet (RA-L 2024: B_d 10.11, S 0.0767, s0 -5.8 l), acting on the follower as momentum",
    _SO2_SYMMETRY, field_parameters(JetWake))
register_field(
    "pybullet", PybulletDownwash,
    "gym-pybullet-drones' law (BaseAviary._downwash, cf2x constants): a Gaussian push ~1/dz^2, per 0.027 kg",
    _SO2_SYMMETRY, field_parameters(PybulletDownwash))
