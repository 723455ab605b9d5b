"""The field of one ordered pair of vehicle kinds (`pair_field`): the one rule by which every field scales.

The fields are set for a paper quad in a paper quad's wake (docs/fields.md, "Vehicles of other
kinds"); `pair_field(field, leader, follower)` gives the field of one ordered pair:

- `sim.field.DownwashField` (so2): strength x `so2_pair_scale(leader, follower)`;
- `sim.fields.momentum.MomentumWake`: the kinds' masses, rotors and arm (`momentum_wake_kwargs`), the
  airframe's drag area x `momentum_drag_area_scale`;
- any other field: its `for_kinds(leader, follower)`, or ConfigError naming these.

It lives in this package because the fields build on it (`sim.fields.shed` pairs its law per kind):
a module outside the package that imported a field class would run the package's registry, and with
it those fields, before it had finished. `sim.vehicle_params` re-exports `pair_field`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from downwash_core.errors import ConfigError
from downwash_core.params import QUAD, QuadParams
from downwash_core.vehicles import (VEHICLES, VehicleKind, as_params, momentum_drag_area_scale, momentum_wake_kwargs,
                                    so2_pair_scale)
from sim.field import DownwashField
from sim.fields.momentum import MomentumWake

__all__ = ["kind_name", "pair_field"]


def kind_name(params: QuadParams) -> str:
    """The kind's name: its own, a registered kind's of the same numbers, else "SimConfig.quad"."""
    if isinstance(params, VehicleKind):
        return params.name
    return next((k.name for k in VEHICLES.values() if k.params == params), "SimConfig.quad")


def pair_field(field: Any, leader: QuadParams, follower: QuadParams) -> Any:
    """The field for one ordered pair: `field` itself for two paper quads (and wherever the kinds change
    nothing), else the field with the kinds' numbers (see the module docstring); ConfigError for a field
    that does not say how it scales."""
    leader, follower = as_params(leader), as_params(follower)
    if leader == QUAD and follower == QUAD:
        return field
    if isinstance(field, DownwashField):
        scale = so2_pair_scale(leader, follower)
        return field if scale == 1.0 else dataclasses.replace(field, strength=field.strength * scale)
    if isinstance(field, MomentumWake):
        paired = dataclasses.replace(field, **momentum_wake_kwargs(leader, follower),
                                     drag_area=field.drag_area * momentum_drag_area_scale(leader, follower))
        return field if paired == field else paired
    for_kinds = getattr(field, "for_kinds", None)
    if callable(for_kinds):
        return for_kinds(leader, follower)
    raise ConfigError(
        f"field {type(field).__name__}: no scaling for a {kind_name(leader)} leader and a {kind_name(follower)} "
        "follower; a scene of other vehicle kinds than the paper quad flies sim.field.DownwashField, "
        "sim.fields.momentum.MomentumWake, or a field with for_kinds(leader, follower) -> the field of that pair")
