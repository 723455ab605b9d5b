"""Real flights: readers of labs' onboard logs.

- `downwash.real_logs.crazyflie_usd`: the Crazyflie micro-SD deck's synchronous log format
  (the Neural-Swarm data set's onboard binaries), read and written exactly
"""

__all__ = ["crazyflie_usd"]
