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


def test_threads_fly_the_flight_of_one_thread_on_a_busy_machine(scene):
    """With a busy process per core, the helper joins late, takes a few chunks or none, and the
    caller runs ticks alone for a while: the flight is the one-thread flight all the same."""
    import subprocess

    W = 24
    sims = [Simulator(scene, _reference(W), list(range(W)), n_threads=n) for n in (1, 2)]
    assert sims[1]._plan.n_threads == 2
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(sim_physics.os.cpu_count() or 2)]
    try:
        for k in range(120):
            rows = [dict(sim.tick()) for sim in sims]
            for name in rows[0]:
                assert np.array_equal(rows[0][name], rows[1][name], equal_nan=True), (k, name)
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    assert np.array_equal(sims[0].physics.qpos, sims[1].physics.qpos, equal_nan=True)


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
    ctl[fork_join.JOINED] = 1  # a tick that a helper joined and will never report
    with pytest.raises(RuntimeError, match="helper thread has died"):
        helpers.end_tick(fork_join.NOT_JOINED, 1)
    with pytest.raises(ValueError, match="n_helpers: expected 1..64, got 0"):
        fork_join.Helpers(0, lambda t: fork_join.EXIT, ctl, owner)


def _open_tick(ctl):
    """What a MAIN call does first: publish (placeholder arguments) and open a new generation."""
    z3, z2 = np.zeros((1, 1, 3)), np.zeros((1, 1))
    fork_join.publish(ctl, np.zeros(1, np.int64), np.zeros(1), np.zeros((1, 4), np.int64), z3, z3, z3, z2, z2, z3, z3,
                      np.zeros(1), 0, 0, 1)


def test_the_caller_waits_only_for_helpers_that_joined():
    """A helper that the OS has not scheduled (or that is parked) never holds up a tick: the caller
    closes it and returns at once; the late helper does not join a closed tick."""
    ctl = fork_join.new_control()
    ctl[fork_join.SPINS_MIN], ctl[fork_join.SEEN + fork_join.BUDGET] = 1_000, 50_000
    _open_tick(ctl)
    assert fork_join.join(ctl, 7) == 7  # no helper joined: no wait
    assert fork_join.await_tick(ctl, 0) == fork_join.IDLE  # came too late: spins out instead of joining
    assert ctl[fork_join.SEEN + fork_join.BUDGET] == 50_000 // 4  # halved twice: late, then idle
    assert ctl[fork_join.GEN] % fork_join._CLOSED == 0  # nobody counted in


def test_a_joined_helper_is_waited_for_and_its_result_added():
    ctl = fork_join.new_control()
    ctl[fork_join.SEEN + fork_join.BUDGET] = 100_000
    _open_tick(ctl)
    assert fork_join.await_tick(ctl, 0) == 1  # joined the open tick
    assert fork_join.join(ctl, 7) == fork_join.NOT_JOINED  # it has not reported yet
    fork_join.report(ctl, 0, 5, 2)
    owner = type("Owner", (), {})()
    helpers = fork_join.Helpers(1, lambda t: fork_join.EXIT, ctl, owner)
    assert helpers.end_tick(fork_join.NOT_JOINED, 1) == 12
    assert ctl[fork_join.HELPED] == 2


def test_spin_budgets_shrink_when_spinning_does_not_pay():
    ctl = fork_join.new_control()
    line = fork_join.SEEN + fork_join.BUDGET
    ctl[fork_join.SPINS_MIN], ctl[fork_join.SPINS_MAX] = 1_000, 64_000
    ctl[line] = 64_000
    assert fork_join.await_tick(ctl, 0) == fork_join.IDLE  # no tick came
    assert ctl[line] == 32_000
    for _ in range(40):
        fork_join.report(ctl, 0, 0, 0)  # joined, but every chunk was already taken
    assert ctl[line] == 1_000
    fork_join.report(ctl, 0, 0, 1)  # took a chunk: the budget stays
    assert ctl[line] == 1_000


class _Clock:
    """A stand-in for time.perf_counter that a test advances by hand."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def _ticks(helpers, clock, n, with_cost, alone_cost, helped=True):
    """Run n ticks as the caller does; each costs with_cost or alone_cost seconds as it runs with
    the helpers or alone (the helpers take a chunk of each if `helped`); returns the ways taken."""
    ways = []
    for _ in range(n):
        with_helpers = helpers.start_tick()
        clock.now += with_cost if with_helpers else alone_cost
        if with_helpers and helped:
            helpers.ctl[fork_join.HELPED] += 1
        helpers.end_tick(0, 1)
        ways.append(with_helpers)
    return ways


def _runs(ways):
    """[(way, length)] of consecutive equal ways."""
    out = []
    for w in ways:
        if out and out[-1][0] == w:
            out[-1][1] += 1
        else:
            out.append([w, 1])
    return [tuple(r) for r in out]


@pytest.fixture
def idle_helpers(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(fork_join.time, "perf_counter", clock)
    helpers = fork_join.Helpers(1, lambda t: fork_join.EXIT, fork_join.new_control(), type("Owner", (), {})())
    return helpers, clock


def test_the_caller_runs_alone_while_its_helpers_take_no_chunk(idle_helpers):
    """Helpers that take no chunk several ticks in a row (no core is free for them in time) are not
    woken for a spell of ticks, which doubles each time they fail again."""
    helpers, clock = idle_helpers
    T, C, U, F = fork_join._TRIAL_TICKS, fork_join._TRIAL_TICKS, fork_join._USELESS_TICKS, fork_join._ALONE_FIRST
    # (ticks with the helpers timed as fast: only the chunks they did not take count against them)
    ways = _ticks(helpers, clock, T + C + U + F + U + 2 * F + 1, 1e-3, 2e-3, helped=False)
    assert _runs(ways)[:6] == [(True, T), (False, C), (True, U), (False, F), (True, U), (False, 2 * F)]


def test_the_caller_keeps_the_helpers_while_they_pay_and_drops_them_when_they_slow_it(idle_helpers):
    helpers, clock = idle_helpers
    T, C, R = fork_join._TRIAL_TICKS, fork_join._TRIAL_TICKS, fork_join._RECHECK_TICKS
    # helpers twice as fast: after the first trial a few ticks alone are timed, then helpers, with a
    # few ticks alone timed again now and then
    ways = _ticks(helpers, clock, T + C + 2 * R + 2 * C, 1e-3, 2e-3)
    assert _runs(ways) == [(True, T), (False, C), (True, R), (False, C), (True, R), (False, C)]
    # the machine gets busy: the helpers now make each tick slower than alone
    ways = _ticks(helpers, clock, 200, 3e-3, 2e-3)
    runs = _runs(ways)
    assert runs[0][0] is True and runs[0][1] <= T + 8  # a trial of the helpers, until the mean crosses
    assert runs[1] == (False, fork_join._ALONE_FIRST)  # then alone
    assert sum(n for way, n in runs if way) < 0.3 * len(ways)  # mostly alone from then on
