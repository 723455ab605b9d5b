"""Ambient wind: a mean wind plus Dryden turbulence, and the drag law through which it acts.

`DrydenWind(mean, w20, altitude)` is the wind every vehicle feels: the air velocity
(m/s, world frame, z up; a +x wind is air moving toward +x) is `mean + gust`.

Axes (MIL-F-8785C sec. 3.7, low altitude: the turbulence axes follow the mean wind).
u longitudinal = the horizontal direction of the mean wind (world x when the mean wind
has no horizontal part), v lateral = z x u (horizontal, left of the wind), w = world z.

Intensities and scales (MIL-F-8785C, 1980, sec. 3.7 atmospheric disturbances; MIL-HDBK-1797,
1997, the same Dryden model; low altitude, h < 1000 ft). With h the altitude in ft and W20
the wind speed at 20 ft (any unit):
    L_w = h,   L_u = L_v = h / (0.177 + 0.000823 h)^1.2            (ft)
    sigma_w = 0.1 W20,   sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4
W20 presets: light 15 kt, moderate 30 kt, severe 45 kt (`PRESETS_KT`). Conversions:
h_ft = h_m / 0.3048, L_m = 0.3048 L_ft (international foot, exact), W20 (m/s) =
kt * 1852 / 3600 (international knot, exact); the sigma laws are ratios, so sigma
carries W20's unit (m/s). The formulas fail near the ground (L -> 0); as in
MIL-HDBK-1797 the altitude is clamped to h >= 10 ft = 3.048 m (`MIN_ALTITUDE`), which is
where this testbed's vehicles fly (1-3 m).

Forming filters (MIL-F-8785C form; MIL-HDBK-1797 writes the same spectra with 2L_v,
2L_w and L_w = h/2), V the airspeed (m/s) and T = L / V (s):
    H_u(s) = sigma_u sqrt(2 L_u / (pi V)) / (1 + T_u s)
    H_v(s) = sigma_v sqrt(L_v / (pi V)) (1 + sqrt(3) T_v s) / (1 + T_v s)^2,  H_w alike
whose one-sided PSDs in omega (rad/s), Phi = |H(j omega)|^2, integrate over [0, inf)
to sigma^2. Driven by white noise of unit intensity (E w(t) w(t') = delta(t - t')) the
filter is sqrt(pi) H. Realisation per axis (state (2,), scaled so that its stationary
covariance does not depend on V: an airspeed change keeps the state stationary):
    u:    x1' = -x1 / T + sigma sqrt(2 / T) w,                   gust = x1   (x2' = -x2 / T, unused)
    v, w: x1' = -x1 / T + sigma / sqrt(T) w,  x2' = (x1 - x2) / T,  gust = sqrt(3) x1 + (1 - sqrt(3)) x2
Exact sampling every dt (the autopilot grid): x[k+1] = A x[k] + B xi[k], gust[k] = C x[k]
(D = 0), xi ~ N(0, I_2) per axis, A = exp(A_c dt) and B B^T = Q = int_0^dt e^(A_c s) b b^T
e^(A_c^T s) ds, so the samples have exactly the continuous process's autocovariance at
every lag (a zero-order hold on white noise would not). With r = dt / T, a = e^-r and
P_n = the regularised lower incomplete gamma P(n, 2r) (`scipy.special.gammainc`):
    u:    A = [[a, 0], [0, a]],       Q = sigma^2 [[P_1, 0], [0, 0]]         (b = sigma sqrt(1 - a^2))
    v, w: A = a [[1, 0], [r, 1]],     Q = sigma^2 [[P_1 / 2, P_2 / 4], [P_2 / 4, P_3 / 4]]
B is Q's Cholesky factor. Taylor's frozen-turbulence hypothesis sets the time scales
from the airspeed V = |v_vehicle - mean| (`airspeed`), floored at `min_airspeed`
(1 m/s): a hovering vehicle in still air still sees the turbulence evolve.

Randomness enters only through the standard normal draws `xi` (..., 3, 2) passed in;
the simulator draws them from a wind generator of each world. `step`, `gust` and
`stationary_state` are the readable law; the simulator's compiled loop runs the same law
per world and tick with `gust_step_into` / `gust_into` (the coefficients of
`coefficients`, computed in the kernel by `coefficients_into` for the airspeed of the
moment), which a test compares with the readable law.

Drag. The wind acts on a vehicle through the airframe's quadratic drag on the
relative air velocity, `drag_acceleration`; its constants are defined once, in
`AIRFRAME` (`AirframeDrag`: C_d = 1.0, A_ref = 0.01 m^2, rho = 1.225 kg/m^3), which the
momentum-theory wake (`sim.fields.momentum.MomentumWake`) uses as well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import gammainc

from downwash_core import libm
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.params import LEADER_POSITION
from downwash_core.validate import number
from downwash_core.numerics import matmul_rows, matvec
from downwash_core.vehicle_kind import AIR_DENSITY  # kg/m^3, ISA sea level: the one definition

__all__ = [
    "DrydenWind", "AirframeDrag", "AIRFRAME", "AIR_DENSITY", "drag_acceleration", "wind_at", "FT", "KT",
    "MIN_ALTITUDE", "MAX_ALTITUDE", "PRESETS_KT", "coefficients_into", "gust_step_into", "gust_into", "drag_gain_speed",
]

FT = 0.3048  # m per international foot (exact)
KT = 1852.0 / 3600.0  # m/s per international knot (exact)
MIN_ALTITUDE = 10.0 * FT  # m, 10 ft: the low-altitude formulas are used at h >= this (MIL-HDBK-1797)
MAX_ALTITUDE = 1000.0 * FT  # m, 1000 ft: the low-altitude model's upper limit
PRESETS_KT = {"light": 15.0, "moderate": 30.0, "severe": 45.0}  # W20, kt (MIL-F-8785C)
_SQRT3 = math.sqrt(3.0)
_C_AXIS = np.array([[1.0, 0.0], [_SQRT3, 1.0 - _SQRT3], [_SQRT3, 1.0 - _SQRT3]])  # (3, 2) gust = C x per axis


@dataclass(frozen=True)
class AirframeDrag:
    """The airframe's quadratic drag constants: the one definition every force law uses.

    C_d = 1.0 and A_ref = 0.01 m^2: a bluff body (Hoerner, *Fluid-Dynamic Drag*, 1965,
    ch. 3: a flat plate normal to the flow has C_d ~ 1.2); A_ref ~ the 8 x 8 cm body plus
    four 9 x 1 cm arms. rho: ISA sea level. Used by the ambient wind in the simulator and
    by `sim.fields.momentum.MomentumWake` (its defaults).
    """

    drag_coefficient: float = 1.0  # -, C_d
    reference_area: float = 0.01  # m^2, A_ref
    air_density: float = AIR_DENSITY  # kg/m^3, rho

    def __post_init__(self) -> None:
        object.__setattr__(self, "drag_coefficient", number("drag_coefficient", self.drag_coefficient, "-", 0.0, 100.0))
        object.__setattr__(self, "reference_area", number("reference_area", self.reference_area, "m^2", 0.0, 100.0))
        object.__setattr__(self, "air_density", number("air_density", self.air_density, "kg/m^3", 0.0, 1e6))

    def gain(self, mass: float) -> float:
        """rho C_d A_ref / (2 m) (1/m) for a vehicle of `mass` (kg > 0)."""
        mass = number("mass", mass, "kg", 0.0, 1e6, lo_open=True)
        return self.air_density * self.drag_coefficient * self.reference_area / (2.0 * mass)

    def acceleration(self, air_velocity, vehicle_velocity, mass) -> np.ndarray:
        """`drag_acceleration` with these constants: (..., 3) m/s^2."""
        return drag_acceleration(air_velocity, vehicle_velocity, mass, self.drag_coefficient, self.reference_area,
                                 self.air_density)

    def describe(self) -> dict[str, Any]:
        return {"type": f"{type(self).__module__}.{type(self).__qualname__}", "drag_coefficient": self.drag_coefficient,
                "reference_area": self.reference_area, "air_density": self.air_density}


AIRFRAME = AirframeDrag()  # the testbed's quadrotor airframe


def drag_acceleration(air_velocity, vehicle_velocity, mass, drag_coefficient, reference_area,
                      air_density=AIR_DENSITY) -> np.ndarray:
    """Quadratic drag on the relative air velocity, mass-normalised (m/s^2, (..., 3)).

    a = rho C_d A_ref / (2 m) |u - v| (u - v): u the air velocity and v the vehicle's
    (m/s, (..., 3), world frame), m (kg), C_d (-), A_ref (m^2), rho (kg/m^3), scalars or
    (...); the testbed's airframe constants are `AIRFRAME`. The airframe drag of
    `sim.fields.momentum.MomentumWake` is this law: its wake share is
    drag_acceleration(u, v_b, ...) - drag_acceleration(0, v_b, ...).
    |u - v| is taken with hypot (no overflow of the squares); the result is finite
    whenever the drag itself is representable. The simulator's compiled loop computes
    the same product, (gain * |u - v|) (u - v), with `drag_gain_speed`.
    """
    rel = np.asarray(air_velocity, dtype=np.float64) - np.asarray(vehicle_velocity, dtype=np.float64)
    mass = np.asarray(mass, dtype=np.float64)
    if np.any(~(mass > 0)):
        raise ConfigError(f"mass: must be > 0 kg, got {mass!r}")
    gain = np.asarray(air_density, dtype=np.float64) * np.asarray(drag_coefficient, dtype=np.float64) \
        * np.asarray(reference_area, dtype=np.float64) / (2.0 * mass)  # 1/m
    speed = np.hypot(np.hypot(rel[..., 0], rel[..., 1]), rel[..., 2])  # m/s
    return (gain * speed)[..., None] * rel


def wind_at(mean, gust) -> np.ndarray:
    """The air velocity (..., 3) m/s, world frame: the mean wind (3,) or (..., 3) plus the gust (..., 3)."""
    return np.asarray(mean, dtype=np.float64) + np.asarray(gust, dtype=np.float64)


@dataclass(frozen=True)
class DrydenWind:
    """A mean wind plus Dryden turbulence (MIL-F-8785C / MIL-HDBK-1797, low altitude).

    Checked on construction (ConfigError naming the bad parameter and its range).
    The defaults are off: no mean wind, no turbulence. See the module docstring.
    """

    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m/s, world frame, the mean air velocity
    w20: float = 0.0  # m/s, wind speed at 20 ft, sets the intensities (0: no turbulence)
    altitude: float = LEADER_POSITION[2]  # m above ground where the turbulence is evaluated (clamped >= 10 ft)
    min_airspeed: float = 1.0  # m/s, floor of V in the time scales L / V (hover)

    def __post_init__(self) -> None:
        bad = ConfigError(f"mean: got {self.mean!r}; allowed 3 finite numbers (m/s) with |mean| <= 100 m/s")
        try:
            mean = tuple(float(x) for x in self.mean)
        except (TypeError, ValueError):
            raise bad from None
        if len(mean) != 3 or not all(math.isfinite(x) for x in mean) or math.hypot(*mean) > 100.0:
            raise bad
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "w20", number("w20", self.w20, "m/s", 0.0, 100.0))
        object.__setattr__(self, "altitude", number("altitude", self.altitude, "m", 0.0, MAX_ALTITUDE, lo_open=True))
        object.__setattr__(self, "min_airspeed", number("min_airspeed", self.min_airspeed, "m/s", 0.0, 100.0,
                                                        lo_open=True))

    @classmethod
    def preset(cls, severity: str, **kwargs: Any) -> DrydenWind:
        """The MIL-F-8785C W20 of `severity` ('light' 15 kt, 'moderate' 30 kt, 'severe' 45 kt), in m/s."""
        if severity not in PRESETS_KT:
            raise ConfigError(f"severity: got {severity!r}; allowed: {', '.join(PRESETS_KT)}")
        return cls(w20=PRESETS_KT[severity] * KT, **kwargs)

    # ------------------------------------------------------------------ the spec
    @property
    def off(self) -> bool:
        """True when there is neither a mean wind nor turbulence."""
        return self.w20 == 0.0 and not any(self.mean)

    @property
    def effective_altitude(self) -> float:
        """m, the altitude used in the formulas: max(altitude, 10 ft)."""
        return max(self.altitude, MIN_ALTITUDE)

    def scales(self) -> dict[str, float]:
        """Intensities sigma_{u,v,w} (m/s) and scale lengths L_{u,v,w} (m) at `effective_altitude`."""
        h = self.effective_altitude / FT  # ft
        k = 0.177 + 0.000823 * h  # -
        sigma_w = 0.1 * self.w20  # m/s
        sigma_u = sigma_w / k**0.4
        L_u = h / k**1.2 * FT  # ft -> m
        return {"sigma_u": sigma_u, "sigma_v": sigma_u, "sigma_w": sigma_w, "L_u": L_u, "L_v": L_u, "L_w": h * FT}

    def axes(self) -> np.ndarray:
        """(3, 3) rows e_u, e_v, e_w: the turbulence axes in the world frame (gust_world = axes.T @ g_uvw)."""
        horizontal = math.hypot(self.mean[0], self.mean[1])
        cx, cy = (self.mean[0] / horizontal, self.mean[1] / horizontal) if horizontal > 0 else (1.0, 0.0)
        return np.array([[cx, cy, 0.0], [-cy, cx, 0.0], [0.0, 0.0, 1.0]])

    def airspeed(self, vehicle_velocity) -> np.ndarray:
        """V (...) m/s: |v_vehicle - mean| floored at `min_airspeed`; vehicle_velocity (..., 3) m/s, world."""
        rel = np.asarray(vehicle_velocity, dtype=np.float64) - np.asarray(self.mean)
        return np.maximum(np.hypot(np.hypot(rel[..., 0], rel[..., 1]), rel[..., 2]), self.min_airspeed)

    def _sigma_T(self, airspeed) -> tuple[np.ndarray, np.ndarray]:
        V = np.asarray(airspeed, dtype=np.float64)
        if not np.all(np.isfinite(V) & (V >= 0.0)):
            raise ConfigError(f"airspeed: must be finite and >= 0 m/s, got {airspeed!r}")
        V = np.maximum(V, self.min_airspeed)[..., None]  # (..., 1)
        s = self.scales()
        sigma = np.array([s["sigma_u"], s["sigma_v"], s["sigma_w"]])  # (3,) m/s
        return sigma, np.array([s["L_u"], s["L_v"], s["L_w"]]) / V  # (3,), (..., 3) s

    # ------------------------------------------------------------------ the filters
    def forming_filter(self, airspeed) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The continuous forming filters for unit-intensity white noise: x' = A_c x + b w, gust = c x.

        airspeed (...) m/s; returns A_c (..., 3, 2, 2) 1/s, b (..., 3, 2) m s^-1.5 (w has units
        s^-0.5), c (3, 2) -. Axis order u, v, w (see `axes`); the state is in m/s.
        """
        sigma, T = self._sigma_T(airspeed)
        A = np.zeros(T.shape + (2, 2))
        A[..., 0, 0] = A[..., 1, 1] = -1.0 / T
        A[..., 1:, 1, 0] = 1.0 / T[..., 1:]
        b = np.zeros(T.shape + (2,))
        b[..., 0] = sigma * np.sqrt(np.array([2.0, 1.0, 1.0]) / T)
        return A, b, _C_AXIS.copy()

    def coefficients(self, dt: float, airspeed) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C) of the exact sampled recursion, for compiled callers.

        x[k+1] = A x[k] + B xi[k] per axis, gust_world[k] = sum_{axis, j} C[:, axis, j] x[k, axis, j]
        (D = 0). dt (s); airspeed (...) m/s (floored at `min_airspeed`). Returns A (..., 3, 2, 2) -,
        B (..., 3, 2, 2) m/s, C (3, 3, 2) -: the axis gains rotated into the world frame.
        """
        dt = number("dt", dt, "s", 0.0, 1.0, lo_open=True)
        sigma, T = self._sigma_T(airspeed)
        r = dt / T  # (..., 3)
        a = libm.exp(-r)
        P1, P2, P3 = (gammainc(n, 2.0 * r) for n in (1, 2, 3))
        second = np.array([0.0, 1.0, 1.0])  # the second state is driven and read on v, w only
        A = np.zeros(T.shape + (2, 2))
        A[..., 0, 0] = a
        A[..., 1, 0] = second * a * r
        A[..., 1, 1] = a
        q11 = sigma**2 * np.where(second > 0, P1 / 2.0, P1)
        q21 = second * sigma**2 * P2 / 4.0
        q22 = second * sigma**2 * P3 / 4.0
        B = np.zeros_like(A)
        B[..., 0, 0] = np.sqrt(q11)
        B[..., 1, 0] = np.divide(q21, B[..., 0, 0], out=np.zeros_like(q21), where=B[..., 0, 0] > 0)
        B[..., 1, 1] = np.sqrt(np.maximum(q22 - B[..., 1, 0] ** 2, 0.0))
        C = self.axes().T[:, :, None] * _C_AXIS[None]  # (world, axis, state)
        return A, B, C

    # ------------------------------------------------------------------ the readable law
    def step(self, state, xi, dt: float, airspeed) -> np.ndarray:
        """The next state (..., 3, 2) from `state` (..., 3, 2) and standard normal draws `xi` (..., 3, 2).

        dt (s); airspeed (...) m/s, the batch shape (e.g. (W, V)) or a scalar.
        """
        A, B, _ = self.coefficients(dt, airspeed)
        state, xi = np.asarray(state, dtype=np.float64), np.asarray(xi, dtype=np.float64)
        return matvec(A, state) + matvec(B, xi)

    def gust(self, state) -> np.ndarray:
        """The gust (..., 3) m/s in the world frame from the state (..., 3, 2)."""
        g_axis = (np.asarray(state, dtype=np.float64) * _C_AXIS).sum(axis=-1)  # (..., 3) u, v, w
        return matmul_rows(g_axis, self.axes())

    def stationary_state(self, xi) -> np.ndarray:
        """A state (..., 3, 2) drawn from the stationary distribution (any airspeed) with draws xi (..., 3, 2).

        Stationary state covariance: u [[sigma^2, 0], [0, 0]]; v, w sigma^2 [[1/2, 1/4], [1/4, 1/4]].
        """
        s = self.scales()
        sigma = np.array([s["sigma_u"], s["sigma_v"], s["sigma_w"]])  # m/s
        L = np.zeros((3, 2, 2))
        L[0, 0, 0] = sigma[0]
        L[1:] = (sigma[1:, None, None] / math.sqrt(2.0)) * np.array([[1.0, 0.0], [0.5, 0.5]])
        return matvec(L, np.asarray(xi, dtype=np.float64))

    def wind(self, state) -> np.ndarray:
        """The air velocity (..., 3) m/s, world frame: mean + gust(state)."""
        return wind_at(self.mean, self.gust(state))

    def kernel_constants(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
        """What the compiled loop needs: mean (3,) m/s, sigma_{u,v,w} (3,) m/s, L_{u,v,w} (3,) m,
        axes (3, 3) (rows e_u, e_v, e_w) and min_airspeed (m/s); float64, contiguous."""
        s = self.scales()
        return (np.array(self.mean), np.array([s["sigma_u"], s["sigma_v"], s["sigma_w"]]),
                np.array([s["L_u"], s["L_v"], s["L_w"]]), np.ascontiguousarray(self.axes()), float(self.min_airspeed))

    def describe(self) -> dict[str, Any]:
        """Stable provenance: the law, every parameter and the derived MIL-spec scales."""
        return {
            "type": f"{type(self).__module__}.{type(self).__qualname__}", "name": "dryden",
            "model": "Dryden, MIL-F-8785C / MIL-HDBK-1797 low altitude",
            "mean": list(self.mean), "w20": self.w20, "altitude": self.altitude,
            "min_airspeed": self.min_airspeed, "effective_altitude": self.effective_altitude,
            **{k: float(v) for k, v in self.scales().items()},
        }


# ----------------------------------------------------------------------- compiled forms
# The simulator advances each world's gust state on the autopilot grid inside its compiled
# loop, with an airspeed that changes every tick; these are `coefficients`, `step` and
# `gust` for one state (3, 2) at one airspeed, in the same arithmetic order (a test compares
# them with the readable law; gammainc is computed here in closed form, see `_gammainc`).


@njit
def _gammainc(n, x):
    """The regularised lower incomplete gamma P(n, x) for n = 1, 2, 3 and x >= 0.

    x < 1: the series e^-x x^n / n! sum_k x^k / ((n + 1) ... (n + k)) (positive terms, no
    cancellation); x >= 1: 1 - e^-x sum_{k < n} x^k / k! (P >= 0.08 there, no cancellation).
    """
    if x < 1.0:
        term = 1.0
        total = 1.0
        k = 1
        while term > 1e-17 * total:
            term *= x / (n + k)
            total += term
            k += 1
        factorial = 1.0
        for j in range(2, n + 1):
            factorial *= j
        return math.exp(-x) * x**n / factorial * total
    partial = 1.0
    term = 1.0
    for k in range(1, n):
        term *= x / k
        partial += term
    return 1.0 - math.exp(-x) * partial


@njit
def coefficients_into(dt, airspeed, sigma, length, min_airspeed, A, B):
    """`DrydenWind.coefficients(dt, airspeed)` for one scalar airspeed (m/s) into A, B (3, 2, 2).

    sigma (3,) m/s and length (3,) m: `kernel_constants`; dt (s); min_airspeed (m/s).
    """
    V = max(airspeed, min_airspeed)
    for ax in range(3):
        T = length[ax] / V  # s
        r = dt / T
        a = math.exp(-r)
        s2 = sigma[ax] ** 2
        A[ax, 0, 0] = a
        A[ax, 0, 1] = 0.0
        A[ax, 1, 1] = a
        B[ax, 0, 1] = 0.0
        if ax == 0:  # longitudinal: first order, the second state only decays
            A[ax, 1, 0] = 0.0
            B[ax, 0, 0] = math.sqrt(s2 * _gammainc(1, 2.0 * r))
            B[ax, 1, 0] = 0.0
            B[ax, 1, 1] = 0.0
        else:
            A[ax, 1, 0] = a * r
            b11 = math.sqrt(s2 * (_gammainc(1, 2.0 * r) / 2.0))
            q21 = s2 * _gammainc(2, 2.0 * r) / 4.0
            q22 = s2 * _gammainc(3, 2.0 * r) / 4.0
            b21 = q21 / b11 if b11 > 0.0 else 0.0
            B[ax, 0, 0] = b11
            B[ax, 1, 0] = b21
            B[ax, 1, 1] = math.sqrt(max(q22 - b21 * b21, 0.0))


@njit
def gust_step_into(state, xi, A, B):
    """state (3, 2) <- A state + B xi in place (`DrydenWind.step`), xi (3, 2) standard normals."""
    for ax in range(3):
        x0, x1 = state[ax, 0], state[ax, 1]
        state[ax, 0] = A[ax, 0, 0] * x0 + A[ax, 0, 1] * x1 + (B[ax, 0, 0] * xi[ax, 0] + B[ax, 0, 1] * xi[ax, 1])
        state[ax, 1] = A[ax, 1, 0] * x0 + A[ax, 1, 1] * x1 + (B[ax, 1, 0] * xi[ax, 0] + B[ax, 1, 1] * xi[ax, 1])


@njit
def gust_into(state, axes, out):
    """The gust (3,) m/s, world frame, from the state (3, 2) (`DrydenWind.gust`) into out."""
    g0 = state[0, 0] * 1.0 + state[0, 1] * 0.0
    g1 = state[1, 0] * _SQRT3 + state[1, 1] * (1.0 - _SQRT3)
    g2 = state[2, 0] * _SQRT3 + state[2, 1] * (1.0 - _SQRT3)
    for k in range(3):
        out[k] = g0 * axes[0, k] + g1 * axes[1, k] + g2 * axes[2, k]


@njit
def drag_gain_speed(rx, ry, rz, gain):
    """gain |r| for the relative air velocity r = u - v (m/s): the drag is this times r (`drag_acceleration`)."""
    return gain * math.hypot(math.hypot(rx, ry), rz)
