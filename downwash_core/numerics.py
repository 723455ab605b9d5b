"""Numbers that come out the same on every CPU.

OpenBLAS and LAPACK pick their kernels per CPU (`OPENBLAS_CORETYPE` says which), and
different kernels sum in different orders: a Riccati solve gives gains that differ in
their last bits from one machine to the next. A flight is chaotic enough to carry
such a bit to every later sample. So:

- the per-step kernels call no BLAS: their small products are explicit loops in the
  compiled kernels, and `matmul_rows`, `matvec` and `downwash_core.geometry.dot` (elementwise
  NumPy in a fixed order, whose results IEEE 754 fixes) in the readable ones;
- a gain solved once at set-up goes through `cpu_independent`, which rounds it to
  float32 precision (24 significant bits, about 7 digits). Two kernels' answers differ
  by a few float64 ulps, about 2^-27 of a float32 step, so they round to the same
  value except with a probability of about 1e-8 per number; the gain itself moves by
  at most 3e-8 of its value, far below anything a flight can feel. Entries below
  1e-9 of the largest are the solve's round-off where the answer is zero (a
  decoupled gain's off-diagonal blocks), different on every CPU: they become 0;
- the readable paths take their elementary functions from the C library, as the compiled
  kernels do (`downwash_core.libm` says why: NumPy's own differ between AVX2 and AVX-512);
- training asks torch for kernels that are the same on every CPU with AVX2
  (`PORTABLE_TORCH`, `request_portable_torch`; `downwash.train` says why and what it
  costs), and the labels' filter coefficients are exact rationals (`downwash.labels`).
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["ROUND_OFF", "PORTABLE_TORCH", "cpu_independent", "matmul_rows", "matvec", "request_portable_torch"]

# torch's kernels that train the same bits on every x86-64 CPU with AVX2: ATen's AVX2 loops and
# MKL's AVX2 path in its reproducible mode (Intel's Conditional Numerical Reproducibility);
# see `downwash.train`
PORTABLE_TORCH = {"ATEN_CPU_CAPABILITY": "avx2", "MKL_CBWR": "AVX2"}


ROUND_OFF = 1e-9  # relative to the largest entry: smaller entries are a solve's round-off


def cpu_independent(x) -> np.ndarray:
    """`x` as float64 rounded to 24 significant bits (float32's precision, in float64's
    range), round-off and subnormals zeroed: the same bits whichever BLAS kernel made it.
    (A subnormal holds fewer than 24 bits, and the few ulps of round-off that move an
    exact zero make one.)"""
    x = np.asarray(x, dtype=np.float64)
    scale = float(np.max(np.abs(x))) if x.size else 0.0
    x = np.where(np.abs(x) < max(ROUND_OFF * scale, np.finfo(np.float64).tiny), 0.0, x)
    # 24 significant bits, as float32 has, but in float64's range (a cast would overflow or
    # flush to zero outside float32's); every step is exact, the rounding half to even
    mantissa, exponent = np.frexp(x)
    return np.ldexp(np.round(mantissa * 2.0**24) / 2.0**24, exponent)


def matmul_rows(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """`x @ m` for x (..., n) and m (n, k), summed over n in index order (the compiled
    kernels' order), with no BLAS: the same bits on every CPU."""
    acc = x[..., 0, None] * m[0]
    for i in range(1, m.shape[0]):
        acc = acc + x[..., i, None] * m[i]
    return acc


def matvec(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """`(m @ x[..., None])[..., 0]` for m (..., k, n) and x (..., n), summed over n in index
    order, with no BLAS: the same bits on every CPU."""
    acc = m[..., :, 0] * x[..., None, 0]
    for i in range(1, m.shape[-1]):
        acc = acc + m[..., :, i] * x[..., None, i]
    return acc


def request_portable_torch() -> dict[str, str]:
    """Ask torch for the kernels of `PORTABLE_TORCH`, through the environment (a value the user set is
    kept). Torch reads these variables at its first operation in a process, so this must come first:
    the experiments call it before any work, and `downwash.train` before training. Returns the
    variables as they now are."""
    for name, value in PORTABLE_TORCH.items():
        os.environ.setdefault(name, value)
    return {name: os.environ[name] for name in PORTABLE_TORCH}

