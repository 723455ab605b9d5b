"""Real flights: readers of labs' onboard logs.

- `downwash.real_logs.crazyflie_usd`: the Crazyflie micro-SD deck's synchronous log format
  (the Neural-Swarm data set's onboard binaries), read and written exactly; compressed quaternions
- `downwash.real_logs.neural_swarm`: the Neural-Swarm data set's flights as flight logs (SI units,
  vehicles aligned at their common start, ``u`` from PWM and battery voltage through each frame's
  thrust map), so that labels, data sets and training are the simulator's own
- `downwash.real_logs.tabular`: a documented CSV (or Parquet) layout any lab can write from its own logger
- `downwash.real_logs.ros2_bag`: ROS 2 bags (MCAP, sqlite3) as flight logs, through a topic mapping
- `downwash.real_logs.crazyflie_events`: the firmware's event-based uSD log as a flight log, through a mapping
- `downwash.real_logs.mapping`: the TOML mappings of logged signals to a flight log's fields, and their unit checks
- `downwash.real_logs.flights`: a data set of real flights, chosen by globs, checked, labelled and typed
- `downwash.real_logs.convert`: what the readers share (resampling, ``u`` from the measured thrust)
- `downwash.real_logs.replay`: real flights' setpoints flown in the simulator, tracking side by side

A real flight is a `sim.logs.FlightLog` with a ``source`` in its metadata and no truth arrays.
"""

__all__ = ["crazyflie_usd", "neural_swarm", "tabular", "flights", "convert",
           "ros2_bag", "crazyflie_events", "mapping", "replay"]
