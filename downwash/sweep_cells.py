"""The unit of a sweep: its grid, its cells, a cell's data and training, and the cache of results.

    # the steps `downwash.sweep.run_sweep` takes, one by one
    cells = plan_cells(grid, {"so2": (collection_key, train.n_minutes, collection_digest(collection_dir))})
    cache = CellCache("runs/cells")
    for batch in batch_cells(cache.missing(cells), size=5):
        for cell, result in zip(batch, run_cells(batch, train, val)):
            cache.store(cell, result)
    summary = summarize_field(cells, cache.load_all(cells), floor)   # downwash.sweep_stats

`downwash.sweep.run_sweep` takes these steps, the missing cells computed on Ray.

The unit: a cell
----------------
A cell is ONE trained model: one field's staged collection, one model kind, one
training length (minutes, or `FULL`, the whole training set) and one seed. Its
training subset is drawn from the collection's training flights by `cell_data`
(`downwash.datasets.shorten_per_stage`, every stage shortened proportionally) with
a generator seeded by (seed, minutes) only, never by the model kind, and the model
trains with that seed (`downwash.staged.train_config`). So every kind of one
(field, minutes, seed) sees the same subset: the trials are paired across models,
and the difference of two models on one seed is a paired difference. The result is
the RMSE over the collection's whole validation set (all stages), overall and per
axis, with the training summary.

Each cell's result is cached as one JSON file named by its key, the `fingerprint`
of `Cell.record`: the collection's provenance key (field, scene, simulator,
collection and its seed), the digest of the collection's data (every log's data
digest as the manifest records them, `downwash.manifest.collection_digest`: a
collection flown again differently never reuses a stale cell), the model kind, the
minutes, the seed, the training config and `CELL_VERSION` (the rules above). The code
version is recorded in the file, not in the key, as for collections
(`downwash_core.provenance`). Files are written atomically, so a killed sweep leaves
only whole cells, and a rerun computes only the missing ones. The collection's logs are
checked against its manifest before they are loaded (`load_collection`). A process
computes a cell only while it holds the cell's lock (`CellCache.claim`), so that sweeps
sharing the cache compute each cell once.

Cells are cached one by one but computed in batches: `run_cells` trains a batch of
cells of one field and one kind (several seeds and minute points) as ONE ensemble
(`downwash.ensemble.train_ensemble`), each member bit-identical to its own
`train_model` (one intra-op thread). So a cell's numbers do not depend on which
batch computed it, or on which node: a resumed or distributed sweep gives the
numbers of an uninterrupted one, bit for bit (with the same BLAS; see
`downwash.ensemble`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.io import atomic_write_json
from downwash_core.locks import describe_holder, file_lock
from downwash_core.provenance import code_version, fingerprint
from downwash.datasets import Dataset, concatenate, load_dataset, shorten_per_stage
from downwash.labels import label_noise_floor
from downwash.models import PAIRWISE_KINDS
from downwash.manifest import collection_digest, collection_logs, read_manifest, verify_collection
from downwash.staged import train_config
from downwash.train import TrainConfig
from sim.fields.registry import resolve_field_spec

__all__ = [
    "FULL", "CELL_VERSION", "PAPER_MINUTES", "PAPER_MODELS", "SEED_MAX", "MAX_SEEDS", "MAX_CELLS", "SweepGrid",
    "Cell", "load_collection", "load_collection_with_digest", "field_minutes", "plan_cells", "cell_data", "batch_cells", "run_cells", "CellCache",
]  # fmt: skip

log = logging.getLogger("downwash.sweep")  # the sweep's logger, as before the cells had a module of their own

FULL = "full"  # the minute point of the whole training set
CELL_VERSION = 2  # bump when the subset draw, the training or the metric of a cell changes meaning; 2: data digest
PAPER_MINUTES = (1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0)  # 7 points, plus the full set
PAPER_MODELS = ("shallow", "deep", "equivariant")  # the paper's three models
_MINUTE_TICKS = 10_000  # the subset generator sees minutes rounded to 1e-4 min (6 ms of flight)
SEED_MAX = 2**32 - 1  # as experiments.common.SEED_MAX: a seed goes to NumPy's and torch's generators
MAX_SEEDS = 1_000  # per sweep: a point's bootstrap interval (BCa's jackknife) takes memory quadratic in them
MAX_CELLS = 100_000  # per sweep: each is a trained model and a file; planning alone takes seconds per 10^4


@dataclass(frozen=True)
class SweepGrid:
    """What a sweep measures: every (field, model, minutes, seed), each validated on construction.

    fields: field specs (`sim.fields.registry` grammar; "" is the default field);
    models: kinds of `downwash.models.PAIRWISE_KINDS`; minutes: training lengths, min
    (> 0; the whole training set is always added as `FULL`, and a length at or
    beyond it is left out for that field); seeds: the trials (ints in 0..`SEED_MAX`, at
    most `MAX_SEEDS`), each a data subset and a training seed shared by all models; at most
    `MAX_CELLS` cells in all (fields x models x (minutes + 1) x seeds); quick: the quick
    training settings (`downwash.staged.train_config`); training: a `TrainConfig`
    whose seed is replaced per cell (None: `train_config(0, quick)`).
    """

    fields: tuple[str, ...] = ("",)
    models: tuple[str, ...] = PAPER_MODELS
    minutes: tuple[float, ...] = PAPER_MINUTES
    seeds: tuple[int, ...] = tuple(range(10))
    quick: bool = False
    training: TrainConfig | None = None

    def __post_init__(self) -> None:
        fields = _as_tuple("fields", self.fields)
        if not fields:
            raise ConfigError("fields: empty; give at least one field spec ('' is the default field)")
        for spec in fields:
            if not isinstance(spec, str):
                raise ConfigError(f"fields: expected field specs (strings), got {spec!r}")
            resolve_field_spec(spec, label=f"field {spec!r}")  # unknown names raise here, naming the registry
        if len(set(fields)) != len(fields):
            raise ConfigError(f"fields: {list(fields)} names a field twice")
        models = _as_tuple("models", self.models)
        if not models:
            raise ConfigError(f"models: empty; allowed: {', '.join(PAIRWISE_KINDS)}")
        for m in models:
            if m not in PAIRWISE_KINDS:
                raise ConfigError(f"models: unknown {m!r}; allowed: {', '.join(PAIRWISE_KINDS)}")
        if len(set(models)) != len(models):
            raise ConfigError(f"models: {list(models)} names a model twice")
        minutes = []
        for m in _as_tuple("minutes", self.minutes):
            try:
                value = float(m)
            except (TypeError, ValueError):
                raise ConfigError(f"minutes: expected numbers > 0 (min), got {m!r}") from None
            if isinstance(m, bool) or not (math.isfinite(value) and value > 0):
                raise ConfigError(f"minutes: every value must be a finite number > 0 (min), got {m!r}")
            minutes.append(value)
        seeds = _as_tuple("seeds", self.seeds)
        if not seeds:
            raise ConfigError("seeds: empty; give at least one seed (one trial each)")
        for s in seeds:
            if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0:
                raise ConfigError(f"seeds: expected integers >= 0, got {s!r}")
            if s > SEED_MAX:
                raise ConfigError(f"seeds: expected integers in 0..{SEED_MAX} (a generator's seed), got {s!r}")
        if len(set(seeds)) != len(seeds):
            raise ConfigError(f"seeds: {_brief(seeds)} repeats a seed (each seed is one trial)")
        points = len(set(minutes)) + 1  # the full set is always added
        cells = len(fields) * len(models) * points * len(seeds)
        if len(seeds) > MAX_SEEDS or cells > MAX_CELLS:
            size = (f"{cells} cells ({_count(len(fields), 'field')} x {_count(len(models), 'model')} x "
                    f"{_count(points, 'minute point')} x {_count(len(seeds), 'seed')})")
            what = f"seeds: {len(seeds)} seeds make" if len(seeds) > MAX_SEEDS else "grid:"
            raise ConfigError(f"{what} {size}; a sweep takes at most {MAX_SEEDS} seeds and {MAX_CELLS} cells: split "
                              "it into sweeps that share the cell cache")
        if self.training is not None and not isinstance(self.training, TrainConfig):
            raise ConfigError(f"training: expected a TrainConfig or None, got {type(self.training).__name__}")
        object.__setattr__(self, "fields", fields)
        object.__setattr__(self, "models", models)
        object.__setattr__(self, "minutes", tuple(sorted(set(minutes))))
        object.__setattr__(self, "seeds", tuple(int(s) for s in seeds))

    def config(self, seed: int) -> TrainConfig:
        """The training settings of a cell of this seed."""
        base = train_config(0, self.quick) if self.training is None else self.training
        return dataclasses.replace(base, seed=int(seed))

    def describe(self) -> dict[str, Any]:
        return {"fields": list(self.fields), "models": list(self.models), "minutes": list(self.minutes),
                "full": True, "seeds": list(self.seeds), "training": self.config(0).to_dict()}


def _brief(items: Sequence[Any], n: int = 12) -> str:
    """A list for a message, its middle elided when long (a sweep may hold a thousand seeds)."""
    if len(items) <= n:
        return str(list(items))
    head, tail = ", ".join(map(str, items[:n // 2])), ", ".join(map(str, items[-(n // 2):]))
    return f"[{head}, ..., {tail}] ({len(items)})"


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _as_tuple(name: str, value: Any) -> tuple:
    if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
        raise ConfigError(f"{name}: expected a list, got {value!r}")
    return tuple(value)


@dataclass(frozen=True)
class Cell:
    """One trained model of a sweep; its result is cached under `key`.

    field: the field spec as given (for tables; the collection key identifies the
    field); collection: the collection's provenance key; model: the kind; minutes:
    training minutes, or `FULL`; seed: the trial; training: the full training config
    (its seed is the cell's); data: the digest of the collection's data
    (`downwash.manifest.collection_digest`).
    """

    field: str
    collection: str
    model: str
    minutes: float | str
    seed: int
    training: TrainConfig
    data: str = ""

    def record(self) -> dict[str, Any]:
        """Everything that determines the result (the key is its fingerprint)."""
        return {"version": CELL_VERSION, "collection": self.collection, "data": self.data, "model": self.model,
                "minutes": self.minutes, "seed": self.seed, "training": self.training.to_dict(),
                "metric": "rmse over the collection's validation flights, all stages"}

    @property
    def key(self) -> str:
        return fingerprint(self.record(), length=16)

    @property
    def label(self) -> str:
        minutes = self.minutes if self.minutes == FULL else f"{self.minutes:g} min"
        return f"{self.field or 'default'}/{self.model}/{minutes}/seed {self.seed}"


def load_collection(collection_dir: str | Path) -> tuple[Dataset, Dataset, dict]:
    """(training data, validation data, label-noise floor) of a staged collection folder.

    Training: every stage's ``train`` flights; validation: every stage's ``val``
    flights, as its manifest lists them. DataError, before anything is read, when the
    folder holds no complete collection or its logs do not match the manifest
    (`downwash.manifest.verify_collection`: a missing, altered or unlisted log).
    """
    return load_collection_with_digest(collection_dir)[:3]


def load_collection_with_digest(collection_dir: str | Path) -> tuple[Dataset, Dataset, dict, str]:
    """`load_collection` and the digest of its data (`downwash.manifest.collection_digest`)."""
    collection_dir = Path(collection_dir)
    manifest = read_manifest(collection_dir / "manifest.json")
    if not manifest.get("complete"):
        raise DataError(f"{collection_dir}: an unfinished staged collection; finish it first (rerun "
                        f"`python -m experiments.staged_collection --collection-dir {collection_dir}` with the "
                        "options that began it)")
    verify_collection(collection_dir, manifest)
    train_files, val_files = collection_logs(collection_dir, "train", manifest), collection_logs(collection_dir, "val",
                                                                                                 manifest)
    if not any(train_files) or not any(val_files):
        raise DataError(f"{collection_dir}: the manifest lists no training or no validation logs; a sweep needs both "
                        "(a collection with --val-ratio > 0)")
    train = concatenate([load_dataset(f) for f in train_files if f])
    val = concatenate([load_dataset(f) for f in val_files if f])
    floor = label_noise_floor([p for f in val_files for p in f])
    return train, val, floor, collection_digest(collection_dir, manifest)


def field_minutes(grid: SweepGrid, full_minutes: float) -> list[float | str]:
    """The minute points of a field whose training set lasts ``full_minutes``: those shorter, then FULL."""
    return [m for m in grid.minutes if m < full_minutes] + [FULL]


def plan_cells(grid: SweepGrid, collections: Mapping[str, tuple[str, float] | tuple[str, float, str]]) -> list[Cell]:
    """Every cell of the grid, in (field, model, minutes, seed) order.

    collections: field spec -> (collection provenance key, training minutes of that
    collection, digest of its data), the digest optional (`Cell.data`).
    """
    missing = [f for f in grid.fields if f not in collections]
    if missing:
        raise ConfigError(f"plan_cells: no collection given for field(s) {missing}")
    cells = []
    for spec in grid.fields:
        key, full, *data = collections[spec]
        for kind in grid.models:
            for m in field_minutes(grid, full):
                cells += [Cell(spec, key, kind, m, s, grid.config(s), *data) for s in grid.seeds]
    return cells


def cell_data(train: Dataset, minutes: float | str, seed: int) -> Dataset:
    """The training subset of a cell: the whole set for FULL, else `minutes` of it, every stage
    shortened proportionally, drawn by a generator of (seed, minutes) (the same for every kind)."""
    if minutes == FULL:
        return train
    rng = np.random.default_rng([int(seed), int(round(float(minutes) * _MINUTE_TICKS))])
    return shorten_per_stage(train, float(minutes), rng)


def batch_cells(cells: Sequence[Cell], size: int) -> list[list[Cell]]:
    """The cells grouped into batches of at most ``size`` cells of one field and one kind.

    Each batch trains as one ensemble (`run_cells`). Within a group the cells are
    taken in (minutes, seed) order, so a batch holds whole minute points where it
    can. Batches come largest estimated cost first (the deep model, the longest
    data), which keeps workers busy to the end when they run in that order.
    Scheduling only: a cell's result does not depend on its batch.
    """
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise ConfigError(f"batch size: expected an integer >= 1, got {size!r}")
    groups: dict[tuple[str, str], list[Cell]] = {}
    for c in cells:
        groups.setdefault((c.collection, c.data, c.model), []).append(c)
    batches = []
    for group in groups.values():
        group = sorted(group, key=lambda c: (math.inf if c.minutes == FULL else c.minutes, c.seed))
        batches += [group[i:i + size] for i in range(0, len(group), size)]

    return sorted(batches, key=lambda b: sum(_cost(c) for c in b), reverse=True)


def _cost(cell: Cell) -> float:
    """A rough training cost of a cell, for scheduling only (measured on 2 cores, the paper's
    collection): rows per step x steps x the kind's cost per row. A cell of m minutes trains on
    0.8 x 3000 m rows (50 Hz, a fifth held out) and runs about 500 + 40 m steps (early stopping
    after ~1500 scheduled); the deep model costs about 7 times a one-hidden-layer model per row."""
    minutes = 20.0 if cell.minutes == FULL else float(cell.minutes)
    rows = min(cell.training.batch_size, 0.8 * 3000 * minutes)
    return (7.0 if cell.model == "deep" else 1.0) * rows * (500 + 40 * minutes)


def run_cells(cells: Sequence[Cell], train: Dataset, val: Dataset) -> list[dict[str, Any]]:
    """Train the cells (one field, one kind) as one ensemble and evaluate each on ``val``.

    Returns one result per cell, in order: ``rmse`` (m/s^2, over samples and the
    three axes), ``rmse_axis`` (x, y, z), ``train_minutes``, ``history`` (epochs,
    best epoch, steps, planned epochs, best early-stopping loss, training rows),
    ``compute`` (the ensemble's wall and CPU seconds and size, host, code version:
    not part of the numbers), ``record`` and ``key``.
    """
    import torch

    from downwash.ensemble import train_ensemble

    if not cells:
        return []
    kinds = {(c.collection, c.data, c.model) for c in cells}
    if len(kinds) != 1:
        raise ConfigError(f"run_cells: a batch must be of one collection and one model kind, got {sorted(kinds)}")
    kind = cells[0].model
    data = [cell_data(train, c.minutes, c.seed) for c in cells]
    t0, c0 = time.perf_counter(), time.process_time()
    trained = train_ensemble(kind, data, [c.training for c in cells])
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    # the features do not depend on the weights: the validation set is encoded once for the batch;
    # one intra-op thread, as in training, so that the numbers do not depend on the machine's cores
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.inference_mode():
            enc, y = trained[0][0].encode_samples(val)
            predictions = [model.decode_samples(enc).double().numpy() for model, _ in trained]
    finally:
        torch.set_num_threads(threads)
    y = y.double().numpy()
    out = []
    for cell, d, (model, history), pred in zip(cells, data, trained, predictions):
        err = pred - y
        out.append({
            "key": cell.key, "record": cell.record(), "field": cell.field,
            "rmse": float(np.sqrt(np.mean(err**2))), "rmse_axis": np.sqrt(np.mean(err**2, axis=0)).tolist(),
            "train_minutes": d.n_minutes,
            "history": {k: history[k] for k in ("epochs", "best_epoch", "steps", "planned_epochs", "best_val_loss",
                                                 "n_train", "n_val")},
            "compute": {"ensemble_seconds": seconds, "ensemble_cpu_seconds": cpu, "ensemble_size": len(cells),
                        "host": socket.gethostname(),
                        "pid": os.getpid(), "code": code_version()},
        })  # fmt: skip
    return out


class CellCache:
    """One JSON file per cell, ``root/<model>/<key>.json``, written atomically.

    A file whose record differs from the cell's (a key collision, or a hand-edited
    file) or that cannot be read counts as missing, with a warning, and is rewritten.
    A process computes a cell only inside `claim` (the lock ``root/<model>/<key>.lock``,
    removed on release), so that sweeps sharing the cache compute each cell once.
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def path(self, cell: Cell) -> Path:
        return self.root / cell.model / f"{cell.key}.json"

    def lock_path(self, cell: Cell) -> Path:
        return self.root / cell.model / f"{cell.key}.lock"

    @contextlib.contextmanager
    def claim(self, cell: Cell, wait: bool = False) -> Iterator[bool]:
        """Hold the cell's lock for the block. Yields True while held; with wait=False, False at
        once when another process holds it (it is computing the cell); wait=True waits for it
        to let go (it stored the cell, failed or died: `load` tells which)."""
        with file_lock(self.lock_path(cell), wait=wait, label=f"sweep cell {cell.label}", remove=True,
                       quiet=True) as held:
            yield held

    def holder(self, cell: Cell) -> str:
        """Who holds the cell's lock, for messages ("pid 123 on host h (...)")."""
        return describe_holder(self.lock_path(cell))

    def load(self, cell: Cell) -> dict[str, Any] | None:
        import json

        path = self.path(cell)
        if not path.is_file():
            return None
        try:
            result = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            log.warning("%s: unreadable cell result (%s); recomputing it", path, e)
            return None
        if result.get("record") != json.loads(json.dumps(cell.record())):
            log.warning("%s: holds another cell's result; recomputing it", path)
            return None
        return result

    def load_all(self, cells: Sequence[Cell]) -> dict[str, dict[str, Any]]:
        """{key: result} of the cached cells among ``cells``."""
        return {c.key: r for c in cells if (r := self.load(c)) is not None}

    def missing(self, cells: Sequence[Cell]) -> list[Cell]:
        return [c for c in cells if self.load(c) is None]

    def store(self, cell: Cell, result: Mapping[str, Any]) -> Path:
        if result.get("key") != cell.key:
            raise ConfigError(f"CellCache.store: result of cell {result.get('key')!r} given for cell {cell.key!r}")
        path = self.path(cell)
        atomic_write_json(path, {**result, "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
        return path
