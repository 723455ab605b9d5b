"""The support of a model's training data: where its inputs lay, for the guard (`downwash.guard`).

Every (neighbour, target) pair a model acts on (the target below the neighbour) is described by
the generalised invariants (`downwash.features`, feature set ``GUARD_FEATURES``: lateral offset,
depth, both vehicles' speeds along and across the neighbour's axis, their angles), whatever the
model's own features, and by both vehicles' kinds (`downwash.features.KIND_FEATURES`, 0 for the
paper quad): a model trained on paper quads alone has never seen a heavier wake or a lighter
target, even at a familiar offset. A data set's support (`support_of`) is each feature's range
between its 0.1 % and 99.9 % quantiles, with a margin of a quarter of that width beyond which a
pair counts as far from the data (`Support.confidence`); a feature the data holds constant (the
kinds of paper-quad data) gets a margin of 0.001 all the same. Every checkpoint records it in its data summary
(`downwash.datasets.Dataset.summary`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from downwash.features import FEATURE_SETS, KIND_FEATURES, model_inputs

__all__ = ["GUARD_FEATURES", "SUPPORT_FEATURES", "SUPPORT_QUANTILE", "MARGIN", "DEPTH_COLUMN", "Support", "support_of",
           "support_inputs"]

GUARD_FEATURES = "general"  # the pair description the support is kept in (every model kind alike)
SUPPORT_QUANTILE = 0.001  # each feature's support: its [0.1 %, 99.9 %] quantile range in the training pairs
MARGIN = 0.25  # confidence falls to 0 this fraction of the support's width beyond it
_MARGIN_FLOOR = 1e-3  # (a constant feature gets a margin all the same)
DEPTH_COLUMN = FEATURE_SETS[GUARD_FEATURES].index("depth")
SUPPORT_FEATURES = (*FEATURE_SETS[GUARD_FEATURES], *(f"neighbour_{k}" for k in KIND_FEATURES),
                    *(f"target_{k}" for k in KIND_FEATURES))  # what a pair is described by


@dataclass(frozen=True)
class Support:
    """Each feature's support (lo, hi) and margin (k,) over ``SUPPORT_FEATURES`` (module doc)."""

    lo: np.ndarray
    hi: np.ndarray
    margin: np.ndarray

    def __post_init__(self) -> None:
        k = len(SUPPORT_FEATURES)
        for name in ("lo", "hi", "margin"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != (k,) or not np.all(np.isfinite(a)):
                raise ConfigError(f"support {name}: expected {k} finite numbers (features "
                                  f"{list(SUPPORT_FEATURES)}), got {getattr(self, name)!r}")
            object.__setattr__(self, name, a)
        if not (np.all(self.hi >= self.lo) and np.all(self.margin > 0)):
            raise ConfigError("support: expected hi >= lo and margin > 0 for every feature")

    def confidence(self, x: np.ndarray) -> np.ndarray:
        """(...,) in [0, 1]: 1 inside the support, the product over features of a linear fall to 0
        one margin beyond it, for features x (..., k)."""
        return np.prod(self._terms(x), axis=-1)

    def kind_confidence(self, x: np.ndarray) -> np.ndarray:
        """(...,) in [0, 1]: ``confidence`` over the kind features alone (the last 2 x
        len(KIND_FEATURES) of ``SUPPORT_FEATURES``): whether the data held these vehicle kinds."""
        return np.prod(self._terms(x)[..., -2 * len(KIND_FEATURES):], axis=-1)

    def holds_kinds(self, descriptors: np.ndarray) -> bool:
        """Whether the data held every ordered pair of these vehicles' kinds (descriptors (V, len(KIND_FEATURES)),
        `downwash.features.kind_descriptors`), each as neighbour and target: full `kind_confidence` for all."""
        d = np.asarray(descriptors, dtype=np.float64)
        a, b = np.meshgrid(np.arange(len(d)), np.arange(len(d)), indexing="ij")
        pairs = (a != b) if len(d) > 1 else np.ones_like(a, dtype=bool)
        x = np.zeros((int(pairs.sum()), len(self.lo)))
        x[:, -2 * d.shape[1]:] = np.concatenate([d[a[pairs]], d[b[pairs]]], axis=-1)
        return bool(np.all(self.kind_confidence(x) == 1.0))

    def _terms(self, x: np.ndarray) -> np.ndarray:
        """(..., k): each feature's factor of the confidence, clip(1 - beyond / margin, 0, 1)."""
        beyond = np.maximum(np.maximum(self.lo - x, x - self.hi), 0.0) / self.margin
        return np.clip(1.0 - beyond, 0.0, 1.0)

    def describe(self) -> dict[str, Any]:
        return {"features": list(SUPPORT_FEATURES), "quantile": SUPPORT_QUANTILE,
                "lo": self.lo.tolist(), "hi": self.hi.tolist(), "margin": self.margin.tolist()}

    @classmethod
    def from_record(cls, record: dict) -> "Support":
        if not isinstance(record, dict) or record.get("features") != list(SUPPORT_FEATURES):
            raise ConfigError(f"support: expected a record of the features {list(SUPPORT_FEATURES)}, got "
                              f"{record!r:.200} (a checkpoint made by older code: retrain it)")
        return cls(record["lo"], record["hi"], record["margin"])


def support_inputs(dp: np.ndarray, v_a: np.ndarray, v_b: np.ndarray, R_a: np.ndarray, kind_a: np.ndarray | None = None,
                   kind_b: np.ndarray | None = None) -> np.ndarray:
    """(..., len(SUPPORT_FEATURES)): pairs (dp, v_a, v_b (..., 3), R_a (..., 3, 3)) and the
    neighbour's and target's kinds (kind_a, kind_b (..., len(KIND_FEATURES)); None: paper quads)
    as the support describes them."""
    x = model_inputs(GUARD_FEATURES, dp, v_a, v_b, R_a)[0]
    shape = (*x.shape[:-1], len(KIND_FEATURES))
    kinds = [np.zeros(shape) if k is None else np.broadcast_to(k, shape) for k in (kind_a, kind_b)]
    return np.concatenate([x, *kinds], axis=-1)


def support_of(dp: np.ndarray, v_a: np.ndarray, v_b: np.ndarray, R_a: np.ndarray, kind_a: np.ndarray | None = None,
               kind_b: np.ndarray | None = None) -> Support | None:
    """The support of training pairs (dp, v_a, v_b (P, 3), R_a (P, 3, 3); the neighbour's and
    target's kinds kind_a, kind_b (P, len(KIND_FEATURES)), None: paper quads): the pairs with their
    target below the neighbour (those a model acts on); None without any."""
    x = support_inputs(dp, v_a, v_b, R_a, kind_a, kind_b)
    x = x[x[:, DEPTH_COLUMN] > 0]
    if len(x) < 2:
        return None
    lo, hi = np.quantile(x, [SUPPORT_QUANTILE, 1.0 - SUPPORT_QUANTILE], axis=0)
    return Support(lo, hi, np.maximum(MARGIN * (hi - lo), _MARGIN_FLOOR))
