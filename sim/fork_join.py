"""Helper threads that share one compiled call, started and joined without a Python lock.

A batched tick of the fused kernel runs its worlds' chunks on n threads. Through a
Python thread pool a tick cost about 125 us more than its work on these machines (a
pool's submit and result: two futex wake-ups and GIL hand-overs), and the threads
queued for the GIL between chunks: each thread sat idle about 16 % of a 64-world tick.
Here the n - 1 helpers stay inside the compiled call between ticks:

* the caller's compiled call (role `MAIN`) publishes the tick's arguments (their
  addresses) in the control block, resets the chunk counter and opens a new generation
  of the state word;
* a helper (role `HELPER + t`) spinning on the state word joins the open tick (an
  atomic compare-and-swap counts it in), reads the arguments back, and takes chunks with
  the caller from one atomic counter (`fetch_add`);
* once every chunk is taken the caller closes the tick (no helper joins after that) and
  waits only for the helpers that joined: a helper that the OS has not scheduled, or
  that is parked, never holds up a tick. The caller runs every chunk itself if need be.

Helpers spin only while spinning pays. Each keeps a spin budget (at most about 1 ms): it
halves when a spell runs out with no tick (the caller does other work between ticks, e.g.
a learner's update), or when the helper came too late to take a chunk (the process or the
machine is oversubscribed: another process, or torch's threads, want the cores); when a
parked helper is woken soon after it parked, the budget grows to twice that pause. A
helper whose budget runs out returns to Python and parks on a condition (an idle
simulator costs no CPU); the caller wakes parked helpers before its call
(`Helpers.start_tick`). The caller, for its part, times its ticks with the helpers and
alone (a few ticks now and then), and runs alone for a while when the helpers took no
chunk of its last ticks or made them slower, trying them again later (`Helpers.end_tick`):
helpers never cost much more than running alone.

A helper only ever works inside a call of the caller, on chunks whose worlds see the same
arithmetic in the same order as on one thread: results are bit-identical whatever the
number of threads and whoever took which chunk (tested).

Control block (int64, `CONTROL_SIZE`): the counters below, each on its own cache line,
then the tick's arguments (`ARG_*`). The state word (`GEN`) is generation * `_GEN_UNIT`
+ `_CLOSED` (once the caller closed the tick) + the number of helpers that joined it.
"""

from __future__ import annotations

import collections
import os
import statistics
import threading
import time
import weakref
from typing import Any, Callable

import numpy as np
from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic

from downwash_core.jit import njit

__all__ = ["Helpers", "SOLO", "MAIN", "HELPER", "IDLE", "EXIT", "NOT_JOINED", "new_control", "fetch_add", "load",
           "store", "compare_exchange"]

# roles of a call: alone (no helpers), the caller with helpers, helper t (HELPER + t)
SOLO, MAIN, HELPER = 0, 1, 2
# what a helper's call returns, and the caller's when the helpers have not all reported yet
IDLE, EXIT, NOT_JOINED = -2, -3, -4

_LINE = 8  # int64 per 64-byte cache line
GEN, NEXT, DONE, RESULT, EXIT_FLAG, POSTED, PARKED, HELPED, JOINED, SPINS = (i * _LINE for i in range(10))
SPINS_MIN, SPINS_MAX = SPINS, SPINS + 1  # a helper's least and largest spin budget
SEEN = 10 * _LINE  # + t * _LINE: the generation helper t saw last; + 1: its spin budget
BUDGET = 1
_MAX_HELPERS = 64
_CLOSED, _GEN_UNIT = 128, 256  # the state word's closed flag and generation step (joined helpers below 128)
ARG = SEEN + _MAX_HELPERS * _LINE  # the tick's arguments, written by the caller
(ARG_TAB, ARG_TAB_SIZE, ARG_FC, ARG_FC_SIZE, ARG_CHUNKS, ARG_N_CHUNKS, ARG_REF_POS, ARG_REF_VEL, ARG_REF_ACC,
 ARG_REF_YAW, ARG_REF_YAW_RATE, ARG_RESIDUAL, ARG_OVERRIDE, ARG_ROW, ARG_ROW_SIZE, ARG_ACTIONS, ARG_SUB_START,
 ARG_SUB_STOP) = range(ARG, ARG + 18)
CONTROL_SIZE = ARG + 18

# a helper's spin budget while waiting for a tick, in seconds (spins per second are measured once
# per process): at most a little more than the gaps between the ticks of a busy simulator
# (about 0.2 ms), at least a few microseconds; the caller's spins waiting for the helpers that joined before it yields its
# core (about 10 us here)
SPIN_SECONDS_MAX, SPIN_SECONDS_MIN = 1e-3, 4e-6
_JOIN_SPINS = 50_000
# the caller's choice between its helpers and running alone (`Helpers.end_tick`), in ticks: the
# helpers may take no chunk this many ticks in a row; a trial (the medians of this many ticks
# each way are compared); the first and longest spell alone (it doubles each time the helpers
# fail again); ticks with the helpers before a trial's worth alone is timed again
_USELESS_TICKS, _TRIAL_TICKS, _ALONE_FIRST, _ALONE_MAX, _RECHECK_TICKS = 8, 6, 64, 4096, 480


@intrinsic
def load(typingctx, addr):
    """The int64 at address addr, read with acquire ordering (a spin loop sees other threads' writes)."""
    sig = types.int64(types.intp)

    def codegen(context, builder, signature, args):
        ptr = builder.inttoptr(args[0], ir.IntType(64).as_pointer())
        return builder.load_atomic(ptr, "acquire", 8)

    return sig, codegen


@intrinsic
def fetch_add(typingctx, addr, value):
    """Atomically add value to the int64 at address addr (sequentially consistent); returns the old value."""
    sig = types.int64(types.intp, types.int64)

    def codegen(context, builder, signature, args):
        ptr = builder.inttoptr(args[0], ir.IntType(64).as_pointer())
        return builder.atomic_rmw("add", ptr, args[1], "seq_cst")

    return sig, codegen


@intrinsic
def compare_exchange(typingctx, addr, expected, value):
    """Atomically replace the int64 at address addr by value if it equals expected (sequentially
    consistent); returns whether it did."""
    sig = types.boolean(types.intp, types.int64, types.int64)

    def codegen(context, builder, signature, args):
        ptr = builder.inttoptr(args[0], ir.IntType(64).as_pointer())
        pair = builder.cmpxchg(ptr, args[1], args[2], "seq_cst", "seq_cst")
        return builder.extract_value(pair, 1)

    return sig, codegen


@intrinsic
def store(typingctx, addr, value):
    """Write value to the int64 at address addr (sequentially consistent: every write before it is
    seen by a thread that reads this one with `load`)."""
    sig = types.void(types.intp, types.int64)

    def codegen(context, builder, signature, args):
        ptr = builder.inttoptr(args[0], ir.IntType(64).as_pointer())
        builder.store_atomic(args[1], ptr, "seq_cst", 8)
        return context.get_dummy_value()

    return sig, codegen


def new_control() -> np.ndarray:
    """A zeroed control block, its start on a cache line (`Helpers` set the spin budgets' bounds)."""
    raw = np.zeros(CONTROL_SIZE + _LINE, np.int64)
    skip = (-raw.ctypes.data % 64) // 8
    return raw[skip:skip + CONTROL_SIZE]


@njit
def publish(ctl, tab, fc, chunks, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, residual, override, row, actions,
            sub_start, sub_stop):
    """Role MAIN: write the tick's arguments, reset the chunk counter and the results, then open the
    tick for the helpers (the state word's atomic store orders every write before it). chunks:
    the caller's (n, 4) table, the first of the (n_threads, n, 4) array whose next ones are the
    helpers' (helper t reads table t + 1)."""
    ctl[ARG_TAB], ctl[ARG_TAB_SIZE], ctl[ARG_FC], ctl[ARG_FC_SIZE] = tab.ctypes.data, tab.shape[0], fc.ctypes.data, fc.shape[0]
    ctl[ARG_CHUNKS], ctl[ARG_N_CHUNKS] = chunks.ctypes.data, chunks.shape[0]
    ctl[ARG_REF_POS], ctl[ARG_REF_VEL], ctl[ARG_REF_ACC] = ref_pos.ctypes.data, ref_vel.ctypes.data, ref_acc.ctypes.data
    ctl[ARG_REF_YAW], ctl[ARG_REF_YAW_RATE] = ref_yaw.ctypes.data, ref_yaw_rate.ctypes.data
    ctl[ARG_RESIDUAL], ctl[ARG_OVERRIDE] = residual.ctypes.data, override.ctypes.data
    ctl[ARG_ROW], ctl[ARG_ROW_SIZE] = row.ctypes.data, row.shape[0]
    ctl[ARG_ACTIONS], ctl[ARG_SUB_START], ctl[ARG_SUB_STOP] = actions, sub_start, sub_stop
    ctl[NEXT] = 0
    ctl[RESULT] = 0
    ctl[DONE] = 0  # every helper that joined the last tick has reported (the caller waited for them)
    base = ctl.ctypes.data
    store(base + 8 * GEN, (load(base + 8 * GEN) // _GEN_UNIT + 1) * _GEN_UNIT)


@njit
def await_tick(ctl, helper):
    """Role HELPER + helper: spin until the caller opens a tick and join it (returns 1), or until exit
    is asked (EXIT) or the spin budget runs out (IDLE; the budget halves). A tick that closed
    before this helper saw it counts as a failed spell too."""
    base = ctl.ctypes.data
    line = SEEN + helper * _LINE
    budget = ctl[line + BUDGET]
    seen = ctl[line]
    spins = 0
    while spins < budget:
        spins += 1
        state = load(base + 8 * GEN)
        gen = state // _GEN_UNIT
        if gen == seen:
            continue
        if load(base + 8 * EXIT_FLAG):
            return EXIT
        if state & _CLOSED:  # came too late: the caller ran this tick without us
            seen = gen
            ctl[line] = gen
            budget = max(ctl[SPINS_MIN], budget // 2)
            ctl[line + BUDGET] = budget
            continue
        if compare_exchange(base + 8 * GEN, state, state + 1):
            ctl[line] = gen
            return 1
    ctl[line + BUDGET] = max(ctl[SPINS_MIN], budget // 2)
    return IDLE


@njit
def report(ctl, helper, result, n_taken):
    """Role HELPER + helper: add this helper's result and count it done for the tick; n_taken: the
    chunks it ran (none: it joined too late to help, and its spin budget halves)."""
    base = ctl.ctypes.data
    line = SEEN + helper * _LINE
    if n_taken == 0:
        ctl[line + BUDGET] = max(ctl[SPINS_MIN], ctl[line + BUDGET] // 2)
    fetch_add(base + 8 * HELPED, n_taken)
    fetch_add(base + 8 * RESULT, result)
    fetch_add(base + 8 * DONE, 1)


@njit
def join(ctl, result):
    """Role MAIN, once every chunk is taken: add the caller's result, close the tick (no helper joins
    it from now on) and spin until the helpers that joined have reported; returns the total, or
    NOT_JOINED when the spin budget ran out first (`Helpers.join` waits on)."""
    base = ctl.ctypes.data
    fetch_add(base + 8 * RESULT, result)
    ctl[JOINED] = fetch_add(base + 8 * GEN, _CLOSED) % _CLOSED
    return _joined(ctl, _JOIN_SPINS)


@njit
def _joined(ctl, spins):
    base = ctl.ctypes.data
    target = ctl[JOINED]
    for _ in range(spins):
        if load(base + 8 * DONE) == target:
            return load(base + 8 * RESULT)
    return NOT_JOINED


class Helpers:
    """n_helpers threads, each running `serve(t)` (a compiled call in role HELPER + t that returns
    IDLE or EXIT) and parking between idle spells. Stopped when `owner` is collected, and
    in a forked child (whose copy has no threads) `alive` is False: start new ones.

    A tick: `start_tick()` (True: a MAIN call, False: a SOLO call), the call, then
    `end_tick(its result, its sub-ticks)`."""

    def __init__(self, n_helpers: int, serve: Callable[[int], int], ctl: np.ndarray, owner: Any):
        if not 1 <= n_helpers <= _MAX_HELPERS:
            raise ValueError(f"n_helpers: expected 1..{_MAX_HELPERS}, got {n_helpers}")
        self.ctl, self.n = ctl, n_helpers
        self.pid = os.getpid()
        self.key: Any = None  # what the owner started them for (it starts new ones when that changes)
        rate = _spin_rate()
        ctl[SPINS_MIN], ctl[SPINS_MAX] = max(1, int(rate * SPIN_SECONDS_MIN)), max(2, int(rate * SPIN_SECONDS_MAX))
        for t in range(n_helpers):
            ctl[SEEN + t * _LINE + BUDGET] = ctl[SPINS_MAX]
        # the caller's choice (`end_tick`): run with the helpers, or alone for `_spell` ticks
        self._with, self._spell, self._ticks = True, 0, 0  # the way, its spell, ticks run that way
        # seconds per sub-tick of the last ticks each way
        self._costs: dict[bool, collections.deque] = {w: collections.deque(maxlen=_TRIAL_TICKS) for w in (True, False)}
        self._helped = 0  # chunks the helpers had taken (ctl[HELPED]) after the last tick
        self._useless = 0  # ticks in a row in which they took none
        self._alone_spell = _ALONE_FIRST  # the next spell alone after the helpers failed
        self._t0 = 0.0
        self._cond = threading.Condition()
        self._threads = [threading.Thread(target=_serve_loop, args=(serve, t, ctl, self._cond, rate),
                                          daemon=True, name=f"sim-helper-{t}") for t in range(n_helpers)]
        for thread in self._threads:
            thread.start()
        self._finalizer = weakref.finalize(owner, _stop, ctl, self._cond, self.pid)

    @property
    def alive(self) -> bool:
        return self.pid == os.getpid() and all(t.is_alive() for t in self._threads)

    def stop(self) -> None:
        """Ask the threads to end (as when the owner is collected); they end within one spin."""
        self._finalizer()

    def start_tick(self) -> bool:
        """Before a tick: whether to run it with the helpers (then count it as posted and wake the
        parked ones, and make it a MAIN call) or alone (a SOLO call), as `end_tick` decided."""
        self._t0 = time.perf_counter()
        if not self._with:
            return False
        ctl = self.ctl
        ctl[POSTED] += 1
        if ctl[PARKED]:
            with self._cond:
                self._cond.notify_all()
        return True

    def end_tick(self, result: int, n_sub: int) -> int:
        """After the tick's call, with its result: the total (with helpers: once those that joined
        have reported, yielding the core while they run: a helper the OS paused holds a chunk).
        Then the choice for the next ticks, from the time per sub-tick (n_sub in this call) of
        the last ticks each way (their medians): the caller runs alone a while when the helpers took no chunk
        of its last ticks or made them slower than alone (the process or the machine is
        oversubscribed), and tries them again after a spell that doubles each time they fail."""
        if self._with:
            while result == NOT_JOINED:
                os.sched_yield()
                result = _joined(self.ctl, _JOIN_SPINS)
                if result == NOT_JOINED and not self.alive:
                    raise RuntimeError("a simulator helper thread has died; the tick cannot complete")
        self._costs[self._with].append((time.perf_counter() - self._t0) / max(n_sub, 1))
        self._ticks += 1
        if self._with:
            helped = int(self.ctl[HELPED])
            self._useless = 0 if helped != self._helped else self._useless + 1
            self._helped = helped
            alone = self._costs[False]
            if self._useless >= _USELESS_TICKS:
                self._fail()
            elif self._ticks % _TRIAL_TICKS == 0:  # medians: the first tick after a start or a park is slow
                if not alone or self._ticks >= _RECHECK_TICKS:  # time a few ticks alone (the machine may change)
                    if alone:
                        self._alone_spell = _ALONE_FIRST  # the helpers paid since the last time
                    self._switch(False, _TRIAL_TICKS)
                elif statistics.median(self._costs[True]) > statistics.median(alone):
                    self._fail()
        elif self._ticks >= self._spell:
            self._switch(True, 0)
        return result

    def _fail(self) -> None:
        """The helpers did not pay: run alone a while, longer each time in a row."""
        self._switch(False, self._alone_spell)
        self._alone_spell = min(_ALONE_MAX, 2 * self._alone_spell)

    def _switch(self, with_helpers: bool, spell: int) -> None:
        self._with, self._spell, self._ticks, self._useless = with_helpers, spell, 0, 0


def _serve_loop(serve: Callable[[int], int], t: int, ctl: np.ndarray, cond: threading.Condition,
                spins_per_s: float) -> None:
    line = SEEN + t * _LINE
    while serve(t) != EXIT:  # idle: park until the caller posts a tick it has not served
        parked_at = time.perf_counter()
        with cond:
            ctl[PARKED] += 1
            # under the GIL, either the caller's `wake` sees PARKED or this test sees its POSTED:
            # no tick is missed (the timeout is only a safety net)
            while ctl[POSTED] == ctl[line] and not ctl[EXIT_FLAG]:
                cond.wait(1.0)
            ctl[PARKED] -= 1
        # woken soon after parking: a spin this long would have caught the tick without a wake
        pause_spins = 2 * (time.perf_counter() - parked_at) * spins_per_s
        if pause_spins < ctl[SPINS_MAX]:
            ctl[line + BUDGET] = max(ctl[line + BUDGET], int(pause_spins))


_SPIN_RATE: list[float] = []


def _spin_rate() -> float:
    """Spins of `await_tick` per second on this CPU (measured once per process, about 0.5 ms)."""
    if not _SPIN_RATE:
        ctl = new_control()
        ctl[SEEN + BUDGET] = 1000
        await_tick(ctl, 0)  # compiled (or loaded) first
        ctl[SEEN + BUDGET] = ctl[SPINS_MIN] = spins = 200_000
        t0 = time.perf_counter()
        await_tick(ctl, 0)
        _SPIN_RATE.append(spins / max(time.perf_counter() - t0, 1e-6))
    return _SPIN_RATE[0]


def _stop(ctl: np.ndarray, cond: threading.Condition, pid: int) -> None:
    if os.getpid() != pid:  # a forked child's copy: its threads do not exist, and cond may be held
        return
    ctl[EXIT_FLAG] = 1
    ctl[POSTED] += 1
    ctl[GEN] += _GEN_UNIT  # spinning helpers see a new generation, then the exit flag
    with cond:
        cond.notify_all()
