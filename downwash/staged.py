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
process per core at once (`downwash.forked_jobs`; each model bit-identical to one trained alone); any other
per-neighbour kind asked for (`ensure_models`: the models with memory) is trained there
on the same data when first asked for.

Provenance. A collection is defined by its `provenance` record, and nothing is reused
unless it matches what was asked for (`downwash.staged_provenance`).

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
import os
import socket
import time
from pathlib import Path
from typing import Any, Iterator, Sequence

from downwash_core.errors import ConfigError, DataError
from downwash_core.locks import folder_lock
from downwash_core.params import LEADER_POSITION
from downwash_core.provenance import fingerprint
from downwash_core.status import Status
from downwash.checkpoint import checkpoint_digest, load_checkpoint, save_checkpoint
from downwash.datasets import Dataset
from downwash.forked_jobs import in_parallel as _in_parallel  # (importable from here as before: tests use it)
from downwash.guard import GuardedPredictor
from downwash.labels import PAIR, label_noise_floor
from downwash.manifest import (check_logs, check_models, integrity_error, listed_logs, rerun_command,
                               verify_collection, write_manifest)
from downwash.models import PAIRWISE_KINDS, STAGED_KINDS
from downwash.predictor import LearnedPredictor
from downwash.stages import CheckedLoader, ProgressFactory, Stage, fly_recorded, locked_folder
from downwash.staged_provenance import (  # the settings and provenance, importable from here as before
    DEPLOYED_KIND, STAGES, CollectionConfig, load_manifest, check_checkpoint, pipeline_dirs, provenance, train_config,
)
from downwash.train import rmse, train_model
from sim.predictor import ZeroPredictor

__all__ = [
    "STAGES", "DEPLOYED_KIND", "CollectionConfig", "train_config", "provenance", "pipeline_dirs", "collect",
    "ensure_models", "ensure_collection", "check_checkpoint", "deployed_predictor",
]  # fmt: skip

log = logging.getLogger(__name__)


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


def _train_and_save(kind: str, data: Dataset, train_dirs: list[Path], path: Path, cfg: CollectionConfig,
                    record: dict, extra: dict) -> dict:
    model, history = train_model(kind, data, None, train_config(cfg.seed, cfg.quick))
    save_checkpoint(path, model, {"training": {k: v for k, v in history.items() if k not in ("train_loss", "val_loss")},
                                  "data": data.summary(), "train_dirs": [str(d) for d in train_dirs],
                                  "provenance": record, "provenance_key": fingerprint(record), **extra})
    return history


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
    manifest = load_manifest(manifest_path, record)
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

    labelled = CheckedLoader(PAIR, {out: manifest}, rerun)  # the pair's samples, each folder checked once
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
        manifest = load_manifest(path, provenance(cfg, field)) if path.is_file() else None  # raises on a mismatch
        if manifest is not None and manifest.get("complete"):
            verify_collection(collection_dir, manifest, models_dir)
        else:
            collect(cfg, collection_dir, models_dir, field, progress, refly_missing=False)
    return collection_dir
