"""Small geometry helpers: dot products, quaternions, rotations, headings.

Readable functions take an array namespace `xp` (NumPy by default; `torch` works too,
which `downwash.features` uses for differentiable inputs) and broadcast over leading
axes. `quat_to_rot` is the compiled form for numba kernels (the simulator's per-tick
passes), and `quat_to_mat_fast` the batched call of it; a test checks it against
`quat_to_mat`.

Conventions: MuJoCo quaternions (w, x, y, z); rotation matrices body to world, so
column 2 is the body's up axis; headings in the Z-Y-X convention.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from downwash_core import libm
from downwash_core.jit import njit

__all__ = [
    "dot",
    "quat_to_mat",
    "quat_to_mat_fast",
    "quat_to_rot",
    "quat_multiply",
    "quat_from_rotvec",
    "perturb_quat",
    "perturb_quat_into",
    "rotation_about_axis",
    "yaw_of",
    "wrap_angle",
]


def dot(a, b, xp: ModuleType = np):
    """Dot product over the last axis (...,), summed component by component in index order.

    Not np.vecdot or torch.linalg.vecdot: their inner loops are BLAS or SIMD kernels that
    each CPU sums in its own order, and a flight must have the same bits on every CPU
    (`downwash_core.numerics`). This order is the compiled kernels' (`a0 b0 + a1 b1 + a2 b2`), and
    it is the same whatever the batch size. Indexing and arithmetic serve NumPy and torch alike:
    `xp` is accepted for symmetry with the other helpers, not needed."""
    total = a[..., 0] * b[..., 0]
    for k in range(1, a.shape[-1]):
        total = total + a[..., k] * b[..., k]
    return total


def quat_to_mat(quat, xp: ModuleType = np):
    """Body-to-world rotations (..., 3, 3) from quaternions (w, x, y, z) (..., 4).

    The quaternion is normalised first, so slightly non-unit input is fine.
    """
    q = quat / xp.sqrt(dot(quat, quat, xp))[..., None]
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, -1) for r in rows], -2)


@njit
def quat_to_rot(w, x, y, z, R):
    """Compiled: unit quaternion (w, x, y, z) -> R (3, 3) body to world, in place; returns the heading (rad)."""
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return np.arctan2(R[1, 0], R[0, 0])


@njit
def _quat_to_mat_kernel(q):
    n = q.shape[0]
    R = np.empty((n, 3, 3))
    for i in range(n):
        quat_to_rot(q[i, 0], q[i, 1], q[i, 2], q[i, 3], R[i])
    return R


def quat_to_mat_fast(q: np.ndarray) -> np.ndarray:
    """`quat_to_mat` for unit quaternions (..., 4) float64 NumPy, compiled (no normalisation)."""
    return _quat_to_mat_kernel(q.reshape(-1, 4).astype(float, copy=False)).reshape(q.shape[:-1] + (3, 3))


def quat_multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product q1 q2 (..., 4) of quaternions (w, x, y, z): rotate by q2, then by q1."""
    w1, x1, y1, z1 = np.moveaxis(q1, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(q2, -1, 0)
    return np.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], axis=-1)


def quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) of rotation vectors v (..., 3) rad (axis times angle)."""
    angle = np.linalg.norm(v, axis=-1)
    half = 0.5 * angle
    scale = np.where(angle > 0.0, np.sin(half) / np.where(angle > 0.0, angle, 1.0), 0.5)
    return np.concatenate([np.cos(half)[..., None], scale[..., None] * v], axis=-1)


def perturb_quat(quat: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """The attitude `quat` (..., 4) turned by the small body-frame rotation `rotvec` (..., 3) rad:
    q exp(rotvec / 2), how a motion-capture attitude error is modelled."""
    return quat_multiply(quat, quat_from_rotvec(rotvec))


@njit
def perturb_quat_into(w, x, y, z, dx, dy, dz, out):
    """Compiled `perturb_quat` for one quaternion (w, x, y, z) and rotation vector (dx, dy, dz) rad;
    writes the result into out (4,)."""
    angle = np.sqrt(dx * dx + dy * dy + dz * dz)
    c = np.cos(0.5 * angle)
    s = np.sin(0.5 * angle) / angle if angle > 0.0 else 0.5
    ew, ex, ey, ez = c, s * dx, s * dy, s * dz
    out[0] = w * ew - x * ex - y * ey - z * ez
    out[1] = w * ex + x * ew + y * ez - z * ey
    out[2] = w * ey - x * ez + y * ew + z * ex
    out[3] = w * ez + x * ey - y * ex + z * ew


def rotation_about_axis(axis, angle, xp: ModuleType = np):
    """Rotation matrices (..., 3, 3) by `angle` (...,) rad about unit `axis` (..., 3) (Rodrigues)."""
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    c, s = xp.cos(angle), xp.sin(angle)
    C = 1 - c
    rows = [
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ]
    return xp.stack([xp.stack(r, -1) for r in rows], -2)


def yaw_of(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) body-to-world rotations -> (...,) heading (rad), Z-Y-X convention."""
    return libm.arctan2(rot[..., 1, 0], rot[..., 0, 0])


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles (rad) to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi
