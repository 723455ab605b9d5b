"""Ground-truth downwash fields beside `sim.field`, and the registry that names them.

- `sim.fields.registry`: the named fields (`FIELDS`, `make_field`, `register_field`)
  and the spec grammar of `--field` / `field=` (`resolve_field_spec`);
- `sim.fields.momentum`: `MomentumWake`, a physics-based wake (momentum theory and the
  turbulent round jet) acting on the follower's rotors and airframe;
- `sim.fields.jet`: `JetWake`, Bauersfeld et al.'s measured turbulent jet (RA-L 2024), acting
  on the follower as `MomentumWake`'s does;
- `sim.fields.pybullet_law`: `PybulletDownwash`, gym-pybullet-drones' downwash law.

`sim.field` keeps the paper's law (`DownwashField`, `pairwise_field`, `check_field`).
Every field has the call signature `field(p_a, v_a, R_a, p_b, v_b) -> (..., 3)` m/s^2.
See docs/fields.md.
"""

from sim.fields.jet import JetWake
from sim.fields.momentum import MomentumWake, rotor_thrust_ratio
from sim.fields.pybullet_law import PybulletDownwash
from sim.fields.registry import (
    DEFAULT_FIELD, FIELDS, FieldEntry, field_parameters, make_field, parse_field_spec, register_field,
    resolve_field_spec,
)

__all__ = [
    "MomentumWake", "rotor_thrust_ratio", "JetWake", "PybulletDownwash", "DEFAULT_FIELD", "FIELDS", "FieldEntry",
    "field_parameters", "make_field", "parse_field_spec", "register_field", "resolve_field_spec",
]
