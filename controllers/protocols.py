"""What the simulator asks of an outer-loop controller (`Controller`), in the layer the simulator builds on.

`sim.simulator.Simulator(controller=...)` calls ``command_setpoint`` once per controller tick on the
readable path and records ``describe()`` in every log's provenance. The fused tick runs the built-in
`controllers.lqr.FeedbackLinearisedLQR` and any controller with a compiled form, ``compiled_controller(W, V)``
(`controllers.compiled`). docs/extending.md, "A new controller", has a recipe of each.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # the types only: the protocol loads no controller
    from controllers.lqr import ControllerState, Setpoint
    from downwash_core.state import RefSample

__all__ = ["Controller"]


@runtime_checkable
class Controller(Protocol):
    """The outer loop: the estimated state, the reference and the predicted downwash in, the setpoint out.

    `isinstance(x, Controller)` checks that both methods exist (not their signatures). A controller
    may also offer ``reset(worlds)``, for state of its own (an integral) that starts afresh with a world.
    """

    def command_setpoint(self, state: ControllerState, ref: RefSample, f_hat: np.ndarray, out: Setpoint,
                         residual: np.ndarray | None = None, override: np.ndarray | None = None,
                         lookahead: float = 0.0) -> None:
        """Fill `out` (`controllers.lqr.Setpoint`: acc, yaw_rate, thrust, rot, batched (W, V, ...)) from
        `state` (`controllers.lqr.ControllerState`), `ref` (`downwash_core.state.RefSample`) and `f_hat`
        (W, V, 3) m/s^2; `residual` (W, V, 3) m/s^2 is added to the command, `override` replaces it where
        finite, and the heading is aimed `lookahead` s ahead."""

    def describe(self) -> dict[str, Any]:
        """Stable provenance: its type and settings (no addresses)."""
