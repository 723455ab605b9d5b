"""The follower envs' observation: one layout, from which everything else is derived.

`OBSERVATION` lists the entries in order; the observation vector (float64,
`OBS_DIM` values) is their concatenation. `OBS_SLICES` (index ranges),
`obs_bounds` (the Box bounds) and `observation_table` (the table in
`downwash_envs.follower.DownwashFollowerEnv`'s docstring and docs/envs.md, which tests compare
with it) all read this one tuple, so adding or changing an entry changes them all. The
helpers behind them (`layout_slices`, `layout_bounds`, `table_row`, `layout_table`) serve
any layout of `ObsEntry`s: the swarm env's too (`downwash_envs.swarm_task`).

Positions and velocities are the vehicle's own knowledge (Kalman-filtered motion
capture), attitudes the onboard (true) ones; all in the world frame, z up.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

__all__ = [
    "ObsEntry", "OBSERVATION", "OBS_DIM", "OBS_SLICES", "obs_bounds", "observation_table",
    "layout_slices", "layout_bounds", "table_row", "layout_table",
]  # fmt: skip


class ObsEntry(NamedTuple):
    """One named block of the observation vector."""

    name: str
    size: int  # values
    unit: str
    frame: str
    bound: float  # each value clipped to [-bound, bound]; NaN: the action bound
    meaning: str


# Bounds are never reached in a live episode (the tracking box ends it first); only a
# diverged world's last observation can be clipped.
OBSERVATION: tuple[ObsEntry, ...] = (
    ObsEntry("dp", 3, "m", "world", 10.0, "p_follower - p_leader"),
    ObsEntry("v_follower", 3, "m/s", "world", 20.0, "follower velocity"),
    ObsEntry("v_leader", 3, "m/s", "world", 20.0, "leader velocity"),
    ObsEntry("pos_error", 3, "m", "world", 10.0, "p_follower - p_ref"),
    ObsEntry("vel_error", 3, "m/s", "world", 25.0, "v_follower - v_ref"),
    ObsEntry("ref_acc", 3, "m/s^2", "world", 25.0, "reference acceleration a_ref"),
    ObsEntry("follower_x_axis", 3, "-", "world", 1.0, "follower body x axis R_b[:, 0] (heading)"),
    ObsEntry("follower_z_axis", 3, "-", "world", 1.0, "follower body z axis R_b[:, 2] (thrust direction)"),
    ObsEntry("leader_z_axis", 3, "-", "world", 1.0, "leader body z axis R_a[:, 2] (the wake's axis)"),
    ObsEntry("last_action", 3, "m/s^2", "world", math.nan, "previous action as applied (0 after reset)"),
)
OBS_DIM = sum(e.size for e in OBSERVATION)


def layout_slices(layout: tuple[ObsEntry, ...]) -> dict[str, slice]:
    """name -> index range of each entry of `layout` (any layout: this one, the swarm env's)."""
    out, start = {}, 0
    for e in layout:
        out[e.name] = slice(start, start + e.size)
        start += e.size
    return out


def layout_bounds(layout: tuple[ObsEntry, ...], action_bound: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (sum of sizes,) float64; `action_bound` (m/s^2) bounds the NaN-bound entries."""
    high = np.concatenate([np.full(e.size, action_bound if math.isnan(e.bound) else e.bound) for e in layout])
    return -high, high


OBS_SLICES: dict[str, slice] = layout_slices(OBSERVATION)  # name -> index range in the vector


def obs_bounds(action_bound: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high), each (OBS_DIM,) float64; `action_bound` (m/s^2) bounds last_action."""
    return layout_bounds(OBSERVATION, action_bound)


def table_row(index: str, e: ObsEntry, name: str | None = None) -> tuple[str, ...]:
    """One row of an observation table: index, name, meaning, unit, frame, bound ("b": the action bound)."""
    bound = "b" if math.isnan(e.bound) else f"{e.bound:g}"
    return (index, e.name if name is None else name, e.meaning, e.unit, e.frame, bound)


def layout_table(rows: list[tuple[str, ...]]) -> str:
    """Rows of `table_row` as a markdown table under its header; columns padded to their widest
    cell, no trailing newline."""
    header = ("index", "name", "meaning", "unit", "frame", "bound")
    widths = [max(len(r[i]) for r in (header, *rows)) for i in range(len(header))]

    def line(cells):
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"

    rule = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(header), rule, *(line(r) for r in rows)])


def observation_table() -> str:
    """The observation as a markdown table: index, name, meaning, unit, frame, bound
    ("b": the action bound). Columns padded to their widest cell; no trailing newline."""
    rows = []
    for e in OBSERVATION:
        s = OBS_SLICES[e.name]
        rows.append(table_row(f"{s.start}-{s.stop - 1}" if e.size > 1 else f"{s.start}", e))
    return layout_table(rows)
