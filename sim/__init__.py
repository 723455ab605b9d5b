"""Simulation: scene, ground-truth downwash field, estimation, the stepping loop, logs, envs.

Importing `sim` registers its Gymnasium environments (entry points are strings, so
this imports gymnasium's registry only: no MuJoCo, no torch):

- ``DownwashFollower-v0``: the follower flies the paper's lemniscate 0.6 m below a
  hovering leader, in its downwash; 500 steps (10 s at 50 Hz).
- ``DownwashFollowerPasses-v0``: randomised passes and hovers through and beside
  the wake, 0.5-1.2 m below the leader; 1000 steps (20 s).

Both take every option of `sim.env.FollowerConfig` as a `gymnasium.make` keyword
(``action_mode="residual"`` by default, or ``"acceleration"``) and have a native
vector env: ``gymnasium.make_vec(id, num_envs=N)``. Without a prior ``import sim``,
use the module-qualified id ``gymnasium.make("sim:DownwashFollower-v0")``.
"""

from gymnasium.envs.registration import register as _register
from gymnasium.envs.registration import registry as _registry

ENV_IDS = ("DownwashFollower-v0", "DownwashFollowerPasses-v0")

_ENVS = {
    "DownwashFollower-v0": ({}, 500),
    "DownwashFollowerPasses-v0": ({"reference": "passes", "separation": (0.5, 1.2)}, 1000),
}

for _id, (_kwargs, _steps) in _ENVS.items():
    if _id not in _registry:  # re-imports (importlib.reload) must not warn about overriding
        _register(
            id=_id,
            entry_point="sim.env:DownwashFollowerEnv",
            vector_entry_point="sim.env:DownwashFollowerVectorEnv",
            max_episode_steps=_steps,
            kwargs=_kwargs,
        )
del _id, _kwargs, _steps
