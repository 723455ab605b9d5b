"""The one data set: every labelled sample of a target vehicle with its set of neighbours.

A `Dataset` is a frozen bundle of per-sample arrays (`downwash.labels.SAMPLE_SCHEMA`):
one sample per 50 Hz controller tick and target vehicle, with the vehicles around the
target padded to a fixed count K with a mask, so that a batch is a set of plain arrays
(B, K, ...). The two-vehicle (leader-follower) data is its K = 1 case with the follower
as the one target (`downwash.labels.PAIR`); `Dataset.pairs` gives every real (target,
neighbour) pair as flat arrays, the samples of the per-neighbour models. Padding slots
hold dp = 0, v_a = 0, R_a = I (finite features) and are ignored by every model.

Flights are the unit of every split: samples of one flight are strongly correlated, so
validation never shares a flight with training.

Provenance. A data set records what its logs were flown with: the field, the flight
config, controller, turbulence and wind, the vehicle model (not the vehicle list:
scenes of different sizes may be mixed) and the aggregation law (how the wakes of
several vehicles combine; `aggregation_record`). Logs that differ in any of these are
never mixed, with one exception: with two vehicles every law of `sim.aggregation` is
the pairwise force, so a two-vehicle log records the law as None ("any") and joins
many-vehicle logs of any one law (`concatenate`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.params import RATES
from downwash_core.provenance import describe, differences
from downwash.labels import DEFAULT_POLYORDER, DEFAULT_WINDOW, PAIR, SAMPLE_SCHEMA, labels_from_log
from downwash.support import Support, support_of
from sim.aggregation import DEFAULT_AGGREGATION, make_aggregation
from sim.logs import load_log
from sim.neighbours import NeighbourSet

__all__ = [
    "PROVENANCE",
    "aggregation_record",
    "log_provenance",
    "merge_provenance",
    "Dataset",
    "Pairs",
    "concatenate",
    "find_logs",
    "load_dataset",
    "split_by_flight",
    "shorten_per_stage",
]

logger = logging.getLogger(__name__)

# What the labels of a log mean depends on these log metadata entries (plus the vehicle
# model and the aggregation law, see `log_provenance`); the vehicle list may differ.
PROVENANCE = ("field", "config", "controller", "turbulence", "wind")


def aggregation_record(law: Any = None) -> dict[str, Any]:
    """The provenance record of an aggregation law: a registered name, a law object, a stored
    record (dict, returned as is) or None (`sim.aggregation.DEFAULT_AGGREGATION`, the linear sum
    that flights flew with before the law was recorded in the logs)."""
    if law is None:
        law = DEFAULT_AGGREGATION
    if isinstance(law, str):
        law = make_aggregation(law)  # ConfigError naming the registered laws
    if isinstance(law, dict):
        return dict(law)
    return describe(law)


def log_provenance(meta: dict[str, Any]) -> dict[str, Any]:
    """What the labels of a log depend on: `PROVENANCE` entries of its metadata (None
    where absent: no wind), the vehicle model (scene digest and timestep, not the vehicle
    list) and the aggregation law (``meta['aggregation']``, default linear; None for a log of
    at most two vehicles, where every law is the pairwise force)."""
    scene = meta.get("scene") or {}
    record = {k: meta.get(k) for k in PROVENANCE}
    record["vehicle_model"] = {k: scene.get(k) for k in ("quad_xml_sha256", "timestep")}
    n_vehicles = len(meta.get("vehicles") or scene.get("vehicles") or ())
    record["aggregation"] = None if n_vehicles <= 2 else aggregation_record(meta.get("aggregation"))
    return record


def _mixed_values(records: Sequence[dict | None], key: str) -> dict[str, list]:
    """{"mixed": the distinct values of `key` over the records, in first-seen order} (a mixed entry's
    values are taken as they are)."""
    values: list = []
    for r in records:
        v = r.get(key) if isinstance(r, dict) else None
        for item in (v["mixed"] if isinstance(v, dict) and set(v) == {"mixed"} else [v]):
            if item not in values:
                values.append(item)
    return {"mixed": values}


def merge_provenance(records: Sequence[dict | None], names: Sequence[str] = (), mixed: Sequence[str] = ()) -> dict | None:
    """The provenance of data sets joined together; DataError naming the differences.

    Records must be equal, except that an aggregation law of None (two-vehicle data) joins
    any one law, and that the entries named in `mixed` (e.g. "wind": indoor and outdoor flights
    trained on together, on purpose) may differ: the result lists their values as
    ``{"mixed": [...]}``, and such an entry joins any other. names: where each record comes
    from, for the message.
    """
    records = list(records)
    mixed = set(mixed) | {k for r in records if isinstance(r, dict) for k, v in r.items()
                          if isinstance(v, dict) and set(v) == {"mixed"}}
    if mixed and all(isinstance(r, dict) for r in records):
        merged = {k: _mixed_values(records, k) for k in mixed}
        records = [{**r, **merged} for r in records]
    laws = [r.get("aggregation") for r in records if isinstance(r, dict)]
    law = next((a for a in laws if a is not None), None)
    strip = lambda r: {k: v for k, v in r.items() if k != "aggregation"} if isinstance(r, dict) else r  # noqa: E731
    first = strip(records[0])
    for i, r in enumerate(records):
        where = names[i] if i < len(names) and names[i] else f"data set {i}"
        diffs = differences(strip(r), first)
        if isinstance(r, dict) and r.get("aggregation") not in (None, law):
            diffs += differences({"aggregation": r.get("aggregation")}, {"aggregation": law})
        if (r is None) != (records[0] is None) or diffs:
            raise DataError(f"{where}: flown with other settings than the first data set:\n  "
                            + "\n  ".join(diffs or ["no provenance record"])
                            + "\nTrain only on logs of one field, configuration and aggregation law.")
    return None if records[0] is None else {**records[0], "aggregation": law}


class Pairs(NamedTuple):
    """Every real (target, neighbour) pair of a `Dataset` as flat arrays (`Dataset.pairs`), the
    call of the per-neighbour models: dp, v_a (P, 3), v_b (P, 3), R_a (P, 3, 3), y (P, 3) (the
    target's label), flight (P,) and hist (P, H, 3) (the neighbour's history)."""

    dp: np.ndarray
    v_a: np.ndarray
    v_b: np.ndarray
    R_a: np.ndarray
    y: np.ndarray
    flight: np.ndarray
    hist: np.ndarray


# the arrays a Dataset holds: name -> trailing shape (K: the neighbour count)
_ARRAYS: dict[str, tuple[str | int, ...]] = {
    **{name: SAMPLE_SCHEMA[name][0] for name in ("dp", "v_a", "v_b", "R_a", "mask", "kind_a", "kind_b", "hist",
                                                 "neighbour", "vehicle", "y")},
    "flight": (),
    "stage": (),
    "t": (),
    "field_mean": (3,),
}
_INTEGER = ("neighbour", "vehicle", "flight", "stage")


@dataclass(frozen=True)
class Dataset:
    """N target samples with their neighbour sets (world frame, SI units).

    dp (N, K, 3) m, v_a (N, K, 3) m/s, v_b (N, 3) m/s, R_a (N, K, 3, 3), mask (N, K) bool:
      model inputs (module doc); kind_a (N, K, D), kind_b (N, D): the neighbour's and target's
      vehicle kinds (`downwash.features.KIND_FEATURES`; default 0: paper quads); hist (N, K, H, 3) m:
      the neighbour's displacement over each lag of `downwash.features.HISTORY_LAGS` (default 0: it
      did not move);
      neighbour (N, K), vehicle (N,): vehicle indices in the log;
    y (N, 3) m/s^2: labels; flight (N,), stage (N,): flight id (an index into ``sources``)
      and collection stage; t (N,) s; field_mean (N, 3) m/s^2: the true mean field;
    neighbours: the neighbour set the samples were built with (K = its max_neighbours);
    provenance: what the flights were flown with (`log_provenance`).

    Splits are by flight (`split_by_flight`).
    """

    dp: np.ndarray
    v_a: np.ndarray
    v_b: np.ndarray
    R_a: np.ndarray
    mask: np.ndarray
    neighbour: np.ndarray
    vehicle: np.ndarray
    y: np.ndarray
    flight: np.ndarray
    stage: np.ndarray
    t: np.ndarray
    field_mean: np.ndarray
    kind_a: np.ndarray | None = None
    kind_b: np.ndarray | None = None
    hist: np.ndarray | None = None
    neighbours: NeighbourSet = PAIR
    sources: tuple[str, ...] = ()
    provenance: dict | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.neighbours, NeighbourSet):
            raise TypeError(f"Dataset.neighbours: expected a NeighbourSet, got {type(self.neighbours).__name__}")
        K = self.neighbours.max_neighbours
        n = np.shape(self.y)[0] if np.ndim(self.y) else -1
        for name, trail in _ARRAYS.items():
            a = getattr(self, name)
            if a is None and name in ("kind_a", "kind_b", "hist"):  # not given: paper quads that did not move
                a = np.zeros((max(n, 0), *(K if d == "K" else d for d in trail)))
            a = np.asarray(a)
            if name == "mask":
                a = a.astype(bool, copy=False)
            elif name in _INTEGER:
                a = a.astype(np.int64, copy=False)
            elif a.dtype != np.float32:
                a = a.astype(np.float64, copy=False)
            want = (n, *(K if d == "K" else d for d in trail))
            if a.shape != want:
                raise ValueError(f"Dataset.{name}: expected shape {want}, got {a.shape}")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "sources", tuple(str(s) for s in self.sources))

    def __len__(self) -> int:
        return int(self.y.shape[0])

    @property
    def n_minutes(self) -> float:
        """Target samples in minutes of one vehicle's flight (one sample per controller tick)."""
        return len(self) * RATES.control_dt / 60.0

    @property
    def flights(self) -> np.ndarray:
        """Sorted unique flight ids."""
        return np.unique(self.flight)

    @property
    def stages(self) -> np.ndarray:
        """Sorted unique stage ids."""
        return np.unique(self.stage)

    def subset(self, index: np.ndarray) -> "Dataset":
        """The samples at an index array or boolean mask (flight ids and sources unchanged)."""
        return Dataset(**{name: getattr(self, name)[index] for name in _ARRAYS}, neighbours=self.neighbours,
                            sources=self.sources, provenance=self.provenance)

    def select_flights(self, flights: Sequence[int] | np.ndarray) -> "Dataset":
        """The samples of the given flight ids."""
        return self.subset(np.isin(self.flight, np.asarray(flights, dtype=np.int64)))

    def summary(self) -> dict[str, Any]:
        """Sizes for metadata: samples, flights, minutes in all and per stage, the neighbour set and
        how full it is, and the support of its pairs (`downwash.support.support_of`, what the guard
        reads from a checkpoint)."""
        per_stage = {str(int(st)): float(np.sum(self.stage == st) * RATES.control_dt / 60.0) for st in self.stages}
        return {
            "n_samples": len(self),
            "n_flights": int(self.flights.size),
            "minutes": self.n_minutes,
            "minutes_per_stage": per_stage,
            "neighbours": self.neighbours.describe(),
            "neighbour_count_histogram": np.bincount(self.mask.sum(axis=1),
                                                     minlength=self.neighbours.max_neighbours + 1).tolist(),
            "support": None if (s := self.support()) is None else s.describe(),  # for the guard
        }

    def support(self) -> Support | None:
        """The support of its real (target, neighbour) pairs, kinds included (`downwash.support.support_of`)."""
        s, k = np.nonzero(self.mask)
        return support_of(self.dp[s, k], self.v_a[s, k], self.v_b[s], self.R_a[s, k], self.kind_a[s, k],
                          self.kind_b[s])

    def pairs(self) -> "Pairs":
        """Every real (target, neighbour) pair as flat arrays: the samples of the per-neighbour models.

        The label of a pair is its target's label, the whole force: for the pair data (K = 1,
        every slot real) these are the samples in order.
        """
        s, k = np.nonzero(self.mask)
        return Pairs(self.dp[s, k], self.v_a[s, k], self.v_b[s], self.R_a[s, k], self.y[s], self.flight[s],
                     self.hist[s, k])

    @staticmethod
    def from_pairs(dp: np.ndarray, v_a: np.ndarray, v_b: np.ndarray, R_a: np.ndarray, y: np.ndarray,
                   flight: np.ndarray, stage: np.ndarray | None = None, t: np.ndarray | None = None,
                   field_mean: np.ndarray | None = None, sources: Sequence[str] = (),
                   provenance: dict | None = None, hist: np.ndarray | None = None) -> "Dataset":
        """Two-vehicle samples (K = 1, `PAIR`) from flat arrays: dp, v_a, v_b (N, 3), R_a (N, 3, 3),
        y (N, 3), flight (N,), hist (N, H, 3); stage 0, t 0, field_mean NaN and hist 0 where not
        given. The target is vehicle 1, its neighbour vehicle 0."""
        n = np.shape(y)[0]
        return Dataset(
            dp=np.asarray(dp)[:, None], v_a=np.asarray(v_a)[:, None], v_b=v_b, R_a=np.asarray(R_a)[:, None],
            mask=np.ones((n, 1), bool), neighbour=np.zeros((n, 1), np.int64), vehicle=np.ones(n, np.int64), y=y,
            flight=flight, stage=np.zeros(n, np.int64) if stage is None else stage,
            t=np.zeros(n) if t is None else t, field_mean=np.full((n, 3), np.nan) if field_mean is None else field_mean,
            hist=None if hist is None else np.asarray(hist)[:, None], neighbours=PAIR, sources=tuple(sources),
            provenance=provenance,
        )  # fmt: skip

    @staticmethod
    def from_labels(labels: dict[str, np.ndarray], neighbours: NeighbourSet, flight: int, stage: int,
                    source: str = "", provenance: dict | None = None) -> "Dataset":
        """One flight's `downwash.labels.labels_from_log` output with the given flight id and stage."""
        n = len(labels["y"])
        sources = [""] * (flight + 1)
        sources[flight] = str(source)
        return Dataset(
            **{name: labels[name] for name in ("dp", "v_a", "v_b", "R_a", "mask", "neighbour", "vehicle", "y", "t")},
            kind_a=labels.get("kind_a"), kind_b=labels.get("kind_b"), hist=labels.get("hist"),
            flight=np.full(n, flight), stage=np.full(n, stage),
            field_mean=labels.get("field_mean", np.full((n, 3), np.nan)), neighbours=neighbours,
            sources=tuple(sources), provenance=provenance,
        )  # fmt: skip


def concatenate(datasets: Sequence[Dataset], mixed: Sequence[str] = ()) -> Dataset:
    """One data set from several of one neighbour set and provenance; flight ids stay distinct.

    DataError naming the differences when the neighbour sets or the provenance differ
    (`merge_provenance`: two-vehicle data joins data of any one aggregation law; the provenance
    entries named in `mixed`, e.g. "wind", may differ and are listed).
    """
    datasets = list(datasets)
    if not datasets:
        raise ValueError("concatenate: need at least one Dataset")
    first = datasets[0]
    names = [next((s for s in ds.sources if s), "") for ds in datasets]
    provenance = merge_provenance([ds.provenance for ds in datasets], names, mixed)
    parts: dict[str, list[np.ndarray]] = {name: [] for name in _ARRAYS}
    sources: list[str] = []
    for ds, where in zip(datasets, names):
        if ds.neighbours != first.neighbours:
            raise DataError(f"{where or 'a data set'}: neighbour set {ds.neighbours.describe()}, the first data set "
                            f"has {first.neighbours.describe()}")
        offset = len(sources)
        for name in _ARRAYS:
            a = getattr(ds, name)
            parts[name].append(a + offset if name == "flight" else a)
        slots = max(len(ds.sources), int(ds.flight.max()) + 1 if len(ds) else 0)
        sources.extend(list(ds.sources) + [""] * (slots - len(ds.sources)))
    return Dataset(**{name: np.concatenate(v) for name, v in parts.items()}, neighbours=first.neighbours,
                        sources=tuple(sources), provenance=provenance)


def find_logs(location: str | os.PathLike | Sequence[str | os.PathLike], recursive: bool = False) -> list[Path]:
    """The `.npz` log files of a folder (sorted), a single file, or a list of files.

    Raises FileNotFoundError for a missing path and ValueError for an empty folder
    or a folder without `.npz` files, naming the folder.
    """
    if isinstance(location, (str, os.PathLike)):
        path = Path(location)
        if path.is_dir():
            files = sorted(path.rglob("*.npz") if recursive else path.glob("*.npz"))
            if not files:
                others = sorted(p.name for p in path.iterdir() if not p.name.startswith("."))
                if not others:
                    raise ValueError(f"{path}: empty folder, no .npz flight logs")
                raise ValueError(f"{path}: no .npz flight logs among {len(others)} entries (e.g. {others[0]!r})")
            return files
        if path.is_file():
            return [path]
        raise FileNotFoundError(f"{path}: no such file or folder")
    files = [Path(p) for p in location]
    if not files:
        raise ValueError("load_dataset: empty list of log files")
    for p in files:
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such log file")
    return files


def load_dataset(
    location: str | os.PathLike | Sequence[str | os.PathLike],
    neighbours: NeighbourSet = PAIR,
    window: int = DEFAULT_WINDOW,
    polyorder: int = DEFAULT_POLYORDER,
    stage: int | None = None,
    recursive: bool = False,
    targets: Sequence[int] | str | None = None,
) -> Dataset:
    """Labelled samples from flight logs (a folder of `.npz` logs, one file, or a list).

    neighbours, targets: as `downwash.labels.labels_from_log` (default: the pair's
    samples, every vehicle but the leader with its nearest other vehicle).
    Flight ids follow the sorted file order (``sources[i]`` is the i-th file); the
    stage is ``stage`` if given, else each log's ``meta['stage']`` (default 0).
    A foreign, truncated or corrupt file raises `sim.logs.LogError` naming it;
    a log too short to label is skipped with a warning; logs flown with other
    settings (`log_provenance`) raise DataError naming the difference.
    """
    if not isinstance(neighbours, NeighbourSet):
        raise ConfigError(f"neighbours: expected a NeighbourSet, got {type(neighbours).__name__}")
    files = find_logs(location, recursive=recursive)
    parts = []
    for path in files:
        log = load_log(path)
        labels = labels_from_log(log, neighbours, window, polyorder, source=path, targets=targets)
        if len(labels["y"]) == 0:
            logger.warning("%s: no labelled samples (only %d rows, status %s), skipped", path, len(log),
                           log.meta.get("status"))
        st = int(log.meta.get("stage", 0)) if stage is None else int(stage)
        parts.append(Dataset.from_labels(labels, neighbours, flight=0, stage=st, source=str(path),
                                         provenance=log_provenance(log.meta)))
    ds = concatenate(parts)  # flight id i <-> files[i], also for skipped (empty) flights
    if len(ds) == 0:
        raise ValueError(f"{location}: none of the {len(files)} logs has labelled samples")
    return ds


def split_by_flight(ds: Dataset, val_fraction: float, rng: np.random.Generator) -> tuple[Dataset, Dataset]:
    """(train, val): whole flights, about ``val_fraction`` of the samples in val.

    Within each stage that has at least two flights, flights are drawn in random
    order (``rng``) into val until that stage's share is met; so validation covers
    every stage that can spare a flight. If no stage can, the split is over all
    flights. Raises ValueError with fewer than two flights.
    """
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction: expected a value in (0, 1), got {val_fraction!r}")
    flights = ds.flights
    if flights.size < 2:
        raise ValueError(f"split_by_flight: need at least 2 flights to split by flight, got {flights.size}")
    counts = {int(f): int(n) for f, n in zip(*np.unique(ds.flight, return_counts=True))}
    flight_stage = {int(f): int(ds.stage[np.argmax(ds.flight == f)]) for f in flights}

    def draw(candidates: list[int]) -> list[int]:
        order = [candidates[i] for i in rng.permutation(len(candidates))]
        target = val_fraction * sum(counts[f] for f in candidates)
        chosen, total = [], 0
        for f in order[:-1]:  # keep at least one flight for training
            if total >= target:
                break
            chosen.append(f)
            total += counts[f]
        return chosen

    val: list[int] = []
    for s in sorted(set(flight_stage.values())):
        cand = sorted(f for f, st in flight_stage.items() if st == s)
        if len(cand) >= 2:
            val += draw(cand)
    if not val:
        val = draw(sorted(counts))
    mask = np.isin(ds.flight, np.asarray(val, dtype=np.int64))
    return ds.subset(~mask), ds.subset(mask)


def shorten_per_stage(ds: Dataset, minutes: float, rng: np.random.Generator) -> Dataset:
    """A shorter data set of ``minutes`` of flight, each stage shortened proportionally.

    Every stage keeps the fraction ``minutes / ds.n_minutes`` of its samples (the
    paper: with three equal stages, 3 min means 1 min per stage). Flights of a
    stage are taken whole in random order (``rng``); the last one is cut to a
    contiguous prefix (in time) to meet the stage's share to the sample.
    """
    total = ds.n_minutes
    if not 0.0 < minutes <= total * (1 + 1e-9):
        raise ValueError(f"minutes: expected a value in (0, {total:.4g}] (the data set's length), got {minutes!r}")
    frac = min(1.0, minutes / total)
    keep: list[np.ndarray] = []
    for s in ds.stages:
        idx_stage = np.flatnonzero(ds.stage == s)
        target = int(round(frac * idx_stage.size))
        stage_flights = np.unique(ds.flight[idx_stage])
        taken = 0
        for f in stage_flights[rng.permutation(stage_flights.size)]:
            if taken >= target:
                break
            idx = idx_stage[ds.flight[idx_stage] == f]
            idx = idx[np.argsort(ds.t[idx], kind="stable")]
            idx = idx[: target - taken]
            keep.append(idx)
            taken += idx.size
    return ds.subset(np.sort(np.concatenate(keep)) if keep else np.zeros(0, dtype=np.int64))
