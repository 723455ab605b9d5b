"""Different controllers in different worlds of one batch (one batch, many conditions).

The experiments fly every condition of a table as one batch of worlds; most conditions differ
only in their predictor (`sim.predictor.PerWorldPredictor` routes those), some in their
controller (the LQR with integral action, the lab controllers). `PerWorldController` routes
each group of worlds to its controller: each sees only its worlds' rows, and its state
(an integral, a filter) is reset with them.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from controllers.lqr import ControllerState, Setpoint
from downwash_core.errors import ConfigError
from downwash_core.state import RefSample

__all__ = ["PerWorldController"]


class PerWorldController:
    """controllers[i] flies the worlds where ``assignment == i``."""

    def __init__(self, controllers: Sequence[Any], assignment: Any):
        assignment = np.asarray(assignment)
        if assignment.ndim != 1 or not np.issubdtype(assignment.dtype, np.integer):
            raise ConfigError(f"assignment: expected a 1-D array of controller indices, got {assignment!r}")
        if assignment.size and (assignment.min() < 0 or assignment.max() >= len(controllers)):
            raise ConfigError(f"assignment: indices must lie in [0, {len(controllers) - 1}], "
                              f"got [{assignment.min()}, {assignment.max()}]")
        self.controllers = list(controllers)
        self.groups = [np.flatnonzero(assignment == i) for i in range(len(controllers))]
        self.n_worlds = assignment.size

    def describe(self) -> dict[str, Any]:
        return {"type": type(self).__name__, "controllers": [
            c.describe() if callable(getattr(c, "describe", None)) else type(c).__name__ for c in self.controllers],
            "worlds": [g.tolist() for g in self.groups]}

    def reset(self, worlds: Any = None) -> None:
        """Reset the controllers with state in these worlds (None: all), each told its own rows."""
        for controller, group in zip(self.controllers, self.groups):
            if callable(getattr(controller, "reset", None)):
                controller.reset(None if worlds is None else np.flatnonzero(np.isin(group, worlds)))

    def command_setpoint(self, state: ControllerState, ref: RefSample, f_hat: np.ndarray, out: Setpoint,
                         residual: np.ndarray | None = None, override: np.ndarray | None = None,
                         lookahead: float = 0.0) -> None:
        if state.pos.shape[0] != self.n_worlds:
            raise ValueError(f"PerWorldController built for {self.n_worlds} worlds, called with {state.pos.shape[0]}")
        for controller, w in zip(self.controllers, self.groups):
            if not w.size:
                continue
            part = Setpoint(*(a[w] for a in out))
            controller.command_setpoint(ControllerState(*(a[w] for a in state)), RefSample(*(a[w] for a in ref)),
                                        f_hat[w], part, None if residual is None else residual[w],
                                        None if override is None else override[w], lookahead)
            for dst, src in zip(out, part):
                dst[w] = src
