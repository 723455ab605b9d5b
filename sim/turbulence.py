"""Turbulence on the downwash: a time-correlated, zero-mean fluctuation that scales with the wake.

`OUTurbulence` is an Ornstein-Uhlenbeck process per vehicle and axis, sampled on the
autopilot grid (exact discretisation, unit stationary variance):

    x[k+1] = a x[k] + b xi[k],   a = exp(-dt / time_constant),  b = sqrt(1 - a^2),  xi ~ N(0, 1)
    applied = mean + intensity |mean| x

so the fluctuation has standard deviation `intensity |mean|` per axis (10 % of the
local mean force by default, zero outside the wake) and correlation time
`time_constant`. The simulator runs this law inside its compiled per-tick pass with
the coefficients of `coefficients(dt)`; `step` and `apply` are the readable law,
and a test checks the compiled pass against them. A new turbulence of this linear
family only needs its own `coefficients` and `intensity`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError

__all__ = ["OUTurbulence"]


@dataclass(frozen=True)
class OUTurbulence:
    """Ornstein-Uhlenbeck turbulence whose standard deviation scales with the mean field."""

    intensity: float = 0.10  # -, std per axis as a fraction of the local mean force magnitude
    time_constant: float = 0.05  # s, correlation time

    def __post_init__(self) -> None:
        if not 0.0 <= self.intensity <= 1.0:
            raise ConfigError(f"turbulence intensity: allowed 0-1, got {self.intensity}")
        if not self.time_constant > 0:
            raise ConfigError(f"turbulence time_constant: must be > 0 s, got {self.time_constant}")

    def coefficients(self, dt: float) -> tuple[float, float]:
        """(a, b) of `x[k+1] = a x[k] + b xi[k]` for samples every dt (s)."""
        a = math.exp(-dt / self.time_constant)
        return a, math.sqrt(1.0 - a * a)

    def step(self, state: np.ndarray, xi: np.ndarray, dt: float) -> np.ndarray:
        """The next state (..., 3) from `state` and standard normal draws `xi` (..., 3)."""
        a, b = self.coefficients(dt)
        return a * state + b * xi

    def apply(self, mean: np.ndarray, state: np.ndarray) -> np.ndarray:
        """The applied field (..., 3) m/s^2: the mean field plus its scaled fluctuation."""
        return mean + self.intensity * np.linalg.norm(mean, axis=-1, keepdims=True) * state

    def describe(self) -> dict[str, Any]:
        return {"type": type(self).__name__, **asdict(self)}
