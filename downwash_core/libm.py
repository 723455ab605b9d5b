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


_EXP, _LOG, _TANH, _SINH, _ARCSINH, _ARCCOS, _CBRT, _POWER, _ARCTAN2 = range(9)  # (the binary ones last)


@njit
def _apply(op, x, y, out):
    """out[i] = the C library's function `op` of x[i] (and y[i] for power and arctan2)."""
    for i in range(out.size):
        v = x[i]
        if op == _EXP:
            r = math.exp(v)
        elif op == _LOG:
            r = math.log(v) if v > 0.0 else (-math.inf if v == 0.0 else math.nan)
        elif op == _TANH:
            r = math.tanh(v)
        elif op == _SINH:
            r = math.sinh(v)
        elif op == _ARCSINH:
            r = math.asinh(v)
        elif op == _ARCCOS:
            r = math.acos(v) if -1.0 <= v <= 1.0 else math.nan
        elif op == _CBRT:
            r = np.cbrt(v)
        elif op == _POWER:
            r = v ** y[i]
        else:
            r = math.atan2(v, y[i])
        out[i] = r


def _contiguous(x) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)  # (0-d stays 0-d, unlike np.ascontiguousarray)
    return a if a.flags.c_contiguous else a.copy()


def _ufunc(name: str, op: int):
    def ufunc(*args):
        a = [_contiguous(v) for v in args]
        shape = np.broadcast_shapes(*(v.shape for v in a))
        a = [v if v.shape == shape else np.broadcast_to(v, shape).copy() for v in a]
        out = np.empty(shape)
        _apply(op, a[0].reshape(-1), a[-1].reshape(-1), out.reshape(-1))
        return out if out.ndim else out[()]

    ufunc.__name__ = ufunc.__qualname__ = name
    ufunc.__doc__ = f"np.{name} with the C library's bits (module doc): float64 arrays or scalars."
    return ufunc


exp, log, tanh, sinh = _ufunc("exp", _EXP), _ufunc("log", _LOG), _ufunc("tanh", _TANH), _ufunc("sinh", _SINH)
arcsinh, arccos, cbrt = _ufunc("arcsinh", _ARCSINH), _ufunc("arccos", _ARCCOS), _ufunc("cbrt", _CBRT)
power, arctan2 = _ufunc("power", _POWER), _ufunc("arctan2", _ARCTAN2)
