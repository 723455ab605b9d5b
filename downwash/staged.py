"""The paper's staged data collection (section 5.A) as a library: batched and resumable.

Stage 0 flies far below the leader (1.35-1.75 m) with no model; stage 1 flies
closer with the stage-0 equivariant model compensating; stage 2 flies at about
0.5 m with the stage-1 model. Each stage is ~5.7 minutes of varied flights
(`trajectories.collection_reference`: randomised passes through and beside the
wake, hovers at offsets, lemniscates), plus validation flights of the same kind from
separate seeds. Labels are always the full downwash (f = a - u with u the command
actually applied). After the last stage the final model of every kind in
`MODEL_KINDS` is trained on all training data into the models folder.

A manifest records the config, the seeds and what is complete; `collect` skips
finished work, so an interrupted run loses at most the flights in progress.
`ensure_models` is what every experiment that needs trained models calls.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from core.errors import ConfigError, DataError
from core.io import atomic_write_json
from core.params import LEADER_POSITION
from downwash.checkpoint import load_checkpoint, save_checkpoint
from downwash.datasets import Dataset, concatenate, find_logs, load_dataset
from downwash.labels import label_noise_floor
from downwash.models import MODEL_KINDS
from downwash.predictor import LearnedPredictor
from downwash.train import TrainConfig, rmse, train_model
from sim.flight import fly
from sim.logs import save_log
from sim.predictor import ZeroPredictor
from sim.scene import build_scene
from trajectories import collection_reference

__all__ = ["STAGES", "DEPLOYED_KIND", "CollectionConfig", "train_config", "collect", "ensure_models",
           "ensure_collection"]

log = logging.getLogger(__name__)

LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here
STAGES = (
    {"separation": (1.35, 1.75)},  # stage 0: far enough for the nominal controller
    {"separation": (0.85, 1.35)},  # stage 1: closer, stage-0 model compensating
    {"separation": (0.45, 0.65)},  # stage 2: ~0.5 m (two body lengths), stage-1 model
)
DEPLOYED_KIND = "equivariant"  # the model each stage trains and the next stage flies with
MANIFEST_VERSION = 1
_QUICK_TRAINING = {"max_epochs": 3, "min_steps": 30}  # --quick: a few steps, enough to exercise the code


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

    def __post_init__(self) -> None:
        if not 0 < self.stage_minutes <= 60:
            raise ConfigError(f"--stage-minutes: allowed (0, 60], got {self.stage_minutes}")
        if not 0 <= self.val_ratio <= 5:
            raise ConfigError(f"--val-ratio: allowed [0, 5], got {self.val_ratio}")
        if not 2.0 <= self.flight_seconds <= 600:
            raise ConfigError(f"--flight-seconds: allowed 2-600 s, got {self.flight_seconds}")
        if not self.clamp > 0:
            raise ConfigError(f"--clamp: must be > 0 m/s^2, got {self.clamp}")

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
                    extra: dict) -> dict:
    model, history = train_model(kind, data, None, train_config(cfg.seed, cfg.quick))
    save_checkpoint(path, model, {"training": {k: v for k, v in history.items() if k not in ("train_loss", "val_loss")},
                                  "data": data.summary(), "train_dirs": [str(d) for d in train_dirs], **extra})
    return history


def _val_rmse(checkpoint: Path, val_data: Dataset) -> float:
    model, _ = load_checkpoint(checkpoint)
    return rmse(model, val_data)[0]


def collect(
    cfg: CollectionConfig,
    out: str | Path,
    models_dir: str | Path,
    field: Any,
    progress: Callable[[str], Callable[[int, int], None] | None] = lambda label: None,
) -> dict:
    """Collect all stages into `out` (resuming), train the final models into `models_dir`.

    progress(label) may return a callback progress(done, total) for each stage's flights.
    Returns the results: per stage (separation, minutes, samples, deployed model and its
    validation RMSE on that stage, failed flights), per final model (path, validation
    RMSE, training seconds), the label-noise floor and the wall time.
    """
    t_start = time.perf_counter()
    out, models_dir = Path(out), Path(models_dir)
    out.mkdir(parents=True, exist_ok=True)
    models_dir.mkdir(parents=True, exist_ok=True)
    n_train, n_val, flight_seconds = cfg.n_train, cfg.n_val, cfg.effective_flight_seconds
    config = {"stage_minutes": cfg.effective_stage_minutes, "flight_seconds": flight_seconds, "n_train": n_train,
              "n_val": n_val, "seed": cfg.seed, "stages": STAGES, "field": repr(field), "clamp": cfg.clamp,
              "quick": cfg.quick}

    manifest_path = out / "manifest.json"
    manifest = _load_manifest(manifest_path, config)
    scene = build_scene()
    labelled = _Labelled()
    stage_results = []
    for k, stage in enumerate(STAGES):
        sdir = out / f"stage{k}"
        entry = manifest["stages"].setdefault(str(k), {})
        deployed = None if k == 0 else out / f"stage{k - 1}" / f"{DEPLOYED_KIND}.pt"
        if not entry.get("flights_done"):
            predictor = (ZeroPredictor() if deployed is None
                         else LearnedPredictor.from_checkpoint(deployed, clamp=cfg.clamp))
            n = n_train + n_val
            rng = np.random.default_rng([cfg.seed, k])
            seeds = [cfg.seed * 100_000 + 1000 * k + i for i in range(n)]  # train: i < n_train, val: the rest
            meta = [{"stage": k, "role": "train" if i < n_train else "val", "deployed_model": str(deployed)}
                    for i in range(n)]
            reference = collection_reference(rng, n, LEADER, stage["separation"], flight_seconds)
            flights = fly(scene, reference, seeds, flight_seconds, field=field, predictor=predictor, meta=meta,
                          n_threads=cfg.threads, progress=progress(f"stage {k}: {n} flights"))
            for i, L in enumerate(flights):
                save_log(sdir / L.meta["role"] / f"flight_{i:03d}.npz", L)
            entry.update(flights_done=True, seeds=seeds, failed=[L.meta["message"] for L in flights if not L.ok])
            atomic_write_json(manifest_path, manifest)
        train_dirs = [out / f"stage{j}" / "train" for j in range(k + 1)]
        if not entry.get("model_done"):  # the stage-k model, deployed in stage k + 1
            _train_and_save(DEPLOYED_KIND, labelled(train_dirs), train_dirs, sdir / f"{DEPLOYED_KIND}.pt", cfg,
                            {"stage": k})
            entry["model_done"] = True
            atomic_write_json(manifest_path, manifest)
        if "deployed_val_rmse" not in entry:
            entry["deployed_val_rmse"] = (None if deployed is None or n_val == 0
                                          else _val_rmse(deployed, labelled([sdir / "val"])))
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
    for kind in MODEL_KINDS:
        path = models_dir / f"{kind}.pt"
        if not finals.get(kind) or not path.is_file():
            t0 = time.perf_counter()
            history = _train_and_save(kind, labelled(train_dirs), train_dirs, path, cfg, {"stage": "final"})
            finals[kind] = {"path": str(path), "train_seconds": time.perf_counter() - t0, "epochs": history["epochs"]}
            atomic_write_json(manifest_path, manifest)
        models[kind] = {"path": str(path), "val_rmse": _val_rmse(path, labelled(val_dirs)) if val_dirs else None,
                        "train_seconds": finals[kind]["train_seconds"]}
    floor = label_noise_floor([p for d in val_dirs for p in find_logs(d)]) if val_dirs else None
    manifest["complete"] = True
    atomic_write_json(manifest_path, manifest)
    return {"stages": stage_results, "training_minutes": len(STAGES) * n_train * flight_seconds / 60,
            "validation_minutes": len(STAGES) * n_val * flight_seconds / 60, "models": models,
            "noise_floor": floor, "wall_seconds": time.perf_counter() - t_start}


def ensure_models(
    models_dir: str | Path,
    kinds: tuple[str, ...] | list[str],
    collection_dir: str | Path,
    cfg: CollectionConfig,
    field: Any,
    progress: Callable[[str], Callable[[int, int], None] | None] = lambda label: None,
) -> dict[str, Path]:
    """Checkpoint paths of `kinds` in `models_dir`, running the staged collection first when any is missing."""
    models_dir = Path(models_dir)
    missing = [k for k in kinds if not (models_dir / f"{k}.pt").is_file()]
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
    progress: Callable[[str], Callable[[int, int], None] | None] = lambda label: None,
) -> Path:
    """The staged collection folder, collected first (with its models) when it has no manifest."""
    collection_dir = Path(collection_dir)
    if not (collection_dir / "manifest.json").is_file():
        collect(cfg, collection_dir, models_dir, field, progress)
    return collection_dir


def _load_manifest(path: Path, config: dict) -> dict:
    if path.is_file():
        manifest = json.loads(path.read_text())
        if manifest.get("version") != MANIFEST_VERSION or manifest.get("config") != json.loads(json.dumps(config)):
            raise DataError(
                f"{path}: this folder holds a staged collection with another config; "
                f"use another --out or delete the folder to start afresh"
            )
        if manifest.get("complete"):
            log.info("%s: collection complete; re-checking models only", path)
        return manifest
    return {"version": MANIFEST_VERSION, "config": config, "stages": {}}

