"""Ground-truth downwash fields beside `sim.field`, and the registry that names them.

- `sim.fields.registry`: the named fields (`FIELDS`, `make_field`, `register_field`)
  and the spec grammar of `--field` / `field=` (`resolve_field_spec`);
- `sim.fields.momentum`: `MomentumWake`, a physics-based wake (momentum theory and the
  turbulent round jet) acting on the follower's rotors and airframe.

`sim.field` keeps the paper's law (`DownwashField`, `pairwise_field`, `check_field`).
Every field has the call signature `field(p_a, v_a, R_a, p_b, v_b) -> (..., 3)` m/s^2.
See docs/fields.md.
"""

from sim.fields.momentum import MomentumWake, rotor_thrust_ratio
from sim.fields.registry import (
    DEFAULT_FIELD, FIELDS, FieldEntry, field_parameters, make_field, parse_field_spec, register_field,
    resolve_field_spec,
)

__all__ = [
    "MomentumWake", "rotor_thrust_ratio", "DEFAULT_FIELD", "FIELDS", "FieldEntry", "field_parameters",
    "make_field", "parse_field_spec", "register_field", "resolve_field_spec",
]
