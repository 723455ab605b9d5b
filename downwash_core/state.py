"""The small named bundles that cross layers: vehicle states and reference samples.

Every array carries a leading batch: worlds W, and vehicles V where there are
several (a single flight is a batch of one). World frame (MuJoCo: z up), SI units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

__all__ = ["VehicleStates", "RefSample"]


@dataclass(frozen=True)
class VehicleStates:
    """States of every vehicle in every world.

    pos: (W, V, 3) m, world frame (z up).
    vel: (W, V, 3) m/s, world frame.
    rot: (W, V, 3, 3) body-to-world rotation; column 2 is the body's up axis.
    """

    pos: np.ndarray
    vel: np.ndarray
    rot: np.ndarray

    def select(self, worlds: np.ndarray) -> "VehicleStates":
        """The states of a subset of worlds (index array or boolean mask)."""
        return VehicleStates(self.pos[worlds], self.vel[worlds], self.rot[worlds])


class RefSample(NamedTuple):
    """One sample of a batched reference; world frame (z up), SI units.

    pos: (W, 3) m; vel: (W, 3) m/s; acc: (W, 3) m/s^2; yaw: (W,) rad;
    yaw_rate: (W,) rad/s. A stacked reference (one per vehicle) gives the same
    fields with a vehicle axis: (W, V, 3) and (W, V).
    """

    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    yaw: np.ndarray
    yaw_rate: np.ndarray
