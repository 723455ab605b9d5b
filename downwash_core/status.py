"""How a flight (or an env episode) ended: one vocabulary, used by the loop, logs and envs."""

from __future__ import annotations

import enum

__all__ = ["Status"]


class Status(enum.IntEnum):
    """Status codes, stored as integers in logs and infos.

    A flight that ends early keeps its rows up to the end; `LEFT_BOX` is set only by
    the envs (the follower left its tracking box), never by the simulator.
    """

    OK = 0
    DIVERGED = 1  # NaN, runaway state or a MuJoCo instability warning
    GROUND = 2  # a vehicle hit the ground
    VEHICLE = 3  # two vehicles collided
    LEFT_BOX = 4  # env only: the follower left the tracking box around its reference

    @property
    def label(self) -> str:
        """Snake-case name, as written in logs and infos ("ok", "ground_collision", ...)."""
        return _LABELS[self]

    @property
    def description(self) -> str:
        """What happened, for messages."""
        return _DESCRIPTIONS[self]


_LABELS = {
    Status.OK: "ok", Status.DIVERGED: "diverged", Status.GROUND: "ground_collision",
    Status.VEHICLE: "vehicle_collision", Status.LEFT_BOX: "left_box",
}  # fmt: skip
_DESCRIPTIONS = {
    Status.OK: "ok",
    Status.DIVERGED: "diverged (NaN, runaway state or MuJoCo instability warning)",
    Status.GROUND: "hit the ground",
    Status.VEHICLE: "vehicles collided",
    Status.LEFT_BOX: "left the tracking box",
}
