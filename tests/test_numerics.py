"""Numbers with the same bits on every CPU (downwash_core.numerics, downwash_core.geometry.dot):
what they compute, the order they sum in, and that the BLAS kernel does not matter."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from downwash_core import libm
from downwash_core.geometry import dot
from downwash_core.numerics import ROUND_OFF, cpu_independent, matmul_rows, matvec

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 6), st.integers(1, 5), st.integers(1, 4), st.data())
def test_matmul_rows_and_matvec_are_the_products_summed_in_index_order(n, k, batch, data):
    x = data.draw(arrays(np.float64, (batch, n), elements=finite))
    m = data.draw(arrays(np.float64, (n, k), elements=finite))
    want = np.zeros((batch, k))
    for i in range(n):  # the readable definition: one term at a time, in index order
        want = want + x[:, i, None] * m[i]
    np.testing.assert_array_equal(matmul_rows(x, m), want if n > 1 else x[:, :1] * m[0])
    # x @ m is a BLAS product whose kernel picks the summation order and FMA: each side is within
    # n u sum_i |x_i m_i| of the exact sum (u = eps / 2), so the two within n eps |x| @ |m| (n + 1: the
    # bound's own rounding; plus an ulp of underflow per product). At |x|, |m| <= 1e3 and n = 6 that
    # is up to 8e-9: the 1e-9 this once allowed was not a bound for every draw and every kernel
    eps, tiny = np.finfo(np.float64).eps, np.finfo(np.float64).smallest_subnormal
    bound = (n + 1) * eps * float(np.max(np.abs(x) @ np.abs(m), initial=0.0)) + 2 * n * tiny
    np.testing.assert_allclose(matmul_rows(x, m), x @ m, rtol=0, atol=bound)
    mt = np.broadcast_to(m.T, (batch, k, n))
    np.testing.assert_array_equal(matvec(mt, x), matmul_rows(x, m))


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (5, 3), elements=finite), arrays(np.float64, (5, 3), elements=finite))
def test_dot_sums_the_components_in_order(a, b):
    np.testing.assert_array_equal(dot(a, b), (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) + a[:, 2] * b[:, 2])
    # einsum is NumPy's own loop (no BLAS, compiled for the baseline, not dispatched per CPU): the same
    # bits on every CPU; it sums the same 3 products in its own order, 2 roundings of partial sums
    # below 3e6 each side, <= 4 * 2.3e-10 = 9.3e-10 apart: 1e-9 holds for any draw
    np.testing.assert_allclose(dot(a, b), np.einsum("ij,ij->i", a, b), rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(dot(a[:2], b[:2]), dot(a, b)[:2])  # the same bits whatever the batch


@settings(max_examples=100, deadline=None)
@given(arrays(np.float64, (4, 7), elements=st.floats(-100, 100, allow_nan=False)), st.integers(-4, 4))
def test_cpu_independent_absorbs_a_few_ulps(x, ulps):
    """A value moved by a few float64 ulps (another kernel's round-off) rounds to the same bits,
    except in the rare case that it straddles the middle of two float32 values."""
    y = cpu_independent(x)
    assert np.array_equal(cpu_independent(y), y)  # idempotent
    # moved by at most half a float32 ulp, or zeroed: round-off next to the largest, or a subnormal
    tiny = np.finfo(np.float64).tiny
    assert np.all(np.abs(y - x) <= np.maximum(np.abs(x) * 2.0**-24, max(ROUND_OFF * np.abs(x).max(), tiny)))
    moved = x.copy()
    for _ in range(abs(ulps)):
        moved = np.nextafter(moved, np.inf if ulps > 0 else -np.inf)
    mid = np.abs(x.astype(np.float32).astype(np.float64) - x) > 0.49 * np.spacing(np.abs(x).astype(np.float32))
    same = cpu_independent(moved) == y
    assert np.all(same | mid)


def test_cpu_independent_zeroes_round_off_and_keeps_real_zeros():
    x = np.array([[1.5, 3e-16], [0.0, -2.0]])
    assert cpu_independent(x).tolist() == [[1.5, 0.0], [0.0, -2.0]]
    assert cpu_independent(np.zeros(3)).tolist() == [0.0, 0.0, 0.0]
    # zeros moved by an ulp (subnormals, found by the property test above) are zeros
    assert cpu_independent(np.full(3, 5e-324)).tolist() == [0.0, 0.0, 0.0]
    tiny = np.array([1e-300, -1e-300])  # normal, if small: kept (to 24 bits)
    assert np.all(np.abs(cpu_independent(tiny) - tiny) <= 1e-300 * 2.0**-24) and np.all(cpu_independent(tiny) != 0)


def test_the_set_up_gains_do_not_depend_on_the_blas_kernel():
    """The LQR and Kalman gains, solved through LAPACK, have the same bits under every OpenBLAS
    kernel this CPU can run (the raw solves do not: they differ in their last bits)."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "golden"))
    import machine

    code = textwrap.dedent("""
        import json
        import control
        from controllers.lqr import DEFAULT_Q, DEFAULT_R, double_integrator, lqr_gain
        from sim.estimation import steady_state_gain
        A, B = double_integrator()
        raw = control.lqr(A, B, DEFAULT_Q, DEFAULT_R)[0]
        print(json.dumps([lqr_gain().tobytes().hex(), steady_state_gain(0.01).tobytes().hex(), raw.tobytes().hex()]))
    """)
    seen = {}
    for kernel in machine.runnable_blas_kernels() or [""]:
        out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, OPENBLAS_CORETYPE=kernel),
                             capture_output=True, text=True, timeout=300, check=True).stdout
        seen[kernel] = json.loads(out.strip().splitlines()[-1])
    assert len({tuple(v[:2]) for v in seen.values()}) == 1, seen


_LIBM = {"exp": (np.exp, 1), "log": (np.log, 1), "power": (np.power, 2), "tanh": (np.tanh, 1), "sinh": (np.sinh, 1),
         "arcsinh": (np.arcsinh, 1), "arccos": (np.arccos, 1), "arctan2": (np.arctan2, 2), "cbrt": (np.cbrt, 1)}


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(sorted(_LIBM)), data=st.data())
def test_libm_ufuncs_are_numpys_to_a_few_ulps(name, data):
    """The C library's functions (`downwash_core.libm`) against NumPy's own: within 4 ulps, NaN where
    NumPy gives NaN (outside the domain), the shapes NumPy broadcasts to, a float for a float."""
    fn, reference = getattr(libm, name), _LIBM[name][0]
    finite = st.floats(-30.0, 30.0, allow_nan=False)
    x = data.draw(arrays(np.float64, st.integers(0, 5), elements=finite))
    args = (x,) if _LIBM[name][1] == 1 else (x, data.draw(arrays(np.float64, 1, elements=finite)))
    if name == "power":
        args = (np.abs(args[0]), args[1])
    with np.errstate(all="ignore"):
        want = reference(*args)
    got = fn(*args)
    assert got.shape == want.shape and got.dtype == np.float64
    assert np.array_equal(np.isnan(got), np.isnan(want))
    ok = ~np.isnan(want)
    with np.errstate(invalid="ignore"):  # (inf - inf where both are inf: equal, so the first test holds)
        assert np.all((got[ok] == want[ok]) | (np.abs(got[ok] - want[ok]) <= 4 * np.spacing(np.abs(want[ok]))))
    assert isinstance(fn(*(np.float64(a.flat[0]) if a.size else 0.5 for a in args)), float)


def test_libm_ufuncs_do_not_depend_on_numpys_simd_loops():
    """Their bits with NumPy's AVX-512 and AVX2 loops masked (as on older CPUs) are this CPU's; NumPy's
    own exp differs on an AVX-512 CPU (measured), which is why the flights do not use it."""
    code = textwrap.dedent("""
        import json
        import numpy as np
        from downwash_core import libm
        x = np.linspace(-20.0, 20.0, 4001)
        out = [getattr(libm, n)(x).tobytes().hex() for n in ("exp", "tanh", "sinh", "arcsinh", "cbrt")]
        out += [libm.log(np.abs(x)).tobytes().hex(), libm.arccos(x / 20.0).tobytes().hex(),
                libm.power(np.abs(x), 1.37).tobytes().hex(), libm.arctan2(x, 3.0).tobytes().hex()]
        print(json.dumps(out))
    """)
    seen = set()
    for masked in ("", "X86_V4 AVX512_ICL AVX512_SPR", "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"):
        out = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, NPY_DISABLE_CPU_FEATURES=masked),
                             capture_output=True, text=True, timeout=300, check=True).stdout
        seen.add(out.strip().splitlines()[-1])
    assert len(seen) == 1
