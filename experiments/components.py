"""What an experiment's own flights are built from: the config file's tables ([lqr], [sim], [training],
[guard], [safety]) applied to their settings classes, and the controller --controller names.

`flight_components(args)` gives the `Simulator` keywords of an experiment's flights; the staged
collection behind its models always flies the defaults (part of its provenance and pipeline key).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any, Callable, Sequence, TypeVar

from downwash_core.errors import ConfigError
from experiments.common import one_line
from experiments.options import DEFAULT_CONTROLLER

__all__ = ["table", "built", "lqr_config", "sim_config", "safety_config", "flight_components", "check_controller",
           "controller_record", "flown_record", "training_config", "guard_config"]

A = TypeVar("A")


def table(args: Any, name: str) -> dict[str, Any]:
    """The checked values of the config file's [name] table for the run `args` ({} when it gives none);
    ConfigError when its experiment does not apply that table: a table is never silently ignored."""
    from experiments.config_file import check_table, refuse_table

    if name not in type(args).config_tables:
        raise ConfigError(refuse_table(name, type(args)))
    return check_table(name, args.tables.get(name, {}))


def built(name: str, make: Callable[..., A], *args: Any, **values: Any) -> A:
    """`make(*args, **values)`, its refusal of a table's values a ConfigError naming the table."""
    try:
        return make(*args, **values)
    except (ConfigError, ValueError, ArithmeticError) as e:  # (a LinAlgError is a ValueError)
        raise ConfigError(f"[{name}]: {one_line(e)}") from e


def lqr_config(args: Any) -> Any:
    """The outer loop of the experiment's flights: `controllers.lqr.LQRConfig` with the [lqr] table's values."""
    from controllers.lqr import LQRConfig

    return built("lqr", LQRConfig, **table(args, "lqr"))


def sim_config(args: Any) -> Any:
    """The experiment's `sim.simulator.SimConfig`, with the [sim] table's values."""
    from sim.simulator import SimConfig

    return built("sim", SimConfig, **table(args, "sim"))


def safety_config(args: Any) -> Any:
    """The flights' safety layer, `sim.safety.SafetyConfig` with the [safety] table's values, when --safety or a
    [safety] table in the config file (even an empty one: TOML has one key for both) turns it on; else None."""
    if "safety" not in type(args).config_tables or not (getattr(args, "safety", False) or "safety" in args.tables):
        return None
    values = table(args, "safety")
    from sim.safety import SafetyConfig

    return built("safety", SafetyConfig, **values)


def flight_components(args: Any) -> dict[str, Any]:
    """The `Simulator` keywords of the experiment's own flights: the controller (--controller; the LQR with the
    [lqr] table's values), the config ([sim]) and the safety layer (--safety, [safety]). The staged collection behind its models flies the defaults
    (part of its provenance), so --controller leaves the pipeline key and the models as they are."""
    name = getattr(args, "controller", DEFAULT_CONTROLLER)
    check_controller(args)
    if name == "lqr":
        from controllers.lqr import FeedbackLinearisedLQR

        controller = built("lqr", FeedbackLinearisedLQR, lqr_config(args))
    else:
        from controllers.registry import make_controller

        controller = make_controller(name)
    return {"controller": controller, "config": sim_config(args), "safety": safety_config(args)}


def check_controller(args: Any, conditions: Sequence[str] = ()) -> list[str]:
    """The `conditions` that --controller flies; ConfigError, before any work, where it and the rest disagree:
    the [lqr] table (the LQR's weights and limits), or the condition integral (integral action on the LQR)
    asked for, with another controller. The default --conditions leave integral out then."""
    name = getattr(args, "controller", DEFAULT_CONTROLLER)
    if name == "lqr":
        return list(conditions)
    if args.tables.get("lqr"):
        raise ConfigError(f"[lqr]: sets the LQR's {', '.join(args.tables['lqr'])}, but --controller is {name}, which "
                          "does not fly the LQR; remove the table, or fly --controller lqr")
    if "integral" not in conditions:
        return list(conditions)
    if args.conditions != next(f.default for f in dataclasses.fields(args) if f.name == "conditions"):
        raise ConfigError(f"--conditions: integral adds integral action to the LQR, but --controller is {name}; "
                          "fly it with --controller lqr, or leave it out")
    logging.getLogger(__name__).info("--controller %s: the default conditions fly without integral (the LQR's)", name)
    return [c for c in conditions if c != "integral"]


def controller_record(args: Any, controller: Any) -> dict[str, Any]:
    """The flights' controller for results.json: the --controller name and the controller's own description."""
    return {"name": getattr(args, "controller", DEFAULT_CONTROLLER), **controller.describe()}


def flown_record(args: Any, components: dict[str, Any]) -> dict[str, Any]:
    """What made the numbers beyond the pipeline, for results.json's provenance: the controller
    (`controller_record`) and the safety layer's settings (None: off)."""
    safety = components.get("safety")
    return {"controller": controller_record(args, components["controller"]),
            "safety": None if safety is None else safety.describe()}


def training_config(args: Any) -> Any:
    """The experiment's training settings: `downwash.staged.train_config` (the defaults, or a few steps
    with --quick) with the [training] table's values; the seed is --seed."""
    from downwash.staged import train_config

    return built("training", dataclasses.replace, train_config(args.seed, args.quick), **table(args, "training"))


def guard_config(args: Any) -> dict[str, float]:
    """The keywords of the experiment's `downwash.guard.GuardedPredictor`s: `GUARD_DEFAULTS` with the
    [guard] table's values."""
    from downwash.guard import GUARD_DEFAULTS

    return {**GUARD_DEFAULTS, **table(args, "guard")}
