"""How the wakes of several vehicles combine on one vehicle: the aggregation law.

A ground-truth field (`sim.field.DownwashField`, `sim.fields.momentum.MomentumWake`)
gives the force f_ij (m/s^2, world frame) of one leader i's wake on one follower j.
With more than two vehicles something must say how the f_ij of all leaders combine
into the force F_j on j. That choice is made here, once, explicitly:

    law          F_j =                                            parameters
    linear       sum_i f_ij  (today's `pairwise_field`, bit for bit)   -
    velocity     |G_j|^(p-1) G_j,  G_j = sum_i |f_ij|^(1/p-1) f_ij     exponent p in [0.5, 3], default 2
    shielding    sum_i f_ij prod_k (1 - eta g_k(i, j))                 eta, radius, ramp

(see each class for the physical argument, the proof that it reduces exactly to the
pairwise force for two vehicles, units and assumptions). Every law is invariant to
the order of the vehicles (a permutation of the vehicle axis permutes the output the
same way) and depends on the vehicles' geometry, never on their indices.

The default is `linear`, deliberately:

1. it is the assumption of the paper and of `sim.field` (the field is "a pairwise
   sum over all leaders"); the learned models are pairwise, and every stored result and
   golden log was made with it, so it stays bit for bit what it was;
2. it is the neutral middle of what the physics gives if the wakes' velocities
   superpose: a response linear in the inflow makes the forces superpose too (`linear`
   is `velocity` with p = 1); the follower's airframe drag is quadratic (p = 2,
   super-linear), while its rotor thrust saturates (`sim.fields.momentum`'s
   rotor_thrust_ratio: linear, p = 1.00, for inflow c = V / v_h < 0.3, but p = 0.81 fitted
   over c = 0.9-1.9, the on-axis inflow 0.3-1.5 m below a leader in `MomentumWake`,
   sub-linear); in `MomentumWake` the two terms are of similar size near the axis;
3. what is not linear (a wake meeting a vehicle in its way, wakes merging) has no
   measured law for these vehicles. arXiv:2312.03488 ("Modeling Aggregate Downwash
   Forces for Dense Multirotor Flight", 2023) measured the aggregate force on a
   multirotor under two others (side by side, leader-follower, stack) and found strong
   non-linearities that a sum of pairwise forces misses, but no closed-form law.
   `velocity` and `shielding` are therefore explicit, documented alternatives, to test
   what learned pairwise models do when the ground truth is not a pairwise sum; they
   are not calibrated replacements.

Select a law with `make_aggregation(spec)`, the spec as for fields
(`sim.fields.registry`): NAME or NAME:KEY=VALUE[,...], e.g. "velocity:exponent=1.5",
"shielding:eta=0.8,radius=0.3". `wake_field(field, pos, vel, rot, law)` is what the
simulator calls each tick: the linear law is `pairwise_field`; the others take every
ordered pair's force (`sim.field.pairwise_forces`, compiled for `DownwashField`) and
combine it, compiled on the (W, V, 3) hot path, with a readable NumPy twin
(`combine_reference`) that the tests compare against.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from downwash_core import libm
from downwash_core.errors import ConfigError
from downwash_core.geometry import dot as _dot
from downwash_core.jit import njit
from downwash_core.registry import Registry
from downwash_core.validate import number
from sim.field import pairwise_field, pairwise_forces

__all__ = [
    "LinearSuperposition",
    "VelocitySuperposition",
    "WakeShielding",
    "AGGREGATIONS",
    "DEFAULT_AGGREGATION",
    "make_aggregation",
    "parse_aggregation_spec",
    "wake_field",
]



def _describe(law: Any) -> dict[str, Any]:
    """Stable provenance: type, registry name and every parameter (plain floats)."""
    return {"type": f"{type(law).__module__}.{type(law).__qualname__}", "name": law.name,
            **{k: float(v) for k, v in asdict(law).items()}}


def _compiled_shapes(forces: Any, pos: Any = None, rot: Any = None) -> bool:
    """True for the hot path's float64 forces (W, V, V, 3), pos (W, V, 3), rot (W, V, 3, 3) (or None)."""
    if type(forces) is not np.ndarray or forces.ndim != 4 or forces.dtype != np.float64:
        return False
    W, V = forces.shape[0], forces.shape[1]
    if forces.shape != (W, V, V, 3):
        return False
    if pos is None:
        return True
    return (type(pos) is np.ndarray and pos.dtype == np.float64 and pos.shape == (W, V, 3)
            and type(rot) is np.ndarray and rot.dtype == np.float64 and rot.shape == (W, V, 3, 3))


# ----------------------------------------------------------------------------- the laws


@dataclass(frozen=True)
class LinearSuperposition:
    """Linear superposition: the force on a vehicle is the sum of every other vehicle's pairwise force.

    F_j = sum_{i != j} f_ij (m/s^2, world frame). `wake_field` evaluates it as
    `sim.field.pairwise_field`, bit for bit; `combine` is the same sum over given
    pair forces. See the module docstring for why it is the default.
    """

    name = "linear"

    def describe(self) -> dict[str, Any]:
        """Stable provenance: type and name (no parameters)."""
        return _describe(self)

    def combine(self, forces: np.ndarray, pos: Any = None, rot: Any = None) -> np.ndarray:
        """(..., V, 3) m/s^2: the sum over leaders of forces (..., V_leader, V_follower, 3)."""
        return np.asarray(forces, dtype=np.float64).sum(axis=-3)

    combine_reference = combine


@dataclass(frozen=True)
class VelocitySuperposition:
    """Induced velocities add before the follower's (power-law) response to them.

    Physical argument. Read each pair force f_i = f_ij (m/s^2) as the follower's
    response to an induced air velocity u_i (m/s), through f = c |u|^(p-1) u with a
    gain c > 0 (p = 2: quadratic drag or momentum flux; for `MomentumWake`'s airframe
    drag c = rho C_d A_ref / (2 m) = 0.0088 1/m). Inverting, u_i = c^(-1/p) |f_i|^(1/p-1) f_i
    (u_i = 0 for f_i = 0). The wakes' velocities superpose at the follower, U = sum_i u_i
    (the linear superposition of wake velocity deficits of wind-farm models: Lissaman,
    J. Energy 3(6), 1979; Katic, Hojstrup & Jensen, EWEC 1986, sum their squares), and
    the force is the response to the total, F = c |U|^(p-1) U. Substituting,

        F = |G|^(p-1) G,   G = sum_i |f_i|^(1/p-1) f_i        (the gain c cancels),

    so the law needs no value of c. The exponent p is the follower's response: p = 2
    quadratic drag (the default: the clearest departure from linear); p = 1 a response
    linear in the inflow (a rotor in a small inflow), the linear law up to rounding;
    p ~ 0.8 a rotor whose thrust saturates in a strong inflow (fitted to
    `rotor_thrust_ratio` over c = 0.9-1.9), sub-additive: F shorter than the sum.

    Reduction to the pairwise force for two vehicles (one leader, f != 0):
    G = |f|^(1/p-1) f, so |G| = |f|^(1/p) and |G|^(p-1) = |f|^(1-1/p), hence
    F = |f|^(1-1/p) |f|^(1/p-1) f = f. (f = 0 gives G = 0 and F = 0.) Exactly, for every
    p; in floating point to a few ulp.

    Worked case: two leaders with equal, parallel forces f on one follower give
    G = 2 |f|^(1/p-1) f and F = 2^p f (p = 2: 4 f, where the linear law gives 2 f);
    equal perpendicular forces f1, f2 give F = 2^((p-1)/2) (f1 + f2), |F| = 2^(p/2) |f|.

    Properties: invariant to the order of the leaders (a sum), rotation-equivariant
    (rotating every f_i rotates F), positively homogeneous of degree 1 (scaling every
    f_i by lambda > 0 scales F by lambda), continuous (|f|^(1/p-1) f -> 0 as f -> 0,
    |G|^(p-1) G -> 0 as G -> 0; F = 0 where G = 0, also for p < 1).

    Assumptions: the wakes' velocities add at the follower (they do not interact with
    each other or with vehicles in between; see `WakeShielding`); each pair force is
    aligned with its wake's velocity (true for drag; for the rotor term, along the
    follower's axis, only roughly), so f_i's direction stands in for u_i's.

    exponent: p (-), in [0.5, 3].
    """

    exponent: float = 2.0  # -, p of the response f = c |u|^(p-1) u: 2 drag, 1 linear, ~0.8 saturating rotor

    name = "velocity"

    def __post_init__(self) -> None:
        object.__setattr__(self, "exponent", number("exponent", self.exponent, "-", 0.5, 3.0))

    def describe(self) -> dict[str, Any]:
        """Stable provenance: type, name and exponent."""
        return _describe(self)

    def combine(self, forces: np.ndarray, pos: Any = None, rot: Any = None) -> np.ndarray:
        """(..., V, 3) m/s^2 from pair forces (..., V_leader, V_follower, 3) m/s^2 (diagonal 0).

        Compiled for float64 (W, V, V, 3); otherwise `combine_reference`. pos and rot unused.
        """
        if _compiled_shapes(forces):
            return _velocity_kernel(forces, self.exponent)
        return self.combine_reference(forces)

    def combine_reference(self, forces: np.ndarray, pos: Any = None, rot: Any = None) -> np.ndarray:
        """Readable twin of `combine`: the formula of the class docstring in NumPy."""
        f = np.asarray(forces, dtype=np.float64)
        p = self.exponent
        m = _norm(f)  # (..., V, V) |f_i|
        nonzero = m > 0.0
        safe = np.where(nonzero, m, 1.0)
        scale = np.where(nonzero, libm.power(safe, 1.0 / p) / safe, 0.0)  # |f|^(1/p-1), 0 for f = 0
        G = (scale[..., None] * f).sum(axis=-3)  # (..., V, 3), the velocity sum (times c^(1/p))
        M = _norm(G)
        big = np.where(M > 0.0, libm.power(np.where(M > 0.0, M, 1.0), p - 1.0), 0.0)  # 0^(p-1) is inf for p < 1
        return big[..., None] * G


@dataclass(frozen=True)
class WakeShielding:
    """A vehicle inside a leader's wake, between it and a follower, shields the follower.

    F_j = sum_{i != j} f_ij prod_{k != i, j} (1 - eta g_k(i, j)), with g in [0, 1]:

        n_i    leader i's axis (R_i[:, 2]);  s_k = -(p_k - p_i) . n_i  depth of k below i (m)
        r_k    = |(p_k - p_i) + s_k n_i|      k's lateral offset from i's axis (m)
        L(r)   = (1 - r^2 / radius^2)^2 for r < radius, else 0
        D      = S(s_k / ramp) S((s_j - s_k) / ramp),  S(x) = t^2 (3 - 2 t), t = clip(x, 0, 1)
        g_k    = L(r_k) D                     1 for k on i's axis well between i and j

    The weights are C1 in the positions (no jump when a vehicle enters or leaves the
    shadow), depend on geometry only, and vanish for k = i (s_k = 0) and k = j
    (s_j - s_k = 0), so even the readable twin needs no index mask. The product and
    the sum are over unordered sets: the law is invariant to the order of vehicles.
    With two vehicles there is no k: the empty product is 1 and F_j = f_ij exactly
    (bit for bit), for any field.

    Physical argument (momentum theory, Leishman, Principles of Helicopter Aerodynamics,
    2006, ch. 2, the rotor in axial climb). Vehicle k, holding its thrust T with disk
    area A, sits in i's wake, which arrives at speed V. Then T = 2 rho A (V + v_i) v_i and
    k's far slipstream moves at V + 2 v_i = sqrt(V^2 + (2 v_h)^2), v_h = sqrt(T / (2 rho A)):
    the incoming wake and k's own slipstream add in quadrature, not linearly. Of i's
    wake the speed sqrt(V^2 + 4 v_h^2) - 2 v_h survives below k: a fraction eta_mt = 1 -
    (sqrt(V^2 + 4 v_h^2) - 2 v_h) / V is removed, 1 for V << 2 v_h and 0.59 for V = 2 v_h
    (identical vehicles, one wake fully developed). Only the part of i's wake that
    passes k's rotors is affected and the jets mix below k, so the effective fraction
    is lower; the default eta = 0.5 is a deliberately moderate value, not a
    measurement. The momentum taken out is not lost: it is i's force on k, f_ik, in k's
    own sum. This is one mechanism of the non-linear aggregation that arXiv:2312.03488
    measured in stacks; it is not fitted to their data.

    Assumptions: the wake from i to j is i's straight axis (not the curved streamtube
    of a tilted or moving leader); k's attitude is ignored (its disk taken normal to
    the wake); several shields multiply (each passes 1 - eta g_k); quasi-steady.

    eta (-, [0, 1]): the fraction of the wake removed by a shield on the axis.
    radius (m): lateral reach of a shield from i's axis; 0.25 m ~ the shield's rotor tips
        (arm + rotor radius = 0.13 m, downwash_core.params.QUAD) plus the wake's half-width near
        the vehicles (~0.1-0.2 m: DownwashField's sigma = 0.10 + 0.12 s); L(0.13 m) = 0.53.
    ramp (m): depth over which a shield fades in below i and out above j (~ a rotor
        diameter plus the vehicle's height), so that g is continuous.
    """

    eta: float = 0.5  # -, fraction of i's wake a shield on the axis removes
    radius: float = 0.25  # m, lateral reach of a shield from i's axis
    ramp: float = 0.1  # m, depth over which a shield fades in below i and out above j

    name = "shielding"

    def __post_init__(self) -> None:
        object.__setattr__(self, "eta", number("eta", self.eta, "-", 0.0, 1.0))
        object.__setattr__(self, "radius", number("radius", self.radius, "m", 0.0, 10.0, lo_open=True))
        object.__setattr__(self, "ramp", number("ramp", self.ramp, "m", 0.0, 10.0, lo_open=True))

    def describe(self) -> dict[str, Any]:
        """Stable provenance: type, name, eta, radius and ramp."""
        return _describe(self)

    def combine(self, forces: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(..., V, 3) m/s^2 from pair forces (..., V_leader, V_follower, 3) m/s^2 (diagonal 0).

        pos (..., V, 3) m and rot (..., V, 3, 3) body-to-world, world frame. Compiled for
        float64 (W, V, ...) arrays; otherwise `combine_reference`.
        """
        if _compiled_shapes(forces, pos, rot):
            return _shielding_kernel(forces, pos, rot, self.eta, self.radius, self.ramp)
        return self.combine_reference(forces, pos, rot)

    def shielding_factors(self, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(..., V_leader, V_follower) -: prod_k (1 - eta g_k(i, j)), readable (1 on the diagonal).

        pos (..., V, 3) m, rot (..., V, 3, 3), world frame.
        """
        pos = np.asarray(pos, dtype=np.float64)
        rot = np.asarray(rot, dtype=np.float64)
        n = rot[..., :, 2]  # (..., V, 3), leader i's axis
        d = pos[..., None, :, :] - pos[..., :, None, :]  # [..., i, k, :] = p_k - p_i
        s = -_dot(d, n[..., :, None, :])  # [..., i, k] depth of k below i
        lateral = d + s[..., None] * n[..., :, None, :]
        reach = np.maximum(1.0 - _dot(lateral, lateral) / (self.radius * self.radius), 0.0)
        L = reach * reach  # [..., i, k]
        below_i = _smoothstep(s / self.ramp)  # [..., i, k]
        above_j = _smoothstep((s[..., :, :, None] - s[..., :, None, :]) / self.ramp)  # [..., i, j, k]
        g = (L * below_i)[..., :, None, :] * above_j  # [..., i, j, k]
        return np.prod(1.0 - self.eta * g, axis=-1)

    def combine_reference(self, forces: np.ndarray, pos: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """Readable twin of `combine`: the formula of the class docstring in NumPy."""
        f = np.asarray(forces, dtype=np.float64)
        return (self.shielding_factors(pos, rot)[..., None] * f).sum(axis=-3)


def _norm(v: np.ndarray) -> np.ndarray:
    """(...) |v| of (..., 3) vectors, scaled by the largest component so that no square underflows."""
    a = np.max(np.abs(v), axis=-1)
    u = v / np.where(a > 0.0, a, 1.0)[..., None]
    return a * np.sqrt(_dot(u, u))


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """t^2 (3 - 2 t), t = clip(x, 0, 1): 0 for x <= 0, 1 for x >= 1, C1."""
    t = np.clip(x, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


DEFAULT_AGGREGATION = "linear"
# name -> the law's class; specs in the registries' grammar (`downwash_core.registry`)
AGGREGATIONS = Registry("aggregation", objects=True, default=DEFAULT_AGGREGATION, name_pattern=r"[a-z][a-z0-9_]*",
                        name_rule="lowercase letters, digits and underscores")
AGGREGATIONS.register("linear", LinearSuperposition, "the sum of the pairwise forces (the paper's assumption)")
AGGREGATIONS.register("velocity", VelocitySuperposition, "the wakes' velocities superpose; the force goes as |v|^p")
AGGREGATIONS.register("shielding", WakeShielding, "a vehicle in a wake's way shields those below it")


# ----------------------------------------------------------------------------- selecting a law


def parse_aggregation_spec(spec: str, label: str = "aggregation") -> tuple[str, dict[str, Any]]:
    """(NAME, {typed params}) from "NAME" or "NAME:KEY=VALUE[,...]" ("" is the default): `AGGREGATIONS.parse`,
    the grammar of every registry. ConfigError (prefixed with `label`) naming the allowed names or parameters."""
    return AGGREGATIONS.parse(spec, label)


def make_aggregation(name: str) -> Any:
    """The aggregation law a spec names: "linear", "velocity:exponent=1.5", "shielding:eta=0.8", ...

    "" is the default (`DEFAULT_AGGREGATION`). ConfigError naming the allowed names,
    parameters or range, before any work.
    """
    return AGGREGATIONS.resolve(name)


# ----------------------------------------------------------------------------- the simulator's call


def wake_field(field: Any, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, law: Any = None) -> np.ndarray:
    """The wake force (..., V, 3) m/s^2 on every vehicle from all the others, combined by `law`.

    pos, vel (..., V, 3) m, m/s and rot (..., V, 3, 3) as in `pairwise_field`; law None or
    `LinearSuperposition()` is exactly `pairwise_field(field, pos, vel, rot)`. Any other
    law gets every ordered pair's force (`pairwise_forces`: the field's compiled
    `pair_forces` for (W, V, 3) inputs when it has one, else the broadcast evaluation,
    diagonal excluded) and combines it with `law.combine(forces, pos, rot)`.
    """
    if law is None or isinstance(law, LinearSuperposition):
        return pairwise_field(field, pos, vel, rot)
    combine = getattr(law, "combine", None)
    if not callable(combine) or isinstance(law, (str, type)):
        raise ConfigError(f"aggregation: expected a law object from make_aggregation(spec) "
                          f"({', '.join(AGGREGATIONS)}), got {law!r}")
    forces = pairwise_forces(field, pos, vel, rot)
    return combine(forces, pos, rot)


# ----------------------------------------------------------------------------- compiled twins


@njit
def _velocity_kernel(forces, p):
    """Compiled `VelocitySuperposition.combine_reference` for (W, V, V, 3) forces, exponent p."""
    W, V = forces.shape[0], forces.shape[1]
    out = np.zeros((W, V, 3))
    inv_p = 1.0 / p
    for w in range(W):
        for j in range(V):  # follower
            gx = gy = gz = 0.0
            for i in range(V):  # leader; the diagonal is 0 and adds nothing
                fx, fy, fz = forces[w, i, j, 0], forces[w, i, j, 1], forces[w, i, j, 2]
                m = _norm_scalar(fx, fy, fz)
                if m > 0.0:
                    scale = m**inv_p / m
                    gx += scale * fx
                    gy += scale * fy
                    gz += scale * fz
            big_m = _norm_scalar(gx, gy, gz)
            big = big_m ** (p - 1.0) if big_m > 0.0 else 0.0  # 0^(p-1) is inf for p < 1
            out[w, j, 0] = big * gx
            out[w, j, 1] = big * gy
            out[w, j, 2] = big * gz
    return out


@njit
def _norm_scalar(x, y, z):
    """|(x, y, z)| as `_norm`: scaled by the largest component (no underflow of the squares)."""
    a = max(abs(x), abs(y), abs(z))
    if a == 0.0:
        return 0.0
    x, y, z = x / a, y / a, z / a
    return a * np.sqrt(x * x + y * y + z * z)


@njit
def _smoothstep_scalar(x):
    t = min(max(x, 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


@njit
def _shielding_kernel(forces, pos, rot, eta, radius, ramp):
    """Compiled `WakeShielding.combine_reference` for (W, V, ...) arrays."""
    W, V = forces.shape[0], forces.shape[1]
    out = np.zeros((W, V, 3))
    r2_max = radius * radius
    for w in range(W):
        for i in range(V):  # leader
            nx, ny, nz = rot[w, i, 0, 2], rot[w, i, 1, 2], rot[w, i, 2, 2]
            for j in range(V):  # follower
                fx, fy, fz = forces[w, i, j, 0], forces[w, i, j, 1], forces[w, i, j, 2]
                if j == i or (fx == 0.0 and fy == 0.0 and fz == 0.0):
                    continue
                s_j = -((pos[w, j, 0] - pos[w, i, 0]) * nx + (pos[w, j, 1] - pos[w, i, 1]) * ny
                        + (pos[w, j, 2] - pos[w, i, 2]) * nz)
                factor = 1.0
                for k in range(V):  # shields; g = 0 exactly for k = i, j (skipped: a factor 1)
                    if k == i or k == j:
                        continue
                    dx, dy, dz = pos[w, k, 0] - pos[w, i, 0], pos[w, k, 1] - pos[w, i, 1], pos[w, k, 2] - pos[w, i, 2]
                    s_k = -(dx * nx + dy * ny + dz * nz)
                    if s_k <= 0.0 or s_k >= s_j:
                        continue  # not between i and j: g = 0
                    lx, ly, lz = dx + s_k * nx, dy + s_k * ny, dz + s_k * nz
                    reach = max(1.0 - (lx * lx + ly * ly + lz * lz) / r2_max, 0.0)
                    g = reach * reach * _smoothstep_scalar(s_k / ramp) * _smoothstep_scalar((s_j - s_k) / ramp)
                    factor *= 1.0 - eta * g
                out[w, j, 0] += factor * fx
                out[w, j, 1] += factor * fy
                out[w, j, 2] += factor * fz
    return out
