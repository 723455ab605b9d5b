"""A data set of real flights: chosen by globs, read, checked, labelled, and each sample typed by who flies above.

`find_flights` lists the flights of the task folders that globs (relative to the data set's
root) match; `read_flights` reads them (`downwash.real_logs.neural_swarm.read_flight`),
keeping the rejected ones apart with the reason: a file that is not exactly its format, or a
coordinated flight (a swap) whose vehicles' setpoints are offset by more than
`MAX_SETPOINT_OFFSET_S` after aligning them at their first ticks. `labelled_samples` labels
every vehicle of every flight (each with its nearest other vehicle, the paper's pair), drops
what no wake model explains (resting on or touching the ground, vehicles within
`CONTACT_DISTANCE` of each other, everything from a crash on, and `CONTACT_MARGIN_S` around
each) and keeps every `stride`-th sample.

Interaction types (`interaction_types`), in the data set's own naming: ``S2L`` is a small
vehicle above a large one, ``SL2S`` a small and a large above a small one (small first) (the vehicles above
within `WAKE_RADIUS` laterally and `WAKE_DEPTH` below them), ``Ge2S`` a small one with none
above and within `GROUND_HEIGHT` of the ground, ``none2S`` one in free air.
"""

from __future__ import annotations

import glob
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.geometry import quat_to_mat
from downwash.datasets import Dataset, concatenate
from downwash.labels import PAIR, labels_from_log
from downwash.real_logs.neural_swarm import flight_files, read_flight, setpoint_offset
from sim.logs import FlightLog
from sim.neighbours import NeighbourSet

__all__ = ["FlightRef", "find_flights", "read_flights", "interaction_types", "labelled_samples",
           "MAX_SETPOINT_OFFSET_S", "COORDINATED_TASKS", "WAKE_RADIUS", "WAKE_DEPTH", "GROUND_HEIGHT",
           "CONTACT_DISTANCE", "CONTACT_MARGIN_S", "REST_HEIGHT", "ROOM_SIZE"]

log = logging.getLogger(__name__)

COORDINATED_TASKS = ("swap",)  # task folders whose vehicles move together (random walks do not)
MAX_SETPOINT_OFFSET_S = 0.05  # s: the data set's swaps align within 0.03 s at their first ticks
WAKE_RADIUS = 0.35  # m, lateral: a vehicle above within it counts as flying over (about 4 rotor diameters)
WAKE_DEPTH = (0.05, 1.5)  # m, how far above the target a vehicle over it may be
GROUND_HEIGHT = 0.3  # m: below it, with none above, a vehicle is in ground effect
REST_HEIGHT = 0.1  # m: below it a vehicle rests on or touches the ground (the data set: 0.05-0.06 m at rest)
CONTACT_DISTANCE = 0.1  # m between two vehicles' centres: they touch
CONTACT_MARGIN_S = 0.3  # s around a contact or crash also dropped: the label filter's window (0.19 s) and the impact
ROOM_SIZE = 5.0  # m, any coordinate: an estimate beyond it has diverged (the log's int16 mm end at 32.7 m)
_MAX_TILT_COS = np.cos(np.radians(45.0))
_TYPE_ORDER = lambda letter: ("SL".find(letter) % 3, letter)  # noqa: E731  S before L (the data set's SL2S), others after


@dataclass(frozen=True)
class FlightRef:
    """One flight: its task folder, number (``NN``) and the files of its vehicles."""

    folder: Path
    number: str
    files: tuple[Path, ...]

    @property
    def name(self) -> str:
        return f"{self.folder.parent.name}/{self.folder.name}/{self.number}"


def find_flights(root: str | os.PathLike, patterns: Sequence[str]) -> list[FlightRef]:
    """The flights of the task folders under `root` that any glob of `patterns` matches (e.g.
    ``datacollection21*/*``), in name order; ConfigError naming a pattern that matches no task folder."""
    root = Path(root)
    if not root.is_dir():
        raise ConfigError(f"--data: {root} is not a folder")
    flights = []
    for pattern in patterns:
        folders = sorted(Path(p) for p in glob.glob(str(root / pattern)) if Path(p).is_dir())
        found = [FlightRef(f, n, tuple(files)) for f in folders for n, files in flight_files(f).items()]
        if not found:
            raise ConfigError(f"{pattern!r}: matches no folder of flights (cf<ID>_<NN> files) under {root}")
        flights += found
    unique = {f.name: f for f in flights}
    return [unique[k] for k in sorted(unique)]


def read_flights(refs: Sequence[FlightRef], motor_time_constant: float | None = None,
                 listed: Mapping[str, Mapping[str, set[str]]] | None = None
                 ) -> tuple[list[tuple[FlightRef, FlightLog]], list[dict]]:
    """(the flights read, the rejected ones as {flight, reason}): a file not exactly its format, a
    coordinated flight whose setpoints stay offset by more than MAX_SETPOINT_OFFSET_S, or a flight its
    day's summary leaves out (`listed`: day, e.g. ``datacollection21``, -> task -> the flight numbers
    kept, `downwash.real_logs.neural_swarm.summary_flights`; a task a summary does not name is kept)."""
    read, rejected = [], []
    for ref in refs:
        kept = (listed or {}).get(ref.folder.parent.name.split("_")[0], {}).get(ref.folder.name)
        if kept is not None and ref.number not in kept:
            rejected.append({"flight": ref.name, "reason": f"left out by the data set's summary of the day (it keeps "
                             f"{', '.join(sorted(kept))} of {ref.folder.name})"})
            continue
        try:
            flight = read_flight(ref.files, motor_time_constant=motor_time_constant)
        except (DataError, ConfigError) as e:
            rejected.append({"flight": ref.name, "reason": str(e)})
            continue
        if any(task in ref.folder.name for task in COORDINATED_TASKS):
            offsets = [setpoint_offset(flight, 0, b) for b in range(1, flight.n_vehicles)]
            flight.meta["setpoint_offsets_s"] = offsets
            worst = max((abs(o) for o in offsets), default=0.0)
            if worst > MAX_SETPOINT_OFFSET_S:
                rejected.append({"flight": ref.name, "reason": f"setpoints offset by {worst:.2f} s after aligning "
                                 f"the first ticks (at most {MAX_SETPOINT_OFFSET_S} s)"})
                continue
        read.append((ref, flight))
    return read, rejected


def interaction_types(flight: FlightLog, rows: np.ndarray, vehicles: np.ndarray) -> np.ndarray:
    """(N,) str: each sample's type (module doc), for samples at log rows (N,) of target vehicles (N,)."""
    pos = flight["pos_est"]
    letters = [frame[0].upper() for frame in flight.meta["frames"]]
    out = np.empty(len(rows), dtype=object)
    rel = pos[rows][:, :, :] - pos[rows, vehicles][:, None, :]  # (N, V, 3): every vehicle from the target
    above = ((np.linalg.norm(rel[..., :2], axis=-1) < WAKE_RADIUS) & (rel[..., 2] > WAKE_DEPTH[0])
             & (rel[..., 2] < WAKE_DEPTH[1]))
    above[np.arange(len(rows)), vehicles] = False
    for i, (r, v) in enumerate(zip(rows, vehicles)):
        over = "".join(sorted((letters[j] for j in np.flatnonzero(above[i])), key=_TYPE_ORDER))
        if not over:
            over = "Ge" if pos[r, v, 2] < GROUND_HEIGHT else "none"
        out[i] = f"{over}2{letters[v]}"
    return out.astype(str)


def _unexplained(flight: FlightLog, margin_s: float = CONTACT_MARGIN_S) -> np.ndarray:
    """(T, V) bool: the rows of each vehicle that no wake model explains, and `margin_s` around them
    (the label filter's window reaches that far): resting on or touching the ground, touching another
    vehicle, and everything from a crash on (tilted past 45 degrees, or an estimate that left the room)."""
    pos = flight["pos_est"]
    T, V, _ = pos.shape
    z_up = quat_to_mat(flight["quat_est"].reshape(-1, 4)).reshape(T, V, 3, 3)[..., 2, 2]
    d = np.linalg.norm(pos[:, :, None, :] - pos[:, None, :, :], axis=-1)
    d[:, np.arange(V), np.arange(V)] = np.inf
    touching = (pos[..., 2] < REST_HEIGHT) | (d.min(axis=2) < CONTACT_DISTANCE)
    crashed = (z_up < _MAX_TILT_COS) | (np.abs(pos) > ROOM_SIZE).any(axis=-1)
    crashed = np.cumsum(crashed, axis=0) > 0  # a crash ends the vehicle's flight
    bad = touching | crashed
    reach = int(round(margin_s / float(flight["t"][1] - flight["t"][0])))
    kernel = np.ones(2 * reach + 1)
    return np.stack([np.convolve(bad[:, v], kernel, mode="same") > 0 for v in range(V)], axis=1)


def labelled_samples(flights: Sequence[tuple[FlightRef, FlightLog]], stride: int = 2,
                     neighbours: NeighbourSet = PAIR) -> tuple[Dataset, np.ndarray]:
    """(the samples of every vehicle of every flight, their interaction types): each vehicle with
    its `neighbours` (default its nearest other vehicle, the paper's pair; flying alone, none: its
    inputs padded), the samples no wake model explains dropped, every `stride`-th kept (labels at
    100 Hz are strongly correlated). The samples and their order do not depend on `neighbours`."""
    if not isinstance(stride, int) or isinstance(stride, bool) or not 1 <= stride <= 100:
        raise ConfigError(f"stride: expected an integer in 1-100, got {stride!r}")
    parts, types = [], []
    for k, (ref, flight) in enumerate(flights):
        labels = labels_from_log(flight, neighbours, targets="all", source=ref.name)
        keep = ~_unexplained(flight)[labels["row"], labels["vehicle"]] & (labels["row"] % stride == 0)
        labels = {name: value[keep] for name, value in labels.items()}
        if len(labels["y"]) == 0:
            continue
        parts.append(Dataset.from_labels(labels, neighbours, flight=k, stage=0, source=ref.name))
        types.append(interaction_types(flight, labels["row"], labels["vehicle"]))
    if not parts:
        raise DataError("no labelled samples in the flights read")
    return concatenate(parts), np.concatenate(types)
