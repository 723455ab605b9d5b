"""The compiled pass of `sim.fields.shed.ShedWake` (numba): `step` and `forces`, and scalar twins of the
momentum law's pieces they use.

`ShedWake.step` and `ShedWake.forces` run here by default; their NumPy forms (`_step_reference`,
`_forces_reference` in `sim.fields.shed`) are the readable reference, and a test ties the two. Each kernel
loops over worlds, vehicles and elements, the same code for one world or many, and repeats the reference's
arithmetic operation by operation, in its order (dot products summed in index order, NumPy's `interp`, the
mean over the ring of rotors summed pairwise as NumPy's `mean` does), so the two agree to the bit wherever
NumPy's transcendental functions (pow, sinh, asinh, cbrt, cos, acos) are the C library's, as they are on an
AVX2 CPU; where a NumPy build uses its own SIMD versions of these (AVX-512) they may differ by an ulp.

Constants arrive as plain arrays, never as Python objects, and no kernel reads a number defined in another
module (numba would not see it change: `downwash_core.jit`):
    jet (J_*) and follower (F_*) constants per ordered pair of kinds, `pair` (Ks, Ks, N_PAIR), built by
        `ShedWake` from each pair's `MomentumWake` (`pair_constants`);
    per source kind `source` (Ks, N_SOURCE): kappa v_h / sqrt(T), the thrust estimate's numerator;
    its travel table `table_x` (G(s)), `table_s` (s), `table_slope` (Ks, M) as `np.interp` uses them.
Scalar twins of `sim.fields.momentum` (`centreline`, `velocity` = `MomentumWake.induced_velocity`,
`follower_response`, `rotor_thrust_ratio`) take one point; tests check them against the NumPy originals.
"""

from __future__ import annotations

import math

import numpy as np

from downwash_core.jit import njit

# a pair's constants: the source's jet (MomentumWake.centreline, induced_velocity) ...
J_VH, J_RADIUS, J_R2, J_K2, J_S0, J_SPREAD, J_FADE, J_BLEND, J_PROFILE = range(9)
# ... and the target's response (MomentumWake.follower_response, rotor_thrust_ratio, drag_acceleration)
F_ARM, F_VH, F_ROTORS, F_DRAG, F_GAIN, F_GRAVITY, F_C_STAR, F_C_SMALL = range(9, 17)
N_PAIR = 17
# a source kind's constants: kappa v_h / sqrt(T) (m/s/sqrt(N)), thrust_scale m g (N)
S_TRAVEL, S_THRUST = range(2)
N_SOURCE = 2


def pair_constants(law, gravity: float, profile_a: float, blend: float, c_star: float, c_small: float) -> np.ndarray:
    """(N_PAIR,) the constants of one `MomentumWake` as the kernels read them, each computed as the law does."""
    mass, cd, area, rho = law.drag_law
    out = np.zeros(N_PAIR)
    out[[J_VH, J_RADIUS, J_R2, J_K2]] = (law.vh_per_sqrt_thrust, law.radius_eq, law.radius_eq**2,
                                         1.0 / (2.0 * float(law.decay_constant) * law.d0))
    out[[J_S0, J_SPREAD, J_FADE, J_BLEND, J_PROFILE]] = (float(law.virtual_origin), float(law.spreading_rate),
                                                         float(law.fade_depth), blend, profile_a)
    out[[F_ARM, F_VH, F_ROTORS, F_DRAG]] = (float(law.follower_arm), law.vh_follower, bool(law.rotors),
                                           bool(law.drag))
    out[[F_GAIN, F_GRAVITY, F_C_STAR, F_C_SMALL]] = (rho * cd * area / (2.0 * mass), gravity, c_star, c_small)
    return out


# ------------------------------------------------------------------ scalar twins of sim.fields.momentum
@njit
def rotor_thrust_ratio(c, c_star, c_small):  # pragma: no cover - compiled
    """`sim.fields.momentum.rotor_thrust_ratio` of one c: the branch that NumPy's np.where picks."""
    if c >= c_small:
        return 2.0 * math.sqrt(c / 3.0) * math.sinh(math.asinh(1.5 * math.sqrt(3.0) * c**-1.5) / 3.0)
    if c >= c_star:
        u = np.cbrt(0.5 + math.sqrt(max(0.25 + c**3.0 / 27.0, 0.0)))
        return u - c / (3.0 * u)
    m = -c
    arg = min(1.5 * math.sqrt(3.0) * m**-1.5, 1.0)
    return 2.0 * math.sqrt(m / 3.0) * math.cos(math.acos(arg) / 3.0)


@njit
def centreline(s, thrust, jet):  # pragma: no cover - compiled
    """`MomentumWake.centreline` at one depth s (m) and thrust (N): U_c, b, dU_c/ds, db/ds."""
    s = max(s, 0.0)
    v_h = jet[J_VH] * math.sqrt(max(thrust, 0.0))
    R2, p, s0, k2 = jet[J_R2], jet[J_BLEND], jet[J_S0], jet[J_K2]
    root = math.sqrt(s * s + R2)
    phi1 = 1.0 + s / root
    dphi1 = R2 / (root * root * root)
    past = s > s0
    g2 = max(s - s0, 0.0) * k2
    dg2 = k2 if past else 0.0
    phi = (phi1**-p + g2**p) ** (-1.0 / p)
    dphi = phi ** (p + 1.0) * (phi1 ** (-p - 1.0) * dphi1 - g2 ** (p - 1.0) * dg2)
    b1 = jet[J_RADIUS] / math.sqrt(phi1)
    db1 = -0.5 * b1 * dphi1 / phi1
    S = jet[J_SPREAD]
    b2 = S * max(s - s0, 0.0)
    db2 = S if past else 0.0
    b = (b1**p + b2**p) ** (1.0 / p)
    db = b ** (1.0 - p) * (b1 ** (p - 1.0) * db1 + b2 ** (p - 1.0) * db2)
    return v_h * phi, b, v_h * dphi, db


@njit
def profile(s, r2, U_c, b, dU_c, db, jet):  # pragma: no cover - compiled
    """`MomentumWake.induced_velocity` given the centreline at s: U (m/s) and V / r (1/s) at squared radius r2, faded."""
    inv_b2 = 1.0 / (b * b)
    q = 1.0 + jet[J_PROFILE] * r2 * inv_b2
    f = 1.0 / (q * q)
    d_flux = dU_c * b * b + 2.0 * U_c * b * db
    v_over_r = (U_c * db * f - d_flux / (2.0 * b * q)) / b
    t = min(max(s / jet[J_FADE], 0.0), 1.0)
    w = t * t * (3.0 - 2.0 * t)
    return w * U_c * f, w * v_over_r


@njit
def velocity(s, r2, thrust, jet):  # pragma: no cover - compiled
    """`MomentumWake.induced_velocity` at one point: U (m/s) and V / r (1/s)."""
    U_c, b, dU_c, db = centreline(s, thrust, jet)
    return profile(s, r2, U_c, b, dU_c, db, jet)


@njit
def _mean(x):  # pragma: no cover - compiled
    """The mean of x (K,), K <= 128, summed as NumPy's `mean` over a last axis (pairwise, 8 accumulators)."""
    n = x.size
    if n < 8:
        total = -0.0
        for i in range(n):
            total += x[i]
        return total / n
    r0, r1, r2, r3, r4, r5, r6, r7 = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
    i = 8
    while i < n - n % 8:
        r0, r1, r2, r3 = r0 + x[i], r1 + x[i + 1], r2 + x[i + 2], r3 + x[i + 3]
        r4, r5, r6, r7 = r4 + x[i + 4], r5 + x[i + 5], r6 + x[i + 6], r7 + x[i + 7]
        i += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        total += x[i]
        i += 1
    return total / n


@njit
def follower_response(n, v_b, ring_speed, air, law, out):  # pragma: no cover - compiled
    """`MomentumWake.follower_response` of one target into out (3,) m/s^2: n, v_b, air (3,), ring_speed (K,)
    (overwritten by the rotors' thrust ratios); each read only where the law has that term."""
    o0 = o1 = o2 = 0.0
    if law[F_ROTORS] != 0.0:
        v_hf, c_star, c_small = law[F_VH], law[F_C_STAR], law[F_C_SMALL]
        climb = v_b[0] * n[0] + v_b[1] * n[1] + v_b[2] * n[2]
        for k in range(ring_speed.size):
            ring_speed[k] = rotor_thrust_ratio((ring_speed[k] + climb) / v_hf, c_star, c_small)
        g = law[F_GRAVITY] * (_mean(ring_speed) - rotor_thrust_ratio(climb / v_hf, c_star, c_small))
        o0, o1, o2 = o0 + g * n[0], o1 + g * n[1], o2 + g * n[2]
    if law[F_DRAG] != 0.0:
        gain = law[F_GAIN]
        x0, x1, x2 = air[0] - v_b[0], air[1] - v_b[1], air[2] - v_b[2]
        y0, y1, y2 = 0.0 - v_b[0], 0.0 - v_b[1], 0.0 - v_b[2]
        gx = gain * math.hypot(math.hypot(x0, x1), x2)
        gy = gain * math.hypot(math.hypot(y0, y1), y2)
        o0, o1, o2 = o0 + (gx * x0 - gy * y0), o1 + (gx * x1 - gy * y1), o2 + (gx * x2 - gy * y2)
    out[0], out[1], out[2] = o0, o1, o2


# ------------------------------------------------------------------ step
BUCKETS_PER_OCTAVE = 32  # the travel tables' search guide: 32 buckets per octave of G, a few table rows each


@njit
def _bucket(x, emin, n_buckets):  # pragma: no cover - compiled
    """A bucket of x (non-decreasing in x): its octave above 2^emin and 1/32 of that octave, clipped."""
    if x <= 0.0:
        return 0
    m, e = math.frexp(x)  # x = m 2^e, 0.5 <= m < 1
    return min(max((e - emin) * BUCKETS_PER_OCTAVE + int((m - 0.5) * (2 * BUCKETS_PER_OCTAVE)), 0), n_buckets - 1)


@njit
def bucket_starts(xp, emin, n_buckets):  # pragma: no cover - compiled
    """(n_buckets + 1,) for each bucket b the number of table rows xp (increasing) in the buckets below it."""
    start = np.zeros(n_buckets + 1, np.int64)
    for j in range(xp.size):
        start[_bucket(xp[j], emin, n_buckets) + 1] += 1
    for b in range(n_buckets):
        start[b + 1] += start[b]
    return start


@njit
def _interp(x, xp, fp, slope, start, emin, out):  # pragma: no cover - compiled
    """out[:] = np.interp(x, xp, fp) for x (n,), as NumPy computes it: fp[j] + slope[j] (x - xp[j]), xp[j] <= x <
    xp[j + 1] (xp increasing, slope its precomputed slopes), found by bisection within x's bucket (start, emin:
    `bucket_starts`): rows of a lower bucket are below x, of a higher one above, so j is the whole table's."""
    last, n_buckets = xp.size - 1, start.size - 1
    for i in range(x.size):
        xi = x[i]
        if xi > xp[last]:
            out[i] = fp[last]
            continue
        if xi < xp[0]:
            out[i] = fp[0]
            continue
        b = _bucket(xi, emin, n_buckets)
        lo, hi = start[b], start[b + 1]  # the first row above xi is one of these
        while lo < hi:
            mid = (lo + hi) >> 1
            if xi >= xp[mid]:
                lo = mid + 1
            else:
                hi = mid
        j = lo - 1
        out[i] = fp[j] if j == last or xp[j] == xi else slope[j] * (xi - xp[j]) + fp[j]


@njit
def _all_finite(x):  # pragma: no cover - compiled
    """Whether every entry of x is finite."""
    for v in x.ravel():
        if not math.isfinite(v):
            return False
    return True


@njit
def step(e_pos, e_axis, e_depth, e_thrust, e_age, e_valid, cursor, clock, dt, pos, vel, rot, thrust, wind,
         kind_of, source, table_x, table_s, table_slope, table_start, emin, period, max_age,
         slack):  # pragma: no cover - compiled
    """`ShedWake.step` on the state (e_* (W, V, N[, 3]), cursor, clock (W,)) in place: carry every element by dt
    (s), drop the old, shed. pos, vel (W, V, 3), rot (W, V, 3, 3); thrust (W, V) N or (0, 0) for the estimate;
    wind (W, 3) m/s or (0, 3) for still air; kind_of (V,) each vehicle's source row; source, table_* its constants
    and travel table (table_start, emin: its search guide, `bucket_starts`); period, max_age (s), slack (-) as
    `ShedWake`'s. Returns 0, or (before touching the state) the 1-based argument (pos, vel, rot, thrust, wind)
    that is not finite."""
    W, V, N = e_valid.shape
    for code, ok in enumerate((_all_finite(pos), _all_finite(vel), _all_finite(rot), _all_finite(thrust),
                               _all_finite(wind))):
        if not ok:
            return code + 1
    estimate, still = thrust.shape[0] == 0, wind.shape[0] == 0
    limit = max_age * (1.0 + slack)
    T_now, key, new_depth = np.empty(V), np.empty(N), np.empty(N)
    for w in range(W):
        wx, wy, wz = (0.0, 0.0, 0.0) if still else (wind[w, 0], wind[w, 1], wind[w, 2])
        for v in range(V):
            k = kind_of[v]
            if estimate:
                T_now[v] = source[k, S_THRUST] / min(max(rot[w, v, 2, 2], 0.5), 1.0)
            else:
                T_now[v] = thrust[w, v]
            travel = source[k, S_TRAVEL]
            for i in range(N):  # carry every element (invalid ones too, as the reference does)
                a = e_age[w, v, i] + dt
                e_age[w, v, i] = a
                key[i] = travel * math.sqrt(max(e_thrust[w, v, i], 0.0)) * a
            _interp(key, table_x[k], table_s[k], table_slope[k], table_start[k], emin, new_depth)
            for i in range(N):  # move each along its axis by its change of depth, and with the wind
                new = new_depth[i]
                ds = new - e_depth[w, v, i]
                e_pos[w, v, i, 0] += ds * e_axis[w, v, i, 0] + wx * dt
                e_pos[w, v, i, 1] += ds * e_axis[w, v, i, 1] + wy * dt
                e_pos[w, v, i, 2] += ds * e_axis[w, v, i, 2] + wz * dt
                e_depth[w, v, i] = new
                e_valid[w, v, i] = e_valid[w, v, i] and e_age[w, v, i] <= limit
        # shed: the clock crossed k periods, the newest min(k, N) survive, oldest first
        c = clock[w] + dt
        crossed = np.int64(math.floor(c / period * (1.0 + slack) + slack))
        kept = min(crossed, N)
        for j in range(kept):
            tau = max(c - float(crossed - kept + 1 + j) * period, 0.0)
            slot = cursor[w]
            for v in range(V):
                k = kind_of[v]
                T = T_now[v]
                key[0] = source[k, S_TRAVEL] * math.sqrt(max(T, 0.0)) * tau
                _interp(key[:1], table_x[k], table_s[k], table_slope[k], table_start[k], emin, new_depth)
                new = new_depth[0]
                for d in range(3):
                    ax = -rot[w, v, d, 2]
                    wd = 0.0 if still else wind[w, d]
                    e_pos[w, v, slot, d] = (pos[w, v, d] - vel[w, v, d] * tau) + (new * ax + wd * tau)
                    e_axis[w, v, slot, d] = ax
                e_depth[w, v, slot] = new
                e_thrust[w, v, slot] = T
                e_age[w, v, slot] = tau
                e_valid[w, v, slot] = tau <= limit
            cursor[w] = (slot + 1) % N
        clock[w] = max(c - float(crossed) * period, 0.0)
    return 0


# ------------------------------------------------------------------ forces
@njit
def forces(e_pos, e_axis, e_depth, e_thrust, e_age, e_valid, cursor, pos, vel, rot, wind, kind_of, pair,
           ring_cos, ring_sin, tiny, out):  # pragma: no cover - compiled
    """`ShedWake.forces` into out (W, V, V, 3) (zeroed here): each source's wake on each target below its rotor
    plane. pos, vel (W, V, 3), rot (W, V, 3, 3), wind (W, 3) m/s or (0, 3); kind_of (V,); pair (Ks, Ks, N_PAIR);
    ring_cos, ring_sin (K,) the rotors' azimuths; tiny (m^2) as `_nearest_segments`. Returns 0, or the 1-based
    argument (pos, vel, rot, wind) that is not finite."""
    W, V, N = e_valid.shape
    for code, ok in enumerate((_all_finite(pos), _all_finite(vel), _all_finite(rot), _all_finite(wind))):
        if not ok:
            return code + 1
    out[:] = 0.0
    still = wind.shape[0] == 0
    K = ring_cos.size
    ok = np.zeros(N + 1, np.bool_)
    start = np.empty((N + 1, 3))  # each segment's start and vector (`_nearest_segments`)
    vec = np.empty((N + 1, 3))
    length2 = np.empty(N + 1)
    ring_speed, n_b, v_b, air, res = np.empty(K), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for w in range(W):
        newest = (cursor[w] - 1) % N
        for vs in range(V):
            if not e_valid[w, vs, newest]:  # no wake (the newest is valid iff any is)
                continue
            n0, n1, n2 = rot[w, vs, 0, 2], rot[w, vs, 1, 2], rot[w, vs, 2, 2]
            for j in range(N + 1):
                if j == 0:
                    ok[0] = True
                    a, b = pos[w, vs], e_pos[w, vs, newest]
                else:
                    i, i1 = j - 1, (j - 2) % N
                    ok[j] = e_valid[w, vs, i] and e_valid[w, vs, i1] and e_age[w, vs, i1] > e_age[w, vs, i]
                    if not ok[j]:
                        continue
                    a, b = e_pos[w, vs, i], e_pos[w, vs, i1]
                for d in range(3):
                    start[j, d] = a[d]
                    vec[j, d] = b[d] - a[d]
                length2[j] = max(vec[j, 0] * vec[j, 0] + vec[j, 1] * vec[j, 1] + vec[j, 2] * vec[j, 2], tiny)
            for vt in range(V):
                p0, p1, p2 = pos[w, vt, 0], pos[w, vt, 1], pos[w, vt, 2]
                if vt == vs or (p0 - pos[w, vs, 0]) * n0 + (p1 - pos[w, vs, 1]) * n1 + (p2 - pos[w, vs, 2]) * n2 > 0.0:
                    continue  # its own wake, or above the source's rotor plane
                # the nearest segment (the first of equally near ones) and the parameter t along it
                best, seg, t = np.inf, 0, 0.0
                for j in range(N + 1):
                    if not ok[j]:
                        continue
                    sx, sy, sz = vec[j, 0], vec[j, 1], vec[j, 2]
                    rx, ry, rz = p0 - start[j, 0], p1 - start[j, 1], p2 - start[j, 2]
                    tj = min(max((rx * sx + ry * sy + rz * sz) / length2[j], 0.0), 1.0)
                    ox, oy, oz = rx - tj * sx, ry - tj * sy, rz - tj * sz
                    d2 = ox * ox + oy * oy + oz * oz
                    if d2 < best:
                        best, seg, t = d2, j, tj
                # the wake there, by linear interpolation along the segment (`ShedWake._nearest`)
                ring = seg > 0
                first = seg - 1 if ring else newest
                second = (seg - 2) % N if ring else newest
                sx, sy, sz = vec[seg, 0], vec[seg, 1], vec[seg, 2]
                o0 = p0 - (start[seg, 0] + t * sx)
                o1 = p1 - (start[seg, 1] + t * sy)
                o2 = p2 - (start[seg, 2] + t * sz)
                x0, y0, z0 = (e_axis[w, vs, first, 0], e_axis[w, vs, first, 1], e_axis[w, vs, first, 2]) if ring \
                    else (-n0, -n1, -n2)
                d0 = x0 + t * (e_axis[w, vs, second, 0] - x0)
                d1 = y0 + t * (e_axis[w, vs, second, 1] - y0)
                d2 = z0 + t * (e_axis[w, vs, second, 2] - z0)
                norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                d0, d1, d2 = d0 / norm, d1 / norm, d2 / norm
                seg_len = math.sqrt(sx * sx + sy * sy + sz * sz)
                if seg_len > 0.0:
                    scale = max(seg_len, tiny)
                    t0, t1, t2 = sx / scale, sy / scale, sz / scale
                else:
                    t0, t1, t2 = d0, d1, d2
                x0 = e_depth[w, vs, first] if ring else 0.0
                s = x0 + t * (e_depth[w, vs, second] - x0)
                x0 = e_thrust[w, vs, first] if ring else e_thrust[w, vs, newest]
                T = x0 + t * (e_thrust[w, vs, second] - x0)
                # the target's response, by the law of this ordered pair of kinds
                law = pair[kind_of[vs], kind_of[vt]]
                U_c, b, dU_c, db = centreline(s, T, law)
                for d in range(3):
                    n_b[d] = rot[w, vt, d, 2]
                    v_b[d] = vel[w, vt, d] if still else vel[w, vt, d] - wind[w, d]
                if law[F_ROTORS] != 0.0:
                    arm = law[F_ARM]
                    for k in range(K):
                        c, sn = ring_cos[k], ring_sin[k]
                        r0 = c * rot[w, vt, 0, 0] + sn * rot[w, vt, 0, 1]
                        r1 = c * rot[w, vt, 1, 0] + sn * rot[w, vt, 1, 1]
                        r2 = c * rot[w, vt, 2, 0] + sn * rot[w, vt, 2, 1]
                        along = r0 * t0 + r1 * t1 + r2 * t2
                        q0 = o0 + arm * (r0 - along * t0)
                        q1 = o1 + arm * (r1 - along * t1)
                        q2 = o2 + arm * (r2 - along * t2)
                        axial, radial = profile(s, q0 * q0 + q1 * q1 + q2 * q2, U_c, b, dU_c, db, law)
                        along = q0 * t0 + q1 * t1 + q2 * t2
                        u0 = axial * d0 + radial * (q0 - along * t0)
                        u1 = axial * d1 + radial * (q1 - along * t1)
                        u2 = axial * d2 + radial * (q2 - along * t2)
                        ring_speed[k] = -(u0 * n_b[0] + u1 * n_b[1] + u2 * n_b[2])
                if law[F_DRAG] != 0.0:
                    axial, radial = profile(s, o0 * o0 + o1 * o1 + o2 * o2, U_c, b, dU_c, db, law)
                    along = o0 * t0 + o1 * t1 + o2 * t2
                    air[0] = axial * d0 + radial * (o0 - along * t0)
                    air[1] = axial * d1 + radial * (o1 - along * t1)
                    air[2] = axial * d2 + radial * (o2 - along * t2)
                follower_response(n_b, v_b, ring_speed, air, law, res)
                out[w, vs, vt, 0], out[w, vs, vt, 1], out[w, vs, vt, 2] = res[0], res[1], res[2]
    return 0
