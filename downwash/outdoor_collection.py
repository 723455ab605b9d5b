"""Data from the outdoor regime (the paper's section 6): a moving leader in wind, after the indoor stages.

The indoor staged collection (`downwash.staged`) hovers the leader in still air; its models
meet a moving leader and wind only in flight. The outdoor stages come after it, one per
wind setting (`OUTDOOR_WINDS`: still air, then light and moderate Dryden gusts with a mean
wind from several directions). In every flight the leader moves: a straight line (even
flights) or a horizontal circle (odd flights) at a speed drawn in `LEADER_SPEEDS` (the
outdoor experiment's range), with a random heading; the follower flies the indoor
collection patterns (passes through and beside the wake, lemniscates) relative to the
moving leader, at the indoor stages' depths (`DEPTH_BAND`, all three stages' separations).
See `downwash.stages` for how a flight's reference and noise follow from its seeds.

What the stages fly with: the indoor collection's final equivariant model, as each indoor
stage flies the model of the stage before, clamped as indoors and behind the guard
(`downwash.staged.deployed_predictor`). Unguarded, that model makes the follower climb into
a moving leader (the outdoor experiment: 100 % of its flights crash); the guard sees the
leader's speed outside the indoor data and applies (next to) nothing, so the outdoor stages
fly much as the nominal controller would, and the logs record what it applied.

Then every requested model kind is trained on the indoor and the outdoor training flights
together ("outdoor": the regime's models), with the indoor schedule (`train_config`). The
models see what an outdoor lab measures, the estimated states of both vehicles, never the
wind: a label holds the whole force the follower's estimate cannot explain (the wake and the
wind's drag and gusts on the follower). The logs of the two regimes differ in their wind
provenance, joined on purpose (`downwash.datasets.concatenate(..., mixed=("wind",))`).

Resumable and keyed by provenance as the indoor collection: a manifest records every log,
checked before any training; a folder of other settings is refused with the differences.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import LEADER_POSITION
from downwash_core.provenance import describe
from downwash.checkpoint import load_checkpoint
from downwash.labels import PAIR
from downwash.models import PAIRWISE_KINDS
from downwash.guard import guard_settings
from downwash.staged import DEPLOYED_KIND, STAGES, deployed_predictor, train_config
from downwash.manifest import write_manifest
from downwash.stages import (CheckedLoader, ProgressFactory, Stage, StageBudget, fly_recorded, locked_folder,
                             open_manifest)
from downwash.train import rmse, save_trained, train_model
from sim.logs import load_log
from sim.wind import DrydenWind

__all__ = ["OUTDOOR_WINDS", "LEADER_SPEEDS", "DEPTH_BAND", "OutdoorCollectionConfig", "outdoor_provenance",
           "outdoor_stages", "collect_outdoor"]

# (name, severity: calm or a MIL-F-8785C preset of sim.wind, mean wind speed m/s, its direction deg from +x)
OUTDOOR_WINDS = (
    ("still", "calm", 0.0, 0.0),
    ("light-0", "light", 2.0, 0.0),
    ("light-120", "light", 2.0, 120.0),
    ("light-240", "light", 2.0, 240.0),
    ("moderate-60", "moderate", 4.0, 60.0),
    ("moderate-180", "moderate", 4.0, 180.0),
    ("moderate-300", "moderate", 4.0, 300.0),
)
LEADER_SPEEDS = (0.5, 3.0)  # m/s, the leader's ground speed (the outdoor experiment's range)
DEPTH_BAND = (min(s["separation"][0] for s in STAGES), max(s["separation"][1] for s in STAGES))  # m below the leader


@dataclass(frozen=True)
class OutdoorCollectionConfig(StageBudget):
    """Size and settings of the outdoor stages (`StageBudget`, validated on construction)."""

    stage_minutes: float = 1.0  # training flight minutes per wind setting
    minutes_option = "--outdoor-minutes"


def _wind(severity: str, speed: float, direction_deg: float) -> DrydenWind | None:
    rad = math.radians(direction_deg)
    mean = (speed * math.cos(rad), speed * math.sin(rad), 0.0)
    wind = DrydenWind(mean=mean) if severity == "calm" else DrydenWind.preset(severity, mean=mean)
    return None if wind.off else wind


def outdoor_stages(cfg: OutdoorCollectionConfig) -> list[Stage]:
    """One stage per wind setting of `OUTDOOR_WINDS`, stage ids 20, 21, ... in the logs."""
    return [Stage(f"outdoor-{name}", LEADER_POSITION, (DEPTH_BAND,), ((cfg.seed, 300 + i),),
                  cfg.seed * 100_000 + 70_000 + 1_000 * i, {"stage": 20 + i}, (), LEADER_SPEEDS,
                  _wind(severity, speed, direction))
            for i, (name, severity, speed, direction) in enumerate(OUTDOOR_WINDS)]


def outdoor_provenance(cfg: OutdoorCollectionConfig, pair_record: dict) -> dict:
    """What defines an outdoor collection: the indoor collection's record and the outdoor settings."""
    return {"pair": {k: v for k, v in pair_record.items() if k != "code"},
            "outdoor": {"winds": [list(w) for w in OUTDOOR_WINDS], "leader_speeds": list(LEADER_SPEEDS),
                        "depth_band": list(DEPTH_BAND), "seconds": cfg.seconds, "n_train": cfg.n_train,
                        "n_val": cfg.n_val, "seed": cfg.seed,
                        "deployed": {"kind": DEPLOYED_KIND, "trained": "indoor",
                                     "clamp": pair_record["collection"]["clamp"], "guard": guard_settings()},
                        "training": train_config(cfg.seed, cfg.quick).to_dict()}}


def collect_outdoor(
    cfg: OutdoorCollectionConfig,
    out: str | Path,
    pair_collection: str | Path,
    pair_record: dict,
    field: Any,
    kinds: Sequence[str],
    deployed: str | Path,
    progress: ProgressFactory = lambda label: None,
) -> dict:
    """Fly the outdoor stages into `out` (resuming) and train each of `kinds` on indoor + outdoor data.

    pair_collection: the complete indoor staged collection folder; pair_record: its provenance;
    deployed: the indoor collection's final `DEPLOYED_KIND` checkpoint, which the stages fly with.
    Returns {checkpoints: {kind: path}, models: {kind: {path, val_rmse}}, stages, provenance, key,
    data_winds (the wind records of the training data, indoor None first)}.
    """
    unknown = [k for k in kinds if k not in PAIRWISE_KINDS]
    if unknown:
        raise ConfigError(f"kinds: unknown {unknown}; allowed: {', '.join(PAIRWISE_KINDS)}")
    with locked_folder(Path(out), "outdoor collection"):
        t0 = time.perf_counter()
        out, pair_collection = Path(out), Path(pair_collection)
        record = outdoor_provenance(cfg, pair_record)
        manifest_path = out / "manifest.json"
        manifest = open_manifest(out, record, "an outdoor collection")
        stages = outdoor_stages(cfg)
        for stage in stages:
            fly_recorded(stage, out / stage.name, manifest["stages"].setdefault(stage.name, {}), cfg.n_train,
                         cfg.n_val, cfg.seconds, collection=str(out),
                         save=lambda: write_manifest(manifest_path, manifest), field=field,
                         predictor=deployed_predictor(Path(deployed), pair_record["collection"]["clamp"], guard=True),
                         batch_flights=cfg.batch_flights, threads=cfg.threads, progress=progress)
        load = CheckedLoader(PAIR, {out: manifest}, f"python -m experiments.outdoor (the outdoor stages of {out})",
                             mixed=("wind",))
        indoor = [pair_collection / f"stage{k}" / "train" for k in range(len(STAGES))]
        data = load(indoor + [out / st.name / "train" for st in stages])
        val = load([out / st.name / "val" for st in stages])  # judged on the regime's own validation flights
        checkpoints, models = {}, {}
        for kind in kinds:
            path = out / "models" / f"{kind}.pt"
            if not path.is_file():
                model, history = train_model(kind, data, None, train_config(cfg.seed, cfg.quick))
                save_trained(path, model, history, data)
            checkpoints[kind] = path
            model = load_checkpoint(path, expect_kind=kind).model
            models[kind] = {"path": str(path), "val_rmse": rmse(model, val)[0]}
        manifest["complete"] = True
        write_manifest(manifest_path, manifest)
        return {"checkpoints": checkpoints, "models": models, "key": manifest["key"], "provenance": record,
                "data_winds": (data.provenance or {}).get("wind", {}).get("mixed"),  # every regime the models saw
                "stages": [{"name": st.name, "wind": describe(st.wind) if st.wind else None,
                            "flights": cfg.n_train + cfg.n_val, "deployed_applied": _mean_applied(out / st.name)}
                           for st in stages],
                "minutes": len(stages) * cfg.n_train * cfg.seconds / 60, "wall_seconds": time.perf_counter() - t0}


def _mean_applied(stage_dir: Path) -> float | None:
    """The mean fraction of the deployed model's prediction the guard applied to the follower over a
    stage's logs (their ``applied``; None in logs without it)."""
    fractions = []
    for path in sorted(stage_dir.glob("*/*.npz")):
        log = load_log(path)
        if "applied" in log.arrays:
            fractions.append(log["applied"][:, log.meta["follower"]])
    return float(np.mean(np.concatenate(fractions))) if fractions else None
