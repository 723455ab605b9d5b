"""Deprecated: the Gymnasium environments moved to the `envs` package.

`from sim.env import X` keeps working for the names below, with a DeprecationWarning;
import them from `envs` instead (`from envs import DownwashFollowerEnv, evaluate_lqr`).
`STATUS_LEFT_BOX` and `STATUS_NAMES` are now `core.status.Status.LEFT_BOX` and
`Status(code).label`.
"""

from __future__ import annotations

import warnings
from types import MappingProxyType

from core.status import Status
from envs.config import (
    ACTION_MODES,
    CONTROL_HZ_ALLOWED,
    DEFAULT_FIELD_RANDOMIZATION,
    DEFAULT_MAX_EPISODE_STEPS,
    FIELD_RANDOMIZABLE,
    PREDICTORS,
    REFERENCES,
    FollowerConfig,
    make_config,
)
from envs.evaluation import env_steps_per_s_single, env_steps_per_s_vector, evaluate_lqr
from envs.follower import DownwashFollowerEnv, DownwashFollowerVectorEnv
from envs.observation import OBS_DIM, OBSERVATION
from envs.task import REWARD_TERMS

warnings.warn(
    "sim.env is deprecated: import the environments from `envs` (e.g. `from envs import DownwashFollowerEnv`)",
    DeprecationWarning,
    stacklevel=2,
)

STATUS_LEFT_BOX = int(Status.LEFT_BOX)
STATUS_NAMES = MappingProxyType({int(s): s.label for s in Status})

__all__ = [
    "ACTION_MODES", "REFERENCES", "PREDICTORS", "CONTROL_HZ_ALLOWED", "DEFAULT_MAX_EPISODE_STEPS",
    "DEFAULT_FIELD_RANDOMIZATION", "FIELD_RANDOMIZABLE", "OBSERVATION", "OBS_DIM", "REWARD_TERMS",
    "STATUS_LEFT_BOX", "STATUS_NAMES", "FollowerConfig", "make_config", "DownwashFollowerEnv",
    "DownwashFollowerVectorEnv", "evaluate_lqr", "env_steps_per_s_single", "env_steps_per_s_vector",
]  # fmt: skip
