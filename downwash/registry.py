"""The one registry of model kinds: the per-neighbour models and the models of sets.

A per-neighbour kind (`downwash.models.PAIRWISE_KINDS`) maps one (neighbour, target) pair to
a force and trains on a data set's real pairs; a model of sets (`downwash.set_models.SET_KINDS`)
maps a target's whole padded neighbour set to its force, summed (``summed_pairwise``, a
trained per-neighbour model on every pair) or learned (the deep sets). Training, checkpoints,
the predictor and the experiments take their names from here. `MODEL_KINDS` is a
`downwash_core.registry.Registry` of the classes (each kind's constructor parameters listed);
a plugin adds a kind through `register`, as a module does.
"""

from __future__ import annotations

import inspect
import re
from typing import Any

from torch import nn

from downwash_core.errors import ConfigError
from downwash_core.registry import Registry
from downwash.models import PAIRWISE_KINDS
from downwash.set_models import SET_KINDS

__all__ = ["MODEL_KINDS", "PAIRWISE_KINDS", "SET_KINDS", "register", "trainable_kinds", "make_model"]

# kind -> model class (a `downwash_core.registry.Registry` of objects: MODEL_KINDS[kind] is the class)
MODEL_KINDS = Registry("model", label="model kind", group="models", objects=True,
                       name_rule="lowercase letters, digits, '-' and '_'")


@MODEL_KINDS.adder
def register(cls: type[nn.Module]) -> type[nn.Module]:
    """Add a model class under its ``kind`` (usable as a class decorator): a `DownwashModel`
    subclass as a per-neighbour kind, a `SetModel` subclass as a model of sets. ConfigError for a
    taken name or another class. Register at the import of the module that defines the class, so
    that forked training processes and checkpoint loading see it too (or in a plugin)."""
    from downwash.models import DownwashModel
    from downwash.set_models import SetModel

    kind = getattr(cls, "kind", "")
    if not isinstance(cls, type) or not issubclass(cls, (DownwashModel, SetModel)) or not kind:
        raise ConfigError(f"register: expected a DownwashModel or SetModel subclass with a kind, got {cls!r}")
    taken = MODEL_KINDS.peek(kind)
    if taken is not None and taken.obj is not cls:
        raise ConfigError(f"register: the kind {kind!r} is taken by {taken.obj.__name__}")
    if taken is None:
        first = " ".join((inspect.getdoc(cls) or kind).split("\n\n")[0].split())  # the doc's first sentence
        MODEL_KINDS.register(kind, cls, re.split(r"(?<=\.)\s+(?=[A-Z])", first, maxsplit=1)[0])
        (PAIRWISE_KINDS if issubclass(cls, DownwashModel) else SET_KINDS)[kind] = cls
    return cls


for _cls in (*PAIRWISE_KINDS.values(), *SET_KINDS.values()):
    register(_cls)


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
    cls = MODEL_KINDS[kind]  # ConfigError naming the registered kinds
    if feature_set is not None:
        architecture = {"feature_set": feature_set, **architecture}
    try:
        return cls(**architecture)
    except TypeError as e:
        raise TypeError(f"model kind {kind!r}: bad architecture arguments {sorted(architecture)}: {e}") from e
