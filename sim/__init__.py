"""The integrator: scene, ground-truth field, turbulence, estimation, physics, the loop, logs, metrics.

Modules (import them directly):

- `sim.scene`: N quadrotors from `assets/quad.xml` with named roles (`build_scene`)
- `sim.field`: the ground-truth downwash field (`DownwashField`, `pairwise_field`)
- `sim.turbulence`: turbulence on the field (`OUTurbulence`)
- `sim.estimation`: motion capture and the Kalman filter
- `sim.physics`: one stepping interface over `MjData` and `mujoco.batch.Batch`
- `sim.simulator`: the multi-rate loop (`Simulator`, `SimConfig`)
- `sim.flight`: fly a batch to the end (`fly`) -> `sim.logs.FlightLog`
- `sim.logs`, `sim.metrics`: flight logs on disk, tracking metrics
- `sim.predictor`: the slot through which a downwash model reaches the loop

`import sim` imports neither gymnasium nor torch: the Gymnasium environments live
in `envs` (`import envs` registers their ids).
"""

import sys as _sys

if "gymnasium" in _sys.modules and "envs" not in _sys.modules:
    # Backward compatibility: the env ids used to be registered by `import sim`, and
    # `gymnasium.make("sim:DownwashFollower-v0")` imports this package to find them. They
    # now live in `envs`; register them the old way only when gymnasium is already loaded,
    # so that importing sim never pulls in gymnasium itself.
    import importlib as _importlib

    _importlib.import_module("envs")
