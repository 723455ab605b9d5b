"""Staged data collection for many vehicles, and the multi-vehicle models trained on it.

The two-vehicle staged collection (`downwash.staged`) comes first and is shared: with
two vehicles every aggregation law is the pairwise field (`sim.aggregation`), so its
logs serve every law. Then, as the two-vehicle stages move the follower closer, the
swarm stages add vehicles deeper in the stack:

    stage 3: a leader hovering and two followers at depths 0.45-0.75 m and 1.0-1.3 m,
             flown with the two-vehicle equivariant model summed over neighbours
             (the naive model: it is what a lab would deploy first);
    stage 4: a third follower at 1.55-1.85 m, flown with the deep-sets equivariant model
             trained on the two-vehicle data and stage 3.

Every follower flies the collection patterns of `downwash_trajectories.collection_reference`
(passes through and beside the wakes, lemniscates) within its own depth band, so no two
vehicles ever share a height (the bands are 0.25 m apart: no collision is possible).

Then the stages of other vehicle kinds (`KIND_STAGES`), flown with no model (there is none
for these kinds yet, as for the paper's first stage): an X500 over two paper quads, a stack
of four Crazyflies at their own scale of depths, and Crazyflies over a paper quad. Small
vehicles fly above large ones, as in the presets (a Crazyflie beneath a paper quad is pushed
past its thrust margin, `sim.presets`).

After the last stage, each trainable model of sets (`downwash.set_models`) is trained on
the two-vehicle data only ("pair") and on all of it ("mixed"), the generalisation question
of the paper's section 6, and once more on all of it reading the vehicle kinds ("kinds",
``kinds=True``), so that "mixed" against "kinds" isolates what knowing the kinds is worth.
The "pair" models depend on no law, so they live in
a folder of their own (`pair_models_dir`) that every law's collection shares, each training
them there under that folder's lock. The
models of sets train on a shorter schedule than the two-vehicle models
(`swarm_train_config`: at least 600 steps, at most 20 epochs, against 1500 and 60), so
that the swarm experiment fits its five minutes on two cores.

A swarm stage flight that ended early (a collision or a divergence, which the deployed
model of a stage can cause) is left out of the models' data: its last seconds hold
labels of tens of m/s^2 that are the crash, not the wakes, and one such flight made a
validation RMSE of 10 m/s^2 out of flights otherwise near 0.13. The count is reported.

Resumable as the two-vehicle collection: a flight's reference and noise come from its
own seeds, each log is written as its batch lands, a manifest records what is done; a
folder of another provenance (field, law, settings, the pair collection) is refused
with the differences.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from downwash_core.errors import ConfigError
from downwash_core.params import LEADER_POSITION
from downwash_core.provenance import describe, fingerprint
from downwash.staged import STAGES, train_config
from downwash.manifest import write_manifest
from downwash.stages import (CheckedLoader, ProgressFactory, Stage, StageBudget, fly_recorded, locked_folder,
                             open_manifest)
from downwash.train import TrainConfig
from downwash.datasets import concatenate
from sim.neighbours import NeighbourSet
from downwash.checkpoint import load_checkpoint, wrap_pairwise
from downwash.predictor import LearnedPredictor
from downwash.registry import SET_KINDS
from downwash.train import rmse, save_trained, train_model

__all__ = ["SWARM_STAGES", "DEPTH_BANDS", "DATA_MIXES", "KIND_STAGES", "CRAZYFLIE_BANDS", "SwarmCollectionConfig", "swarm_train_config",
           "swarm_provenance", "pair_models_key", "collect_swarm", "swarm_model_path"]

DEPTH_BANDS = ((0.45, 0.75), (1.0, 1.3), (1.55, 1.85))  # m below the leader, follower k of a swarm stage
SWARM_STAGES = (3, 4)  # vehicles per swarm stage
DEPLOYED_SWARM_KIND = "deepsets_equivariant"  # trained after stage 3, flown in stage 4
DATA_MIXES = ("pair", "mixed", "kinds")  # the two-vehicle data only, all of it, all of it reading the kinds
CRAZYFLIE_BANDS = ((0.15, 0.25), (0.32, 0.42), (0.49, 0.59))  # m below the leader: Crazyflies as labs stack them
# (name, each vehicle's kind leader first, the followers' depth bands): the stages of other kinds
KIND_STAGES = (
    ("heavy", ("x500", "paper_quad", "paper_quad"), DEPTH_BANDS[:2]),
    ("crazyflies", ("crazyflie_2_1",) * 4, CRAZYFLIE_BANDS),
    ("small_over_large", ("crazyflie_2_1", "crazyflie_2_1", "paper_quad"), (CRAZYFLIE_BANDS[0], DEPTH_BANDS[0])),
)
TRAINABLE_SET_KINDS = tuple(k for k, cls in SET_KINDS.items() if cls.trainable)  # the models of sets trained here


@dataclass(frozen=True)
class SwarmCollectionConfig(StageBudget):
    """Size and settings of the swarm stages (validated on construction; `StageBudget` the sizes)."""

    stage_minutes: float = 2.0  # training flight minutes per swarm stage
    max_neighbours: int = 3  # the models' neighbour slots: every other vehicle of a 4-vehicle scene
    clamp: float = 6.0  # m/s^2, bound on the deployed model's prediction
    minutes_option = "--swarm-minutes"

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 1 <= self.max_neighbours <= 7:
            raise ConfigError(f"max_neighbours: allowed 1-7, got {self.max_neighbours}")

    @property
    def neighbours(self) -> NeighbourSet:
        return NeighbourSet(self.max_neighbours)


def swarm_train_config(seed: int, quick: bool) -> TrainConfig:
    """The schedule of the models of sets (see the module docstring); --quick: a few steps."""
    return train_config(seed, quick) if quick else TrainConfig(seed=seed, max_epochs=20, min_steps=600)


def pair_models_key(cfg: SwarmCollectionConfig, pair_record: dict) -> str:
    """The fingerprint of what the law-free "pair" models depend on: the two-vehicle collection,
    the neighbour set and the training schedule."""
    return fingerprint({"pair": {k: v for k, v in pair_record.items() if k != "code"},
                        "neighbours": cfg.neighbours.describe(),
                        "training": swarm_train_config(cfg.seed, cfg.quick).to_dict()})


def swarm_provenance(cfg: SwarmCollectionConfig, law: Any, pair_record: dict) -> dict:
    """What defines a swarm collection: the two-vehicle collection's record (field, scene, sim,
    controller, ...), the aggregation law and the swarm settings."""
    return {"pair": {k: v for k, v in pair_record.items() if k != "code"}, "aggregation": describe(law),
            "swarm": {"stages": list(SWARM_STAGES), "depth_bands": [list(b) for b in DEPTH_BANDS],
                      "kind_stages": [[name, list(kinds), [list(b) for b in bands]] for name, kinds, bands in KIND_STAGES],
                      "stage_minutes": 0.1 if cfg.quick else cfg.stage_minutes, "seconds": cfg.seconds,
                      "n_train": cfg.n_train, "n_val": cfg.n_val, "neighbours": cfg.neighbours.describe(),
                      "clamp": cfg.clamp, "deployed_kind": DEPLOYED_SWARM_KIND, "seed": cfg.seed,
                      "data": "swarm stage flights that ended early are left out",
                      "training": swarm_train_config(cfg.seed, cfg.quick).to_dict()}}


def swarm_model_path(models_dir: str | Path, kind: str, mix: str) -> Path:
    return Path(models_dir) / f"{kind}-{mix}.pt"


def _stage(cfg: SwarmCollectionConfig, n_vehicles: int) -> Stage:
    """The swarm stage of n vehicles: a hovering leader, follower k in depth band k."""
    return Stage(f"stage{n_vehicles}", LEADER_POSITION, DEPTH_BANDS[:n_vehicles - 1],
                 tuple((cfg.seed, 100 + n_vehicles, k) for k in range(1, n_vehicles)),
                 cfg.seed * 100_000 + 10_000 * n_vehicles, {"stage": n_vehicles})


def _kind_stages(cfg: SwarmCollectionConfig) -> list[Stage]:
    """The stages of other vehicle kinds (`KIND_STAGES`), stage ids 10, 11, ... in the logs."""
    return [Stage(f"kinds-{name}", LEADER_POSITION, bands, tuple((cfg.seed, 200 + i, k) for k in range(1, len(kinds))),
                  cfg.seed * 100_000 + 50_000 + 1_000 * i, {"stage": 10 + i}, kinds)
            for i, (name, kinds, bands) in enumerate(KIND_STAGES)]


def _swarm_dirs(cfg: SwarmCollectionConfig, out: Path, split: str) -> list[Path]:
    """The train or val folders of every swarm stage and stage of other kinds."""
    return [out / f"stage{n}" / split for n in SWARM_STAGES] + [out / st.name / split for st in _kind_stages(cfg)]


def _pair_dirs(pair_collection: Path, split: str) -> list[Path]:
    return [pair_collection / f"stage{k}" / split for k in range(len(STAGES))]


def collect_swarm(
    cfg: SwarmCollectionConfig,
    out: str | Path,
    pair_collection: str | Path,
    pair_model: str | Path,
    pair_record: dict,
    field: Any,
    law: Any,
    pair_models_dir: str | Path,
    progress: ProgressFactory = lambda label: None,
) -> dict:
    """Fly the swarm stages into `out` (resuming) and train the models of every kind and data mix.

    pair_collection: the complete two-vehicle staged collection folder; pair_model: its
    final equivariant checkpoint (flown summed in stage 3); pair_record: its provenance;
    pair_models_dir: where the law-free "pair" models are (trained there when missing; name
    it by `pair_models_key`, so that a folder never holds models of other settings).
    Returns {stages: [...], models: {kind-mix: {path, val_rmse}}, provenance, key}.
    """
    with locked_folder(Path(out), "swarm collection"):
        t0 = time.perf_counter()
        out, pair_collection = Path(out), Path(pair_collection)
        record = swarm_provenance(cfg, law, pair_record)
        manifest_path = out / "manifest.json"
        manifest = open_manifest(out, record, "a swarm collection", models={})
        neighbours = cfg.neighbours

        def fly(stage: Stage, key: str, deployed: Any) -> None:
            """The stage flown with `deployed` where flights are missing, recorded in the manifest's entry `key`."""
            fly_recorded(stage, out / stage.name, manifest["stages"].setdefault(key, {}), cfg.n_train, cfg.n_val,
                         cfg.seconds, collection=str(out), save=lambda: write_manifest(manifest_path, manifest),
                         field=field, predictor=deployed, aggregation=law, batch_flights=cfg.batch_flights,
                         threads=cfg.threads, progress=progress)

        # every vehicle is a target, the leader too: the models of sets fly on every vehicle, so they learn that a
        # set of neighbours all below pushes nothing
        load = CheckedLoader(neighbours, {out: manifest},
                             f"python -m experiments.swarm --collection-dir {pair_collection} "
                             f"(the swarm stages of {out})",
                             targets="all")
        stages = []
        for n_vehicles in SWARM_STAGES:
            if n_vehicles == SWARM_STAGES[0]:
                model = wrap_pairwise(pair_model, neighbours, expect_kind="equivariant")
            else:
                model = swarm_model_path(out / "staged_models", DEPLOYED_SWARM_KIND, "mixed")
            deployed = LearnedPredictor(model, clamp=cfg.clamp)  # bounded as the pair stages' deployed models
            fly(_stage(cfg, n_vehicles), str(n_vehicles), deployed)
            if n_vehicles != SWARM_STAGES[-1]:  # the model the next stage flies with
                path = swarm_model_path(out / "staged_models", DEPLOYED_SWARM_KIND, "mixed")
                if not path.is_file():
                    swarm_dirs = [out / f"stage{n}" / "train" for n in SWARM_STAGES if n <= n_vehicles]
                    data = concatenate([load(_pair_dirs(pair_collection, "train")), load(swarm_dirs, True)])
                    _train(DEPLOYED_SWARM_KIND, data, path, cfg)
            stages.append({"vehicles": n_vehicles, "flights": cfg.n_train + cfg.n_val,
                           "minutes": cfg.n_train * cfg.seconds / 60, "deployed": type(deployed.model).__name__})
        for stage in _kind_stages(cfg):
            fly(stage, stage.name, None)
            stages.append({"vehicles": stage.n_vehicles, "kinds": list(stage.kinds), "flights": cfg.n_train + cfg.n_val,
                           "minutes": cfg.n_train * cfg.seconds / 60, "deployed": None})

        pair_data = load(_pair_dirs(pair_collection, "train"))
        everything = concatenate([pair_data, load(_swarm_dirs(cfg, out, "train"), True)])
        data = {"pair": pair_data, "mixed": everything, "kinds": everything}
        # every model is judged on the same many-vehicle validation flights
        val = load(_swarm_dirs(cfg, out, "val"), True)
        models = {}
        for kind in TRAINABLE_SET_KINDS:
            for mix in DATA_MIXES:
                path = swarm_model_path(Path(pair_models_dir) if mix == "pair" else out / "models", kind, mix)
                # the pair models' folder is every law's: another law's collection may be training there
                with locked_folder(path.parent, "swarm pair models") if mix == "pair" else contextlib.nullcontext():
                    if not path.is_file():
                        _train(kind, data[mix], path, cfg, kinds=mix == "kinds")
                model = load_checkpoint(path, expect_kind=kind).model
                models[f"{kind}-{mix}"] = {"path": str(path), "val_rmse": rmse(model, val)[0]}
        manifest["complete"] = True
        write_manifest(manifest_path, manifest)
        return {"stages": stages, "models": models, "provenance": record, "key": manifest["key"],
                "pair_models_dir": str(pair_models_dir),
                "failed_flights_left_out": {str(d.relative_to(out)): n for d, n in load.skipped.items()
                                            if n and d.is_relative_to(out)},
                "wall_seconds": time.perf_counter() - t0}


def _train(kind: str, data, path: Path, cfg: SwarmCollectionConfig, kinds: bool = False) -> None:
    """Train and save a model of sets (kinds: one that reads the vehicle kinds)."""
    model, history = train_model(kind, data, None, swarm_train_config(cfg.seed, cfg.quick),
                                 **({"kinds": True} if kinds else {}))
    save_trained(path, model, history, data)
