"""Named N-vehicle scenes: who flies where, ready to fly (2-8 vehicles from one quad.xml).

A preset is the vehicles (names and roles, top of the stack first), one reference per
vehicle and a flight duration. `make_preset("stack3")` or `make_preset("stack:n=6")`
gives it; `preset.scene()` compiles the MuJoCo scene, `preset.reference(W)` the stacked
reference of W worlds. Every vehicle's wake acts on every other vehicle (the field is
evaluated on every ordered pair and combined by the aggregation law, `sim.aggregation`).

| name | vehicles | what it exercises |
|---|---|---|
| pair | 2 | the paper's: Alpha hovers, Bravo flies a lemniscate 0.6 m beneath |
| stack3 | 3 | a vertical stack, 0.6 m apart: each vehicle in the wake of the one above, the lower ones on small lemniscates |
| stack4 | 4 | the same with four (the bottom one beneath three wakes) |
| stack:n=N | N = 2-8 | the same with N (spacing 0.6 m, or `spacing=`) |
| swap | 3 | two vehicles at different heights cross beneath a hovering third, in opposite directions |
| formation5 | 5 | every vehicle moving: horizontal circles at five heights, alternating direction, so each passes through the wakes above it |

Followers' lemniscates are phase-shifted so that no two move in step. A start in which
two vehicles lie inside each other's collision ellipsoid is refused before any flight
(`sim.scene.check_clearance`).

Every preset's vehicles are the paper quad. `preset.with_kinds(["x500", "paper_quad", ...])`
gives the same preset with vehicles of other kinds (`downwash_core.vehicles`), one per
vehicle, for its `scene()`; the simulator still flies every vehicle with `SimConfig.quad`.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Callable

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import LEADER_POSITION
from downwash_core.roles import MAX_VEHICLES, VEHICLE_NAMES, Role
from downwash_core.vehicles import PAPER_QUAD, VEHICLES
from sim.scene import Scene, build_scene, check_clearance, resolve_kinds
from downwash_trajectories.base import Reference
from downwash_trajectories.combinators import StackedReference, TimeShifted, stack
from downwash_trajectories.primitives import Circle, Hover, Lemniscate, Transect

__all__ = ["Preset", "PRESETS", "make_preset", "parse_preset_spec", "SWARM_SIZES"]

SWARM_SIZES = (2, MAX_VEHICLES)  # a preset has 2-8 vehicles: one leader and at least one other
_TOP = np.array(LEADER_POSITION)  # m, where the top vehicle of every preset flies
_MIN_HEIGHT = 0.6  # m, the lowest a preset puts a vehicle (well above the 0.03 m ground check)


@dataclass(frozen=True)
class Preset:
    """Named vehicles and their references.

    name: the spec it was made from; vehicles: (name, role) in scene order, the top first;
    make_refs(n_worlds) -> one Reference per vehicle; duration: s, the default flight;
    params: the parameters (provenance); kinds: each vehicle's kind name
    (`downwash_core.vehicles.VEHICLES`), empty for all the paper quad (see `with_kinds`).
    """

    name: str
    description: str
    vehicles: tuple[tuple[str, Role], ...]
    make_refs: Callable[[int], list[Reference]] = field(repr=False)
    duration: float
    params: dict[str, Any] = field(default_factory=dict)
    kinds: tuple[str, ...] = ()

    @property
    def n_vehicles(self) -> int:
        return len(self.vehicles)

    def with_kinds(self, kinds: Any) -> "Preset":
        """This preset with vehicles of other kinds: one name (all of it) or one per vehicle,
        top first; ConfigError for an unknown name or a wrong count."""
        resolved = resolve_kinds(kinds, self.n_vehicles)
        for k in resolved:
            if VEHICLES.get(k.name) is not k:  # a name keeps the preset's provenance short and stable
                raise ConfigError(f"kinds: a preset takes registered vehicle names ({', '.join(VEHICLES)}), "
                                  f"got {k.name!r}")
        names = tuple(k.name for k in resolved)
        return dataclasses.replace(self, kinds=() if all(k == PAPER_QUAD for k in resolved) else names)

    def scene(self, **kwargs: Any) -> Scene:
        """The compiled MuJoCo scene of these vehicles (`sim.scene.build_scene` keywords; `kinds`
        defaults to the preset's)."""
        if self.kinds:
            kwargs.setdefault("kinds", self.kinds)
        return build_scene(self.vehicles, **kwargs)

    def reference(self, n_worlds: int = 1, radius_xy: float = 0.26, radius_z: float = 0.08) -> StackedReference:
        """The stacked reference of `n_worlds` identical worlds; ConfigError if two vehicles start
        inside each other's collision ellipsoid (radii m, as `SimConfig`'s)."""
        ref = stack(self.make_refs(int(n_worlds)))
        check_clearance(ref(np.zeros(ref.n_worlds)).pos, [n for n, _ in self.vehicles], radius_xy, radius_z)
        return ref

    def describe(self) -> dict[str, Any]:
        out = {"preset": self.name, "vehicles": [n for n, _ in self.vehicles],
               "roles": [r.value for _, r in self.vehicles], "params": dict(self.params)}
        if self.kinds:  # only when not all the paper quad: the presets' provenance is unchanged
            out["kinds"] = list(self.kinds)
        return out


def _roles(n: int) -> tuple[tuple[str, Role], ...]:
    return tuple((VEHICLE_NAMES[i], Role.LEADER if i == 0 else Role.FOLLOWER) for i in range(n))


def _stack(n: int = 3, spacing: float = 0.6) -> Preset:
    """A vertical stack of n: the top hovers, the others fly small lemniscates beneath it."""
    if not SWARM_SIZES[0] <= n <= SWARM_SIZES[1]:
        raise ConfigError(f"n: a stack has {SWARM_SIZES[0]}-{SWARM_SIZES[1]} vehicles, got {n}")
    if not 0.3 <= spacing <= 2.0:
        raise ConfigError(f"spacing: allowed 0.3-2.0 m (closer collides, farther leaves little wake), got {spacing}")
    top = _TOP.copy()
    top[2] = max(top[2], _MIN_HEIGHT + (n - 1) * spacing)  # tall stacks start higher, never below 0.6 m
    period = 10.0  # s

    def make_refs(W: int) -> list[Reference]:
        refs: list[Reference] = [Hover(top, n_worlds=W, duration=period)]
        for k in range(1, n):
            centre = top - np.array([0.0, 0.0, k * spacing])
            lem = Lemniscate(centre, half_length=0.3, half_width=0.15, period=period, n_worlds=W)
            refs.append(TimeShifted(lem, np.full(W, (k - 1) * period / (n - 1))) if k > 1 else lem)
        return refs

    name = {3: "stack3", 4: "stack4"}.get(n, f"stack:n={n}") if spacing == 0.6 else f"stack:n={n},spacing={spacing}"
    return Preset(name, f"a vertical stack of {n}, {spacing} m apart", _roles(n), make_refs, period,
                  {"n": n, "spacing": spacing})


def _swap(speed_period: float = 8.0) -> Preset:
    """Two vehicles cross beneath a hovering third, at 0.6 m and 1.0 m below it, in opposite directions."""

    def make_refs(W: int) -> list[Reference]:
        upper = Transect(_TOP - [0.0, 0.0, 0.6], x_offset=0.0, half_length=1.0, period=speed_period, n_worlds=W)
        lower = Transect(_TOP - [0.0, 0.0, 1.0], x_offset=0.0, half_length=1.0, period=speed_period, n_worlds=W)
        return [Hover(_TOP, n_worlds=W, duration=speed_period), upper,
                TimeShifted(lower, np.full(W, speed_period / 2.0))]  # starts at the far end: they cross

    return Preset("swap", "two vehicles cross beneath a third, in opposite directions", _roles(3), make_refs,
                  speed_period, {"period": speed_period})


def _formation5(radius: float = 0.4, speed: float = 0.5, spacing: float = 0.45) -> Preset:
    """Five vehicles on horizontal circles at five heights, alternate ones turning the other way."""

    def make_refs(W: int) -> list[Reference]:
        return [Circle(_TOP - [0.0, 0.0, k * spacing], radius=radius, speed=speed if k % 2 == 0 else -speed,
                       phase=k * 2.0 * np.pi / 5.0, n_worlds=W) for k in range(5)]

    lap = 2.0 * np.pi * radius / speed
    return Preset("formation5", "five vehicles, all moving, each passing through the wakes above it", _roles(5),
                  make_refs, lap, {"radius": radius, "speed": speed, "spacing": spacing})


# name -> (factory, its parameters and their types): `stack` is the parametrised family
_FACTORIES: MappingProxyType = MappingProxyType({
    "pair": (lambda: _stack(2), {}),
    "stack3": (lambda: _stack(3), {}),
    "stack4": (lambda: _stack(4), {}),
    "stack": (_stack, {"n": int, "spacing": float}),
    "swap": (_swap, {}),
    "formation5": (_formation5, {}),
})
PRESETS = tuple(_FACTORIES)
_SPEC = re.compile(r"^([a-z0-9]+)(?::(.*))?$")


def parse_preset_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """'stack:n=6,spacing=0.5' -> ('stack', {'n': 6, 'spacing': 0.5}); ConfigError naming what is allowed."""
    m = _SPEC.match(spec.strip()) if isinstance(spec, str) else None
    if m is None or m.group(1) not in _FACTORIES:
        raise ConfigError(f"preset: unknown {spec!r}; allowed: {', '.join(PRESETS)} (stack takes n=2-8, spacing=)")
    name, rest = m.group(1), m.group(2)
    types = _FACTORIES[name][1]
    params: dict[str, Any] = {}
    for part in filter(None, (rest or "").split(",")):
        key, eq, value = part.partition("=")
        if not eq or key.strip() not in types:
            allowed = ", ".join(f"{k}=" for k in types) or "no parameters"
            raise ConfigError(f"preset {name!r}: bad parameter {part!r}; allowed: {allowed}")
        try:
            params[key.strip()] = types[key.strip()](value)
        except ValueError:
            raise ConfigError(f"preset {name!r}: {key}={value!r} is not a {types[key.strip()].__name__}") from None
    return name, params


def make_preset(spec: str) -> Preset:
    """The preset named by `spec` (see the module table); ConfigError for an unknown name or a bad parameter."""
    name, params = parse_preset_spec(spec)
    return _FACTORIES[name][0](**params)
