"""The outer-loop controllers by name: what an experiment's `--controller` flies.

    lqr        controllers.lqr.FeedbackLinearisedLQR, the default (the paper's)
    mellinger  controllers.crazyflie.MellingerController, Mellinger & Kumar 2011 with the Crazyflie firmware's gains
    pid        controllers.crazyflie.CrazyfliePID, the Crazyflie firmware's cascaded PID
    indi       controllers.indi.INDIController, outer-loop INDI with the LQR's bandwidth

Every controller commands accelerations (collective specific thrust and a desired attitude for
the autopilot, which applies each vehicle's own mass and inertia), and the gains are in
acceleration units: the firmware's force gains over the mass they were tuned with
(`controllers.crazyflie`). So one controller flies every vehicle kind with the same
closed loop, and a vehicle kind changes only what is stated relative to the vehicle: the
PID's thrust ceiling, the firmware's full thrust command, is the kind's thrust_to_weight g.
"""

from __future__ import annotations

from typing import Any, Callable

from downwash_core.errors import ConfigError
from downwash_core.registry import Registry

__all__ = ["CONTROLLERS", "CONTROLLER_NAMES", "DEFAULT_CONTROLLER", "make_controller"]


def _lqr(vehicle_kind: Any = None) -> Any:
    from controllers.lqr import FeedbackLinearisedLQR

    return FeedbackLinearisedLQR()


def _mellinger(vehicle_kind: Any = None) -> Any:
    from controllers.crazyflie import MellingerController

    return MellingerController()


def _pid(vehicle_kind: Any = None) -> Any:
    from controllers.crazyflie import CrazyfliePID

    return CrazyfliePID(thrust_max_g=None if vehicle_kind is None else vehicle_kind.thrust_to_weight)


def _indi(vehicle_kind: Any = None) -> Any:
    from controllers.indi import INDIController

    return INDIController()


# name -> factory(vehicle_kind: a downwash_core.vehicles.VehicleKind or None) -> controller; plugins add theirs
CONTROLLERS = Registry("controller", group="controllers", objects=True, name_pattern=r"[a-z][a-z0-9_]*",
                       name_rule="lowercase letters, digits and underscores")
CONTROLLERS.register("lqr", _lqr, "controllers.lqr.FeedbackLinearisedLQR, the default (the paper's)")
CONTROLLERS.register("mellinger", _mellinger, "controllers.crazyflie.MellingerController, Mellinger & Kumar 2011")
CONTROLLERS.register("pid", _pid, "controllers.crazyflie.CrazyfliePID, the Crazyflie firmware's cascaded PID")
CONTROLLERS.register("indi", _indi, "controllers.indi.INDIController, outer-loop INDI with the LQR's bandwidth")
CONTROLLER_NAMES = ("lqr", "mellinger", "pid", "indi")  # the built-in ones (static: no plugin is loaded at import)
DEFAULT_CONTROLLER = "lqr"


def make_controller(name: str, vehicle_kind: Any = None) -> Any:
    """The controller `name` (one of `CONTROLLER_NAMES`) with its default gains, for vehicles of
    `vehicle_kind` (a name or `VehicleKind` of `downwash_core.vehicles`; None: any vehicle, see the
    module doc). ConfigError naming the allowed names or kinds."""
    factory: Callable[..., Any] | None = CONTROLLERS.get(name) if isinstance(name, str) else None
    if factory is None:
        raise ConfigError(f"controller: unknown {name!r}; allowed: {', '.join(CONTROLLERS)}")
    if vehicle_kind is not None:
        from downwash_core.vehicles import get_vehicle

        vehicle_kind = get_vehicle(vehicle_kind)
    return factory(vehicle_kind)
