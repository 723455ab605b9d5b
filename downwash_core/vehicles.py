"""Vehicle kinds: the numbers of one multirotor type, each with where it comes from.

A `VehicleKind` is a quadrotor's mass, inertia, geometry and actuator limits, plus a
`source` that cites every number. `VEHICLES` is the registry (a `downwash_core.registry.Registry`:
name -> kind), `get_vehicle(name)` the lookup and `register_vehicle(kind)` adds one (as plugins
do); `sim.scene.build_scene(..., kinds=...)` builds scenes of mixed kinds from it. The kinds:

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
import re
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, QUAD, QuadParams
from downwash_core.registry import Registry

__all__ = [
    "VehicleKind", "ThrustMap", "VEHICLES", "VEHICLE_NAMES", "DEFAULT_VEHICLE", "PAPER_QUAD", "CRAZYFLIE_2_1",
    "CRAZYFLIE_LARGE", "X500",
    "AIR_DENSITY", "N_ROTORS", "get_vehicle", "register_vehicle", "hover_induced_velocity", "so2_strength_scale",
    "momentum_wake_kwargs", "so2_pair_scale", "momentum_drag_area_scale", "airframe_area_scale", "size_scale",
    "as_params",
]

AIR_DENSITY = 1.225  # kg/m^3, ISA sea level (the same as sim.wind.AIR_DENSITY; a test ties them)
N_ROTORS = 4  # -, every kind is a quadrotor in an X (the scene's vehicle and the mixer have four rotors)
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")
_QUAD_FIELDS = tuple(f.name for f in fields(QuadParams))


@dataclass(frozen=True)
class ThrustMap:
    """One rotor's thrust from its PWM and the battery voltage, a system identification's polynomial:
    grams-force ``c00 + c10 p + c01 v + c20 p^2 + c11 p v`` with ``p = pwm / 65536`` and
    ``v = vbat / 4.2 V``; `source` says where the coefficients come from."""

    c00: float
    c10: float
    c01: float
    c20: float
    c11: float
    source: str = ""

    def thrust(self, pwm: Any, vbat: Any) -> np.ndarray:
        """N per rotor: pwm (..., R) 0-65535, vbat (...) V."""
        p, v = np.asarray(pwm, np.float64) / 65536.0, np.asarray(vbat, np.float64)[..., None] / 4.2
        grams = self.c00 + self.c10 * p + self.c01 * v + self.c20 * p * p + self.c11 * p * v
        return grams * 1e-3 * GRAVITY

    def describe(self) -> dict[str, Any]:
        return {"c00": self.c00, "c10": self.c10, "c01": self.c01, "c20": self.c20, "c11": self.c11,
                "source": self.source}


@dataclass(frozen=True)
class VehicleKind(QuadParams):
    """One quadrotor type: its numbers (SI units) and where each comes from.

    A `downwash_core.params.QuadParams` (its numbers and derived values: weight, rotor
    thrusts, rotor positions) with a name and the sources, so a kind drops in wherever a
    `QuadParams` goes; `params` gives the plain `QuadParams` back. Every kind of the
    registry states every number (the base class's defaults are the paper quad's).

    name: registry key (lower case, digits, underscores).
    mass: kg, whole vehicle (airframe, battery, rotors).
    inertia: kg m^2, body-frame diagonal about the centre of mass.
    arm_length: m, body centre to each rotor axis (X configuration, rotors at 45 deg).
    rotor_radius: m, propeller radius (sets the disc area of the wake laws).
    thrust_to_weight: -, all four rotors at full thrust over the weight (> 1).
    motor_time_constant: s, first-order lag from commanded to actual thrust.
    yaw_moment_coeff: m, rotor drag torque per newton of thrust.
    source: where every number comes from, one line per number after a first summary line.
    description: one line, what the vehicle is.
    estimated: the names of the fields that are estimates rather than published values.
    thrust_map: a rotor's thrust from PWM and battery voltage (`ThrustMap`), where one is known.
    """

    name: str = field(kw_only=True)
    source: str = field(kw_only=True)
    description: str = field(default="", kw_only=True)
    estimated: tuple[str, ...] = field(default=(), kw_only=True)
    thrust_map: ThrustMap | None = field(default=None, kw_only=True)

    def __post_init__(self) -> None:
        label = f"vehicle {self.name!r}"
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise ConfigError(f"vehicle name: expected lower case letters, digits and underscores, got {self.name!r}")
        for key in ("mass", "arm_length", "rotor_radius", "thrust_to_weight", "motor_time_constant",
                    "yaw_moment_coeff"):
            _positive(label, key, getattr(self, key))
        inertia = tuple(self.inertia) if isinstance(self.inertia, (tuple, list)) else None
        if inertia is None or len(inertia) != 3:
            raise ConfigError(f"{label}: inertia: expected 3 numbers (kg m^2, body-frame diagonal), "
                              f"got {self.inertia!r}")
        for axis, value in zip("xyz", inertia):
            _positive(label, f"inertia {axis}", value)
        ixx, iyy, izz = (float(v) for v in inertia)
        if ixx + iyy < izz * (1.0 - 1e-9) or ixx + izz < iyy * (1.0 - 1e-9) or iyy + izz < ixx * (1.0 - 1e-9):
            raise ConfigError(f"{label}: inertia {inertia} breaks the triangle inequality (each principal moment "
                              "must be at most the sum of the other two): not a rigid body")
        if not self.thrust_to_weight > 1.0:
            raise ConfigError(f"{label}: thrust_to_weight: got {self.thrust_to_weight!r}; allowed > 1 "
                              "(the rotors must lift the vehicle)")
        if not self.motor_time_constant < 1.0:
            raise ConfigError(f"{label}: motor_time_constant: got {self.motor_time_constant!r}; allowed (0, 1) s")
        spacing = self.arm_length * math.sqrt(2.0)  # m, between neighbouring rotor axes
        if 2.0 * self.rotor_radius > spacing:
            raise ConfigError(f"{label}: rotor_radius {self.rotor_radius} m: neighbouring rotors "
                              f"{spacing:.4g} m apart overlap; allowed <= arm_length / sqrt(2) = {spacing / 2:.4g} m")
        if not isinstance(self.source, str) or not self.source.strip():
            raise ConfigError(f"{label}: source: expected where the numbers come from, got {self.source!r}")
        unknown = [e for e in self.estimated if e not in _QUAD_FIELDS]
        if unknown:
            raise ConfigError(f"{label}: estimated: unknown fields {unknown}; allowed: {', '.join(_QUAD_FIELDS)}")
        if inertia is not self.inertia:
            object.__setattr__(self, "inertia", inertia)

    # ------------------------------------------------------------------ QuadParams
    @classmethod
    def from_params(cls, name: str, params: QuadParams, source: str, **kw: Any) -> "VehicleKind":
        """A kind with the numbers of `params` (the very same float objects)."""
        return cls(name=name, source=source, **{k: getattr(params, k) for k in _QUAD_FIELDS}, **kw)

    @property
    def params(self) -> QuadParams:
        """The kind as a `QuadParams` (equal to `QUAD` for `paper_quad`)."""
        return QuadParams(**{k: getattr(self, k) for k in _QUAD_FIELDS})

    # ------------------------------------------------------------------ derived
    @property
    def diagonal(self) -> float:
        """m, rotor tip to rotor tip across the body."""
        return 2.0 * (self.arm_length + self.rotor_radius)

    @property
    def disc_area(self) -> float:
        """m^2, A = n pi r^2: the rotors' total disc area."""
        return N_ROTORS * math.pi * self.rotor_radius**2

    @property
    def disc_loading(self) -> float:
        """N/m^2, hover thrust over disc area, m g / A."""
        return self.weight / self.disc_area

    def hover_induced_velocity(self, air_density: float = AIR_DENSITY) -> float:
        """m/s, v_h = sqrt(m g / (2 rho A)) (momentum theory, hover)."""
        return hover_induced_velocity(self, air_density)

    @property
    def short_source(self) -> str:
        """The first line of `source`."""
        return self.source.strip().splitlines()[0].strip()

    def describe(self) -> dict[str, Any]:
        """Every number, the derived ones and the source (for results files and provenance)."""
        return {
            "name": self.name, "description": self.description,
            **{k: (list(getattr(self, k)) if k == "inertia" else getattr(self, k)) for k in _QUAD_FIELDS},
            "max_rotor_thrust": self.max_rotor_thrust, "hover_rotor_thrust": self.hover_rotor_thrust,
            "diagonal": self.diagonal, "disc_loading": self.disc_loading,
            "hover_induced_velocity": self.hover_induced_velocity(),
            "so2_strength_scale": so2_strength_scale(self),
            "estimated": list(self.estimated), "source": self.source,
            **({"thrust_map": self.thrust_map.describe()} if self.thrust_map is not None else {}),
        }


def _positive(label: str, key: str, value: Any) -> None:
    try:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    except TypeError:
        ok = False
    if not ok:
        raise ConfigError(f"{label}: {key}: expected a finite number > 0, got {value!r}")


# ---------------------------------------------------------------------------- the kinds

PAPER_QUAD = VehicleKind.from_params(
    "paper_quad", QUAD,
    description="the paper's custom quadrotor (Alpha and Bravo), the testbed's default",
    estimated=("inertia", "arm_length", "rotor_radius", "thrust_to_weight", "motor_time_constant", "yaw_moment_coeff"),
    source="""Smith et al. 2023 (arXiv 2305.18983) sec. 5.C, as downwash_core.params.QUAD
mass 0.70 kg: paper sec. 5.C ("weigh ~0.7 kg (including batteries)")
arm_length 0.09 m: paper sec. 5.C's 0.26 m longest body diagonal = 2 (arm + rotor radius), with the chosen radius
inertia, rotor_radius, thrust_to_weight, motor_time_constant, yaw_moment_coeff: the testbed's choices
  (downwash_core.params.QuadParams, assets/quad.xml), not given in the paper; rotor_radius 0.04 m is a
  collision/visual size, smaller than the real vehicle's propellers (docs/fields.md)""",
)

_NEURAL_SWARM = "Neural-Swarm data set (github.com/aerorobotics/neural-swarm), data/training/"

# utiasDSL/drone-models release 0.1.0 (commit 77f04ab13efbee1179322c9e22119e1d964113bd, MIT),
# the parameters the crazyflow simulator validates against. Configuration cf2x_L250.
_CF_L = 0.03253  # m, drone-models `L`: per-axis moment arm (the mixing matrix is +-1 on x and y)
_CF_THRUST_MAX = 0.12  # N per motor, drone-models `thrust_max`
_CF_MASS = 0.0319  # kg, drone-models `mass`

CRAZYFLIE_2_1 = VehicleKind(
    name="crazyflie_2_1",
    mass=_CF_MASS,
    inertia=(16.8e-6, 16.8e-6, 29.8e-6),
    arm_length=_CF_L * math.sqrt(2.0),  # 0.0460 m: centre to motor (Bitcraze: 92 mm motor to motor)
    rotor_radius=23.55e-3,
    thrust_to_weight=4.0 * _CF_THRUST_MAX / (_CF_MASS * GRAVITY),  # so that max_rotor_thrust is 0.12 N
    motor_time_constant=0.0858607,
    yaw_moment_coeff=0.007350862856566459,
    description="Bitcraze Crazyflie 2.1, brushed motors, stock propellers, 250 mAh battery (drone-models cf2x_L250)",
    estimated=("inertia", "rotor_radius"),
    thrust_map=ThrustMap(11.093358483549203, -39.08104165843915, -9.525647087583181, 20.573302305476638,
                         38.42885066644033, source=_NEURAL_SWARM + "datacollection19_12_11_2019/defaultcf.txt "
                         "(C_00 ... C_11, fit score 0.998): an unmodified Crazyflie 2.1"),
    source="""utiasDSL/drone-models 0.1.0 (commit 77f04ab, MIT), drone_models/data/params.toml [cf2x_L250]
mass 0.0319 kg: params.toml [cf2x_L250] mass
arm_length 0.0460 m: params.toml L = 0.03253 m is the per-axis moment arm (mixing matrix +-1 on x and y), x sqrt(2)
inertia (16.8, 16.8, 29.8) e-6 kg m^2: params.toml J (marked TODO there); Foerster 2015, "System
  Identification of the Crazyflie 2.0 Nano Quadrocopter" (BSc thesis, ETH Zurich) identified
  (16.57, 16.66, 29.26) e-6 on a 0.027 kg vehicle, within 2 %
rotor_radius 0.02355 m: params.toml prop_radius (marked "TODO check" there)
thrust_to_weight 1.53: params.toml thrust_max = 0.12 N per motor, 4 x 0.12 N / (0.0319 kg g)
motor_time_constant 0.0859 s: drone_models/so_rpy_rotor/params.toml [cf2x_L250] thrust_time_coef (fitted
  first-order lag of the collective thrust, rotor_vel_dot = (cmd - rotor_vel) / thrust_time_coef)
yaw_moment_coeff 0.00735 m: params.toml thrust2torque (Foerster 2015: 0.005964552)
thrust_map: the Neural-Swarm data set's system identification of an unmodified Crazyflie 2.1""",
)

# The Neural-Swarm data set's "large" vehicle: a Crazyflie 2.1 on a larger (Parrot) frame with its
# propellers. The data set gives its mass, its ground clearance and its thrust map; the geometry is
# estimated (the data set states none): larger propellers on a frame that clears them.
_LARGE_MAP = ThrustMap(44.10386631845999, -122.51151800146272, -36.18484254283743, 53.10772568607133,
                       107.6819263349139, source=_NEURAL_SWARM + "datacollection19_12_11_2019/parrot_frame.txt "
                       "(C_00 ... C_11, fit score 0.995): the large frame")
_LARGE_MASS = 0.067  # kg, parrot_frame.txt ("mass: 67g")
_LARGE_MAX_ROTOR_THRUST = float(_LARGE_MAP.thrust(65535.0, 4.2)[0])  # N, full PWM on a full battery
_CF_ARM = _CF_L * math.sqrt(2.0)
_LARGE_ARM, _LARGE_ROTOR = 0.06, 0.033  # m, estimated

CRAZYFLIE_LARGE = VehicleKind(
    name="crazyflie_large",
    mass=_LARGE_MASS,
    # the Crazyflie's inertia scaled as m l^2 (the same mass distribution on a larger frame)
    inertia=tuple(i * (_LARGE_MASS / _CF_MASS) * (_LARGE_ARM / _CF_ARM) ** 2 for i in (16.8e-6, 16.8e-6, 29.8e-6)),
    arm_length=_LARGE_ARM,
    rotor_radius=_LARGE_ROTOR,
    thrust_to_weight=4.0 * _LARGE_MAX_ROTOR_THRUST / (_LARGE_MASS * GRAVITY),
    motor_time_constant=-0.01 / math.log(1.0 - 0.16),  # 0.057 s
    yaw_moment_coeff=0.007350862856566459,
    description="Crazyflie 2.1 on a larger (Parrot) frame and propellers: the Neural-Swarm data set's large vehicle",
    estimated=("inertia", "arm_length", "rotor_radius", "motor_time_constant", "yaw_moment_coeff"),
    thrust_map=_LARGE_MAP,
    source="""Neural-Swarm data set (Shi et al., github.com/aerorobotics/neural-swarm, data/training), vehicles cf100-cf102
mass 0.067 kg: data/training/datacollection19_12_11_2019/parrot_frame.txt ("mass: 67g")
thrust_to_weight: its thrust map at full PWM and 4.2 V (4 rotors), over the weight
thrust_map: parrot_frame.txt (C_00 ... C_11)
arm_length 0.06 m, rotor_radius 0.033 m: estimated (the data set states no geometry): a larger propeller
  than the Crazyflie's 23.5 mm, on a frame whose rotors do not overlap
inertia: estimated, crazyflie_2_1's scaled by mass x arm length^2
motor_time_constant 0.057 s: estimated from the data set's training code, which lags the thrust by a
  first-order filter of 0.16 per 10 ms step (learning/utils.py), -0.01 s / ln(0.84)
yaw_moment_coeff: estimated, crazyflie_2_1's""",
)


def _x500_whole_vehicle() -> tuple[float, tuple[float, float, float]]:
    """Mass (kg) and inertia diagonal (kg m^2) of PX4's x500: base_link plus the four rotor links.

    From PX4/PX4-gazebo-models models/x500_base/model.sdf: base_link 2.0 kg, inertia
    (0.021667, 0.021667, 0.04) at its origin; rotors 0.016077 kg each at (+-0.174, +-0.174,
    0.06) m with ixx 3.846e-7, iyy 2.612e-5, izz 2.650e-5 (a blade along x): averaged over
    a turn ((ixx + iyy) / 2 in the plane), moved to the combined centre of mass (parallel axes).
    """
    m_b, i_b = 2.0, (0.02166666666666667, 0.02166666666666667, 0.04000000000000001)
    m_r, xy, z = 0.016076923076923075, 0.174, 0.06
    i_r_plane, i_r_z = (3.8464910483993325e-07 + 2.6115851691700804e-05) / 2.0, 2.649858234714004e-05
    mass = m_b + 4.0 * m_r
    z_c = 4.0 * m_r * z / mass  # the centre of mass lies above base_link's origin
    d_b2 = z_c**2
    d_r_lat2, d_r_z2 = xy**2, (z - z_c) ** 2
    ixx = i_b[0] + m_b * d_b2 + 4.0 * (i_r_plane + m_r * (d_r_lat2 + d_r_z2))
    iyy = i_b[1] + m_b * d_b2 + 4.0 * (i_r_plane + m_r * (d_r_lat2 + d_r_z2))
    izz = i_b[2] + 4.0 * (i_r_z + m_r * 2.0 * d_r_lat2)
    return mass, (ixx, iyy, izz)


_X500_MASS, _X500_INERTIA = _x500_whole_vehicle()
_X500_MAX_ROTOR_THRUST = 8.54858e-06 * 1000.0**2  # N: motorConstant x maxRotVelocity^2

X500 = VehicleKind(
    name="x500",
    mass=_X500_MASS,
    inertia=_X500_INERTIA,
    arm_length=0.174 * math.sqrt(2.0),  # 0.246 m (a 500 mm wheelbase frame)
    rotor_radius=0.2792307692307692 / 2.0,  # 0.1396 m: the rotor collision box (an 11 inch propeller)
    thrust_to_weight=4.0 * _X500_MAX_ROTOR_THRUST / (_X500_MASS * GRAVITY),
    motor_time_constant=(0.0125 + 0.025) / 2.0,
    yaw_moment_coeff=0.016,
    description="Holybro X500, 2 kg class (PX4's Gazebo x500 model)",
    estimated=("inertia", "motor_time_constant"),
    source="""PX4/PX4-gazebo-models (BSD-3-Clause) models/x500_base/model.sdf and models/x500/model.sdf
files as of commits 008216e (x500_base/model.sdf) and 0f0e45d (x500/model.sdf)
mass 2.064 kg: base_link 2.0 kg + 4 rotor links x 0.016077 kg (x500_base/model.sdf)
arm_length 0.246 m: rotor links at (+-0.174, +-0.174) m, x sqrt(2) (x500_base/model.sdf)
inertia (0.0239, 0.0239, 0.0440) kg m^2: estimated, base_link's (0.02167, 0.02167, 0.04) plus the rotor links by
  parallel axes, rotor inertia averaged over a turn (x500_base/model.sdf)
rotor_radius 0.1396 m: half the rotor collision box, 0.27923 m (x500_base/model.sdf; an 11 inch propeller)
thrust_to_weight 1.69: motorConstant 8.54858e-6 N s^2 x maxRotVelocity (1000 rad/s)^2 = 8.549 N per rotor
  (x500/model.sdf, gz MulticopterMotorModel)
motor_time_constant 0.01875 s: estimated, the mean of timeConstantUp 0.0125 s and timeConstantDown 0.025 s
  (x500/model.sdf); one symmetric lag here
yaw_moment_coeff 0.016 m: momentConstant (x500/model.sdf)""",
)

VEHICLES = Registry("vehicle", group="vehicles", objects=True, name_pattern=_NAME.pattern,
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
    k = get_vehicle(kind)
    if not (isinstance(air_density, (int, float)) and math.isfinite(air_density) and air_density > 0):
        raise ConfigError(f"air_density: expected a finite number > 0 (kg/m^3), got {air_density!r}")
    return math.sqrt(k.weight / (2.0 * air_density * k.disc_area))


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
