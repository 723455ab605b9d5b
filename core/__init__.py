"""Foundation shared by every layer: parameters, vocabulary, geometry, I/O, validation, errors.

Modules (import them directly; this package imports nothing on its own):

- `core.params`: the one source of every physical and timing parameter, with units
- `core.jit`: the one place that configures compiled kernels (numba)
- `core.geometry`: dot products, quaternions, rotations, headings (readable and compiled)
- `core.state`: the small named bundles that cross layers (`VehicleStates`, `RefSample`)
- `core.status`: `Status`, how a flight or an episode ended
- `core.roles`: `Role`, what a vehicle is in a scene (leader, follower)
- `core.io`: atomic writes and JSON of NumPy values
- `core.validate`: argument checks that name the argument and the allowed range
- `core.errors`: the project's exception hierarchy

`core` imports none of gymnasium, torch or matplotlib (a contract in pyproject.toml,
run by a test), so every layer can use it.
"""
