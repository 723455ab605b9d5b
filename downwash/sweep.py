"""Resumable sweeps of validation RMSE over fields x model kinds x training minutes x seeds.

    grid = SweepGrid(fields=("so2",), models=("shallow", "equivariant"), minutes=(1.0, 5.0), seeds=(0, 1, 2))
    results = run_sweep(grid, {"so2": pipeline}, "runs/cells", workers=2)   # a local Ray of 2 CPUs
    results["fields"]["so2"]["models"]["equivariant"]["rmse_ci_low"]        # per minute point

    # the steps it takes, one by one
    cells = plan_cells(grid, {"so2": (collection_key, train.n_minutes, collection_digest(collection_dir))})
    cache = CellCache("runs/cells")
    for batch in batch_cells(cache.missing(cells), size=5):
        for cell, result in zip(batch, run_cells(batch, train, val)):
            cache.store(cell, result)
    summary = summarize_field(cells, cache.load_all(cells), floor)

This module holds the cells, their cache, their statistics and `run_sweep`, which
spreads the missing cells over Ray (imported only when cells must be computed); the
command lines are `experiments.sweep` and its preset `experiments.sample_efficiency`
(experiments do not import each other, so what they share lives here).

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
checked against its manifest before they are loaded (`load_collection`).

Concurrent sweeps share the cache: a process computes a cell only while it holds the
cell's lock (`CellCache.claim`, a `downwash_core.locks.file_lock` beside the result),
taken just before the cell's batch is submitted. A second sweep on the same cache skips
the cells another process holds, computes the rest, then waits for those and loads
them, so no cell is computed twice; a holder that dies lets go of its cells at once
(the kernel drops its locks) and the waiting sweep computes them.

Cells are cached one by one but computed in batches: `run_cells` trains a batch of
cells of one field and one kind (several seeds and minute points) as ONE ensemble
(`downwash.ensemble.train_ensemble`), each member bit-identical to its own
`train_model` (one intra-op thread). So a cell's numbers do not depend on which
batch computed it, or on which node: a resumed or distributed sweep gives the
numbers of an uninterrupted one, bit for bit (with the same BLAS; see
`downwash.ensemble`).

Statistics
----------
Per (field, model, minutes): the mean RMSE over seeds with a 95 % bootstrap
confidence interval (`bootstrap_ci`: `scipy.stats.bootstrap`, BCa, a fixed seed).
The paper's claim, "the equivariant model at 5 min beats the best baseline at
15 min" (`PAPER_CLAIM`), is tested seed by seed (`paired_comparison`): the
difference ``d_s = rmse(equivariant, 5, s) - min_b rmse(b, 15, s)``, its mean with
a bootstrap CI, and the fraction of seeds where ``d_s < 0``.
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
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.io import atomic_write_json
from downwash_core.locks import describe_holder, file_lock
from downwash_core.provenance import code_version, fingerprint
from downwash.datasets import Dataset, concatenate, load_dataset, shorten_per_stage
from downwash.labels import label_noise_floor
from downwash.models import PAIRWISE_KINDS
from downwash.manifest import collection_digest, collection_logs, read_manifest, verify_collection
from downwash.staged import ensure_collection, train_config
from downwash.train import TrainConfig
from sim.fields.registry import resolve_field_spec

__all__ = [
    "FULL", "CELL_VERSION", "PAPER_MINUTES", "PAPER_MODELS", "Claim", "PAPER_CLAIM", "SweepGrid", "Cell",
    "load_collection", "field_minutes", "plan_cells", "cell_data", "batch_cells", "run_cells", "CellCache", "bootstrap_ci",
    "paired_comparison", "summarize_field", "grid_from_text", "check_execution", "run_sweep", "minute_labels",
    "table_rows", "claim_text", "markdown", "plot_field",
]  # fmt: skip

log = logging.getLogger(__name__)

FULL = "full"  # the minute point of the whole training set
CELL_VERSION = 2  # bump when the subset draw, the training or the metric of a cell changes meaning; 2: data digest
PAPER_MINUTES = (1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0)  # 7 points, plus the full set
PAPER_MODELS = ("shallow", "deep", "equivariant")  # the paper's three models
_MINUTE_TICKS = 10_000  # the subset generator sees minutes rounded to 1e-4 min (6 ms of flight)


@dataclass(frozen=True)
class Claim:
    """``model`` at ``minutes`` beats the best of ``baselines`` at ``baseline_minutes``, seed by seed."""

    model: str = "equivariant"
    minutes: float | str = 5.0  # or FULL
    baselines: tuple[str, ...] = ("shallow", "deep")
    baseline_minutes: float | str = 15.0

    def describe(self) -> str:
        at = lambda m: "the full set" if m == FULL else f"{m:g} min"  # noqa: E731
        return f"{self.model} at {at(self.minutes)} < min({', '.join(self.baselines)}) at {at(self.baseline_minutes)}"


PAPER_CLAIM = Claim()  # the paper's abstract: 5 min of data beat the baselines with 15 min


@dataclass(frozen=True)
class SweepGrid:
    """What a sweep measures: every (field, model, minutes, seed), each validated on construction.

    fields: field specs (`sim.fields.registry` grammar; "" is the default field);
    models: kinds of `downwash.models.PAIRWISE_KINDS`; minutes: training lengths, min
    (> 0; the whole training set is always added as `FULL`, and a length at or
    beyond it is left out for that field); seeds: the trials (ints >= 0), each a
    data subset and a training seed shared by all models; quick: the quick
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
        if len(set(seeds)) != len(seeds):
            raise ConfigError(f"seeds: {list(seeds)} repeats a seed (each seed is one trial)")
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
    return _load_collection(collection_dir)[:3]


def _load_collection(collection_dir: str | Path) -> tuple[Dataset, Dataset, dict, str]:
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


# -- statistics -------------------------------------------------------------------------------

def bootstrap_ci(values: Sequence[float], confidence: float = 0.95, seed: int = 0,
                 n_resamples: int = 9999) -> tuple[float, float]:
    """The bootstrap confidence interval (low, high) of the mean of ``values``.

    `scipy.stats.bootstrap` (BCa) with a generator seeded by ``seed``: the same
    values give the same interval. Fewer than two values, or values that are all
    equal, have no spread to resample: the interval is the mean itself.
    """
    from scipy import stats

    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1 or x.size == 0 or not np.all(np.isfinite(x)):
        raise ConfigError(f"bootstrap_ci: expected a non-empty 1-D list of finite numbers, got {values!r}")
    if not 0 < confidence < 1:
        raise ConfigError(f"bootstrap_ci: confidence must be in (0, 1), got {confidence!r}")
    mean = float(np.mean(x))
    if x.size < 2 or np.ptp(x) <= 1e-12 * max(1.0, abs(mean)):
        return mean, mean
    res = stats.bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=n_resamples, method="BCa",
                          vectorized=True, random_state=np.random.default_rng(seed))
    low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
    if not (math.isfinite(low) and math.isfinite(high)):  # BCa undefined (e.g. one odd value): percentile
        res = stats.bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=n_resamples,
                              method="percentile", vectorized=True, random_state=np.random.default_rng(seed))
        low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return low, high


def paired_comparison(target: Mapping[int, float], baselines: Sequence[Mapping[int, float]],
                      seed: int = 0) -> dict[str, Any]:
    """Seed by seed: ``d_s = target[s] - min_b baselines[b][s]`` over the seeds all of them have.

    Returns n, seeds, differences, mean_difference with its bootstrap CI
    (`bootstrap_ci`), and fraction_holds, the share of seeds with ``d_s < 0``.
    ConfigError when no baseline is given or no seed is shared.
    """
    if not baselines:
        raise ConfigError("paired_comparison: no baseline given")
    seeds = sorted(set(target).intersection(*[set(b) for b in baselines]))
    if not seeds:
        raise ConfigError("paired_comparison: the target and the baselines share no seed (no pairs)")
    d = np.array([target[s] - min(b[s] for b in baselines) for s in seeds])
    low, high = bootstrap_ci(d, seed=seed)
    return {"n": len(seeds), "seeds": seeds, "differences": d.tolist(), "mean_difference": float(d.mean()),
            "ci_low": low, "ci_high": high, "fraction_holds": float(np.mean(d < 0))}


def summarize_field(cells: Sequence[Cell], results: Mapping[str, Mapping[str, Any]], floor: Mapping[str, Any],
                    claim: Claim = PAPER_CLAIM, seed: int = 0) -> dict[str, Any]:
    """The statistics of one field's cells (all of them must have results).

    Returns minutes (the FULL point as its length in minutes), seeds, models ->
    rmse_mean, rmse_std, rmse_ci_low, rmse_ci_high (per minute point) and rmse_runs
    (minutes x seeds), the label-noise floor and validation minutes, and ``claim``:
    `paired_comparison` at the claim's points, or None with ``claim_skipped`` saying why.
    """
    absent = [c.label for c in cells if c.key not in results]
    if absent:
        raise ConfigError(f"summarize_field: {len(absent)} cells have no result, e.g. {absent[:3]}")
    models = list(dict.fromkeys(c.model for c in cells))
    points = list(dict.fromkeys(c.minutes for c in cells))
    seeds = sorted({c.seed for c in cells})
    full = next((results[c.key]["train_minutes"] for c in cells if c.minutes == FULL), None)
    value = {(c.model, c.minutes, c.seed): results[c.key]["rmse"] for c in cells}
    out: dict[str, Any] = {
        "minutes": [full if m == FULL else m for m in points], "seeds": seeds, "models": {},
        "noise_floor": floor["rmse_mean"], "noise_floor_applied": floor["rmse"],
    }
    for kind in models:
        runs = np.array([[value[(kind, m, s)] for s in seeds] for m in points])
        cis = [bootstrap_ci(row, seed=seed) for row in runs]
        out["models"][kind] = {"rmse_mean": runs.mean(axis=1).tolist(), "rmse_std": runs.std(axis=1).tolist(),
                               "rmse_ci_low": [c[0] for c in cis], "rmse_ci_high": [c[1] for c in cis],
                               "rmse_runs": runs.tolist()}
    out["claim"], out["claim_skipped"] = None, None
    needed = [(claim.model, claim.minutes)] + [(b, claim.baseline_minutes) for b in claim.baselines]
    lacking = [f"{k} at {m if m == FULL else f'{m:g} min'}" for k, m in needed if k not in models or m not in points]
    if lacking:
        out["claim_skipped"] = f"not in the grid: {', '.join(lacking)}"
    else:
        per_seed = lambda k, m: {s: value[(k, m, s)] for s in seeds}  # noqa: E731
        out["claim"] = {"statement": claim.describe(), **dataclasses.asdict(claim),
                        **paired_comparison(per_seed(claim.model, claim.minutes),
                                            [per_seed(b, claim.baseline_minutes) for b in claim.baselines], seed)}
    return out


# -- the sweep ---------------------------------------------------------------------------------

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

        self.owned = not ray.is_initialized()
        if self.owned:
            if self.address:
                ray.init(address=self.address, logging_level=logging.WARNING)
            else:
                # workers at normal priority: Ray lowers them (nice 15) to keep a driver responsive, but here
                # they are the computation and the driver only waits
                ray.init(num_cpus=self.workers or os.cpu_count() or 1, include_dashboard=False,
                         logging_level=logging.WARNING, _system_config={"worker_niceness": 0})
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


# -- presentation (text; the figure is drawn on the caller's axes) ----------------------------

def minute_labels(minutes: Sequence[float]) -> list[str]:
    """Column titles: "5 min", ..., the last "16.9 min (full)"."""
    return [f"{m:.3g} min (full)" if i == len(minutes) - 1 else f"{m:g} min" for i, m in enumerate(minutes)]


def table_rows(summary: Mapping[str, Any], digits: int = 3) -> list[list[str]]:
    """Rows [model, "mean [low, high]", ...] of one field's summary."""
    return [[k] + [f"{mu:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"
                   for mu, lo, hi in zip(m["rmse_mean"], m["rmse_ci_low"], m["rmse_ci_high"])]
            for k, m in summary["models"].items()]


def claim_text(summary: Mapping[str, Any]) -> str:
    """One sentence on the paired claim of a field's summary (or why it was not tested)."""
    c = summary.get("claim")
    if not c:
        return f"Claim not tested: {summary.get('claim_skipped')}."
    return (f"Claim \"{c['statement']}\", paired over {c['n']} seeds: mean difference {c['mean_difference']:+.4f} "
            f"m/s^2, 95 % CI [{c['ci_low']:+.4f}, {c['ci_high']:+.4f}]; it holds for "
            f"{100 * c['fraction_holds']:.0f} % of the seeds.")


def markdown(fields: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown: per field, mean RMSE [95 % CI] per model and minute point, and the claim."""
    parts = []
    for spec, r in fields.items():
        header = ["model"] + minute_labels(r["minutes"])
        lines = [f"### Field `{spec or 'default'}` (collection `{r.get('collection_key')}`)", "",
                 f"Validation RMSE (m/s^2), mean [95 % bootstrap CI] over {len(r['seeds'])} seeds; label-noise "
                 f"floor {r['noise_floor']:.4f} m/s^2; validation set {r.get('validation_minutes', 0):.3g} min.", "",
                 "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(row) + " |" for row in table_rows(r, 4)]
        lines += ["", claim_text(r)]
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"


_COLORS = {"shallow": "tab:orange", "deep": "tab:blue", "equivariant": "tab:green", "equivariant_general": "tab:purple"}


def plot_field(ax: Any, summary: Mapping[str, Any], title: str) -> None:
    """Draw one field's mean RMSE against minutes, its 95 % CI band and the noise floor on ``ax``
    (a matplotlib Axes; this module imports no plotting library)."""
    minutes = summary["minutes"]
    for kind, m in summary["models"].items():
        ax.plot(minutes, m["rmse_mean"], "o-", color=_COLORS.get(kind), label=kind)
        ax.fill_between(minutes, m["rmse_ci_low"], m["rmse_ci_high"], color=_COLORS.get(kind), alpha=0.2)
    ax.axhline(summary["noise_floor"], color="k", ls="--", lw=1, label="label noise floor")
    ax.set_xlabel("training flight time (min)")
    ax.set_ylabel("validation RMSE (m/s^2)")
    ax.set_title(title)
    ax.legend()
