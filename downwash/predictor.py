"""A learned model in the control loop: the `sim.predictor.Predictor` protocol.

For every ordered pair (leader i, follower j != i) of every world the model is
evaluated on the ESTIMATED states, ``dp = p_j - p_i``, ``v_a = v_i``,
``v_b = v_j``, ``R_a = rot_i``, in one batched call, and the predictions are summed
over leaders. A pair whose follower is not below its leader (depth
``s = -(dp . n_i) <= 0``) contributes 0: the models are trained on follower-below
data only and have no business extrapolating above a wake.
"""

from __future__ import annotations

import copy
import os

import numpy as np
import torch

from downwash.checkpoint import load_checkpoint
from downwash.features import FEATURE_SETS, assemble, depth, model_inputs
from downwash.fused import feature_code, pack_abi, pack_layers, predict_address, predict_into
from downwash.models import DownwashModel
from downwash_core.geometry import dot
from downwash_core.state import VehicleStates
from downwash_core.numerics import matmul_rows
from sim.predictor import CompiledPredictor

__all__ = ["LearnedPredictor", "clamp_magnitude"]

_ZERO = np.zeros(())  # 0-d: cheaper per NumPy call than a Python float


def _f64(a: np.ndarray) -> np.ndarray:
    """float64 as is (numba takes strided views), else converted."""
    return a if isinstance(a, np.ndarray) and a.dtype == np.float64 else np.asarray(a, dtype=np.float64)


def _frozen(model: DownwashModel) -> DownwashModel:
    """An inference copy: eval mode (spectral-norm estimates fixed), no gradients.

    (Not `parametrize.remove_parametrizations`: on a deep copy it edits the
    parametrized class that the copy shares with the original.)
    """
    model = copy.deepcopy(model).eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


class LearnedPredictor:
    """Downwash prediction (W, V, 3) m/s^2, world frame, float64, from a trained model.

    model: a `DownwashModel` (copied and frozen; the original is untouched).
    clamp: optional bound (m/s^2) on the magnitude of each vehicle's summed prediction.
    backend: "compiled" (default) runs features, network, basis, depth gate and
      clamp in one compiled pass (`downwash.fused`, float64): a few microseconds a
      call. "numpy" is its readable reference: the same features (`downwash.features`,
      NumPy namespace) and the model's float64 `folded_layers` in NumPy (~55 us a call
      at one world, mostly per-operation overhead); the two agree to float64
      rounding (a test). "torch" calls the frozen torch model once under
      ``torch.inference_mode`` (float32 unless the model is float64), agreeing to
      float32 rounding.
    """

    BACKENDS = ("compiled", "numpy", "torch")

    def __init__(self, model: DownwashModel, clamp: float | None = None, backend: str = "compiled"):
        if not isinstance(model, DownwashModel):
            raise TypeError(f"model: expected a DownwashModel, got {type(model).__name__}")
        if clamp is not None and not clamp > 0:
            raise ValueError(f"clamp: expected None or a magnitude > 0 (m/s^2), got {clamp!r}")
        if backend not in self.BACKENDS:
            raise ValueError(f"backend: expected one of {list(self.BACKENDS)}, got {backend!r}")
        self.model = _frozen(model)
        self.clamp = None if clamp is None else float(clamp)
        self.backend = backend
        self.feature_set = self.model.feature_set
        layers = self.model.folded_layers()
        self._layers = [(np.ascontiguousarray(w.T), b) for w, b in layers]  # (in, out): h @ W + b
        names = FEATURE_SETS[self.feature_set]
        self._depth_col = names.index("depth") if "depth" in names else None
        self._pairs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._packed = pack_layers(layers)
        self._code = feature_code(self.feature_set)
        self._clamp_kernel = 0.0 if self.clamp is None else self.clamp  # <= 0: no bound
        self._abi = pack_abi(self._packed, self._code, self._clamp_kernel)

    def compiled(self) -> CompiledPredictor | None:
        """The compiled backend as a C function for the simulator's fused loop (`sim.predictor`);
        None for the "numpy" and "torch" backends, which the loop calls through `__call__`."""
        if self.backend != "compiled":
            return None
        return CompiledPredictor(predict_address, *self._abi)

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        clamp: float | None = None,
        backend: str = "compiled",
        expect_kind: str | None = None,
        expect_feature_set: str | None = None,
    ) -> "LearnedPredictor":
        """A predictor from a checkpoint written by `downwash.checkpoint.save_checkpoint`."""
        model, _ = load_checkpoint(path, expect_kind=expect_kind, expect_feature_set=expect_feature_set)
        return cls(model, clamp=clamp, backend=backend)

    def _pair_index(self, n_veh: int) -> tuple[np.ndarray | slice, np.ndarray | slice]:
        """(leaders, followers) of the V (V - 1) ordered pairs, grouped by follower.

        For V = 2 these are slices (views, no copies): followers (0, 1), leaders (1, 0).
        """
        pairs = self._pairs.get(n_veh)
        if pairs is None:
            if n_veh == 2:
                pairs = (slice(None, None, -1), slice(None))
            else:
                followers = np.repeat(np.arange(n_veh), n_veh - 1)
                leaders = np.array([i for j in range(n_veh) for i in range(n_veh) if i != j], dtype=np.intp)
                pairs = (leaders, followers)
            self._pairs[n_veh] = pairs
        return pairs

    def predict_pairs(self, dp: np.ndarray, v_a: np.ndarray, v_b: np.ndarray, R_a: np.ndarray) -> np.ndarray:
        """The model on a batch of pairs (..., 3) m/s^2, float64, zero where the follower is not below."""
        if self.backend == "torch":
            with torch.inference_mode():
                f = self.model(dp, v_a, v_b, R_a).numpy().astype(np.float64)
            return np.where((depth(dp, R_a) > 0)[..., None], f, 0.0)
        x, basis = model_inputs(self.feature_set, dp, v_a, v_b, R_a)
        h = x
        for w, b in self._layers[:-1]:
            h = matmul_rows(h, w)
            h += b
            np.maximum(h, _ZERO, out=h)
        w, b = self._layers[-1]
        f = matmul_rows(h, w) + b
        if basis is not None:
            f = assemble(f, basis)
        s = x[..., self._depth_col] if self._depth_col is not None else depth(dp, R_a)
        return np.where((s > 0)[..., None], f, 0.0)

    def __call__(self, estimated: VehicleStates, true: VehicleStates | None = None) -> np.ndarray:
        """Summed prediction on every vehicle (W, V, 3) m/s^2 from ``estimated`` ((W, V, ...) arrays).

        ``true`` is ignored (a learned model only knows the estimates).
        """
        pos, vel, rot = estimated.pos, estimated.vel, estimated.rot
        n_worlds, n_veh = pos.shape[:2]
        if n_veh < 2:
            return np.zeros(pos.shape, dtype=np.float64)
        if self.backend == "compiled":
            out = np.empty((n_worlds, n_veh, 3))
            predict_into(_f64(pos), _f64(vel), _f64(rot), *self._packed, self._code, self._clamp_kernel, out)
            return out
        leaders, followers = self._pair_index(n_veh)
        n_pairs = n_veh * (n_veh - 1)
        f = self.predict_pairs(
            (pos[:, followers] - pos[:, leaders]).reshape(-1, 3),
            vel[:, leaders].reshape(-1, 3),
            vel[:, followers].reshape(-1, 3),
            rot[:, leaders].reshape(-1, 3, 3),
        ).reshape(n_worlds, n_pairs, 3)
        total = f.reshape(n_worlds, n_veh, n_veh - 1, 3).sum(axis=2) if n_veh > 2 else f
        return total if self.clamp is None else clamp_magnitude(total, self.clamp)


def clamp_magnitude(f: np.ndarray, bound: float) -> np.ndarray:
    """f (..., 3) scaled down where its magnitude exceeds bound (m/s^2): the clamp of every learned
    predictor, pair or swarm (the compiled pass, `downwash.fused`, applies the same bound)."""
    norm = np.sqrt(dot(f, f))
    return f * np.minimum(1.0, bound / np.maximum(norm, 1e-300))[..., None]
