"""Resumable sweeps of validation RMSE over fields x model kinds x training minutes x seeds.

    from downwash.sweep_cells import SweepGrid
    grid = SweepGrid(fields=("so2",), models=("shallow", "equivariant"), minutes=(1.0, 5.0), seeds=(0, 1, 2))
    results = run_sweep(grid, {"so2": pipeline}, "runs/cells", workers=2)   # a local Ray of 2 CPUs
    results["fields"]["so2"]["models"]["equivariant"]["rmse_ci_low"]        # per minute point

This module holds `run_sweep`, which spreads the missing cells over Ray (imported
only when cells must be computed); the checks of the command lines' options are
`downwash.sweep_options`' (cheap to import: the command lines call them while they
parse; re-exported here). A local Ray it
starts is shut down however the sweep ends, Ctrl-C and SIGTERM included. A
sweep's parts have modules of their own: the grid, the cells, their training and
their cache `downwash.sweep_cells` (with the steps `run_sweep` takes, one by one);
the bootstrap intervals and the paired claim `downwash.sweep_stats`; the tables and
the figure `downwash.sweep_report`. The command lines are `experiments.sweep` and
its preset `experiments.sample_efficiency` (experiments do not import each other,
so what they share lives here).

Concurrent sweeps share the cache: a process computes a cell only while it holds the
cell's lock (`CellCache.claim`, a `downwash_core.locks.file_lock` beside the result),
taken just before the cell's batch is submitted. A second sweep on the same cache skips
the cells another process holds, computes the rest, then waits for those and loads
them, so no cell is computed twice; a holder that dies lets go of its cells at once
(the kernel drops its locks) and the waiting sweep computes them.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Mapping

from downwash_core.errors import ConfigError
from downwash.sweep_options import (ADDRESS_TIMEOUT, address_problem, check_address, check_execution, grid_from_text,
                                    workers_problem)

if TYPE_CHECKING:
    from downwash.datasets import Dataset
    from downwash.sweep_cells import Cell, CellCache, SweepGrid
    from downwash.sweep_stats import Claim

# the heavy stack (torch, the simulator, Ray) is imported in the functions that use it

__all__ = ["grid_from_text", "check_execution", "workers_problem", "address_problem", "check_address", "run_sweep",
           "map_on_ray", "Terminated", "ADDRESS_TIMEOUT"]

log = logging.getLogger(__name__)


def run_sweep(
    grid: SweepGrid,
    pipelines: Mapping[str, Any],
    cache_dir: str | Path,
    *,
    workers: int = 0,
    address: str = "",
    batch: int = 5,
    claim: Claim | None = None,
    progress: Callable[[str], Callable[[int, int], None] | None] = lambda label: None,
) -> dict[str, Any]:
    """Compute the grid's missing cells on Ray and summarise every field.

    pipelines: field spec -> its collection, an object with ``collection_dir``,
    ``models_dir``, ``config`` (`downwash.staged.CollectionConfig`), ``field`` and
    ``record`` (the provenance record), as `experiments.common.Pipeline`. Each
    field's collection is made first when incomplete, here, once, and its logs are
    checked against its manifest (DataError naming a missing or altered log). The
    missing cells then run as Ray tasks of one CPU, `batch_cells` of ``batch`` cells
    each, each cell only while this process holds its claim (`CellCache.claim`: cells
    another sweep is computing are waited for and loaded); their results are cached
    here as each task lands. Ray: the one this process is connected to, else
    ``ray.init(address=address)``, else a local Ray of ``workers`` CPUs (0: all
    usable cores), shut down however the sweep ends (`_ray_session`: Ctrl-C and
    SIGTERM included, which then raises `Terminated`); none at all when no cell is
    computed here. A malformed ``address``, or one where nothing answers, is a
    ConfigError (`check_address`) before Ray is started.
    ``claim`` (None: the paper's, `downwash.sweep_stats.PAPER_CLAIM`) is tested per field
    (`summarize_field`); ``progress(label)`` may return a
    ``(done, total)`` callback.

    Returns ``fields`` (spec -> `summarize_field` plus ``collection_key``,
    ``collection_dir``, ``data_digest`` and ``validation_minutes``), ``cells``
    (total, cached: found in the cache, also those another sweep computed meanwhile,
    and computed here), ``computed_elsewhere`` (cells another sweep computed while
    this one ran), ``workers`` (the Ray CPUs, 0 when nothing ran) and ``grid``.
    """
    from downwash_core.provenance import fingerprint
    from downwash.staged import ensure_collection
    from downwash.sweep_cells import CellCache, load_collection_with_digest, plan_cells
    from downwash.sweep_stats import PAPER_CLAIM, summarize_field

    check_execution(workers, batch, address)
    claim = PAPER_CLAIM if claim is None else claim
    missing = [f for f in grid.fields if f not in pipelines]
    if missing:
        raise ConfigError(f"run_sweep: no pipeline given for field(s) {missing}")
    data: dict[str, tuple[Dataset, Dataset, dict]] = {}
    collections: dict[str, tuple[str, float, str]] = {}
    for spec in grid.fields:
        p = pipelines[spec]
        ensure_collection(p.collection_dir, p.models_dir, p.config, p.field, progress)
        *data[spec], digest = load_collection_with_digest(p.collection_dir)
        collections[spec] = (fingerprint(p.record), data[spec][0].n_minutes, digest)
    cells = plan_cells(grid, collections)
    cache = CellCache(cache_dir)
    # two specs of one field (say "so2" and "so2:strength=10.6") share their cells: each is computed once
    todo = list({c.key: c for c in cache.missing(cells)}.values())
    log.info("sweep: %d cells, %d cached, %d to compute", len(cells), len(cells) - len(todo), len(todo))
    here, elsewhere, cpus = (_compute_missing(todo, data, cache, workers, address, batch, progress("sweep cells"),
                                              len(cells)) if todo else (0, 0, 0))
    results = cache.load_all(cells)
    fields = {}
    for spec in grid.fields:
        _, val, floor = data[spec]
        fields[spec] = {**summarize_field([c for c in cells if c.field == spec], results, floor, claim),
                        "collection_key": collections[spec][0], "collection_dir": str(pipelines[spec].collection_dir),
                        "data_digest": collections[spec][2], "validation_minutes": val.n_minutes}
    return {"fields": fields, "cells": {"total": len(cells), "cached": len(cells) - here, "computed": here},
            "computed_elsewhere": elsewhere, "workers": cpus, "grid": grid.describe()}


def _ray_task(cells: list[Cell], train: Dataset, val: Dataset) -> list[dict[str, Any]]:
    """One Ray task: `run_cells`, with the Ray node that ran it in each result's ``compute``."""
    import ray

    from downwash.sweep_cells import run_cells

    node = ray.get_runtime_context().get_node_id()
    results = run_cells(cells, train, val)
    for r in results:
        r["compute"]["ray_node"] = node
    return results


class Terminated(SystemExit):
    """SIGTERM (or SIGHUP) while this process ran a Ray it started, raised once that Ray is shut down;
    the exit status is the signal's usual one, 128 + its number."""

    def __init__(self, signum: int):
        super().__init__(128 + signum)
        self.signal = signal.Signals(signum).name


_STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))
_received: list[int] = []  # the stop signals of the running session


def _on_stop_signal(signum: int, frame: Any) -> None:
    for other in _STOP_SIGNALS:  # a repeated signal must not cut the shutdown short
        signal.signal(other, signal.SIG_IGN)
    _received.append(signum)
    # KeyboardInterrupt: the one exception ray.get and ray.wait pass on as it is (any other raised in a
    # handler comes out as SystemExit(1) or SystemError); `_ray_session` turns it into Terminated
    raise KeyboardInterrupt


def _stopped_by() -> str:
    """What stopped the sweep, for its last message: the signal, else Ctrl-C."""
    return signal.Signals(_received[0]).name if _received else "Ctrl-C"


@contextlib.contextmanager
def _ray_session(workers: int, address: str) -> Iterator[bool]:
    """Connect to Ray for the block: the one this process is connected to (yields False), else
    ``ray.init(address)``, else a local Ray of ``workers`` CPUs (0: all usable cores); yields True.

    A Ray this call started is shut down on every way out of the block: its end, an exception,
    Ctrl-C, and SIGTERM or SIGHUP, which stop the block as Ctrl-C does and raise `Terminated` once
    Ray is down. (Ray's core answers a SIGTERM by aborting the process, which skips every ``finally``:
    the shutdown never runs and the local cluster's processes are left to end on their own.) A
    signal ignored before stays ignored; the handlers before are restored after.
    """
    import ray

    if ray.is_initialized():
        yield False
        return
    check_address(address)
    # only the main thread may set handlers; elsewhere Ray's stay (and so does its abort)
    before = ({s: signal.getsignal(s) for s in _STOP_SIGNALS}
              if threading.current_thread() is threading.main_thread() else {})
    _received.clear()
    _catch_stop_signals(before)
    others = {c.pid for c in _descendants()}  # this process's own, before Ray's
    try:
        try:
            with _driver_keeps_sigterm():
                _init_ray(workers, address)
        except ConnectionError as e:  # "auto" with no cluster on this machine, or one that stopped meanwhile
            if not address:
                raise
            why = "no running Ray cluster found on this machine" if address == "auto" else str(e)
            raise ConfigError(f"--address {address}: {why}; start one with ray start --head, or give its head's "
                              "HOST:PORT") from None
        except SystemExit as e:  # ray.init's own handler while it ran: sys.exit(SIGTERM)
            if before and e.code == signal.SIGTERM:
                _received.append(signal.SIGTERM)
            raise
        _catch_stop_signals(before)  # again: ray.init set its own
        yield True
    except (KeyboardInterrupt, SystemExit):
        if _received:
            raise Terminated(_received[0]) from None
        raise
    finally:
        try:
            started = [c for c in _descendants() if c.pid not in others] if not address else []
            ray.shutdown()  # also after a half-done ray.init: it stops the processes that one started
            _end_leftovers(started)
        finally:
            for signum, handler in before.items():  # None: set outside Python; the default is the closest
                signal.signal(signum, signal.SIG_DFL if handler is None else handler)
    if _received:  # the block caught the interrupt itself: the process must still end
        raise Terminated(_received[0])


def _descendants() -> list[Any]:
    """This process's descendants (`psutil.Process`, which comes with Ray), [] where that fails."""
    try:
        import psutil

        return psutil.Process().children(recursive=True)
    except Exception:  # no psutil, or a process gone while listed: nothing to end then
        return []


def _end_leftovers(processes: list[Any], grace: float = 3.0) -> None:
    """End those of ``processes`` (a local Ray's) still running ``grace`` seconds after ``ray.shutdown``:
    SIGTERM, then SIGKILL ``grace`` seconds later. A shutdown after a half-done ray.init, or after the
    cluster's processes were signalled too, leaves some (the raylet's agents and starting workers,
    then children of no one), which would otherwise run on in the background."""
    import psutil

    def alive(p: Any) -> bool:
        try:
            return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
        except psutil.Error:
            return False

    def wait(left: list[Any]) -> list[Any]:
        # polled: one that ends stays a zombie where no one reaps it, which psutil.wait_procs waits out
        deadline = time.monotonic() + grace
        while left and time.monotonic() < deadline:
            time.sleep(0.1)
            left = [p for p in left if alive(p)]
        return left

    left = wait([p for p in processes if alive(p)])  # the workers end on their own soon after the raylet
    if not left:
        return
    log.info("ending %d processes of the local Ray that outlived its shutdown", len(left))
    for p in left:
        with contextlib.suppress(psutil.Error):
            p.terminate()
    for p in wait(left):
        with contextlib.suppress(psutil.Error):
            p.kill()


@contextlib.contextmanager
def _driver_keeps_sigterm() -> Iterator[None]:
    """ray.init without the failure handler of this process's Ray core: it takes SIGTERM too, and
    aborts the process (skipping every ``finally``, the shutdown's included). The core's handlers of
    crashes (SIGSEGV...) go with it, here only: the workers and the cluster's processes read their
    own setting. (A private setting of Ray's, read when the driver's core starts; where a Ray has
    none, nothing changes.)"""
    from ray._private import ray_constants

    name = "RAY_DISABLE_FAILURE_SIGNAL_HANDLER"
    had = getattr(ray_constants, name, None)
    if had is None:
        yield
        return
    setattr(ray_constants, name, True)
    try:
        yield
    finally:
        setattr(ray_constants, name, had)


def _catch_stop_signals(before: Mapping[int, Any]) -> None:
    """Each signal of ``before`` goes to `_on_stop_signal`, except those ignored in ``before``, which stay ignored."""
    for signum, handler in before.items():
        signal.signal(signum, signal.SIG_IGN if handler is signal.SIG_IGN else _on_stop_signal)


def _init_ray(workers: int, address: str) -> None:
    """``ray.init(address)``, else a local Ray of ``workers`` CPUs (0: all usable cores)."""
    import ray

    from downwash_core.numerics import PORTABLE_TORCH
    from sim.physics import usable_cores

    if address:  # (a local Ray's workers inherit this process's environment, the portable kernels' request included)
        portable = {name: os.environ[name] for name in PORTABLE_TORCH if name in os.environ}
        ray.init(address=address, logging_level=logging.WARNING, runtime_env={"env_vars": portable})
    else:
        # workers at normal priority: Ray lowers them (nice 15) to keep a driver responsive, but here
        # they are the computation and the driver only waits
        ray.init(num_cpus=workers or usable_cores(), include_dashboard=False, logging_level=logging.WARNING,
                 _system_config={"worker_niceness": 0})


def map_on_ray(fn: Callable[[Any], Any], items: list[Any], workers: int = 0, address: str = "") -> list[Any]:
    """``[fn(x) for x in items]``, each call a Ray task of one CPU (Ray as `_ray_session`: one this call
    started is shut down at the end, however it ends). ``fn`` must be importable by name (a module's
    function)."""
    import ray

    check_execution(workers, 1, address)
    with _ray_session(workers, address):
        task = ray.remote(num_cpus=1, max_retries=0)(fn)
        return ray.get([task.remote(x) for x in items])


class _Ray:
    """The Ray the sweep computes on, started at the first task (a sweep whose missing cells other
    processes hold needs none), as `_ray_session`; one it started is shut down by `close`."""

    def __init__(self, workers: int, address: str, data: Mapping[str, tuple]):
        self.workers, self.address, self.data = workers, address, data
        self.started = False
        self.cpus = 0
        self.task: Any = None
        self.refs: dict[str, tuple] = {}
        self._session = contextlib.ExitStack()

    def _start(self) -> None:
        import ray

        self._session.enter_context(_ray_session(self.workers, self.address))
        self.started = True
        self.task = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
        self.cpus = int(ray.cluster_resources().get("CPU", 0))

    @property
    def window(self) -> int:
        """Tasks kept in flight: two per CPU keeps every CPU busy, and a cell is claimed only just
        before its task is submitted (another sweep can take the rest meanwhile)."""
        return max(2, 2 * self.cpus) if self.started else 1

    def submit(self, cells: list[Cell]) -> Any:
        if not self.started:
            self._start()
        import ray

        spec = cells[0].field
        if spec not in self.refs:  # each field's data goes to the object store once
            train, val, _ = self.data[spec]
            self.refs[spec] = (ray.put(train), ray.put(val))
        return self.task.remote(cells, *self.refs[spec])

    def count_cpus(self) -> None:
        """The Ray CPUs at the end of a sweep (a cluster's nodes may have changed). Not on the way out of
        an interrupted one: with the local Ray's processes gone (Ctrl-C reaches them all), the query waits
        for ever."""
        if self.started:
            import ray

            self.cpus = int(ray.cluster_resources().get("CPU", 0))

    def close(self) -> None:
        self._session.close()


def _compute_missing(todo: list[Cell], data: Mapping[str, tuple], cache: CellCache, workers: int, address: str,
                     batch: int, progress: Callable[[int, int], None] | None, total: int) -> tuple[int, int, int]:
    """Compute the cells ``todo`` on Ray, each only while this process holds its claim, caching each
    task's results as it lands; then wait for the cells other processes held and compute those they
    left undone. Returns (cells computed here, cells computed by other processes, the Ray CPUs)."""
    ray_ = _Ray(workers, address, data)
    counts = {"here": 0, "elsewhere": 0, "done": total - len(todo)}
    if progress:
        progress(counts["done"], total)
    remaining = todo
    try:
        while remaining:
            busy, who = _compute_round(remaining, cache, ray_, batch, progress, total, counts)
            if busy:
                log.info("sweep: %d cells are being computed by other processes (e.g. %s); waiting for them",
                         len(busy), who)
            remaining = []
            for cell in busy:
                with cache.claim(cell, wait=True):
                    if cache.load(cell) is None:  # its holder failed or died: computed here, next round
                        remaining.append(cell)
                        continue
                counts["elsewhere"] += 1
                counts["done"] += 1
                if progress:
                    progress(counts["done"], total)
        ray_.count_cpus()
    except (KeyboardInterrupt, Terminated):  # Ctrl-C, or SIGTERM while a local Ray runs (`_ray_session`)
        log.warning("sweep stopped by %s: %d of %d cells are cached; the same command computes the rest",
                    _stopped_by(), counts["done"], total)
        raise
    finally:
        ray_.close()
    return counts["here"], counts["elsewhere"], ray_.cpus if counts["here"] else 0


def _compute_round(cells: list[Cell], cache: CellCache, ray_: _Ray, batch: int,
                   progress: Callable[[int, int], None] | None, total: int,
                   counts: dict[str, int]) -> tuple[list[Cell], str]:
    """One pass over ``cells``: claim each batch's cells just before submitting it (largest first: a
    free CPU takes the next, so the long deep batches start early) and compute those claimed.
    Returns the cells another process held, and who held the first of them."""
    import ray

    from downwash.sweep_cells import batch_cells

    busy: list[Cell] = []
    who = ""
    queue = batch_cells(cells, batch)
    pending: dict[Any, tuple[list[Cell], contextlib.ExitStack]] = {}
    try:
        while queue or pending:
            while queue and len(pending) < ray_.window:
                claims = contextlib.ExitStack()
                mine = []
                for cell in queue.pop(0):
                    if not claims.enter_context(cache.claim(cell)):
                        who = who or cache.holder(cell)
                        busy.append(cell)
                    elif cache.load(cell) is not None:  # stored by another process since this one looked
                        counts["elsewhere"] += 1
                        counts["done"] += 1
                    else:
                        mine.append(cell)
                if mine:
                    pending[ray_.submit(mine)] = (mine, claims)
                else:
                    claims.close()
            if not pending:
                continue
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                done_cells, claims = pending.pop(ref)
                try:
                    for cell, result in zip(done_cells, ray.get(ref)):
                        cache.store(cell, result)
                finally:
                    claims.close()
                counts["here"] += len(done_cells)
                counts["done"] += len(done_cells)
                if progress:
                    progress(counts["done"], total)
    finally:
        for _, claims in pending.values():
            claims.close()
    return busy, who
