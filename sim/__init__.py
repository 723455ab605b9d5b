"""The integrator: scene, ground-truth field, turbulence, sensors, estimation, physics, the loop, logs, metrics.

Modules (import them directly):

- `sim.scene`: N quadrotors from `assets/quad.xml` with named roles (`build_scene`)
- `sim.field`: the ground-truth downwash field (`DownwashField`, `pairwise_field`)
- `sim.turbulence`: turbulence on the field (`OUTurbulence`)
- `sim.sensors`: the sensor, motion capture (`MocapConfig`, `BiasedMocap`, `make_sensor`)
- `sim.estimation`: the Kalman filter on the sensor's positions
- `sim.physics`: one stepping interface over `MjData` and `mujoco.batch.Batch`
- `sim.simulator`: the multi-rate loop (`Simulator`, `SimConfig`)
  over `sim.plan` (fused or readable), `sim.fused` (the fused tick), `sim.passes` (the
  compiled passes both paths share) and `sim.rows` (a tick's log row, `Row`)
- `sim.flight`: fly a batch to the end (`fly`) -> `sim.logs.FlightLog`
- `sim.logs`, `sim.metrics`: flight logs on disk, tracking metrics
- `sim.predictor`: the slot through which a downwash model reaches the loop

`import sim` imports neither gymnasium nor torch: the Gymnasium environments live
in `downwash_envs` (`import downwash_envs` registers their ids).
"""
