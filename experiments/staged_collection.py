"""The paper's staged data collection (section 5.A), batched and resumable.

    python -m experiments.staged_collection [--models-dir runs/models] [--quick]

Stage 0 flies far below the leader (1.35-1.75 m) with no model; stage 1 flies
closer with the stage-0 equivariant model compensating; stage 2 flies at about
0.5 m with the stage-1 model. Each stage is ~5.7 minutes of varied flights
(randomised passes through and beside the wake at many headings and speeds,
hovers at offsets, lemniscates), plus validation flights of the same kind from
separate seeds. Labels are always the full downwash (f = a - u with u the
command actually applied). After the last stage the final shallow, deep and
equivariant models are trained on all training data into --models-dir.

A manifest records the config, the seeds and what is complete; rerunning skips
finished stages, and an interrupted run loses at most the flights in progress.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controllers.references import Hover, Lemniscate, Mixed, random_passes, stack
from experiments.common import CommonArgs, ProgressBar, arg, format_table, load_field, parse_args, setup_logging, write_results
from sim.flight import fly
from sim.logs import atomic_write_json, save_log
from sim.predictor import ZeroPredictor
from sim.params import LEADER_POSITION
from sim.scene import build_scene

__all__ = ["STAGES", "StagedArgs", "run", "main"]

log = logging.getLogger(__name__)

LEADER = np.array(LEADER_POSITION)  # m, Alpha hovers here
# (name, vertical separation range (m), model deployed while flying: the previous stage's)
STAGES = (
    {"separation": (1.35, 1.75)},  # stage 0: far enough for the nominal controller
    {"separation": (0.85, 1.35)},  # stage 1: closer, stage-0 model compensating
    {"separation": (0.45, 0.65)},  # stage 2: ~0.5 m (two body lengths), stage-1 model
)
MODEL_KINDS = ("shallow", "deep", "equivariant")
LEMNISCATE_SHARE = 0.2  # share of each stage's flights that are lemniscates (the rest: random passes and hovers)
MANIFEST_VERSION = 1


@dataclass(frozen=True)
class StagedArgs(CommonArgs):
    models_dir: str = arg("runs/models", "where the final shallow/deep/equivariant models are written")
    stage_minutes: float = arg(5.7, "training flight minutes per stage (paper: ~5.7, ~17 in all)")
    val_ratio: float = arg(1.0, "validation minutes per training minute (paper: similar size)")
    flight_seconds: float = arg(28.5, "length of one flight, s (12 flights of 28.5 s: 5.7 min per stage)")
    clamp: float = arg(6.0, "magnitude bound of the deployed model's prediction, m/s^2")
    threads: int = arg(0, "worker threads for batched flights (0: all cores); training uses one")


def _validate(args: StagedArgs) -> None:
    if not 0 < args.stage_minutes <= 60:
        raise ValueError(f"--stage-minutes: allowed (0, 60], got {args.stage_minutes}")
    if not 0 <= args.val_ratio <= 5:
        raise ValueError(f"--val-ratio: allowed [0, 5], got {args.val_ratio}")
    if not 2.0 <= args.flight_seconds <= 600:
        raise ValueError(f"--flight-seconds: allowed 2-600 s, got {args.flight_seconds}")
    if not args.clamp > 0:
        raise ValueError(f"--clamp: must be > 0 m/s^2, got {args.clamp}")


def _stage_reference(rng: np.random.Generator, n: int, separation: tuple[float, float], seconds: float):
    """Follower references for n flights of one stage: mostly random passes, some lemniscates."""
    n_lem = int(round(LEMNISCATE_SHARE * n)) if n >= 3 else 0
    parts = []
    if n - n_lem:
        passes = random_passes(rng, n - n_lem, LEADER, depth_range=separation, duration=seconds)
        parts.append((passes, np.arange(n - n_lem)))
    if n_lem:
        depth = rng.uniform(*separation, n_lem)
        center = LEADER - np.stack([rng.uniform(-0.2, 0.2, n_lem), rng.uniform(-0.2, 0.2, n_lem), depth], axis=1)
        lem = Lemniscate(center, half_length=rng.uniform(0.6, 1.2, n_lem), half_width=rng.uniform(0.3, 0.7, n_lem),
                         period=rng.uniform(10.0, 24.0, n_lem), n_worlds=n_lem)
        parts.append((lem, np.arange(n - n_lem, n)))
    follower = Mixed(parts)
    return stack([Hover(LEADER, n_worlds=n), follower])


class _Logs:
    """Labelled samples per folder, loaded once per run (a finished stage's logs never change)."""

    def __init__(self):
        self._cache: dict[Path, Any] = {}

    def __call__(self, dirs: list[Path]):
        from downwash.datasets import concatenate, load_dataset

        for d in dirs:
            if d not in self._cache:
                self._cache[d] = load_dataset(d)
        return concatenate([self._cache[d] for d in dirs])


def _train_and_save(kind: str, data: Any, train_dirs: list[Path], path: Path, args: StagedArgs, extra: dict) -> dict:
    from downwash.checkpoint import save_checkpoint
    from downwash.train import TrainConfig, train_model

    config = TrainConfig(seed=args.seed, **({"max_epochs": 3, "min_steps": 30} if args.quick else {}))
    model, history = train_model(kind, data, None, config)
    save_checkpoint(path, model, {"training": {k: v for k, v in history.items() if k not in ("train_loss", "val_loss")},
                                  "data": data.summary(), "train_dirs": [str(d) for d in train_dirs], **extra})
    return history


def _val_rmse(checkpoint: Path, val_data: Any) -> float:
    from downwash.checkpoint import load_checkpoint
    from downwash.train import rmse

    model, _ = load_checkpoint(checkpoint)
    return rmse(model, val_data)[0]


def run(args: StagedArgs, field: Any | None = None) -> dict:
    """Collect all stages (resuming), train the final models; returns the results dict."""
    _validate(args)
    field = load_field(args.field) if field is None else field
    t_start = time.perf_counter()
    out, models_dir = Path(args.out), Path(args.models_dir)
    out.mkdir(parents=True, exist_ok=True)
    models_dir.mkdir(parents=True, exist_ok=True)
    stage_minutes = 0.1 if args.quick else args.stage_minutes
    flight_seconds = 4.0 if args.quick else args.flight_seconds
    n_train = max(2, math.ceil(stage_minutes * 60 / flight_seconds))
    n_val = max(1, math.ceil(args.val_ratio * n_train)) if args.val_ratio > 0 else 0
    config = {"stage_minutes": stage_minutes, "flight_seconds": flight_seconds, "n_train": n_train, "n_val": n_val,
              "seed": args.seed, "stages": STAGES, "field": repr(field), "clamp": args.clamp, "quick": args.quick}

    manifest_path = out / "manifest.json"
    manifest = _load_manifest(manifest_path, config)
    scene = build_scene()
    from downwash.predictor import LearnedPredictor

    labelled = _Logs()
    stage_results = []
    for k, stage in enumerate(STAGES):
        sdir = out / f"stage{k}"
        entry = manifest["stages"].setdefault(str(k), {})
        deployed = None if k == 0 else out / f"stage{k - 1}" / "equivariant.pt"
        if not entry.get("flights_done"):
            predictor = ZeroPredictor() if deployed is None else LearnedPredictor.from_checkpoint(deployed, clamp=args.clamp)
            n = n_train + n_val
            rng = np.random.default_rng([args.seed, k])
            seeds = [args.seed * 100_000 + 1000 * k + i for i in range(n)]  # train: i < n_train, val: the rest
            meta = [{"stage": k, "role": "train" if i < n_train else "val", "deployed_model": str(deployed)}
                    for i in range(n)]
            flights = fly(scene, _stage_reference(rng, n, stage["separation"], flight_seconds), seeds, flight_seconds,
                       field=field, predictor=predictor, meta=meta, n_threads=args.threads,
                       progress=ProgressBar(f"stage {k}: {n} flights"))
            for i, L in enumerate(flights):
                save_log(sdir / L.meta["role"] / f"flight_{i:03d}.npz", L)
            entry.update(flights_done=True, seeds=seeds, failed=[L.meta["message"] for L in flights if not L.ok])
            _save_manifest(manifest_path, manifest)
        train_dirs = [out / f"stage{j}" / "train" for j in range(k + 1)]
        if not entry.get("model_done"):  # the stage-k equivariant model, deployed in stage k + 1
            _train_and_save("equivariant", labelled(train_dirs), train_dirs, sdir / "equivariant.pt", args, {"stage": k})
            entry["model_done"] = True
            _save_manifest(manifest_path, manifest)
        if "deployed_val_rmse" not in entry:
            entry["deployed_val_rmse"] = (None if deployed is None or n_val == 0
                                          else _val_rmse(deployed, labelled([sdir / "val"])))
            _save_manifest(manifest_path, manifest)
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
            history = _train_and_save(kind, labelled(train_dirs), train_dirs, path, args, {"stage": "final"})
            finals[kind] = {"path": str(path), "train_seconds": time.perf_counter() - t0, "epochs": history["epochs"]}
            _save_manifest(manifest_path, manifest)
        models[kind] = {"path": str(path), "val_rmse": _val_rmse(path, labelled(val_dirs)) if val_dirs else None,
                        "train_seconds": finals[kind]["train_seconds"]}
    if val_dirs:
        from downwash.labels import label_noise_floor
        from downwash.datasets import find_logs

        floor = label_noise_floor([p for d in val_dirs for p in find_logs(d)])
    else:
        floor = None
    manifest["complete"] = True
    _save_manifest(manifest_path, manifest)

    results = {"stages": stage_results, "training_minutes": len(STAGES) * n_train * flight_seconds / 60,
               "validation_minutes": len(STAGES) * n_val * flight_seconds / 60, "models": models,
               "noise_floor": floor, "wall_seconds": time.perf_counter() - t_start}
    path = write_results(out, results, args)
    rows = [[s["stage"], f"{s['separation'][0]}-{s['separation'][1]}", s["minutes"], s["samples"],
             s["deployed_val_rmse"] if s["deployed_val_rmse"] is not None else "-"] for s in stage_results]
    print(format_table(rows, ["stage", "separation m", "minutes", "samples", "deployed val RMSE"]))
    rows = [[k, m["val_rmse"] if m["val_rmse"] is not None else "-", m["train_seconds"]] for k, m in models.items()]
    print(format_table(rows, ["model", "val RMSE m/s^2", "train s"]))
    if floor:
        print(f"label noise floor (labels vs true mean field): {floor['rmse_mean']:.4f} m/s^2")
    print(f"\nwrote {path}; models in {models_dir}/ ({results['wall_seconds']:.1f} s)")
    return results


def _load_manifest(path: Path, config: dict) -> dict:
    import json

    if path.is_file():
        manifest = json.loads(path.read_text())
        if manifest.get("version") != MANIFEST_VERSION or manifest.get("config") != json.loads(json.dumps(config)):
            raise ValueError(
                f"{path}: this folder holds a staged collection with another config; "
                f"use another --out or delete the folder to start afresh"
            )
        if manifest.get("complete"):
            log.info("%s: collection complete; re-checking models only", path)
        return manifest
    return {"version": MANIFEST_VERSION, "config": config, "stages": {}}


def _save_manifest(path: Path, manifest: dict) -> None:
    atomic_write_json(path, manifest)


def main(argv=None) -> dict:
    setup_logging()
    return run(parse_args(StagedArgs, "staged_collection", argv, __doc__))


if __name__ == "__main__":
    main()
