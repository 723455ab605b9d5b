"""What defines a staged collection: its stages, its settings, its provenance record, and the
checks that reuse a folder or a checkpoint only when that record matches.

Provenance. A collection is defined by its `provenance` record: the field, the
scene, the simulator and its components, the collection settings, the training
settings and the seed base (the code version is recorded beside it). The manifest and
every checkpoint carry it, and nothing is reused unless it matches what was asked
for: `pipeline_dirs` gives the default folders, keyed by its fingerprint, so another
field or config collects afresh into its own folder; an explicit folder that holds
something else stops with an error that lists the differences.

The collection itself (flights, training, the manifest) is `downwash.staged`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from controllers.autopilot import Autopilot
from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError, DataError
from downwash_core.provenance import code_version, describe, differences, fingerprint
from downwash.checkpoint import read_metadata
from downwash.guard import guard_settings
from downwash.manifest import MANIFEST_VERSION, read_manifest
from downwash.train import TrainConfig
from sim.logs import SCHEMA_VERSION
from sim.physics import resolve_threads, usable_cores
from sim.scene import build_scene
from sim.simulator import SimConfig
from sim.turbulence import OUTurbulence
from downwash_trajectories import LEMNISCATE_SHARE

__all__ = ["STAGES", "DEPLOYED_KIND", "CollectionConfig", "train_config", "provenance", "pipeline_dirs",
           "check_checkpoint"]

log = logging.getLogger("downwash.staged")  # the collection's logger, as before this module was split off

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


def load_manifest(path: Path, record: dict) -> dict:
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
