"""A disturbance observer: the external acceleration estimated from what the vehicle felt.

The generic tool a control engineer reaches for before any learned model. After every
controller tick the observer measures the force each vehicle felt over the tick before,

    d_meas = (v_est(t_k) - v_est(t_k-1)) / (t_k - t_k-1) - u_cmd(t_k-1),

from the motion capture's estimated velocities and the command applied (what a lab has at the
control rate), and low-passes it with a first-order filter of bandwidth ``bandwidth`` (rad/s):

    d_hat <- d_hat + (1 - exp(-bandwidth dt)) (d_meas - inner_held - d_hat),

so a constant disturbance is estimated with the time constant 1 / bandwidth (the estimate after
n ticks of dt is d (1 - exp(-bandwidth n dt))). Its prediction is ``inner + d_hat``: with no inner
predictor (``DisturbanceObserver()``, the ``dob`` condition) the observer alone compensates; with a
learned model inside (``<model>_dob``) the model is the feed-forward and the observer estimates
only what the model missed (``inner_held``: the inner prediction held through the measured tick).
Because the command ``u`` includes the compensation, ``a - u`` is the whole disturbance whatever
is compensated, as for the labels (`downwash.labels`).

It is a stateful predictor (`sim.predictor`): ``reset(worlds)`` forgets those worlds, ``due=``
says which worlds' prediction is due, and ``observe(t, vel_est, u_cmd)`` runs after every tick.
It flies the simulator's readable path (the fused tick runs no stateful predictor but a guard).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from downwash_core import libm
from downwash_core.errors import ConfigError
from downwash_core.state import VehicleStates
from sim.predictor import ZeroPredictor, is_stateful

__all__ = ["DisturbanceObserver", "DEFAULT_BANDWIDTH", "bandwidth_for"]

# rad/s (a time constant of 0.125 s): chosen once on the staged collection's training flights, never
# on a test flight, by `python -m experiments.observer_bandwidth` (results/observer_bandwidth.json)
DEFAULT_BANDWIDTH = 8.0  # under the paper's LQR; each controller states its own (`bandwidth_for`)


def bandwidth_for(controller: Any) -> float:
    """The observer's bandwidth under `controller`, rad/s: its ``observer_bandwidth`` (chosen for it as
    `DEFAULT_BANDWIDTH` was for the LQR: the observer estimates what the command misses, so the best
    bandwidth depends on the controller), else `DEFAULT_BANDWIDTH` (None: the default LQR)."""
    return float(getattr(controller, "observer_bandwidth", DEFAULT_BANDWIDTH))


class DisturbanceObserver:
    """``inner`` (a predictor, None: none) plus a low-passed estimate of what it misses (module doc).

    bandwidth: rad/s, the first-order filter's (the estimate's time constant is 1 / bandwidth);
    bound: m/s^2, the largest estimate magnitude applied per vehicle (a measurement glitch
    cannot command more), None: unbounded.
    """

    stateful = True

    def __init__(self, inner: Any = None, bandwidth: float = DEFAULT_BANDWIDTH, bound: float | None = 20.0):
        if not (isinstance(bandwidth, (int, float)) and not isinstance(bandwidth, bool) and math.isfinite(bandwidth)
                and bandwidth > 0):
            raise ConfigError(f"bandwidth: expected a finite number > 0 rad/s, got {bandwidth!r}")
        if bound is not None and not (isinstance(bound, (int, float)) and bound > 0):
            raise ConfigError(f"bound: expected a number > 0 m/s^2 or None, got {bound!r}")
        self.inner = ZeroPredictor() if inner is None else inner
        self.bandwidth, self.bound = float(bandwidth), None if bound is None else float(bound)
        self._estimate: np.ndarray | None = None  # (W, V, 3) d_hat
        self._last_inner: np.ndarray | None = None  # (W, V, 3) the inner prediction of the last due call
        self._held = self._vel = self._cmd = None  # (W, V, 3) each, as of the last tick seen
        self._t: np.ndarray | None = None  # (W,) the last tick seen; NaN: none since reset

    def describe(self) -> dict[str, Any]:
        inner = getattr(self.inner, "describe", None)
        return {"type": "DisturbanceObserver", "bandwidth": self.bandwidth, "bound": self.bound,
                "inner": inner() if callable(inner) else type(self.inner).__name__}

    def for_vehicles(self, kinds: Any) -> "DisturbanceObserver":
        """The observer around its inner predictor told the scene's vehicle kinds (`sim.vehicle_params.told_kinds`)."""
        bind = getattr(self.inner, "for_vehicles", None)
        inner = bind(kinds) if callable(bind) else self.inner
        return self if inner is self.inner else DisturbanceObserver(inner, self.bandwidth, self.bound)

    def _arrays(self, W: int, V: int) -> None:
        if self._estimate is None or self._estimate.shape[:2] != (W, V):
            self._estimate, self._last_inner = np.zeros((W, V, 3)), np.zeros((W, V, 3))
            self._held = np.zeros((W, V, 3))
            self._vel, self._cmd = np.zeros((W, V, 3)), np.zeros((W, V, 3))
            self._t = np.full(W, np.nan)

    def reset(self, worlds: Any = None) -> None:
        """These worlds (None: all) start afresh: no estimate, no tick seen."""
        rows = slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64)
        if self._estimate is not None:
            for a in (self._estimate, self._last_inner, self._held, self._vel, self._cmd):
                a[rows] = 0.0
            self._t[rows] = np.nan
        if is_stateful(self.inner):
            self.inner.reset(worlds)

    @property
    def estimate(self) -> np.ndarray | None:
        """(W, V, 3) m/s^2 the current estimate of what the inner predictor misses (None before a call)."""
        return self._estimate

    def __call__(self, estimated: VehicleStates, true: VehicleStates | None = None,
                 due: np.ndarray | None = None) -> np.ndarray:
        when = {"due": due} if is_stateful(self.inner) else {}
        inner = np.asarray(self.inner(estimated, true, **when), dtype=np.float64)
        W, V = inner.shape[:2]
        self._arrays(W, V)
        rows = slice(None) if due is None else np.asarray(due, dtype=bool)
        self._last_inner[rows] = inner[rows]
        estimate = self._estimate
        if self.bound is not None:
            norm = np.sqrt(np.sum(estimate * estimate, axis=-1, keepdims=True))
            estimate = estimate * np.minimum(1.0, self.bound / np.maximum(norm, 1e-300))
        return inner + estimate

    def observe(self, t: np.ndarray, vel_est: np.ndarray, u_cmd: np.ndarray) -> None:
        """After each tick, from its row: t (W,) s, vel_est (W, V, 3) m/s at its start, u_cmd (W, V, 3)
        m/s^2 applied during it. The force of the tick before, less the inner prediction held through
        it, moves the estimate (module doc); a world with no tick seen since reset, or a non-finite
        measurement, leaves it."""
        if self._estimate is None or len(self._estimate) != len(t):
            return  # (no call yet in these worlds)
        dt = t - self._t
        seen = np.isfinite(dt) & (dt > 0)
        step = np.where(seen, dt, 1.0)[:, None, None]
        missed = (vel_est - self._vel) / step - self._cmd - self._held
        ok = seen[:, None] & np.isfinite(missed).all(axis=-1)
        gain = 1.0 - libm.exp(-self.bandwidth * np.where(seen, dt, 0.0))[:, None, None]
        self._estimate[:] = np.where(ok[..., None], self._estimate + gain * (missed - self._estimate), self._estimate)
        self._held[:] = self._last_inner  # (the inner prediction held through the tick just flown)
        self._vel[:], self._cmd[:] = vel_est, u_cmd
        self._t[:] = t
