"""The type of a vehicle kind: a quadrotor's numbers, each with where it comes from, and its checks.

`VehicleKind` is a `downwash_core.params.QuadParams` with a name, the sources of its numbers and the
names of those that are estimates; a bad number raises `ConfigError` naming the field and the
allowed range. `ThrustMap` is one rotor's thrust from its PWM and the battery voltage. The built-in
kinds are in `downwash_core.vehicle_catalog`, the registry and the wake scaling in
`downwash_core.vehicles` (which re-exports everything here). Units: SI (kg, m, N, s).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, QUAD, QuadParams

__all__ = ["VehicleKind", "ThrustMap", "AIR_DENSITY", "N_ROTORS", "KIND_NAME_PATTERN"]

AIR_DENSITY = 1.225  # kg/m^3, ISA sea level (sim.wind drags the airframes in it)
N_ROTORS = 4  # -, every kind is a quadrotor in an X (the scene's vehicle and the mixer have four rotors)
KIND_NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_]*$")  # a kind's name: lower case letters, digits, underscores
_QUAD_FIELDS = tuple(f.name for f in fields(QuadParams))
# N/m^2, the paper quad's disc loading (`paper_quad` is QUAD, float for float): the reference of
# `so2_strength_scale` in `VehicleKind.describe`
_PAPER_DISC_LOADING = QUAD.weight / (N_ROTORS * math.pi * QUAD.rotor_radius**2)


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
        if not isinstance(self.name, str) or not KIND_NAME_PATTERN.match(self.name):
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
        if not (isinstance(air_density, (int, float)) and math.isfinite(air_density) and air_density > 0):
            raise ConfigError(f"air_density: expected a finite number > 0 (kg/m^3), got {air_density!r}")
        return math.sqrt(self.weight / (2.0 * air_density * self.disc_area))

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
            "so2_strength_scale": self.disc_loading / _PAPER_DISC_LOADING,  # downwash_core.vehicles.so2_strength_scale
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
