"""Conditions of the tracking experiments: what compensates the downwash in each batch of worlds.

Every condition flies the same seeds, so the same motion-capture noise and
turbulence draws: worlds differ only in the predictor (and, for `no_downwash`, in
the field being off).

    no_downwash   the field is off: the controller's own tracking error
    baseline      the LQR with no model (the paper's baseline)
    oracle        the LQR compensating with the true mean field (the best any model can do)
    <model kind>  the LQR compensating with that trained model (`downwash.models.PAIRWISE_KINDS`;
                  the experiments fly `STAGED_KINDS` unless asked, the models with memory on request);
                  <model kind>-<data>: the same kind trained on other data (`experiments.outdoor`)
    <learned>_guarded  the same model behind the guard (`downwash.guard.GuardedPredictor`): scaled
                  toward no model where its inputs leave its training data's support

`guard` ({setting: value}, the keywords of `GuardedPredictor`; None: `GUARD_DEFAULTS`) lets an
experiment fly its guarded conditions with other settings (its config file's [guard] table);
`guard_record` records the settings flown.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash.models import PAIRWISE_KINDS, STAGED_KINDS
from downwash.guard import GuardedPredictor, guard_settings
from downwash.predictor import LearnedPredictor
from sim.flight import fly
from sim.logs import FlightLog
from sim.predictor import OraclePredictor, PerWorldPredictor, Predictor, ZeroPredictor
from sim.scene import Scene
from downwash_trajectories import Reference

__all__ = ["REFERENCE_CONDITIONS", "GUARDED", "CONDITIONS", "DEFAULT_CONDITIONS", "parse_conditions", "learned",
           "data_variant", "guard_record", "make_predictor", "fly_conditions"]

REFERENCE_CONDITIONS = ("no_downwash", "baseline", "oracle")
GUARDED = "_guarded"  # the suffix of a guarded learned condition
# every condition a flight can name
CONDITIONS = REFERENCE_CONDITIONS + tuple(PAIRWISE_KINDS) + tuple(k + GUARDED for k in PAIRWISE_KINDS)
# what the experiments fly unless asked: each staged model, also behind the guard
DEFAULT_CONDITIONS = REFERENCE_CONDITIONS + STAGED_KINDS + tuple(k + GUARDED for k in STAGED_KINDS)


def parse_conditions(text: str) -> list[str]:
    """Condition names from a comma list; ConfigError naming unknown or duplicate ones."""
    names = [c.strip() for c in text.split(",") if c.strip()]
    if not names:
        raise ConfigError(f"--conditions: expected a comma list of {', '.join(CONDITIONS)}, got {text!r}")
    unknown = [c for c in names if c not in CONDITIONS]
    if unknown:
        raise ConfigError(f"--conditions: unknown {unknown}; allowed: {', '.join(CONDITIONS)}")
    if len(set(names)) != len(names):
        raise ConfigError(f"--conditions: duplicate names in {names}")
    return names


def _kind(condition: str) -> str:
    """The model kind of a condition ("<kind>[-<data>][_guarded]")."""
    return condition.removesuffix(GUARDED).partition("-")[0]


def learned(conditions: Sequence[str]) -> list[str]:
    """The model kinds the conditions fly (each once, in order)."""
    return list(dict.fromkeys(_kind(c) for c in conditions if _kind(c) in PAIRWISE_KINDS))


def data_variant(condition: str, data: str) -> str:
    """A learned condition's model trained on other data: "equivariant_guarded", "outdoor" ->
    "equivariant-outdoor_guarded"."""
    guarded = condition.endswith(GUARDED)
    return f"{_kind(condition)}-{data}" + (GUARDED if guarded else "")


def guard_record(conditions: Sequence[str], guard: dict | None = None) -> dict | None:
    """The guard's settings as flown (`downwash.guard.guard_settings`, with `guard`'s values) when a
    condition flies guarded, else None."""
    return {**guard_settings(), **(guard or {})} if any(c.endswith(GUARDED) for c in conditions) else None


def make_predictor(condition: str, field: Any, checkpoints: dict[str, Path], guard: dict | None = None) -> Predictor:
    """The predictor a condition flies with; learned ones load from `checkpoints["<kind>[-<data>]"]`, and
    guarded ones take the `GuardedPredictor` keywords `guard` (None: its defaults)."""
    if condition in ("no_downwash", "baseline"):
        return ZeroPredictor()
    if condition == "oracle":
        return OraclePredictor(field)
    # "<kind>" or "<kind>-<data>" (the same kind trained on other data, e.g. equivariant-outdoor), maybe guarded
    model = condition.removesuffix(GUARDED)
    predictor = LearnedPredictor.from_checkpoint(checkpoints[model], expect_kind=_kind(condition))
    return GuardedPredictor(predictor, **(guard or {})) if condition.endswith(GUARDED) else predictor


def fly_conditions(
    scene: Scene,
    conditions: Sequence[str],
    reference: Reference,
    seeds: Sequence[int],
    duration: float,
    field: Any,
    checkpoints: dict[str, Path],
    meta: dict | None = None,
    guard: dict | None = None,
    **components: Any,
) -> dict[str, list[FlightLog]]:
    """Fly every condition on every seed as one batch of worlds; returns the logs per condition.

    reference: a stacked reference (one per vehicle of `scene`) over len(conditions) x
    len(seeds) worlds, condition-major (world i * K + k is condition i, seed k).
    guard: the guarded conditions' `GuardedPredictor` keywords (None: its defaults).
    components: further `Simulator` keywords shared by every world (e.g. wind, aggregation).
    """
    K = len(seeds)
    predictor = PerWorldPredictor([make_predictor(c, field, checkpoints, guard) for c in conditions],
                                  np.repeat(np.arange(len(conditions)), K))
    field_enabled = np.array([c != "no_downwash" for c in conditions for _ in range(K)])
    world_meta = [{"condition": c, **(meta or {})} for c in conditions for _ in range(K)]
    logs = fly(scene, reference, [s for _ in conditions for s in seeds], duration, field=field,
               predictor=predictor, field_enabled=field_enabled, meta=world_meta, **components)
    return {c: logs[i * K:(i + 1) * K] for i, c in enumerate(conditions)}
