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

from controllers.compiled import CompiledController, controller_function, run_step
from controllers.lqr import MAX_TILT_DEG, MIN_THRUST_G, ControllerState, Setpoint
from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, RATES
from downwash_core.state import RefSample

__all__ = ["PerWorldState", "LabController", "positive", "number_in", "three"]


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
    """A controller's memory between ticks: one float64 block (W, V, S), zero when fresh, and its named
    parts as views (W, V, *trailing), the parts side by side along the last axis in the order given.

    The block is what a compiled form hands the fused tick (`controllers.compiled`). Allocated (zeros) at
    the first `of(W, V)` and again when the batch's shape changes (a controller handed to another
    simulator starts fresh); `reset(worlds)` zeroes those worlds.
    """

    def __init__(self, **trailing: tuple[int, ...]):
        self._trailing = trailing
        self.width = sum(int(np.prod(shape)) for shape in trailing.values())
        self.block: np.ndarray | None = None
        self.arrays: dict[str, np.ndarray] | None = None

    def of(self, n_worlds: int, n_vehicles: int) -> np.ndarray:
        """The block (W, V, S) for this batch shape (allocated afresh when the shape changed)."""
        if self.block is None or self.block.shape[:2] != (n_worlds, n_vehicles):
            self.block = np.zeros((n_worlds, n_vehicles, self.width))
            self.arrays, start = {}, 0
            for name, shape in self._trailing.items():
                size = int(np.prod(shape))
                self.arrays[name] = self.block[:, :, start:start + size].reshape(n_worlds, n_vehicles, *shape)
                start += size
        return self.block

    def reset(self, worlds: Any = None) -> None:
        if self.block is not None:
            self.block[slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64)] = 0.0


_C_FUNCTIONS: dict[type, Any] = {}  # each lab controller class's C function, compiled at its first use


class LabController:
    """The controller interface of `controllers.lqr.FeedbackLinearisedLQR` around a compiled step, with its
    compiled form for the fused tick (`controllers.compiled`).

    Subclasses set `_state` (a `PerWorldState`), `_params` (their constants, float64, packed as their
    `step_function` reads them) and `step_function`, their law in the array form of
    `controllers.compiled` (numba-compiled). dt: s, the period of `command_setpoint` calls (the
    simulator's controller rate, `Rates.control_dt`), by which integrators and finite differences
    advance. max_tilt_deg, min_thrust_g: the limits of feedback linearisation, the LQR's by default.
    """

    _state: PerWorldState
    _params: np.ndarray
    step_function: Any  # the class's law in the array form (controllers.compiled), numba-compiled

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
        """The per-world arrays by name (views of the state block; None before the first command)."""
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
        run_step(type(self).step_function, state, ref, f_hat, out, residual, override, lookahead, self._state.of(W, V),
                 self._params)

    def compiled_controller(self, n_worlds: int, n_vehicles: int) -> CompiledController:
        """Its compiled form for a simulator of (W, V) (`controllers.compiled`): the class's C function, its
        constants and its state block (the one `reset` clears)."""
        cls = type(self)
        if cls not in _C_FUNCTIONS:
            _C_FUNCTIONS[cls] = controller_function(cls.step_function, self._state.width, len(self._params))
        return CompiledController(int(_C_FUNCTIONS[cls].address), self._params, self._state.of(n_worlds, n_vehicles))
