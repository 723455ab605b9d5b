"""What the lab controllers (`controllers.crazyflie`, `controllers.indi`) share.

Each keeps history (integrators, filters, a previous velocity) per world and vehicle, so a
world the simulator resets must start afresh while the others fly on: `PerWorldState` holds
those arrays, allocated at the first command for the batch's (W, V) and zeroed (zero means
"fresh") for the worlds `reset(worlds)` names. `LabController` is the interface of
`controllers.lqr.FeedbackLinearisedLQR.command_setpoint` around a compiled step, and
`finish_one` the last part of every step: the interface's `residual` and `override`, then
feedback linearisation with the LQR's limits (`controllers.lqr.attitude_setpoint`), so the
autopilot below receives collective specific thrust and a desired attitude from every
controller alike.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from controllers.lqr import MAX_TILT_DEG, MIN_THRUST_G, ControllerState, Setpoint, _setpoint_one
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_core.params import GRAVITY, RATES
from downwash_core.state import RefSample

__all__ = ["PerWorldState", "LabController", "finish_one", "positive", "number_in", "three"]


def _number(value: Any) -> float | None:
    """`value` as a float when it is a finite real number (NumPy's included, bool not), else None."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    x = float(value)
    return x if math.isfinite(x) else None


def positive(name: str, value: Any) -> float:
    """`value` as a float when finite and > 0; ConfigError naming `name` otherwise."""
    x = _number(value)
    if x is None or not x > 0:
        raise ConfigError(f"{name}: expected a finite number > 0, got {value!r}")
    return x


def number_in(name: str, value: Any, low: float, high: float, unit: str = "", low_closed: bool = False) -> float:
    """`value` as a float in (low, high) ([low, high) when `low_closed`); ConfigError naming `name`,
    the allowed range and `unit` otherwise."""
    x = _number(value)
    if x is None or not (low <= x if low_closed else low < x) or not x < high:
        raise ConfigError(f"{name}: allowed {'[' if low_closed else '('}{low:g}, {high:g}){' ' + unit if unit else ''}, "
                          f"got {value!r}")
    return x


def three(name: str, values: Any, strictly_positive: bool = False) -> tuple[float, float, float]:
    """`values` as 3 finite floats (x, y, z), each >= 0 (> 0 when `strictly_positive`); ConfigError
    naming `name` and what it takes otherwise."""
    items = list(values) if isinstance(values, (list, tuple, np.ndarray)) else None
    numbers = [_number(x) for x in items] if items is not None and len(items) == 3 else []
    bound = "> 0" if strictly_positive else ">= 0"
    if len(numbers) != 3 or any(x is None or x < 0 or (strictly_positive and x == 0) for x in numbers):
        raise ConfigError(f"{name}: expected 3 finite numbers {bound} (x, y, z), got {values!r}")
    return numbers[0], numbers[1], numbers[2]


class PerWorldState:
    """Named float64 arrays (W, V, *trailing) that a controller keeps between ticks, zero when fresh.

    Allocated (zeros) at the first `of(W, V)` and again when the batch's shape changes (a
    controller handed to another simulator starts fresh); `reset(worlds)` zeroes those worlds.
    """

    def __init__(self, **trailing: tuple[int, ...]):
        self._trailing = trailing
        self.arrays: dict[str, np.ndarray] | None = None

    def of(self, n_worlds: int, n_vehicles: int) -> dict[str, np.ndarray]:
        arrays = self.arrays
        if arrays is None or next(iter(arrays.values())).shape[:2] != (n_worlds, n_vehicles):
            arrays = {k: np.zeros((n_worlds, n_vehicles, *shape)) for k, shape in self._trailing.items()}
            self.arrays = arrays
        return arrays

    def reset(self, worlds: Any = None) -> None:
        if self.arrays is not None:
            index = slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64)
            for a in self.arrays.values():
                a[index] = 0.0


class LabController:
    """The controller interface of `controllers.lqr.FeedbackLinearisedLQR` around a compiled step.

    Subclasses set `_state` (a `PerWorldState`) and implement `_step`. dt: s, the period
    of `command_setpoint` calls (the simulator's controller rate, `Rates.control_dt`), by
    which integrators and finite differences advance. max_tilt_deg, min_thrust_g: the limits
    of feedback linearisation, the LQR's by default.
    """

    _state: PerWorldState

    def __init__(self, dt: float = RATES.control_dt, max_tilt_deg: float = MAX_TILT_DEG,
                 min_thrust_g: float = MIN_THRUST_G):
        self.dt = positive("dt", dt)
        self.max_tilt_deg = number_in("max_tilt_deg", max_tilt_deg, 0.0, 90.0, "deg")
        self.min_thrust_g = number_in("min_thrust_g", min_thrust_g, 0.0, 1.0, "g", low_closed=True)
        self._tan_tilt = math.tan(math.radians(self.max_tilt_deg))
        self._min_vertical = self.min_thrust_g * GRAVITY  # m/s^2

    def describe(self) -> dict[str, Any]:
        return {"type": type(self).__name__, "dt": self.dt, "max_tilt_deg": self.max_tilt_deg,
                "min_thrust_g": self.min_thrust_g}

    @property
    def state(self) -> dict[str, np.ndarray] | None:
        """The per-world arrays (None before the first command)."""
        return self._state.arrays

    def reset(self, worlds: Any = None) -> None:
        """These worlds (None: all) start afresh: integrators, filters and history cleared."""
        self._state.reset(worlds)

    def command_setpoint(self, state: ControllerState, ref: RefSample, f_hat: np.ndarray, out: Setpoint,
                         residual: np.ndarray | None = None, override: np.ndarray | None = None,
                         lookahead: float = 0.0) -> None:
        """One control period for (W, V, ...) float64 arrays: fills `out` (see `controllers.lqr.Setpoint`).

        f_hat (W, V, 3) m/s^2, the predicted downwash, is compensated; `residual` (W, V, 3) m/s^2 is
        added to the acceleration command and `override` replaces it where finite; the heading is
        the reference's `lookahead` s ahead (the attitude set-point is held for one period)."""
        W, V = state.pos.shape[:2]
        arrays = self._state.of(W, V)
        actions = (f_hat if residual is None else residual, f_hat if override is None else override,  # (unread when None)
                   residual is not None, override is not None)
        self._step(state, ref, f_hat, actions, lookahead, arrays, out)

    def _step(self, state: ControllerState, ref: RefSample, f_hat: np.ndarray, actions: tuple, lookahead: float,
              arrays: dict[str, np.ndarray], out: Setpoint) -> None:
        raise NotImplementedError


@njit
def finish_one(acc, w, i, residual, override, use_residual, use_override, yaw_des, tan_tilt, min_vertical, rot):
    """The end of one vehicle's step: acc[w, i] (W, V, 3) m/s^2 holds the controller's command (gravity
    excluded, the downwash compensated); `residual` is added, `override` replaces it where finite
    (flags, not None arguments, as the LQR's kernel), in place. Returns the collective specific
    thrust (m/s^2) and writes the desired attitude into rot[w, i] (feedback linearisation)."""
    for k in range(3):
        a = acc[w, i, k]
        if use_residual:
            a = a + residual[w, i, k]
        if use_override and np.isfinite(override[w, i, k]):
            a = override[w, i, k]
        acc[w, i, k] = a
    return _setpoint_one(acc[w, i, 0], acc[w, i, 1], acc[w, i, 2], yaw_des, tan_tilt, min_vertical, rot[w, i])
