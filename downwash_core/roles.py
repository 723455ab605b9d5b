"""What each vehicle of a scene is: the one place that says which index is the leader."""

from __future__ import annotations

import enum

__all__ = ["Role", "DEFAULT_VEHICLES", "SCENE_VEHICLE_NAMES", "MIN_VEHICLES", "MAX_VEHICLES"]


class Role(str, enum.Enum):
    """A vehicle's role. The leader's wake acts on the followers below it."""

    LEADER = "leader"  # Alpha: hovers (or flies) above, its wake is the downwash
    FOLLOWER = "follower"  # Bravo: flies through the leader's wake


# The paper's two vehicles, in scene order: name -> role.
DEFAULT_VEHICLES: tuple[tuple[str, Role], ...] = (("alpha", Role.LEADER), ("bravo", Role.FOLLOWER))

# Names of the vehicles of an N-vehicle scene, top of a stack first (NATO alphabet, as the paper's two).
SCENE_VEHICLE_NAMES: tuple[str, ...] = ("alpha", "bravo", "charlie", "delta", "echo", "foxtrot", "golf", "hotel")
MIN_VEHICLES, MAX_VEHICLES = 1, len(SCENE_VEHICLE_NAMES)  # a scene holds 1-8 vehicles (a swarm preset 2-8)
