"""The predictor slot: how a downwash model reaches the control loop.

`sim` never imports `downwash`; a learned model enters through this small
interface. The stepping loop calls the predictor at 45 Hz and holds the result
between calls; the controller subtracts it: `u = a_ref - K (x - x_ref) - f_hat`.
"""

from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from core.errors import ConfigError
from core.state import VehicleStates
from sim.field import pairwise_field

__all__ = [
    "VehicleStates",
    "Predictor",
    "ZeroPredictor",
    "OraclePredictor",
    "PerWorldPredictor",
]


@runtime_checkable
class Predictor(Protocol):
    """Anything that predicts the downwash acceleration on each vehicle.

    `estimated` is what the vehicles know (Kalman-filtered motion capture);
    `true` is the simulator's state, for oracles and diagnostics only.
    Returns (W, V, 3) m/s^2, world frame, the summed effect of all other vehicles.
    """

    def __call__(self, estimated: VehicleStates, true: VehicleStates) -> np.ndarray: ...


class ZeroPredictor:
    """No model: the baseline controller."""

    def __call__(self, estimated: VehicleStates, true: VehicleStates) -> np.ndarray:
        return np.zeros_like(estimated.pos)


class OraclePredictor:
    """The true mean field (no turbulence) at the true state: the best any model can do."""

    def __init__(self, field):
        self.field = field

    def __call__(self, estimated: VehicleStates, true: VehicleStates) -> np.ndarray:
        return pairwise_field(self.field, true.pos, true.vel, true.rot)


class PerWorldPredictor:
    """Routes groups of worlds to different predictors (one batch, many conditions).

    predictors[i] serves the worlds where `assignment == i`.
    """

    def __init__(self, predictors: Sequence[Predictor], assignment: np.ndarray):
        assignment = np.asarray(assignment)
        if assignment.ndim != 1:
            raise ConfigError(f"assignment: expected a 1-D array of predictor indices, got shape {assignment.shape}")
        if assignment.size and (assignment.min() < 0 or assignment.max() >= len(predictors)):
            raise ConfigError(
                f"assignment: indices must lie in [0, {len(predictors) - 1}], "
                f"got [{assignment.min()}, {assignment.max()}]"
            )
        self.predictors = list(predictors)
        self.groups = [np.flatnonzero(assignment == i) for i in range(len(predictors))]
        self.n_worlds = assignment.size

    def __call__(self, estimated: VehicleStates, true: VehicleStates) -> np.ndarray:
        if estimated.pos.shape[0] != self.n_worlds:
            raise ValueError(f"PerWorldPredictor built for {self.n_worlds} worlds, called with {estimated.pos.shape[0]}")
        out = np.zeros_like(estimated.pos)
        for predictor, worlds in zip(self.predictors, self.groups):
            if worlds.size and not isinstance(predictor, ZeroPredictor):
                out[worlds] = predictor(estimated.select(worlds), true.select(worlds))
        return out
