"""gym-pybullet-drones' downwash law as a ground-truth field.

gym-pybullet-drones (utiasDSL/gym-pybullet-drones, `gym_pybullet_drones/envs/BaseAviary.py`,
`BaseAviary._downwash`, at commit 90b178aba69b09085dd70e7a1e88bb58ca00b4c9; "based on experiments
conducted at the Dynamic Systems Lab by SiQi Zhou") pushes a vehicle down when another is above it.
For a vehicle above at height difference dz > 0 (m) and horizontal distance dxy (m) it applies, in
newtons, at the lower vehicle's centre of mass along its body -z (`p.LINK_FRAME`),

    F = alpha exp(-0.5 (dxy / beta)^2),   alpha = C1 (r / (4 dz))^2,   beta = C2 dz + C3

with the constants of its Crazyflie model `gym_pybullet_drones/assets/cf2x.urdf` (`<properties>`,
commit 889ce4a5c068ae4d811df1442ceb4f4d6cdf43eb): C1 = dw_coeff_1 = 2267.18 N, C2 = dw_coeff_2 =
0.16, C3 = dw_coeff_3 = -0.11 m, r = prop_radius = 0.0231348 m, on a vehicle of 0.027 kg
(`base_link` mass), so alpha = 0.0758 N / dz^2. (racer.urdf has the same coefficients with
r = 0.127 m on 0.830 kg: the same acceleration within 2 %.)

Here, as every field, the law returns the follower's acceleration: F / m with m = `follower_mass`
= 0.027 kg, the vehicle the law was written for: 2.81 m/s^2 / dz^2 (dz in m) on the axis, 2.81
m/s^2 at 1 m. The geometry is measured along the leader's thrust axis n (dz = s = -dp . n, dxy = r the
distance from the axis) and the push is along -n: the convention of `sim.field`, the
same for a level leader and a level follower as gym-pybullet-drones' world-z geometry and body-z push.

Where the law is not defined, and how it is defined here (all parameters, so a fit can move them):

- beta <= 0 for dz <= -C3 / C2 = 0.6875 m: the published width is negative near the leader.
  gym-pybullet-drones squares it, so it flies a width |beta| that shrinks to 0 at 0.6875 m
  (0/0 there on the axis: NaN) and grows again toward the leader. Here the width is
  beta_eff = (max(beta, 0)^4 + w0^4)^(1/4): the law's beta where it is wide, never narrower than
  w0 = `min_width` = 0.030 m (the lateral standard deviation of a Crazyflie's four rotor discs about
  its centre, sqrt(L^2 / 2 + r^2 / 4) with arm L = 0.0397 m and r from cf2x.urdf: an estimate; the
  wake is no narrower than the rotors that make it), smooth in beta and C2, C3, and monotone in
  dz. `mirror_width=true` takes gym-pybullet-drones' |beta| instead (beta^4 in place of
  max(beta, 0)^4), which reproduces what it flies except where |beta| < w0.
- alpha grows as 1 / dz^2 without bound. Here alpha is taken at max(dz, near_depth), near_depth
  = 0.535 m: the depth at which the law's push equals the Crazyflie's weight, (r / 4)
  sqrt(C1 / (m g)) (an estimate: a hovering leader's wake carries a momentum flux equal to its
  weight, and a follower of its kind cannot stop more of it than all of it).
- dz <= 0 (the follower level with or above the leader): zero, as in gym-pybullet-drones; the push is
  faded in over `fade_depth` = r below the leader by a smoothstep (the `momentum` field's fade: one rotor
  radius), so the field is continuous and exactly zero at and above the leader.
- gym-pybullet-drones ignores vehicles more than 10 m apart horizontally; that cut-off is left out (a
  jump in the field of at most 5e-4 m/s^2, at dz ~ 45 m: the Gaussian is tiny there).

Other vehicle kinds (`sim.vehicle_params.pair_field` calls `for_kinds`): the push, an acceleration of a
Crazyflie in a Crazyflie's wake, is scaled as `so2`'s strength, by `so2_pair_scale(leader, follower)`
= (m_l / m_f) min(1, A_f / A_l) (the leader's disc loading on the part of the follower's discs inside
the wake, per kilogram; docs/fields.md): 1 for two vehicles of one kind, as gym-pybullet-drones' own
racer confirms. The law's widths and depths stay the Crazyflie's.

Units: m, N, kg; returns (..., 3) m/s^2. Symmetry: SO(2) about the leader's axis and reflections
through planes containing it, for any leader tilt; translation-invariant; v_a and v_b unused.
Finite for every finite input.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from downwash_core import libm
from downwash_core.errors import ConfigError
from downwash_core.geometry import dot as _dot
from downwash_core.validate import number
from downwash_core.vehicles import so2_pair_scale

__all__ = ["PybulletDownwash", "CF2X_DW_COEFF_1", "CF2X_DW_COEFF_2", "CF2X_DW_COEFF_3", "CF2X_PROP_RADIUS",
           "CF2X_MASS"]

# gym-pybullet-drones gym_pybullet_drones/assets/cf2x.urdf (commit 889ce4a), <properties> and base_link
CF2X_DW_COEFF_1 = 2267.18  # N, dw_coeff_1
CF2X_DW_COEFF_2 = 0.16  # -, dw_coeff_2
CF2X_DW_COEFF_3 = -0.11  # m, dw_coeff_3
CF2X_PROP_RADIUS = 0.0231348  # m, prop_radius
CF2X_MASS = 0.027  # kg, base_link <mass value="0.027"/>


@dataclass(frozen=True)
class PybulletDownwash:
    """gym-pybullet-drones' downwash law (`BaseAviary._downwash`), as the follower's acceleration.

    See the module docstring for the law, its sources, and how it is defined where the original
    is not. Every constant is a plain number, checked on construction (ConfigError naming the bad one).
    """

    dw_coeff_1: float = CF2X_DW_COEFF_1  # N, C1: alpha = C1 (r / (4 dz))^2
    dw_coeff_2: float = CF2X_DW_COEFF_2  # -, C2: beta = C2 dz + C3
    dw_coeff_3: float = CF2X_DW_COEFF_3  # m, C3
    prop_radius: float = CF2X_PROP_RADIUS  # m, r
    follower_mass: float = CF2X_MASS  # kg, the vehicle the law's force acts on: accel = F / m
    min_width: float = 0.030  # m, w0: beta_eff = (max(beta, 0)^4 + w0^4)^(1/4) (estimate, module docstring)
    near_depth: float = 0.535  # m, alpha is taken at max(dz, near_depth) (estimate: the push = the weight)
    fade_depth: float = CF2X_PROP_RADIUS  # m, the push fades in over this depth below the leader
    mirror_width: bool = False  # take |beta| where beta < 0, as gym-pybullet-drones flies, not max(beta, 0)

    def __post_init__(self) -> None:
        number("dw_coeff_1", self.dw_coeff_1, "N", 0.0, 1e9)
        number("dw_coeff_2", self.dw_coeff_2, "-", -100.0, 100.0)
        number("dw_coeff_3", self.dw_coeff_3, "m", -100.0, 100.0)
        number("prop_radius", self.prop_radius, "m", 0.0, 10.0, lo_open=True)
        number("follower_mass", self.follower_mass, "kg", 0.0, 1e6, lo_open=True)
        number("min_width", self.min_width, "m", 0.0, 100.0, lo_open=True)
        number("near_depth", self.near_depth, "m", 0.0, 100.0, lo_open=True)
        number("fade_depth", self.fade_depth, "m", 0.0, 100.0, lo_open=True)
        if not isinstance(self.mirror_width, (bool, np.bool_)):
            raise ConfigError(f"mirror_width: expected True or False, got {self.mirror_width!r}")
        w0 = float(self.min_width)
        derived = {
            # accel on the axis = this / max(dz, near_depth)^2, m^3/s^2
            "_alpha_accel": float(self.dw_coeff_1) * (float(self.prop_radius) / 4.0) ** 2 / float(self.follower_mass),
            "_near_depth2": float(self.near_depth) ** 2,
            "_w0_4": w0 ** 4,  # m^4
        }
        for name, value in derived.items():
            object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ provenance and kinds
    def describe(self) -> dict[str, Any]:
        """Stable provenance: the law's name, type and every parameter (no addresses)."""
        params = {k: (bool(v) if isinstance(v, (bool, np.bool_)) else v) for k, v in asdict(self).items()}
        return {"type": f"{type(self).__module__}.{type(self).__qualname__}", "name": "pybullet", **params}

    def for_kinds(self, leader: Any, follower: Any) -> "PybulletDownwash":
        """The law for a `leader` over a `follower` of these kinds: C1 x `so2_pair_scale(leader, follower)`
        (itself where that is 1: every pair of one kind)."""
        scale = so2_pair_scale(leader, follower)
        return self if scale == 1.0 else dataclasses.replace(self, dw_coeff_1=self.dw_coeff_1 * scale)

    # ------------------------------------------------------------------ the law
    def width(self, dz: Any) -> np.ndarray:
        """beta_eff (...) m at depth dz (...) m: (max(beta, 0)^4 + w0^4)^(1/4), beta = C2 dz + C3 (|beta| when
        `mirror_width`)."""
        return np.sqrt(self._width2(dz))

    def _width2(self, dz: Any) -> np.ndarray:
        """beta_eff^2 (...) m^2 = sqrt(core^4 + w0^4) >= w0^2 > 0 at depth dz (...) m."""
        beta = float(self.dw_coeff_2) * np.asarray(dz, dtype=np.float64) + float(self.dw_coeff_3)
        core = beta if self.mirror_width else np.maximum(beta, 0.0)
        core2 = core * core
        return np.sqrt(core2 * core2 + self._w0_4)

    def push(self, dz: Any, r2: Any) -> np.ndarray:
        """(...) m/s^2, the push's magnitude at depth dz (...) m below the leader and squared distance r2 (...) m^2
        from its axis: w(dz) alpha(max(dz, near_depth)) exp(-0.5 r2 / beta_eff^2) / m; 0 for dz <= 0."""
        dz = np.asarray(dz, dtype=np.float64)
        width2 = self._width2(dz)  # m^2, beta_eff^2
        t = np.clip(dz / float(self.fade_depth), 0.0, 1.0)
        alpha = self._alpha_accel / np.maximum(dz * dz, self._near_depth2)
        gauss = libm.exp(-0.5 * np.asarray(r2, dtype=np.float64) / width2)
        return (t * t * (3.0 - 2.0 * t)) * alpha * gauss  # exactly 0 at and above the leader

    def __call__(self, p_a: np.ndarray, v_a: np.ndarray, R_a: np.ndarray, p_b: np.ndarray,
                 v_b: np.ndarray) -> np.ndarray:
        """The law's push on the follower.

        Args:
            p_a, v_a: (..., 3) m, m/s, world frame, leader position and velocity (v_a unused).
            R_a: (..., 3, 3) leader attitude, body-to-world; its axis n = R_a[..., :, 2].
            p_b, v_b: (..., 3) m, m/s, world frame, follower position and velocity (v_b unused).

        Returns:
            (..., 3) m/s^2, world frame: -push(s, r^2) n, s = -dp . n, r the distance from the axis.
        """
        p_a, v_a, R_a, p_b, v_b = (np.asarray(x, dtype=np.float64) for x in (p_a, v_a, R_a, p_b, v_b))
        n = R_a[..., :, 2]
        dp = p_b - p_a
        s = -_dot(dp, n)
        r_vec = dp + s[..., None] * n
        shape = np.broadcast_shapes(s.shape, v_a.shape[:-1], v_b.shape[:-1])
        return np.zeros(shape + (3,)) - self.push(s, _dot(r_vec, r_vec))[..., None] * n
