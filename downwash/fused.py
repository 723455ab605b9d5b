"""The compiled pieces of the per-neighbour models: features, network and output basis of one pair.

The same features as `downwash.features` (`model_inputs`), a model's float64 `folded_layers`
(input normalisation and output scaling folded in, `pack_layers`), the equivariant basis,
the depth gate's quantities and the clamp, in float64, one pair at a time. The compiled
predictor kernels (`downwash.set_fused`: ``summed_pairwise``, which flies every
per-neighbour model, and the deep sets) are built from them; per call they cost a few
microseconds where NumPy's per-operation overhead cost ~55 us at one world. The readable
reference is the model's NumPy twin (`DownwashModel.numpy_forward`); tests check the two
agree to float64 rounding (the sums run in another order than BLAS's).
"""

from __future__ import annotations

import numpy as np

from downwash_core.jit import njit
from downwash.features import EQUIVARIANT_FEATURE_SETS, FEATURE_SETS, MEMORY_FEATURE_SETS, R_EPS, V_EPS

__all__ = ["pack_layers", "feature_code", "pair_inputs", "mlp_inplace", "pair_force", "clamped"]

_RAW, _SET5, _SET6, _GENERAL = 0, 1, 2, 3  # feature-set codes of the kernel


def feature_code(feature_set: str) -> int:
    """The kernel's code of a feature set ("raw", "5", "6" or "general")."""
    return {"raw": _RAW, "5": _SET5, "6": _SET6, "general": _GENERAL}[feature_set]


def pack_layers(layers: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(weights, biases, widths) for the kernel from `folded_layers` [(W (out, in), b (out,)), ...]:
    every W transposed to (in, out) and flattened row-major, one after another; widths (L + 1,)."""
    widths = np.array([layers[0][0].shape[1]] + [w.shape[0] for w, _ in layers], dtype=np.int64)
    weights = np.concatenate([np.ascontiguousarray(w.T, dtype=np.float64).ravel() for w, _ in layers])
    biases = np.concatenate([np.asarray(b, dtype=np.float64) for _, b in layers])
    return weights, biases, widths


@njit
def pair_inputs(dx, dy, dz, nx, ny, nz, dp_n, vbx, vby, vbz, vax, vay, vaz, code, x):
    """One pair's network inputs (`downwash.features.model_inputs`) into x[:k]; returns (px, py, pz, r_soft).

    dx, dy, dz: dp = p_follower - p_leader (m); nx, ny, nz: the leader's axis n; dp_n = dp . n
    (summed in index order); vb*, va*: the follower's and the leader's velocities (m/s); code from
    `feature_code`. (px, py, pz) = P dp and r_soft = sqrt(|P dp|^2 + R_EPS^2), for `pair_force`.
    """
    # features (downwash.features): see its docstring for their meaning
    px, py, pz = dx - dp_n * nx, dy - dp_n * ny, dz - dp_n * nz
    r_soft = np.sqrt(px * px + py * py + pz * pz + R_EPS * R_EPS)
    if code == _RAW:
        x[0], x[1], x[2] = dx, dy, dz
        x[3], x[4], x[5] = vbx, vby, vbz
    elif code == _GENERAL:
        vb_n = vbx * nx + vby * ny + vbz * nz
        ux, uy, uz = vbx - vb_n * nx, vby - vb_n * ny, vbz - vb_n * nz
        va_n = vax * nx + vay * ny + vaz * nz
        ax, ay, az = vax - va_n * nx, vay - va_n * ny, vaz - va_n * nz
        r2 = px * px + py * py + pz * pz
        q2 = ux * ux + uy * uy + uz * uz
        qa2 = ax * ax + ay * ay + az * az
        den_b = r_soft * np.sqrt(q2 + V_EPS * V_EPS)
        den_a = r_soft * np.sqrt(qa2 + V_EPS * V_EPS)
        x[0] = (px * ux + py * uy + pz * uz) / den_b
        x[1] = (nx * (py * uz - pz * uy) + ny * (pz * ux - px * uz) + nz * (px * uy - py * ux)) / den_b
        x[2], x[3], x[4], x[5], x[6] = np.sqrt(r2), np.sqrt(q2), -dp_n, -vb_n, np.sqrt(qa2)
        x[7] = (px * ax + py * ay + pz * az) / den_a
        x[8] = (nx * (py * az - pz * ay) + ny * (pz * ax - px * az) + nz * (px * ay - py * ax)) / den_a
        x[9] = -va_n
    else:
        vb_n = vbx * nx + vby * ny + vbz * nz
        ux, uy, uz = vbx - vb_n * nx, vby - vb_n * ny, vbz - vb_n * nz
        r2 = px * px + py * py + pz * pz
        q2 = ux * ux + uy * uy + uz * uz
        x[0] = (px * ux + py * uy + pz * uz) / (r_soft * np.sqrt(q2 + V_EPS * V_EPS))
        x[1], x[2], x[3], x[4] = np.sqrt(r2), np.sqrt(q2), -dp_n, -vb_n
        if code == _SET6:
            va_n = vax * nx + vay * ny + vaz * nz
            ax, ay, az = vax - va_n * nx, vay - va_n * ny, vaz - va_n * nz
            x[5] = np.sqrt(ax * ax + ay * ay + az * az)
    return px, py, pz, r_soft


@njit
def mlp_inplace(x, y, weights, biases, widths):
    """The network of `pack_layers` on x[:widths[0]], its output left in x[:widths[-1]]: ReLU between
    layers, none after the last (y: scratch of at least max(widths)).

    Each output is summed in input order from 0, then its bias added (the bits of a plain loop
    per output), but the loop runs over the inputs outside and the outputs inside: the outputs'
    sums are independent, so they run side by side (SIMD) instead of waiting on one another.
    """
    n_layers = widths.shape[0] - 1
    wo, bo = 0, 0
    for layer in range(n_layers):
        n_in, n_out = widths[layer], widths[layer + 1]
        for o in range(n_out):
            y[o] = 0.0
        for k in range(n_in):
            xk = x[k]
            row = weights[wo + k * n_out:wo + (k + 1) * n_out]
            for o in range(n_out):
                y[o] += xk * row[o]
        last = layer == n_layers - 1
        for o in range(n_out):
            acc = y[o] + biases[bo + o]
            x[o] = acc if last or acc > 0.0 else 0.0
        wo += n_in * n_out
        bo += n_out


@njit
def pair_force(x, code, px, py, pz, r_soft, nx, ny, nz, fx, fy, fz):
    """(fx, fy, fz) plus the pair's world-frame force from the network outputs x (`mlp_inplace`) and
    `pair_inputs`' (px, py, pz, r_soft): world axes for "raw", else f1 r_hat + f2 d (+ f3 t_hat)."""
    if code == _RAW:
        return fx + x[0], fy + x[1], fz + x[2]
    # F = f1 r_hat + f2 d (+ f3 t_hat), r_hat = P dp / r_soft, d = -n, t_hat = n x r_hat
    fx += x[0] * px / r_soft - x[1] * nx
    fy += x[0] * py / r_soft - x[1] * ny
    fz += x[0] * pz / r_soft - x[1] * nz
    if code == _GENERAL:
        fx += x[2] * (ny * pz - nz * py) / r_soft
        fy += x[2] * (nz * px - nx * pz) / r_soft
        fz += x[2] * (nx * py - ny * px) / r_soft
    return fx, fy, fz


@njit
def clamped(fx, fy, fz, clamp):
    """(fx, fy, fz) scaled to magnitude `clamp` where it exceeds it (clamp <= 0: no bound); the same
    bits as `downwash.predictor.clamp_magnitude`."""
    scale = 1.0
    if clamp > 0.0:
        norm = np.sqrt(fx * fx + fy * fy + fz * fz)
        if norm > clamp:
            scale = clamp / norm
    return fx * scale, fy * scale, fz * scale


# (the sets with memory have no kernel: their predictors keep a history, which the fused tick cannot tell)
assert set(FEATURE_SETS) == {"raw", *EQUIVARIANT_FEATURE_SETS, *MEMORY_FEATURE_SETS}, "a new feature set needs a kernel code"
