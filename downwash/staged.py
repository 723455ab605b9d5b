"""The paper's staged data collection (section 5.A) as a library: provenance-checked and resumable.

Stage 0 flies far below the leader (1.35-1.75 m) with no model; stage 1 flies
closer with the stage-0 equivariant model compensating; stage 2 flies at about
0.5 m with the stage-1 model. Each stage is ~5.7 minutes of varied flights
(`downwash_trajectories.collection_reference`: randomised passes through and beside the
wake, hovers at offsets, lemniscates), plus validation flights of the same kind from
separate seeds. Labels are always the full downwash (f = a - u with u the command
actually applied). After the last stage the final model of every kind in
`MODEL_KINDS` is trained on all training data into the models folder, one forked
process per core at once (each model bit-identical to one trained alone).

Provenance. A collection is defined by its `provenance` record: the field, the
scene, the simulator and its components, the collection settings, the training
settings and the seed base (the code version is recorded beside it). The manifest and
every checkpoint carry it, and nothing is reused unless it matches what was asked
for: `pipeline_dirs` gives the default folders, keyed by its fingerprint, so another
field or config collects afresh into its own folder; an explicit folder that holds
something else stops with an error that lists the differences.

Resuming. Flights fly in batches of `batch_flights` and each log is written as soon
as its batch lands; every flight draws its reference and noise from its own seeds,
so a rerun flies only the missing flights and gets the same results as an
uninterrupted run. A kill loses at most the batch in flight.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError, DataError
from downwash_core.io import atomic_write_json
from downwash_core.params import LEADER_POSITION
from downwash_core.provenance import code_version, describe, differences, fingerprint
from downwash.checkpoint import load_checkpoint, read_metadata, save_checkpoint
from downwash.datasets import Dataset, concatenate, find_logs, load_dataset
from downwash.labels import label_noise_floor
from downwash.models import MODEL_KINDS
from downwash.predictor import LearnedPredictor
from downwash.train import TrainConfig, rmse, train_model
from sim.flight import fly
from sim.logs import SCHEMA_VERSION, load_log, save_log
from sim.physics import resolve_threads, usable_cores
from sim.predictor import ZeroPredictor
from sim.scene import build_scene
from sim.simulator import SimConfig
from sim.turbulence import OUTurbulence
from downwash_trajectories import LEMNISCATE_SHARE, collection_reference

__all__ = [
    "STAGES", "DEPLOYED_KIND", "CollectionConfig", "train_config", "provenance", "pipeline_dirs", "collect",
    "ensure_models", "ensure_collection", "check_checkpoint",
]  # fmt: skip

log = logging.getLogger(__name__)

LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here
STAGES = (
    {"separation": (1.35, 1.75)},  # stage 0: far enough for the nominal controller
    {"separation": (0.85, 1.35)},  # stage 1: closer, stage-0 model compensating
    {"separation": (0.45, 0.65)},  # stage 2: ~0.5 m (two body lengths), stage-1 model
)
DEPLOYED_KIND = "equivariant"  # the model each stage trains and the next stage flies with
MANIFEST_VERSION = 2  # 2: provenance record and flight-grain resume
_QUICK_TRAINING = {"max_epochs": 3, "min_steps": 30}  # --quick: a few steps, enough to exercise the code
ProgressFactory = Callable[[str], Callable[[int, int], None] | None]


@dataclass(frozen=True)
class CollectionConfig:
    """Size and settings of a staged collection (each validated on construction)."""

    stage_minutes: float = 5.7  # training flight minutes per stage (paper: ~5.7, ~17 in all)
    val_ratio: float = 1.0  # validation minutes per training minute (paper: similar size)
    flight_seconds: float = 28.5  # length of one flight, s (12 flights of 28.5 s: 5.7 min per stage)
    clamp: float = 6.0  # magnitude bound of the deployed model's prediction, m/s^2
    seed: int = 0  # base seed of flights, patterns and training
    quick: bool = False  # a tiny budget (0.1 min per stage of 4 s flights, a few training steps)
    threads: int = 0  # worker threads for batched flights (0: all cores); training uses one
    batch_flights: int = 12  # flights flown as one batch; a kill loses at most one batch

    def __post_init__(self) -> None:
        if not 0 < self.stage_minutes <= 60:
            raise ConfigError(f"--stage-minutes: allowed (0, 60], got {self.stage_minutes}")
        if not 0 <= self.val_ratio <= 5:
            raise ConfigError(f"--val-ratio: allowed [0, 5], got {self.val_ratio}")
        if not 2.0 <= self.flight_seconds <= 600:
            raise ConfigError(f"--flight-seconds: allowed 2-600 s, got {self.flight_seconds}")
        if not self.clamp > 0:
            raise ConfigError(f"--clamp: must be > 0 m/s^2, got {self.clamp}")
        if isinstance(self.batch_flights, bool) or not isinstance(self.batch_flights, int) or not 1 <= self.batch_flights <= 256:
            raise ConfigError(f"--batch-flights: allowed integers 1-256, got {self.batch_flights!r}")
        try:
            resolve_threads(self.threads)
        except ConfigError:
            raise ConfigError(f"--threads: allowed 0 (every usable core) or 1-{usable_cores()} (the cores this "
                              f"process may use), got {self.threads!r}") from None

    @property
    def effective_stage_minutes(self) -> float:
        return 0.1 if self.quick else self.stage_minutes

    @property
    def effective_flight_seconds(self) -> float:
        return 4.0 if self.quick else self.flight_seconds

    @property
    def n_train(self) -> int:
        """Training flights per stage."""
        return max(2, math.ceil(self.effective_stage_minutes * 60 / self.effective_flight_seconds))

    @property
    def n_val(self) -> int:
        """Validation flights per stage."""
        return max(1, math.ceil(self.val_ratio * self.n_train)) if self.val_ratio > 0 else 0


def train_config(seed: int, quick: bool) -> TrainConfig:
    """The training settings every experiment uses: the defaults, or a few steps with --quick."""
    return TrainConfig(seed=seed, **(_QUICK_TRAINING if quick else {}))


def provenance(cfg: CollectionConfig, field: Any) -> dict[str, Any]:
    """What defines a collection and the models trained on it (see the module docstring)."""
    return {
        "field": describe(field),
        "scene": build_scene().describe(),
        "sim": describe(SimConfig()),
        "controller": describe(FeedbackLinearisedLQR()),
        "turbulence": describe(OUTurbulence()),
        "collection": {
            "stages": describe(STAGES), "stage_minutes": cfg.effective_stage_minutes,
            "flight_seconds": cfg.effective_flight_seconds, "n_train": cfg.n_train, "n_val": cfg.n_val,
            "clamp": cfg.clamp, "deployed_kind": DEPLOYED_KIND, "lemniscate_share": LEMNISCATE_SHARE,
            "log_schema": SCHEMA_VERSION, "training": train_config(cfg.seed, cfg.quick).to_dict(),
        },
        "seed": cfg.seed,
        "code": code_version(),
    }


def pipeline_dirs(record: dict[str, Any], root: str | Path = "runs/pipeline") -> tuple[Path, Path]:
    """The default (collection, models) folders of a provenance record: root/<field>-<fingerprint>/..."""
    field = record["field"]
    name = field.get("type", "field").rsplit(".", 1)[-1] if isinstance(field, dict) else "field"
    base = Path(root) / f"{name}-{fingerprint(record)}"
    return base / "collection", base / "models"


class _Labelled:
    """Labelled samples per folder, loaded once per run (a finished stage's logs never change)."""

    def __init__(self) -> None:
        self._cache: dict[Path, Dataset] = {}

    def __call__(self, dirs: list[Path]) -> Dataset:
        for d in dirs:
            if d not in self._cache:
                self._cache[d] = load_dataset(d)
        return concatenate([self._cache[d] for d in dirs])


def _train_and_save(kind: str, data: Dataset, train_dirs: list[Path], path: Path, cfg: CollectionConfig,
                    record: dict, extra: dict) -> dict:
    model, history = train_model(kind, data, None, train_config(cfg.seed, cfg.quick))
    save_checkpoint(path, model, {"training": {k: v for k, v in history.items() if k not in ("train_loss", "val_loss")},
                                  "data": data.summary(), "train_dirs": [str(d) for d in train_dirs],
                                  "provenance": record, "provenance_key": fingerprint(record), **extra})
    return history


def _in_parallel(fn: Callable[[str], dict], items: Sequence[str]) -> Iterator[tuple[str, dict]]:
    """(item, fn(item)) for every item, as each finishes, up to one forked process per core at once.

    For independent trainings: each trains on one thread (`TrainConfig.num_threads`) from its
    own seed, so a model is bit-identical to one trained in this process (a test checks), and
    two cores train two at once. fn must write its own outputs (atomically); its result (small,
    picklable) comes back through a pipe. Not on Linux (fork is unsafe on macOS, absent on Windows),
    with one core, or inside a daemonic process: one after another, in this process.
    """
    workers = min(len(items), os.cpu_count() or 1)
    # fork is the only start method without re-imports; a daemonic process may not have children
    if workers < 2 or not sys.platform.startswith("linux") or multiprocessing.current_process().daemon:
        for item in items:
            yield item, fn(item)
        return
    ctx = multiprocessing.get_context("fork")
    todo, running = list(items), {}
    try:
        while todo or running:
            while todo and len(running) < workers:
                item = todo.pop(0)
                receive, send = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_run_child, args=(fn, item, send), daemon=True)
                proc.start()
                send.close()
                running[receive] = (item, proc)
            for receive in multiprocessing.connection.wait(list(running)):
                item, proc = running.pop(receive)
                try:
                    ok, value = receive.recv()
                except EOFError:
                    ok, value = False, "the process ended without a result"
                proc.join()
                if not ok and proc.exitcode:
                    value = f"{value} (exit code {proc.exitcode})"
                if not ok:
                    raise RuntimeError(f"{item}: {value}")
                yield item, value
    finally:
        for _, proc in running.values():
            proc.kill()


def _run_child(fn: Callable[[str], dict], item: str, send: Any) -> None:
    try:
        send.send((True, fn(item)))
    except BaseException:  # the parent raises it, with the child's traceback
        send.send((False, traceback.format_exc()))


def _val_rmse(checkpoint: Path, kind: str, val_data: Dataset) -> float:
    model, _ = load_checkpoint(checkpoint, expect_kind=kind)
    return rmse(model, val_data)[0]


def _fly_stage(k: int, sdir: Path, cfg: CollectionConfig, field: Any, deployed: Path | None,
               progress: ProgressFactory) -> None:
    """Fly the stage's missing flights in batches, writing each log as soon as its batch lands."""
    n_train, n_val, seconds = cfg.n_train, cfg.n_val, cfg.effective_flight_seconds
    paths = [sdir / ("train" if i < n_train else "val") / f"flight_{i:03d}.npz" for i in range(n_train + n_val)]
    todo = [i for i, p in enumerate(paths) if not p.is_file()]
    if not todo:
        return
    predictor = (ZeroPredictor() if deployed is None
                 else LearnedPredictor.from_checkpoint(deployed, clamp=cfg.clamp, expect_kind=DEPLOYED_KIND))
    scene = build_scene()
    for start in range(0, len(todo), cfg.batch_flights):
        batch = todo[start:start + cfg.batch_flights]
        reference = collection_reference((cfg.seed, k), batch, n_train, n_val, LEADER, STAGES[k]["separation"], seconds)
        seeds = [cfg.seed * 100_000 + 1000 * k + i for i in batch]  # train: i < n_train, val: the rest
        meta = [{"stage": k, "index": i, "role": "train" if i < n_train else "val", "deployed_model": str(deployed)}
                for i in batch]
        label = f"stage {k}: flights {batch[0]}-{batch[-1]} of {len(paths)}"
        flights = fly(scene, reference, seeds, seconds, field=field, predictor=predictor, meta=meta,
                      n_threads=cfg.threads, progress=progress(label))
        for i, L in zip(batch, flights):
            save_log(paths[i], L)


def collect(
    cfg: CollectionConfig,
    collection_dir: str | Path,
    models_dir: str | Path,
    field: Any,
    progress: ProgressFactory = lambda label: None,
) -> dict:
    """Collect all stages into `collection_dir` (resuming), train the final models into `models_dir`.

    progress(label) may return a callback progress(done, total) for each batch of flights.
    Raises DataError before any flight when `collection_dir` holds a collection of
    another provenance. Returns the results: per stage (separation, minutes, samples,
    deployed model and its validation RMSE on that stage, failed flights), per final
    model (path, validation RMSE, training seconds), the label-noise floor, the
    provenance, this run's wall time and `collection_seconds`, the time the whole
    collection took (summed over the runs that worked on it; a killed run cannot record its part).
    """
    t_start = time.perf_counter()
    out, models_dir = Path(collection_dir), Path(models_dir)
    record = provenance(cfg, field)
    manifest_path = out / "manifest.json"
    manifest = _load_manifest(manifest_path, record)
    for kind in MODEL_KINDS:  # never overwrite models of another provenance
        if (models_dir / f"{kind}.pt").is_file():
            check_checkpoint(models_dir / f"{kind}.pt", kind, record)
    out.mkdir(parents=True, exist_ok=True)
    models_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(manifest_path, manifest)
    n_train, n_val, flight_seconds = cfg.n_train, cfg.n_val, cfg.effective_flight_seconds

    labelled = _Labelled()
    stage_results = []
    for k, stage in enumerate(STAGES):
        sdir = out / f"stage{k}"
        entry = manifest["stages"].setdefault(str(k), {})
        deployed = None if k == 0 else out / f"stage{k - 1}" / f"{DEPLOYED_KIND}.pt"
        if not entry.get("flights_done"):
            _fly_stage(k, sdir, cfg, field, deployed, progress)
            entry["flights_done"] = True
            entry["failed"] = [m for p in sorted(sdir.glob("*/flight_*.npz")) if (m := load_log(p).meta["message"])]
            atomic_write_json(manifest_path, manifest)
        train_dirs = [out / f"stage{j}" / "train" for j in range(k + 1)]
        # the stage-k model, deployed in stage k + 1 (the last stage's would be the final model of its kind)
        if k + 1 < len(STAGES) and not entry.get("model_done"):
            _train_and_save(DEPLOYED_KIND, labelled(train_dirs), train_dirs, sdir / f"{DEPLOYED_KIND}.pt", cfg,
                            record, {"stage": k})
            entry["model_done"] = True
            atomic_write_json(manifest_path, manifest)
        if "deployed_val_rmse" not in entry:
            entry["deployed_val_rmse"] = (None if deployed is None or n_val == 0
                                          else _val_rmse(deployed, DEPLOYED_KIND, labelled([sdir / "val"])))
            atomic_write_json(manifest_path, manifest)
        samples = len(labelled([sdir / "train"]))
        stage_results.append({"stage": k, "separation": list(stage["separation"]),
                              "minutes": n_train * flight_seconds / 60, "samples": samples,
                              "deployed_model": None if deployed is None else str(deployed),
                              "deployed_val_rmse": entry["deployed_val_rmse"], "failed_flights": entry.get("failed", [])})

    train_dirs = [out / f"stage{k}" / "train" for k in range(len(STAGES))]
    val_dirs = [out / f"stage{k}" / "val" for k in range(len(STAGES))] if n_val else []
    finals = manifest.setdefault("final_models", {})
    models: dict[str, Any] = {}
    missing = [kind for kind in MODEL_KINDS if not finals.get(kind) or not (models_dir / f"{kind}.pt").is_file()]
    if missing:
        data = labelled(train_dirs)

        def train_one(kind: str) -> dict:
            path, t0 = models_dir / f"{kind}.pt", time.perf_counter()
            history = _train_and_save(kind, data, train_dirs, path, cfg, record, {"stage": "final"})
            return {"path": str(path), "train_seconds": time.perf_counter() - t0, "epochs": history["epochs"]}

        for kind, entry in _in_parallel(train_one, missing):
            finals[kind] = entry
            atomic_write_json(manifest_path, manifest)
    for kind in MODEL_KINDS:
        path = models_dir / f"{kind}.pt"
        models[kind] = {"path": str(path), "val_rmse": _val_rmse(path, kind, labelled(val_dirs)) if val_dirs else None,
                        "train_seconds": finals[kind]["train_seconds"]}
    floor = label_noise_floor([p for d in val_dirs for p in find_logs(d)]) if val_dirs else None
    if not manifest.get("complete"):  # the time this collection took, over every run that worked on it
        manifest["collection_seconds"] = manifest.get("collection_seconds", 0.0) + time.perf_counter() - t_start
    manifest["complete"] = True
    atomic_write_json(manifest_path, manifest)
    return {"stages": stage_results, "training_minutes": len(STAGES) * n_train * flight_seconds / 60,
            "validation_minutes": len(STAGES) * n_val * flight_seconds / 60, "models": models,
            "noise_floor": floor, "collection_dir": str(out), "models_dir": str(models_dir),
            "provenance": record, "provenance_key": fingerprint(record), "wall_seconds": time.perf_counter() - t_start,
            "collection_seconds": manifest["collection_seconds"]}


def check_checkpoint(path: str | Path, kind: str, record: dict[str, Any]) -> None:
    """DataError unless the checkpoint at `path` is a `kind` model trained on data of provenance `record`."""
    meta = read_metadata(path)
    found = meta.get("model", {}).get("kind")
    if found != kind:
        raise DataError(f"{path}: holds a {found!r} model, not the {kind!r} model expected under that name; "
                        "delete it or point --models-dir elsewhere")
    have = meta.get("provenance")
    if have is None or fingerprint(have) != fingerprint(record):
        diffs = differences(have, record) if have is not None else ["no provenance record (made by older code)"]
        raise DataError(
            f"{path}: this {kind} model was trained on data other than what was asked for:\n  "
            + "\n  ".join(diffs)
            + f"\nLeave out --models-dir (and --collection-dir) to use the folders keyed by this setup, "
            f"{pipeline_dirs(record)[1].parent}/, or delete {Path(path).parent} to train afresh there."
        )
    _warn_code(have, path)


def ensure_models(
    models_dir: str | Path,
    kinds: Sequence[str],
    collection_dir: str | Path,
    cfg: CollectionConfig,
    field: Any,
    progress: ProgressFactory = lambda label: None,
) -> dict[str, Path]:
    """Checkpoint paths of `kinds` in `models_dir`, collecting and training first when any is missing.

    Every checkpoint already there must be of its kind and of this collection's
    provenance (else DataError, before any flight, naming the differences).
    """
    models_dir = Path(models_dir)
    record = provenance(cfg, field)
    missing = []
    for kind in kinds:
        path = models_dir / f"{kind}.pt"
        if path.is_file():
            check_checkpoint(path, kind, record)
        else:
            missing.append(kind)
    if missing:
        log.info("models %s missing in %s: running the staged collection into %s first", missing, models_dir,
                 collection_dir)
        collect(cfg, collection_dir, models_dir, field, progress)
    return {k: models_dir / f"{k}.pt" for k in kinds}


def ensure_collection(
    collection_dir: str | Path,
    models_dir: str | Path,
    cfg: CollectionConfig,
    field: Any,
    progress: ProgressFactory = lambda label: None,
) -> Path:
    """The staged collection folder, collected first (with its models) unless complete;
    DataError when it holds a collection of another provenance."""
    collection_dir = Path(collection_dir)
    manifest = collection_dir / "manifest.json"
    if manifest.is_file():
        _load_manifest(manifest, provenance(cfg, field))  # raises on a mismatch
    if not (manifest.is_file() and json.loads(manifest.read_text()).get("complete")):
        collect(cfg, collection_dir, models_dir, field, progress)
    return collection_dir


def _load_manifest(path: Path, record: dict) -> dict:
    if not path.is_file():
        return {"version": MANIFEST_VERSION, "provenance": record, "key": fingerprint(record), "stages": {}}
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: unreadable collection manifest ({e}); delete the folder to start afresh") from e
    if manifest.get("version") != MANIFEST_VERSION or "provenance" not in manifest:
        raise DataError(f"{path}: a collection of an older format (manifest version {manifest.get('version')!r}); "
                        "delete the folder or use another --collection-dir")
    have = manifest["provenance"]
    if fingerprint(have) != fingerprint(record):
        raise DataError(
            f"{path.parent}: this folder holds a staged collection made with other settings:\n  "
            + "\n  ".join(differences(have, record))
            + f"\nLeave out --collection-dir (and --models-dir) to use the folders keyed by this setup, "
            f"{pipeline_dirs(record)[0].parent}/, use another folder, or delete this one to start afresh."
        )
    _warn_code(have, path)
    if manifest.get("complete"):
        log.info("%s: collection complete; re-checking models only", path)
    return manifest


def _warn_code(have: dict, where: Path | str) -> None:
    now = code_version()
    if have.get("code") != now:
        log.warning("%s was made by code %s; reusing it with code %s (the provenance key matches)",
                    where, have.get("code"), now)
