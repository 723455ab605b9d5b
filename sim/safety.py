"""A safety layer on the commanded accelerations: a control barrier function (CBF) filter.

In a tight vertical stack a vehicle that sags under an under-predicted wake can fall onto the one below. The
filter takes the controller's commanded accelerations u_nom (W, V, 3) m/s^2 of every vehicle of every world
and returns the nearest commands (least squares) that keep, with the double-integrator model p'' = u + f_hat
(the controller's own: f_hat is the held prediction) and the estimated states the controller uses,

- every stacked pair's vertical gap (horizontal distance under `stack_radius`):
  h = s (z_i - z_j) - vertical_gap, s = +1 when i is the upper one;
- every pair's distance: h = |p_i - p_j| - min_distance;
- every vehicle's height: h = z_i - ground_clearance.

Each barrier is of second order (exponential, HOCBF), since a position has relative degree 2:
h'' + k1 h' + k0 h >= 0, linear in the commands. k1 >= 2 sqrt(k0) (real poles -l1, -l2 of
s^2 + k1 s + k0): from a state with h >= 0 and h' + l1 h >= 0 (l1 the smaller root) the barrier
keeps h >= 0, and one control period of constant acceleration keeps it too (tests/test_safety.py).
Pairwise constraints couple the vehicles of a world, so each world is one QP:

    min |u - u_nom|^2  s.t.  A u >= b  (the barriers)  and  lower <= u <= upper  (`actuator_box`)

solved exactly by Goldfarb and Idnani's dual active-set method (1983) for a unit Hessian: it starts at u_nom
and adds the most violated constraint at a time, so a command that violates no barrier (by more than
`TOLERANCE`) comes out unchanged bit for bit. The box is the commands feedback linearisation realises
(`controllers.lqr`: the tilt limit, the floor MIN_THRUST_G, a `thrust_fraction` of each vehicle's full
thrust), widened to include u_nom itself: the filter never clips a command it leaves alone, nor moves one out
of the box. Where the box makes the barriers infeasible together, a barrier that cannot be met with those
already held is left unmet (counted; the vehicles do what their thrust allows).

Two paths, one algorithm: `SafetyFilter.reference` in NumPy (`np.linalg.solve` on the active normals) and
`cbf_filter_kernel`, compiled (a small Cholesky, no BLAS: the same bits on every CPU), tested equal.
`Simulator(..., safety=SafetyConfig())` runs the compiled one on both of its paths (`SafetyFilter.apply`; the
fused tick through `safety_function`, a C function).
"""

from __future__ import annotations

import functools
import math
import numbers
from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numba
import numpy as np
from numba import carray
from numba import types as nbt

from controllers.lqr import MAX_TILT_DEG, MIN_THRUST_G, FeedbackLinearisedLQR, attitude_setpoint
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.params import GRAVITY
from downwash_core.validate import number

__all__ = ["SafetyConfig", "SafetyFilter", "safety_filter", "actuator_box", "constraint_rows", "solve_qp",
           "cbf_filter_kernel", "SAFETY_SIGNATURE", "safety_function", "TOLERANCE", "DEPENDENT", "N_PARAMS"]

TOLERANCE = 1e-9  # m/s^2: a barrier counts as violated (active) only by more than this
DEPENDENT = 1e-10  # a normal whose squared part outside the active normals' span is below this share is dependent
_MIN_RANGE = 1e-9  # m: two vehicles closer than this have no direction, so no distance barrier
_MAX_STEPS = 10  # the solver's steps per world, per row and command: far beyond a QP's need (rounding cannot loop it)
N_PARAMS = 8  # the packed settings (`SafetyConfig.packed`): the six numbers, then TOLERANCE and DEPENDENT

# name, unit, lowest, highest, lowest excluded
_RANGES = (("vertical_gap", "m", 0.0, 10.0, True), ("stack_radius", "m", 0.0, 10.0, True),
           ("min_distance", "m", 0.0, 10.0, True), ("ground_clearance", "m", 0.0, 100.0, False),
           ("k0", "1/s^2", 0.0, 1e4, True), ("k1", "1/s", 0.0, 1e3, True), ("thrust_fraction", "-", 0.0, 1.0, True))


@dataclass(frozen=True)
class SafetyConfig:
    """The CBF filter's settings (module docstring). The defaults: a stack's gap no closer than the
    experiments' closest (downwash_core.params.SEPARATION_RANGE, 0.3 m), pairs no closer than two paper
    quads' collision radius (0.26 m) and a bit, a double pole at 2 rad/s (the approach's time constant 0.5 s)."""

    vertical_gap: float = 0.3  # m, the least vertical separation of a stacked pair
    stack_radius: float = 0.3  # m, a pair closer than this horizontally is stacked
    min_distance: float = 0.27  # m, the least distance of any pair
    ground_clearance: float = 0.1  # m, the least height of a vehicle's centre
    k0: float = 4.0  # 1/s^2, the barrier's gain on h
    k1: float = 4.0  # 1/s, its gain on h' (>= 2 sqrt(k0): real poles)
    thrust_fraction: float = 0.9  # -, of a vehicle's full thrust the filter may command (the rest: the attitude's)

    def __post_init__(self) -> None:
        for name, unit, lo, hi, lo_open in _RANGES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ConfigError(f"SafetyConfig.{name}: got {value!r}; allowed a number in {'(' if lo_open else '['}"
                                  f"{lo}, {hi}] {unit}")
            object.__setattr__(self, name, number(f"SafetyConfig.{name}", value, unit, lo, hi, lo_open=lo_open))
        if self.k1 * self.k1 < 4.0 * self.k0:
            raise ConfigError(f"SafetyConfig.k1: got {self.k1} with k0 = {self.k0}; allowed k1 >= 2 sqrt(k0) = "
                              f"{2.0 * math.sqrt(self.k0):.6g} 1/s (real poles: the barrier does not overshoot)")

    @property
    def poles(self) -> tuple[float, float]:
        """(l1, l2) 1/s, l1 <= l2: s^2 + k1 s + k0 = (s + l1)(s + l2)."""
        root = math.sqrt(max(self.k1 * self.k1 - 4.0 * self.k0, 0.0))
        return (self.k1 - root) / 2.0, (self.k1 + root) / 2.0

    def packed(self) -> np.ndarray:
        """(N_PARAMS,) float64, as the compiled filter reads them."""
        return np.array([self.vertical_gap, self.stack_radius, self.min_distance, self.ground_clearance, self.k0,
                         self.k1, TOLERANCE, DEPENDENT], dtype=np.float64)

    def describe(self) -> dict[str, Any]:
        """Class, settings and method (JSON-serialisable), for logs and provenance."""
        return {"type": type(self).__name__, **asdict(self), "barrier": "h'' + k1 h' + k0 h >= 0",
                "solver": "dual active set (Goldfarb-Idnani), least squares on the commands", "tolerance": TOLERANCE}


def actuator_box(config: SafetyConfig, quads: Sequence[Any], max_tilt: float = math.radians(MAX_TILT_DEG),
                 min_vertical: float = MIN_THRUST_G * GRAVITY) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) lower and upper bounds (m/s^2, gravity excluded) of the commands the filter may give each
    vehicle: what feedback linearisation (`controllers.lqr.attitude_setpoint`, with these limits) realises.

    Vertical: from min_vertical - g (its floor, MIN_THRUST_G) to sqrt((c T/W g)^2 - a_lat^2) - g, where
    c = `thrust_fraction` and T/W the vehicle's thrust-to-weight (`quads[i].thrust_to_weight`).
    Lateral, each axis: |a| <= tan(max_tilt) min_vertical / sqrt(2), so that the lateral command stays in
    the tilt cone for every admissible vertical one, and the thrust within c T/W g.
    ConfigError when the box leaves a vehicle unable to hover (c too small for its T/W)."""
    lateral = math.tan(max_tilt) * min_vertical  # m/s^2, the lateral force the cone allows at the floor
    lower, upper = np.full((len(quads), 3), -lateral / math.sqrt(2.0)), np.full((len(quads), 3), lateral / math.sqrt(2.0))
    for i, q in enumerate(quads):
        most = config.thrust_fraction * q.thrust_to_weight * GRAVITY  # m/s^2, the specific thrust allowed
        if most * most - lateral * lateral <= GRAVITY * GRAVITY:
            need = math.sqrt(GRAVITY * GRAVITY + lateral * lateral) / (q.thrust_to_weight * GRAVITY)
            raise ConfigError(f"SafetyConfig.thrust_fraction: got {config.thrust_fraction}; vehicle {i} (thrust-to-"
                              f"weight {q.thrust_to_weight:.4g}) cannot hover within it: allowed ({need:.4g}, 1]")
        lower[i, 2], upper[i, 2] = min_vertical - GRAVITY, math.sqrt(most * most - lateral * lateral) - GRAVITY
    return lower, upper


# ----------------------------------------------------------------------------- the readable path


def constraint_rows(config: SafetyConfig, lower: np.ndarray, upper: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                    f_hat: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every world's constraints A[w] x >= b[w] on its commands x = u[w].reshape(3 V): A (W, m, 3 V), b (W, m),
    m = 2 P + 7 V for the P = V (V - 1) / 2 pairs. Rows: for each pair i < j in turn, its vertical row (a stacked
    pair's) and its distance row; each vehicle's ground row; each command's lower and upper bound (the box
    widened to include u). A row that does not apply (a pair not stacked) is zero with b = -inf."""
    W, V = pos.shape[:2]
    I, J = np.triu_indices(V, 1)
    P, n = len(I), 3 * V
    k0, k1 = config.k0, config.k1
    A, b = np.zeros((W, 2 * P + 7 * V, n)), np.full((W, 2 * P + 7 * V), -np.inf)
    dp, dv, df = pos[:, I] - pos[:, J], vel[:, I] - vel[:, J], f_hat[:, I] - f_hat[:, J]  # (W, P, 3), i minus j
    vertical, distance = 2 * np.arange(P), 2 * np.arange(P) + 1
    # vertical: h = s dz - gap, with s = +1 when i is above j
    stacked = np.sqrt(dp[..., 0] * dp[..., 0] + dp[..., 1] * dp[..., 1]) < config.stack_radius
    s = np.where(dp[..., 2] >= 0.0, 1.0, -1.0)
    A[:, vertical, 3 * I + 2], A[:, vertical, 3 * J + 2] = np.where(stacked, s, 0.0), np.where(stacked, -s, 0.0)
    h, hd = s * dp[..., 2] - config.vertical_gap, s * dv[..., 2]
    b[:, vertical] = np.where(stacked, -k1 * hd - k0 * h - s * df[..., 2], -np.inf)
    # distance: h = r - d, h' = n.dv, h'' = n.da + (|dv|^2 - (n.dv)^2) / r
    r = np.sqrt(dp[..., 0] * dp[..., 0] + dp[..., 1] * dp[..., 1] + dp[..., 2] * dp[..., 2])
    apart = r > _MIN_RANGE
    normal = dp / np.where(apart, r, 1.0)[..., None]
    hd = (normal * dv).sum(axis=-1)
    bend = ((dv * dv).sum(axis=-1) - hd * hd) / np.where(apart, r, 1.0)
    for k in range(3):
        A[:, distance, 3 * I + k] = np.where(apart, normal[..., k], 0.0)
        A[:, distance, 3 * J + k] = np.where(apart, -normal[..., k], 0.0)
    b[:, distance] = np.where(apart, -k1 * hd - k0 * (r - config.min_distance) - (normal * df).sum(axis=-1) - bend,
                              -np.inf)
    # ground: h = z - clearance
    ground = 2 * P + np.arange(V)
    A[:, ground, 3 * np.arange(V) + 2] = 1.0
    b[:, ground] = -f_hat[..., 2] - k1 * vel[..., 2] - k0 * (pos[..., 2] - config.ground_clearance)
    # the box, widened to include the nominal command
    x, bound = u.reshape(W, n), 2 * P + V + 2 * np.arange(n)
    A[:, bound, np.arange(n)], A[:, bound + 1, np.arange(n)] = 1.0, -1.0
    b[:, bound] = np.minimum(lower.reshape(n), x)
    b[:, bound + 1] = -np.maximum(upper.reshape(n), x)
    return A, b


def solve_qp(A: np.ndarray, b: np.ndarray, u: np.ndarray, max_steps: int) -> tuple[np.ndarray, int]:
    """min |x - u|^2 s.t. A x >= b, one world (A (m, n), b (m,), u (n,)), by the dual active-set method of
    Goldfarb and Idnani (1983) with a unit Hessian: from x = u, add the most violated constraint p, moving
    x along z (a_p's part outside the active normals' span) and the active multipliers by -t r
    (a_p = N r + z); a multiplier reaching zero first drops its constraint (a partial step). Returns x and
    how many constraints were left unmet (one that cannot be met with those active: z = 0, no multiplier
    can fall). The readable form of `cbf_filter_kernel`'s solver (the same steps, in the same order)."""
    x = u.astype(np.float64, copy=True)
    active: list[int] = []
    lam = np.zeros(0)
    unmet = np.zeros(len(b), bool)
    steps = 0
    while steps < max_steps:
        slack = A @ x - b
        slack[active] = np.inf
        slack[unmet] = np.inf
        p = int(np.argmin(slack))  # (the first of equals, as the kernel)
        if not slack[p] < -TOLERANCE:
            break
        a, lam_p = A[p], 0.0
        while steps < max_steps:
            steps += 1
            N = A[active].T  # (n, q), the active normals
            try:
                r = np.linalg.solve(N.T @ N, N.T @ a) if active else np.zeros(0)
            except np.linalg.LinAlgError:
                unmet[p] = True
                break
            z = a - N @ r
            ratios = np.where(r > 0.0, lam / np.where(r > 0.0, r, 1.0), np.inf)
            drop = int(np.argmin(ratios)) if active else -1
            t1 = ratios[drop] if active else np.inf  # the step at which an active multiplier reaches zero
            zz = z @ z
            t2 = (b[p] - a @ x) / zz if zz > DEPENDENT * (a @ a) else np.inf  # the step that meets p
            t = min(t1, t2)
            if t == np.inf:  # p is infeasible with the active constraints
                unmet[p] = True
                break
            if t2 < np.inf:
                x = x + t * z
            lam, lam_p = lam - t * r, lam_p + t
            if t2 <= t1:
                active.append(p)
                lam = np.append(lam, lam_p)
                break
            del active[drop]
            lam = np.delete(lam, drop)
    return x, int(unmet.sum())


# ----------------------------------------------------------------------------- the compiled path


@njit
def _dot(a, b, n):
    out = 0.0
    for c in range(n):
        out += a[c] * b[c]
    return out


@njit
def _world_rows(params, lower, upper, p, v, f, x, A, b):
    """One world's rows of `constraint_rows` into A (m, n), b (m,), in the same order; x (n,) its nominal commands."""
    V = p.shape[0]
    gap, radius, dmin, zmin, k0, k1 = params[0], params[1], params[2], params[3], params[4], params[5]
    A[:, :] = 0.0
    row = 0
    for i in range(V):
        for j in range(i + 1, V):
            dx, dy, dz = p[i, 0] - p[j, 0], p[i, 1] - p[j, 1], p[i, 2] - p[j, 2]
            if np.sqrt(dx * dx + dy * dy) < radius:  # stacked: the vertical gap
                s = 1.0 if dz >= 0.0 else -1.0
                A[row, 3 * i + 2], A[row, 3 * j + 2] = s, -s
                h, hd = s * dz - gap, s * (v[i, 2] - v[j, 2])
                b[row] = -k1 * hd - k0 * h - s * (f[i, 2] - f[j, 2])
            else:
                b[row] = -np.inf
            r = np.sqrt(dx * dx + dy * dy + dz * dz)
            if r > _MIN_RANGE:  # the distance
                nx, ny, nz = dx / r, dy / r, dz / r
                vx, vy, vz = v[i, 0] - v[j, 0], v[i, 1] - v[j, 1], v[i, 2] - v[j, 2]
                hd = nx * vx + ny * vy + nz * vz
                bend = (vx * vx + vy * vy + vz * vz - hd * hd) / r
                A[row + 1, 3 * i], A[row + 1, 3 * i + 1], A[row + 1, 3 * i + 2] = nx, ny, nz
                A[row + 1, 3 * j], A[row + 1, 3 * j + 1], A[row + 1, 3 * j + 2] = -nx, -ny, -nz
                b[row + 1] = (-k1 * hd - k0 * (r - dmin) - (nx * (f[i, 0] - f[j, 0]) + ny * (f[i, 1] - f[j, 1])
                                                            + nz * (f[i, 2] - f[j, 2])) - bend)
            else:
                b[row + 1] = -np.inf
            row += 2
    for i in range(V):  # the ground
        A[row, 3 * i + 2] = 1.0
        b[row] = -f[i, 2] - k1 * v[i, 2] - k0 * (p[i, 2] - zmin)
        row += 1
    for q in range(3 * V):  # the box, widened to include the nominal command
        A[row, q], A[row + 1, q] = 1.0, -1.0
        b[row], b[row + 1] = min(lower[q // 3, q % 3], x[q]), -max(upper[q // 3, q % 3], x[q])
        row += 2


@njit
def _project(A, active, q, p, n, G, L, r, z):
    """r = (N^T N)^-1 N^T a_p and z = a_p - N r for the q active normals N (Cholesky of N^T N); False when
    N^T N is not numerically positive definite."""
    for k in range(q):
        r[k] = _dot(A[active[k]], A[p], n)
        for l in range(k + 1):
            G[k, l] = _dot(A[active[k]], A[active[l]], n)
    for k in range(q):  # L L^T = G, lower triangular
        d = G[k, k]
        for l in range(k):
            d -= L[k, l] * L[k, l]
        if not d > 0.0:
            return False
        L[k, k] = np.sqrt(d)
        for i in range(k + 1, q):
            e = G[i, k]
            for l in range(k):
                e -= L[i, l] * L[k, l]
            L[i, k] = e / L[k, k]
    for k in range(q):  # L y = N^T a_p, then L^T r = y (r holds y, then r)
        e = r[k]
        for l in range(k):
            e -= L[k, l] * r[l]
        r[k] = e / L[k, k]
    for k in range(q - 1, -1, -1):
        e = r[k]
        for l in range(k + 1, q):
            e -= L[l, k] * r[l]
        r[k] = e / L[k, k]
    for c in range(n):
        e = A[p, c]
        for k in range(q):
            e -= r[k] * A[active[k], c]
        z[c] = e
    return True


@njit
def _solve_world(A, b, m, n, x, tol, dependent, max_steps, active, lam, r, z, G, L, is_active, unmet):
    """`solve_qp` on one world's rows, compiled (scratch arrays given); x in place; returns the unmet count."""
    for j in range(m):
        is_active[j] = False
        unmet[j] = False
    q, steps, n_unmet = 0, 0, 0
    while steps < max_steps:
        p, worst = -1, -tol
        for j in range(m):
            if not (is_active[j] or unmet[j]):
                s = _dot(A[j], x, n) - b[j]
                if s < worst:
                    p, worst = j, s
        if p < 0:
            break
        lam_p = 0.0
        while steps < max_steps:
            steps += 1
            if not _project(A, active, q, p, n, G, L, r, z):
                unmet[p] = True
                n_unmet += 1
                break
            t1, drop = np.inf, -1
            for k in range(q):
                if r[k] > 0.0 and lam[k] / r[k] < t1:
                    t1, drop = lam[k] / r[k], k
            zz = _dot(z, z, n)
            t2 = (b[p] - _dot(A[p], x, n)) / zz if zz > dependent * _dot(A[p], A[p], n) else np.inf
            t = min(t1, t2)
            if t == np.inf:
                unmet[p] = True
                n_unmet += 1
                break
            if t2 < np.inf:
                for c in range(n):
                    x[c] = x[c] + t * z[c]
            for k in range(q):
                lam[k] = lam[k] - t * r[k]
            lam_p += t
            if t2 <= t1:
                active[q], lam[q], is_active[p] = p, lam_p, True
                q += 1
                break
            is_active[active[drop]] = False
            for k in range(drop, q - 1):
                active[k], lam[k] = active[k + 1], lam[k + 1]
            q -= 1
    return n_unmet


@njit
def cbf_filter_kernel(params, lower, upper, pos, vel, f_hat, u, counts):
    """The filter, compiled: u (W, V, 3) m/s^2 in place, from pos, vel (W, V, 3) (estimates) and f_hat (W, V, 3);
    params (N_PARAMS,) (`SafetyConfig.packed`), lower, upper (V, 3) (`actuator_box`). Adds to counts (2,) int64
    the worlds whose commands changed and the barriers left unmet. A world whose nominal commands violate no
    barrier is not written."""
    W, V = pos.shape[0], pos.shape[1]
    n = 3 * V
    m = V * (V - 1) + 7 * V
    A, b, x = np.empty((m, n)), np.empty(m), np.empty(n)
    active, lam, r, z = np.empty(n, np.int64), np.empty(n), np.empty(n), np.empty(n)
    G, L = np.empty((n, n)), np.empty((n, n))
    is_active, unmet = np.empty(m, np.bool_), np.empty(m, np.bool_)
    tol, dependent = params[6], params[7]
    for w in range(W):
        for q in range(n):
            x[q] = u[w, q // 3, q % 3]
        _world_rows(params, lower, upper, pos[w], vel[w], f_hat[w], x, A, b)
        violated = False
        for j in range(m):
            if _dot(A[j], x, n) - b[j] < -tol:
                violated = True
                break
        if not violated:
            continue
        counts[1] += _solve_world(A, b, m, n, x, tol, dependent, _MAX_STEPS * (m + n), active, lam, r, z, G, L,
                                  is_active, unmet)
        changed = False
        for q in range(n):
            changed = changed or x[q] != u[w, q // 3, q % 3]
            u[w, q // 3, q % 3] = x[q]
        counts[0] += changed


# void f(n_worlds, n_vehicles, pos, vel, f_hat, u, params, lower, upper, counts, unused): the fused tick calls it
# by address with the argument types of `sim.predictor.PREDICTOR_SIGNATURE` (pointers as addresses)
_F64P, _I64P = nbt.CPointer(nbt.float64), nbt.CPointer(nbt.int64)
SAFETY_SIGNATURE = nbt.void(nbt.int64, nbt.int64, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _I64P, _F64P)


def _safety_c(n_worlds, n_veh, pos, vel, f_hat, u, params, lower, upper, counts, unused):
    shape = (n_worlds, n_veh, 3)
    cbf_filter_kernel(carray(params, (N_PARAMS,)), carray(lower, (n_veh, 3)), carray(upper, (n_veh, 3)), carray(pos, shape),
                      carray(vel, shape), carray(f_hat, shape), carray(u, shape), carray(counts, (2,)))


@functools.lru_cache(maxsize=1)
def safety_function() -> Any:
    """`cbf_filter_kernel` as a C function of `SAFETY_SIGNATURE` (a numba cfunc, compiled at the first use,
    then cached on disk); kept alive here for the process."""
    return numba.cfunc(SAFETY_SIGNATURE, cache=True, nopython=True)(_safety_c)


# ----------------------------------------------------------------------------- the filter


def safety_filter(config: SafetyConfig | None, quads: Sequence[Any], controller: Any) -> SafetyFilter | None:
    """A simulator's filter for `config` (None: none; ConfigError for anything else) under `controller`'s feedback
    linearisation limits (its `max_tilt`, `min_vertical` where it has them, else the LQR's defaults)."""
    tilt = getattr(controller, "max_tilt", math.radians(MAX_TILT_DEG))
    floor = getattr(controller, "min_vertical", MIN_THRUST_G * GRAVITY)
    return None if config is None else SafetyFilter(config, quads, tilt, floor)


class SafetyFilter:
    """The CBF filter for a scene's vehicles (`quads`, each with its `thrust_to_weight`) under a feedback
    linearisation with limits `max_tilt` (rad) and `min_vertical` (m/s^2): `actuator_box`."""

    def __init__(self, config: SafetyConfig, quads: Sequence[Any], max_tilt: float = math.radians(MAX_TILT_DEG),
                 min_vertical: float = MIN_THRUST_G * GRAVITY):
        if not isinstance(config, SafetyConfig):
            raise ConfigError(f"safety: expected a sim.safety.SafetyConfig or None, got {type(config).__name__}")
        self.config = config
        self.max_tilt, self.min_vertical = float(max_tilt), float(min_vertical)
        self.lower, self.upper = actuator_box(config, quads, self.max_tilt, self.min_vertical)
        self.params = config.packed()

    @property
    def address(self) -> int:
        """The address of the compiled filter's C function (`safety_function`), for the fused tick."""
        return int(safety_function().address)

    def filter_into(self, pos: np.ndarray, vel: np.ndarray, f_hat: np.ndarray, u: np.ndarray) -> tuple[int, int]:
        """The compiled filter on u (W, V, 3) float64 in place; returns (worlds changed, barriers left unmet)."""
        counts = np.zeros(2, np.int64)
        cbf_filter_kernel(self.params, self.lower, self.upper, pos, vel, f_hat, u, counts)
        return int(counts[0]), int(counts[1])

    def __call__(self, pos: np.ndarray, vel: np.ndarray, u: np.ndarray, f_hat: np.ndarray | None = None) -> np.ndarray:
        """The filtered commands (W, V, 3) m/s^2, compiled (a fresh array)."""
        out = np.array(u, dtype=np.float64, order="C")
        pos, vel = (np.ascontiguousarray(a, dtype=np.float64) for a in (pos, vel))
        f_hat = np.zeros_like(out) if f_hat is None else np.ascontiguousarray(f_hat, dtype=np.float64)
        self.filter_into(pos, vel, f_hat, out)
        return out

    def reference(self, pos: np.ndarray, vel: np.ndarray, u: np.ndarray, f_hat: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, int]:
        """The filtered commands (W, V, 3) and the barriers left unmet, in NumPy (the readable form)."""
        u = np.asarray(u, dtype=np.float64)
        f_hat = np.zeros_like(u) if f_hat is None else np.asarray(f_hat, dtype=np.float64)
        A, b = constraint_rows(self.config, self.lower, self.upper, np.asarray(pos, float), np.asarray(vel, float),
                               f_hat, u)
        W, V = u.shape[:2]
        x = u.reshape(W, 3 * V)
        out, unmet = u.copy(), 0
        violated = np.flatnonzero(((A @ x[..., None])[..., 0] - b < -TOLERANCE).any(axis=1))
        for w in violated:  # one QP per world: its pairs couple its vehicles
            solved, missed = solve_qp(A[w], b[w], x[w], _MAX_STEPS * sum(A[w].shape))
            out[w], unmet = solved.reshape(V, 3), unmet + missed
        return out, unmet

    def apply(self, controller: Any, state: Any, ref: Any, f_hat: np.ndarray, out: Any, lookahead: float) -> int:
        """The simulator's step after `controller.command_setpoint(state, ref, f_hat, out, ...)`: filter out.acc
        (the `controllers.lqr.Setpoint` buffers) and redo feedback linearisation where it acted; returns the
        worlds changed. A `FeedbackLinearisedLQR` (stateless) runs its own step again with the filtered command as
        the override, as the fused tick does; any other controller gets `attitude_setpoint` on the changed
        vehicles, towards the heading of its own set-point."""
        exact = type(controller) is FeedbackLinearisedLQR
        nominal = None if exact else out.acc.copy()
        changed, _ = self.filter_into(state.pos, state.vel, f_hat, out.acc)
        if not changed:
            return 0
        if exact:
            controller.command_setpoint(state, ref, f_hat, out, None, out.acc, lookahead)
            return changed
        moved = (out.acc != nominal).any(axis=-1)  # (W, V)
        rot = out.rot[moved]  # the heading c1 in span(b1, b3) with no vertical part: b1 - (b1_z / b3_z) b3
        heading = rot[:, :, 0] - (rot[:, 2, 0] / rot[:, 2, 2])[:, None] * rot[:, :, 2]
        thrust, rot_des = attitude_setpoint(out.acc[moved], np.arctan2(heading[:, 1], heading[:, 0]), self.max_tilt,
                                            self.min_vertical)
        out.thrust[moved], out.rot[moved] = thrust, rot_des
        return changed
