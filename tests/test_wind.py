"""Ambient wind (`sim.wind`) against the SPEC: MIL-F-8785C / MIL-HDBK-1797 Dryden turbulence.

The spec numbers (intensities, scale lengths, PSDs, autocorrelations) are written here by
hand from the MIL-spec formulas, not read from the code. With h in ft:
    L_w = h, L_u = L_v = h / (0.177 + 0.000823 h)^1.2 (ft);  sigma_w = 0.1 W20,
    sigma_u = sigma_v = sigma_w / (0.177 + 0.000823 h)^0.4;  1 ft = 0.3048 m, 1 kt = 1852/3600 m/s.
At h = 10 ft (the clamp, where this testbed flies): 0.177 + 0.00823 = 0.18523,
0.18523^0.4 = 0.5094300, 0.18523^1.2 = 0.1322067, L_u = 10 / 0.1322067 = 75.63911 ft = 23.05480 m.
At h = 100 ft: 0.177 + 0.0823 = 0.2593, 0.2593^0.4 = 0.5828020, 0.2593^1.2 = 0.1979534,
L_u = 505.1693 ft = 153.9756 m, L_w = 30.48 m.

PSD convention: Phi(omega) is one-sided in omega (rad/s), integral over [0, inf) = sigma^2
(checked numerically below); scipy's Welch density P(f) is one-sided per Hz, so
Phi(omega = 2 pi f) = P(f) / (2 pi) (Parseval checked below as well).

Statistics are measured on R independent replicas of the readable recursion; each
estimator's standard error is the spread across replicas / sqrt(R), so the tolerances
(Z standard errors) come from the data, not from an assumed variance.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError
from downwash_core.provenance import describe
from sim.fields.momentum import MomentumWake
from sim.wind import DrydenWind, drag_acceleration, wind_at

KT = 1852.0 / 3600.0  # m/s per knot
H10 = 3.048  # m, 10 ft
SIGMA_W_10FT = {"light": 0.7716667, "moderate": 1.5433333, "severe": 2.3150000}  # m/s, 0.1 W20 (1.5, 3, 4.5 kt)
SIGMA_U_10FT = {"light": 1.5147648, "moderate": 3.0295296, "severe": 4.5442945}  # m/s, sigma_w / 0.5094300
SIGMA_U_100FT = {"light": 1.3240633, "moderate": 2.6481265, "severe": 3.9721898}  # m/s, sigma_w / 0.5828020
L_U_10FT, L_W_10FT = 23.05480, 3.048  # m
L_U_100FT, L_W_100FT = 153.9756, 30.48  # m

# the statistical test: moderate turbulence at 10 ft, a vehicle hovering in a 10 m/s wind
V = 10.0  # m/s, airspeed
DT = 0.01  # s, the autopilot grid
SIGMA = np.array([3.0295296, 3.0295296, 1.5433333])  # m/s, u, v, w
T = np.array([L_U_10FT, L_U_10FT, L_W_10FT]) / V  # s, 2.305 / 2.305 / 0.305
R, N, BURN_IN = 64, 32768, 2000  # replicas, samples each (328 s = 142 T_u), discarded start (20 s = 8.7 T_u)
NPERSEG = 8192  # Welch segment (82 s): resolves the u corner V / L_u = 0.43 rad/s (0.07 Hz)
BAND = (0.02, 5.0)  # Hz: the corners lie inside; 5 Hz = Nyquist / 10
# Bias of the expected Welch estimate against the continuous PSD in BAND, computed during
# development from the exact sampled autocovariance and the Hann kernel: <= 0.9 % (aliasing at 5 Hz
# dominates; the window's leakage is < 0.1 % at 8192 samples). Allowed on top of Z standard errors.
PSD_BIAS = 0.01
Z = 5.0


def phi_u(omega, sigma, T_):
    """Dryden longitudinal PSD, one-sided in omega (rad/s): sigma^2 (2 L/(pi V)) / (1 + (L omega/V)^2)."""
    return sigma**2 * (2.0 * T_ / np.pi) / (1.0 + (T_ * omega) ** 2)


def phi_v(omega, sigma, T_):
    """Dryden lateral/vertical PSD: sigma^2 (L/(pi V)) (1 + 3 (L omega/V)^2) / (1 + (L omega/V)^2)^2."""
    x2 = (T_ * omega) ** 2
    return sigma**2 * (T_ / np.pi) * (1.0 + 3.0 * x2) / (1.0 + x2) ** 2


PHI = (phi_u, phi_v, phi_v)


def dryden_tf(axis, sigma, T_):
    """sqrt(pi) H(s) as (num, den): the forming filter for unit-intensity white noise, from the spec."""
    if axis == 0:
        return [sigma * math.sqrt(2.0 * T_)], [T_, 1.0]
    return [sigma * math.sqrt(T_) * math.sqrt(3.0) * T_, sigma * math.sqrt(T_)], [T_ * T_, 2.0 * T_, 1.0]


# ----------------------------------------------------------------------- construction


@pytest.mark.parametrize("kwargs, name", [
    ({"mean": (1.0, 2.0)}, "mean"), ({"mean": (0.0, float("nan"), 0.0)}, "mean"), ({"mean": "east"}, "mean"),
    ({"mean": (200.0, 0.0, 0.0)}, "mean"), ({"w20": -1.0}, "w20"), ({"w20": float("inf")}, "w20"),
    ({"altitude": 0.0}, "altitude"), ({"altitude": 400.0}, "altitude"), ({"min_airspeed": 0.0}, "min_airspeed"),
])
def test_validation_names_the_parameter(kwargs, name):
    with pytest.raises(ConfigError, match=rf"^{name}:.*allowed"):
        DrydenWind(**kwargs)


def test_call_arguments_are_validated():
    wind = DrydenWind.preset("light")
    with pytest.raises(ConfigError, match="^severity:.*light"):
        DrydenWind.preset("hurricane")
    with pytest.raises(ConfigError, match="^dt:"):
        wind.coefficients(0.0, 1.0)
    with pytest.raises(ConfigError, match="^airspeed:"):
        wind.coefficients(DT, np.array([1.0, np.nan]))
    with pytest.raises(ConfigError, match="^mass:"):
        drag_acceleration(np.zeros(3), np.ones(3), 0.0, 1.0, 0.01)


@pytest.mark.parametrize("severity", ["light", "moderate", "severe"])
def test_presets_give_the_mil_spec_intensities(severity):
    w20 = {"light": 15.0, "moderate": 30.0, "severe": 45.0}[severity] * KT
    at10 = DrydenWind.preset(severity, altitude=H10)
    assert at10.w20 == pytest.approx(w20, rel=1e-12)
    s = at10.scales()
    assert s["sigma_w"] == pytest.approx(SIGMA_W_10FT[severity], rel=1e-6)
    assert s["sigma_u"] == s["sigma_v"] == pytest.approx(SIGMA_U_10FT[severity], rel=1e-6)
    assert (s["L_u"], s["L_v"], s["L_w"]) == pytest.approx((L_U_10FT, L_U_10FT, L_W_10FT), rel=1e-6)
    s = DrydenWind.preset(severity, altitude=100 * 0.3048).scales()
    assert s["sigma_w"] == pytest.approx(SIGMA_W_10FT[severity], rel=1e-6)  # sigma_w does not depend on h
    assert s["sigma_u"] == pytest.approx(SIGMA_U_100FT[severity], rel=1e-6)
    assert (s["L_u"], s["L_w"]) == pytest.approx((L_U_100FT, L_W_100FT), rel=1e-6)


def test_altitude_is_clamped_to_10_ft():
    low = DrydenWind(w20=10.0, altitude=0.5)
    assert low.effective_altitude == pytest.approx(H10)
    assert low.scales() == pytest.approx(DrydenWind(w20=10.0, altitude=H10).scales())


def test_off_describe_axes_airspeed():
    assert DrydenWind().off and not DrydenWind(mean=(0.0, 0.0, 0.1)).off and not DrydenWind(w20=1.0).off
    A, B, C = DrydenWind().coefficients(DT, 3.0)
    assert not B.any()  # no turbulence: nothing is ever driven
    wind = DrydenWind.preset("moderate", mean=(3.0, 4.0, 0.0))
    d = wind.describe()
    assert d == DrydenWind.preset("moderate", mean=(3, 4, 0)).describe() == describe(wind)
    assert json.loads(json.dumps(d)) == d and d["type"] == "sim.wind.DrydenWind"
    e = wind.axes()
    # rows (0.6, 0.8, 0), (-0.8, 0.6, 0), z, each entry within half an ulp; a 3-term BLAS dot of unit rows is
    # within 3 u = 3.3e-16 of exact on any kernel: |e e^T - I| <= ~8e-16 (2.7e-17 or 0 measured)
    np.testing.assert_allclose(e @ e.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(e[0], [0.6, 0.8, 0.0])  # u along the horizontal mean wind
    np.testing.assert_allclose(np.cross(e[0], e[1]), e[2])  # right-handed, w = world z
    np.testing.assert_allclose(DrydenWind(mean=(0.0, 0.0, 2.0)).axes(), np.eye(3))  # no horizontal wind: u = x
    assert wind.airspeed(np.zeros(3)) == pytest.approx(5.0)  # hovering in a 5 m/s wind
    assert wind.airspeed(np.array([[3.0, 4.0, 0.0]])) == pytest.approx([1.0])  # drifting with it: the floor
    assert np.array_equal(wind.coefficients(DT, 0.0)[1], wind.coefficients(DT, 1.0)[1])


def test_step_and_gust_match_the_compiled_coefficients():
    """The readable law and the arrays a compiled caller uses agree, batched over (W, V)."""
    wind = DrydenWind.preset("severe", mean=(-2.0, 1.0, 0.5))
    rng = np.random.default_rng(1)
    state, xi = rng.standard_normal((2, 4, 3, 2)), rng.standard_normal((2, 4, 3, 2))
    airspeed = rng.uniform(0.0, 20.0, (2, 4))
    A, B, C = wind.coefficients(DT, airspeed)
    assert A.shape == B.shape == (2, 4, 3, 2, 2) and C.shape == (3, 3, 2)
    expected = np.einsum("wvaij,wvaj->wvai", A, state) + np.einsum("wvaij,wvaj->wvai", B, xi)
    np.testing.assert_allclose(wind.step(state, xi, DT, airspeed), expected, rtol=1e-13, atol=1e-13)
    gust = wind.gust(state)
    np.testing.assert_allclose(gust, np.einsum("iaj,wvaj->wvi", C, state), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(wind.wind(state), wind_at(wind.mean, gust))
    g_u = state[..., 0, 0]  # the longitudinal gust is its first state, along the horizontal mean wind
    # a 3-term BLAS dot with a unit row: within ~3 eps |gust| ~ 1e-14 of exact on any kernel
    np.testing.assert_allclose(gust @ wind.axes()[0], g_u, rtol=1e-12, atol=1e-12)


# ----------------------------------------------------------------------- the exact discretisation


def test_forming_filter_is_the_dryden_filter():
    """|c (j omega - A_c)^-1 b|^2 = pi Phi(omega): unit-intensity noise, one-sided Phi."""
    wind = DrydenWind.preset("moderate", altitude=H10)
    A_c, b, c = wind.forming_filter(V)
    omega = np.logspace(-3, 3, 25)
    for axis in range(3):
        response = [c[axis] @ np.linalg.solve(1j * w * np.eye(2) - A_c[axis], b[axis]) for w in omega]
        np.testing.assert_allclose(np.abs(response) ** 2, np.pi * PHI[axis](omega, SIGMA[axis], T[axis]), rtol=1e-6)
        variance, _ = scipy.integrate.quad(PHI[axis], 0.0, np.inf, args=(SIGMA[axis], T[axis]))
        assert variance == pytest.approx(SIGMA[axis] ** 2, rel=1e-8)  # the one-sided convention


@pytest.mark.parametrize("airspeed", [0.0, 3.0, V, 40.0])
@pytest.mark.parametrize("dt", [DT, 0.1])
def test_sampled_recursion_is_exact(airspeed, dt):
    """Stationary covariance (discrete Lyapunov) = continuous variance = sigma^2, and the sampled
    autocovariance equals the continuous one at every lag, with the continuous one computed from a
    realisation of the spec's transfer function (scipy's tf2ss), not the code's."""
    wind = DrydenWind.preset("moderate", altitude=H10)
    A, B, _ = wind.coefficients(dt, airspeed)
    A_c, b, c = wind.forming_filter(airspeed)
    Vf = max(airspeed, 1.0)
    unit = np.broadcast_to(np.eye(2)[:, None, :], (2, 3, 2))  # xi = e_j on every axis, j = 0, 1
    for axis in range(3):
        P = scipy.linalg.solve_discrete_lyapunov(A[axis], B[axis] @ B[axis].T)
        Sigma = scipy.linalg.solve_continuous_lyapunov(A_c[axis], -np.outer(b[axis], b[axis]))
        # two LAPACK Lyapunov solves: the discrete one's condition ~1 / (1 - a^2) <= ~1e3 (a = e^(-dt/T) at
        # T <= 23 s), so ~1e3 eps = 2e-13 relative apart on any kernel (measured 2.3e-13): rtol 1e-9 is 4000x
        np.testing.assert_allclose(P, Sigma, rtol=1e-9, atol=1e-12)  # the state stays stationary for any V
        np.testing.assert_allclose(c[axis] @ P @ c[axis], SIGMA[axis] ** 2, rtol=1e-7)  # SIGMA: 8 digits
        T_ = T[axis] * V / Vf
        As, Bs, Cs, _ = scipy.signal.tf2ss(*dryden_tf(axis, SIGMA[axis], T_))
        Ss = scipy.linalg.solve_continuous_lyapunov(As, -Bs @ Bs.T)
        for k in (0, 1, 7, 100, 1000):
            r_cont = (Cs @ scipy.linalg.expm(As * k * dt) @ Ss @ Cs.T).item()
            r_disc = c[axis] @ np.linalg.matrix_power(A[axis], k) @ P @ c[axis]
            assert r_disc == pytest.approx(r_cont, rel=1e-6, abs=1e-12 * SIGMA[axis] ** 2)  # 8-digit T, SIGMA
        L = wind.stationary_state(unit)[:, axis, :].T  # the stationary factor, column by column
        # closed-form L against LAPACK's continuous Lyapunov solve (2x2, well conditioned: one repeated
        # eigenvalue -1/T, no near-cancellation): a few eps relative on any kernel, measured 4e-16
        np.testing.assert_allclose(L @ L.T, Sigma, rtol=1e-12, atol=1e-15)


def rk4(f, Y: np.ndarray, h: float, n: int) -> np.ndarray:
    """n classical Runge-Kutta steps of h for Y' = f(Y)."""
    for _ in range(n):
        k1 = f(Y)
        k2 = f(Y + h / 2 * k1)
        k3 = f(Y + h / 2 * k2)
        k4 = f(Y + h * k3)
        Y = Y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return Y


@pytest.mark.parametrize("airspeed", [1.0, V, 40.0])
def test_one_step_coefficients_equal_a_fine_integration(airspeed):
    """A = Phi(dt) and B B^T = Q(dt) from 100 RK4 sub-steps of dt/100 of Phi' = A_c Phi and
    Q' = A_c Q + Q A_c^T + b b^T (the continuous filter's transition and noise covariance)."""
    wind = DrydenWind.preset("severe", altitude=H10)
    A, B, _ = wind.coefficients(DT, airspeed)
    A_c, b, _ = wind.forming_filter(airspeed)
    for axis in range(3):
        M, bb = A_c[axis], np.outer(b[axis], b[axis])
        Phi = rk4(lambda X: M @ X, np.eye(2), DT / 100, 100)  # noqa: B023
        Q = rk4(lambda X: M @ X + X @ M.T + bb, np.zeros((2, 2)), DT / 100, 100)  # noqa: B023
        # sized for RK4's truncation error (0.001 and 0.16 of these tolerances measured); the round-off of the
        # 2x2 BLAS products over 100 steps is a few hundred eps (< 1e-13 relative) on any kernel
        np.testing.assert_allclose(A[axis], Phi, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(B[axis] @ B[axis].T, Q, rtol=1e-9, atol=1e-14 * SIGMA[axis] ** 2)


# ----------------------------------------------------------------------- statistics of long sequences


@pytest.fixture(scope="module")
def gusts() -> np.ndarray:
    """(R, 3, N) m/s: the u, v, w gusts of R replicas, a vehicle hovering in a +x 10 m/s wind (so the
    world axes are the turbulence axes), started at rest and run with the code's coefficients."""
    wind = DrydenWind.preset("moderate", mean=(V, 0.0, 0.0), altitude=H10)
    airspeed = wind.airspeed(np.zeros((R, 3)))
    A, B, C = wind.coefficients(DT, airspeed)  # the readable `step` equals these (tested above)
    rng = np.random.default_rng(20240611)
    x = np.zeros((R, 3, 2, 1))
    out = np.empty((N, R, 3))
    chunk = 1000
    for start in range(-BURN_IN, N, chunk):
        xi = rng.standard_normal((chunk, R, 3, 2, 1))
        for i in range(chunk):
            x = A @ x + B @ xi[i]
            if 0 <= start + i < N:
                out[start + i] = wind.gust(x[..., 0])
    return np.ascontiguousarray(out.transpose(1, 2, 0))


def per_replica_mean(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over replicas (axis 0) and its standard error."""
    return values.mean(axis=0), values.std(axis=0, ddof=1) / math.sqrt(values.shape[0])


def test_standard_deviation_per_axis(gusts):
    var, se = per_replica_mean((gusts**2).mean(axis=-1))  # the true mean is 0
    std, se_std = np.sqrt(var), se / (2.0 * np.sqrt(var))
    assert np.all(np.abs(std - SIGMA) <= Z * se_std), (std, SIGMA, se_std)
    mean, se_mean = per_replica_mean(gusts.mean(axis=-1))
    assert np.all(np.abs(mean) <= Z * se_mean), (mean, se_mean)


def autocorrelation_pooled(x: np.ndarray, lags) -> tuple[np.ndarray, np.ndarray]:
    """rho(k) = sum x_t x_{t+k} / sum x_t^2 pooled over replicas (R, N), and its jackknife standard error."""
    den = (x**2).sum(axis=-1)
    num = np.stack([(x[:, :-k] * x[:, k:]).sum(axis=-1) for k in lags], axis=-1)  # (R, K)
    rho = num.sum(0) / den.sum()
    loo = (num.sum(0) - num) / (den.sum() - den)[:, None]
    se = np.sqrt((x.shape[0] - 1) * ((loo - loo.mean(0)) ** 2).mean(0))
    return rho, se


def test_autocorrelation_decays_as_the_spec(gusts):
    """u: rho(tau) = exp(-V tau / L_u); v, w: (1 - V tau / (2L)) exp(-V tau / L) (MIL-F-8785C), at lags
    0.05-2 T. The pooled ratio's own bias, O(2 T / (R N dt)) = 2e-4, is far below its standard error."""
    for axis in range(3):
        lags = np.unique(np.round(np.array([0.05, 0.25, 0.5, 1.0, 2.0]) * T[axis] / DT).astype(int))
        rho, se = autocorrelation_pooled(gusts[:, axis], lags)
        x = lags * DT / T[axis]
        spec = np.exp(-x) if axis == 0 else (1.0 - x / 2.0) * np.exp(-x)
        assert np.all(np.abs(rho - spec) <= Z * se), (axis, rho, spec, se)


def psd_check(x: np.ndarray, phi, sigma: float, T_: float, n_bands: int = 12) -> tuple[bool, np.ndarray]:
    """Welch PSD of x (R, N) against phi over BAND, in log-spaced bands of bins: per replica the band's
    mean of P/Phi, then its mean and standard error over replicas. Passes if every band is within
    Z standard errors plus PSD_BIAS of 1. Returns (passed, the band ratios)."""
    # one-sided, per Hz; no detrending: the mean is known to be 0 (removing each segment's mean
    # would take ~2 T / 82 s of the variance out of the lowest bins)
    f, P = scipy.signal.welch(x, fs=1.0 / DT, nperseg=NPERSEG, detrend=False, axis=-1)
    sel = (f >= BAND[0]) & (f <= BAND[1])
    ratio = P[:, sel] / (2.0 * np.pi) / phi(2.0 * np.pi * f[sel], sigma, T_)
    edges = np.geomspace(*BAND, n_bands + 1)
    band = np.clip(np.searchsorted(edges, f[sel], side="right") - 1, 0, n_bands - 1)
    per_band = np.stack([ratio[:, band == j].mean(axis=1) for j in range(n_bands)], axis=1)
    mean, se = per_replica_mean(per_band)
    return bool(np.all(np.abs(mean - 1.0) <= Z * se + PSD_BIAS)), mean


def test_power_spectral_density_matches_dryden(gusts):
    # scipy's one-sided density per Hz (Welch uses the same scaling) integrates to the mean square:
    # exactly so for the boxcar periodogram (Parseval)
    f, P = scipy.signal.periodogram(gusts[:4], fs=1.0 / DT, window="boxcar", detrend=False, axis=-1)
    # scipy's FFT (pocketfft: no BLAS) against a mean: ~log2(N) eps = 3e-15 relative, 4e-16 measured under
    # every kernel (the gusts themselves come from BLAS 2x2 products, so their bits are the kernel's)
    np.testing.assert_allclose(P.sum(axis=-1) * (f[1] - f[0]), (gusts[:4] ** 2).mean(axis=-1), rtol=1e-10)
    for axis in range(3):
        passed, ratios = psd_check(gusts[:, axis], PHI[axis], SIGMA[axis], T[axis])
        assert passed, (axis, ratios)


def test_psd_check_rejects_white_noise_and_a_first_order_lateral(gusts):
    """Negative controls: white noise of the same variance, and a first-order (Ornstein-Uhlenbeck)
    process with the lateral axis's sigma and L in place of the second-order lateral filter."""
    rng = np.random.default_rng(7)
    white = SIGMA[1] * rng.standard_normal((R, N))
    assert white.std() == pytest.approx(gusts[:, 1].std(), rel=0.05)
    assert not psd_check(white, phi_v, SIGMA[1], T[1])[0]
    a = math.exp(-DT / T[1])
    ou = scipy.signal.lfilter([SIGMA[1] * math.sqrt(1 - a * a)], [1.0, -a], rng.standard_normal((R, N + BURN_IN)))
    ou = ou[:, BURN_IN:]
    assert psd_check(ou, phi_u, SIGMA[1], T[1])[0]  # it is a correct longitudinal process ...
    assert not psd_check(ou, phi_v, SIGMA[1], T[1])[0]  # ... but not a lateral one


# ----------------------------------------------------------------------- drag


def test_drag_sign_magnitude_and_zero():
    a = drag_acceleration([5.0, 0.0, 0.0], np.zeros(3), 0.7, 1.0, 0.01)
    assert a[0] > 0 and a[1] == a[2] == 0  # at rest in a +x wind: pushed +x
    # rho C_d A / (2 m) = 1.225 * 1.0 * 0.01 / 1.4 = 0.00875 1/m; |u - v| = 5 m/s; times (3, 4, 0)
    a = drag_acceleration([3.0, 4.0, 0.0], np.zeros(3), 0.7, 1.0, 0.01)
    np.testing.assert_allclose(a, [0.13125, 0.175, 0.0], rtol=1e-12)
    v = np.array([[1.0, -2.0, 3.0], [0.0, 0.0, 0.0]])
    assert not drag_acceleration(v, v, 0.7, 1.0, 0.01).any()
    assert drag_acceleration(np.zeros(3), [2.0, 0.0, 0.0], 0.7, 1.0, 0.01, air_density=0.0).tolist() == [0, 0, 0]


def test_drag_is_the_momentum_fields_airframe_law():
    """MomentumWake's airframe term is drag(u_wake, v) - drag(0, v) with this law."""
    field = MomentumWake(rotors=False)
    rng = np.random.default_rng(3)
    p_a = np.array([0.0, 0.0, 2.5])
    R_a = np.eye(3)
    p_b = p_a + np.column_stack([rng.uniform(-0.3, 0.3, (8, 2)), rng.uniform(-1.5, -0.3, 8)])
    v_b = rng.uniform(-1.0, 1.0, (8, 3))
    u = field.wind(p_a, R_a, p_b)
    args = (field.follower_mass, field.drag_coefficient, field.drag_area, field.air_density)
    law = drag_acceleration(u, v_b, *args) - drag_acceleration(np.zeros(3), v_b, *args)
    np.testing.assert_allclose(field(p_a, np.zeros(3), R_a, p_b, v_b), law, rtol=1e-12, atol=1e-14)


finite = st.floats(-1e3, 1e3, allow_nan=False)
vec = st.tuples(finite, finite, finite)


@settings(max_examples=200, deadline=None)
@given(vec, vec, st.floats(1e-3, 1e3), st.floats(0.0, 10.0), st.floats(0.0, 10.0), st.floats(0.0, 10.0))
def test_drag_is_finite_and_opposes_the_relative_motion(u, v, mass, cd, area, rho):
    a = drag_acceleration(np.array(u), np.array(v), mass, cd, area, rho)
    assert a.shape == (3,) and np.all(np.isfinite(a))
    rel = np.array(u) - np.array(v)
    assert a @ rel >= 0.0  # pushes the vehicle toward the air's velocity
    np.testing.assert_allclose(drag_acceleration(np.array(v), np.array(u), mass, cd, area, rho), -a)
