"""Resumable sweeps of validation RMSE over fields x model kinds x training minutes x seeds.

    from downwash.sweep_cells import SweepGrid
    grid = SweepGrid(fields=("so2",), models=("shallow", "equivariant"), minutes=(1.0, 5.0), seeds=(0, 1, 2))
    results = run_sweep(grid, {"so2": pipeline}, "runs/cells", workers=2)   # a local Ray of 2 CPUs
    results["fields"]["so2"]["models"]["equivariant"]["rmse_ci_low"]        # per minute point

This module holds `run_sweep`, which spreads the missing cells over Ray (imported
only when cells must be computed), and the checks of the command lines' options. A
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
from pathlib import Path
from typing import Any, Callable, Mapping

from downwash_core.errors import ConfigError
from downwash_core.numerics import PORTABLE_TORCH
from downwash_core.provenance import fingerprint
from downwash.datasets import Dataset
from downwash.staged import ensure_collection
from downwash.sweep_cells import Cell, CellCache, SweepGrid, _load_collection, batch_cells, plan_cells, run_cells
from downwash.sweep_stats import PAPER_CLAIM, Claim, summarize_field

__all__ = ["grid_from_text", "check_execution", "run_sweep", "map_on_ray"]

log = logging.getLogger(__name__)


def grid_from_text(fields: str, models: str, minutes: str, seeds: str, quick: bool = False) -> SweepGrid:
    """A grid from the command line's text: fields separated by ';' (a field spec holds commas),
    the rest by ','. ConfigError naming the option for an item that is not a number."""

    def items(name: str, text: str, convert: Callable[[str], Any], sep: str = ",") -> tuple:
        try:
            return tuple(convert(t.strip()) for t in text.split(sep) if t.strip())
        except ValueError:
            what = "numbers" if convert is float else "integers" if convert is int else "names"
            raise ConfigError(f"--{name}: expected a comma list of {what}, got {text!r}") from None

    specs = tuple(dict.fromkeys(t.strip() for t in fields.split(";"))) if fields.strip() else ("",)
    return SweepGrid(fields=specs, models=items("models", models, str), minutes=items("minutes", minutes, float),
                     seeds=items("seeds", seeds, int), quick=quick)


def check_execution(workers: int, batch: int) -> None:
    """ConfigError unless ``workers >= 0`` (0: all cores) and ``batch >= 1``."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise ConfigError(f"--workers: expected an integer >= 0 (0: all cores), got {workers!r}")
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ConfigError(f"--batch: expected an integer >= 1 (cells per task), got {batch!r}")


def run_sweep(
    grid: SweepGrid,
    pipelines: Mapping[str, Any],
    cache_dir: str | Path,
    *,
    workers: int = 0,
    address: str = "",
    batch: int = 5,
    claim: Claim = PAPER_CLAIM,
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
    cores), shut down at the end; none at all when no cell is computed here.
    ``claim`` is tested per field (`summarize_field`); ``progress(label)`` may return a
    ``(done, total)`` callback.

    Returns ``fields`` (spec -> `summarize_field` plus ``collection_key``,
    ``collection_dir``, ``data_digest`` and ``validation_minutes``), ``cells``
    (total, cached: found in the cache, also those another sweep computed meanwhile,
    and computed here), ``computed_elsewhere`` (cells another sweep computed while
    this one ran), ``workers`` (the Ray CPUs, 0 when nothing ran) and ``grid``.
    """
    check_execution(workers, batch)
    missing = [f for f in grid.fields if f not in pipelines]
    if missing:
        raise ConfigError(f"run_sweep: no pipeline given for field(s) {missing}")
    data: dict[str, tuple[Dataset, Dataset, dict]] = {}
    collections: dict[str, tuple[str, float, str]] = {}
    for spec in grid.fields:
        p = pipelines[spec]
        ensure_collection(p.collection_dir, p.models_dir, p.config, p.field, progress)
        *data[spec], digest = _load_collection(p.collection_dir)
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

    node = ray.get_runtime_context().get_node_id()
    results = run_cells(cells, train, val)
    for r in results:
        r["compute"]["ray_node"] = node
    return results


def _init_ray(workers: int, address: str) -> bool:
    """Connect to Ray: the one this process is connected to, else ``ray.init(address)``, else a local
    Ray of ``workers`` CPUs (0: all cores). True when this call started it (the caller shuts it down)."""
    import ray

    if ray.is_initialized():
        return False
    if address:  # (a local Ray's workers inherit this process's environment, the portable kernels' request included)
        portable = {name: os.environ[name] for name in PORTABLE_TORCH if name in os.environ}
        ray.init(address=address, logging_level=logging.WARNING, runtime_env={"env_vars": portable})
    else:
        # workers at normal priority: Ray lowers them (nice 15) to keep a driver responsive, but here
        # they are the computation and the driver only waits
        ray.init(num_cpus=workers or os.cpu_count() or 1, include_dashboard=False, logging_level=logging.WARNING,
                 _system_config={"worker_niceness": 0})
    return True


def map_on_ray(fn: Callable[[Any], Any], items: list[Any], workers: int = 0, address: str = "") -> list[Any]:
    """``[fn(x) for x in items]``, each call a Ray task of one CPU (Ray as `_init_ray`; one this call
    started is shut down at the end). ``fn`` must be importable by name (a module's function)."""
    import ray

    check_execution(workers, 1)
    owned = _init_ray(workers, address)
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(fn)
        return ray.get([task.remote(x) for x in items])
    finally:
        if owned:
            ray.shutdown()


class _Ray:
    """The Ray the sweep computes on, started at the first task (a sweep whose missing cells other
    processes hold needs none): the one this process is connected to, else ``ray.init(address)``,
    else a local Ray of ``workers`` CPUs; one it started is shut down by `close`."""

    def __init__(self, workers: int, address: str, data: Mapping[str, tuple]):
        self.workers, self.address, self.data = workers, address, data
        self.started = self.owned = False
        self.cpus = 0
        self.task: Any = None
        self.refs: dict[str, tuple] = {}

    def _start(self) -> None:
        import ray

        self.owned = _init_ray(self.workers, self.address)
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

    def close(self) -> None:
        if self.started:
            import ray

            self.cpus = int(ray.cluster_resources().get("CPU", 0))
            if self.owned:
                ray.shutdown()


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
