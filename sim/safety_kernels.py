"""The safety layer's compiled path: the CBF filter's QP per world and its force estimate, as one C function.

`cbf_filter_kernel` is `sim.safety`'s algorithm (see that module's docstring: the barriers, the robust
drift, the dual active-set solver) over (W, V, 3) arrays, with a small Cholesky and no BLAS, so that it
gives the same bits on every CPU; `safety_function` is it as a C function of `SAFETY_SIGNATURE`, which
the fused tick calls by address (`sim.tick_stages.control_stage`) and `sim.safety.SafetyFilter` calls on
the readable path. tests/test_safety.py holds it equal to the NumPy form in `sim.safety`.
"""

from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
from numba import carray
from numba import types as nbt

from downwash_core.jit import njit
from downwash_core.params import GRAVITY

__all__ = ["cbf_filter_kernel", "SAFETY_SIGNATURE", "safety_function", "TOLERANCE", "DEPENDENT", "MIN_Q", "MAX_STEPS",
           "N_PARAMS", "STATE_WIDTH"]

TOLERANCE = 1e-9  # m/s^2: a barrier counts as violated (active) only by more than this
DEPENDENT = 1e-10  # a normal whose squared part outside the active normals' span is below this share is dependent
MIN_Q = 1e-9  # -: two vehicles closer than this (in ellipsoid units) have no direction, so no pair barrier
MAX_STEPS = 10  # the solver's steps per world, per row and command: far beyond a QP's need (rounding cannot loop it)
N_PARAMS = 10  # the packed scalars (`SafetyFilter.params`): inflation, ground_clearance, k0, k1, the estimate's gain
#                per tick, the tick dt, TOLERANCE, DEPENDENT, tan(max_tilt), min_vertical; then each pair's radii
#                a (V, V) and c (V, V) m, then each vehicle's full specific thrust (V,) m/s^2
STATE_WIDTH = 10  # per world and vehicle: the estimate d (3), the last v_est (3), the last command (3), seen (1)


# ----------------------------------------------------------------------------- the compiled path


@njit
def _dot(a, b, n):
    out = 0.0
    for c in range(n):
        out += a[c] * b[c]
    return out


@njit
def _world_rows(params, lower, upper, p, v, f, d, x, A, b):
    """One world's rows of `constraint_rows` into A (m, n), b (m,), in the same order and arithmetic; x (n,) its
    nominal commands, d (V, STATE_WIDTH) its vehicles' estimates (the first three columns)."""
    V = p.shape[0]
    inflation, zmin, k0, k1 = params[0], params[1], params[2], params[3]
    A[:, :] = 0.0
    row = 0
    for i in range(V):
        for j in range(i + 1, V):
            a, c = params[N_PARAMS + i * V + j], params[N_PARAMS + V * V + i * V + j]
            a2, c2 = a * a, c * c
            dx, dy, dz = p[i, 0] - p[j, 0], p[i, 1] - p[j, 1], p[i, 2] - p[j, 2]
            gx, gy, gz = dx / a2, dy / a2, dz / c2
            q = np.sqrt(dx * gx + dy * gy + dz * gz)
            if q > MIN_Q:
                g = np.sqrt(gx * gx + gy * gy + gz * gz)
                nx, ny, nz = gx / g, gy / g, gz / g
                vx, vy, vz = v[i, 0] - v[j, 0], v[i, 1] - v[j, 1], v[i, 2] - v[j, 2]
                qd = (gx * vx + gy * vy + gz * vz) / q
                bend = ((vx * vx + vy * vy) / a2 + vz * vz / c2 - qd * qd) / q
                drift = min(nx * (f[i, 0] - f[j, 0]) + ny * (f[i, 1] - f[j, 1]) + nz * (f[i, 2] - f[j, 2]),
                            nx * (d[i, 0] - d[j, 0]) + ny * (d[i, 1] - d[j, 1]) + nz * (d[i, 2] - d[j, 2]))
                A[row, 3 * i], A[row, 3 * i + 1], A[row, 3 * i + 2] = nx, ny, nz
                A[row, 3 * j], A[row, 3 * j + 1], A[row, 3 * j + 2] = -nx, -ny, -nz
                b[row] = -(q / g) * (k1 * qd + k0 * (q - inflation) + bend) - drift
            else:
                b[row] = -np.inf
            row += 1
    for i in range(V):  # the ground
        A[row, 3 * i + 2] = 1.0
        b[row] = -min(f[i, 2], d[i, 2]) - k1 * v[i, 2] - k0 * (p[i, 2] - zmin)
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
            t2 = (b[p] - _dot(A[p], x, n)) / zz if zz > dependent * _dot(A[p], A[p], n) and q < n else np.inf
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
def _estimate_world(params, v, state):
    """`estimate_step` on one world's rows (v (V, 3), state (V, STATE_WIDTH)), the same arithmetic."""
    gain, dt = params[4], params[5]
    for i in range(v.shape[0]):
        if state[i, 9] == 0.0:
            continue
        m0 = (v[i, 0] - state[i, 3]) / dt - state[i, 6]
        m1 = (v[i, 1] - state[i, 4]) / dt - state[i, 7]
        m2 = (v[i, 2] - state[i, 5]) / dt - state[i, 8]
        if np.isfinite(m0) and np.isfinite(m1) and np.isfinite(m2):
            state[i, 0] = state[i, 0] + gain * (m0 - state[i, 0])
            state[i, 1] = state[i, 1] + gain * (m1 - state[i, 1])
            state[i, 2] = state[i, 2] + gain * (m2 - state[i, 2])


@njit
def _record_world(params, v, u, state):
    """`record_step` on one world's rows (v, u (V, 3), state (V, STATE_WIDTH)), `realised`'s arithmetic."""
    V = v.shape[0]
    tan_tilt, floor = params[8], params[9]
    for i in range(V):
        top = params[N_PARAMS + 2 * V * V + i]
        fx, fy, fz = u[i, 0], u[i, 1], u[i, 2] + GRAVITY
        low = fz < floor
        if low:
            fz = floor
        nxy = np.sqrt(fx * fx + fy * fy)
        limit = tan_tilt * fz
        tilted = nxy > limit
        if tilted:
            fx, fy = fx * limit / nxy, fy * limit / nxy
        t = np.sqrt(fx * fx + fy * fy + fz * fz)
        over = t > top
        if over:
            scale = top / t
            fx, fy, fz = fx * scale, fy * scale, fz * scale
        for k in range(3):
            state[i, 3 + k] = v[i, k]
        if low or tilted or over:
            state[i, 6], state[i, 7], state[i, 8] = fx, fy, fz - GRAVITY
        else:  # (within the limits: the command itself, bit for bit)
            state[i, 6], state[i, 7], state[i, 8] = u[i, 0], u[i, 1], u[i, 2]
        state[i, 9] = 1.0


@njit
def cbf_filter_kernel(params, lower, upper, pos, vel, f_hat, u, counts, state):
    """The filter, compiled: u (W, V, 3) m/s^2 in place, from pos, vel (W, V, 3) (estimates) and f_hat (W, V, 3);
    params (`SafetyFilter.params`), lower, upper (V, 3) (`actuator_box`), state (W, V, STATE_WIDTH) the estimate's
    (updated: `estimate_step` before, `record_step` after). Adds to counts (2,) int64 the worlds whose commands
    changed and the barriers left unmet. A world whose nominal commands violate no barrier is not written."""
    W, V = pos.shape[0], pos.shape[1]
    n = 3 * V
    m = V * (V - 1) // 2 + 7 * V
    A, b, x = np.empty((m, n)), np.empty(m), np.empty(n)
    active, lam, r, z = np.empty(n, np.int64), np.empty(n), np.empty(n), np.empty(n)
    G, L = np.empty((n, n)), np.empty((n, n))
    is_active, unmet = np.empty(m, np.bool_), np.empty(m, np.bool_)
    tol, dependent = params[6], params[7]
    for w in range(W):
        _estimate_world(params, vel[w], state[w])
        for q in range(n):
            x[q] = u[w, q // 3, q % 3]
        _world_rows(params, lower, upper, pos[w], vel[w], f_hat[w], state[w], x, A, b)
        violated = False
        for j in range(m):
            if _dot(A[j], x, n) - b[j] < -tol:
                violated = True
                break
        if violated:
            counts[1] += _solve_world(A, b, m, n, x, tol, dependent, MAX_STEPS * (m + n), active, lam, r, z, G, L,
                                      is_active, unmet)
            changed = False
            for q in range(n):  # into the widened box (where it and the barriers conflict, the box holds)
                nominal = u[w, q // 3, q % 3]
                x[q] = min(max(x[q], min(lower[q // 3, q % 3], nominal)), max(upper[q // 3, q % 3], nominal))
                changed = changed or x[q] != nominal
                u[w, q // 3, q % 3] = x[q]
            counts[0] += changed
        _record_world(params, vel[w], u[w], state[w])


# void f(n_worlds, n_vehicles, pos, vel, f_hat, u, params, lower, upper, counts, state): the fused tick calls it
# by address with the argument types of `sim.predictor.PREDICTOR_SIGNATURE` (pointers as addresses); state points
# at the first world's rows of the (W, V, STATE_WIDTH) estimate (`SafetyFilter.state`)
_F64P, _I64P = nbt.CPointer(nbt.float64), nbt.CPointer(nbt.int64)
SAFETY_SIGNATURE = nbt.void(nbt.int64, nbt.int64, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _F64P, _I64P, _F64P)


def _safety_c(n_worlds, n_veh, pos, vel, f_hat, u, params, lower, upper, counts, state):
    shape = (n_worlds, n_veh, 3)
    cbf_filter_kernel(carray(params, (N_PARAMS + 2 * n_veh * n_veh + n_veh,)), carray(lower, (n_veh, 3)),
                      carray(upper, (n_veh, 3)), carray(pos, shape), carray(vel, shape), carray(f_hat, shape),
                      carray(u, shape), carray(counts, (2,)), carray(state, (n_worlds, n_veh, STATE_WIDTH)))


@functools.lru_cache(maxsize=1)
def safety_function() -> Any:
    """`cbf_filter_kernel` as a C function of `SAFETY_SIGNATURE` (a numba cfunc, compiled at the first use,
    then cached on disk); kept alive here for the process."""
    return numba.cfunc(SAFETY_SIGNATURE, cache=True, nopython=True)(_safety_c)
