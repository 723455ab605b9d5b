"""`Recorded`: recorded setpoints played back. Analytic answers (a circle within the linear
interpolation bound, a line's derived velocity exact, the ends held at rest), batched equals one
by one, stacking, and every bad input named."""

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_trajectories import Circle, Recorded, Reference, stack


def _circle(r=0.8, omega=1.3, h=0.05, n=200):
    t = np.arange(n) * h
    th = omega * t
    pos = np.stack([r * np.cos(th), r * np.sin(th), np.full(n, 1.0)], axis=1)
    vel = np.stack([-r * omega * np.sin(th), r * omega * np.cos(th), np.zeros(n)], axis=1)
    acc = np.stack([-r * omega**2 * np.cos(th), -r * omega**2 * np.sin(th), np.zeros(n)], axis=1)
    return t, pos, vel, acc


def test_a_recorded_circle_plays_back_within_the_interpolation_bound():
    r, omega, h = 0.8, 1.3, 0.05
    t, pos, vel, acc = _circle(r, omega, h)
    ref = Recorded(t, pos, vel, acc)
    truth = Circle([0.0, 0.0, 1.0], radius=r, speed=r * omega)
    mid = t[:-1] + 0.37 * h  # between samples, where linear interpolation errs most
    for tk in mid[::7]:
        got, want = ref(tk), truth(tk)
        # |f - interp f| <= h^2 / 8 max|f''| per component; the chord of the circle lies inside it
        for name, bound in (("pos", r * omega**2), ("vel", r * omega**3), ("acc", r * omega**4)):
            err = np.linalg.norm(getattr(got, name) - getattr(want, name))
            assert err <= h**2 / 8 * bound * np.sqrt(2) + 1e-12, name
    at = ref(t[10])
    np.testing.assert_array_equal(at.pos[0], pos[10])  # on a sample: the sample
    assert np.all(at.yaw == 0.0) and np.all(at.yaw_rate == 0.0)
    assert isinstance(ref, Reference) and ref.duration == pytest.approx(t[-1]) and ref.n_worlds == 1


def test_a_circle_without_recorded_derivatives_derives_them_to_second_order():
    r, omega, h = 0.8, 1.3, 0.01
    t, pos, vel, acc = _circle(r, omega, h, n=400)
    ref = Recorded(t, pos)
    inner = slice(2, -2)  # one-sided at the ends
    np.testing.assert_allclose(ref.vel[0, inner], vel[inner], atol=r * omega**3 * h**2 / 6 * 1.01)
    np.testing.assert_allclose(ref.acc[0, inner], acc[inner], atol=2 * r * omega**4 * h**2 / 6 * 1.01)


def test_the_derived_velocity_of_a_line_is_its_slope_exactly():
    t = np.array([0.0, 0.1, 0.25, 0.3, 0.7, 1.0])  # uneven steps
    slope = np.array([0.5, -0.25, 0.125])  # m/s, exact in binary
    pos = np.array([0.0, 1.0, 2.0]) + t[:, None] * slope
    ref = Recorded(t, pos)
    np.testing.assert_allclose(ref.vel[0], np.tile(slope, (t.size, 1)), rtol=0, atol=1e-14)
    np.testing.assert_allclose(ref.acc[0], 0.0, atol=1e-12)
    s = ref(0.5)
    np.testing.assert_allclose(s.pos[0], [0.0, 1.0, 2.0] + 0.5 * slope, atol=1e-15)
    np.testing.assert_allclose(s.vel[0], slope, atol=1e-14)


def test_the_ends_are_held_at_rest():
    t = np.array([0.5, 1.0, 2.0])
    pos = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 2.0, 1.5]])
    ref = Recorded(t, pos)
    for when, end in ((0.0, 0), (0.2, 0), (2.5, -1), (100.0, -1)):
        s = ref(when)
        np.testing.assert_array_equal(s.pos[0], pos[end])
        np.testing.assert_array_equal(s.vel[0], 0.0)
        np.testing.assert_array_equal(s.acc[0], 0.0)
    np.testing.assert_array_equal(ref(2.0).pos[0], pos[-1])  # the last sample itself
    np.testing.assert_array_equal(ref(2.0).vel[0], ref.vel[0, -1])
    assert ref.duration == 2.0


def test_batched_equals_one_by_one_and_per_world_times():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.005, 0.03, 50))
    pos = rng.normal(size=(4, 50, 3))
    vel = rng.normal(size=(4, 50, 3))
    batched = Recorded(t, pos, vel)
    singles = [Recorded(t, pos[w], vel[w]) for w in range(4)]
    times = np.array([t[0] - 1.0, t[7] + 0.001, t[30], t[-1] + 2.0])
    got = batched(times)
    for w, ref in enumerate(singles):
        one = ref(times[w])
        for a, b in zip(got, one):
            np.testing.assert_array_equal(a[w], b[0])
    shared = batched(t[12] + 0.002)
    for w, ref in enumerate(singles):
        np.testing.assert_array_equal(shared.pos[w], ref(t[12] + 0.002).pos[0])
    # (N, 3) shared by n_worlds worlds
    wide = Recorded(t, pos[1], n_worlds=3)
    assert wide.n_worlds == 3
    np.testing.assert_array_equal(wide(times[:3]).pos[2], singles[1](times[2]).pos[0])


def test_stacked_vehicles_sample_like_each_alone():
    t = np.linspace(0.0, 2.0, 21)
    a = Recorded(t, np.stack([t, 0 * t, 1 + 0 * t], axis=1))
    b = Recorded(t, np.stack([0 * t, t**2, 0.5 + 0 * t], axis=1))
    both = stack([a, b])
    s = both(np.array([0.33]))
    assert s.pos.shape == (1, 2, 3) and s.yaw.shape == (1, 2)
    for v, ref in enumerate((a, b)):
        one = ref(0.33)
        np.testing.assert_array_equal(s.pos[:, v], one.pos)
        np.testing.assert_array_equal(s.vel[:, v], one.vel)
        np.testing.assert_array_equal(s.acc[:, v], one.acc)


@pytest.mark.parametrize("t,pos,kw,match", [
    ([0.0, 0.1, 0.1], np.zeros((3, 3)), {}, r"t: sample 2 \(0.1 s\) does not follow sample 1 .*strictly increasing"),
    ([0.0, 0.2, 0.1], np.zeros((3, 3)), {}, r"t: sample 2 .*strictly increasing"),
    ([0.0, np.nan, 0.2], np.zeros((3, 3)), {}, r"t: sample 1 is nan; allowed: finite"),
    ([0.0], np.zeros((1, 3)), {}, r"t: expected a 1-D array of at least 2"),
    ([0.0, 0.1, 0.2], np.zeros((2, 3)), {}, r"pos: expected shape \(3, 3\) or \(W, 3, 3\) in m.*got \(2, 3\)"),
    ([0.0, 0.1, 0.2], np.zeros((3, 2)), {}, r"pos: expected shape \(3, 3\)"),
    ([0.0, 0.1, 0.2], [[0, 0, 0], [0, np.nan, 0], [0, 0, 0]], {}, r"pos: sample 1 is not finite; allowed: finite"),
    ([0.0, 0.1, 0.2], np.zeros((3, 3)), {"vel": np.full((3, 3), np.inf)}, r"vel: sample 0 is not finite.*m/s"),
    ([0.0, 0.1, 0.2], np.zeros((3, 3)), {"acc": np.zeros((4, 3))}, r"acc: expected shape \(3, 3\) or \(W, 3, 3\)"),
    ([0.0, 0.1, 0.2], np.zeros((2, 3, 3)), {"vel": np.zeros((3, 3, 3))}, r"disagree on the number of worlds"),
    ([0.0, 0.1, 0.2], np.zeros((2, 3, 3)), {"n_worlds": 3}, r"n_worlds: got 3 but pos is batched over 2"),
])
def test_bad_input_is_named(t, pos, kw, match):
    with pytest.raises(ConfigError, match=match):
        Recorded(t, pos, **kw)


def test_bad_sample_times_are_named():
    ref = Recorded([0.0, 1.0], np.zeros((2, 3)), n_worlds=2)
    with pytest.raises(ConfigError, match=r"t: expected a float or shape \(2,\)"):
        ref(np.zeros(3))
