"""Combinators: references made of references.

- `stack`: one reference per vehicle, sampled together as (W, V, ...) arrays.
- `Mixed`: different references for different worlds of one batch.
- `TimeShifted`: a reference sampled at t + t0 (a per-world start phase).
- `Cached`: returns its last sample again when asked for the same times.
- `Offset`: a reference moved by a fixed offset (a follower flying beneath a moving leader).
- `Relative`: a pattern flown relative to a moving reference (collection beneath a moving leader).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from downwash_core.errors import ConfigError
from downwash_trajectories.base import RefSample, Reference, empty_sample, sample_times

__all__ = ["Mixed", "StackedReference", "stack", "TimeShifted", "Cached", "Offset", "Relative"]


class Mixed:
    """Different references for different worlds of one batch.

    parts: (reference, worlds) pairs; `worlds` (index array) are the batch worlds that
    `reference` (built with n_worlds = len(worlds)) serves. Every world must be served
    exactly once. Sampling calls each part once on its worlds' times.
    """

    def __init__(self, parts: Sequence[tuple[Reference, ArrayLike]]) -> None:
        parts = [(ref, np.asarray(worlds, dtype=np.int64).reshape(-1)) for ref, worlds in parts]
        if not parts:
            raise ConfigError("parts: expected at least one (reference, worlds) pair")
        for ref, worlds in parts:
            if int(ref.n_worlds) != worlds.size:
                raise ConfigError(f"parts: a reference with n_worlds={ref.n_worlds} was given {worlds.size} worlds")
        all_worlds = np.sort(np.concatenate([w for _, w in parts]))
        if not np.array_equal(all_worlds, np.arange(all_worlds.size)):
            raise ConfigError("parts: the worlds must be 0..W-1, each served by exactly one reference")
        self.parts = parts
        self.n_worlds = int(all_worlds.size)
        self.duration = np.zeros(self.n_worlds)
        for ref, worlds in parts:
            self.duration[worlds] = np.broadcast_to(np.asarray(ref.duration, dtype=float), (worlds.size,))

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)): the fields of RefSample, (W, 3) and (W,)."""
        t = sample_times(t, self.n_worlds)
        W = self.n_worlds
        out = RefSample(np.empty((W, 3)), np.empty((W, 3)), np.empty((W, 3)), np.empty(W), np.empty(W))
        for ref, worlds in self.parts:
            for dst, src in zip(out, ref(t[worlds])):
                dst[worlds] = src
        return out


class StackedReference:
    """One reference per vehicle, sampled together: `(W, V, ...)` arrays.

    refs: V references with the same `n_worlds`. `duration` (s, (W,)) is the
    longest natural length over the vehicles.
    """

    def __init__(self, refs: Sequence[Reference]) -> None:
        refs = list(refs)
        if not refs:
            raise ConfigError("refs: expected at least one reference")
        counts = [int(r.n_worlds) for r in refs]
        if len(set(counts)) != 1:
            raise ConfigError(f"refs: all references must have the same n_worlds, got {counts}")
        self.refs = refs
        self.n_worlds = counts[0]
        self.n_vehicles = len(refs)
        self.duration: np.ndarray = np.max(
            [np.broadcast_to(np.asarray(r.duration, dtype=float), (self.n_worlds,)) for r in refs], axis=0
        )
        self._writers = _writers(refs, self.n_worlds)

    def __call__(self, t: float | ArrayLike) -> RefSample:
        """Sample at `t` (s, float or (W,)): pos/vel/acc (W, V, 3), yaw/yaw_rate (W, V)."""
        vec, ang, out = empty_sample(self.n_worlds, self.n_vehicles)
        self.fill(t, vec, ang)
        return out

    def fill(self, t: float | ArrayLike, vec: np.ndarray, ang: np.ndarray) -> None:
        """Sample at `t` into storage of `empty_sample`'s layout: vec (3, W, V, 3) (pos, vel, acc),
        ang (2, W, V) (yaw, yaw rate). A caller that samples every tick keeps its storage (the
        simulator's fused tick): the same sample as `self(t)`, without new arrays."""
        t = sample_times(t, self.n_worlds)
        for into, slots in self._writers:
            into(t, vec, ang, slots)


def _writers(refs: list[Reference], n_worlds: int) -> list[tuple[Callable[..., None], Any]]:
    """(into, slots) pairs: `into(t, vec, ang, slots)` fills those vehicle slots of a stacked sample.

    References of a class with `group_into` (possibly under one `TimeShifted`) share one `into`
    per class, with their slots (V_g,): one compiled call for, say, five circles, where one each
    cost more than the sample. Other references with `sample_into` fill their own slot v; any
    other Reference is sampled and copied. The slots are disjoint, so the order does not matter.
    """
    groups: dict[type, list[tuple[int, Reference, np.ndarray | None]]] = {}
    writers: list[tuple[Callable[..., None], Any]] = []
    for v, ref in enumerate(refs):
        inner, shift = ref, None
        if type(ref) is TimeShifted:
            t0 = np.asarray(ref.t0)
            if t0.dtype == np.float64 and t0.shape in ((), (n_worlds,)):  # else t + t0 is not plain float64 (W,)
                inner, shift = ref.ref, np.broadcast_to(t0, (n_worlds,))
        if hasattr(type(inner), "group_into"):
            groups.setdefault(type(inner), []).append((v, inner, shift))
        elif (into := getattr(ref, "sample_into", None)) is not None:
            writers.append((into, v))
        else:
            writers.append((functools.partial(_copy_into, ref), v))
    for cls, members in groups.items():
        slots, grouped, shifts = zip(*members)
        writers.append((cls.group_into(list(grouped), list(shifts)), np.array(slots, dtype=np.int64)))
    return writers


def _copy_into(ref: Reference, t: np.ndarray, vec: np.ndarray, ang: np.ndarray, v: int) -> None:
    """Sample `ref` at t and copy it into vehicle slot v (a Reference without `sample_into`)."""
    for dst, src in zip((vec[0, :, v], vec[1, :, v], vec[2, :, v], ang[0, :, v], ang[1, :, v]), ref(t)):
        dst[...] = src


def stack(refs: Sequence[Reference]) -> StackedReference:
    """Stack one reference per vehicle: `stack([Hover(leader), Lemniscate(c)])(t)`
    gives pos (W, 2, 3) etc. All refs must have the same `n_worlds` (ValueError)."""
    return StackedReference(refs)


class TimeShifted:
    """A batched reference sampled at t + t0 (per-world start phase t0 (W,) s)."""

    def __init__(self, ref: Reference, t0: np.ndarray):
        self.ref, self.t0 = ref, t0
        self.n_worlds = ref.n_worlds
        self.duration = ref.duration
        into = getattr(ref, "sample_into", None)
        if into is not None:  # stacked: write the slots in place too (see downwash_trajectories.base)
            self.sample_into = lambda t, vec, ang, v: into(t + self.t0, vec, ang, v)

    def __call__(self, t: Any) -> RefSample:
        return self.ref(np.asarray(t, dtype=float) + self.t0)


class Cached:
    """A reference that returns its last sample again when asked for the same times.

    An env samples the reference at the end of a step (observation, reward) and the
    next controller tick samples it at the same times: one evaluation serves both.
    Samples are shared between callers, which only read them.
    """

    def __init__(self, ref: Reference):
        self.ref = ref
        self.n_worlds = ref.n_worlds
        self.duration = ref.duration
        self._key: tuple | None = None
        self._sample: RefSample | None = None

    def __call__(self, t: Any) -> RefSample:
        t = np.asarray(t, dtype=float)
        key = (t.shape, t.tobytes())  # the times, bit for bit (a copy: the simulator's clock changes in place)
        if key != self._key:
            self._sample = self.ref(t)
            self._key = key
        return self._sample


class Offset:
    """`ref` moved by a fixed offset: the same velocity, acceleration and yaw.

    offset: (W, 3) or (3,) m, world frame (e.g. (0, 0, -0.6): 0.6 m beneath a leader).
    """

    def __init__(self, ref: Reference, offset: ArrayLike):
        off = np.array(offset, dtype=float)
        if off.shape not in ((3,), (ref.n_worlds, 3)) or not np.all(np.isfinite(off)):
            raise ConfigError(f"offset: expected 3 finite numbers or shape ({ref.n_worlds}, 3) in m, got {offset!r}")
        self.ref, self.offset = ref, off
        self.n_worlds = ref.n_worlds
        self.duration = ref.duration

    def __call__(self, t: Any) -> RefSample:
        s = self.ref(t)
        return RefSample(s.pos + self.offset, s.vel, s.acc, s.yaw, s.yaw_rate)


class Relative:
    """`pattern` flown relative to a moving `base`: the pattern's displacement from `origin` added to the
    base, so a follower's collection patterns around a hovering leader's position become the same
    patterns beneath a moving leader::

        pos = base.pos + (pattern.pos - origin),  vel = base.vel + pattern.vel,  acc = base.acc + pattern.acc

    with the pattern's yaw. base, pattern: references of the same n_worlds; origin (3,) or (W, 3) m,
    the point the pattern was laid out around (the hovering leader's position). `duration` is the
    pattern's.
    """

    def __init__(self, base: Reference, pattern: Reference, origin: ArrayLike):
        if int(base.n_worlds) != int(pattern.n_worlds):
            raise ConfigError(f"base, pattern: expected the same n_worlds, got {base.n_worlds} and {pattern.n_worlds}")
        o = np.array(origin, dtype=float)
        if o.shape not in ((3,), (int(base.n_worlds), 3)) or not np.all(np.isfinite(o)):
            raise ConfigError(f"origin: expected 3 finite numbers or shape ({base.n_worlds}, 3) in m, got {origin!r}")
        self.base, self.pattern, self.origin = base, pattern, o
        self.n_worlds = int(base.n_worlds)
        self.duration = pattern.duration

    def __call__(self, t: Any) -> RefSample:
        b, p = self.base(t), self.pattern(t)
        return RefSample(b.pos + (p.pos - self.origin), b.vel + p.vel, b.acc + p.acc, p.yaw, p.yaw_rate)
