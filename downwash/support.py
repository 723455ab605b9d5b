"""The support of a model's training data: where its inputs lay, for the guard (`downwash.guard`).

Every (neighbour, target) pair a model acts on (the target below the neighbour) is described by
the generalised invariants (`downwash.features`, feature set ``GUARD_FEATURES``: lateral offset,
depth, both vehicles' speeds along and across the neighbour's axis, their angles), whatever the
model's own features. A data set's support (`support_of`) is each feature's range between its
0.1 % and 99.9 % quantiles, with a margin of a quarter of that width beyond which a pair counts as
far from the data (`Support.confidence`). Every checkpoint records it in its data summary
(`downwash.datasets.Dataset.summary`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from downwash.features import FEATURE_SETS, model_inputs

__all__ = ["GUARD_FEATURES", "SUPPORT_QUANTILE", "MARGIN", "DEPTH_COLUMN", "Support", "support_of"]

GUARD_FEATURES = "general"  # the pair description the support is kept in (every model kind alike)
SUPPORT_QUANTILE = 0.001  # each feature's support: its [0.1 %, 99.9 %] quantile range in the training pairs
MARGIN = 0.25  # confidence falls to 0 this fraction of the support's width beyond it
_MARGIN_FLOOR = 1e-3  # (a constant feature gets a margin all the same)
DEPTH_COLUMN = FEATURE_SETS[GUARD_FEATURES].index("depth")


@dataclass(frozen=True)
class Support:
    """Each feature's support (lo, hi) and margin (k,) over ``GUARD_FEATURES`` (module doc)."""

    lo: np.ndarray
    hi: np.ndarray
    margin: np.ndarray

    def __post_init__(self) -> None:
        k = len(FEATURE_SETS[GUARD_FEATURES])
        for name in ("lo", "hi", "margin"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != (k,) or not np.all(np.isfinite(a)):
                raise ConfigError(f"support {name}: expected {k} finite numbers (features "
                                  f"{list(FEATURE_SETS[GUARD_FEATURES])}), got {getattr(self, name)!r}")
            object.__setattr__(self, name, a)
        if not (np.all(self.hi >= self.lo) and np.all(self.margin > 0)):
            raise ConfigError("support: expected hi >= lo and margin > 0 for every feature")

    def confidence(self, x: np.ndarray) -> np.ndarray:
        """(...,) in [0, 1]: 1 inside the support, the product over features of a linear fall to 0
        one margin beyond it, for features x (..., k)."""
        beyond = np.maximum(np.maximum(self.lo - x, x - self.hi), 0.0) / self.margin
        return np.prod(np.clip(1.0 - beyond, 0.0, 1.0), axis=-1)

    def describe(self) -> dict[str, Any]:
        return {"features": list(FEATURE_SETS[GUARD_FEATURES]), "quantile": SUPPORT_QUANTILE,
                "lo": self.lo.tolist(), "hi": self.hi.tolist(), "margin": self.margin.tolist()}

    @classmethod
    def from_record(cls, record: dict) -> "Support":
        if not isinstance(record, dict) or record.get("features") != list(FEATURE_SETS[GUARD_FEATURES]):
            raise ConfigError(f"support: expected a record of the features {list(FEATURE_SETS[GUARD_FEATURES])}, "
                              f"got {record!r:.200}")
        return cls(record["lo"], record["hi"], record["margin"])


def support_of(dp: np.ndarray, v_a: np.ndarray, v_b: np.ndarray, R_a: np.ndarray) -> Support | None:
    """The support of training pairs (dp, v_a, v_b (P, 3), R_a (P, 3, 3)): the pairs with their target
    below the neighbour (those a model acts on); None without any."""
    x = model_inputs(GUARD_FEATURES, dp, v_a, v_b, R_a)[0]
    x = x[x[:, DEPTH_COLUMN] > 0]
    if len(x) < 2:
        return None
    lo, hi = np.quantile(x, [SUPPORT_QUANTILE, 1.0 - SUPPORT_QUANTILE], axis=0)
    return Support(lo, hi, np.maximum(MARGIN * (hi - lo), _MARGIN_FLOOR))
