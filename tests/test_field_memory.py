"""A ground truth with memory in the loop (sim.field_memory): stepping, resets, the oracle, checks."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_trajectories import Hover, Lemniscate, stack
from sim.field import check_field
from sim.field_memory import FieldMemory, is_stateful_field
from sim.predictor import OraclePredictor, PerWorldPredictor, ZeroPredictor
from sim.scene import build_scene
from sim.simulator import Simulator

LEADER = np.array([0.0, 0.0, 2.5])


class _Age(NamedTuple):
    age: np.ndarray  # (W,) s since the wake started
    steps: np.ndarray  # (W,) steps taken


class GrowingPush:
    """A toy field with memory: every vehicle's wake pushes every other one down by `rate` times
    its age (m/s^2 per s), so the force tells how long the wake has been stepped."""

    def __init__(self, rate: float = 0.5):
        self.rate = rate

    def describe(self) -> dict:
        return {"type": "GrowingPush", "rate": self.rate}

    def initial_state(self, W: int, V: int) -> _Age:
        return _Age(np.zeros(W), np.zeros(W, np.int64))

    def step(self, state: _Age, dt: float, pos, vel, rot, thrust=None, wind=None) -> None:
        state.age[:] += dt
        state.steps[:] += 1

    def forces(self, state: _Age, pos, vel, rot) -> np.ndarray:
        W, V = pos.shape[:2]
        out = np.zeros((W, V, V, 3))
        out[..., 2] = -self.rate * state.age[:, None, None]
        out[:, np.arange(V), np.arange(V)] = 0.0
        return out


def _sim(W: int, field, predictor=None, seeds=None) -> Simulator:
    scene = build_scene()
    ref = stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=W)])
    return Simulator(scene, ref, list(range(W)) if seeds is None else seeds, field=field, predictor=predictor)


def test_the_toy_field_is_stateful_and_the_paper_law_is_not():
    from sim.field import DownwashField

    assert is_stateful_field(GrowingPush()) and not is_stateful_field(DownwashField())


def test_the_wake_is_stepped_once_per_autopilot_tick_and_acts_on_every_vehicle():
    sim = _sim(2, GrowingPush())
    rows = [sim.tick() for _ in range(5)]
    assert sim._plan is None and isinstance(rows[0], dict)  # a field with memory flies the readable path
    dt = sim.cfg.rates.autopilot_dt
    steps = 5 * sim.cfg.rates.autopilot_per_control
    assert sim._memory.state.steps.tolist() == [steps, steps]
    # the row holds the mean of the tick's first autopilot tick: age = (its index + 1) dt, one other vehicle
    for k, row in enumerate(rows):
        expected = -0.5 * (k * sim.cfg.rates.autopilot_per_control + 1) * dt
        np.testing.assert_allclose(row["field_mean"][:, :, 2], expected, rtol=1e-12)


def test_a_reset_world_starts_with_an_empty_wake_and_the_others_keep_theirs():
    sim = _sim(3, GrowingPush())
    for _ in range(4):
        sim.tick()
    before = sim._memory.state.age.copy()
    sim.reset(np.array([1]))
    assert sim._memory.state.age[1] == 0.0 and sim._memory.state.age[0] == before[0] == before[2]


def test_the_wake_lives_on_when_another_component_changes_and_starts_afresh_with_a_new_field():
    field = GrowingPush()
    sim = _sim(1, field)
    sim.tick()
    memory = sim._memory
    sim.predictor = OraclePredictor(field)  # the plan is rebound; the wake is kept
    sim.tick()
    assert sim._memory is memory
    sim.field = GrowingPush(rate=1.0)
    with pytest.raises(ConfigError, match="knows the wake only when the simulator flies that same field"):
        sim.tick()  # the oracle's field is not the one flown: nothing steps its wake
    sim.predictor = OraclePredictor(sim.field)
    sim.tick()
    assert sim._memory is not memory and sim._memory.state.steps[0] == sim.cfg.rates.autopilot_per_control


def test_batched_flights_equal_single_ones():
    sims = [_sim(3, GrowingPush(), seeds=[4, 5, 6])] + [_sim(1, GrowingPush(), seeds=[s]) for s in (4, 5, 6)]
    rows = [[s.tick()["pos"].copy() for _ in range(6)] for s in sims]
    for w in range(3):
        for a, b in zip(rows[0], rows[1 + w]):
            np.testing.assert_array_equal(a[w], b[0])


def test_the_oracle_of_a_field_with_memory_reads_the_wake_the_vehicles_feel():
    field = GrowingPush()
    sim = _sim(2, field, predictor=OraclePredictor(field))
    for _ in range(3):
        row = sim.tick()
    # the prediction is held from the last due autopilot tick: the truth of that tick, never 0
    assert np.all(row["f_hat"][:, :, 2] < 0)
    assert set(np.round(row["f_hat"][:, :, 2].ravel(), 12)) <= set(
        np.round(-0.5 * np.arange(1, 7) * sim.cfg.rates.autopilot_dt, 12))


def test_the_oracle_among_other_predictors_reads_its_own_worlds_wake():
    """An oracle of the wake in a PerWorldPredictor (the experiments' batches of conditions) reads the
    wake of its own worlds: the same prediction as an oracle flying alone in those worlds."""
    field = GrowingPush()
    routed = PerWorldPredictor([ZeroPredictor(), OraclePredictor(field)], np.array([0, 1, 1]))
    sim = _sim(3, field, predictor=routed, seeds=[0, 1, 2])
    alone = _sim(2, field, predictor=OraclePredictor(field), seeds=[1, 2])
    sim.reset(np.array([0]))  # world 0's wake starts afresh: the oracle's worlds keep theirs
    for _ in range(4):
        row, row_alone = sim.tick(), alone.tick()
    np.testing.assert_array_equal(row["f_hat"][0], 0.0)
    np.testing.assert_array_equal(row["f_hat"][1:], row_alone["f_hat"])
    assert np.all(row["f_hat"][1:, :, 2] < 0)


class _Broken(GrowingPush):
    def forces(self, state, pos, vel, rot):
        return np.zeros(pos.shape)  # (W, V, 3): not per pair


class _NaN(GrowingPush):
    def forces(self, state, pos, vel, rot):
        return np.full(pos.shape[:2] + pos.shape[1:], np.nan)


def test_a_field_with_memory_of_the_wrong_shape_or_nan_is_named_before_any_flight():
    with pytest.raises(ConfigError, match=r"_Broken: forces\(...\) must be \(W, V, V, 3\)"):
        check_field(_Broken())
    with pytest.raises(ConfigError, match="_NaN: returned non-finite"):
        check_field(_NaN())
    with pytest.raises(ConfigError, match="forces"):
        _sim(1, _Broken())


def test_the_memory_combines_by_the_aggregation_law():
    from sim.aggregation import make_aggregation

    W, V = 1, 3
    pos = np.array([[[0.0, 0.0, 2.5], [0.0, 0.0, 1.9], [0.0, 0.0, 1.3]]])
    vel, rot = np.zeros((W, V, 3)), np.broadcast_to(np.eye(3), (W, V, 3, 3)).copy()
    linear = FieldMemory(GrowingPush(), W, V, 0.01).advance(pos, vel, vel, rot, None)
    np.testing.assert_allclose(linear[..., 2], -2 * 0.5 * 0.01)  # two other vehicles, each 0.005
    law = make_aggregation("velocity")
    combined = FieldMemory(GrowingPush(), W, V, 0.01).advance(pos, vel, vel, rot, None, law)
    forces = GrowingPush().forces(_Age(np.full(W, 0.01), np.ones(W, np.int64)), pos, vel, rot)
    np.testing.assert_array_equal(combined, law.combine(forces, pos, rot))


# ----------------------------------------------------------------------------- the shed wake in the loop


def _hover_pair(W: int, kinds=None):
    scene = build_scene(kinds=kinds)
    ref = stack([Hover(LEADER, n_worlds=W), Hover(LEADER - [0, 0, 0.6], n_worlds=W)])
    return scene, ref


def test_the_shed_wake_reaches_the_follower_late_then_pushes_as_the_momentum_jet():
    from downwash_core.geometry import quat_to_mat
    from sim.fields.momentum import MomentumWake
    from sim.fields.registry import make_field

    scene, ref = _hover_pair(2)
    sim = Simulator(scene, ref, [0, 1], field=make_field("shed"))
    rows = [sim.tick() for _ in range(60)]  # 1.2 s: past the wake's age at 0.6 m
    first = rows[0]["field_mean"][:, 1, 2]
    assert np.all(first == 0.0)  # at t = 0 nothing has been shed yet: the wake has memory
    arrived = next(k for k, r in enumerate(rows) if np.all(r["field_mean"][:, 1, 2] < -1.0))
    assert 1 <= arrived <= 6  # about 0.06 s to travel 0.6 m at half the jet's speed, ticks of 0.02 s
    last = rows[-1]
    pos, vel, rot = last["pos"], last["vel"], quat_to_mat(last["quat"])
    steady = MomentumWake()(pos[:, 0], vel[:, 0], rot[:, 0], pos[:, 1], vel[:, 1])
    np.testing.assert_allclose(last["field_mean"][:, 1], steady, rtol=0.05, atol=0.05)


def test_the_shed_wake_takes_the_scenes_kinds():
    scene, ref = _hover_pair(1, kinds=["x500", "paper_quad"])
    from sim.fields.shed import ShedWake

    field = ShedWake()
    sim = Simulator(scene, ref, [0], field=field)
    sim.tick()
    assert sim._memory.source is field and sim._memory.field.vehicles == ("x500", "paper_quad")


def test_the_oracle_combines_the_wake_by_its_own_law_not_the_simulators():
    from sim.aggregation import make_aggregation
    from sim.field_memory import MemoryOracle

    W, V = 1, 3
    pos = np.array([[[0.0, 0.0, 2.5], [0.0, 0.0, 1.9], [0.0, 0.0, 1.3]]])
    vel, rot = np.zeros((W, V, 3)), np.broadcast_to(np.eye(3), (W, V, 3, 3)).copy()
    memory = FieldMemory(GrowingPush(), W, V, 0.01)
    law = make_aggregation("velocity")
    flown = memory.advance(pos, vel, vel, rot, None, law)  # the simulator's law
    linear = MemoryOracle(memory)(None)
    np.testing.assert_allclose(linear[..., 2], -2 * 0.5 * 0.01)  # the oracle's law: the plain sum of the two wakes
    np.testing.assert_array_equal(MemoryOracle(memory, law)(None), flown)
    assert not np.allclose(linear, flown)
