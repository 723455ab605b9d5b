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
    integral      the LQR with integral action on the position error (`controllers.integral`), no model
    dob           the LQR compensating with a disturbance observer (`sim.observer`), no model
    <learned>_dob the model as feed-forward and the observer on what it misses

The conditions with a controller or predictor of their own kind (`integral`, `dob`, `<learned>_dob`)
fly as a second batch on the simulator's readable path; every world's flight is the same whichever
batch it flies in (`sim.simulator`), so the other conditions keep their fused speed and their bits.

`guard` ({setting: value}, the keywords of `GuardedPredictor`; None: `GUARD_DEFAULTS`) lets an
experiment fly its guarded conditions with other settings (its config file's [guard] table);
`guard_record` records the settings flown.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from controllers.integral import IntegralLQR
from controllers.lqr import FeedbackLinearisedLQR
from controllers.per_world import PerWorldController
from downwash_core.errors import ConfigError
from downwash_core.state import RefSample
from downwash.models import PAIRWISE_KINDS, STAGED_KINDS
from downwash.guard import GuardedPredictor, guard_settings
from downwash.predictor import LearnedPredictor
from sim.flight import fly
from sim.logs import FlightLog
from sim.observer import DisturbanceObserver, bandwidth_for
from sim.predictor import OraclePredictor, PerWorldPredictor, Predictor, ZeroPredictor
from sim.scene import Scene
from downwash_trajectories import Reference

__all__ = ["REFERENCE_CONDITIONS", "UNLEARNED", "GUARDED", "OBSERVED", "CONDITIONS", "DEFAULT_CONDITIONS",
           "parse_conditions", "learned", "data_variant", "guard_record", "make_predictor", "condition_controller",
           "kinds_in_data", "model_of", "fly_conditions", "fly_predictors"]

REFERENCE_CONDITIONS = ("no_downwash", "baseline", "oracle")
UNLEARNED = ("integral", "dob")  # the generic tools a control engineer uses first
GUARDED = "_guarded"  # the suffix of a guarded learned condition
OBSERVED = "_dob"  # the suffix of a learned condition with the disturbance observer on its residual
# every condition a flight can name
CONDITIONS = (REFERENCE_CONDITIONS + UNLEARNED + tuple(PAIRWISE_KINDS) + tuple(k + GUARDED for k in PAIRWISE_KINDS)
              + tuple(k + OBSERVED for k in PAIRWISE_KINDS))
# what the experiments fly unless asked: each staged model, also behind the guard, the non-learned tools and
# each staged model with the observer on its residual
DEFAULT_CONDITIONS = (REFERENCE_CONDITIONS + STAGED_KINDS + tuple(k + GUARDED for k in STAGED_KINDS) + UNLEARNED
                      + tuple(k + OBSERVED for k in STAGED_KINDS))


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


def model_of(condition: str) -> str:
    """A learned condition's model, `<kind>[-<data>]`, with its `_guarded` or `_dob` suffix removed."""
    return condition.removesuffix(GUARDED).removesuffix(OBSERVED)


def _kind(condition: str) -> str:
    """The model kind of a condition (its model's name up to the first `-`)."""
    return model_of(condition).partition("-")[0]


def _readable(condition: str) -> bool:
    """Whether a condition flies a controller or predictor that the fused tick cannot run."""
    return condition in UNLEARNED or condition.endswith(OBSERVED)


def learned(conditions: Sequence[str]) -> list[str]:
    """The model kinds the conditions fly (each once, in order)."""
    return list(dict.fromkeys(_kind(c) for c in conditions if _kind(c) in PAIRWISE_KINDS))


def data_variant(condition: str, data: str) -> str:
    """A learned condition's model trained on other data: "equivariant_guarded", "outdoor" ->
    "equivariant-outdoor_guarded"."""
    suffix = next((x for x in (GUARDED, OBSERVED) if condition.endswith(x)), "")
    return f"{_kind(condition)}-{data}" + suffix


def guard_record(conditions: Sequence[str], guard: dict | None = None) -> dict | None:
    """The guard's settings as flown (`downwash.guard.guard_settings`, with `guard`'s values) when a
    condition flies guarded, else None."""
    return {**guard_settings(), **(guard or {})} if any(c.endswith(GUARDED) for c in conditions) else None


def make_predictor(condition: str, field: Any, checkpoints: dict[str, Path] | None = None, guard: dict | None = None,
                   *, aggregation: Any = None, load: Callable[[str], Predictor] | None = None,
                   controller: Any = None) -> Predictor:
    """The predictor a condition flies with, the one factory every experiment uses. A learned condition's
    model "<kind>[-<data>]" comes from load(model) (default: `checkpoints[model]`, checked to be of its
    kind); guarded ones take the `GuardedPredictor` keywords `guard` (None: its defaults); the oracle
    sums its field under `aggregation` (None: linear); the observer (``dob``, ``<model>_dob``) runs at
    the bandwidth chosen for the flights' `controller` (`sim.observer.bandwidth_for`; None: the LQR)."""
    if condition in ("no_downwash", "baseline", "integral"):
        return ZeroPredictor()
    if condition == "oracle":
        return OraclePredictor(field, aggregation=aggregation)
    if condition == "dob":
        return DisturbanceObserver(bandwidth=bandwidth_for(controller))
    # "<kind>" or "<kind>-<data>" (the same kind trained on other data, e.g. equivariant-outdoor), maybe guarded
    model = model_of(condition)
    predictor = (load(model) if load is not None
                 else LearnedPredictor.from_checkpoint(checkpoints[model], expect_kind=_kind(condition)))
    if condition.endswith(OBSERVED):
        return DisturbanceObserver(predictor, bandwidth=bandwidth_for(controller))
    return GuardedPredictor(predictor, **(guard or {})) if condition.endswith(GUARDED) else predictor


def condition_controller(condition: str, controller: Any = None) -> Any:
    """The controller a condition flies: `controller` (None: the default LQR), or for ``integral`` the LQR
    with integral action and that LQR's weights and limits (ConfigError for another controller)."""
    if condition != "integral":
        return controller
    if controller is not None and type(controller) is not FeedbackLinearisedLQR:
        raise ConfigError(f"the integral condition adds integral action to the LQR; the flight's controller is "
                          f"{type(controller).__name__} (fly it with the LQR, or leave the condition out)")
    return IntegralLQR(controller.config if controller is not None else None)


def kinds_in_data(conditions: Sequence[str], checkpoints: dict[str, Path], vehicle_kinds: Sequence[Any] | Scene
                  ) -> dict[str, bool]:
    """{learned condition: whether its model's training data held every ordered pair of the vehicle kinds (of a
    scene: its vehicles')} (`downwash.support.Support.holds_kinds`, from the checkpoint's support record): the
    guard's promise to keep a gain holds only where they did. A checkpoint without a support record: False."""
    from downwash.checkpoint import read_metadata
    from downwash.features import kind_descriptors
    from downwash.support import Support

    if isinstance(vehicle_kinds, Scene):  # (a scene of paper quads lists no kinds)
        vehicle_kinds = [k.name for k in vehicle_kinds.kinds] or ["paper_quad"] * len(vehicle_kinds.roles)
    descriptors = kind_descriptors(list(vehicle_kinds))
    out = {}
    for c in conditions:
        if c in REFERENCE_CONDITIONS or c in UNLEARNED:
            continue
        record = ((read_metadata(checkpoints[model_of(c)]) or {}).get("data") or {}).get("support")
        out[c] = record is not None and Support.from_record(record).holds_kinds(descriptors)
    return out


class _WorldsOf:
    """The rows `worlds` of a reference over `n_worlds` worlds (its other worlds sampled at the first's time)."""

    def __init__(self, reference: Reference, worlds: np.ndarray, n_worlds: int):
        self.reference, self.worlds, self.n_worlds = reference, worlds, n_worlds

    def __call__(self, t: Any) -> RefSample:
        t = np.broadcast_to(np.asarray(t, dtype=np.float64), (len(self.worlds),))
        full = np.full(self.n_worlds, t[0])
        full[self.worlds] = t
        return RefSample(*(a[self.worlds] for a in self.reference(full)))


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
    """Fly every condition on every seed; returns the logs per condition.

    reference: a stacked reference (one per vehicle of `scene`) over len(conditions) x
    len(seeds) worlds, condition-major (world i * K + k is condition i, seed k).
    guard: the guarded conditions' `GuardedPredictor` keywords (None: its defaults).
    components: further `Simulator` keywords shared by every world (e.g. wind, aggregation, the
    controller). The conditions the fused tick can fly go as one batch, the others as a second
    (module doc).
    """
    predictors = [make_predictor(c, field, checkpoints, guard, controller=components.get("controller"))
                  for c in conditions]
    return fly_predictors(scene, conditions, predictors, reference, seeds, duration, meta=meta, field=field,
                          **components)


def fly_predictors(scene: Scene, conditions: Sequence[str], predictors: Sequence[Predictor], reference: Reference,
                   seeds: Sequence[int], duration: float, meta: dict | None = None,
                   **components: Any) -> dict[str, list[FlightLog]]:
    """`fly_conditions` with each condition's predictor given (`predictors[i]` flies `conditions[i]`; the
    condition still picks the controller: ``integral``'s): the fused-capable conditions as one batch, the
    others as a second (module doc). components: the `Simulator` keywords shared by every world."""
    K, n = len(seeds), len(conditions) * len(seeds)
    logs: dict[str, list[FlightLog]] = {}
    for batch in ([i for i, c in enumerate(conditions) if not _readable(c)],
                  [i for i, c in enumerate(conditions) if _readable(c)]):
        if not batch:
            continue
        names = [conditions[i] for i in batch]
        rows = np.concatenate([np.arange(K) + i * K for i in batch])
        controllers = [condition_controller(c, components.get("controller")) for c in names]
        parts = dict(components)
        if any(c is not components.get("controller") for c in controllers):
            parts["controller"] = PerWorldController(
                [c if c is not None else FeedbackLinearisedLQR() for c in controllers], np.repeat(np.arange(len(batch)), K))
        predictor = PerWorldPredictor([predictors[i] for i in batch], np.repeat(np.arange(len(batch)), K))
        field_enabled = np.array([c != "no_downwash" for c in names for _ in range(K)])
        world_meta = [{"condition": c, **(meta or {})} for c in names for _ in range(K)]
        flown = fly(scene, reference if len(batch) == len(conditions) else _WorldsOf(reference, rows, n),
                    [s for _ in batch for s in seeds], duration, predictor=predictor, field_enabled=field_enabled,
                    meta=world_meta, **parts)
        logs.update({c: flown[j * K:(j + 1) * K] for j, c in enumerate(names)})
    return {c: logs[c] for c in conditions}
