"""A controller without a compiled form flies the readable path, and the simulator says so once."""

import logging

import numpy as np
import pytest

from controllers.lqr import FeedbackLinearisedLQR
from sim.scene import build_scene
from sim.simulator import Simulator
from downwash_trajectories import Hover, Lemniscate, stack

LEADER = np.array([0.0, 0.0, 2.5])


class MyLQR(FeedbackLinearisedLQR):
    """A user's controller: the built-in LQR's subclass (it could override `command_setpoint`)."""


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _lemniscate(W):
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=W)])


def _fallback_warnings(caplog):
    return [r for r in caplog.records if r.levelno == logging.WARNING and "readable path" in r.getMessage()]


def test_a_user_controller_is_warned_about_once_per_simulator(scene, caplog):
    with caplog.at_level(logging.WARNING):
        sim = Simulator(scene, _lemniscate(2), [0, 1], controller=MyLQR())
        assert sim._plan is None
        for _ in range(3):
            sim.tick()
        sim.controller = MyLQR()  # a rebind: still the same simulator, no second warning
        sim.tick()
        sim.reset(np.arange(2))
        sim.tick()
    warnings = _fallback_warnings(caplog)
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    message = warnings[0].getMessage()
    assert "MyLQR" in message and "FeedbackLinearisedLQR" in message and "2x slower" in message
    assert warnings[0].name == "sim.simulator"

    caplog.clear()
    with caplog.at_level(logging.WARNING):
        Simulator(scene, _lemniscate(1), [0], controller=MyLQR()).tick()  # another simulator: its own warning
    assert len(_fallback_warnings(caplog)) == 1


def test_the_built_in_controller_and_fast_false_are_not_warned_about(scene, caplog):
    with caplog.at_level(logging.WARNING):
        sim = Simulator(scene, _lemniscate(1), [0])
        assert sim._plan is not None
        sim.tick()
        Simulator(scene, _lemniscate(1), [0], controller=FeedbackLinearisedLQR()).tick()
        Simulator(scene, _lemniscate(1), [0], controller=MyLQR(), fast=False).tick()  # asked for: no warning
    assert _fallback_warnings(caplog) == []


def test_a_user_controller_switched_in_later_is_warned_about(scene, caplog):
    with caplog.at_level(logging.WARNING):
        sim = Simulator(scene, _lemniscate(1), [0])
        sim.tick()
        sim.controller = MyLQR()
        sim.tick()
        assert sim._plan is None
    assert len(_fallback_warnings(caplog)) == 1


def test_the_readable_path_of_a_user_controller_flies_the_same_flight(scene):
    """The subclass computes what the LQR computes: the same bits on the readable path as the
    built-in controller on the fused one (what the warning costs is time only)."""
    rows = []
    for controller in (FeedbackLinearisedLQR(), MyLQR()):
        sim = Simulator(scene, _lemniscate(2), [3, 4], controller=controller)
        rows.append([dict(sim.tick()) for _ in range(20)])
    for a, b in zip(*rows):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
