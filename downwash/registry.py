"""The one registry of model kinds: the per-neighbour models and the models of sets.

A per-neighbour kind (`downwash.models.PAIRWISE_KINDS`) maps one (neighbour, target) pair to
a force and trains on a data set's real pairs; a model of sets (`downwash.set_models.SET_KINDS`)
maps a target's whole padded neighbour set to its force, summed (``summed_pairwise``, a
trained per-neighbour model on every pair) or learned (the deep sets). Training, checkpoints,
the predictor and the experiments take their names from here.
"""

from __future__ import annotations

from typing import Any

from torch import nn

from downwash_core.errors import ConfigError
from downwash.models import PAIRWISE_KINDS
from downwash.set_models import SET_KINDS

__all__ = ["MODEL_KINDS", "PAIRWISE_KINDS", "SET_KINDS", "register", "trainable_kinds", "make_model"]

MODEL_KINDS: dict[str, type[nn.Module]] = {**PAIRWISE_KINDS, **SET_KINDS}


def register(cls: type[nn.Module]) -> type[nn.Module]:
    """Add a model class under its ``kind`` (usable as a class decorator): a `DownwashModel`
    subclass as a per-neighbour kind, a `SetModel` subclass as a model of sets. ConfigError for a
    taken name or another class. Register at the import of the module that defines the class, so
    that forked training processes and checkpoint loading see it too."""
    from downwash.models import DownwashModel
    from downwash.set_models import SetModel

    kind = getattr(cls, "kind", "")
    if not isinstance(cls, type) or not issubclass(cls, (DownwashModel, SetModel)) or not kind:
        raise ConfigError(f"register: expected a DownwashModel or SetModel subclass with a kind, got {cls!r}")
    if MODEL_KINDS.get(kind, cls) is not cls:
        raise ConfigError(f"register: the kind {kind!r} is taken by {MODEL_KINDS[kind].__name__}")
    MODEL_KINDS[kind] = cls
    (PAIRWISE_KINDS if issubclass(cls, DownwashModel) else SET_KINDS)[kind] = cls
    return cls


def trainable_kinds() -> tuple[str, ...]:
    """The registered kinds that `downwash.train.train_model` trains (all but ``summed_pairwise``)."""
    return tuple(kind for kind, cls in MODEL_KINDS.items() if cls.trainable)


def make_model(kind: str, feature_set: str | None = None, **architecture: Any) -> nn.Module:
    """A fresh model of a registered kind (float32, initialised from torch's global RNG).

    feature_set: the kind's own by default ("5" for equivariant, "raw" for the baselines,
      "general" for the equivariant deep sets); architecture: constructor arguments (as
      stored by the model's ``architecture()``; ``summed_pairwise`` needs ``pairwise=``, a
      trained per-neighbour model or its record). ConfigError naming the allowed kinds or
      feature sets, TypeError naming bad architecture arguments.
    """
    if kind not in MODEL_KINDS:
        raise ConfigError(f"model kind: expected one of {sorted(MODEL_KINDS)}, got {kind!r}")
    cls = MODEL_KINDS[kind]
    if feature_set is not None:
        architecture = {"feature_set": feature_set, **architecture}
    try:
        return cls(**architecture)
    except TypeError as e:
        raise TypeError(f"model kind {kind!r}: bad architecture arguments {sorted(architecture)}: {e}") from e
