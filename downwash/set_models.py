"""Models of sets: the force on a target from its whole neighbour set.

Every model takes a batch of padded neighbour sets (`downwash.datasets.Dataset`)::

    dp   (B, K, 3)    m     p_target - p_neighbour, world frame (z up)
    v_a  (B, K, 3)    m/s   neighbour velocities
    v_b  (B, 3)       m/s   target velocity
    R_a  (B, K, 3, 3) -     neighbour body-to-world rotations
    mask (B, K)       bool  real neighbours (False: padding, ignored whatever it holds)
    kind_a (B, K, D)  -     the neighbours' vehicle kinds (`downwash.features.KIND_FEATURES`),
    kind_b (B, D)     -     and the target's; optional, default 0 (paper quads)
    hist (B, K, H, 3) m     the neighbours' displacements over `downwash.features.HISTORY_LAGS`;
                            optional, read by a summed per-neighbour model with memory only
    F    (B, 3)       m/s^2 predicted force on the target, world frame

and is invariant to the order of the neighbours (sums over the set) and to padding;
a target without neighbours gets exactly 0. The kinds (`SET_KINDS`; `downwash.registry`
lists them with the per-neighbour kinds):

- ``summed_pairwise``: a trained per-neighbour model (any of `downwash.models.PAIRWISE_KINDS`)
  on each (neighbour, target) pair, summed: the paper's naive multi-vehicle approach
  (its conclusion) and `downwash.predictor.LearnedPredictor`'s law, with the same gate
  (a pair whose target is not below the neighbour, depth <= 0, adds 0). No training.
- ``deepsets_equivariant``: ours. Each neighbour i gives the SO(2)-invariant features
  x_i of `downwash.features` about its own axis and its output basis rows b_i,c
  (radial r_hat_i, axial d_i = -n_i, and tangential t_hat_i for the "general" set).
  phi(x_i) gives a latent z_i and weights a_i,g,c; the set is pooled into invariants
  ``S = sum_i z_i`` and world vectors ``U_g = sum_i sum_c a_i,g,c b_i,c`` (G channels).
  Per neighbour, ``rho(z_i, S, [U_g . b_i,c])`` gives coefficients c_i and
  ``F = sum_i sum_c c_i,c b_i,c``. A rotation Q of the whole configuration about world z
  (indeed any rotation) leaves every x_i, S and U_g . b_i,c unchanged and rotates every
  b_i,c, so F(Q x) = Q F(x); the vector channels let the model see where the other
  neighbours sit relative to each one (the relative azimuth of two wakes), which
  invariants per neighbour alone cannot.
- ``deepsets``: Neural-Swarm2's deep sets on raw world-frame inputs: phi([dp_i, v_i, v_b])
  summed, then rho -> 3 world axes. Not equivariant.

Vehicles of other kinds (``kinds=True``, both deep sets): each neighbour's features also hold
its kind and the target's (`kind_columns`), as Neural-Swarm2's heterogeneous deep sets tell
vehicle types apart (they keep an encoder per type; one encoder that reads the kind serves any
number of kinds, also kinds it interpolates between). The kinds are scalars, which no rotation
changes, so the equivariant model stays equivariant. A model without them (the default) reads
every vehicle as the paper quad.

The deep-sets networks are spectrally normalised as the paper's deep baseline
(`torch.nn.utils.parametrizations.spectral_norm`, largest singular value of each layer
``gamma = 2``). Each holds its input normalisation and output scaling as buffers; the
equivariant one scales its outputs by one scalar, which keeps it equivariant.

Checkpoints (`downwash.checkpoint`) record the neighbour set and the aggregation law a
model of sets was trained for; `downwash.predictor.LearnedPredictor` flies it, by default
as one compiled pass (`downwash.set_fused`), checked against the model's float64 NumPy
twin (`SetModel.numpy_forward`, its network `downwash.numpy_mlp`'s), which is tested against the
torch model.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
import torch
from torch import nn

from downwash_core.errors import ConfigError
from downwash_core.validate import count, positive_float
from downwash.features import (EQUIVARIANT_FEATURE_SETS, FEATURE_SETS, KIND_FEATURES, MEMORY_FEATURE_SETS, N_BASIS, depth,
                               model_inputs)
from downwash.models import (MAX_WIDTH, PAIRWISE_KINDS, DownwashModel, SpectralLinear, count_parameters, layer_widths,
                             settle_spectral_norm)
# the NumPy twins' network, under the names downwash.set_fused takes from here
from downwash.numpy_mlp import numpy_layers as numpy_set_layers
from downwash.numpy_mlp import numpy_mlp as _numpy_mlp

__all__ = ["Encoded", "kind_columns", "SetModel", "SummedPairwise", "DeepSetsEquivariant", "DeepSets", "SET_KINDS"]

_STD_FLOOR = 1e-6  # a feature or output with a smaller spread is left unscaled
RAW_SWARM_FEATURES = ("dp_x", "dp_y", "dp_z", "va_x", "va_y", "va_z", "vb_x", "vb_y", "vb_z")


class Encoded(NamedTuple):
    """Parameter-free model inputs (computed once for a whole data set in training).

    x (B, K, k): per-neighbour features; basis (B, K, n_basis, 3) world-frame output
    rows, or None; mask (B, K) bool: the neighbours that count.
    """

    x: torch.Tensor
    basis: torch.Tensor | None
    mask: torch.Tensor

    def index(self, idx: Any) -> "Encoded":
        """The samples at ``idx`` (index tensor or slice)."""
        return Encoded(self.x[idx], None if self.basis is None else self.basis[idx], self.mask[idx])


def _tensor(a: Any, dtype: torch.dtype) -> torch.Tensor:
    if isinstance(a, np.ndarray) and (not a.flags.writeable or any(st < 0 for st in a.strides)):
        a = np.array(a)  # torch wants writable, positive strides
    return torch.as_tensor(a, dtype=dtype)


def _check_shapes(dp, v_a, v_b, R_a, mask) -> None:
    """ConfigError naming the first input whose shape is not the batched neighbour layout."""
    shapes = {name: tuple(np.shape(a))
              for name, a in (("dp", dp), ("v_a", v_a), ("v_b", v_b), ("R_a", R_a), ("mask", mask))}
    if len(shapes["dp"]) != 3:
        raise ConfigError(f"dp: expected (B, K, 3), got {shapes['dp']}")
    B, K = shapes["dp"][:2]
    want = {"dp": (B, K, 3), "v_a": (B, K, 3), "v_b": (B, 3), "R_a": (B, K, 3, 3), "mask": (B, K)}
    for name, shape in want.items():
        if shapes[name] != shape:
            raise ConfigError(f"{name}: expected {shape} (B, K from dp), got {shapes[name]}")


def kind_columns(kind_a: Any, kind_b: Any, B: int, K: int) -> np.ndarray:
    """(B, K, 2 D) float64: per neighbour slot its kind and the target's (`KIND_FEATURES` each), the
    columns a kind-aware model appends to its features; None stands for paper quads (0)."""
    D = len(KIND_FEATURES)
    a = np.zeros((B, K, D)) if kind_a is None else np.asarray(kind_a, dtype=np.float64)
    b = np.zeros((B, D)) if kind_b is None else np.asarray(kind_b, dtype=np.float64)
    if a.shape != (B, K, D) or b.shape != (B, D):
        raise ConfigError(f"kind_a, kind_b: expected ({B}, {K}, {D}) and ({B}, {D}) (B, K from dp; "
                          f"D = len(KIND_FEATURES)), got {a.shape} and {b.shape}")
    return np.concatenate([a, np.broadcast_to(b[:, None, :], (B, K, D))], -1)


def _floored_std(a: torch.Tensor) -> torch.Tensor:
    std = a.std(0) if a.shape[0] > 1 else torch.ones(a.shape[1:], dtype=a.dtype)
    return torch.where(std > _STD_FLOOR, std, torch.ones_like(std))


def _sn_mlp(widths: Sequence[int], gamma: float) -> nn.Sequential:
    """Spectrally normalised MLP (each layer's largest singular value gamma), ReLU between layers."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
        if i:
            layers.append(nn.ReLU())
        layers.append(SpectralLinear(a, b, gamma))
    return nn.Sequential(*layers)


def _with_kinds(kinds: bool, x: np.ndarray, kind_a: Any, kind_b: Any) -> np.ndarray:
    """x (B, K, k) with the kind columns appended for a model that reads the kinds (NumPy twins)."""
    return np.concatenate([x, kind_columns(kind_a, kind_b, *x.shape[:2])], -1) if kinds else x


def _numpy_inputs(dp, v_a, v_b, R_a, mask) -> tuple[np.ndarray, ...]:
    _check_shapes(dp, v_a, v_b, R_a, mask)
    dp, v_a, v_b, R_a = (np.asarray(a, dtype=np.float64) for a in (dp, v_a, v_b, R_a))
    return dp, v_a, np.broadcast_to(v_b[:, None, :], dp.shape), R_a, np.asarray(mask, dtype=bool)


class SetModel(nn.Module):
    """Common part: the batched call, encode (parameter-free) -> decode (network), description.

    Subclasses set ``kind`` and implement `_features` and `decode`.
    """

    kind: str = ""
    trainable: bool = True
    kinds: bool = False  # whether the model reads the vehicle kinds (module doc)
    # Peak learning rates of the trainable kinds were picked on 3-vehicle flight data (four 30 s
    # flights, a hovering leader and two followers on transects 0.5 and 1.0 m below; two more for
    # validation; the TrainConfig defaults): validation RMSE (m/s^2) at lr 2e-3, 5e-3, 1e-2, 3e-2 was
    # deepsets_equivariant 0.127, 0.119, 0.118, 0.119 and deepsets 0.149, 0.144, 0.146, 0.166
    # (label-noise floor 0.105).
    default_lr: float = 1e-2

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the inputs the model computes in (that of its normalisation buffers)."""
        return next(self.buffers()).dtype

    def _features(self, dp: torch.Tensor, v_a: torch.Tensor, v_b: torch.Tensor, R_a: torch.Tensor, hist: Any):
        """(x (B, K, k), basis or None) of tensors; v_b is broadcast to (B, K, 3); hist (B, K, H, 3) or None."""
        raise NotImplementedError

    def encode(self, dp, v_a, v_b, R_a, mask, kind_a=None, kind_b=None, hist=None) -> Encoded:
        """Features, basis and mask of a batch (module doc for the shapes), in the model's dtype."""
        _check_shapes(dp, v_a, v_b, R_a, mask)
        dtype = self.dtype
        B, K = np.shape(mask)
        columns = kind_columns(kind_a, kind_b, B, K) if self.kinds else None  # checked before any work
        dp, v_a, v_b, R_a = (_tensor(a, dtype) for a in (dp, v_a, v_b, R_a))
        mask = _tensor(mask, torch.bool)
        x, basis = self._features(dp, v_a, v_b[:, None, :].expand_as(dp), R_a, None if hist is None else _tensor(hist, dtype))
        if columns is not None:
            x = torch.cat([x, _tensor(columns, dtype)], -1)
        return Encoded(x, basis, mask)

    def decode(self, enc: Encoded) -> torch.Tensor:
        """Force on each target (B, 3) m/s^2, world frame."""
        raise NotImplementedError

    def forward(self, dp, v_a, v_b, R_a, mask, kind_a=None, kind_b=None, hist=None) -> torch.Tensor:
        """Predicted force on each target (B, 3) m/s^2 (see the module doc)."""
        return self.decode(self.encode(dp, v_a, v_b, R_a, mask, kind_a, kind_b, hist))

    def fit_normalization(self, enc: Encoded, y: torch.Tensor) -> None:
        """Set the normalisation buffers from training inputs and labels y (B, 3) m/s^2."""

    def architecture(self) -> dict[str, Any]:
        """Constructor arguments that rebuild this architecture (JSON-serialisable)."""
        return {}

    def normalization(self) -> dict[str, list[float]]:
        return {}

    def describe(self) -> dict[str, Any]:
        """Kind, architecture and parameter count (JSON-serialisable)."""
        return {"kind": self.kind, "architecture": self.architecture(), "n_parameters": count_parameters(self)}

    def numpy_forward(self) -> Callable[..., np.ndarray]:
        """The model as a float64 NumPy function ``f(dp, v_a, v_b, R_a, mask, kind_a=None, kind_b=None,
        hist=None) -> F (B, 3)`` (the inputs of `forward`): the weights as they are now (eval mode), copied. The predictor's
        default path: a few hundred microseconds less per call than torch's per-operation cost."""
        raise NotImplementedError

    def spectral_layers(self) -> list[SpectralLinear]:
        return [m for m in self.modules() if isinstance(m, SpectralLinear)]

    def settle_spectral_norm(self) -> None:
        """Power iterations to convergence, so eval mode bounds every layer exactly (see `DeepSNMLP`)."""
        settle_spectral_norm(self)

    # -- the trainer's protocol (`downwash.train`): the same three steps for every kind -----------
    def encode_samples(self, data: Any) -> tuple[Encoded, torch.Tensor]:
        """(encoding, labels (B, 3)) of the padded neighbour sets of a `Dataset`."""
        with torch.no_grad():
            enc = self.encode(data.dp, data.v_a, data.v_b, data.R_a, data.mask, data.kind_a, data.kind_b,
                              getattr(data, "hist", None))
        return enc, torch.as_tensor(np.asarray(data.y), dtype=enc.x.dtype)

    def fit_samples(self, enc: Encoded, y: torch.Tensor) -> None:
        """The normalisation fitted on a training encoding and its labels."""
        self.fit_normalization(enc, y)

    def decode_samples(self, enc: Encoded) -> torch.Tensor:
        """Predictions (B, 3) m/s^2 on an encoding."""
        return self.decode(enc)


class SummedPairwise(SetModel):
    """A two-vehicle model applied to each (neighbour, target) pair and summed (masked).

    pairwise: a `DownwashModel` (used as is, not copied), or the record of one
      (``{"kind", "feature_set", "architecture", "dtype"}``) to rebuild with fresh weights
      before a state dict is loaded. A pair whose target is not below its neighbour
      (depth ``-(dp . n) <= 0``) adds 0, as in `LearnedPredictor`.
    """

    kind = "summed_pairwise"
    trainable = False
    default_lr = 0.0

    def __init__(self, pairwise: DownwashModel | dict):
        super().__init__()
        if isinstance(pairwise, dict):
            pairwise = _rebuild_pairwise(pairwise)
        if not isinstance(pairwise, DownwashModel):
            raise ConfigError(f"pairwise: expected a DownwashModel or its record, got {type(pairwise).__name__}")
        self.pairwise = pairwise

    def encode(self, dp, v_a, v_b, R_a, mask, kind_a=None, kind_b=None, hist=None) -> Encoded:
        enc = super().encode(dp, v_a, v_b, R_a, mask, hist=hist)  # a per-neighbour model reads no kinds
        below = depth(_tensor(dp, self.dtype), _tensor(R_a, self.dtype)) > 0
        return Encoded(enc.x, enc.basis, enc.mask & below)

    def _features(self, dp, v_a, v_b, R_a, hist):
        return model_inputs(self.pairwise.feature_set, dp, v_a, v_b, R_a, hist if self.pairwise.memory else None)

    def decode(self, enc: Encoded) -> torch.Tensor:
        f = self.pairwise.decode(enc.x, enc.basis)  # (B, K, 3)
        return torch.where(enc.mask[..., None], f, 0.0).sum(1)

    def numpy_forward(self) -> Callable[..., np.ndarray]:
        pairs = self.pairwise.numpy_forward()  # its float64 pair law, depth gate included

        def forward(dp, v_a, v_b, R_a, mask, kind_a=None, kind_b=None, hist=None):  # the kinds: not read
            _check_shapes(dp, v_a, v_b, R_a, mask)
            B, K = np.shape(mask)
            f = pairs(np.reshape(dp, (B * K, 3)), np.reshape(v_a, (B * K, 3)),
                      np.repeat(np.asarray(v_b, dtype=np.float64), K, axis=0), np.reshape(R_a, (B * K, 3, 3)),
                      None if hist is None else np.reshape(hist, (B * K, *np.shape(hist)[2:])))
            return np.where(np.asarray(mask)[..., None], f.reshape(B, K, 3), 0.0).sum(1)

        return forward

    def architecture(self) -> dict[str, Any]:
        p = self.pairwise
        return {"pairwise": {"kind": p.kind, "feature_set": p.feature_set, "architecture": p.architecture(),
                             "dtype": str(p.in_mean.dtype).replace("torch.", "")}}

    def normalization(self) -> dict[str, list[float]]:
        return self.pairwise.normalization()


def _rebuild_pairwise(record: dict) -> DownwashModel:
    kind = record.get("kind")
    if kind not in PAIRWISE_KINDS:
        raise ConfigError(f"pairwise kind: expected one of {sorted(PAIRWISE_KINDS)}, got {kind!r}")
    architecture = dict(record.get("architecture") or {})
    try:
        model = PAIRWISE_KINDS[kind](record.get("feature_set"), **architecture)
    except TypeError as e:
        raise TypeError(f"pairwise kind {kind!r}: bad architecture arguments {sorted(architecture)}: {e}") from e
    return model.double() if record.get("dtype") == "float64" else model


class _DeepSetsBase(SetModel):
    """Input normalisation (k,) of the per-neighbour features, fitted over real neighbours only."""

    def __init__(self, n_features: int, kinds: bool = False):
        super().__init__()
        if not isinstance(kinds, bool):
            raise ConfigError(f"kinds: expected True or False (whether the model reads the vehicle kinds), got {kinds!r}")
        self.kinds = kinds
        n_features += 2 * len(KIND_FEATURES) if kinds else 0
        self.n_features = n_features
        self.register_buffer("in_mean", torch.zeros(n_features))
        self.register_buffer("in_std", torch.ones(n_features))

    def _normalised(self, enc: Encoded) -> torch.Tensor:
        """(x - mean) / std, 0 in padding (so padding never reaches a sum, whatever it holds)."""
        return torch.where(enc.mask[..., None], (enc.x - self.in_mean) / self.in_std, 0.0)

    @torch.no_grad()
    def fit_normalization(self, enc: Encoded, y: torch.Tensor) -> None:
        real = enc.x[enc.mask]
        if real.shape[0] >= 2:
            self.in_mean.copy_(real.mean(0))
            self.in_std.copy_(_floored_std(real))
        self._fit_output(torch.as_tensor(y, dtype=self.in_mean.dtype))

    def _fit_output(self, y: torch.Tensor) -> None:
        raise NotImplementedError

    def normalization(self) -> dict[str, list[float]]:
        return {name: buf.tolist() for name, buf in self.named_buffers() if "." not in name}


class DeepSetsEquivariant(_DeepSetsBase):
    """Deep sets on each neighbour's invariant features, with an equivariant output (module doc).

    feature_set: one of `features.EQUIVARIANT_FEATURE_SETS` ("general": 10 features and
      three basis rows, default; "5", "6": the paper's, two rows).
    phi_hidden, latent: phi's hidden widths and its invariant latent size L.
    vectors: G, the pooled world-vector channels.
    rho_hidden: rho's hidden widths; rho maps (z_i, S, U . b_i) (2 L + G n_basis) to n_basis.
    gamma: largest singular value of every layer.
    kinds: read the vehicle kinds (`kind_columns`: 2 D more features per neighbour).
    Buffers: in_mean, in_std (k,) of the features; out_scale (1,) m/s^2, one scalar for
    every output channel (keeps the model equivariant).
    """

    kind = "deepsets_equivariant"

    def __init__(self, feature_set: str = "general", phi_hidden: Sequence[int] = (32, 32), latent: int = 16,
                 vectors: int = 4, rho_hidden: Sequence[int] = (32, 32), gamma: float = 2.0, kinds: bool = False):
        allowed = [f for f in EQUIVARIANT_FEATURE_SETS if f not in MEMORY_FEATURE_SETS]
        if feature_set not in allowed:
            raise ConfigError(f"feature_set: {self.kind!r} accepts {allowed}, got {feature_set!r}")
        super().__init__(len(FEATURE_SETS[feature_set]), kinds)
        self.feature_set = feature_set
        self.n_basis = N_BASIS[feature_set]
        self.phi_hidden, self.rho_hidden = layer_widths("phi_hidden", phi_hidden), layer_widths("rho_hidden", rho_hidden)
        self.latent, self.vectors = count("latent", latent, 1, MAX_WIDTH), count("vectors", vectors, 1, MAX_WIDTH)
        self.gamma = positive_float("gamma", gamma, "(largest singular value)")
        nb = self.n_basis
        self.phi = _sn_mlp([self.n_features, *self.phi_hidden, self.latent + self.vectors * nb], self.gamma)
        self.rho = _sn_mlp([2 * self.latent + self.vectors * nb, *self.rho_hidden, nb], self.gamma)
        self.register_buffer("out_scale", torch.ones(1))
        self.settle_spectral_norm()

    def _features(self, dp, v_a, v_b, R_a, hist):  # the history: not read
        return model_inputs(self.feature_set, dp, v_a, v_b, R_a)

    def decode(self, enc: Encoded) -> torch.Tensor:
        m = enc.mask[..., None]
        B, K = enc.mask.shape
        L, G, nb = self.latent, self.vectors, self.n_basis
        basis = torch.where(m[..., None], enc.basis, 0.0)  # (B, K, nb, 3)
        h = torch.where(m, self.phi(self._normalised(enc)), 0.0)
        z, a = h[..., :L], h[..., L:].reshape(B, K, G, nb)
        pooled = z.sum(1)  # (B, L) invariant
        vec = torch.einsum("bkgc,bkcj->bgj", a, basis)  # (B, G, 3) world vectors: rotate with the configuration
        seen = torch.einsum("bgj,bkcj->bkgc", vec, basis).reshape(B, K, G * nb)  # invariant in each frame
        coef = self.rho(torch.cat([z, pooled[:, None, :].expand(B, K, L), seen], -1)) * self.out_scale
        return torch.einsum("bkc,bkcj->bj", torch.where(m, coef, 0.0), basis)

    def numpy_forward(self) -> Callable[..., np.ndarray]:
        phi, rho = numpy_set_layers(self.phi), numpy_set_layers(self.rho)
        mean, std = self.in_mean.double().numpy().copy(), self.in_std.double().numpy().copy()
        scale, L, G, nb, feature_set = float(self.out_scale), self.latent, self.vectors, self.n_basis, self.feature_set
        kinds = self.kinds

        def forward(dp, v_a, v_b, R_a, mask, kind_a=None, kind_b=None, hist=None):  # decode, step for step
            dp, v_a, v_b, R_a, mask = _numpy_inputs(dp, v_a, v_b, R_a, mask)
            B, K = mask.shape
            x, basis = model_inputs(feature_set, dp, v_a, v_b, R_a)
            x = _with_kinds(kinds, x, kind_a, kind_b)
            m = mask[..., None]
            basis = np.where(m[..., None], basis, 0.0)
            h = np.where(m, _numpy_mlp(phi, np.where(m, (x - mean) / std, 0.0)), 0.0)
            z, a = h[..., :L], h[..., L:].reshape(B, K, G, nb)
            rows = basis.reshape(B, K * nb, 3)  # the einsums of decode as batched matrix products
            vec = a.transpose(0, 2, 1, 3).reshape(B, G, K * nb) @ rows  # (B, G, 3)
            seen = (rows @ vec.transpose(0, 2, 1)).reshape(B, K, nb, G).transpose(0, 1, 3, 2).reshape(B, K, G * nb)
            pooled = np.broadcast_to(z.sum(1)[:, None, :], (B, K, L))
            coef = _numpy_mlp(rho, np.concatenate([z, pooled, seen], -1)) * scale
            return (np.where(m, coef, 0.0).reshape(B, 1, K * nb) @ rows)[:, 0]

        return forward

    def _fit_output(self, y: torch.Tensor) -> None:
        rms = torch.sqrt(torch.mean(y**2))  # one scalar for every channel keeps the model equivariant
        self.out_scale.fill_(float(rms) if float(rms) > _STD_FLOOR else 1.0)

    def architecture(self) -> dict[str, Any]:
        return {"feature_set": self.feature_set, "phi_hidden": list(self.phi_hidden), "latent": self.latent,
                "vectors": self.vectors, "rho_hidden": list(self.rho_hidden), "gamma": self.gamma,
                **({"kinds": True} if self.kinds else {})}  # (a kind-blind model's record as before kinds existed)


class DeepSets(_DeepSetsBase):
    """Neural-Swarm2's deep sets: ``rho(sum_i phi([dp_i, v_i, v_b]))`` -> 3 world axes (not equivariant).

    Buffers: in_mean, in_std (9,); out_mean, out_std (3,) m/s^2 per world axis.
    A target with no neighbour gets 0 (rho of the empty sum is not used).
    """

    kind = "deepsets"
    default_lr = 5e-3

    def __init__(self, phi_hidden: Sequence[int] = (48, 48), latent: int = 24, rho_hidden: Sequence[int] = (48, 48),
                 gamma: float = 2.0, kinds: bool = False):
        super().__init__(len(RAW_SWARM_FEATURES), kinds)
        self.phi_hidden, self.rho_hidden = layer_widths("phi_hidden", phi_hidden), layer_widths("rho_hidden", rho_hidden)
        self.latent = count("latent", latent, 1, MAX_WIDTH)
        self.gamma = positive_float("gamma", gamma, "(largest singular value)")
        self.phi = _sn_mlp([self.n_features, *self.phi_hidden, self.latent], self.gamma)
        self.rho = _sn_mlp([self.latent, *self.rho_hidden, 3], self.gamma)
        self.register_buffer("out_mean", torch.zeros(3))
        self.register_buffer("out_std", torch.ones(3))
        self.settle_spectral_norm()

    def _features(self, dp, v_a, v_b, R_a, hist):  # the history: not read
        return torch.cat([dp, v_a, v_b], -1), None

    def decode(self, enc: Encoded) -> torch.Tensor:
        pooled = torch.where(enc.mask[..., None], self.phi(self._normalised(enc)), 0.0).sum(1)
        out = self.rho(pooled) * self.out_std + self.out_mean
        return torch.where(enc.mask.any(1, keepdim=True), out, 0.0)

    def numpy_forward(self) -> Callable[..., np.ndarray]:
        phi, rho = numpy_set_layers(self.phi), numpy_set_layers(self.rho)
        mean, std, out_mean, out_std = (getattr(self, k).double().numpy().copy()
                                        for k in ("in_mean", "in_std", "out_mean", "out_std"))
        kinds = self.kinds

        def forward(dp, v_a, v_b, R_a, mask, kind_a=None, kind_b=None, hist=None):  # decode, step for step
            dp, v_a, v_b, R_a, mask = _numpy_inputs(dp, v_a, v_b, R_a, mask)
            m = mask[..., None]
            x = _with_kinds(kinds, np.concatenate([dp, v_a, v_b], -1), kind_a, kind_b)
            xn = np.where(m, (x - mean) / std, 0.0)
            pooled = np.where(m, _numpy_mlp(phi, xn), 0.0).sum(1)
            out = _numpy_mlp(rho, pooled) * out_std + out_mean
            return np.where(mask.any(1)[:, None], out, 0.0)

        return forward

    def _fit_output(self, y: torch.Tensor) -> None:
        self.out_mean.copy_(y.mean(0))
        self.out_std.copy_(_floored_std(y))

    def architecture(self) -> dict[str, Any]:
        return {"phi_hidden": list(self.phi_hidden), "latent": self.latent, "rho_hidden": list(self.rho_hidden),
                "gamma": self.gamma, **({"kinds": True} if self.kinds else {})}


# The models of sets; `downwash.registry.MODEL_KINDS` lists them with the per-neighbour kinds.
SET_KINDS: dict[str, type[SetModel]] = {
    "summed_pairwise": SummedPairwise,
    "deepsets_equivariant": DeepSetsEquivariant,
    "deepsets": DeepSets,
}
