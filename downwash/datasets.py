"""Training data sets assembled from flight logs: samples, flights and stages.

A `Dataset` is a frozen bundle of per-sample arrays (one sample per 50 Hz
controller tick, follower of one flight). Flights are the unit of every split:
samples of one flight are strongly correlated, so validation never shares a
flight with training.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from downwash_core.errors import DataError
from downwash_core.provenance import differences
from downwash.labels import DEFAULT_POLYORDER, DEFAULT_WINDOW, MODEL_INPUTS, SAMPLE_SCHEMA, labels_from_log
from sim.logs import load_log
from downwash_core.params import RATES

# The log metadata every flight of one data set must share: what the labels mean depends on it
# (the wind too: a log flown in wind holds its `describe()`, one flown without holds none).
FLIGHT_PROVENANCE = ("field", "scene", "config", "controller", "turbulence", "wind")

__all__ = [
    "FLIGHT_PROVENANCE",
    "Dataset",
    "concatenate",
    "load_dataset",
    "find_logs",
    "split_by_flight",
    "shorten_per_stage",
]

logger = logging.getLogger(__name__)

# name -> trailing shape: the labelled sample (SAMPLE_SCHEMA) with where it came from
_ARRAYS = {
    **{name: SAMPLE_SCHEMA[name][0] for name in (*MODEL_INPUTS, "y")},
    "flight": (),
    "stage": (),
    **{name: SAMPLE_SCHEMA[name][0] for name in ("t", "field_mean")},
}


@dataclass(frozen=True)
class Dataset:
    """N samples (world frame, SI units).

    dp (N, 3) m, v_a (N, 3) m/s, v_b (N, 3) m/s, R_a (N, 3, 3): model inputs (see
      `downwash.features`); y (N, 3) m/s^2: labels;
    flight (N,) int: flight id, an index into ``sources``; stage (N,) int: data
      collection stage; t (N,) s: tick time within the flight;
    field_mean (N, 3) m/s^2: the true mean field (NaN where unknown);
    sources: flight id -> where it came from (file path), may be empty.
    """

    dp: np.ndarray
    v_a: np.ndarray
    v_b: np.ndarray
    R_a: np.ndarray
    y: np.ndarray
    flight: np.ndarray
    stage: np.ndarray
    t: np.ndarray
    field_mean: np.ndarray
    sources: tuple[str, ...] = ()
    provenance: dict | None = None  # what every flight was flown with (FLIGHT_PROVENANCE of the logs' meta)

    def __post_init__(self) -> None:
        n = np.shape(self.dp)[0] if np.ndim(self.dp) else -1
        for name, trail in _ARRAYS.items():
            a = np.asarray(getattr(self, name))
            if name in ("flight", "stage"):
                a = a.astype(np.int64, copy=False)
            elif a.dtype != np.float32:
                a = a.astype(np.float64, copy=False)
            if a.shape != (n, *trail):
                raise ValueError(f"Dataset.{name}: expected shape {(n, *trail)}, got {a.shape}")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "sources", tuple(str(s) for s in self.sources))

    def __len__(self) -> int:
        return int(self.dp.shape[0])

    @property
    def n_minutes(self) -> float:
        """Flight time covered, min (one sample per controller tick)."""
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
        return Dataset(**{name: getattr(self, name)[index] for name in _ARRAYS}, sources=self.sources,
                       provenance=self.provenance)

    def select_flights(self, flights: Sequence[int] | np.ndarray) -> "Dataset":
        """The samples of the given flight ids."""
        return self.subset(np.isin(self.flight, np.asarray(flights, dtype=np.int64)))

    def summary(self) -> dict:
        """Sizes for metadata: samples, flights, minutes in all and per stage."""
        per_stage = {str(int(s)): float(np.sum(self.stage == s) * RATES.control_dt / 60.0) for s in self.stages}
        return {
            "n_samples": len(self),
            "n_flights": int(self.flights.size),
            "minutes": self.n_minutes,
            "minutes_per_stage": per_stage,
        }

    @staticmethod
    def from_labels(labels: dict[str, np.ndarray], flight: int, stage: int, source: str = "",
                    provenance: dict | None = None) -> "Dataset":
        """One flight's `labels_from_log` output as a Dataset with the given flight id and stage."""
        n = len(labels["y"])
        sources = [""] * (flight + 1)
        sources[flight] = str(source)
        return Dataset(
            dp=labels["dp"], v_a=labels["v_a"], v_b=labels["v_b"], R_a=labels["R_a"], y=labels["y"],
            flight=np.full(n, flight), stage=np.full(n, stage), t=labels["t"],
            field_mean=labels.get("field_mean", np.full((n, 3), np.nan)), sources=tuple(sources),
            provenance=provenance,
        )  # fmt: skip


def _n_flight_slots(ds: Dataset) -> int:
    return max(len(ds.sources), int(ds.flight.max()) + 1 if len(ds) else 0)


def concatenate(datasets: Sequence[Dataset]) -> Dataset:
    """One data set from several; flight ids of each later part are offset so that they stay distinct."""
    datasets = list(datasets)
    if not datasets:
        raise ValueError("concatenate: need at least one Dataset")
    parts: dict[str, list[np.ndarray]] = {name: [] for name in _ARRAYS}
    sources: list[str] = []
    provenance = datasets[0].provenance
    for ds in datasets:
        if ds.provenance != provenance:
            where = next((s for s in ds.sources if s), "a data set")
            raise DataError(f"{where}: flown with other settings than {next((s for s in datasets[0].sources if s), 'the first')}:"
                            "\n  " + "\n  ".join(differences(ds.provenance, provenance))
                            + "\nTrain only on logs of one field and configuration.")
        offset = len(sources)
        for name in _ARRAYS:
            a = getattr(ds, name)
            parts[name].append(a + offset if name == "flight" else a)
        slots = _n_flight_slots(ds)
        sources.extend(list(ds.sources) + [""] * (slots - len(ds.sources)))
    return Dataset(**{name: np.concatenate(v) for name, v in parts.items()}, sources=tuple(sources),
                   provenance=provenance)


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
    window: int = DEFAULT_WINDOW,
    polyorder: int = DEFAULT_POLYORDER,
    stage: int | None = None,
    recursive: bool = False,
) -> Dataset:
    """Labelled samples from flight logs (a folder of `.npz` logs, one file, or a list).

    Flight ids follow the sorted file order (``sources[i]`` is the i-th file); the
    stage is ``stage`` if given, else each log's ``meta['stage']`` (default 0).
    A foreign, truncated or corrupt file raises `sim.logs.LogError` naming it;
    a log too short to label is skipped with a warning.
    """
    files = find_logs(location, recursive=recursive)
    parts = []
    for i, path in enumerate(files):
        log = load_log(path)
        labels = labels_from_log(log, window, polyorder, source=path)
        if len(labels["y"]) == 0:
            logger.warning("%s: no labelled samples (only %d rows, status %s), skipped", path, len(log), log.meta.get("status"))
        st = int(log.meta.get("stage", 0)) if stage is None else int(stage)
        record = {k: log.meta.get(k) for k in FLIGHT_PROVENANCE}
        parts.append(Dataset.from_labels(labels, flight=0, stage=st, source=str(path), provenance=record))
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
