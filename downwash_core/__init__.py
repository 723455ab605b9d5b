"""Foundation shared by every layer: parameters, vocabulary, geometry, I/O, validation, errors.

Modules (import them directly; this package imports nothing on its own):

- `downwash_core.params`: the one source of every physical and timing parameter, with units
- `downwash_core.vehicles`: vehicle kinds (`VEHICLES`: the paper quad, a Crazyflie 2.1, an X500), each number with its source
- `downwash_core.vehicle_kind`, `downwash_core.vehicle_catalog`: a vehicle kind's type and the built-in kinds' numbers
- `downwash_core.registry`: the one `Registry` type and `NAME:KEY=VALUE,...` spec grammar, and the plugins
- `downwash_core.locks`: cross-process locks on folders and files (`flock`)
- `downwash_core.jit`: the one place that configures compiled kernels (numba)
- `downwash_core.geometry`: dot products, quaternions, rotations, headings (readable and compiled)
- `downwash_core.state`: the small named bundles that cross layers (`VehicleStates`, `RefSample`)
- `downwash_core.status`: `Status`, how a flight or an episode ended
- `downwash_core.roles`: `Role`, what a vehicle is in a scene (leader, follower)
- `downwash_core.numerics`: `cpu_independent`, set-up results with the same bits on every CPU
- `downwash_core.io`: atomic writes and JSON of NumPy values
- `downwash_core.validate`: argument checks that name the argument and the allowed range
- `downwash_core.errors`: the project's exception hierarchy

`downwash_core` imports none of gymnasium, torch or matplotlib (a contract in pyproject.toml,
run by a test), so every layer can use it.
"""
