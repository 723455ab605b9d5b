"""Named N-vehicle scenes: who flies where, ready to fly (2-8 vehicles from one quad.xml).

A preset is the vehicles (names and roles, top of the stack first), one reference per
vehicle and a flight duration. `make_preset("stack3")` or `make_preset("stack:n=6")` (the
registries' spec grammar, `downwash_core.registry`; `PRESETS` is the registry and `register_preset`
adds to it, as plugins do) gives it; `preset.scene()` compiles the MuJoCo scene,
`preset.reference(W)` the stacked reference of W worlds. Every vehicle's wake acts on every
other vehicle (the field is evaluated on every ordered pair and combined by the aggregation law,
`sim.aggregation`).

| name | vehicles | what it exercises |
|---|---|---|
| pair | 2 | the paper's: Alpha hovers, Bravo flies a lemniscate 0.6 m beneath |
| stack3 | 3 | a vertical stack, 0.6 m apart: each vehicle in the wake of the one above, the lower ones on small lemniscates |
| stack4 | 4 | the same with four (the bottom one beneath three wakes) |
| stack:n=N | N = 2-8 | the same with N (spacing 0.6 m, or `spacing=`) |
| swap | 3 | two vehicles at different heights cross beneath a hovering third, in opposite directions |
| formation5 | 5 | every vehicle moving: horizontal circles at five heights, alternating direction, so each passes through the wakes above it |
| heavy_over_light | 2 | an X500 (2.06 kg) hovers, a paper quad flies the pair's lemniscate 0.8 m beneath it (`separation=`) |
| crazyflie_stack | 4 | four Crazyflie 2.1 stacked 0.25 m apart, as labs fly them: the top hovers, the others on small lemniscates |
| mixed_formation | 5 | formation5's circles with three Crazyflies above two paper quads (a small/large mix, as Neural-Swarm2's) |

Followers' lemniscates are phase-shifted so that no two move in step. A start in which
two vehicles lie inside each other's collision ellipsoid is refused before any flight
(`sim.scene.check_clearance`).

The last three mix vehicle kinds (`downwash_core.vehicles`); the others are paper quads, and
`preset.with_kinds(["x500", "paper_quad", ...])` gives any preset with vehicles of other kinds,
one per vehicle, for its `scene()`. Each vehicle flies its own kind's numbers and each wake
scales with its pair of kinds (`sim.vehicle_params`); a mixed preset's collision ellipsoid is
per pair, scaled by the two vehicles' sizes. Why the mixes are as they are (the default field,
`so2_pair_scale`): a Crazyflie beneath a paper quad is pushed 7.6x as hard as a paper quad
there, beyond its thrust margin (thrust to weight 1.53), and falls to the ground within 3 s
(as in formation5's order with the paper quads on top, and under `momentum` too), so the
small vehicles fly above the large ones; beneath an X500 a paper quad feels 0.24x the pair's
law under `so2` (its light disc loading) but a push on the pair's scale under `momentum`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import LEADER_POSITION
from downwash_core.registry import Registry
from downwash_core.roles import MAX_VEHICLES, SCENE_VEHICLE_NAMES, Role
from downwash_core.vehicles import PAPER_QUAD, VEHICLES
from sim.scene import Scene, build_scene, check_clearance, resolve_kinds
from sim.vehicle_params import collision_radii
from downwash_trajectories.base import Reference
from downwash_trajectories.combinators import StackedReference, TimeShifted, stack
from downwash_trajectories.primitives import Circle, Hover, Lemniscate, Transect

__all__ = ["Preset", "PRESETS", "make_preset", "parse_preset_spec", "register_preset", "SWARM_SIZES"]

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
        inside each other's collision ellipsoid (radii m, as `SimConfig`'s: two paper quads'; per
        pair scaled by the vehicles' sizes, `collision_radii`, as the loop checks them)."""
        ref = stack(self.make_refs(int(n_worlds)))
        check_clearance(ref(np.zeros(ref.n_worlds)).pos, [n for n, _ in self.vehicles],
                        *self.collision_radii(radius_xy, radius_z))
        return ref

    def collision_radii(self, radius_xy: float = 0.26, radius_z: float = 0.08) -> tuple[Any, Any]:
        """Each pair's collision radii (m): the given ones for paper quads, (V, V) arrays for mixed kinds."""
        if not self.kinds:
            return radius_xy, radius_z
        return collision_radii(resolve_kinds(self.kinds, self.n_vehicles), radius_xy, radius_z)

    def describe(self) -> dict[str, Any]:
        out = {"preset": self.name, "vehicles": [n for n, _ in self.vehicles],
               "roles": [r.value for _, r in self.vehicles], "params": dict(self.params)}
        if self.kinds:  # only when not all the paper quad: the presets' provenance is unchanged
            out["kinds"] = list(self.kinds)
        return out


def _roles(n: int) -> tuple[tuple[str, Role], ...]:
    return tuple((SCENE_VEHICLE_NAMES[i], Role.LEADER if i == 0 else Role.FOLLOWER) for i in range(n))


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


def _heavy_over_light(separation: float = 0.8) -> Preset:
    """An X500 leader hovers; a paper quad flies the pair's lemniscate `separation` below it.

    0.8 m: twice the X500's rotor-tip reach (0.39 m) below it, clear of its legs, and inside the
    X500's near wake (momentum theory: the jet of its 0.28 m equivalent disc holds its speed to
    B d0 = 5.8 x 0.39 m = 2.3 m down), where the two fields differ most (see the module docstring).
    """
    if not 0.6 <= separation <= 2.0:
        raise ConfigError(f"separation: allowed 0.6-2.0 m (closer reaches the X500's legs, 0.39 m rotor tips and "
                          f"its collision ellipsoid; farther leaves little wake), got {separation}")
    period = 10.0  # s, the pair's

    def make_refs(W: int) -> list[Reference]:
        return [Hover(_TOP, n_worlds=W, duration=period),
                Lemniscate(_TOP - [0.0, 0.0, separation], half_length=0.3, half_width=0.15, period=period, n_worlds=W)]

    name = "heavy_over_light" if separation == 0.8 else f"heavy_over_light:separation={separation}"
    return Preset(name, f"an X500 hovers, a paper quad flies a lemniscate {separation} m beneath it", _roles(2),
                  make_refs, period, {"separation": separation}, kinds=("x500", "paper_quad"))


def _crazyflie_stack() -> Preset:
    """Four Crazyflie 2.1 stacked 0.25 m apart: the stack preset at a Crazyflie lab's spacing.

    0.25 m (labs fly Crazyflies 0.15-0.3 m apart): under the default field a Crazyflie 0.25 m
    below another feels what a paper quad 0.25 m below a paper quad would (`so2_pair_scale`
    is 1 for a pair of one kind), 5.1 m/s^2 on the axis, about its thrust margin (0.53 g);
    the lower ones cross the axes above on the stack's small lemniscates, not hover in them.
    """
    top, spacing, period = _TOP.copy(), 0.25, 10.0  # m, m, s: the stack's period and lemniscates

    def make_refs(W: int) -> list[Reference]:
        refs: list[Reference] = [Hover(top, n_worlds=W, duration=period)]
        for k in range(1, 4):
            lem = Lemniscate(top - [0.0, 0.0, k * spacing], half_length=0.3, half_width=0.15, period=period, n_worlds=W)
            refs.append(TimeShifted(lem, np.full(W, (k - 1) * period / 3)) if k > 1 else lem)
        return refs

    return Preset("crazyflie_stack", "four Crazyflie 2.1 stacked 0.25 m apart", _roles(4), make_refs, period,
                  {"n": 4, "spacing": spacing}, kinds=("crazyflie_2_1",) * 4)


def _mixed_formation() -> Preset:
    """formation5's circles with three Crazyflies on the upper three and two paper quads on the lower two."""
    base = _formation5()
    return dataclasses.replace(base, name="mixed_formation",
                               description="three Crazyflies above two paper quads, all moving, each through the wakes "
                                           "above it",
                               kinds=("crazyflie_2_1",) * 3 + ("paper_quad",) * 2)


PRESETS = Registry("preset", group="presets", name_pattern=r"[a-z][a-z0-9_]*",
                   name_rule="lowercase letters, digits and '_'",
                   hint="stack takes n=2-8, spacing=; heavy_over_light separation=")  # name -> factory(**params)


@PRESETS.adder
def register_preset(name: str, factory: Callable[..., Preset], description: str,
                    params: dict[str, type] | None = None) -> Any:
    """Add a preset: factory(**params) -> `Preset`; params {name: type} a spec may set (default: the
    factory's typed keyword parameters). ConfigError for a taken or bad name."""
    return PRESETS.register(name, factory, description, params=params)


register_preset("pair", lambda: _stack(2), "the paper's: Alpha hovers, Bravo flies a lemniscate 0.6 m beneath")
register_preset("stack3", lambda: _stack(3), "a vertical stack of 3, 0.6 m apart, the lower ones on small lemniscates")
register_preset("stack4", lambda: _stack(4), "the same with four (the bottom one beneath three wakes)")
register_preset("stack", _stack, "a vertical stack of n = 2-8 (spacing 0.6 m)")
register_preset("swap", _swap, "two vehicles cross beneath a hovering third, in opposite directions", params={})
register_preset("formation5", _formation5, "five vehicles on circles at five heights, each through the wakes above it",
                params={})
register_preset("heavy_over_light", _heavy_over_light, "an X500 hovers, a paper quad flies a lemniscate beneath it")
register_preset("crazyflie_stack", _crazyflie_stack, "four Crazyflie 2.1 stacked 0.25 m apart")
register_preset("mixed_formation", _mixed_formation, "formation5's circles with three Crazyflies above two paper quads")


def parse_preset_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """'stack:n=6,spacing=0.5' -> ('stack', {'n': 6, 'spacing': 0.5}); ConfigError naming what is allowed."""
    return PRESETS.parse(spec)


def make_preset(spec: str) -> Preset:
    """The preset named by `spec` (see the module table); ConfigError for an unknown name or a bad parameter."""
    return PRESETS.resolve(spec)
