"""The fused tick's helper threads (sim.fork_join): same flights on any number of threads, parking,
stopping, forking, and the atomic counter they share."""

import gc
import multiprocessing
import sys
import threading
import time

import numpy as np
import pytest

from downwash_core.jit import njit
import sim.physics as sim_physics
from sim import fork_join
from sim.scene import build_scene
from sim.simulator import Simulator
from downwash_trajectories import Hover, Lemniscate, stack

LEADER = np.array([0.0, 0.0, 2.5])


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _reference(W):
    """Lemniscates below the leader; from t = 0.1 s on, every third world's follower is sent into the
    ground, one world after another (0.05 s apart), so that worlds end in the chunks of every
    thread, at different ticks."""
    follower = Lemniscate(LEADER - [0, 0, 0.6], n_worlds=W)
    start = np.full(W, np.inf)
    start[::3] = 0.1 + 0.05 * np.arange(len(start[::3]))

    def reference(t):
        ref = stack([Hover(LEADER, n_worlds=W), follower])(t)
        ref.pos[t >= start, 1, 2] = -1.0
        return ref

    return reference


def _helper_threads():
    return [t for t in threading.enumerate() if t.name.startswith("sim-helper")]


@pytest.mark.parametrize("n_threads", [2, 3])
def test_threads_fly_the_flight_of_one_thread_with_pauses_and_ending_worlds(scene, n_threads, monkeypatch):
    """Random pauses between ticks (none, shorter and longer than a helper's spin before it parks)
    and worlds that end in every chunk: rows, states and statuses equal the one-thread flight.
    Three threads on a two-core machine take turns (slowly), which is all this needs: the
    check that refuses more threads than cores is lifted here."""
    monkeypatch.setattr(sim_physics, "usable_cores", lambda: max(n_threads, sim_physics.os.cpu_count() or 1))
    W = 24
    sims = [Simulator(scene, _reference(W), list(range(W)), n_threads=n) for n in (1, n_threads)]
    assert sims[0]._plan.n_threads == 1 and sims[1]._plan.n_threads == n_threads
    pauses = np.random.default_rng(0).choice([0.0, 2e-4, 5e-3], size=90)
    for k, pause in enumerate(pauses):
        rows = [dict(sim.tick()) for sim in sims]
        for name in rows[0]:
            assert np.array_equal(rows[0][name], rows[1][name], equal_nan=True), (k, name)
        time.sleep(pause)
    one, many = sims
    assert (~many.active).sum() == W // 3  # worlds ended one by one, in several threads' chunks
    assert np.array_equal(one.status, many.status) and one.message == many.message
    assert np.array_equal(one.physics.qpos, many.physics.qpos, equal_nan=True)


def test_idle_helpers_park_and_wake_for_the_next_tick(scene):
    W = 16
    a, b = (Simulator(scene, _reference(W), list(range(W)), n_threads=n) for n in (1, 2))
    a.tick(), b.tick()
    deadline = time.monotonic() + 5.0
    while b._helpers.ctl[fork_join.PARKED] != 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert b._helpers.ctl[fork_join.PARKED] == 1  # no tick for a while: the helper left its spin
    for _ in range(5):
        a.tick(), b.tick()
    assert np.array_equal(a.physics.qpos, b.physics.qpos)


def test_helpers_serve_every_plan_of_their_simulator(scene):
    """A replaced component rebuilds the plan (an env does it at each autoreset with randomised
    fields): the same helper threads serve the new plan, and the flights stay equal."""
    W = 16
    a, b = (Simulator(scene, _reference(W), list(range(W)), n_threads=n) for n in (1, 2))
    a.tick(), b.tick()
    helpers, threads = b._helpers, len(_helper_threads())
    for k in range(6):
        enabled = np.arange(W) % (k + 2) != 0
        for sim in (a, b):
            sim.field_enabled = enabled.copy()  # a bound input: the next tick binds a new plan
        plan = b._plan
        rows = [dict(sim.tick()) for sim in (a, b)]
        assert b._plan is not plan and b._helpers is helpers and len(_helper_threads()) == threads
        for name in rows[0]:
            assert np.array_equal(rows[0][name], rows[1][name]), (k, name)


def _settled_helper_count() -> int:
    """The helper threads alive once the simulators of earlier tests are collected and their
    helpers have stopped (a helper stops a moment after its simulator goes)."""
    gc.collect()
    deadline = time.monotonic() + 5.0
    n = len(_helper_threads())
    while n and time.monotonic() < deadline:
        time.sleep(0.01)
        n = len(_helper_threads())
    return n


def test_helpers_stop_with_their_simulator(scene):
    before = _settled_helper_count()
    sim = Simulator(scene, _reference(16), list(range(16)), n_threads=2)
    sim.tick()
    assert len(_helper_threads()) == before + 1
    del sim
    gc.collect()
    deadline = time.monotonic() + 5.0
    while len(_helper_threads()) > before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(_helper_threads()) == before


def _tick_in_child(sim, n, queue):
    for _ in range(n):
        sim.tick()
    queue.put(sim.physics.qpos.copy())


@pytest.mark.skipif(sys.platform != "linux", reason="fork is the start method under test; Linux only")
def test_a_forked_child_starts_helpers_of_its_own(scene):
    """The child's copy of the simulator has no helper threads: it starts its own instead of
    waiting for threads that do not exist, and flies on as the parent does."""
    sim = Simulator(scene, _reference(16), list(range(16)), n_threads=2)
    for _ in range(5):
        sim.tick()
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_tick_in_child, args=(sim, 10, queue))
    child.start()
    for _ in range(10):
        sim.tick()
    child_qpos = queue.get(timeout=120)
    child.join(timeout=60)
    assert child.exitcode == 0
    assert np.array_equal(child_qpos, sim.physics.qpos, equal_nan=True)


@njit
def _count(ctl, n, seen):
    for i in range(n):
        seen[i] = fork_join.fetch_add(ctl.ctypes.data + 8 * fork_join.NEXT, 1)


def test_fetch_add_hands_out_every_value_once_across_threads():
    n = 200_000
    ctl = fork_join.new_control()
    seen = [np.empty(n, np.int64) for _ in range(2)]
    _count(ctl, 1, np.empty(1, np.int64))  # compiled before the race
    ctl[fork_join.NEXT] = 0
    threads = [threading.Thread(target=_count, args=(ctl, n, s)) for s in seen]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert ctl[fork_join.NEXT] == 2 * n
    assert np.array_equal(np.sort(np.concatenate(seen)), np.arange(2 * n))


def test_join_names_a_dead_helper_instead_of_waiting_forever():
    ctl = fork_join.new_control()
    owner = type("Owner", (), {})()
    helpers = fork_join.Helpers(1, lambda t: fork_join.EXIT, ctl, owner)  # the thread ends at once
    for thread in helpers._threads:
        thread.join(timeout=5)
    ctl[fork_join.GEN] = 1  # a tick that no helper will report
    with pytest.raises(RuntimeError, match="helper thread has died"):
        helpers.join()
    with pytest.raises(ValueError, match="n_helpers: expected 1..64, got 0"):
        fork_join.Helpers(0, lambda t: fork_join.EXIT, ctl, owner)
