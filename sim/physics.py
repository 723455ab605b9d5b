"""One stepping interface over plain `MjData` (one world) and `mujoco.batch.Batch` (many).

Both expose the same live (W, ...) arrays, so the control stack above them is a
single code path: a single flight is a batch of one.
"""

from __future__ import annotations

import copy
import ctypes
import functools
import glob
import logging
import os
import threading

import mujoco
import mujoco.batch
import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.jit import njit

__all__ = ["Physics", "SerialPhysics", "make_physics", "mj_step_address", "profiling_timer_off", "resolve_threads",
           "usable_cores", "available_memory", "check_world_memory", "world_bytes", "MEMORY_FRACTION"]

log = logging.getLogger(__name__)

# warnings after which MuJoCo has reset or corrupted the state: the flight diverged
_FATAL_WARNINGS = np.array(
    [int(mujoco.mjtWarning.mjWARN_BADQPOS), int(mujoco.mjtWarning.mjWARN_BADQVEL), int(mujoco.mjtWarning.mjWARN_BADQACC)]
)
FATAL_0, FATAL_1, FATAL_2 = (int(i) for i in _FATAL_WARNINGS)
# the single world's step result, shared read-only (no allocation at 100 Hz)
_DIVERGED_1, _FINE_1 = np.ones(1, bool), np.zeros(1, bool)
_DIVERGED_1.flags.writeable = _FINE_1.flags.writeable = False


class Physics:
    """Live state arrays of W worlds and a step that advances the active ones.

    qpos (W, nq), qvel (W, nv), act (W, na), ctrl (W, nu), xfrc_applied (W, nbody, 6)
    are writable views of the simulation state.
    """

    n_worlds: int
    revision: int = 0  # counts the changes of the worlds' models (set_body_mass)
    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    ctrl: np.ndarray
    xfrc_applied: np.ndarray

    def step(self, nstep: int, active: np.ndarray) -> np.ndarray:
        """Advance active worlds by nstep physics steps; returns (W,) bool: which diverged.

        The returned array may be shared and read-only; copy it to keep or modify it.
        """
        raise NotImplementedError

    def reset(self, worlds: np.ndarray) -> None:
        """Reset the given worlds to the model's defaults (warnings cleared)."""
        raise NotImplementedError

    def set_body_mass(self, worlds: np.ndarray, body_ids: np.ndarray, mass: np.ndarray) -> None:
        """Give bodies of the given worlds their own mass (kg), e.g. for domain randomisation.

        mass: (len(worlds), len(body_ids)). Inertia scales with the mass (same shape).
        """
        raise NotImplementedError

    def mjdata(self, world: int) -> mujoco.MjData:
        """An MjData with world `world`'s state and derived quantities (for rendering)."""
        raise NotImplementedError


class SerialPhysics(Physics):
    def __init__(self, model: mujoco.MjModel):
        self.model = model
        self.data = mujoco.MjData(model)
        self.n_worlds = 1
        d = self.data
        self.qpos, self.qvel, self.act = d.qpos[None], d.qvel[None], d.act[None]
        self.ctrl, self.xfrc_applied = d.ctrl[None], d.xfrc_applied[None]
        self._warnings = d.warning.number  # (mjNWARNING,) live counts since the last reset
        self._nominal: tuple[np.ndarray, np.ndarray] | None = None  # mass, inertia before any change

    def step(self, nstep: int, active: np.ndarray) -> np.ndarray:
        if active[0]:
            mujoco.mj_step(self.model, self.data, nstep=nstep)
        n = self._warnings  # three scalar reads: a fancy-indexed check cost ~4x more per step
        return _DIVERGED_1 if n[FATAL_0] or n[FATAL_1] or n[FATAL_2] else _FINE_1

    def reset(self, worlds: np.ndarray) -> None:
        if len(worlds):
            mujoco.mj_resetData(self.model, self.data)

    def set_body_mass(self, worlds: np.ndarray, body_ids: np.ndarray, mass: np.ndarray) -> None:
        if len(worlds):
            if self._nominal is None:  # copy on write: the scene's model may be shared
                self._nominal = (self.model.body_mass.copy(), self.model.body_inertia.copy())
                self.model = copy.copy(self.model)
            mass0, inertia0 = self._nominal
            scale = np.asarray(mass, float).reshape(len(worlds), len(body_ids))[-1] / mass0[body_ids]
            self.model.body_mass[body_ids] = scale * mass0[body_ids]
            self.model.body_inertia[body_ids] = scale[:, None] * inertia0[body_ids]
            mujoco.mj_setConst(self.model, self.data)
            self.revision += 1

    def mjdata(self, world: int) -> mujoco.MjData:
        mujoco.mj_forward(self.model, self.data)
        return self.data

    def native_step(self) -> tuple[int, int, int, np.ndarray] | None:
        """(address of mj_step, of the mjModel, of the mjData, the live warning counts (mjNWARNING,) int32),
        for a compiled caller that steps this world itself (the simulator's fused loop), or None
        where libmujoco's mj_step cannot be found. The model address changes when
        `set_body_mass` copies the model: ask again after that."""
        fn = mj_step_address()
        if fn is None:
            return None
        return fn, int(self.model._address), int(self.data._address), self._warnings


class _BatchPhysics(Physics):
    def __init__(self, model: mujoco.MjModel, n_worlds: int, n_threads: int):
        self.model = model
        self.batch = mujoco.batch.Batch(model, n_worlds, nthread=n_threads)
        self.n_worlds = n_worlds
        b = self.batch
        self.qpos, self.qvel, self.act = b.bind("qpos"), b.bind("qvel"), b.bind("act")
        self.ctrl, self.xfrc_applied = b.bind("ctrl"), b.bind("xfrc_applied")

    def step(self, nstep: int, active: np.ndarray) -> np.ndarray:
        failed = np.zeros(self.n_worlds, bool)
        ids = None if active.all() else np.flatnonzero(active)
        if ids is not None and ids.size == 0:
            return failed
        try:
            self.batch.step(ids=ids, nstep=nstep)
        except mujoco.batch.SimulationError as e:  # those worlds kept their state; the rest stepped
            failed[e.ids] = True
            log.warning("%s", e)
        _mark_fatal(self.batch.warning, _FATAL_WARNINGS, failed)
        return failed

    def reset(self, worlds: np.ndarray) -> None:
        if len(worlds):
            self.batch.reset(ids=np.asarray(worlds), stage=0)

    def set_body_mass(self, worlds: np.ndarray, body_ids: np.ndarray, mass: np.ndarray) -> None:
        if len(worlds):
            worlds = np.asarray(worlds)
            masses = self.batch.expand("body_mass")
            inertia = self.batch.expand("body_inertia")
            scale = np.asarray(mass, float).reshape(len(worlds), len(body_ids)) / self.model.body_mass[body_ids]
            masses[np.ix_(worlds, body_ids)] = scale * self.model.body_mass[body_ids]
            inertia[np.ix_(worlds, body_ids)] = scale[..., None] * self.model.body_inertia[body_ids]
            self.batch.set_const(ids=worlds)
            self.revision += 1

    def native_step(self, n_scratch: int) -> tuple | None:
        """What a compiled caller needs to step the worlds itself, or None (then it calls `step`).

        Returns (address of mj_step, of mj_setState, of mj_getState, of the mjModel, state
        (W, nstate) float64, the state spec (mjSTATE_INTEGRATION), warning (W, mjNWARNING, 2)
        int32 [last info, count], and n_scratch MjData of the model, one per thread).
        A world is stepped as the batch does it (its docstring): its state row loaded into
        an MjData, nstep mj_step, the row saved back, bit for bit (tested); the caller
        clears the MjData's warnings before and adds them to `warning` after. None where the
        worlds have models of their own (`set_body_mass`), the state rows are not the
        integration state, or libmujoco's functions cannot be found.
        """
        step = mj_step_address()
        if step is None or self.revision or self.batch.persistent or self.batch._models is not None:
            return None
        spec = int(mujoco.mjtState.mjSTATE_INTEGRATION)
        state, warning = self.batch.state, self.batch.warning
        if state.shape[1] != mujoco.mj_stateSize(self.model, spec) or not state.flags.c_contiguous \
                or not warning.flags.c_contiguous or warning.dtype != np.int32:
            return None
        lib = ctypes.CDLL(_libmujoco_path())
        set_state, get_state = (int(ctypes.cast(getattr(lib, f), ctypes.c_void_p).value) for f in ("mj_setState", "mj_getState"))
        scratch = getattr(self, "_scratch", [])
        while len(scratch) < n_scratch:
            scratch.append(mujoco.MjData(self.model))
        self._scratch = scratch
        return step, set_state, get_state, int(self.model._address), state, spec, warning, scratch[:n_scratch]

    def mjdata(self, world: int) -> mujoco.MjData:
        if not hasattr(self, "_render_data"):
            self._render_data = mujoco.MjData(self.model)
        data = self.batch.get_data(world, self._render_data)
        mujoco.mj_forward(self.batch.get_model(world) if self.batch.expanded("body_mass") is not None else self.model, data)
        return data


@njit
def _mark_fatal(warning, fatal, failed):
    """failed[w] |= any fatal warning counted in world w; warning: (W, mjNWARNING, 2) [last, count]."""
    for w in range(warning.shape[0]):
        for i in fatal:
            if warning[w, i, 1] > 0:
                failed[w] = True


@functools.lru_cache(maxsize=1)
def mj_step_address() -> int | None:
    """The address of `mj_step(const mjModel*, mjData*)` in the libmujoco that the bindings load, or None.

    A compiled loop calls it directly (no Python call per physics step); the result equals
    `mujoco.mj_step` bit for bit (tested). dlopen of the bindings' own library file returns
    the library already loaded.
    """
    path = _libmujoco_path()
    if path is None:
        return None
    return int(ctypes.cast(ctypes.CDLL(path).mj_step, ctypes.c_void_p).value)


class _ProfilingTimerOff:
    """MuJoCo's profiling timer off while a simulator steps (a context manager; `profiling_timer_off()`).

    The mujoco bindings install a timer callback (`mjcb_time`) at import, so that `MjData.timer`
    records how long each stage of `mj_step` takes (the viewer's profiler shows it): a clock read at
    the start and end of every stage, a large share of a small scene's step (benchmark:
    bare_mj_step_per_s against bare_mj_step_per_s_no_timer). The simulator never reads those timings:
    it clears the callback while it steps and puts back what was there when it leaves. Entries are
    counted, so simulators ticking in several threads at once give the callback back when the last
    one leaves. The physics is the same bit for bit (the callback only reads a clock); the timers of a
    simulator's worlds stay zero, and a callback of a user's own is also off during a tick.
    Without a libmujoco to reach, a no-op."""

    def __init__(self, path: str | None):
        try:
            self._slot = None if path is None else ctypes.c_void_p.in_dll(ctypes.CDLL(path), "mjcb_time")
        except ValueError:  # a library without the symbol
            self._slot = None
        self._lock = threading.Lock()
        self._depth = 0
        self._saved: int | None = None

    def __enter__(self) -> None:
        if self._slot is None:
            return
        with self._lock:
            if self._depth == 0:
                self._saved, self._slot.value = self._slot.value, None
            self._depth += 1

    def __exit__(self, *exc: object) -> None:
        if self._slot is None:
            return
        with self._lock:
            self._depth -= 1
            if self._depth == 0:
                self._slot.value = self._saved


@functools.lru_cache(maxsize=1)
def profiling_timer_off() -> _ProfilingTimerOff:
    """The process's one switch of MuJoCo's profiling timer (`with profiling_timer_off(): ...`)."""
    return _ProfilingTimerOff(_libmujoco_path())


@functools.lru_cache(maxsize=1)
def _libmujoco_path() -> str | None:
    """The bindings' libmujoco with its mj_step, setState and getState, or None."""
    folder = os.path.dirname(mujoco.__file__)
    for pattern in ("libmujoco.so*", "libmujoco*.dylib", "mujoco*.dll"):
        for path in sorted(glob.glob(os.path.join(folder, pattern))):
            try:
                lib = ctypes.CDLL(path)
                lib.mj_step, lib.mj_setState, lib.mj_getState  # noqa: B018 (all three must exist)
                return path
            except (OSError, AttributeError):  # not loadable here, or no such symbol
                continue
    return None


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, as a container or `taskset` sets
    it), not the machine's count."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity on this platform
        return os.cpu_count() or 1


def resolve_threads(n_threads: int) -> int:
    """The thread count for `n_threads`: 0 means every usable core (`usable_cores`); 1..that many
    as given. ConfigError otherwise: more threads than cores only take turns on them."""
    cores = usable_cores()
    if isinstance(n_threads, bool) or not isinstance(n_threads, (int, np.integer)) or not 0 <= n_threads <= cores:
        raise ConfigError(f"n_threads: expected 0 (every usable core, {cores} here) or 1..{cores} "
                          f"(the cores this process may use), got {n_threads!r}")
    return cores if n_threads == 0 else int(n_threads)


# Bytes one world of the batched simulator holds (MuJoCo's batch, the simulator's and the task's arrays), with
# margin: measured by RSS after construction and a few steps, per world at 1024 worlds, about 55 KB for the
# follower env (2 vehicles), 81 KB for the swarm's stack3, 128 KB for formation5 (5 vehicles at 512 worlds).
WORLD_BYTES_BASE = 16 * 1024
WORLD_BYTES_PER_VEHICLE = 32 * 1024
MEMORY_FRACTION = 0.5  # worlds may take at most this share of the memory available when the env is made


def world_bytes(n_vehicles: int) -> int:
    """Estimated bytes of one world of `n_vehicles` vehicles (an upper estimate, about 1.4 x measured)."""
    return WORLD_BYTES_BASE + WORLD_BYTES_PER_VEHICLE * int(n_vehicles)


def _read_int(path: str) -> int | None:
    try:
        with open(path) as fh:
            text = fh.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # cgroup v2 writes "max" for no limit


def available_memory() -> int | None:
    """Bytes this process may still allocate: /proc/meminfo's MemAvailable, lowered to the room left under
    a cgroup memory limit (a container's); the physical memory where there is no /proc; None when unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        avail = None
    if avail is None:
        try:
            avail = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, ValueError, OSError):
            return None
    for limit_path, used_path in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                  ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                   "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        limit, used = _read_int(limit_path), _read_int(used_path)
        if limit is not None and used is not None and limit < 1 << 60:  # v1 reports "no limit" as a huge number
            avail = min(avail, max(limit - used, 0))
    return avail


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1024 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TB"


def check_world_memory(n_worlds: int, n_vehicles: int = 2, *, name: str = "num_envs",
                       available: int | None = None) -> int:
    """The estimated bytes of `n_worlds` worlds of `n_vehicles` vehicles; ConfigError naming `name`, the
    estimate, the bound and a count that fits, before anything is allocated, when the estimate exceeds
    MEMORY_FRACTION of the available memory (`available`, default `available_memory()`; no check when unknown).

    Without it a huge count allocates gigabytes, or swaps the machine, before anything complains.
    """
    per_world = world_bytes(n_vehicles)
    estimate = int(n_worlds) * per_world
    avail = available_memory() if available is None else int(available)
    if avail is None:
        return estimate
    bound = int(avail * MEMORY_FRACTION)
    if estimate > bound:
        fits = bound // per_world
        hint = f"use {name} <= {fits}" if fits >= 1 else "free memory first"
        raise ConfigError(
            f"{name}: {n_worlds} worlds of {n_vehicles} vehicles need about {_size(estimate)} "
            f"(~{_size(per_world)} each), more than the bound of {_size(bound)} "
            f"({MEMORY_FRACTION:.0%} of the {_size(avail)} available); {hint}"
        )
    return estimate


def make_physics(model: mujoco.MjModel, n_worlds: int, n_threads: int = 0) -> Physics:
    """Plain MjData for one world (faster there), `mujoco.batch.Batch` for more, stepped on
    `resolve_threads(n_threads)` threads."""
    if n_worlds < 1:
        raise ValueError(f"n_worlds: expected >= 1, got {n_worlds}")
    n_threads = resolve_threads(n_threads)
    if n_worlds == 1:
        return SerialPhysics(model)
    return _BatchPhysics(model, n_worlds, n_threads)
