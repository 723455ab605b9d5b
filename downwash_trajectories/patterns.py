"""Data-collection patterns: the randomised passes and hovers of the staged collection.

`random_passes` draws one pattern per world (passes through and beside the wake
at random headings, offsets and speeds, hovers at offsets); `collection_reference`
mixes them with lemniscates as every stage of the staged collection does, one
generator per flight.
Randomness only through the `numpy.random.Generator` passed in.
"""

from __future__ import annotations

import math

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError
from downwash_core.validate import count, ordered_range, positive_float, vec3
from downwash_trajectories.combinators import Mixed, StackedReference, stack
from downwash_trajectories.primitives import Hover, Lemniscate
from downwash_trajectories.waypoints import MIN_JERK_PEAK, Waypoints

__all__ = ["SPEED_RANGE", "LEMNISCATE_SHARE", "random_passes", "collection_reference"]

SPEED_RANGE = (0.1, 1.0)  # m/s, allowed peak speeds of data-collection moves
LEMNISCATE_SHARE = 0.2  # share of a stage's flights that are lemniscates (the rest: random passes and hovers)


def random_passes(
    rng: np.random.Generator,
    n_worlds: int,
    center: ArrayLike,
    *,
    depth_range: tuple[float, float] = (1.35, 1.75),
    speed_range: tuple[float, float] = (0.1, 1.0),
    max_offset: float = 0.6,
    pass_half_length: float = 1.0,
    duration: float = 60.0,
    n_segments: int | None = None,
    hover_prob: float = 0.2,
    hover_radius: float = 0.8,
    hover_time_range: tuple[float, float] = (2.0, 5.0),
    reposition_speed: float = 0.5,
    min_move_time: float = 1.0,
    start: ArrayLike | None = None,
) -> Waypoints:
    """Randomised passes through and beside the leader's wake.

    Each world flies a sequence of items, each a straight pass (probability
    1 - hover_prob) or a hover (probability hover_prob), joined by
    repositioning moves; every move is minimum-jerk and every waypoint lies
    `depth` below the leader, depth uniform in `depth_range` per waypoint.

    - A pass has a heading uniform in [0, 2 pi), a lateral offset from the wake
      axis (the vertical line through `center`) uniform in [0, max_offset] m,
      and runs from -pass_half_length to +pass_half_length m along its heading
      about its closest point to the axis; its peak speed v is uniform in
      `speed_range` and its duration 1.875 * distance / v (tag "pass").
    - A hover sits at a horizontal offset of radius uniform in
      [0, hover_radius] m (uniform angle) for a time uniform in
      `hover_time_range` s (the dwell at that waypoint).
    - A repositioning move (tag "reposition") goes from where the last item
      ended to where the next begins, with peak speed `reposition_speed` m/s
      and at least `min_move_time` s.

    Items are added until a world's pattern lasts at least `duration` s, or,
    when `n_segments` is given, exactly `n_segments` items per world. The
    pattern begins at `start` when given, else at the first item's start point.
    Randomness only through `rng`: the same generator state gives the same
    patterns.

    rng: numpy Generator.
    n_worlds: number of worlds, >= 1.
    center: (W, 3) or (3,) m, the leader's position, world frame (z up).
    depth_range: (low, high) m, 0 < low <= high, vertical separation below `center`.
    speed_range: (low, high) m/s, within 0.1-1.0 m/s.
    start: optional (W, 3) or (3,) m, the first waypoint of every world.
    Returns a `Waypoints` over `n_worlds` worlds with move tags "pass" and
    "reposition".
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    w = count("n_worlds", n_worlds)
    c = vec3("center", center)
    if c.ndim == 2 and c.shape[0] != w:
        raise ConfigError(f"center: expected shape ({w}, 3) or (3,), got {c.shape}")
    c = np.broadcast_to(c, (w, 3))
    d_lo, d_hi = ordered_range("depth_range", depth_range, "m", 0.0, np.inf)
    s_lo, s_hi = ordered_range("speed_range", speed_range, "m/s", *SPEED_RANGE)
    max_offset = positive_float("max_offset", max_offset, "m", allow_zero=True)
    pass_half_length = positive_float("pass_half_length", pass_half_length, "m")
    duration = positive_float("duration", duration, "s")
    if n_segments is not None and (
        isinstance(n_segments, bool) or not isinstance(n_segments, (int, np.integer)) or n_segments < 1
    ):
        raise ConfigError(f"n_segments: expected None or an integer >= 1, got {n_segments!r}")
    hover_prob = float(hover_prob)
    if not 0.0 <= hover_prob <= 1.0:
        raise ConfigError(f"hover_prob: got {hover_prob!r}; allowed 0-1")
    hover_radius = positive_float("hover_radius", hover_radius, "m", allow_zero=True)
    h_lo, h_hi = ordered_range("hover_time_range", hover_time_range, "s", 0.0, np.inf)
    reposition_speed = float(reposition_speed)
    if not SPEED_RANGE[0] <= reposition_speed <= SPEED_RANGE[1]:
        raise ConfigError(
            f"reposition_speed: got {reposition_speed!r}; allowed {SPEED_RANGE[0]}-{SPEED_RANGE[1]} m/s"
        )
    min_move_time = positive_float("min_move_time", min_move_time, "s")
    st = None
    if start is not None:
        st = vec3("start", start)
        if st.ndim == 2 and st.shape[0] != w:
            raise ConfigError(f"start: expected shape ({w}, 3) or (3,), got {st.shape}")
        st = np.broadcast_to(st, (w, 3))

    def below(cw: np.ndarray, xy: np.ndarray) -> np.ndarray:
        return np.array([cw[0] + xy[0], cw[1] + xy[1], cw[2] - rng.uniform(d_lo, d_hi)])

    all_pts, all_durs, all_dwell, all_tags = [], [], [], []
    for wi in range(w):
        cw = c[wi]
        pts: list[np.ndarray] = []
        durs: list[float] = []
        dwl: list[float] = []
        tags: list[str] = []
        total = 0.0
        n_items = 0

        def move_to(p: np.ndarray, dur: float, tag: str) -> float:
            pts.append(p)
            durs.append(dur)
            dwl.append(0.0)
            tags.append(tag)
            return dur

        def reposition(p: np.ndarray) -> float:
            dist = math.dist(p, pts[-1])  # not np.linalg.norm: a BLAS dot, CPU-dependent bits
            return move_to(p, max(MIN_JERK_PEAK * dist / reposition_speed, min_move_time), "reposition")

        if st is not None:
            pts.append(st[wi].copy())
            dwl.append(0.0)
        while (n_items < n_segments) if n_segments is not None else (total < duration):
            if rng.uniform() < hover_prob:
                r = rng.uniform(0.0, hover_radius)
                ang = rng.uniform(0.0, 2.0 * np.pi)
                p = below(cw, r * np.array([np.cos(ang), np.sin(ang)]))
                hold = rng.uniform(h_lo, h_hi)
                if pts:
                    total += reposition(p)
                else:
                    pts.append(p)
                    dwl.append(0.0)
                dwl[-1] = hold
                total += hold
            else:
                heading = rng.uniform(0.0, 2.0 * np.pi)
                offset = rng.uniform(0.0, max_offset)
                speed = rng.uniform(s_lo, s_hi)
                u = np.array([np.cos(heading), np.sin(heading)])
                n = np.array([-u[1], u[0]])
                p_a = below(cw, offset * n - pass_half_length * u)
                p_b = below(cw, offset * n + pass_half_length * u)
                if pts:
                    total += reposition(p_a)
                else:
                    pts.append(p_a)
                    dwl.append(0.0)
                dist = math.dist(p_b, p_a)
                total += move_to(p_b, MIN_JERK_PEAK * dist / speed, "pass")
            n_items += 1
        all_pts.append(np.array(pts))
        all_durs.append(np.array(durs))
        all_dwell.append(np.array(dwl))
        all_tags.append(tags)
    return Waypoints.from_patterns(all_pts, all_durs, all_dwell, move_tags=all_tags)


def collection_reference(
    seed: Sequence[int],
    flights: Sequence[int],
    n_train: int,
    n_val: int,
    leader: ArrayLike,
    separation: tuple[float, float],
    seconds: float,
) -> StackedReference:
    """Leader hover and follower references for some flights of one collection stage.

    A stage has n_train training flights (indices 0..n_train-1) and n_val validation
    flights (the rest); `flights` picks which to build, in that order, as the worlds of
    one batch. Each flight draws from its own generator, `default_rng([*seed, index])`,
    so a flight's reference does not depend on which others share its batch (the
    collection can resume flight by flight). Of each role, the last LEMNISCATE_SHARE
    (rounded; none in a role of fewer than 3 flights) are lemniscates with random
    centres, sizes and periods; the others are `random_passes` (depth uniform in
    `separation`, m). Returns the (leader, follower) stack over len(flights) worlds.
    """
    leader = np.asarray(leader, dtype=float)
    n_all = n_train + n_val
    passes: list[tuple[int, Waypoints]] = []  # (world, one-world pattern)
    lems: list[tuple[int, np.ndarray]] = []  # (world, [cx, cy, cz, half_length, half_width, period])
    for world, i in enumerate(flights):
        if not 0 <= i < n_all:
            raise ConfigError(f"flights: index {i} outside the stage's {n_all} flights")
        j, n_role = (i, n_train) if i < n_train else (i - n_train, n_val)
        rng = np.random.default_rng([*seed, i])
        n_lem = int(round(LEMNISCATE_SHARE * n_role)) if n_role >= 3 else 0
        if j >= n_role - n_lem:
            c = leader - [rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(*separation)]
            lems.append((world, np.array([*c, rng.uniform(0.6, 1.2), rng.uniform(0.3, 0.7), rng.uniform(10.0, 24.0)])))
        else:
            passes.append((world, random_passes(rng, 1, leader, depth_range=separation, duration=seconds)))
    parts = []
    if passes:
        parts.append((Waypoints.concatenate([wp for _, wp in passes]), [w for w, _ in passes]))
    if lems:
        p = np.array([v for _, v in lems])
        parts.append((Lemniscate(p[:, :3], half_length=p[:, 3], half_width=p[:, 4], period=p[:, 5],
                                 n_worlds=len(lems)), [w for w, _ in lems]))
    return stack([Hover(leader, n_worlds=len(flights)), Mixed(parts)])
