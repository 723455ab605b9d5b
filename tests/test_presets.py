"""N-vehicle presets: sizes, roles, clearance at the start and along the flight, bad specs."""

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_core.roles import MAX_VEHICLES, Role
from sim.presets import PRESETS, make_preset
from sim.scene import build_scene, check_clearance

SPECS = ["pair", "stack3", "stack4", "stack:n=2", "stack:n=8", "stack:n=5,spacing=0.5", "swap", "formation5"]


@pytest.mark.parametrize("spec", SPECS)
def test_preset_scene_and_reference_agree(spec):
    p = make_preset(spec)
    scene = p.scene()
    assert scene.n_vehicles == p.n_vehicles and 2 <= p.n_vehicles <= MAX_VEHICLES
    assert scene.roles[0] == Role.LEADER and all(r == Role.FOLLOWER for r in scene.roles[1:])
    ref = p.reference(4)
    s = ref(np.zeros(4))
    assert s.pos.shape == (4, p.n_vehicles, 3)
    # the worlds are identical copies
    np.testing.assert_array_equal(s.pos, np.broadcast_to(s.pos[:1], s.pos.shape))


@pytest.mark.parametrize("spec", SPECS)
def test_no_two_references_ever_come_within_the_collision_ellipsoid(spec):
    """The presets are flyable: along the whole duration the references keep apart and above 0.5 m."""
    p = make_preset(spec)
    ref = p.reference(1)
    for t in np.linspace(0.0, p.duration, 301):
        pos = ref(np.full(1, t)).pos
        check_clearance(pos, [n for n, _ in p.vehicles], 0.26, 0.08)
        assert pos[..., 2].min() >= 0.5


def test_stack_vehicles_are_each_in_the_wake_of_the_one_above():
    """In a stack, vehicle k's lemniscate is centred 0.6 k m below the top: it crosses the axis above it."""
    p = make_preset("stack4")
    ts = np.linspace(0.0, p.duration, 401)
    pos = np.stack([p.reference(1)(np.full(1, t)).pos[0] for t in ts])  # (T, V, 3)
    for k in range(1, 4):
        np.testing.assert_allclose(pos[:, k, 2], pos[0, 0, 2] - 0.6 * k)
        lateral = np.hypot(*(pos[:, k, :2] - pos[:, 0, :2]).T)
        assert lateral.min() < 0.01 and lateral.max() > 0.2  # through the axis and out of the core


def test_every_vehicle_of_the_formation_moves():
    p = make_preset("formation5")
    s = p.reference(1)(np.zeros(1))
    assert np.all(np.linalg.norm(s.vel[0], axis=-1) > 0.4)


def test_swap_crosses_beneath_the_top():
    p = make_preset("swap")
    ref = p.reference(1)
    ys = np.array([ref(np.full(1, t)).pos[0, 1:, 1] for t in np.linspace(0, p.duration, 81)])  # (T, 2) y
    assert np.all(np.sign(ys[0]) == np.array([-1, 1]))  # opposite ends at the start
    assert np.any(np.diff(np.sign(ys[:, 0] - ys[:, 1])) != 0)  # they pass each other


@pytest.mark.parametrize("spec, message", [
    ("nope", "unknown 'nope'.*allowed: pair"),
    ("stack:n=9", "2-8 vehicles, got 9"),
    ("stack:n=1", "2-8 vehicles, got 1"),
    ("stack:n=x", r"'stack:n=x': preset 'stack' parameter n='x': expected an integer"),
    ("stack:spacing=0.1", "spacing: allowed 0.3-2.0"),
    ("swap:n=3", "allowed: no parameters"),
])
def test_bad_preset_specs_are_named(spec, message):
    with pytest.raises(ConfigError, match=message):
        make_preset(spec)


def test_scene_size_is_checked():
    with pytest.raises(ConfigError, match="1-8 vehicles, got 9"):
        build_scene([f"v{i}" for i in range(9)])


def test_vehicles_starting_inside_each_other_are_refused():
    pos = np.array([[0.0, 0.0, 2.5], [0.1, 0.0, 2.52], [0.0, 0.0, 1.0]])
    with pytest.raises(ConfigError, match="a and b start inside each other"):
        check_clearance(pos, ["a", "b", "c"], 0.26, 0.08)
    check_clearance(pos[[0, 2]], ["a", "c"], 0.26, 0.08)  # far apart: fine


def test_presets_listed():
    assert set(PRESETS) == {"pair", "stack3", "stack4", "stack", "swap", "formation5", "heavy_over_light",
                            "crazyflie_stack", "mixed_formation"}  # the last three of mixed kinds: test_heterogeneous


def test_n_vehicle_flights_batched_equal_serial_and_are_deterministic():
    """formation5 under the nonlinear velocity law with wind: world k of a batch of 3 is, bit for bit, the
    flight of seed k alone, and flying again gives the same logs."""
    from sim.aggregation import make_aggregation
    from sim.flight import fly
    from sim.wind import DrydenWind

    p = make_preset("formation5")
    kwargs = dict(aggregation=make_aggregation("velocity"), wind=DrydenWind.preset("light", mean=(1.0, 0.0, 0.0)))
    batch = fly(p.scene(), p.reference(3), [5, 6, 7], 1.0, **kwargs)
    for k, seed in enumerate([5, 6, 7]):
        alone = fly(p.scene(), p.reference(1), [seed], 1.0, **kwargs)[0]
        for name, array in alone.arrays.items():
            np.testing.assert_array_equal(batch[k][name], array, err_msg=name)
    again = fly(p.scene(), p.reference(3), [5, 6, 7], 1.0, **kwargs)
    for a, b in zip(batch, again):
        for name in a.arrays:
            np.testing.assert_array_equal(a[name], b[name])
    # every vehicle feels the others: the bottom one's field is non-zero at some point
    assert np.abs(batch[0]["field_mean"][:, 4]).max() > 0.1
    assert batch[0].meta["aggregation"]["name"] == "velocity" and "wind" in batch[0].arrays
