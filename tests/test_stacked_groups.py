"""A stack fills references of one class together (`group_into`, e.g. formation5's five circles in one
compiled call): every vehicle's sample must be, bit for bit, its reference sampled on its own."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_trajectories import Circle, Hover, Lemniscate, TimeShifted, Transect, stack

KINDS = ["circle", "shifted_circle", "twice_shifted_circle", "int_shifted_circle", "hover", "lemniscate",
         "shifted_lemniscate", "transect", "opaque"]


class Opaque:
    """A Reference without `sample_into`: the stack samples and copies it."""

    def __init__(self, ref):
        self.ref, self.n_worlds, self.duration = ref, ref.n_worlds, ref.duration

    def __call__(self, t):
        return self.ref(t)


def _circle(rng, W, batched):
    size = W if batched else None
    return Circle(rng.normal(size=(W, 3) if batched else 3) * 5, radius=rng.uniform(0.05, 20, size),
                  speed=rng.choice([-1, 1], size) * rng.uniform(0.01, 10, size), phase=rng.uniform(-50, 50, size),
                  n_worlds=W)


def _make(kind, rng, W, batched):
    if kind == "circle":
        return _circle(rng, W, batched)
    if kind == "shifted_circle":
        return TimeShifted(_circle(rng, W, batched), rng.uniform(-100, 100, W) if batched else float(rng.uniform(0, 9)))
    if kind == "twice_shifted_circle":  # t + t0 + t1 is not t + (t0 + t1): not grouped, still exact
        return TimeShifted(TimeShifted(_circle(rng, W, batched), rng.uniform(0, 10, W)), rng.uniform(0, 10, W))
    if kind == "int_shifted_circle":  # an integer t0: not grouped, still exact
        return TimeShifted(_circle(rng, W, batched), rng.integers(0, 10, W))
    if kind == "hover":
        return Hover(rng.normal(size=(W, 3)))
    if kind == "lemniscate":
        return Lemniscate(rng.normal(size=(W, 3)), rng.uniform(0.1, 2, W), rng.uniform(0.1, 1, W), rng.uniform(2, 30, W))
    if kind == "shifted_lemniscate":
        return TimeShifted(Lemniscate(rng.normal(size=3), 0.3, 0.15, 10.0, n_worlds=W), rng.uniform(0, 10, W))
    if kind == "transect":
        return Transect(rng.normal(size=(W, 3)), rng.normal(size=W), rng.uniform(0.1, 2, W), rng.uniform(2, 30, W))
    return Opaque(_circle(rng, W, batched))


def _same_bits(a, b):
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


@settings(max_examples=150, deadline=None)
@given(
    kinds=st.lists(st.sampled_from(KINDS), min_size=1, max_size=8),
    n_circles=st.integers(0, 8),
    W=st.sampled_from([1, 3, 64]),
    batched=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
    times=st.sampled_from(["float", "per_world", "zero", "minus_zero", "far"]),
)
def test_a_stack_samples_every_reference_bit_for_bit_as_on_its_own(kinds, n_circles, W, batched, seed, times):
    rng = np.random.default_rng(seed)
    kinds = list(kinds) + ["circle"] * n_circles  # groups of up to 16 circles, interleaved with the rest
    rng.shuffle(kinds)
    refs = [_make(k, rng, W, batched) for k in kinds]
    t = {"float": float(rng.uniform(-20, 100)), "per_world": rng.uniform(-20, 100, W), "zero": 0.0,
         "minus_zero": np.full(W, -0.0), "far": rng.uniform(-1e6, 1e6, W)}[times]
    stacked = stack(refs)(t)
    for v, ref in enumerate(refs):
        alone = ref(t)
        for field, want in zip(stacked, alone):
            assert _same_bits(field[:, v], want), (kinds[v], v)


def test_circles_of_a_stack_are_filled_in_one_call_and_match_the_numpy_formula():
    """formation5's five circles (alternate ones turning the other way, two of them shifted): one
    writer; the samples are the circle's closed form (the kernel replaced NumPy expressions)."""
    W = 3
    refs = [Circle([0.0, 0.0, 2.5 - 0.45 * k], radius=0.4, speed=0.5 if k % 2 == 0 else -0.5,
                   phase=k * 2.0 * np.pi / 5.0, n_worlds=W) for k in range(5)]
    refs[3] = TimeShifted(refs[3], np.array([0.0, 1.0, 2.0]))
    refs[4] = TimeShifted(refs[4], 4.5)
    ref = stack(refs)
    assert len(ref._writers) == 1
    t = np.array([0.0, 1.3, 77.0])
    s = ref(t)
    for v, r in enumerate(refs):
        c, t0 = (r.ref, r.t0) if isinstance(r, TimeShifted) else (r, 0.0)
        th = c.phase + c._omega * (t + t0)
        rel = np.stack([np.cos(th), np.sin(th), np.zeros(W)], axis=1)
        om = c._omega[:, None]
        np.testing.assert_allclose(s.pos[:, v], c.center + c.radius[:, None] * rel, rtol=0, atol=1e-14)
        np.testing.assert_allclose(s.vel[:, v], om * c.radius[:, None] * rel[:, [1, 0, 2]] * [-1, 1, 0],
                                   rtol=0, atol=1e-14)
        np.testing.assert_allclose(s.acc[:, v], -om**2 * c.radius[:, None] * rel, rtol=0, atol=1e-14)
        assert np.all(s.yaw[:, v] == 0.0) and np.all(s.yaw_rate[:, v] == 0.0)
