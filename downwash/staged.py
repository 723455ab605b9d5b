"""The paper's staged data collection (section 5.A) as a library: provenance-checked and resumable.

Stage 0 flies far below the leader (1.35-1.75 m) with no model; stage 1 flies
closer with the stage-0 equivariant model compensating; stage 2 flies at about
0.5 m with the stage-1 model. Each deployed model is clamped (``clamp``) and, with
``guard`` (``--guard-stages``), flies behind the guard (`downwash.guard`): a stage model
applies nothing where the closer stage leaves its training data's support until the forces
felt there show it right, so collecting closer is no riskier than flying without a model
(the paper's worry). Off by default:
the paper deploys its stage models clamped only, and the lemniscate experiment reproduces it.

Each stage is ~5.7 minutes of varied flights
(`downwash_trajectories.collection_reference`: randomised passes through and beside the
wake, hovers at offsets, lemniscates), plus validation flights of the same kind from
separate seeds. Labels are always the full downwash (f = a - u with u the command
actually applied). After the last stage the final model of every kind in
`STAGED_KINDS` is trained on all training data into the models folder, one forked
process per core at once (each model bit-identical to one trained alone); any other
per-neighbour kind asked for (`ensure_models`: the models with memory) is trained there
on the same data when first asked for.

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

Integrity. As each stage's flights are done, the manifest records every log of the
stage (`downwash.manifest`), and as each model is trained, its content digest; before
anything is trained or flown on a collection its logs and models are checked against that
record: a missing, altered or unlisted log, or an altered model, stops the run, naming
the file and what to do. `collect` itself re-flies the missing logs of a finished
stage (only those; the re-flown log must hold the same data as the one recorded, else it
stops). A stage where most flights diverge (a field with NaN or runaway forces where it
was never checked) stops with the counts before training.

Concurrency. `collect` (and `ensure_models` when a model is missing) holds the lock of
the collection folder and then of the models folder, `ensure_collection` the
collection folder's (`downwash_core.locks`, `flock`: a killed run lets go): a second run
on the same folders waits for the first and then reuses what it made.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import socket
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from controllers.autopilot import Autopilot
from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError, DataError
from downwash_core.locks import folder_lock
from downwash_core.params import LEADER_POSITION
from downwash_core.provenance import code_version, describe, differences, fingerprint
from downwash_core.status import Status
from downwash.checkpoint import checkpoint_digest, load_checkpoint, read_metadata, save_checkpoint
from downwash.datasets import Dataset, concatenate, load_dataset
from downwash.guard import GuardedPredictor, guard_settings
from downwash.labels import label_noise_floor
from downwash.manifest import (MANIFEST_VERSION, check_logs, check_models, integrity_error, listed_logs,
                               read_manifest, rerun_command, verify_collection, write_manifest)
from downwash.models import PAIRWISE_KINDS, STAGED_KINDS
from downwash.predictor import LearnedPredictor
from downwash.stages import ProgressFactory, Stage, fly_recorded, locked_folder
from downwash.train import TrainConfig, rmse, train_model
from sim.logs import SCHEMA_VERSION
from sim.physics import resolve_threads, usable_cores
from sim.predictor import ZeroPredictor
from sim.scene import build_scene
from sim.simulator import SimConfig
from sim.turbulence import OUTurbulence
from downwash_trajectories import LEMNISCATE_SHARE

__all__ = [
    "STAGES", "DEPLOYED_KIND", "CollectionConfig", "train_config", "provenance", "pipeline_dirs", "collect",
    "ensure_models", "ensure_collection", "check_checkpoint", "deployed_predictor",
]  # fmt: skip

log = logging.getLogger(__name__)

STAGES = (
    {"separation": (1.35, 1.75)},  # stage 0: far enough for the nominal controller
    {"separation": (0.85, 1.35)},  # stage 1: closer, stage-0 model compensating
    {"separation": (0.45, 0.65)},  # stage 2: ~0.5 m (two body lengths), stage-1 model
)
DEPLOYED_KIND = "equivariant"  # the model each stage trains and the next stage flies with
_QUICK_TRAINING = {"max_epochs": 3, "min_steps": 30}  # --quick: a few steps, enough to exercise the code


@dataclass(frozen=True)
class CollectionConfig:
    """Size and settings of a staged collection (each validated on construction)."""

    stage_minutes: float = 5.7  # training flight minutes per stage (paper: ~5.7, ~17 in all)
    val_ratio: float = 1.0  # validation minutes per training minute (paper: similar size)
    flight_seconds: float = 28.5  # length of one flight, s (12 flights of 28.5 s: 5.7 min per stage)
    clamp: float = 6.0  # magnitude bound of the deployed model's prediction, m/s^2
    guard: bool = False  # deploy each stage model behind the guard (downwash.guard)
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
        "autopilot": describe(Autopilot()),
        "turbulence": describe(OUTurbulence()),
        "collection": {
            "stages": describe(STAGES), "stage_minutes": cfg.effective_stage_minutes,
            "flight_seconds": cfg.effective_flight_seconds, "n_train": cfg.n_train, "n_val": cfg.n_val,
            "clamp": cfg.clamp, "deployed_kind": DEPLOYED_KIND, "lemniscate_share": LEMNISCATE_SHARE,
            "log_schema": SCHEMA_VERSION, "training": train_config(cfg.seed, cfg.quick).to_dict(),
            **({"guard": guard_settings()} if cfg.guard else {}),  # (absent when off: folders keep their key)
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


def _check_stage(k: int, sdir: Path, entry: dict, cfg: CollectionConfig, deployed: Path | None) -> None:
    """DataError, with the counts, when a stage's flights cannot train a model: most of them diverged
    (NaN or runaway states), or fewer than two training flights or no validation flight has
    labelled samples. (Flights that end in a collision keep their samples up to it: a stage
    flown with a poor deployed model, e.g. under --quick, may lose many and still train.)

    The usual cause is the field: `sim.field.check_field` tests it at a few points near a
    leader only, and a NaN or runaway force elsewhere ends the flights that meet it as diverged.
    """
    files = entry["files"]
    n = len(files)
    diverged = [(rel, f) for rel, f in sorted(files.items()) if f["status"] == Status.DIVERGED.label]
    samples = sum(f["samples"] for f in files.values())
    train_ok = sum(1 for rel, f in files.items() if rel.startswith("train/") and f["samples"] > 0)
    val_samples = sum(f["samples"] for rel, f in files.items() if rel.startswith("val/"))
    found = []
    if 2 * len(diverged) > n:
        rel, f = diverged[0]
        found.append(f"{len(diverged)} of its {n} flights diverged (e.g. {rel}: {f['message'] or f['status']}); "
                     f"{samples} samples could be labelled")
    if train_ok < 2:
        found.append(f"{train_ok} of its {cfg.n_train} training flights {'has' if train_ok == 1 else 'have'} labelled "
                     "samples (training needs two: one is held out for early stopping)")
    if cfg.n_val and val_samples == 0:
        found.append(f"none of its {cfg.n_val} validation flights has labelled samples")
    if not found:
        return
    lo, hi = STAGES[k]["separation"]
    also = f" (or the stage-{k - 1} model it flew with, {deployed})" if deployed is not None else ""
    raise DataError(
        f"{sdir}: stage {k} (the follower {lo}-{hi} m below the leader) cannot train a model:\n  "
        + "\n  ".join(found) + f"\nThe ground-truth field is the likely cause{also}: it is checked before flying only "
        "at a few points near a leader (`sim.field.check_field`), and a NaN or runaway force elsewhere ends each "
        "flight that meets it as diverged. Check the field over this stage's separations "
        "(`python -m experiments.force_maps --field ...`); each log's metadata holds its flight's status and message."
    )


class _Labelled:
    """Labelled samples per folder, each folder's logs checked against the manifest before they are
    read, loaded once per run (a finished stage's logs never change)."""

    def __init__(self, out: Path, manifest: dict, rerun: str) -> None:
        self.out, self.manifest, self.rerun = out, manifest, rerun
        self._cache: dict[Path, Dataset] = {}

    def __call__(self, dirs: list[Path]) -> Dataset:
        for d in dirs:
            if d not in self._cache:
                problems = check_logs(self.out, self.manifest, [d])
                if problems:
                    raise integrity_error(self.out, problems, self.rerun)
                files = [p for p in listed_logs(self.out, self.manifest) if p.parent == d]
                if not files:
                    raise DataError(f"{d}: the manifest lists no logs here; run `{self.rerun}` to collect them")
                self._cache[d] = load_dataset(files)
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


def _stage(k: int, cfg: CollectionConfig, deployed: Path | None) -> Stage:
    """Stage k of the collection: the follower in the stage's band of separations below the leader."""
    return Stage(f"stage{k}", LEADER_POSITION, (STAGES[k]["separation"],), ((cfg.seed, k),),
                 cfg.seed * 100_000 + 1000 * k, {"stage": k, "deployed_model": str(deployed)})


def deployed_predictor(checkpoint: Path | None, clamp: float, guard: bool) -> Any:
    """What a stage flies with: a stage model (`DEPLOYED_KIND`), clamped and, with `guard`, behind the
    guard (`downwash.guard.GuardedPredictor`); no model without a checkpoint (the first stage)."""
    if checkpoint is None:
        return ZeroPredictor()
    model = LearnedPredictor.from_checkpoint(checkpoint, clamp=clamp, expect_kind=DEPLOYED_KIND)
    return GuardedPredictor(model) if guard else model


def collect(
    cfg: CollectionConfig,
    collection_dir: str | Path,
    models_dir: str | Path,
    field: Any,
    progress: ProgressFactory = lambda label: None,
    *,
    refly_missing: bool = True,
    kinds: Sequence[str] = STAGED_KINDS,
) -> dict:
    """Collect all stages into `collection_dir` (resuming), train the final models into `models_dir`:
    `STAGED_KINDS`, and any other per-neighbour kinds in `kinds` (e.g. the models with memory).

    progress(label) may return a callback progress(done, total) for each batch of flights.
    Holds the lock of both folders (a second run waits, then reuses). Raises DataError
    before any flight when `collection_dir` holds a collection of another provenance, or
    when a finished stage's logs do not match the manifest: an altered or unlisted log,
    or a missing one unless `refly_missing` (then only the missing flights are flown
    again). Returns the results: per stage (separation, minutes, samples, deployed model
    and its validation RMSE on that stage, failed flights), per final model (path,
    validation RMSE, training seconds), the label-noise floor, the provenance, this run's
    wall time and `collection_seconds`, the time the whole collection took (summed over
    the runs that worked on it; a killed run cannot record its part).
    """
    unknown = [k for k in kinds if k not in PAIRWISE_KINDS]
    if unknown:
        raise ConfigError(f"kinds: unknown {unknown}; allowed: {', '.join(PAIRWISE_KINDS)}")
    kinds = list(dict.fromkeys([*STAGED_KINDS, *kinds]))
    with _pipeline_lock(collection_dir, models_dir):
        return _collect(cfg, Path(collection_dir), Path(models_dir), field, progress, refly_missing, kinds)


@contextlib.contextmanager
def _pipeline_lock(collection_dir: str | Path, models_dir: str | Path) -> Iterator[None]:
    """The locks of a collection folder and then of its models folder (always in this order: no deadlock),
    with what killed runs left half-written there removed."""
    with locked_folder(Path(collection_dir), "staged collection"), locked_folder(Path(models_dir), "staged models"):
        yield


def _collect(cfg: CollectionConfig, out: Path, models_dir: Path, field: Any, progress: ProgressFactory,
             refly_missing: bool, kinds: Sequence[str]) -> dict:
    t_start = time.perf_counter()
    record = provenance(cfg, field)
    manifest_path = out / "manifest.json"
    manifest = _load_manifest(manifest_path, record)
    for kind in PAIRWISE_KINDS:  # never overwrite models of another provenance
        if (models_dir / f"{kind}.pt").is_file():
            check_checkpoint(models_dir / f"{kind}.pt", kind, record)
    rerun = rerun_command(out, models_dir)
    problems = check_logs(out, manifest) + check_models(out, manifest, models_dir)  # before any work
    if any(p[0] != "missing" for p in problems) or (problems and not refly_missing):
        raise integrity_error(out, problems, rerun)
    refly: dict[Path, list[Path]] = {}
    for _, path, _ in problems:
        refly.setdefault(path.parent.parent, []).append(path)
    if refly:
        log.warning("%s: %d recorded logs are missing; re-flying only those: %s", out, len(problems),
                    ", ".join(str(p[1]) for p in problems))
    out.mkdir(parents=True, exist_ok=True)
    models_dir.mkdir(parents=True, exist_ok=True)
    write_manifest(manifest_path, manifest)
    n_train, n_val, flight_seconds = cfg.n_train, cfg.n_val, cfg.effective_flight_seconds
    # what this run did, in the manifest's "runs" when it did anything
    run = {"pid": os.getpid(), "host": socket.gethostname(),
           "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "flights": 0, "models": []}

    labelled = _Labelled(out, manifest, rerun)
    stage_results = []
    for k, stage in enumerate(STAGES):
        sdir = out / f"stage{k}"
        entry = manifest["stages"].setdefault(str(k), {})
        deployed = None if k == 0 else out / f"stage{k - 1}" / f"{DEPLOYED_KIND}.pt"
        if not entry.get("flights_done") or sdir in refly:  # (a done stage's missing logs: refly_missing)
            run["flights"] += fly_recorded(
                _stage(k, cfg, deployed), sdir, entry, n_train, n_val, flight_seconds,
                collection=f"{out} and {models_dir}", save=lambda: write_manifest(manifest_path, manifest),
                field=field, predictor=deployed_predictor(deployed, cfg.clamp, cfg.guard),
                batch_flights=cfg.batch_flights, threads=cfg.threads,
                progress=progress)
        _check_stage(k, sdir, entry, cfg, deployed)
        train_dirs = [out / f"stage{j}" / "train" for j in range(k + 1)]
        # the stage-k model, deployed in stage k + 1 (the last stage's would be the final model of its kind)
        if k + 1 < len(STAGES) and not (entry.get("model_done") and (sdir / f"{DEPLOYED_KIND}.pt").is_file()):
            log.info("stage %d: training the %s model that stage %d flies with", k, DEPLOYED_KIND, k + 1)
            _train_and_save(DEPLOYED_KIND, labelled(train_dirs), train_dirs, sdir / f"{DEPLOYED_KIND}.pt", cfg,
                            record, {"stage": k})
            entry.update(model_done=True, model_file=f"{DEPLOYED_KIND}.pt",
                         model_sha256=checkpoint_digest(sdir / f"{DEPLOYED_KIND}.pt"))
            run["models"].append(f"stage{k}/{DEPLOYED_KIND}")
            write_manifest(manifest_path, manifest)
        if "deployed_val_rmse" not in entry:
            entry["deployed_val_rmse"] = (None if deployed is None or n_val == 0
                                          else _val_rmse(deployed, DEPLOYED_KIND, labelled([sdir / "val"])))
            write_manifest(manifest_path, manifest)
        samples = len(labelled([sdir / "train"]))
        stage_results.append({"stage": k, "separation": list(stage["separation"]),
                              "minutes": n_train * flight_seconds / 60, "samples": samples,
                              "deployed_model": None if deployed is None else str(deployed),
                              "deployed_val_rmse": entry["deployed_val_rmse"], "failed_flights": entry.get("failed", [])})

    train_dirs = [out / f"stage{k}" / "train" for k in range(len(STAGES))]
    val_dirs = [out / f"stage{k}" / "val" for k in range(len(STAGES))] if n_val else []
    finals = manifest.setdefault("final_models", {})
    models: dict[str, Any] = {}
    missing = [kind for kind in kinds if not finals.get(kind) or not (models_dir / f"{kind}.pt").is_file()]
    if missing:
        log.info("training the final models %s into %s", missing, models_dir)
        data = labelled(train_dirs)

        def train_one(kind: str) -> dict:
            path, t0 = models_dir / f"{kind}.pt", time.perf_counter()
            history = _train_and_save(kind, data, train_dirs, path, cfg, record, {"stage": "final"})
            return {"path": str(path), "train_seconds": time.perf_counter() - t0, "epochs": history["epochs"],
                    "sha256": checkpoint_digest(path)}

        for kind, entry in _in_parallel(train_one, missing):
            finals[kind] = entry
            run["models"].append(kind)
            write_manifest(manifest_path, manifest)
    for kind in kinds:
        path = models_dir / f"{kind}.pt"
        models[kind] = {"path": str(path), "val_rmse": _val_rmse(path, kind, labelled(val_dirs)) if val_dirs else None,
                        "train_seconds": finals[kind]["train_seconds"]}
    val_logs = [p for d in val_dirs for p in listed_logs(out, manifest) if p.parent == d]
    floor = label_noise_floor(val_logs) if val_dirs else None
    if not manifest.get("complete"):  # the time this collection took, over every run that worked on it
        manifest["collection_seconds"] = manifest.get("collection_seconds", 0.0) + time.perf_counter() - t_start
    manifest["complete"] = True
    if run["flights"] or run["models"]:
        manifest.setdefault("runs", []).append(run)
    write_manifest(manifest_path, manifest)
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
    provenance (else DataError, before any flight, naming the differences). When all
    are there, nothing else is read or locked (the models folder may be read-only).
    Otherwise, under the folders' lock (another run making them is waited for, and
    what it made is used), the collection's logs are checked against its manifest
    before anything is trained on them: a missing or altered log raises DataError.
    """
    models_dir = Path(models_dir)
    record = provenance(cfg, field)

    def missing() -> list[str]:
        out = []
        for kind in kinds:
            path = models_dir / f"{kind}.pt"
            if path.is_file():
                check_checkpoint(path, kind, record)
            else:
                out.append(kind)
        return out

    if missing():
        with _pipeline_lock(collection_dir, models_dir):
            todo = missing()  # another run may have made them while this one waited
            if todo:
                log.info("models %s missing in %s: running the staged collection into %s first", todo, models_dir,
                         collection_dir)
                collect(cfg, collection_dir, models_dir, field, progress, refly_missing=False, kinds=todo)
    return {k: models_dir / f"{k}.pt" for k in kinds}


def ensure_collection(
    collection_dir: str | Path,
    models_dir: str | Path,
    cfg: CollectionConfig,
    field: Any,
    progress: ProgressFactory = lambda label: None,
) -> Path:
    """The staged collection folder, collected first (with its models) unless complete.

    Under the collection folder's lock (and the models folder's too when it collects): a
    run collecting into it is waited for. DataError when the folder holds a collection of
    another provenance, or when its logs do not match its manifest (a missing, altered or
    unlisted log, named with how to re-fly it).
    """
    collection_dir = Path(collection_dir)
    with folder_lock(collection_dir, label="staged collection"):
        path = collection_dir / "manifest.json"
        manifest = _load_manifest(path, provenance(cfg, field)) if path.is_file() else None  # raises on a mismatch
        if manifest is not None and manifest.get("complete"):
            verify_collection(collection_dir, manifest, models_dir)
        else:
            collect(cfg, collection_dir, models_dir, field, progress, refly_missing=False)
    return collection_dir


def _load_manifest(path: Path, record: dict) -> dict:
    if not path.is_file():
        return {"version": MANIFEST_VERSION, "provenance": record, "key": fingerprint(record), "stages": {}}
    manifest = read_manifest(path)
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
        log.info("%s: collection complete; checking its logs and models", path)
    return manifest


def _warn_code(have: dict, where: Path | str) -> None:
    now = code_version()
    if have.get("code") != now:
        log.warning("%s was made by code %s; reusing it with code %s (the provenance key matches)",
                    where, have.get("code"), now)
