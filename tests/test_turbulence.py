"""Turbulence statistics against the SPEC (DESIGN, README "The design in brief").

The spec: the turbulence on the downwash is zero-mean, time-correlated
(Ornstein-Uhlenbeck, correlation time 0.05 s), with a standard deviation per axis of
10 % of the local mean force magnitude. The two numbers are written here, not read
from the code's constants, so that a constant that drifts from the spec fails.

Each statistic is measured with an estimator that does not use the code's law (sample
standard deviation, autocorrelation fitted or integrated, sample mean, cross
correlation), and compared with the spec within a few of its standard errors; the
negative controls show that the same checks reject a process that is off the spec.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import downwash_trajectories
from sim.flight import fly
from sim.scene import build_scene
from sim.turbulence import OUTurbulence

SPEC_INTENSITY = 0.10  # -, std per axis / |local mean force|
SPEC_TAU = 0.05  # s, correlation time

DT = 0.01  # s, step of the direct test (the autopilot grid on which the simulator samples it)
N_SAMPLES = 200_000
BURN_IN = 1_000  # samples (10 s = 200 correlation times): the state starts at 0, not stationary
MEAN = np.array([0.3, -0.4, -2.5])  # m/s^2, unequal components: the std must scale with |MEAN|, per axis
Z = 5.0  # tolerance in standard errors for the 200k-sample direct test


# ----------------------------------------------------------------------- estimators


def autocorrelation(x: np.ndarray, lags) -> np.ndarray:
    """Sample autocorrelation (len(lags),) of a 1-D series at integer lags >= 1."""
    x = x - x.mean()
    var = np.dot(x, x)
    return np.array([np.dot(x[:-k], x[k:]) / var for k in lags])


def tau_from_fit(x: np.ndarray, dt: float, max_lag: int = 7) -> float:
    """Correlation time from a least-squares fit of log rho(k dt) = -k dt / tau over lags
    1..max_lag (0.01-0.07 s at dt = 0.01 s, where rho is 0.8-0.25: far above its noise)."""
    lag_t = dt * np.arange(1, max_lag + 1)
    rho = autocorrelation(x, range(1, max_lag + 1))
    return float(-np.dot(lag_t, lag_t) / np.dot(lag_t, np.log(rho)))


def tau_from_integral(x: np.ndarray, dt: float, horizon: float = 0.5) -> float:
    """Integral time scale: the trapezoidal integral of the autocorrelation up to `horizon` s
    (10 correlation times: the truncated tail is e^-10). For an exponential it equals tau
    (the trapezoid rule over-reads by (1 + a) / (2 (1 - a)) dt - tau = +0.3 % at dt = 0.01 s)."""
    m = int(round(horizon / dt))
    return float(dt * (0.5 + autocorrelation(x, range(1, m + 1)).sum()))


def batch_standard_error(estimator, x: np.ndarray, n_blocks: int = 20) -> float:
    """Standard error of estimator(x) from its spread over n_blocks contiguous blocks (batch means)."""
    values = [estimator(block) for block in np.array_split(x, n_blocks)]
    return float(np.std(values, ddof=1) / math.sqrt(n_blocks))


def direct_series(turbulence: OUTurbulence, seed: int = 0) -> np.ndarray:
    """apply(MEAN, state) - MEAN (N_SAMPLES, 3) m/s^2 from the readable law, stepped at DT."""
    rng = np.random.default_rng(seed)
    xi = rng.standard_normal((BURN_IN + N_SAMPLES, 3))
    state = np.zeros(3)
    states = np.empty((BURN_IN + N_SAMPLES, 3))
    for k in range(BURN_IN + N_SAMPLES):
        state = turbulence.step(state, xi[k], DT)
        states[k] = state
    return turbulence.apply(MEAN, states[BURN_IN:]) - MEAN


def spec_violations(fluct: np.ndarray, scale: float, dt: float, z: float = Z) -> list[str]:
    """The spec checks that a fluctuation series (N, 3) fails; `scale` is |mean force|.

    Standard errors are those of an AR(1) series with the spec's correlation,
    a = exp(-dt / tau) (checked by Monte Carlo over 200 series of N = 200k: each within the
    +/-5 % sampling error of that check):
      sample std, relative: sqrt((1 + a^2) / (1 - a^2) / (2 N))     (0.36 % here)
      sample mean, in stds: sqrt((1 + a) / (1 - a) / N)             (0.71 %)
      cross correlation of two independent axes: sqrt((1 + a^2) / (1 - a^2) / N)   (0.005)
    and for the two correlation-time estimators the batch-means error of the series itself.
    """
    n = fluct.shape[0]
    a = math.exp(-dt / SPEC_TAU)
    ratio = (1 + a * a) / (1 - a * a)
    sigma = SPEC_INTENSITY * scale
    failed = []
    for axis, x in enumerate(fluct.T):
        std = x.std()
        if abs(std / sigma - 1) > z * math.sqrt(ratio / (2 * n)):
            failed.append(f"std[{axis}] = {std / scale:.4f} |mean| (spec {SPEC_INTENSITY})")
        if abs(x.mean()) > z * sigma * math.sqrt((1 + a) / (1 - a) / n):
            failed.append(f"mean[{axis}] = {x.mean() / sigma:.4f} sigma (spec 0)")
        for name, estimator in (("tau_fit", tau_from_fit), ("tau_int", tau_from_integral)):
            tau = estimator(x, dt)
            se = batch_standard_error(lambda b: estimator(b, dt), x)
            assert se < 0.05 * tau, f"{name}: the estimator is not informative (SE {se:.4g} s of {tau:.4g} s)"
            if abs(tau - SPEC_TAU) > z * se:
                failed.append(f"{name}[{axis}] = {tau:.4f} s +/- {se:.4f} (spec {SPEC_TAU})")
    for i, j in ((0, 1), (0, 2), (1, 2)):
        c = np.corrcoef(fluct[:, i], fluct[:, j])[0, 1]
        if abs(c) > z * math.sqrt(ratio / n):
            failed.append(f"corr[{i},{j}] = {c:.4f} (spec 0)")
    return failed


# ----------------------------------------------------------------------- direct law


@pytest.fixture(scope="module")
def default_series() -> np.ndarray:
    return direct_series(OUTurbulence())


def test_default_turbulence_meets_the_spec(default_series):
    """Per axis: std = 0.10 |mean|, zero mean, correlation time 0.05 s by two estimators
    (fitted and integrated autocorrelation); the axes are uncorrelated."""
    assert spec_violations(default_series, np.linalg.norm(MEAN), DT) == []


def test_default_turbulence_autocorrelation_is_exponential(default_series):
    """The autocorrelation at 0.01-0.10 s is exp(-lag / 0.05 s) (Bartlett standard error of an
    AR(1) lag-k estimate: sqrt((1 + a^2)(1 - a^2k) / (1 - a^2) - 2 k a^2k) / N), 5 of them)."""
    n = default_series.shape[0]
    lags = np.arange(1, 11)
    a = math.exp(-DT / SPEC_TAU)
    want = np.exp(-lags * DT / SPEC_TAU)
    se = np.sqrt(((1 + a * a) * (1 - a ** (2 * lags)) / (1 - a * a) - 2 * lags * a ** (2 * lags)) / n)
    for x in default_series.T:
        got = autocorrelation(x, lags)
        assert np.all(np.abs(got - want) <= Z * se), (got, want)


@pytest.mark.parametrize(
    "turbulence, expected",
    [
        (OUTurbulence(intensity=0.2), {"std"}),
        (OUTurbulence(time_constant=0.2), {"tau_fit", "tau_int"}),
        (OUTurbulence(intensity=0.05, time_constant=0.025), {"std", "tau_fit", "tau_int"}),
    ],
)
def test_checks_reject_turbulence_off_the_spec(turbulence, expected):
    """Negative control: the same checks flag twice or half the spec's intensity and time constant."""
    failed = spec_violations(direct_series(turbulence), np.linalg.norm(MEAN), DT)
    flagged = {f.split("[")[0] for f in failed}
    assert expected <= flagged, failed
    for check in expected:  # on every axis
        assert sum(f.startswith(check + "[") for f in failed) == 3, failed


def test_checks_reject_a_biased_or_cross_correlated_series(default_series):
    """Negative control of the mean and cross-correlation checks, on the spec's own series
    with a 0.05 sigma offset on x, or with y mixed into z (correlation 0.1)."""
    scale = np.linalg.norm(MEAN)
    sigma = SPEC_INTENSITY * scale
    biased = default_series + [0.05 * sigma, 0.0, 0.0]  # 7 standard errors of the mean
    assert [f for f in spec_violations(biased, scale, DT) if f.startswith("mean")] == [
        f"mean[0] = {biased[:, 0].mean() / sigma:.4f} sigma (spec 0)"
    ]
    mixed = default_series.copy()
    mixed[:, 2] = math.sqrt(1 - 0.1**2) * mixed[:, 2] + 0.1 * mixed[:, 1]  # same std, corr 0.1
    assert any(f.startswith("corr[1,2]") for f in spec_violations(mixed, scale, DT))


# ------------------------------------------------------------------ through the simulator

FLIGHT_S = 60.0
SETTLE_ROWS = 50  # 1 s at 50 Hz: the turbulence state starts at 0 (and the follower settles)
Z_SIM = 4.0  # tolerance in standard errors for the ~2950-row flight


def _hover_flight(turbulence: OUTurbulence | None = None):
    """The follower hovering 0.6 m directly below a leader hovering at (0, 0, 2.5) m."""
    leader = np.array([0.0, 0.0, 2.5])
    reference = downwash_trajectories.stack(
        [downwash_trajectories.Hover(leader, n_worlds=1), downwash_trajectories.Hover(leader - [0.0, 0.0, 0.6], n_worlds=1)]
    )
    components = {} if turbulence is None else {"turbulence": turbulence}
    (log,) = fly(build_scene(), reference, [0], FLIGHT_S, **components)
    assert log.meta["status"] == 0 and len(log) == round(FLIGHT_S / 0.02)
    return log


def _flight_statistics(log) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Per axis: std and lag-1 autocorrelation of (applied - mean) / |mean| on the follower,
    its mean, and the number of rows used (50 Hz rows after the first second)."""
    f = log.meta["follower"]
    mean = log["field_mean"][SETTLE_ROWS:, f]
    fluct = log["field_applied"][SETTLE_ROWS:, f] - mean
    norm = np.linalg.norm(mean, axis=-1, keepdims=True)
    assert np.all(norm > 0.5)  # the follower is in the wake all along: the ratio is well defined
    x = fluct / norm  # the spec's ratio, per row: the mean force sags as the follower is pushed down
    lag1 = np.array([autocorrelation(col, [1])[0] for col in x.T])
    return x.std(axis=0), lag1, x.mean(axis=0), x.shape[0]


@pytest.fixture(scope="module")
def hover_log():
    return _hover_flight()


def _flight_tolerances(n: int) -> tuple[float, float, float, float]:
    """(lag-1 autocorrelation a^2 of the 50 Hz rows under the spec, and the standard errors of
    the std ratio, the lag-1 estimate and the mean) for n rows of an AR(1) series with that a^2:
    std: a rel. SE sqrt((1 + a^4) / (1 - a^4) / (2 n)) = 2.1 % for n = 2950; lag 1 (Bartlett):
    sqrt((1 - a^4) / n) = 0.014; mean: sqrt((1 + a^2) / (1 - a^2) / n) = 0.041 sigma."""
    rho = math.exp(-0.02 / SPEC_TAU)  # rows 0.02 s apart
    se_std = SPEC_INTENSITY * math.sqrt((1 + rho**2) / (1 - rho**2) / (2 * n))
    se_lag1 = math.sqrt((1 - rho**2) / n)
    se_mean = SPEC_INTENSITY * math.sqrt((1 + rho) / (1 - rho) / n)
    return rho, se_std, se_lag1, se_mean


def test_flight_turbulence_on_the_follower_meets_the_spec(hover_log):
    """Per axis of the follower's applied - mean field over ~59 s of hover: std / |mean| = 0.10,
    lag-1 (0.02 s) autocorrelation exp(-0.02 / 0.05) = 0.670, mean 0; all within 4 standard errors."""
    std, lag1, mean, n = _flight_statistics(hover_log)
    rho, se_std, se_lag1, se_mean = _flight_tolerances(n)
    assert n > 2900
    np.testing.assert_array_less(np.abs(std - SPEC_INTENSITY), Z_SIM * se_std)
    np.testing.assert_array_less(np.abs(lag1 - rho), Z_SIM * se_lag1)
    np.testing.assert_array_less(np.abs(mean), Z_SIM * se_mean)


def test_flight_leader_feels_no_field(hover_log):
    """The leader is above the follower, so it is outside every wake: its field is exactly 0."""
    lead = hover_log.meta["leader"]
    assert lead != hover_log.meta["follower"]
    assert np.all(hover_log["field_mean"][:, lead] == 0.0)
    assert np.all(hover_log["field_applied"][:, lead] == 0.0)


@pytest.mark.parametrize(
    "turbulence, rejected",
    [(OUTurbulence(intensity=0.2), "std"), (OUTurbulence(time_constant=0.2), "lag1")],
)
def test_flight_checks_reject_turbulence_off_the_spec(turbulence, rejected):
    """Negative control: through the simulator, twice the intensity or four times the time
    constant is rejected by the same checks."""
    std, lag1, _, n = _flight_statistics(_hover_flight(turbulence))
    rho, se_std, se_lag1, _ = _flight_tolerances(n)
    if rejected == "std":
        assert np.all(np.abs(std - SPEC_INTENSITY) > Z_SIM * se_std), std
    else:
        assert np.all(np.abs(lag1 - rho) > Z_SIM * se_lag1), lag1
