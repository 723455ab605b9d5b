"""Samples for models of many vehicles: every vehicle's label with its set of neighbours.

The two-vehicle data (`downwash.labels`) pairs the follower's label with ONE leader.
Here every vehicle of a V-vehicle log is a target, and each of its samples carries
the vehicles around it, padded to a fixed count K with a mask, so that a batch is a
set of plain tensors (B, K, ...). For target j and neighbour i (estimated states,
exactly as `downwash.labels` uses them)::

    dp   (K, 3)    m     p_j - p_i, world frame (z up): the target relative to the neighbour
    v_a  (K, 3)    m/s   neighbour velocity v_i ("leader" in the pair models' call)
    v_b  (3,)      m/s   target velocity v_j ("follower"), shared by its neighbours
    R_a  (K, 3, 3) -     neighbour body-to-world rotation (motion-capture attitude)
    mask (K,)      bool  True for a real neighbour, False for padding
    y    (3,)      m/s^2 label f = a - u on the target

Padding slots hold dp = 0, v_a = 0, R_a = I (finite features) and are ignored by
every model through the mask. With K = 1 on a two-vehicle log the follower's
samples are exactly `labels.labels_from_log`'s (a test checks it bit for bit).

Neighbour set (`sim.neighbours.NeighbourSet`): the candidates are all other vehicles
with a finite distance; those farther than ``radius`` (if given) are dropped; the
``max_neighbours`` nearest (ties by vehicle index) are kept. The same selection
(`sim.neighbours.select_neighbours`) serves the data, the predictor in the loop and the
swarm env's observation, so a model sees in flight the sets it was trained on.

Provenance. A data set records what its logs were flown with: the field, the flight
config, controller, turbulence and wind, the vehicle model (not the vehicle list:
scenes of different sizes may be mixed) and the aggregation law (how the wakes of
several vehicles combine; `aggregation_record`). Logs that differ in any of these are
never mixed, with one exception: with two vehicles every law of `sim.aggregation` is
the pairwise force, so a two-vehicle log records the law as None ("any") and joins
many-vehicle logs of any one law (`concatenate_swarm`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.geometry import quat_to_mat
from downwash_core.params import RATES
from downwash_core.provenance import describe, differences
from downwash.datasets import Dataset, find_logs
from downwash.labels import (
    DEFAULT_POLYORDER,
    DEFAULT_WINDOW,
    FAIL_MARGIN_S,
    _check_filter,
    finite_rows,
    follower_acceleration,
    sample_period,
    smooth_command,
)
from sim.aggregation import DEFAULT_AGGREGATION, make_aggregation
from sim.neighbours import NeighbourSet, gather_neighbours, select_neighbours
from sim.logs import FlightLog, load_log

__all__ = [
    "SWARM_SAMPLE_SCHEMA",
    "SWARM_PROVENANCE",
    "aggregation_record",
    "log_provenance",
    "merge_provenance",
    "swarm_labels_from_log",
    "SwarmDataset",
    "concatenate_swarm",
    "load_swarm_dataset",
]

logger = logging.getLogger(__name__)

# One labelled sample of a V-vehicle log: name -> (trailing shape with K = max_neighbours, meaning).
SWARM_SAMPLE_SCHEMA: dict[str, tuple[tuple[str | int, ...], str]] = {
    "dp": (("K", 3), "m, p_target - p_neighbour (estimates), world frame; 0 in padding"),
    "v_a": (("K", 3), "m/s, neighbour velocity (estimate), world frame; 0 in padding"),
    "v_b": ((3,), "m/s, target velocity (estimate), world frame"),
    "R_a": (("K", 3, 3), "neighbour body-to-world rotation (motion capture); identity in padding"),
    "mask": (("K",), "True for a real neighbour, False for padding"),
    "neighbour": (("K",), "vehicle index of each neighbour in the log, -1 in padding"),
    "vehicle": ((), "vehicle index of the target in the log"),
    "y": ((3,), "m/s^2, label f = a - u on the target, world frame"),
    "t": ((), "s, tick time within the flight"),
    "row": ((), "row index in the log"),
    "field_mean": ((3,), "m/s^2, true mean field on the target (diagnostics only)"),
    "field_applied": ((3,), "m/s^2, true applied field on the target (diagnostics only)"),
}

# What the labels of a log mean depends on these log metadata entries (plus the vehicle
# model and the aggregation law, see `log_provenance`); the vehicle list may differ.
SWARM_PROVENANCE = ("field", "config", "controller", "turbulence", "wind")


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
    """What the labels of a log depend on: `SWARM_PROVENANCE` entries of its metadata (None
    where absent: no wind), the vehicle model (scene digest and timestep, not the vehicle
    list) and the aggregation law (``meta['aggregation']``, default linear; None for a log of
    at most two vehicles, where every law is the pairwise force)."""
    scene = meta.get("scene") or {}
    record = {k: meta.get(k) for k in SWARM_PROVENANCE}
    record["vehicle_model"] = {k: scene.get(k) for k in ("quad_xml_sha256", "timestep")}
    n_vehicles = len(meta.get("vehicles") or scene.get("vehicles") or ())
    record["aggregation"] = None if n_vehicles <= 2 else aggregation_record(meta.get("aggregation"))
    return record


def merge_provenance(records: Sequence[dict | None], names: Sequence[str] = ()) -> dict | None:
    """The provenance of data sets joined together; DataError naming the differences.

    Records must be equal, except that an aggregation law of None (two-vehicle data) joins
    any one law. names: where each record comes from, for the message.
    """
    records = list(records)
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


def _empty(K: int) -> dict[str, np.ndarray]:
    out = {}
    for name, (shape, _) in SWARM_SAMPLE_SCHEMA.items():
        dtype = bool if name == "mask" else np.int64 if name in ("neighbour", "vehicle", "row") else np.float64
        out[name] = np.zeros((0, *(K if d == "K" else d for d in shape)), dtype=dtype)
    return out


def swarm_labels_from_log(
    log: FlightLog,
    neighbours: NeighbourSet,
    window: int = DEFAULT_WINDOW,
    polyorder: int = DEFAULT_POLYORDER,
    fail_margin_s: float = FAIL_MARGIN_S,
    source: str | os.PathLike | None = None,
    targets: Sequence[int] | None = None,
) -> dict[str, np.ndarray]:
    """Labelled samples of every target vehicle of one flight, with their neighbour sets.

    Labels are `downwash.labels`'s: the Savitzky-Golay acceleration of each vehicle's
    motion-capture positions minus its command smoothed by the same kernel. The kept
    rows are the same as there (filter edges, the end of a failed flight, everything from
    the first non-finite value on), with the finiteness checked over ALL vehicles.
    targets: vehicle indices (default all). Returns the arrays of `SWARM_SAMPLE_SCHEMA`,
    N = (targets) x (kept rows), target-major: each target's samples in time order.
    """
    _check_filter(window, polyorder)
    where = f"{source}: " if source is not None else ""
    arr = log.arrays
    T, V = arr["pos"].shape[:2]
    targets = list(range(V)) if targets is None else [int(v) for v in targets]
    if not targets or any(not 0 <= v < V for v in targets) or len(set(targets)) != len(targets):
        raise ConfigError(f"{where}targets: expected distinct vehicle indices in [0, {V - 1}], got {targets}")
    K = neighbours.max_neighbours
    if T < 2:
        return _empty(K)
    dt = sample_period(arr["t"])
    end = T
    if log.meta.get("status", 0) != 0:
        end -= int(round(fail_margin_s / dt))
    end = min(end, finite_rows(arr))
    if end < window:
        return _empty(K)
    h = window // 2
    rows = np.arange(h, end - h)
    pos, vel = arr["pos_est"][rows], arr["vel_est"][rows]
    rot = quat_to_mat(arr["quat_est"][rows].astype(np.float64))
    index, mask = select_neighbours(pos, neighbours)  # (R, V, K)
    inputs = gather_neighbours(pos, vel, rot, index, mask)
    parts = []
    for v in targets:  # one vehicle at a time: bit-identical to labels_from_log's follower
        acc = follower_acceleration(arr["t"][:end], arr["mocap_pos"][:end, v], window, polyorder)
        u = smooth_command(arr["u_cmd"][:end, v], window, polyorder)
        parts.append({
            "dp": inputs["dp"][:, v], "v_a": inputs["v_a"][:, v], "v_b": inputs["v_b"][:, v].astype(np.float64),
            "R_a": inputs["R_a"][:, v], "mask": mask[:, v], "neighbour": index[:, v],
            "vehicle": np.full(rows.size, v, dtype=np.int64), "y": acc[rows] - u[rows],
            "t": arr["t"][rows].astype(np.float64), "row": rows.astype(np.int64),
            "field_mean": arr["field_mean"][rows, v].astype(np.float64),
            "field_applied": arr["field_applied"][rows, v].astype(np.float64),
        })  # fmt: skip
    return {name: np.concatenate([p[name] for p in parts]) for name in SWARM_SAMPLE_SCHEMA}


# the arrays a SwarmDataset holds: name -> trailing shape (K: the neighbour count)
_ARRAYS: dict[str, tuple[str | int, ...]] = {
    **{name: SWARM_SAMPLE_SCHEMA[name][0] for name in ("dp", "v_a", "v_b", "R_a", "mask", "neighbour", "vehicle", "y")},
    "flight": (),
    "stage": (),
    "t": (),
    "field_mean": (3,),
}
_INTEGER = ("neighbour", "vehicle", "flight", "stage")


@dataclass(frozen=True)
class SwarmDataset:
    """N target samples with their neighbour sets (world frame, SI units).

    dp (N, K, 3) m, v_a (N, K, 3) m/s, v_b (N, 3) m/s, R_a (N, K, 3, 3), mask (N, K) bool:
      model inputs (module doc); neighbour (N, K), vehicle (N,): vehicle indices in the log;
    y (N, 3) m/s^2: labels; flight (N,), stage (N,): flight id (an index into ``sources``)
      and collection stage; t (N,) s; field_mean (N, 3) m/s^2: the true mean field;
    neighbours: the neighbour set the samples were built with (K = its max_neighbours);
    provenance: what the flights were flown with (`log_provenance`).

    Splits by flight work as for `downwash.datasets.Dataset` (`split_by_flight`).
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
    neighbours: NeighbourSet = NeighbourSet()
    sources: tuple[str, ...] = ()
    provenance: dict | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.neighbours, NeighbourSet):
            raise TypeError(f"SwarmDataset.neighbours: expected a NeighbourSet, got {type(self.neighbours).__name__}")
        K = self.neighbours.max_neighbours
        n = np.shape(self.y)[0] if np.ndim(self.y) else -1
        for name, trail in _ARRAYS.items():
            a = np.asarray(getattr(self, name))
            if name == "mask":
                a = a.astype(bool, copy=False)
            elif name in _INTEGER:
                a = a.astype(np.int64, copy=False)
            elif a.dtype != np.float32:
                a = a.astype(np.float64, copy=False)
            want = (n, *(K if d == "K" else d for d in trail))
            if a.shape != want:
                raise ValueError(f"SwarmDataset.{name}: expected shape {want}, got {a.shape}")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "sources", tuple(str(s) for s in self.sources))

    def __len__(self) -> int:
        return int(self.y.shape[0])

    @property
    def vehicle_minutes(self) -> float:
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

    def subset(self, index: np.ndarray) -> "SwarmDataset":
        """The samples at an index array or boolean mask (flight ids and sources unchanged)."""
        return SwarmDataset(**{name: getattr(self, name)[index] for name in _ARRAYS}, neighbours=self.neighbours,
                            sources=self.sources, provenance=self.provenance)

    def select_flights(self, flights: Sequence[int] | np.ndarray) -> "SwarmDataset":
        """The samples of the given flight ids."""
        return self.subset(np.isin(self.flight, np.asarray(flights, dtype=np.int64)))

    def summary(self) -> dict[str, Any]:
        """Sizes for metadata: samples, flights, vehicle-minutes, the neighbour set and how full it is."""
        n_real = self.mask.sum(axis=1)
        return {
            "n_samples": len(self),
            "n_flights": int(self.flights.size),
            "vehicle_minutes": self.vehicle_minutes,
            "neighbours": self.neighbours.describe(),
            "neighbour_count_histogram": np.bincount(n_real, minlength=self.neighbours.max_neighbours + 1).tolist(),
        }

    def pairs(self) -> Dataset:
        """Every real (target, neighbour) pair as a two-vehicle `Dataset` (the pair models' samples).

        The label of a pair is its target's label, the whole force: for K = 1 these are
        exactly the samples of `labels.labels_from_log` (the target as follower).
        """
        s, k = np.nonzero(self.mask)
        return Dataset(dp=self.dp[s, k], v_a=self.v_a[s, k], v_b=self.v_b[s], R_a=self.R_a[s, k], y=self.y[s],
                       flight=self.flight[s], stage=self.stage[s], t=self.t[s], field_mean=self.field_mean[s],
                       sources=self.sources, provenance=self.provenance)

    @staticmethod
    def from_labels(labels: dict[str, np.ndarray], neighbours: NeighbourSet, flight: int, stage: int,
                    source: str = "", provenance: dict | None = None) -> "SwarmDataset":
        """One flight's `swarm_labels_from_log` output with the given flight id and stage."""
        n = len(labels["y"])
        sources = [""] * (flight + 1)
        sources[flight] = str(source)
        return SwarmDataset(
            **{name: labels[name] for name in ("dp", "v_a", "v_b", "R_a", "mask", "neighbour", "vehicle", "y", "t")},
            flight=np.full(n, flight), stage=np.full(n, stage),
            field_mean=labels.get("field_mean", np.full((n, 3), np.nan)), neighbours=neighbours,
            sources=tuple(sources), provenance=provenance,
        )  # fmt: skip


def concatenate_swarm(datasets: Sequence[SwarmDataset]) -> SwarmDataset:
    """One data set from several of one neighbour set and provenance; flight ids stay distinct.

    DataError naming the differences when the neighbour sets or the provenance differ
    (`merge_provenance`: two-vehicle data joins data of any one aggregation law).
    """
    datasets = list(datasets)
    if not datasets:
        raise ValueError("concatenate_swarm: need at least one SwarmDataset")
    first = datasets[0]
    names = [next((s for s in ds.sources if s), "") for ds in datasets]
    provenance = merge_provenance([ds.provenance for ds in datasets], names)
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
    return SwarmDataset(**{name: np.concatenate(v) for name, v in parts.items()}, neighbours=first.neighbours,
                        sources=tuple(sources), provenance=provenance)


def load_swarm_dataset(
    location: str | os.PathLike | Sequence[str | os.PathLike],
    neighbours: NeighbourSet,
    window: int = DEFAULT_WINDOW,
    polyorder: int = DEFAULT_POLYORDER,
    stage: int | None = None,
    recursive: bool = False,
    targets: Sequence[int] | None = None,
) -> SwarmDataset:
    """Every vehicle's labelled samples from flight logs (a folder of `.npz` logs, a file, or a list).

    As `downwash.datasets.load_dataset`: flight id i is the i-th file (sorted), the stage is
    ``stage`` or each log's ``meta['stage']``; a foreign or truncated file raises
    `sim.logs.LogError` naming it; logs too short to label are skipped with a warning;
    logs flown with other settings (`log_provenance`) raise DataError.
    """
    if not isinstance(neighbours, NeighbourSet):
        raise ConfigError(f"neighbours: expected a NeighbourSet, got {type(neighbours).__name__}")
    files = find_logs(location, recursive=recursive)
    parts = []
    for path in files:
        log = load_log(path)
        labels = swarm_labels_from_log(log, neighbours, window, polyorder, source=path, targets=targets)
        if len(labels["y"]) == 0:
            logger.warning("%s: no labelled samples (only %d rows, status %s), skipped", path, len(log),
                           log.meta.get("status"))
        st = int(log.meta.get("stage", 0)) if stage is None else int(stage)
        parts.append(SwarmDataset.from_labels(labels, neighbours, flight=0, stage=st, source=str(path),
                                              provenance=log_provenance(log.meta)))
    ds = concatenate_swarm(parts)
    if len(ds) == 0:
        raise ValueError(f"{location}: none of the {len(files)} logs has labelled samples")
    return ds
