"""The per-neighbour downwash models (paper sections 4 and 5.D): one equivariant, two baselines.

A per-neighbour model maps one (neighbour, target) pair to the force the neighbour's wake
puts on the target (the models with memory, `EquivariantMemoryModel` and `DeepMemoryModel`, also
read the neighbour's recent past, ``hist (..., H, 3)``: `downwash.features.HISTORY_LAGS`);
`downwash.set_models.SummedPairwise` sums it over a neighbour set, and `downwash.registry` lists these kinds beside the models of sets. All share one call,
``model(dp, v_a, v_b, R_a, hist=None) -> F``:

    dp  (..., 3)    m     follower minus leader position, world frame (z up)
    v_a (..., 3)    m/s   leader velocity, world frame
    v_b (..., 3)    m/s   follower velocity, world frame
    R_a (..., 3, 3) -     leader body-to-world rotation
    F   (..., 3)    m/s^2 predicted downwash acceleration on the follower, world frame

Inputs are computed in `downwash.features` (the only place). Every model holds
its input normalisation (mean/std of its own features) and an output scaling as
buffers, so they travel in the state dict. For the equivariant model the output
scaling acts on its invariant outputs (radial and NED-down, plus tangential for the
generalised model), one scalar each,
which keeps the model exactly equivariant.

float32 by default; ``.double()`` gives a float64 model (used by the property tests).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
import torch
from torch import nn
from torch.nn.utils.parametrizations import spectral_norm

from downwash_core.errors import ConfigError
from downwash_core.validate import count

from downwash.features import (FEATURE_SETS, MEMORY_FEATURE_SETS, assemble, depth, model_inputs,
                               project_onto_basis)
from downwash_core.numerics import matmul_rows

__all__ = [
    "DownwashModel",
    "PairEncoded",
    "EquivariantModel",
    "GeneralEquivariantModel",
    "ShallowMLP",
    "DeepSNMLP",
    "EquivariantMemoryModel",
    "DeepMemoryModel",
    "PAIRWISE_KINDS",
    "STAGED_KINDS",
    "count_parameters",
    "settle_spectral_norm",
    "MAX_WIDTH",
]

_STD_FLOOR = 1e-6  # a feature or output with a smaller spread is left unscaled
MAX_WIDTH = 4096  # the widest layer a model (or a checkpoint's record of one) may ask for
_ZERO = np.zeros(())  # 0-d: cheaper per NumPy call than a Python float


def count_parameters(model: nn.Module) -> int:
    """Number of trainable scalars (buffers such as normalisation are not counted)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


class PairEncoded(NamedTuple):
    """Parameter-free inputs of a per-neighbour model for a whole data set (computed once in
    training): x (P, k) features, basis (P, m, 3) output rows or None."""

    x: torch.Tensor
    basis: torch.Tensor | None

    def index(self, idx: Any) -> "PairEncoded":
        """The samples at ``idx`` (index tensor or slice)."""
        return PairEncoded(self.x[idx], None if self.basis is None else self.basis[idx])


class DownwashModel(nn.Module):
    """Common part: feature set, normalisation buffers, the shared forward signature.

    Subclasses set ``kind``, ``ALLOWED_FEATURE_SETS``, ``DEFAULT_FEATURE_SET``,
    ``n_outputs`` and build ``self.net`` (normalised features -> normalised outputs).

    Buffers (all in the state dict):
      in_mean, in_std (k,)   mean and std of the k input features (their units)
      out_mean, out_std (m,) output scaling, m/s^2: world axes (m = 3) for the
                             baselines, (radial, NED-down) (m = 2) for the equivariant model
    """

    kind: str = ""
    ALLOWED_FEATURE_SETS: tuple[str, ...] = ()
    DEFAULT_FEATURE_SET: str = ""
    n_outputs: int = 3
    trainable: bool = True
    default_lr: float = 1e-2  # peak Adam learning rate of `downwash.train` (each kind sets its own)

    def __init__(self, feature_set: str | None = None):
        super().__init__()
        feature_set = self.DEFAULT_FEATURE_SET if feature_set is None else str(feature_set)
        if feature_set not in self.ALLOWED_FEATURE_SETS:
            raise ConfigError(
                f"feature_set: model kind {self.kind!r} accepts {list(self.ALLOWED_FEATURE_SETS)}, got {feature_set!r}"
            )
        self.feature_set = feature_set
        k = len(FEATURE_SETS[feature_set])
        self.n_features = k
        self.register_buffer("in_mean", torch.zeros(k))
        self.register_buffer("in_std", torch.ones(k))
        self.register_buffer("out_mean", torch.zeros(self.n_outputs))
        self.register_buffer("out_std", torch.ones(self.n_outputs))

    @property
    def memory(self) -> bool:
        """Whether the model reads the neighbour's history (``hist``, `downwash.features.HISTORY_LAGS`)."""
        return self.feature_set in MEMORY_FEATURE_SETS

    # -- the pipeline: encode (features, parameter-free) -> decode (network) -----------
    def encode(self, dp, v_a, v_b, R_a, hist=None):
        """Unnormalised features (..., k) and output basis (..., 2, 3) or None, model dtype.

        Parameter-free: training computes it once for the whole data set. ``hist`` (..., H, 3):
        the neighbour's history, read by a model with memory only.
        """
        dtype = self.in_mean.dtype
        dp, v_a, v_b, R_a = (_to_tensor(a, dtype) for a in (dp, v_a, v_b, R_a))
        hist = _to_tensor(hist, dtype) if self.memory and hist is not None else None
        return model_inputs(self.feature_set, dp, v_a, v_b, R_a, hist)

    def decode(self, x: torch.Tensor, basis: torch.Tensor | None) -> torch.Tensor:
        """World-frame acceleration (..., 3) m/s^2 from features x (..., k) and basis."""
        out = self.net((x - self.in_mean) / self.in_std) * self.out_std + self.out_mean
        return out if basis is None else assemble(out, basis)

    def forward(self, dp, v_a, v_b, R_a, hist=None) -> torch.Tensor:
        """Predicted downwash on the follower (..., 3) m/s^2, world frame (see module doc)."""
        x, basis = self.encode(dp, v_a, v_b, R_a, hist)
        return self.decode(x, basis)

    def output_targets(self, y: torch.Tensor, basis: torch.Tensor | None) -> torch.Tensor:
        """World-frame labels y (..., 3) in the coordinates of the network's outputs (..., m)."""
        return y if basis is None else project_onto_basis(y, basis)

    # -- the trainer's protocol (`downwash.train`): the same three steps for every kind -----------
    def encode_samples(self, data: Any) -> tuple[PairEncoded, torch.Tensor]:
        """(encoding, labels (P, 3)) of every real (target, neighbour) pair of a `Dataset`
        (`Dataset.pairs`), or of an object of flat arrays dp, v_a, v_b, R_a (hist for a model with
        memory) and y (labels None without y)."""
        pairs = data.pairs() if hasattr(data, "pairs") else data
        with torch.no_grad():
            x, basis = self.encode(pairs.dp, pairs.v_a, pairs.v_b, pairs.R_a, getattr(pairs, "hist", None))
        y = getattr(pairs, "y", None)
        return PairEncoded(x, basis), None if y is None else torch.as_tensor(np.asarray(y), dtype=x.dtype)

    def fit_samples(self, enc: PairEncoded, y: torch.Tensor) -> None:
        """The normalisation fitted on a training encoding and its labels."""
        self.fit_normalization(enc.x, self.output_targets(y, enc.basis))

    def decode_samples(self, enc: PairEncoded) -> torch.Tensor:
        """Predictions (P, 3) m/s^2 on an encoding."""
        return self.decode(enc.x, enc.basis)

    def spectral_layers(self) -> list["SpectralLinear"]:
        """The spectrally normalised layers (none in the one-hidden-layer models)."""
        return [m for m in self.modules() if isinstance(m, SpectralLinear)]

    def settle_spectral_norm(self) -> None:
        """Exact spectral-norm estimates (`settle_spectral_norm`); nothing to do without such layers."""
        settle_spectral_norm(self)

    # -- normalisation -----------------------------------------------------------------
    @torch.no_grad()
    def fit_normalization(self, x: torch.Tensor, targets: torch.Tensor) -> None:
        """Set the buffers from training features x (N, k) and output targets (N, m).

        A (near-)constant column keeps std 1 so that it is not blown up.
        """
        x = torch.as_tensor(x, dtype=self.in_mean.dtype).reshape(-1, self.n_features)
        targets = torch.as_tensor(targets, dtype=self.in_mean.dtype).reshape(-1, self.n_outputs)
        if x.shape[0] < 2:
            raise ValueError(f"fit_normalization: need at least 2 samples, got {x.shape[0]}")
        self.set_normalization(x.mean(0), _floored_std(x), targets.mean(0), _floored_std(targets))

    @torch.no_grad()
    def set_normalization(self, in_mean, in_std, out_mean, out_std) -> None:
        """Copy normalisation statistics into the buffers (shapes (k,), (k,), (m,), (m,))."""
        for name, value in (("in_mean", in_mean), ("in_std", in_std), ("out_mean", out_mean), ("out_std", out_std)):
            buf = getattr(self, name)
            value = torch.as_tensor(value, dtype=buf.dtype)
            if value.shape != buf.shape:
                raise ValueError(f"{name}: expected shape {tuple(buf.shape)}, got {tuple(value.shape)}")
            if name.endswith("std") and not bool((value > 0).all()):
                raise ValueError(f"{name}: must be positive, got {value.tolist()}")
            buf.copy_(value)

    def normalization(self) -> dict[str, list[float]]:
        """The normalisation buffers as plain lists (for checkpoint metadata)."""
        return {k: getattr(self, k).tolist() for k in ("in_mean", "in_std", "out_mean", "out_std")}

    @torch.no_grad()
    def folded_layers(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The network as float64 NumPy ``[(W_i (out, in), b_i (out,)), ...]`` with ReLU between.

        Input normalisation is folded into the first layer and the output scaling
        into the last, so ``decode(x, basis)`` equals the plain MLP of these layers
        applied to the raw features x, then `features.assemble` with the basis.
        Spectral normalisation is applied as in eval mode (stored estimate).
        """
        layers = []
        for m in self.net:
            if isinstance(m, nn.Linear):
                layers.append((m.weight, m.bias))
            elif isinstance(m, SpectralLinear):
                layers.append((m.effective_weight(), m.linear.bias))
            elif not isinstance(m, nn.ReLU):  # pragma: no cover - guards future architectures
                raise TypeError(f"folded_layers: unsupported layer {type(m).__name__}")
        f64 = [(w.detach().double().clone(), b.detach().double().clone()) for w, b in layers]
        mean, std = self.in_mean.double(), self.in_std.double()
        w0, b0 = f64[0]
        f64[0] = (w0 / std, b0 - (w0 / std) @ mean)
        wl, bl = f64[-1]
        out_mean, out_std = self.out_mean.double(), self.out_std.double()
        f64[-1] = (wl * out_std[:, None], bl * out_std + out_mean)
        return [(w.numpy(), b.numpy()) for w, b in f64]

    def numpy_forward(self) -> Callable[..., np.ndarray]:
        """The model as a float64 NumPy function of pairs ``f(dp, v_a, v_b, R_a, hist=None) -> F (..., 3)``: the
        `folded_layers` as they are now (eval mode), copied; 0 where the target is not below the
        neighbour (depth ``-(dp . n) <= 0``: the models are trained on targets below only and have
        no business extrapolating above a wake). The readable reference of every predictor's law."""
        was_training = self.training
        self.eval()  # the spectral-norm estimates as stored
        try:
            layers = [(np.ascontiguousarray(w.T), b) for w, b in self.folded_layers()]  # (in, out): h @ W + b
        finally:
            self.train(was_training)
        feature_set = self.feature_set
        names = FEATURE_SETS[feature_set]
        depth_col = names.index("depth") if "depth" in names else None

        def forward(dp, v_a, v_b, R_a, hist=None):
            x, basis = model_inputs(feature_set, dp, v_a, v_b, R_a, hist)
            h = x
            for w, b in layers[:-1]:
                h = matmul_rows(h, w)
                h += b
                np.maximum(h, _ZERO, out=h)
            w, b = layers[-1]
            f = matmul_rows(h, w) + b
            if basis is not None:
                f = assemble(f, basis)
            s = x[..., depth_col] if depth_col is not None else depth(dp, R_a)
            return np.where((s > 0)[..., None], f, 0.0)

        return forward

    # -- description ---------------------------------------------------------------------
    def architecture(self) -> dict[str, Any]:
        """Constructor arguments that rebuild this architecture (JSON-serialisable)."""
        return {}

    def describe(self) -> dict[str, Any]:
        """Kind, feature set, architecture and parameter count (JSON-serialisable)."""
        return {
            "kind": self.kind,
            "feature_set": self.feature_set,
            "features": list(FEATURE_SETS[self.feature_set]),
            "architecture": self.architecture(),
            "n_parameters": count_parameters(self),
        }


def _to_tensor(a: Any, dtype: torch.dtype) -> torch.Tensor:
    """A tensor of the model's dtype (no copy when it already is one); NumPy views of any stride."""
    if isinstance(a, np.ndarray) and (not a.flags.writeable or any(st < 0 for st in a.strides)):
        a = np.array(a, dtype=_NUMPY_DTYPES.get(dtype, a.dtype))  # torch wants writable, positive strides
    return torch.as_tensor(a, dtype=dtype)


_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def _floored_std(a: torch.Tensor) -> torch.Tensor:
    std = a.std(0)
    return torch.where(std > _STD_FLOOR, std, torch.ones_like(std))


def layer_widths(name: str, widths: Sequence[int]) -> tuple[int, ...]:
    """Hidden widths: a sequence of integers in [1, MAX_WIDTH]; ConfigError naming the argument."""
    if isinstance(widths, (int, str)) or not hasattr(widths, "__iter__"):
        raise ConfigError(f"{name}: expected a sequence of layer widths, got {widths!r}")
    return tuple(count(name, w, 1, MAX_WIDTH) for w in widths)


def _mlp(widths: Sequence[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
        if i:
            layers.append(nn.ReLU())
        layers.append(nn.Linear(a, b))
    return nn.Sequential(*layers)


class _OneHiddenLayer(DownwashModel):
    """The paper's shallow network: k features - `hidden` ReLU units - n_outputs."""

    def __init__(self, feature_set: str | None = None, hidden: int = 32):
        super().__init__(feature_set)
        self.hidden = count("hidden", hidden, 1, MAX_WIDTH)
        self.net = _mlp([self.n_features, self.hidden, self.n_outputs])

    def architecture(self) -> dict[str, Any]:
        return {"hidden": self.hidden}


class EquivariantModel(_OneHiddenLayer):
    """The paper's SO(2)-equivariant model (eq. 5): ``F = f1 r_hat + f2 d``.

    ``(f1, f2) = MLP(h)`` with h the invariant features of `features.invariant_features`
    (feature set "5": 5-32-2 ReLU, 258 parameters; "6": 6-32-2, 290 parameters).
    ``r_hat`` is the radial unit vector in the leader's rotor plane and ``d = -n``
    the leader's NED-down axis (`features.equivariant_basis`): f2 > 0 pushes the
    follower away from the leader along its axis (toward the ground when level).
    """

    kind = "equivariant"
    ALLOWED_FEATURE_SETS = ("5", "6")
    DEFAULT_FEATURE_SET = "5"
    n_outputs = 2
    # Peak learning rates of the pair kinds were picked on synthetic data from the true field
    # (51k samples, batch 2048, 60 epochs, cosine decay): the equivariant model kept improving
    # up to 0.1, the shallow MLP was best at 0.03, the deep SN-MLP at 0.003-0.01 (diverged at 0.03).
    default_lr = 5e-2


class GeneralEquivariantModel(_OneHiddenLayer):
    """A generalised SO(2)-equivariant model: ``F = f1 r_hat + f2 d + f3 t_hat``, ``t_hat = n x r_hat``.

    ``(f1, f2, f3) = MLP(h)`` with h the 10 invariant features of the "general" set
    (`downwash.features`): the paper's, plus the signed angles of v_b and v_a about the
    leader's axis and the leader's lateral and axial speed. 10-32-3 ReLU, 451 parameters.
    The tangential channel represents swirl and the leader's velocity represents skewed
    wakes, which the paper's model cannot. Equivariant under rotations about n applied
    to dp, v_b and v_a together (tested like the paper's model).
    """

    kind = "equivariant_general"
    ALLOWED_FEATURE_SETS = ("general",)
    DEFAULT_FEATURE_SET = "general"
    n_outputs = 3
    default_lr = 5e-2


class ShallowMLP(_OneHiddenLayer):
    """Shallow non-equivariant baseline: ``[dp, v_b]`` 6-32-3 ReLU (323 parameters), world axes out."""

    kind = "shallow"
    ALLOWED_FEATURE_SETS = ("raw",)
    DEFAULT_FEATURE_SET = "raw"
    n_outputs = 3
    default_lr = 3e-2


class SpectralLinear(nn.Module):
    """``y = gamma (W / sigma_max(W)) x + b``: largest singular value of the effective weight = gamma.

    The division uses torch's `spectral_norm` parametrization (power iteration,
    one step per training forward); `DeepSNMLP.settle_spectral_norm` runs it to
    convergence after training so the stored estimate is exact.
    """

    def __init__(self, n_in: int, n_out: int, gamma: float):
        super().__init__()
        self.linear = spectral_norm(nn.Linear(n_in, n_out))
        self.gamma = float(gamma)

    def effective_weight(self) -> torch.Tensor:
        """The weight actually applied (n_out, n_in)."""
        return self.gamma * self.linear.weight

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.linear(x, self.effective_weight(), self.linear.bias)


class DeepSNMLP(DownwashModel):
    """Deep non-equivariant baseline (Neural-Swarm style): 8 spectrally normalised layers, ReLU.

    Input ``[dp, v_b]``, widths 6-40-40-40-40-40-40-25-3: 9583 parameters, the
    paper's count. Each layer's largest singular value is bounded by ``gamma = 2``
    (exactly 2 with torch's normalisation), so the network (between the input
    normalisation and output scaling) is 2^8-Lipschitz.

    During training torch's power iteration (one step per forward) tracks the
    changing weights with a lag, so the bound holds only approximately there
    (we measured up to ~2.4 at a high learning rate, ~2.04 at the end of a cosine
    schedule); the estimates are made exact at construction and after training
    (`settle_spectral_norm`), and eval mode uses the stored estimates.
    """

    kind = "deep"
    ALLOWED_FEATURE_SETS = ("raw",)
    DEFAULT_FEATURE_SET = "raw"
    n_outputs = 3
    default_lr = 5e-3
    DEFAULT_HIDDEN = (40, 40, 40, 40, 40, 40, 25)

    def __init__(self, feature_set: str | None = None, hidden: Sequence[int] = DEFAULT_HIDDEN, gamma: float = 2.0):
        super().__init__(feature_set)
        self.hidden = layer_widths("hidden", hidden)
        self.gamma = float(gamma)
        widths = [self.n_features, *self.hidden, 3]
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(widths[:-1], widths[1:])):
            if i:
                layers.append(nn.ReLU())
            layers.append(SpectralLinear(a, b, self.gamma))
        self.net = nn.Sequential(*layers)
        self.settle_spectral_norm()  # start training from exact estimates (torch does only 15 iterations)

    def architecture(self) -> dict[str, Any]:
        return {"hidden": list(self.hidden), "gamma": self.gamma}


@torch.no_grad()
def settle_spectral_norm(model: nn.Module, max_iterations: int = 5000, rtol: float = 1e-9) -> None:
    """Run the power iteration of every spectrally normalised layer of ``model`` until its
    singular-value estimate converges.

    Afterwards the stored estimate matches sigma_max(W) to about rtol, so every effective
    weight has largest singular value gamma (up to rtol) in eval mode.
    """
    for layer in (m for m in model.modules() if isinstance(m, SpectralLinear)):
        param = layer.linear.parametrizations.weight[0]
        W = layer.linear.parametrizations.weight.original
        old_n, old_mode = param.n_power_iterations, param.training
        param.n_power_iterations, chunk = 20, 20
        param.train()
        try:
            prev = None
            for _ in range(0, max_iterations, chunk):
                param(W)  # training-mode forward: 20 power iterations on _u, _v in place
                sigma = float(torch.dot(param._u, torch.mv(W, param._v)))
                if prev is not None and abs(sigma - prev) <= rtol * abs(sigma):
                    break
                prev = sigma
        finally:
            param.n_power_iterations = old_n
            param.train(old_mode)


class EquivariantMemoryModel(GeneralEquivariantModel):
    """The generalised equivariant model with memory: ``F = f1 r_hat + f2 d + f3 t_hat`` from the
    "general" invariants and the neighbour's displacement over each of `downwash.features.HISTORY_LAGS`
    along the three basis rows (feature set "general_memory", 22 features; 22-32-3 ReLU, 835
    parameters). The history rotates with the rest of the configuration, so the model stays
    SO(2)-equivariant (tested). A wake met now was shed where the neighbour was a moment ago: this
    model can see where that was, the memoryless ones cannot."""

    kind = "equivariant_memory"
    ALLOWED_FEATURE_SETS = ("general_memory",)
    DEFAULT_FEATURE_SET = "general_memory"


class DeepMemoryModel(DeepSNMLP):
    """The deep baseline with memory: ``[dp, v_b]`` and the neighbour's displacement over each lag of
    `downwash.features.HISTORY_LAGS`, all in world axes (feature set "raw_memory", 18 features), the
    same spectrally normalised network as `DeepSNMLP`. Not equivariant."""

    kind = "deep_memory"
    ALLOWED_FEATURE_SETS = ("raw_memory",)
    DEFAULT_FEATURE_SET = "raw_memory"


# The per-neighbour kinds (the paper's table order, then the models with memory);
# `downwash.registry.MODEL_KINDS` lists them with the models of sets, and experiments, conditions,
# checkpoints and training take names there.
PAIRWISE_KINDS: dict[str, type[DownwashModel]] = {
    "shallow": ShallowMLP,
    "deep": DeepSNMLP,
    "equivariant": EquivariantModel,
    "equivariant_general": GeneralEquivariantModel,
    "equivariant_memory": EquivariantMemoryModel,
    "deep_memory": DeepMemoryModel,
}
# The kinds the staged collection trains as its final models (the paper's and the generalised
# model); it trains any other kind on the same data when one is asked for (`downwash.staged`).
STAGED_KINDS = ("shallow", "deep", "equivariant", "equivariant_general")
