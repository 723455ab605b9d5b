"""Vehicle kinds: the numbers of one multirotor type, each with where it comes from.

A `VehicleKind` is a quadrotor's mass, inertia, geometry and actuator limits, plus a
`source` that cites every number. `VEHICLES` is the registry (a `downwash_core.registry.Registry`:
name -> kind), `get_vehicle(name)` the lookup and `register_vehicle(kind)` adds one (as plugins
do); `sim.scene.build_scene(..., kinds=...)` builds scenes of mixed kinds from it. The type and its
checks are `downwash_core.vehicle_kind`'s, the kinds' numbers `downwash_core.vehicle_catalog`'s
(both re-exported here). The kinds:

| name | what | mass | source |
|---|---|---|---|
| `paper_quad` | the paper's vehicle (the default) | 0.70 kg | `downwash_core.params.QUAD`, paper sec. 5.C |
| `crazyflie_2_1` | Bitcraze Crazyflie 2.1, brushed (`cf2x_L250`) | 0.0319 kg | utiasDSL/drone-models 0.1.0 |
| `crazyflie_large` | a Crazyflie 2.1 on a larger frame (the Neural-Swarm data set's "large") | 0.067 kg | Neural-Swarm data set; geometry estimated |
| `x500` | Holybro X500 (PX4's Gazebo model) | 2.064 kg | PX4/PX4-gazebo-models `x500` |

A kind may carry a `ThrustMap`, one rotor's thrust from its PWM and the battery voltage (a
system identification's polynomial): what turns a lab's logged motor commands into the
thrust that labels need (`downwash.real_logs`).

`paper_quad` is `QUAD` itself, field for field (the same float objects): nothing moves.
Its scene vehicle is `assets/quad.xml` as written; any other kind is that file with the
kind's numbers written over (`sim.scene`).

The wakes a vehicle sheds scale with it (docs/fields.md, "Vehicles of other kinds"):

- momentum theory (`sim.fields.momentum.MomentumWake`): hover thrust T = m g on the
  disc area A = n pi r^2 gives the induced velocity v_h = sqrt(T / (2 rho A));
  `momentum_wake_kwargs(leader, follower)` are the field's parameters for two kinds;
- the paper's law (`sim.field.DownwashField`): its strength is an acceleration on the
  scale of the induced flow's dynamic pressure, rho v_h^2 / 2 = T / (4 A), i.e. of the
  disc loading T / A; `so2_strength_scale(leader)` is the leader's disc loading over the
  paper quad's, the factor to multiply `strength` by (`basis="thrust"`: the far wake's
  scaling, the thrust ratio).

Between two vehicles of any kinds (`sim.vehicle_params.pair_field` applies these, the one
place the simulator does):

- `so2_pair_scale(leader, follower)`: the factor on the paper's law for a pair, the
  leader's disc-loading scale times what the follower catches of the wake per kilogram;
- `momentum_wake_kwargs(leader, follower)` with `momentum_drag_area_scale(leader, follower)`
  on the airframe's drag area;
- `airframe_area_scale(kind)`: the airframe's frontal area (the wind's drag) over the paper
  quad's; `size_scale(kind)`: its half-diagonal over the paper quad's (the collision ellipsoid).

Every factor is exactly 1.0 for two paper quads. The simulator flies each vehicle with its
own kind's numbers (`sim.vehicle_params`). Units: SI (kg, m, N, s).
"""

from __future__ import annotations

import math
from typing import Any

from downwash_core.errors import ConfigError
from downwash_core.params import QuadParams
from downwash_core.registry import Registry
from downwash_core.vehicle_catalog import CRAZYFLIE_2_1, CRAZYFLIE_LARGE, PAPER_QUAD, X500
from downwash_core.vehicle_kind import AIR_DENSITY, KIND_NAME_PATTERN, N_ROTORS, ThrustMap, VehicleKind

__all__ = [
    "VehicleKind", "ThrustMap", "VEHICLES", "VEHICLE_NAMES", "DEFAULT_VEHICLE", "PAPER_QUAD", "CRAZYFLIE_2_1",
    "CRAZYFLIE_LARGE", "X500",
    "AIR_DENSITY", "N_ROTORS", "get_vehicle", "register_vehicle", "hover_induced_velocity", "so2_strength_scale",
    "momentum_wake_kwargs", "so2_pair_scale", "momentum_drag_area_scale", "airframe_area_scale", "size_scale",
    "as_params",
]


VEHICLES = Registry("vehicle", group="vehicles", objects=True, name_pattern=KIND_NAME_PATTERN.pattern,
                    name_rule="lower case letters, digits and underscores")  # name -> VehicleKind
DEFAULT_VEHICLE = PAPER_QUAD.name


@VEHICLES.adder
def register_vehicle(kind: VehicleKind) -> VehicleKind:
    """Add `kind` under its name (as plugins do); ConfigError for a taken name or no `VehicleKind`."""
    if not isinstance(kind, VehicleKind):
        raise ConfigError(f"register_vehicle: expected a VehicleKind, got {type(kind).__name__}")
    VEHICLES.register(kind.name, None, kind.description or kind.short_source, params={}, obj=kind)
    return kind


VEHICLE_NAMES = tuple(register_vehicle(k).name for k in (PAPER_QUAD, CRAZYFLIE_2_1, X500, CRAZYFLIE_LARGE))  # built-in


def get_vehicle(kind: "str | VehicleKind") -> VehicleKind:
    """The kind named `kind` (a `VehicleKind` is returned as it is); ConfigError naming the allowed names."""
    return kind if isinstance(kind, VehicleKind) else VEHICLES[kind.strip() if isinstance(kind, str) else kind]


# ---------------------------------------------------------------------------- wake scaling


def hover_induced_velocity(kind: "str | VehicleKind", air_density: float = AIR_DENSITY) -> float:
    """m/s, v_h = sqrt(T / (2 rho A)) with T = m g and A = n pi r^2 (momentum theory, hover).

    The paper quad: sqrt(0.70 * 9.81 / (2 * 1.225 * 4 pi 0.04^2)) = 11.8 m/s.
    """
    return get_vehicle(kind).hover_induced_velocity(air_density)


def so2_strength_scale(leader: "str | VehicleKind", reference: "str | VehicleKind" = DEFAULT_VEHICLE,
                       basis: str = "disc_loading") -> float:
    """-, the factor on `sim.field.DownwashField.strength` for a leader of this kind.

    The paper's law is set on the scale of the paper quad's wake (the reference). Its
    strength, an acceleration of the follower, is taken to scale with the dynamic pressure
    of the leader's wake:

    - basis "disc_loading" (the default; the near wake): the induced flow's
      rho v_h^2 / 2 = T / (4 A), so scale = (m_l g / A_l) / (m_ref g / A_ref), A = n pi r^2;
    - basis "thrust" (the far wake): a round jet's centreline speed is
      B sqrt(4 T / (pi rho)) / s, independent of the disc area, so its dynamic pressure at a
      depth s scales with the thrust: scale = m_l / m_ref.

    1 for the reference. Use: `DownwashField(strength=DownwashField().strength * scale)`. The
    width, the fade-in and the follower (the paper quad) are left as they are; the simulator's
    factor for a pair, the follower's kind included, is `so2_pair_scale` (this one for a
    paper-quad follower under a leader of larger discs).
    """
    a, ref = get_vehicle(leader), get_vehicle(reference)
    if basis == "disc_loading":
        return a.disc_loading / ref.disc_loading
    if basis == "thrust":
        return a.weight / ref.weight
    raise ConfigError(f"basis: unknown {basis!r}; allowed: disc_loading, thrust")


def momentum_wake_kwargs(leader: "str | QuadParams",
                         follower: "str | QuadParams" = DEFAULT_VEHICLE) -> dict[str, Any]:
    """The `sim.fields.momentum.MomentumWake` parameters for a leader and a follower of these kinds.

    The leader's hover thrust m g on its disc area n pi r^2 sets the wake's induced velocity
    v_h = sqrt(T / (2 rho A)); its rotor radius sets the fade-in depth below the rotor
    plane; the follower's mass, rotor radius and arm set how its rotors feel the stream.
    `MomentumWake(**momentum_wake_kwargs(leader, follower))`; the follower is the paper quad
    unless given, and both `paper_quad` gives the field's defaults. (The follower's airframe
    drag area is the field's `drag_area` times `momentum_drag_area_scale(leader, follower)`,
    applied by `sim.vehicle_params.pair_field`.) A kind, its name, or a plain `QuadParams`.
    """
    a, b = _numbers(leader), _numbers(follower)
    return {"leader_mass": a.mass, "rotor_radius": a.rotor_radius, "n_rotors": N_ROTORS, "fade_depth": a.rotor_radius,
            "follower_mass": b.mass, "follower_rotor_radius": b.rotor_radius, "follower_arm": b.arm_length}


def as_params(kind: QuadParams) -> QuadParams:
    """A vehicle's numbers as a plain `QuadParams` (a `VehicleKind` compares unequal to its own numbers:
    a dataclass compares its class too), so that vehicles of the same numbers compare equal."""
    return kind.params if isinstance(kind, VehicleKind) else kind


def _numbers(kind: "str | QuadParams") -> QuadParams:
    """A kind's numbers: a `QuadParams` (a `VehicleKind` is one) as it is, a name looked up."""
    return kind if isinstance(kind, QuadParams) else get_vehicle(kind)


def _disc_area(q: QuadParams) -> float:
    """m^2, n pi r^2 (`VehicleKind.disc_area`, for any `QuadParams`)."""
    return N_ROTORS * math.pi * q.rotor_radius**2


def so2_pair_scale(leader: "str | QuadParams", follower: "str | QuadParams") -> float:
    """-, the factor on `sim.field.DownwashField.strength` for a leader and a follower of these kinds.

    The paper's law is an acceleration of a paper quad in a paper quad's wake. For other kinds:

    - the leader's wake: its dynamic pressure q ~ T_l / A_l (its disc loading,
      `so2_strength_scale`: the near wake, where the testbed's vehicles fly);
    - the follower: the wake pushes on the part of its rotor discs inside the wake, at most
      the leader's own disc area (the wake's cross-section near the leader: narrower than
      the follower, it is caught whole), so the force is q min(A_l, A_f) and the
      acceleration that over the follower's mass m_f.

    Relative to two paper quads (q_p A_p / m_p):

        scale = (T_l / A_l) min(A_l, A_f) / m_f / (T_p / m_p) = (m_l / m_f) min(1, A_f / A_l)

    Same kinds: exactly 1.0 (m / m and A / A are exact). A paper-quad follower under a
    larger-disc leader: the disc-loading ratio `so2_strength_scale(leader)`; under a
    smaller-disc leader: the thrust ratio m_l / m_p (the whole jet is caught). A light
    follower under a heavy leader is pushed hardest: a Crazyflie under an X500, 1.84; under
    a paper quad, 7.6; a paper quad under an X500, 0.242 (the paper quad's 0.04 m rotors
    are a collision size that loads them heavily: docs/fields.md).
    """
    a, b = _numbers(leader), _numbers(follower)
    return (a.mass / b.mass) * min(1.0, _disc_area(b) / _disc_area(a))


def momentum_drag_area_scale(leader: "str | QuadParams", follower: "str | QuadParams") -> float:
    """-, the factor on `MomentumWake.drag_area` (the paper quad's airframe) for this pair.

    The field's drag term is a point follower's: the wake's speed at its centre on its whole
    frontal area. The follower's area is its own (`airframe_area_scale`), of which at most
    the wake's cross-section is in the stream; as for `so2_pair_scale`, the wake near the
    leader is taken as wide as the leader's discs, so the area is capped at the disc-area
    ratio: airframe_area_scale(f) min(1, A_l / A_f). An X500 under a paper quad's 0.12 m
    jet: 7.5 x 0.082 = 0.61 (its 0.075 m^2 airframe is not all in the jet); a Crazyflie under
    anything larger: its own 0.26. Exactly 1.0 for two paper quads.
    """
    a, b = _numbers(leader), _numbers(follower)
    return airframe_area_scale(b) * min(1.0, _disc_area(a) / _disc_area(b))


def airframe_area_scale(kind: "str | QuadParams") -> float:
    """-, the airframe's frontal area over the paper quad's: (arm / arm_paper)^2.

    `sim.wind.AIRFRAME`'s A_ref = 0.01 m^2 is the paper quad's body and arms; another kind
    is taken geometrically similar (its body and arms scale with its arm length): the
    Crazyflie 0.26 (2.6 cm^2), the X500 7.5 (0.075 m^2). Exactly 1.0 for the paper quad.
    """
    return (_numbers(kind).arm_length / PAPER_QUAD.arm_length) ** 2


def size_scale(kind: "str | QuadParams") -> float:
    """-, the half-diagonal (arm + rotor radius: the reach of the rotor tips) over the paper quad's.

    The Crazyflie 0.535, the X500 2.97; exactly 1.0 for the paper quad. `sim.vehicle_params`
    scales `SimConfig`'s collision ellipsoid (set for two paper quads) per pair by the mean of
    the two vehicles' factors.
    """
    q = _numbers(kind)
    return (q.arm_length + q.rotor_radius) / (PAPER_QUAD.arm_length + PAPER_QUAD.rotor_radius)
