"""Batched reference trajectories with analytic derivatives, and how to combine them.

- `downwash_trajectories.base`: the `Reference` protocol and `RefSample`
- `downwash_trajectories.primitives`: `Hover`, `Lemniscate`, `Transect`, `Line`, `Circle`
- `downwash_trajectories.waypoints`: `Waypoints`, piecewise minimum-jerk moves with dwells, a pattern per world
- `downwash_trajectories.recorded`: `Recorded`, recorded setpoints played back (a lab's logged flight)
- `downwash_trajectories.combinators`: `stack`, `Mixed`, `TimeShifted`, `Cached`, `Offset`, `Relative`
- `downwash_trajectories.patterns`: the staged collection's `random_passes` and `collection_reference`
- `downwash_trajectories.factory`: `make_reference(name, center, n_worlds, **shape)`, the one name -> reference factory

A new trajectory is any object with `n_worlds`, `duration` and `__call__(t) -> RefSample`.
"""

from downwash_trajectories.base import RefSample, Reference
from downwash_trajectories.combinators import Cached, Mixed, Offset, Relative, StackedReference, TimeShifted, stack
from downwash_trajectories.factory import REFERENCE_KWARGS, REFERENCES, make_reference
from downwash_trajectories.patterns import LEMNISCATE_SHARE, SPEED_RANGE, collection_reference, random_passes
from downwash_trajectories.primitives import Circle, Hover, Lemniscate, Line, Transect
from downwash_trajectories.recorded import Recorded
from downwash_trajectories.waypoints import Waypoints

__all__ = [
    "RefSample", "Reference", "Hover", "Lemniscate", "Transect", "Waypoints", "Line", "Circle", "Recorded", "Offset", "Relative", "Mixed",
    "StackedReference",
    "stack", "TimeShifted", "Cached", "random_passes", "collection_reference", "SPEED_RANGE",
    "LEMNISCATE_SHARE", "REFERENCES", "REFERENCE_KWARGS", "make_reference",
]  # fmt: skip
