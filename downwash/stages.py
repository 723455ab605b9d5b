"""A collection stage and the one driver that flies it: the pair's stages and the swarm's alike.

A `Stage` is a hovering leader over followers, each follower flying the collection
patterns (`downwash_trajectories.collection_reference`: passes through and beside the
wakes, lemniscates) in its own band of depths below the leader, so that no two vehicles
share a height. The pair's stages (`downwash.staged`) have one follower; the swarm's
(`downwash.swarm_collection`) two or three. A stage has ``n_train`` training flights, then
``n_val`` validation flights; flight i flies the noise seed ``flight_seed + i`` and each
follower's patterns from ``default_rng([*pattern_seed, i])``, so a flight never depends on
which others share its batch and a collection resumes flight by flight (`fly_stage` flies
only the missing logs). An outdoor stage (`leader_speeds`, `wind`) moves the leader instead:
flight i flies a straight line (even i) or a horizontal circle (odd i) at a speed drawn from
``default_rng([*pattern_seeds[0], 1_000_000 + i])`` in `leader_speeds`, through the stage's
wind, and each follower flies its patterns relative to the moving leader (`Relative`).
What a stage flies with, the deployed model and its clamp, is the predictor handed to
`fly_stage`.

As the stage's flights are done, `record_stage` writes every log's digests, rows, labelled
samples and status into the stage's manifest entry (`downwash.manifest`), against which
the logs are checked before anything is trained on them; a finished stage's missing logs
are re-flown and kept only if they hold the recorded data (`accept_reflown`).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.io import remove_temporaries
from downwash_core.locks import folder_lock
from downwash_core.provenance import differences, fingerprint
from downwash_core.roles import SCENE_VEHICLE_NAMES, Role
from downwash.datasets import concatenate, load_dataset
from downwash.manifest import (check_logs, integrity_error, listed_logs, load_manifest_file, log_record, read_manifest,
                               write_manifest)
from sim.flight import fly
from sim.logs import load_log, save_log
from sim.neighbours import NeighbourSet
from sim.scene import build_scene
from downwash_trajectories import (Circle, Hover, Line, Mixed, Relative, StackedReference, collection_reference,
                                   stack)

__all__ = ["Stage", "StageBudget", "locked_folder", "open_manifest", "fly_stage", "record_stage", "accept_reflown", "fly_recorded",
           "CheckedLoader", "ProgressFactory"]

log = logging.getLogger(__name__)

ProgressFactory = Callable[[str], Callable[[int, int], None] | None]


@dataclass(frozen=True)
class Stage:
    """One collection stage (see the module doc).

    name: its folder within the collection; leader: m, where the leader hovers;
    bands: (min, max) m below the leader, one per follower (top first);
    pattern_seeds: the seed of each follower's patterns; flight_seed: flight i's noise seed
    is flight_seed + i; meta: recorded in every log's metadata (with "index" and "role");
    kinds: each vehicle's kind, leader first (`downwash_core.vehicles`; empty: paper quads);
    leader_speeds: (min, max) m/s of a moving leader (None: it hovers); wind: a
    `sim.wind.DrydenWind` every flight of the stage flies through (None: still air).
    """

    name: str
    leader: tuple[float, float, float]
    bands: tuple[tuple[float, float], ...]
    pattern_seeds: tuple[tuple[int, ...], ...]
    flight_seed: int
    meta: dict[str, Any] = field(default_factory=dict)
    kinds: tuple[str, ...] = ()
    leader_speeds: tuple[float, float] | None = None
    wind: Any = None

    def __post_init__(self) -> None:
        if not self.bands or len(self.bands) != len(self.pattern_seeds):
            raise ValueError(f"Stage {self.name}: one depth band and one pattern seed per follower, got "
                             f"{len(self.bands)} and {len(self.pattern_seeds)}")
        if self.kinds and len(self.kinds) != self.n_vehicles:
            raise ValueError(f"Stage {self.name}: {len(self.kinds)} vehicle kinds for {self.n_vehicles} vehicles")

    @property
    def n_vehicles(self) -> int:
        return 1 + len(self.bands)

    def paths(self, sdir: Path, n_train: int, n_val: int) -> list[Path]:
        """The stage's logs in flight order: train/flight_000.npz, ..., then val/."""
        return [sdir / ("train" if i < n_train else "val") / f"flight_{i:03d}.npz" for i in range(n_train + n_val)]

    def reference(self, flights: list[int], n_train: int, n_val: int, seconds: float) -> StackedReference:
        """The leader's hover (or path) and each follower's patterns in its band, for these flights (the
        worlds of a batch)."""
        leader = np.asarray(self.leader, dtype=float)
        followers = [collection_reference(seed, flights, n_train, n_val, leader, band, seconds).refs[1]
                     for seed, band in zip(self.pattern_seeds, self.bands)]
        if self.leader_speeds is None:
            return stack([Hover(leader, n_worlds=len(flights)), *followers])
        path = Mixed([(self._leader_path(i, seconds), [w]) for w, i in enumerate(flights)])
        return stack([path, *(Relative(path, f, leader) for f in followers)])

    def _leader_path(self, i: int, seconds: float) -> Any:
        """Flight i's leader: a line (even i) centred on `leader`, or a circle through it (odd i)."""
        rng = np.random.default_rng([*self.pattern_seeds[0], 1_000_000 + i])
        speed, heading = rng.uniform(*self.leader_speeds), rng.uniform(0.0, 2.0 * np.pi)
        leader, direction = np.asarray(self.leader, dtype=float), np.array([np.cos(heading), np.sin(heading), 0.0])
        if i % 2 == 0:
            return Line(leader - 0.5 * speed * seconds * direction, speed * direction, duration=seconds, n_worlds=1)
        radius = rng.uniform(1.5, 4.0)
        return Circle(leader - radius * direction, radius=radius, speed=speed * rng.choice([-1.0, 1.0]),
                      phase=heading, n_worlds=1)

    def scene(self):
        """A leader over the followers, top first, each of its kind."""
        return build_scene([(SCENE_VEHICLE_NAMES[i], Role.LEADER if i == 0 else Role.FOLLOWER)
                            for i in range(self.n_vehicles)], kinds=list(self.kinds) or None)


@dataclass(frozen=True)
class StageBudget:
    """The size of the stages of a collection that follows the indoor one (the swarm's, the outdoor
    one): training minutes per stage, validation flights per training flight, flight length, seed,
    --quick, and how the flights are batched. Validated on construction; `minutes_option` names
    the command-line option of `stage_minutes` in the messages."""

    stage_minutes: float = 2.0  # training flight minutes per stage
    val_ratio: float = 0.5  # validation minutes per training minute
    flight_seconds: float = 20.0
    seed: int = 0
    quick: bool = False  # 0.1 min per stage of 4 s flights, a few training steps
    batch_flights: int = 16
    threads: int = 0
    minutes_option = "stage_minutes"

    def __post_init__(self) -> None:
        if not 0 < self.stage_minutes <= 60:
            raise ConfigError(f"{self.minutes_option}: allowed (0, 60], got {self.stage_minutes}")
        if not 0 < self.val_ratio <= 5:
            raise ConfigError(f"val_ratio: allowed (0, 5], got {self.val_ratio}")
        if not 2.0 <= self.flight_seconds <= 600:
            raise ConfigError(f"flight_seconds: allowed 2-600 s, got {self.flight_seconds}")

    @property
    def seconds(self) -> float:
        return 4.0 if self.quick else self.flight_seconds

    @property
    def n_train(self) -> int:
        return max(2, math.ceil((0.1 if self.quick else self.stage_minutes) * 60 / self.seconds))

    @property
    def n_val(self) -> int:
        return max(1, math.ceil(self.val_ratio * self.n_train))


@contextlib.contextmanager
def locked_folder(folder: Path, label: str) -> Iterator[None]:
    """The lock of a folder a collection writes in (`downwash_core.locks.folder_lock`: a second run waits,
    then resumes what the first made), with the temporary files that killed runs left there removed
    first: under the lock no live writer's file is taken."""
    with folder_lock(folder, label=label):
        stale = remove_temporaries(folder)
        if stale:
            log.info("%s: removed %d temporary files that an interrupted run left", folder, len(stale))
        yield


def open_manifest(out: Path, record: dict, what: str, **fields: Any) -> dict:
    """The manifest of the collection in `out` made with `record` (its provenance): the one there, or a
    new one ({provenance, key, stages, **fields}) written there; DataError with the differences when
    the folder holds `what` made with other settings."""
    manifest_path = out / "manifest.json"
    manifest = {"provenance": record, "key": fingerprint(record), "stages": {}, **fields}
    if manifest_path.is_file():
        have = load_manifest_file(manifest_path)
        if have.get("key") != manifest["key"]:
            raise DataError(f"{out}: this folder holds {what} made with other settings:\n  "
                            + "\n  ".join(differences(have.get("provenance"), record))
                            + "\nuse another folder or delete this one to start afresh")
        manifest = have
    out.mkdir(parents=True, exist_ok=True)
    write_manifest(manifest_path, manifest)
    return manifest


def fly_stage(stage: Stage, sdir: Path, n_train: int, n_val: int, seconds: float, *, field: Any, predictor: Any,
              aggregation: Any = None, batch_flights: int, threads: int,
              progress: ProgressFactory = lambda label: None) -> int:
    """Fly the stage's missing flights in batches of `batch_flights`, writing each log as soon as its batch
    lands (a kill loses at most the batch in flight); how many flew."""
    paths = stage.paths(sdir, n_train, n_val)
    todo = [i for i, p in enumerate(paths) if not p.is_file()]
    if not todo:
        return 0
    log.info("%s: %d of %d flights to fly into %s", stage.name, len(todo), len(paths), sdir)
    scene = stage.scene()
    for start in range(0, len(todo), batch_flights):
        batch = todo[start:start + batch_flights]
        meta = [{**stage.meta, "index": i, "role": "train" if i < n_train else "val"} for i in batch]
        logs = fly(scene, stage.reference(batch, n_train, n_val, seconds), [stage.flight_seed + i for i in batch],
                   seconds, field=field, aggregation=aggregation, predictor=predictor, meta=meta, n_threads=threads,
                   wind=stage.wind,
                   progress=progress(f"{stage.name}: flights {batch[0]}-{batch[-1]} of {len(paths)}"))
        for i, flown in zip(batch, logs):
            save_log(paths[i], flown)
    return len(todo)


def record_stage(sdir: Path, entry: dict, paths: list[Path]) -> None:
    """Record every log of a stage whose flights are all on disk in its manifest entry (digests, rows,
    samples, status; `downwash.manifest.log_record`)."""
    entry["files"] = {p.relative_to(sdir).as_posix(): log_record(p) for p in paths}
    entry["failed"] = [f["message"] for f in entry["files"].values() if f["message"]]
    entry["flights_done"] = True


def accept_reflown(sdir: Path, entry: dict, paths: list[Path], collection: str) -> None:
    """Record the re-flown logs `paths` of a finished stage if they hold the data recorded for them (what
    the collection's models were trained on); else remove them all and raise DataError (`collection`:
    the folders to delete to collect afresh)."""
    new = {path: log_record(path) for path in paths}
    rel = {path: path.relative_to(sdir).as_posix() for path in paths}
    differ = [path for path in paths if new[path]["data_sha256"] != entry["files"][rel[path]]["data_sha256"]]
    if differ:
        for path in paths:
            path.unlink()
        raise DataError(
            f"{', '.join(map(str, differ))}: re-flown, but the data differ from the logs recorded in "
            f"{sdir.parent / 'manifest.json'}, which the collection's models were trained on: this code or machine "
            "flies those flights differently (the manifest's provenance names the code that flew them). The "
            f"re-flown logs were removed. Delete {collection} to collect afresh, or restore the original logs."
        )
    for path in paths:
        if new[path]["sha256"] != entry["files"][rel[path]]["sha256"]:
            log.info("%s: re-flown with the same data (its metadata differ: another code version or folder)", path)
        entry["files"][rel[path]] = new[path]


def fly_recorded(stage: Stage, sdir: Path, entry: dict, n_train: int, n_val: int, seconds: float, *,
                 collection: str, save: Callable[[], None], **flight: Any) -> int:
    """A stage brought up to its manifest entry: the missing flights flown (`fly_stage`, with `flight`:
    field, predictor, aggregation, batch_flights, threads, progress), then every log recorded
    (`record_stage`) if the stage was not done, else the re-flown ones accepted against their
    records (`accept_reflown`; collection: what to delete to collect afresh); `save()` writes the
    manifest. How many flew (0: nothing was missing)."""
    paths = stage.paths(sdir, n_train, n_val)
    missing = [p for p in paths if not p.is_file()]
    if entry.get("flights_done") and not missing:
        return 0
    flown = fly_stage(stage, sdir, n_train, n_val, seconds, **flight)
    if entry.get("flights_done"):
        accept_reflown(sdir, entry, missing, collection)
    else:
        record_stage(sdir, entry, paths)
    save()
    return flown


class CheckedLoader:
    """Data sets per stage folder (<collection>/<stage>/<train|val>), each folder's logs checked against its
    collection's manifest before they are read (DataError naming the file and `rerun`), loaded once.

    neighbours, targets: as `downwash.datasets.load_dataset`; manifests: {collection folder: manifest}
    already read (others are read when first needed); mixed: provenance entries that may differ
    between the folders (`downwash.datasets.concatenate`). `skipped[folder]`: the flights left out
    by ``skip_failed`` (those that ended early).
    """

    def __init__(self, neighbours: NeighbourSet, manifests: dict[Path, dict], rerun: str, targets: Any = None,
                 mixed: tuple[str, ...] = ()):
        self.neighbours, self.manifests, self.rerun, self.targets, self.mixed = neighbours, manifests, rerun, targets, mixed
        self._cache: dict[tuple[Path, bool], Any] = {}
        self.skipped: dict[Path, int] = {}

    def __call__(self, dirs: list[Path], skip_failed: bool = False):
        for d in dirs:
            if (d, skip_failed) not in self._cache:
                root = d.parent.parent
                if root not in self.manifests:
                    self.manifests[root] = read_manifest(root / "manifest.json")
                problems = check_logs(root, self.manifests[root], [d])
                if problems:
                    raise integrity_error(root, problems, self.rerun)
                files = [p for p in listed_logs(root, self.manifests[root]) if p.parent == d]
                ok = [f for f in files if not skip_failed or load_log(f).meta.get("status", 0) == 0]
                self.skipped[d] = len(files) - len(ok)
                self._cache[d, skip_failed] = load_dataset(ok, self.neighbours, targets=self.targets)
        return concatenate([self._cache[d, skip_failed] for d in dirs], self.mixed)
