"""A controller tick's log row: its names and shapes, its flat layout, and `Row`.

The readable path returns a tick's row as a dict of fresh arrays; the fused path
(`sim.fused`) writes the same names into one flat float64 array per tick, laid out by
`row_layout`, and returns it as a `Row`, a read-only mapping of views into it.
`sim.flight` stacks many rows' flat arrays at once.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Iterator

import numpy as np

__all__ = ["Row", "row_layout"]

# The row of a controller tick: name -> trailing shape after (W,), in the order of the
# readable path's dicts. "wind" and "wind_acc" only when the wind is on.
_ROW_FIELDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("t", ()), ("pos", ("V", 3)), ("vel", ("V", 3)), ("quat", ("V", 4)), ("pos_est", ("V", 3)),
    ("vel_est", ("V", 3)), ("quat_est", ("V", 4)), ("yaw_est", ("V",)), ("mocap_pos", ("V", 3)),
    ("ref_pos", ("V", 3)), ("ref_vel", ("V", 3)), ("ref_acc", ("V", 3)), ("u_cmd", ("V", 3)), ("f_hat", ("V", 3)),
    ("field_mean", ("V", 3)), ("field_applied", ("V", 3)),
)
_WIND_ROW_FIELDS = (("wind", ("V", 3)), ("wind_acc", ("V", 3)))
_GUARD_ROW_FIELDS = (("applied", ("V",)),)  # a guard's applied fraction (`sim.predictor`)
# Storage order in the flat row: the five (W, V, 3) kinematic arrays of `Sensed.kin`
# first and contiguous (the sense pass writes them as one (5, W, V, 3) block).
_ROW_STORAGE = ("pos", "vel", "mocap_pos", "pos_est", "vel_est", "t", "quat", "quat_est", "yaw_est", "field_applied",
                "ref_pos", "ref_vel", "ref_acc", "u_cmd", "f_hat", "field_mean", "wind", "wind_acc", "applied")


def row_layout(W: int, V: int, wind: bool, guard: bool = False) -> tuple[dict[str, tuple[int, tuple[int, ...]]], int]:
    """({name: (offset, shape)}, size) of a flat row; shapes (W, ...) in the order of `_ROW_FIELDS`, then
    the wind's and the guard's fields when they are there."""
    fields = dict(_ROW_FIELDS + (_WIND_ROW_FIELDS if wind else ()) + (_GUARD_ROW_FIELDS if guard else ()))
    shapes = {name: (W,) + tuple(V if d == "V" else d for d in trail) for name, trail in fields.items()}
    offsets, size = {}, 0
    for name in _ROW_STORAGE:
        if name in shapes:
            offsets[name] = size
            size += int(np.prod(shapes[name]))
    return {name: (offsets[name], shapes[name]) for name in fields}, size


class Row(Mapping):
    """One controller tick's log row (the fast path's): name -> (W, ...) float64 array.

    A read-only mapping with the keys of the readable path's dict rows; its arrays are
    views of one flat array written once by the tick and never again (fresh each tick).
    `flat` and `layout` ({name: (offset, shape)}) let `sim.flight` stack many rows at once.
    """

    __slots__ = ("flat", "layout")

    def __init__(self, flat: np.ndarray, layout: dict[str, tuple[int, tuple[int, ...]]]):
        self.flat = flat
        self.layout = layout

    def __getitem__(self, name: str) -> np.ndarray:
        offset, shape = self.layout[name]
        return self.flat[offset:offset + math.prod(shape)].reshape(shape)

    def __iter__(self) -> Iterator[str]:
        return iter(self.layout)

    def __len__(self) -> int:
        return len(self.layout)

    def __repr__(self) -> str:
        return f"Row({', '.join(self.layout)})"

