"""Helper threads that share one compiled call, started and joined without a Python lock.

A batched tick of the fused kernel runs its worlds' chunks on n threads. Through a
Python thread pool a tick cost about 125 us more than its work on these machines (a
pool's submit and result: two futex wake-ups and GIL hand-overs), and the threads
queued for the GIL between chunks: each thread sat idle about 16 % of a 64-world tick.
Here the n - 1 helpers stay inside the compiled call between ticks:

* the caller's compiled call (role `MAIN`) publishes the tick's arguments (their
  addresses) in the control block, resets the chunk counter and bumps the generation;
* each helper (role `HELPER + t`) spins on the generation, reads the arguments back,
  and takes chunks with the caller from one atomic counter (`fetch_add`);
* each adds its result and counts itself done; the caller spins until all are.

A helper that sees no tick for about a millisecond returns to Python and parks on a
condition (an idle simulator costs no CPU); the caller wakes parked helpers before its
call (`Helpers.wake`). A helper only ever works inside a call of the caller, so worlds
see the same arithmetic in the same order as on one thread: results are bit-identical
whatever the number of threads (tested).

Control block (int64, `CONTROL_SIZE`): the counters below, each on its own cache line,
then the tick's arguments (`ARG_*`).
"""

from __future__ import annotations

import os
import threading
import weakref
from typing import Any, Callable

import numpy as np
from llvmlite import ir
from numba import types
from numba.core.extending import intrinsic

from downwash_core.jit import njit

__all__ = ["Helpers", "SOLO", "MAIN", "HELPER", "IDLE", "EXIT", "NOT_JOINED", "new_control", "fetch_add", "load"]

# roles of a call: alone (no helpers), the caller with helpers, helper t (HELPER + t)
SOLO, MAIN, HELPER = 0, 1, 2
# what a helper's call returns, and the caller's when the helpers have not all reported yet
IDLE, EXIT, NOT_JOINED = -2, -3, -4

_LINE = 8  # int64 per 64-byte cache line
GEN, NEXT, DONE, RESULT, EXIT_FLAG, POSTED, PARKED = (i * _LINE for i in range(7))
SEEN = 7 * _LINE  # + t: the generation helper t served last (one line each)
_MAX_HELPERS = 64
ARG = SEEN + _MAX_HELPERS * _LINE  # the tick's arguments, written by the caller
(ARG_TAB, ARG_TAB_SIZE, ARG_FC, ARG_FC_SIZE, ARG_CHUNKS, ARG_N_CHUNKS, ARG_REF_POS, ARG_REF_VEL, ARG_REF_ACC,
 ARG_REF_YAW, ARG_REF_YAW_RATE, ARG_RESIDUAL, ARG_OVERRIDE, ARG_ROW, ARG_ROW_SIZE, ARG_ACTIONS, ARG_SUB_START,
 ARG_SUB_STOP) = range(ARG, ARG + 18)
CONTROL_SIZE = ARG + 18

# spins of a helper waiting for a tick before it parks (about a millisecond here), and of the
# caller waiting for its helpers before it checks on them from Python
_IDLE_SPINS = 6_000_000
_JOIN_SPINS = 20_000_000


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


def new_control() -> np.ndarray:
    """A zeroed control block, its start on a cache line."""
    raw = np.zeros(CONTROL_SIZE + _LINE, np.int64)
    skip = (-raw.ctypes.data % 64) // 8
    return raw[skip:skip + CONTROL_SIZE]


@njit
def publish(ctl, tab, fc, chunks, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, residual, override, row, actions,
            sub_start, sub_stop):
    """Role MAIN: write the tick's arguments, reset the chunk counter and the results, then start the
    helpers (the generation's atomic increment orders every write before it). chunks: the
    caller's (n, 4) table, the first of the (n_threads, n, 4) array whose next ones are the
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
    fetch_add(ctl.ctypes.data + 8 * GEN, 1)


@njit
def await_tick(ctl, helper):
    """Role HELPER + helper: spin until the caller starts a tick (returns 1), exit is asked (EXIT), or
    none comes within the spin budget (IDLE)."""
    base = ctl.ctypes.data
    seen = ctl[SEEN + helper * _LINE]
    for _ in range(_IDLE_SPINS):
        gen = load(base + 8 * GEN)
        if gen != seen:
            if load(base + 8 * EXIT_FLAG):
                return EXIT
            ctl[SEEN + helper * _LINE] = gen
            return 1
    return IDLE


@njit
def report(ctl, result):
    """Role HELPER: add this helper's result and count it done for the tick."""
    base = ctl.ctypes.data
    fetch_add(base + 8 * RESULT, result)
    fetch_add(base + 8 * DONE, 1)


@njit
def join(ctl, result, n_helpers):
    """Role MAIN: add the caller's result, spin until every helper has reported this tick; returns the
    total, or NOT_JOINED when the spin budget ran out first (`Helpers.join` waits on)."""
    base = ctl.ctypes.data
    fetch_add(base + 8 * RESULT, result)
    return _joined(ctl, n_helpers, _JOIN_SPINS)


@njit
def _joined(ctl, n_helpers, spins):
    base = ctl.ctypes.data
    target = load(base + 8 * GEN) * n_helpers  # each helper reports once per generation
    for _ in range(spins):
        if load(base + 8 * DONE) == target:
            return load(base + 8 * RESULT)
    return NOT_JOINED


class Helpers:
    """n_helpers threads, each running `serve(t)` (a compiled call in role HELPER + t that returns
    IDLE or EXIT) and parking between idle spells. Stopped when `owner` is collected, and
    in a forked child (whose copy has no threads) `alive` is False: start new ones."""

    def __init__(self, n_helpers: int, serve: Callable[[int], int], ctl: np.ndarray, owner: Any):
        if not 1 <= n_helpers <= _MAX_HELPERS:
            raise ValueError(f"n_helpers: expected 1..{_MAX_HELPERS}, got {n_helpers}")
        self.ctl, self.n = ctl, n_helpers
        self.pid = os.getpid()
        self.key: Any = None  # what the owner started them for (it starts new ones when that changes)
        self._cond = threading.Condition()
        self._threads = [threading.Thread(target=_serve_loop, args=(serve, t, ctl, self._cond), daemon=True,
                                          name=f"sim-helper-{t}") for t in range(n_helpers)]
        for thread in self._threads:
            thread.start()
        self._finalizer = weakref.finalize(owner, _stop, ctl, self._cond, self.pid)

    @property
    def alive(self) -> bool:
        return self.pid == os.getpid() and all(t.is_alive() for t in self._threads)

    def stop(self) -> None:
        """Ask the threads to end (as when the owner is collected); they end within one spin."""
        self._finalizer()

    def wake(self) -> None:
        """Before a MAIN call: count the tick as posted, and wake the parked helpers."""
        ctl = self.ctl
        ctl[POSTED] += 1
        if ctl[PARKED]:
            with self._cond:
                self._cond.notify_all()

    def join(self) -> int:
        """After a MAIN call returned NOT_JOINED: wait for the helpers (checking that they live)."""
        while True:
            total = _joined(self.ctl, self.n, _JOIN_SPINS)
            if total != NOT_JOINED:
                return total
            if not self.alive:
                raise RuntimeError("a simulator helper thread has died; the tick cannot complete")


def _serve_loop(serve: Callable[[int], int], t: int, ctl: np.ndarray, cond: threading.Condition) -> None:
    while serve(t) != EXIT:  # idle: park until the caller posts a tick it has not served
        with cond:
            ctl[PARKED] += 1
            # under the GIL, either the caller's `wake` sees PARKED or this test sees its POSTED:
            # no tick is missed (the timeout is only a safety net)
            while ctl[POSTED] == ctl[SEEN + t * _LINE] and not ctl[EXIT_FLAG]:
                cond.wait(1.0)
            ctl[PARKED] -= 1


def _stop(ctl: np.ndarray, cond: threading.Condition, pid: int) -> None:
    if os.getpid() != pid:  # a forked child's copy: its threads do not exist, and cond may be held
        return
    ctl[EXIT_FLAG] = 1
    ctl[POSTED] += 1
    ctl[GEN] += 1  # spinning helpers see a new generation, then the exit flag
    with cond:
        cond.notify_all()
