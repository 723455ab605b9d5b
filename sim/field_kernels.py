"""The compiled loops of the paper's field (`sim.field.DownwashField`): its sum over leaders
(`pairwise_kernel`, what `DownwashField.pairwise` and the fused tick call) and its force per
ordered pair (`pair_forces_kernel`, `DownwashField.pair_forces`).

Both read the field's constants packed in declaration order (`DownwashField.packed`) and a
(V_leader, V_follower) factor per pair; the tests tie them to each other and to
`DownwashField.__call__`, the readable law. `sim.field` re-exports them under their former
names (`sim.field._pairwise_kernel`, `sim.field._pair_forces_kernel`).
"""

from __future__ import annotations

import numpy as np

from downwash_core.jit import njit

__all__ = ["pairwise_kernel", "pair_forces_kernel", "C4_CORE"]

C4_CORE = 0.5  # -, radius (in units of sigma) inside which the c4 modulation tapers to 0


@njit
def pairwise_kernel(pos, vel, rot, c, scale):
    """Loop form of `sim.field.pairwise_field(DownwashField(...))` for (W, V, ...) arrays.

    c: the DownwashField constants in declaration order (strength, strength_depth,
    width0, width_slope, fade_start, fade_end, approach_gain, approach_speed,
    radial_gain, radial_offset, radial_speed_gain, radial_speed, leader_speed_scale,
    c4_amplitude, swirl, skew). scale (V_leader, V_follower): each pair's factor on the
    strength (`sim.vehicle_params`: the two vehicles' kinds); 1.0, exact, flies the law as given.
    """
    strength, depth0, width0, width_slope, fade_start, fade_end = c[0], c[1], c[2], c[3], c[4], c[5]
    approach_gain, approach_speed, radial_gain, radial_offset = c[6], c[7], c[8], c[9]
    radial_speed_gain, radial_speed, speed_scale, c4, swirl, skew = c[10], c[11], c[12], c[13], c[14], c[15]
    W, V = pos.shape[0], pos.shape[1]
    out = np.zeros((W, V, 3))
    for w in range(W):
        for i in range(V):  # leader
            nx, ny, nz = rot[w, i, 0, 2], rot[w, i, 1, 2], rot[w, i, 2, 2]
            va_n = vel[w, i, 0] * nx + vel[w, i, 1] * ny + vel[w, i, 2] * nz
            vax, vay, vaz = vel[w, i, 0] - va_n * nx, vel[w, i, 1] - va_n * ny, vel[w, i, 2] - va_n * nz
            k = 1.0 / (1.0 + (vax * vax + vay * vay + vaz * vaz) / (speed_scale * speed_scale))
            for j in range(V):  # follower
                if j == i:
                    continue
                dx, dy, dz = pos[w, j, 0] - pos[w, i, 0], pos[w, j, 1] - pos[w, i, 1], pos[w, j, 2] - pos[w, i, 2]
                s = -(dx * nx + dy * ny + dz * nz)
                t = min(max((s - fade_start) / (fade_end - fade_start), 0.0), 1.0)
                if t == 0.0:
                    continue  # above the leader or just below it: exactly no wake
                sp = max(s, 0.0)
                rx, ry, rz = dx + s * nx, dy + s * ny, dz + s * nz
                if skew != 0.0:
                    rx, ry, rz = rx + skew * sp * vax, ry + skew * sp * vay, rz + skew * sp * vaz
                vb_n = vel[w, j, 0] * nx + vel[w, j, 1] * ny + vel[w, j, 2] * nz
                ux, uy, uz = vel[w, j, 0] - vb_n * nx, vel[w, j, 1] - vb_n * ny, vel[w, j, 2] - vb_n * nz
                q = np.sqrt(ux * ux + uy * uy + uz * uz)
                r = np.sqrt(rx * rx + ry * ry + rz * rz)
                v_r = (ux * rx + uy * ry + uz * rz) / max(r, 1e-12)
                sigma = width0 + width_slope * sp
                rho = r / sigma
                a = strength * scale[i, j] / (1.0 + sp / depth0) ** 2  # (strength x 1.0 is exact)
                kawg = k * a * t * t * (3.0 - 2.0 * t) * np.exp(-0.5 * rho * rho)
                down = kawg * (1.0 - approach_gain * np.tanh(v_r / approach_speed) * rho)
                if c4 != 0.0:
                    x = rx * rot[w, i, 0, 0] + ry * rot[w, i, 1, 0] + rz * rot[w, i, 2, 0]
                    y = rx * rot[w, i, 0, 1] + ry * rot[w, i, 1, 1] + rz * rot[w, i, 2, 1]
                    x2, y2 = x * x, y * y
                    r4 = (x2 + y2) ** 2
                    down *= 1.0 + c4 * (r4 - 8.0 * x2 * y2) / (r4 + (C4_CORE * sigma) ** 4)
                radial = radial_gain * (rho * rho - radial_offset * (1.0 + radial_speed_gain * q / radial_speed))
                radial *= kawg / sigma
                out[w, j, 0] += radial * rx - down * nx
                out[w, j, 1] += radial * ry - down * ny
                out[w, j, 2] += radial * rz - down * nz
                if swirl != 0.0:
                    g = swirl * kawg * rho / sigma  # times n x r_vec
                    out[w, j, 0] += g * (ny * rz - nz * ry)
                    out[w, j, 1] += g * (nz * rx - nx * rz)
                    out[w, j, 2] += g * (nx * ry - ny * rx)
    return out


@njit
def pair_forces_kernel(pos, vel, rot, c, scale):
    """(W, V_leader, V_follower, 3): the terms of `pairwise_kernel`'s sum, kept per pair.

    The same statements as `pairwise_kernel`, accumulating into out[w, i, j] instead
    of out[w, j] (so for V = 2 the two agree bit for bit). A copy rather than a shared
    helper: a helper called per pair cost `pairwise_kernel`, the 100 Hz path, 20-100 %
    (measured). One inlined into both (`downwash_core.jit.njit_inline`) would have to hand back
    the radial-and-down and the swirl terms apart, since `pairwise_kernel` adds them to its sum
    one after the other (their bits); not tried. The tests pin the two loops to each other and
    to `DownwashField.__call__`. c and scale as in `pairwise_kernel`.
    """
    strength, depth0, width0, width_slope, fade_start, fade_end = c[0], c[1], c[2], c[3], c[4], c[5]
    approach_gain, approach_speed, radial_gain, radial_offset = c[6], c[7], c[8], c[9]
    radial_speed_gain, radial_speed, speed_scale, c4, swirl, skew = c[10], c[11], c[12], c[13], c[14], c[15]
    W, V = pos.shape[0], pos.shape[1]
    out = np.zeros((W, V, V, 3))
    for w in range(W):
        for i in range(V):  # leader
            nx, ny, nz = rot[w, i, 0, 2], rot[w, i, 1, 2], rot[w, i, 2, 2]
            va_n = vel[w, i, 0] * nx + vel[w, i, 1] * ny + vel[w, i, 2] * nz
            vax, vay, vaz = vel[w, i, 0] - va_n * nx, vel[w, i, 1] - va_n * ny, vel[w, i, 2] - va_n * nz
            k = 1.0 / (1.0 + (vax * vax + vay * vay + vaz * vaz) / (speed_scale * speed_scale))
            for j in range(V):  # follower
                if j == i:
                    continue
                dx, dy, dz = pos[w, j, 0] - pos[w, i, 0], pos[w, j, 1] - pos[w, i, 1], pos[w, j, 2] - pos[w, i, 2]
                s = -(dx * nx + dy * ny + dz * nz)
                t = min(max((s - fade_start) / (fade_end - fade_start), 0.0), 1.0)
                if t == 0.0:
                    continue  # above the leader or just below it: exactly no wake
                sp = max(s, 0.0)
                rx, ry, rz = dx + s * nx, dy + s * ny, dz + s * nz
                if skew != 0.0:
                    rx, ry, rz = rx + skew * sp * vax, ry + skew * sp * vay, rz + skew * sp * vaz
                vb_n = vel[w, j, 0] * nx + vel[w, j, 1] * ny + vel[w, j, 2] * nz
                ux, uy, uz = vel[w, j, 0] - vb_n * nx, vel[w, j, 1] - vb_n * ny, vel[w, j, 2] - vb_n * nz
                q = np.sqrt(ux * ux + uy * uy + uz * uz)
                r = np.sqrt(rx * rx + ry * ry + rz * rz)
                v_r = (ux * rx + uy * ry + uz * rz) / max(r, 1e-12)
                sigma = width0 + width_slope * sp
                rho = r / sigma
                a = strength * scale[i, j] / (1.0 + sp / depth0) ** 2  # (strength x 1.0 is exact)
                kawg = k * a * t * t * (3.0 - 2.0 * t) * np.exp(-0.5 * rho * rho)
                down = kawg * (1.0 - approach_gain * np.tanh(v_r / approach_speed) * rho)
                if c4 != 0.0:
                    x = rx * rot[w, i, 0, 0] + ry * rot[w, i, 1, 0] + rz * rot[w, i, 2, 0]
                    y = rx * rot[w, i, 0, 1] + ry * rot[w, i, 1, 1] + rz * rot[w, i, 2, 1]
                    x2, y2 = x * x, y * y
                    r4 = (x2 + y2) ** 2
                    down *= 1.0 + c4 * (r4 - 8.0 * x2 * y2) / (r4 + (C4_CORE * sigma) ** 4)
                radial = radial_gain * (rho * rho - radial_offset * (1.0 + radial_speed_gain * q / radial_speed))
                radial *= kawg / sigma
                out[w, i, j, 0] += radial * rx - down * nx
                out[w, i, j, 1] += radial * ry - down * ny
                out[w, i, j, 2] += radial * rz - down * nz
                if swirl != 0.0:
                    g = swirl * kawg * rho / sigma  # times n x r_vec
                    out[w, i, j, 0] += g * (ny * rz - nz * ry)
                    out[w, i, j, 1] += g * (nz * rx - nx * rz)
                    out[w, i, j, 2] += g * (nx * ry - ny * rx)
    return out
