"""The C library's elementary functions as NumPy ufuncs: the same bits on every CPU.

NumPy's own vectorised exp, log, power, arctan2, arcsin, arccos, sinh, cbrt and tanh give
other last bits on an AVX-512 CPU than on an AVX2 one (and tanh on AVX2 than on older CPUs;
sqrt, sin, cos and hypot agree; measured with NumPy 2.4 by masking its CPU features,
``NPY_DISABLE_CPU_FEATURES``), and a flight carries such a bit to every later sample. The
compiled kernels call the C library's functions, which are the same on every x86-64 CPU with
FMA. So a readable path uses these ufuncs, numba-compiled loops around the same calls, and
agrees with its compiled twin bit for bit on every CPU (`downwash_core.numerics`). float64 in,
float64 out (broadcast as NumPy); NaN outside a function's domain, as NumPy.
"""

from __future__ import annotations

import math

import numpy as np

from downwash_core.jit import njit

__all__ = ["exp", "log", "power", "tanh", "sinh", "arcsinh", "arccos", "arctan2", "cbrt"]


def _contiguous(x) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)  # (0-d stays 0-d, unlike np.ascontiguousarray)
    return a if a.flags.c_contiguous else a.copy()


def _unary(kernel):
    def ufunc(x):
        a = _contiguous(x)
        out = np.empty_like(a)
        kernel(a.reshape(-1), out.reshape(-1))
        return out if out.ndim else out[()]

    return ufunc


def _binary(kernel):
    def ufunc(x, y):
        a, b = _contiguous(x), _contiguous(y)
        shape = np.broadcast_shapes(a.shape, b.shape)
        a, b = (v if v.shape == shape else np.broadcast_to(v, shape).copy() for v in (a, b))
        out = np.empty_like(a)
        kernel(a.reshape(-1), b.reshape(-1), out.reshape(-1))
        return out if out.ndim else out[()]

    return ufunc


@njit
def _exp(x, out):
    for i in range(x.size):
        out[i] = math.exp(x[i])


@njit
def _log(x, out):
    for i in range(x.size):
        out[i] = math.log(x[i]) if x[i] > 0.0 else (-math.inf if x[i] == 0.0 else math.nan)


@njit
def _power(x, y, out):
    for i in range(x.size):
        out[i] = x[i] ** y[i]


@njit
def _tanh(x, out):
    for i in range(x.size):
        out[i] = math.tanh(x[i])


@njit
def _sinh(x, out):
    for i in range(x.size):
        out[i] = math.sinh(x[i])


@njit
def _arcsinh(x, out):
    for i in range(x.size):
        out[i] = math.asinh(x[i])


@njit
def _arccos(x, out):
    for i in range(x.size):
        out[i] = math.acos(x[i]) if -1.0 <= x[i] <= 1.0 else math.nan


@njit
def _arctan2(y, x, out):
    for i in range(x.size):
        out[i] = math.atan2(y[i], x[i])


@njit
def _cbrt(x, out):
    for i in range(x.size):
        out[i] = np.cbrt(x[i])


exp, log, tanh, sinh, arcsinh, arccos, cbrt = (_unary(k) for k in (_exp, _log, _tanh, _sinh, _arcsinh, _arccos, _cbrt))
power, arctan2 = _binary(_power), _binary(_arctan2)
for _name in __all__:
    globals()[_name].__name__ = globals()[_name].__qualname__ = _name
    globals()[_name].__doc__ = f"np.{_name} with the C library's bits (module doc): float64 arrays or scalars."
