"""A physics-based ground truth: the leader's rotor wake as a turbulent round jet.

`MomentumWake()(p_a, v_a, R_a, p_b, v_b)` is the mean acceleration (m/s^2, world
frame, z up) that the leader's wake exerts on a follower, written from first
principles and deliberately *not* of the paper's (or `sim.field`'s) functional form.
Coordinates, as in `sim.field`: n = R_a[..., :, 2] the leader's thrust axis,
dp = p_b - p_a, s = -dp . n the depth below the leader's rotor plane (m),
r_vec = dp + s n the lateral offset from the wake axis, r = |r_vec|.

1. The wake (momentum theory; Leishman, *Principles of Helicopter Aerodynamics*, 2nd
   ed., 2006, ch. 2). The leader's n_rotors rotors of radius R (total disk area
   A = n_rotors pi R^2) carry its thrust T, so the hover induced velocity is
   v_h = sqrt(T / (2 rho A)) and the fully contracted slipstream (the vena contracta,
   area A/2) moves at U_J = 2 v_h. The rotors are lumped into one equivalent disk of
   radius R_d = R sqrt(n_rotors), so the vena contracta has diameter d0 = sqrt(2) R_d.
   (The four rotor jets, 0.13 m apart, merge where their half-widths S s reach half
   that spacing, s ~ 0.7 m; above that the real flow is weaker under the leader's
   centre and stronger under its rotors than this single jet.)
   Thrust: the signature has no thrust argument, so T is estimated from the leader's
   state as the thrust that holds its altitude at its tilt,
   T = thrust_scale m_a g / clip(n_z, 0.5, 1), or taken from the optional keyword
   `thrust` (N, shape (...)) of `__call__` when the caller knows it.
2. Near field (0 < s, the contraction). On the axis of a uniformly loaded actuator
   disk (a semi-infinite vortex cylinder) the axial velocity is
   U_near = v_h (1 + s / sqrt(s^2 + R_d^2)): v_h at the disk, 2 v_h downstream; the
   slipstream radius follows from continuity, b_near = R_d sqrt(v_h / U_near).
3. Far field (self-similar turbulent round jet; Pope, *Turbulent Flows*, 2000,
   sec. 5.1-5.2 and table 5.1; Hussein, Capp & George, J. Fluid Mech. 258, 31-75, 1994):
   centreline U_far = B U_J d0 / (s - s0) with decay constant B = 5.8, half-width
   b_far = S (s - s0) with spreading rate S = 0.094 (Hussein et al.'s LDA values;
   the other entries of Pope's table give S = 0.086-0.102, B = 5.7-6.1), virtual
   origin s0 (default 0: at the rotor plane). The two regions are joined by smooth
   minimum / maximum, U_c = (U_near^-4 + U_far^-4)^(-1/4), b = (b_near^4 + b_far^4)^(1/4);
   momentum is conserved through the join because U b is nearly constant in both.
   Consistency check: this profile carries J = rho pi U_c^2 b^2 / (3a), which with
   S = 0.094 and B = 5.8 is 96 % of the thrust (the rest is turbulent stress).
4. Profile and entrainment. U(s, r) = U_c f(r / b), f(xi) = (1 + a xi^2)^-2 with
   a = sqrt(2) - 1 (so b is the velocity half-width): Pope's constant-eddy-viscosity
   round-jet profile (sec. 5.2; close to the measured one). The radial
   velocity follows from continuity, d(U r)/ds + d(r V)/dr = 0, for any U_c(s), b(s):
       V = U_c b' xi f(xi) - (U_c b^2)' / b * xi / (2 (1 + a xi^2))   (outward +).
   Beyond xi = 1/sqrt(a) in the far field it is an inflow ~ 1/r (entrainment); in
   the near field b' < 0 and it is the contraction.
   The wake velocity is faded in over `fade_depth` below the rotor plane by a
   smoothstep (exactly zero at and above the rotor plane: the inflow above the
   disk is left out), so the field is continuous and zero above the leader.
   Air velocity: u = w(s) (-U n + V r_vec / r) (m/s, world frame).
5. Action on the follower (point vehicle whose thrust axis is assumed to be n:
   the signature carries no follower attitude; both vehicles fly near level).
   Rotors: each of the follower's rotors at `follower_arm` from its centre sees the
   axial stream at its own position; the yaw is unknown, so the rotors are spread
   evenly over that ring (`ring_points` azimuths, the yaw average). A rotor whose air
   moves down through it at V_c relative to it is a rotor climbing at V_c: at the
   rotor's hover power P_h = T_h v_hf (the shaft power does not change within the
   field's time scale) momentum theory, T = 2 rho A (V_c + v_i) v_i and
   T (V_c + v_i) = P_h, gives tau = T / T_h as the positive root of
   tau^3 + c tau - 1 = 0, c = V_c / v_hf (`rotor_thrust_ratio`). Small c: tau ~ 1 - c/3,
   close to blade-element theory at fixed rotor speed (slope k / (4 lambda_h + k),
   ~0.3 for a small rotor with lambda_h ~ 0.08, k = solidity x lift slope / 4 ~ 0.14),
   and free of blade parameters. c < 0 (up-flow, i.e. descent) uses the same formula,
   outside momentum theory's validity for -2 < c < 0 (vortex ring state).
   Airframe: quadratic drag on the relative air velocity,
   a = rho C_d A_ref / (2 m_b) |u - v_b| (u - v_b): `sim.wind.drag_acceleration`, with the
   airframe constants of `sim.wind.AIRFRAME` (C_d = 1.0, A_ref = 0.01 m^2, rho = 1.225
   kg/m^3; a bluff body, Hoerner, *Fluid-Dynamic Drag*, 1965, ch. 3), the same law and
   constants through which the ambient wind acts on every vehicle.
   Only the wake's share is returned: each term minus its value in still air
   (u = 0), so the follower's own climb and drag stay out of the field, and the
   field is exactly zero where there is no wake.

Units: m, m/s, kg, N; returns (..., 3) m/s^2. Symmetry: the law uses dp, v_b, n and
scalars of the leader's tilt only, so it is SO(2)-equivariant about n for any leader
attitude (rotating dp and v_b about n rotates the output), also under reflections
through planes containing n (no swirl), and translation-invariant; v_a is unused
(a quasi-steady wake: the leader's lateral speed, < 1 m/s here, is < 10 % of the
wake's). Finite at r = 0, dp = 0, v = 0, T = 0.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from downwash_core import libm
from downwash_core.errors import ConfigError
from downwash_core.geometry import dot as _dot
from downwash_core.params import GRAVITY, QUAD
from downwash_core.validate import count, number
from sim.wind import AIRFRAME, drag_acceleration

__all__ = ["MomentumWake", "rotor_thrust_ratio", "PROFILE_A"]

PROFILE_A = math.sqrt(2.0) - 1.0  # -, f(xi) = (1 + a xi^2)^-2 has f(1) = 1/2
BLEND = 4.0  # -, exponent of the smooth min/max joining near and far field (sharp, yet C1)
_MIN_TILT_COS = 0.5  # -, the thrust estimate m g / n_z is capped at 2 m g (60 deg tilt)
C_STAR = -(27.0 / 4.0) ** (1.0 / 3.0)  # the cubic's discriminant changes sign here
C_SMALL = 0.5  # above: the sinh form, cancellation-free for large c
_STILL_AIR = np.zeros(3)  # m/s


def rotor_thrust_ratio(c: Any) -> np.ndarray:
    """T / T_h of a rotor climbing at c = V_c / v_h at its hover power (momentum theory).

    The positive root of tau^3 + c tau - 1 = 0 (unique for every real c); tau(0) = 1,
    tau(1) = 0.6823, tau -> 1/c for c -> inf, sqrt(-c) for c -> -inf. Closed form in
    three branches, each fed clamped inputs so that no branch warns or overflows.
    c: (...) -, returns (...) -.
    """
    c = np.asarray(c, dtype=np.float64)
    # c >= 0.5: tau = 2 sqrt(c/3) sinh(asinh((3 sqrt(3)/2) c^-1.5) / 3), ~1/c without cancellation
    cs = np.maximum(c, C_SMALL)
    big = 2.0 * np.sqrt(cs / 3.0) * libm.sinh(libm.arcsinh(1.5 * math.sqrt(3.0) * libm.power(cs, -1.5)) / 3.0)
    # c_* <= c < 0.5: Cardano, one real root
    cc = np.clip(c, C_STAR, C_SMALL)
    u = libm.cbrt(0.5 + np.sqrt(np.maximum(0.25 + libm.power(cc, 3.0) / 27.0, 0.0)))
    mid = u - cc / (3.0 * u)
    # c < c_*: three real roots, the largest (the only positive one), trigonometric form
    m = np.maximum(-c, -C_STAR)
    arg = np.minimum(1.5 * math.sqrt(3.0) * libm.power(m, -1.5), 1.0)
    low = 2.0 * np.sqrt(m / 3.0) * np.cos(libm.arccos(arg) / 3.0)
    return np.where(c >= C_SMALL, big, np.where(c >= C_STAR, mid, low))


@dataclass(frozen=True)
class MomentumWake:
    """The leader's wake as a momentum-theory jet, acting on the follower's rotors and airframe.

    See the module docstring for the equations and their sources. All constants are
    plain numbers, checked on construction (ConfigError naming the bad one).
    """

    air_density: float = AIRFRAME.air_density  # kg/m^3, ISA sea level
    leader_mass: float = QUAD.mass  # kg, sets the hover thrust m g
    rotor_radius: float = QUAD.rotor_radius  # m, each of the leader's rotors
    n_rotors: int = 4  # -, rotors per vehicle (both vehicles)
    thrust_scale: float = 1.0  # -, leader thrust = thrust_scale m g / n_z (unless `thrust=` is given)
    spreading_rate: float = 0.094  # -, S: far-field half-width b = S (s - s0)
    decay_constant: float = 5.8  # -, B: far-field centreline U = B U_J d0 / (s - s0)
    virtual_origin: float = 0.0  # m, s0: the far field's virtual origin below the rotor plane
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
        pos = dict(lo=0.0, hi=1e6, lo_open=True)
        number("air_density", self.air_density, "kg/m^3", **pos)
        number("leader_mass", self.leader_mass, "kg", **pos)
        number("rotor_radius", self.rotor_radius, "m", **pos)
        count("n_rotors", self.n_rotors, 1, 64)
        number("thrust_scale", self.thrust_scale, "-", 0.0, 10.0)
        number("spreading_rate", self.spreading_rate, "-", 0.0, 1.0, lo_open=True)
        number("decay_constant", self.decay_constant, "-", 0.0, 100.0, lo_open=True)
        number("virtual_origin", self.virtual_origin, "m", -10.0, 10.0)
        number("fade_depth", self.fade_depth, "m", 0.0, 10.0, lo_open=True)
        number("follower_mass", self.follower_mass, "kg", **pos)
        number("follower_rotor_radius", self.follower_rotor_radius, "m", **pos)
        number("follower_arm", self.follower_arm, "m", 0.0, 10.0)
        count("ring_points", self.ring_points, 1, 64)
        number("drag_coefficient", self.drag_coefficient, "-", 0.0, 100.0)
        number("drag_area", self.drag_area, "m^2", 0.0, 100.0)
        for name in ("rotors", "drag"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ConfigError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        rho = float(self.air_density)
        disk_area = self.n_rotors * math.pi * float(self.rotor_radius) ** 2  # m^2, A
        radius_eq = float(self.rotor_radius) * math.sqrt(self.n_rotors)  # m, R_d
        follower_area = self.n_rotors * math.pi * float(self.follower_rotor_radius) ** 2
        azimuth = (np.arange(self.ring_points) + 0.5) * (2.0 * math.pi / self.ring_points)
        derived = {
            "vh_per_sqrt_thrust": 1.0 / math.sqrt(2.0 * rho * disk_area),  # v_h = this sqrt(T)
            "radius_eq": radius_eq,
            "d0": math.sqrt(2.0) * radius_eq,  # m, vena contracta diameter
            "_hover_thrust": float(self.leader_mass) * GRAVITY,  # N
            "vh_follower": math.sqrt(float(self.follower_mass) * GRAVITY / (2.0 * rho * follower_area)),  # m/s
            # the airframe drag law's constants (sim.wind.drag_acceleration)
            "drag_law": (float(self.follower_mass), float(self.drag_coefficient), float(self.drag_area), rho),
            "_ring_cos": np.cos(azimuth),  # (K,) azimuths of the rotors relative to r_vec
        }
        for name, value in derived.items():
            object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ provenance
    def describe(self) -> dict[str, Any]:
        """Stable provenance: the law's name, type and every parameter (no addresses)."""
        params = {k: (bool(v) if isinstance(v, (bool, np.bool_)) else v) for k, v in asdict(self).items()}
        return {"type": f"{type(self).__module__}.{type(self).__qualname__}", "name": "momentum", **params}

    # ------------------------------------------------------------------ the wake
    def leader_thrust(self, R_a: np.ndarray) -> np.ndarray:
        """(...) N, the estimated thrust: thrust_scale m_a g / clip(n_z, 0.5, 1), R_a (..., 3, 3)."""
        n_z = np.clip(np.asarray(R_a, dtype=np.float64)[..., 2, 2], _MIN_TILT_COS, 1.0)
        return (float(self.thrust_scale) * self._hover_thrust) / n_z

    def centreline(self, s: Any, thrust: Any) -> tuple[np.ndarray, ...]:
        """Axis speed and half-width of the wake, before the fade across the rotor plane.

        Args:
            s: (...) m, depth below the leader's rotor plane (clamped to >= 0).
            thrust: (...) N, the leader's thrust (clamped to >= 0).

        Returns:
            U_c (...) m/s (downstream), b (...) m, and their depth derivatives
            dU_c/ds (1/s), db/ds (-).
        """
        s = np.maximum(np.asarray(s, dtype=np.float64), 0.0)
        v_h = self.vh_per_sqrt_thrust * np.sqrt(np.maximum(np.asarray(thrust, dtype=np.float64), 0.0))
        R2, p = self.radius_eq**2, BLEND
        root = np.sqrt(s * s + R2)
        phi1 = 1.0 + s / root  # U_near / v_h, in [1, 2)
        dphi1 = R2 / (root * root * root)
        # far field as 1 / (U / v_h): grows linearly, 0 above the virtual origin
        k2 = 1.0 / (2.0 * float(self.decay_constant) * self.d0)
        past = s > float(self.virtual_origin)
        g2 = np.maximum(s - float(self.virtual_origin), 0.0) * k2
        dg2 = np.where(past, k2, 0.0)
        pw = libm.power  # (the C library's pow, as the compiled twin: the same bits on every CPU)
        phi = pw(pw(phi1, -p) + pw(g2, p), -1.0 / p)  # U_c / v_h: smooth minimum of near and far
        dphi = pw(phi, p + 1.0) * (pw(phi1, -p - 1.0) * dphi1 - pw(g2, p - 1.0) * dg2)
        b1 = self.radius_eq / np.sqrt(phi1)  # slipstream radius by continuity
        db1 = -0.5 * b1 * dphi1 / phi1
        S = float(self.spreading_rate)
        b2 = S * np.maximum(s - float(self.virtual_origin), 0.0)
        db2 = np.where(past, S, 0.0)
        b = pw(pw(b1, p) + pw(b2, p), 1.0 / p)  # smooth maximum, >= b1 > 0
        db = pw(b, 1.0 - p) * (pw(b1, p - 1.0) * db1 + pw(b2, p - 1.0) * db2)
        return v_h * phi, b, v_h * dphi, db

    def wind(self, p_a: np.ndarray, R_a: np.ndarray, p: np.ndarray, thrust: Any = None) -> np.ndarray:
        """(..., 3) m/s, world frame: the wake's air velocity at points p (..., 3) m.

        p_a (..., 3) m and R_a (..., 3, 3) the leader's position and attitude; thrust
        (...) N, default the estimate of `leader_thrust`.
        """
        p_a, R_a, p = (np.asarray(x, dtype=np.float64) for x in (p_a, R_a, p))
        n = R_a[..., :, 2]
        dp = p - p_a
        s = -_dot(dp, n)
        r_vec = dp + s[..., None] * n
        T = self.leader_thrust(R_a) if thrust is None else thrust
        axial, radial_over_r = self.induced_velocity(s, _dot(r_vec, r_vec), T)
        return radial_over_r[..., None] * r_vec - axial[..., None] * n

    def induced_velocity(self, s, r2, thrust):
        """Downstream speed U (...) m/s and V / r (...) 1/s at depth s, squared radius r2, faded."""
        U_c, b, dU_c, db = self.centreline(s, thrust)
        inv_b2 = 1.0 / (b * b)
        q = 1.0 + PROFILE_A * r2 * inv_b2  # 1 + a xi^2
        f = 1.0 / (q * q)
        d_flux = dU_c * b * b + 2.0 * U_c * b * db  # (U_c b^2)', the entrainment rate / pi * a
        v_over_r = (U_c * db * f - d_flux / (2.0 * b * q)) / b  # V / r: finite at r = 0
        t = np.clip(np.asarray(s, dtype=np.float64) / float(self.fade_depth), 0.0, 1.0)
        w = t * t * (3.0 - 2.0 * t)  # exactly 0 at and above the rotor plane
        return w * U_c * f, w * v_over_r

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
            R_a: (..., 3, 3) leader attitude, body-to-world; the wake axis is R_a[..., :, 2].
            p_b, v_b: (..., 3) m, m/s, world frame, follower position and velocity.
            thrust: optional (...) N, the leader's actual thrust; default the estimate
                thrust_scale m_a g / clip(n_z, 0.5, 1).

        Returns:
            (..., 3) m/s^2, world frame: the wake's share of the follower's rotor thrust
            change (along n) and airframe drag, mass-normalised.
        """
        p_a, v_a, R_a, p_b, v_b = (np.asarray(x, dtype=np.float64) for x in (p_a, v_a, R_a, p_b, v_b))
        n = R_a[..., :, 2]
        dp = p_b - p_a
        s = -_dot(dp, n)
        r_vec = dp + s[..., None] * n
        r2 = _dot(r_vec, r_vec)
        T = self.leader_thrust(R_a) if thrust is None else np.asarray(thrust, dtype=np.float64)
        shape = np.broadcast_shapes(s.shape, v_b.shape[:-1], v_a.shape[:-1], np.shape(T))  # as DownwashField
        ring_speed = air = None
        if self.rotors:
            # rotors on a ring of radius a about the follower: r_k^2 = r^2 + a^2 + 2 r a cos(phi_k)
            a = float(self.follower_arm)
            r = np.sqrt(r2)[..., None]
            rk2 = np.maximum(r * r + a * a + (2.0 * a) * r * self._ring_cos, 0.0)  # (..., K)
            ring_speed, _ = self.induced_velocity(s[..., None], rk2, np.asarray(T)[..., None])
        if self.drag:
            axial, radial_over_r = self.induced_velocity(s, r2, T)
            air = radial_over_r[..., None] * r_vec - axial[..., None] * n
        return np.zeros(shape + (3,)) + self.follower_response(n, v_b, ring_speed, air)

    def follower_response(self, n: np.ndarray, v_b: np.ndarray, ring_speed: Any = None, air: Any = None) -> np.ndarray:
        """The follower's rotors and airframe in a given air velocity: the wake's share (minus still air).

        Args:
            n: (..., 3) -, world frame, unit: the follower's thrust axis (along which its rotors push).
            v_b: (..., 3) m/s, world frame: the follower's velocity relative to the ambient air.
            ring_speed: (..., K) m/s, the air's speed down through each rotor of the ring of
                `ring_points` rotors at `follower_arm`, along -n (needed when `rotors`).
            air: (..., 3) m/s, world frame: the wake's air velocity at the follower's centre
                (needed when `drag`).

        Returns:
            (..., 3) m/s^2, world frame: g (mean_k tau(c_k) - tau(c_0)) n, c_k = (ring_speed_k + v_b.n) / v_hf
            (`rotor_thrust_ratio`), plus drag_acceleration(air, v_b) - drag_acceleration(0, v_b).
        """
        out = np.zeros(np.broadcast_shapes(np.shape(n), np.shape(v_b)))
        if self.rotors:
            climb = _dot(v_b, n)  # m/s, the follower's own climb rate along n
            c0 = climb / self.vh_follower
            c_k = (ring_speed + climb[..., None]) / self.vh_follower
            d_tau = rotor_thrust_ratio(c_k).mean(axis=-1) - rotor_thrust_ratio(c0)
            out = out + (GRAVITY * d_tau)[..., None] * n  # T_h / m = g
        if self.drag:
            # the wake's share: the drag in the wake minus the drag in still air
            in_wake = drag_acceleration(air, v_b, *self.drag_law)
            out = out + (in_wake - drag_acceleration(_STILL_AIR, v_b, *self.drag_law))
        return out
