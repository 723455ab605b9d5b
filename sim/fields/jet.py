"""The leader's wake as Bauersfeld et al.'s turbulent round jet, acting on the follower as `momentum`'s does.

`JetWake()(p_a, v_a, R_a, p_b, v_b)` is the mean acceleration (m/s^2, world frame, z up) that the
leader's wake exerts on a follower, with the wake of

    Bauersfeld, Muller, Ziegler, Coletti & Scaramuzza, "Robotics meets Fluid Dynamics: A
    Characterization of the Induced Airflow below a Quadrotor as a Turbulent Jet", IEEE RA-L 2024
    (arXiv 2403.13321).

From 16 hours of flights of six quadrotors they find that the mean flow below a hovering vehicle
is a self-similar turbulent round jet beyond about 2.5 motor distances, and that one law in
units of the vehicle's hover induced velocity U_H and its motor distance l (between opposite
motors, the "drone diameter") fits every vehicle. Coordinates as in `sim.field`: n the leader's
thrust axis, s = -dp . n the depth below its rotor plane, r the distance from the axis.

    U_H = sqrt(T / (2 rho n_rotors pi R^2))        hover induced velocity, momentum theory (T = m g)  [Eq. 1]
    x   = s / l - s0                               distance from the virtual origin, in motor distances
    U_c = B_d U_H / x                              centreline speed                                     [Eq. 2]
    b   = S l x                                    velocity half-width: U(r = b) = U_c / 2              [Eq. 6]
    U   = U_c (1 + (sqrt(2) - 1) (r / b)^2)^-2     radial profile (Pope's round-jet profile)           [Eqs. 3, 4]
    B_d = 10.11, S = 0.07668, s0 = -5.817          the paper's far-field fit                            [Eq. 9]

Source of the equations and constants: the paper's text could not be read here; they are taken
as implemented, with the paper's equation numbers in its comments (the numbers above), by
learnsyslab/crazyflow `examples/plugins/downwash.py` (commit 4b32a459608c2de120dcb86fea941ee572dbf129),
whose constants agree with an independent implementation (the gaden gas-dispersion simulator's
`QuadrotorDisturbance`, citing IEEE document 10804051). l as the distance between opposite motors
(2 x arm) is crazyflow's reading and the abstract's ("a turbulent jet after 2.5 drone-diameters").
The virtual origin lies 5.8 motor distances *above* the rotor plane, so the law is finite at and
below it: U_c = 1.74 U_H at s = 0, 1.22 U_H at s = 2.5 l.

What this field adds to the paper's law, each stated where it acts:

- Thrust: U_H from the leader's thrust T, estimated from its state as `momentum` does
  (thrust_scale m g / clip(n_z, 0.5, 1), or the keyword `thrust`); T = m g in a hover, the paper's case.
- Near the leader: the paper fits s >= 2.5 l (0.45 m for the paper quad); nearer, the law is
  extrapolated. U_c is capped at 2 U_H (x >= B_d / 2: momentum theory's fully contracted
  slipstream), which the paper's constants never reach at or below the rotor plane
  (x >= 5.817 > 5.055); it keeps a fitted virtual origin below the plane finite. The wake is faded
  in over `fade_depth` below the rotor plane by a smoothstep, exactly zero at and above it, as
  `momentum`'s.
- Only the axial velocity: the paper models the mean speed. Continuity would add a radial
  (entrainment) velocity of about S U_c (1.1 % of U_c at r = b); it is left out.
- The axis is the leader's thrust axis n (the paper's hovering vehicle: the vertical).

The follower: exactly `MomentumWake.follower_response` (its rotors on a ring at `follower_arm`,
yaw-averaged, each losing thrust as a rotor climbing at the stream's speed at its hover power;
its airframe's quadratic drag; each the wake's share, minus still air), fed this jet's air.

Why not a preset of `MomentumWake`, whose profile is the same: its far field is in units of the
vena contracta (U_J = 2 U_H, d0 = 2 sqrt(2) R) with a virtual origin in metres, and it is joined
to a momentum-theory near field by a smooth minimum and maximum that no parameter turns off.
With B = B_d l / (2 d0) and s0 in metres the two agree far down, but the join lowers the speed
3 % and widens the jet 1.5 % at 2.5 l for the paper quad, more nearer; and for a scene of other
vehicle kinds `sim.vehicle_params.pair_field` rescales a `MomentumWake` by its rotors, not by the
leader's motor distance, which is the paper's length scale. So the jet is its own law
(`for_kinds` scales l with the leader) sharing `momentum`'s follower.

Units: m, m/s, kg, N; returns (..., 3) m/s^2. Symmetry: dp, v_b and n only: SO(2)-equivariant about
n for any leader tilt, and under reflections through planes containing n; translation-invariant;
v_a unused. Finite for every finite input.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from downwash_core.geometry import dot as _dot
from downwash_core.params import QUAD
from downwash_core.validate import number
from downwash_core.vehicles import as_params, momentum_drag_area_scale, momentum_wake_kwargs
from sim.fields.momentum import PROFILE_A, MomentumWake
from sim.wind import AIRFRAME

__all__ = ["JetWake", "BAUERSFELD_DECAY", "BAUERSFELD_SPREADING", "BAUERSFELD_ORIGIN"]

# Bauersfeld et al. 2024, Eq. 9 (as implemented by learnsyslab/crazyflow, commit 4b32a45; module docstring)
BAUERSFELD_DECAY = 10.11  # -, B_d: U_c = B_d U_H / (s / l - s0)
BAUERSFELD_SPREADING = 0.07668  # -, S: half-width b = S l (s / l - s0)
BAUERSFELD_ORIGIN = -5.817  # -, s0: the virtual origin, in motor distances below the rotor plane (above: < 0)
_MAX_SPEED_RATIO = 2.0  # -, U_c <= 2 U_H: momentum theory's fully contracted slipstream
# The MomentumWake parameters that the jet shares (the leader's thrust, the follower's rotors and airframe).
_SHARED = ("air_density", "leader_mass", "rotor_radius", "n_rotors", "thrust_scale", "fade_depth", "follower_mass",
           "follower_rotor_radius", "follower_arm", "ring_points", "drag_coefficient", "drag_area", "rotors", "drag")


@dataclass(frozen=True)
class JetWake:
    """The leader's wake as Bauersfeld et al.'s turbulent jet, acting on the follower's rotors and airframe.

    See the module docstring for the law and its sources. Every constant is a plain number,
    checked on construction (ConfigError naming the bad one). The jet's own constants
    (`motor_distance`, `decay_constant`, `spreading_rate`, `virtual_origin`) are the paper's;
    the others are `sim.fields.momentum.MomentumWake`'s, with its meaning and defaults.
    """

    air_density: float = AIRFRAME.air_density  # kg/m^3, ISA sea level
    leader_mass: float = QUAD.mass  # kg, sets the hover thrust m g
    rotor_radius: float = QUAD.rotor_radius  # m, each of the leader's rotors: U_H
    n_rotors: int = 4  # -, rotors per vehicle (both vehicles)
    motor_distance: float = 2.0 * QUAD.arm_length  # m, l: the leader's distance between opposite motors
    thrust_scale: float = 1.0  # -, leader thrust = thrust_scale m g / n_z (unless `thrust=` is given)
    decay_constant: float = BAUERSFELD_DECAY  # -, B_d: U_c = B_d U_H / (s / l - s0)
    spreading_rate: float = BAUERSFELD_SPREADING  # -, S: b = S l (s / l - s0)
    virtual_origin: float = BAUERSFELD_ORIGIN  # -, s0 in motor distances below the rotor plane (< 0: above it)
    fade_depth: float = QUAD.rotor_radius  # m, the wake fades in over this depth below the rotor plane
    follower_mass: float = QUAD.mass  # kg, nominal: hover thrust m g, drag per unit mass
    follower_rotor_radius: float = QUAD.rotor_radius  # m, sets the follower's hover induced velocity
    follower_arm: float = QUAD.arm_length  # m, follower centre to each rotor axis
    ring_points: int = 8  # -, azimuths of the yaw average over the follower's rotor ring
    drag_coefficient: float = AIRFRAME.drag_coefficient  # -, C_d of the follower's airframe
    drag_area: float = AIRFRAME.reference_area  # m^2, A_ref of the follower's airframe
    rotors: bool = True  # include the follower's rotor thrust change
    drag: bool = True  # include the follower's airframe drag

    def __post_init__(self) -> None:
        number("motor_distance", self.motor_distance, "m", 0.0, 100.0, lo_open=True)
        number("decay_constant", self.decay_constant, "-", 0.0, 1000.0, lo_open=True)
        number("spreading_rate", self.spreading_rate, "-", 0.0, 1.0, lo_open=True)
        number("virtual_origin", self.virtual_origin, "motor distances", -1000.0, 1000.0)
        # the leader's thrust estimate and the follower's response: MomentumWake's, which checks the shared constants
        action = MomentumWake(**{k: getattr(self, k) for k in _SHARED})
        l, B = float(self.motor_distance), float(self.decay_constant)
        derived = {
            "_action": action,
            "_uh_per_sqrt_thrust": 1.0 / math.sqrt(
                2.0 * float(self.air_density) * self.n_rotors * math.pi * float(self.rotor_radius) ** 2),
            "_inv_l": 1.0 / l,
            "_x_min": B / _MAX_SPEED_RATIO,  # x >= this: U_c <= 2 U_H
            "_half_width_per_x": float(self.spreading_rate) * l,  # m, b / x
            "_ring_cos": np.cos((np.arange(self.ring_points) + 0.5) * (2.0 * math.pi / self.ring_points)),
        }
        for name, value in derived.items():
            object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ provenance and kinds
    def describe(self) -> dict[str, Any]:
        """Stable provenance: the law's name, type and every parameter (no addresses)."""
        params = {k: (bool(v) if isinstance(v, (bool, np.bool_)) else v) for k, v in asdict(self).items()}
        return {"type": f"{type(self).__module__}.{type(self).__qualname__}", "name": "jet", **params}

    def for_kinds(self, leader: Any, follower: Any) -> "JetWake":
        """The jet of a `leader` over a `follower` of these kinds (`sim.vehicle_params.pair_field`).

        As `momentum` (`downwash_core.vehicles.momentum_wake_kwargs`: the leader's mass and rotors, the
        follower's mass, rotors and arm; the drag area times `momentum_drag_area_scale`), and the
        paper's length scale, the leader's motor distance 2 x arm. The jet's B_d, S and s0 and the
        switches stay the given field's: the paper's law is one for every vehicle size. Itself when
        nothing changes.
        """
        paired = dataclasses.replace(self, **momentum_wake_kwargs(leader, follower),
                                     motor_distance=2.0 * as_params(leader).arm_length,
                                     drag_area=self.drag_area * momentum_drag_area_scale(leader, follower))
        return self if paired == self else paired

    # ------------------------------------------------------------------ the wake
    def hover_induced_velocity(self, thrust: Any) -> np.ndarray:
        """U_H (...) m/s = sqrt(T / (2 rho n pi R^2)) of the leader at thrust T (...) N (clamped to >= 0)."""
        return self._uh_per_sqrt_thrust * np.sqrt(np.maximum(np.asarray(thrust, dtype=np.float64), 0.0))

    def centreline(self, s: Any, thrust: Any) -> tuple[np.ndarray, np.ndarray]:
        """Axis speed U_c (...) m/s (downstream) and half-width b (...) m at depth s (...) m, before the fade.

        U_c = B_d U_H / x, b = S l x, x = max(s / l - s0, B_d / 2); thrust (...) N.
        """
        x = np.maximum(np.asarray(s, dtype=np.float64) * self._inv_l - float(self.virtual_origin), self._x_min)
        return float(self.decay_constant) * self.hover_induced_velocity(thrust) / x, self._half_width_per_x * x

    def speed(self, s: Any, r2: Any, thrust: Any) -> np.ndarray:
        """(...) m/s, the air's speed down the axis (along -n) at depth s (m), squared radius r2 (m^2), faded in."""
        U_c, b = self.centreline(s, thrust)
        q = 1.0 + PROFILE_A * np.asarray(r2, dtype=np.float64) / (b * b)  # 1 + a xi^2
        t = np.clip(np.asarray(s, dtype=np.float64) / float(self.fade_depth), 0.0, 1.0)
        return (t * t * (3.0 - 2.0 * t)) * U_c / (q * q)  # exactly 0 at and above the rotor plane

    def wind(self, p_a: np.ndarray, R_a: np.ndarray, p: np.ndarray, thrust: Any = None) -> np.ndarray:
        """(..., 3) m/s, world frame: the jet's air velocity at points p (..., 3) m.

        p_a (..., 3) m and R_a (..., 3, 3) the leader's position and attitude; thrust (...) N,
        default the estimate `MomentumWake.leader_thrust`.
        """
        p_a, R_a, p = (np.asarray(x, dtype=np.float64) for x in (p_a, R_a, p))
        n = R_a[..., :, 2]
        dp = p - p_a
        s = -_dot(dp, n)
        r_vec = dp + s[..., None] * n
        T = self._action.leader_thrust(R_a) if thrust is None else thrust
        return -self.speed(s, _dot(r_vec, r_vec), T)[..., None] * n

    # ------------------------------------------------------------------ the force
    def __call__(
        self,
        p_a: np.ndarray,
        v_a: np.ndarray,
        R_a: np.ndarray,
        p_b: np.ndarray,
        v_b: np.ndarray,
        *,
        thrust: Any = None,
    ) -> np.ndarray:
        """Mean wake acceleration on the follower.

        Args:
            p_a, v_a: (..., 3) m, m/s, world frame, leader position and velocity (v_a unused).
            R_a: (..., 3, 3) leader attitude, body-to-world; the jet's axis is R_a[..., :, 2].
            p_b, v_b: (..., 3) m, m/s, world frame, follower position and velocity.
            thrust: optional (...) N, the leader's actual thrust; default the estimate
                thrust_scale m_a g / clip(n_z, 0.5, 1).

        Returns:
            (..., 3) m/s^2, world frame: the wake's share of the follower's rotor thrust change
            (along n) and airframe drag, mass-normalised (`MomentumWake.follower_response`).
        """
        p_a, v_a, R_a, p_b, v_b = (np.asarray(x, dtype=np.float64) for x in (p_a, v_a, R_a, p_b, v_b))
        n = R_a[..., :, 2]
        dp = p_b - p_a
        s = -_dot(dp, n)
        r_vec = dp + s[..., None] * n
        r2 = _dot(r_vec, r_vec)
        T = self._action.leader_thrust(R_a) if thrust is None else np.asarray(thrust, dtype=np.float64)
        shape = np.broadcast_shapes(s.shape, v_b.shape[:-1], v_a.shape[:-1], np.shape(T))  # as MomentumWake
        ring_speed = air = None
        if self.rotors:
            # rotors on a ring of radius a about the follower: r_k^2 = r^2 + a^2 + 2 r a cos(phi_k)
            a = float(self.follower_arm)
            r = np.sqrt(r2)[..., None]
            rk2 = np.maximum(r * r + a * a + (2.0 * a) * r * self._ring_cos, 0.0)  # (..., K)
            ring_speed = self.speed(s[..., None], rk2, np.asarray(T)[..., None])
        if self.drag:
            air = -self.speed(s, r2, T)[..., None] * n
        return np.zeros(shape + (3,)) + self._action.follower_response(n, v_b, ring_speed, air)

