"""Deprecated: the references moved to the `trajectories` package."""

import warnings

from trajectories import (  # noqa: F401
    SPEED_RANGE,
    Hover,
    Lemniscate,
    Mixed,
    RefSample,
    Reference,
    StackedReference,
    Transect,
    Waypoints,
    random_passes,
    stack,
)

warnings.warn(
    "controllers.references is deprecated; import from trajectories instead", DeprecationWarning, stacklevel=2
)
