"""A learned model in the control loop: the `sim.predictor.Predictor` protocol, for every kind.

Every vehicle's predicted force is its model's answer on its neighbour set, selected from the
ESTIMATED states (`sim.neighbours`, the data's selection). A per-neighbour model
(`downwash.models`) is flown as ``summed_pairwise`` over every other vehicle: for each ordered
pair (neighbour i, target j != i) of every world the model is evaluated on ``dp = p_j - p_i``,
``v_a = v_i``, ``v_b = v_j``, ``R_a = rot_i``, and the predictions are summed over the
neighbours. A pair whose target is not below its neighbour (depth ``s = -(dp . n_i) <= 0``)
contributes 0: the models are trained on targets below only and have no business
extrapolating above a wake. A model of sets (`downwash.set_models`) takes the padded set.

A model that reads the vehicle kinds (``kinds=True``) is told each vehicle's kind: the simulator
binds it to its scene (`LearnedPredictor.for_vehicles`, called by `sim.vehicle_params.scene_predictor`);
unbound it reads every vehicle as the paper quad.

A model with memory (`downwash.models.EquivariantMemoryModel`, `DeepMemoryModel`) reads each
neighbour's displacement over the lags of `downwash.features.HISTORY_LAGS`. The predictor keeps
the estimated positions of its last calls per world, as a lab's compensator would (a stateful
predictor, `sim.predictor`): the simulator resets a world's history with the world and tells it
which worlds each call is due for. Before a world has a full history its oldest position stands
in for the older ones, as in the labels (`downwash.labels.past_positions`).
"""

from __future__ import annotations

import copy
import math
import os
from typing import Any

import numpy as np
import torch
from torch import nn

from downwash_core.errors import ConfigError
from downwash_core.geometry import dot
from downwash_core.state import VehicleStates
from downwash_core.validate import count
from downwash.checkpoint import Checkpoint, check_expectations, load_checkpoint, wrap_pairwise
from downwash_core.params import RATES
from downwash.features import HISTORY_LAGS, kind_descriptors, neighbour_history, neighbour_kinds
from downwash.models import DownwashModel, SpectralLinear
from downwash.set_models import SetModel, SummedPairwise
from downwash.set_fused import COMPILED_KINDS, pack_model
from sim.neighbours import NeighbourSet, gather_neighbours, select_neighbours
from sim.predictor import CompiledPredictor

__all__ = ["LearnedPredictor", "clamp_magnitude"]


@torch.no_grad()
def _fold_spectral(model: nn.Module) -> nn.Module:
    """Replace every spectrally normalised layer (in eval mode) by a plain linear layer with its
    effective weight: the same function, without the per-call normalisation (inference only)."""
    for module in list(model.modules()):
        for name, child in list(module.named_children()):
            if isinstance(child, SpectralLinear):
                w = child.effective_weight()
                plain = nn.Linear(w.shape[1], w.shape[0], dtype=w.dtype)
                plain.weight.copy_(w)
                plain.bias.copy_(child.linear.bias)
                setattr(module, name, plain)
    return model


class LearnedPredictor:
    """A learned model in the predictor slot: (W, V, 3) m/s^2, world frame, float64.

    model: a per-neighbour model (`downwash.models.DownwashModel`, flown as `summed_pairwise`
      over ``neighbours``, by default every other vehicle), a `downwash.checkpoint.Checkpoint`
      (e.g. from `load_checkpoint` or `wrap_pairwise`), or a checkpoint's path. Models are
      copied; the caller's stay as they are.
    clamp: optional bound (m/s^2) on the magnitude of each vehicle's prediction (`clamp_magnitude`).
    backend: "compiled" (the default for a kind in `downwash.set_fused.COMPILED_KINDS`, every
      registered kind): selection, model and clamp in one compiled pass, float64, which the
      simulator's fused tick calls without leaving compiled code (`compiled()`); "numpy" (the
      default for a kind without a compiled form): the model's float64 NumPy twin
      (``numpy_forward``), the compiled pass's readable reference; "torch" (the default for a
      network with layers the twin does not have, only linear layers and ReLUs): the frozen torch
      model under ``torch.inference_mode``, the twin's readable reference, 2-5x slower on these
      small batches. All three agree to float64 rounding (tests).
    neighbours: the neighbour set of a per-neighbour model (a checkpoint brings its own).
    expect_neighbours, expect_aggregation: what the flight needs; a model made for another
      neighbour set or aggregation law raises CheckpointError here, before any flight.
    vehicle_kinds: each vehicle's kind (`downwash_core.vehicles` names or kinds), for a model that
      reads them; None: every vehicle a paper quad, or the scene's once the simulator binds it
      (`for_vehicles`). Ignored by a model that does not read them.
    dtype: the torch backend's precision (default float64: the model is copied and converted).
    num_threads: torch intra-op threads during a torch call (default 1: these small batches
      ran 15-25x slower with two threads on two busy cores; None leaves torch's setting).
    predictor_hz: the rate it is called at per world (the loop's, `downwash_core.params.RATES`), for
      a model with memory: every lag of `HISTORY_LAGS` must be a whole number of calls.
    """

    BACKENDS = ("compiled", "numpy", "torch")

    def __init__(self, model: DownwashModel | Checkpoint | str | os.PathLike, clamp: float | None = None,
                 backend: str | None = None, *, neighbours: NeighbourSet | None = None,
                 expect_neighbours: NeighbourSet | None = None, expect_aggregation: Any = None,
                 vehicle_kinds: Any = None, dtype: torch.dtype = torch.float64, num_threads: int | None = 1,
                 predictor_hz: float = RATES.predictor_hz):
        if isinstance(model, (str, os.PathLike)):
            model = load_checkpoint(model, expect_neighbours=expect_neighbours, expect_aggregation=expect_aggregation)
        if isinstance(model, DownwashModel) or (isinstance(model, Checkpoint) and isinstance(model.model, DownwashModel)):
            model = wrap_pairwise(model, neighbours)  # (a checkpoint's record travels: the guard reads its support)
        elif neighbours is not None:
            raise ConfigError("neighbours: a model of sets flies the neighbour set of its checkpoint")
        if not isinstance(model, Checkpoint) or not isinstance(model.model, SetModel):
            raise TypeError(f"model: expected a per-neighbour model, a Checkpoint or a path, got {type(model).__name__}")
        check_expectations(f"{model.model.kind} model", model.neighbours, model.record, expect_neighbours,
                           expect_aggregation)
        kind = model.model.kind
        memory = isinstance(model.model, SummedPairwise) and model.model.pairwise.memory
        twin = _has_numpy_twin(model.model)  # its layers folded into float64 arrays: the twin's and the compiled pass's
        if backend is None:  # the fastest form the model has
            backend = "compiled" if kind in COMPILED_KINDS and not memory and twin else "numpy" if twin else "torch"
        if backend not in self.BACKENDS:
            raise ConfigError(f"backend: expected one of {list(self.BACKENDS)}, got {backend!r}")
        if backend != "torch" and not twin:
            raise ConfigError(f"backend: {backend!r} runs networks of linear layers and ReLUs; this model has other "
                              "layers: use 'torch' (the default for it)")
        if backend == "compiled" and (kind not in COMPILED_KINDS or memory):
            what = f"a {model.model.pairwise.kind!r} model (it reads its history)" if memory else repr(kind)
            raise ConfigError(f"backend: {what} has no compiled form (kinds with one: {sorted(COMPILED_KINDS)}, "
                              "without memory); use 'numpy' or 'torch'")
        self.predictor_hz = float(predictor_hz)
        self._lags = _lags_in_calls(self.predictor_hz) if memory else None  # calls back, per lag
        self._past: np.ndarray | None = None  # (max lag + 1, W, V, 3) the last calls' positions, newest first
        self._calls: np.ndarray | None = None  # (W,) calls since each world's reset
        if clamp is not None and not (math.isfinite(clamp) and clamp > 0):
            raise ConfigError(f"clamp: expected None or a finite magnitude > 0 (m/s^2), got {clamp!r}")
        self.clamp = None if clamp is None else float(clamp)
        self.backend = backend
        reads_kinds = bool(getattr(model.model, "kinds", False))
        self.vehicle_kinds = None if vehicle_kinds is None or not reads_kinds else tuple(vehicle_kinds)
        self._kinds = None if self.vehicle_kinds is None else kind_descriptors(self.vehicle_kinds)  # (V, D)
        frozen = copy.deepcopy(model.model).eval()  # eval: the spectral-norm estimates stay as stored
        self._numpy = frozen.numpy_forward() if backend == "numpy" else None
        # the compiled pass's constants (params, iparams): the twin's, packed before the torch copy is converted
        # and folded; the kernel and its C function are looked up by kind (valid in any process, e.g. unpickled)
        self._abi = pack_model(frozen, model.neighbours, self.clamp, self._kinds)[1][1:] if backend == "compiled" else None
        # what `for_vehicles` rebuilds a kind-reading model from (a copy: the caller's may change)
        self._checkpoint = Checkpoint(copy.deepcopy(model.model), model.record) if reads_kinds else None
        frozen = _fold_spectral(frozen.to(dtype))
        for p in frozen.parameters():
            p.requires_grad_(False)
        self.model = frozen
        self.neighbours = model.neighbours
        self.record = model.record
        self.kind = kind
        self.num_threads = None if num_threads is None else count("num_threads", num_threads, 1)

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, clamp: float | None = None, backend: str | None = None,
                        expect_kind: str | None = None, expect_feature_set: str | None = None,
                        **options: Any) -> "LearnedPredictor":
        """A predictor from a checkpoint file (`downwash.checkpoint.save_checkpoint`); expect_kind,
        expect_feature_set as `load_checkpoint`; options (the neighbour set and law expected among
        them, checked by the constructor) as the constructor's."""
        checkpoint = load_checkpoint(path, expect_kind=expect_kind, expect_feature_set=expect_feature_set)
        return cls(checkpoint, clamp, backend, **options)

    def for_vehicles(self, kinds: Any) -> "LearnedPredictor":
        """This predictor for a scene of these vehicle kinds (V names or kinds): itself for a model that
        does not read kinds or when they are its own, else a copy that tells the model each kind."""
        kinds = tuple(getattr(k, "name", k) for k in kinds)
        if self._checkpoint is None or kinds == self.vehicle_kinds:
            return self
        return LearnedPredictor(self._checkpoint, self.clamp, self.backend, vehicle_kinds=kinds,
                                dtype=next(self.model.parameters()).dtype, num_threads=self.num_threads,
                                predictor_hz=self.predictor_hz)

    @property
    def stateful(self) -> bool:
        """Whether the model reads the neighbours' history, which this predictor keeps (module doc,
        `sim.predictor.is_stateful`)."""
        return self._lags is not None

    def reset(self, worlds: Any = None) -> None:
        """Forget the history of these worlds (indices; None: every world): each starts afresh at its
        next call. Nothing to do for a model without memory."""
        if self._calls is not None:
            self._calls[slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64)] = 0

    def _remember(self, pos: np.ndarray, due: np.ndarray | None) -> np.ndarray:
        """Push this call's positions (W, V, 3) into the due worlds' histories (all worlds when due
        is None); returns the positions each lag ago (H, W, V, 3)."""
        W = pos.shape[0]
        if self._past is None or self._past.shape[1:] != pos.shape:  # first call, or other worlds
            self._past = np.empty((max(self._lags) + 1, *pos.shape))
            self._calls = np.zeros(W, dtype=np.int64)
        due = np.ones(W, bool) if due is None else np.asarray(due, dtype=bool)
        fresh = due & (self._calls == 0)
        self._past[:, fresh] = pos[fresh]  # a world's first call stands in for its past
        going = due & ~fresh
        self._past[1:, going] = self._past[:-1, going]
        self._past[0, going] = pos[going]
        self._calls[due] += 1
        return self._past[self._lags]

    def compiled(self) -> CompiledPredictor | None:
        """The compiled backend as a C function for the simulator's fused loop (`sim.predictor`): one
        per model kind, this model's constants in its params; None for "numpy" and "torch"."""
        return None if self._abi is None else CompiledPredictor(COMPILED_KINDS[self.kind].address, *self._abi)

    def describe(self) -> dict[str, Any]:
        out = {"kind": self.kind, "neighbours": self.neighbours.describe(),
               "aggregation": self.record.get("aggregation"), "backend": self.backend, "clamp": self.clamp}
        if self.stateful:
            out["history_lags"] = list(HISTORY_LAGS)
        return out if self.vehicle_kinds is None else {**out, "vehicle_kinds": list(self.vehicle_kinds)}

    def __call__(self, estimated: VehicleStates, true: VehicleStates | None = None,
                 due: np.ndarray | None = None) -> np.ndarray:
        """Predicted force on every vehicle (W, V, 3) m/s^2 from ``estimated``; ``true`` is ignored
        (a learned model only knows the estimates). due (W,) bool: the worlds whose prediction this
        call is (a model with memory remembers only theirs; None: every world); the others' rows
        are computed all the same, for the caller to ignore."""
        pos, vel, rot = estimated.pos, estimated.vel, estimated.rot
        W, V = pos.shape[:2]
        if self._kinds is not None and len(self._kinds) != V:
            raise ConfigError(f"vehicle_kinds: the predictor was given {len(self._kinds)} vehicle kinds, the states "
                              f"hold {V} vehicles")
        past = None if self._lags is None else self._remember(np.asarray(pos, dtype=np.float64), due)
        if V < 2:
            return np.zeros((W, V, 3))
        if self._abi is not None:  # selection, model and clamp in one pass
            out = np.empty((W, V, 3))
            COMPILED_KINDS[self.kind].kernel(*(np.ascontiguousarray(a, dtype=np.float64) for a in (pos, vel, rot)),
                                             *self._abi, out)
            return out
        index, mask = select_neighbours(pos, self.neighbours)
        g = gather_neighbours(pos, vel, rot, index, mask)
        K = index.shape[-1]
        batch = (g["dp"].reshape(W * V, K, 3), g["v_a"].reshape(W * V, K, 3), g["v_b"].reshape(W * V, 3),
                 g["R_a"].reshape(W * V, K, 3, 3), mask.reshape(W * V, K))
        if self._kinds is not None:  # each slot's neighbour kind (0 in padding) and the target's
            D = self._kinds.shape[1]
            kind_a = neighbour_kinds(self._kinds, index, mask)
            batch += (kind_a.reshape(W * V, K, D), np.broadcast_to(self._kinds, (W, V, D)).reshape(W * V, D))
        elif past is not None:
            batch += (None, None)
        if past is not None:  # each neighbour's displacement over each lag
            batch += (neighbour_history(pos, past, index, mask).reshape(W * V, K, len(HISTORY_LAGS), 3),)
        if self._numpy is not None:
            out = self._numpy(*batch).reshape(W, V, 3)
        else:
            old_threads = torch.get_num_threads()
            if self.num_threads is not None:
                torch.set_num_threads(self.num_threads)
            try:
                with torch.inference_mode():
                    out = self.model(*batch).double().numpy().reshape(W, V, 3)
            finally:
                if self.num_threads is not None:
                    torch.set_num_threads(old_threads)
        return out if self.clamp is None else clamp_magnitude(out, self.clamp)


def _has_numpy_twin(model: Any) -> bool:
    """Whether the model's NumPy twin can be built: its networks are of the layers the twin has
    (`downwash.numpy_mlp`: (spectral) linear layers and ReLUs)."""
    try:
        copy.deepcopy(model).eval().numpy_forward()
    except TypeError:  # a layer the twin does not have (numpy_mlp names it)
        return False
    return True


def _lags_in_calls(predictor_hz: float) -> list[int]:
    """Each lag of `HISTORY_LAGS` in calls at predictor_hz; ConfigError unless each is a whole number."""
    calls = [lag * predictor_hz for lag in HISTORY_LAGS]
    if not (math.isfinite(predictor_hz) and predictor_hz > 0) or any(abs(c - round(c)) > 1e-6 or round(c) < 1
                                                                    for c in calls):
        raise ConfigError(f"predictor_hz: a model with memory reads lags {[round(lag, 4) for lag in HISTORY_LAGS]} s, "
                          f"which must be whole numbers of calls; got {predictor_hz!r} Hz (45 Hz, the loop's rate, "
                          "works)")
    return [int(round(c)) for c in calls]


def clamp_magnitude(f: np.ndarray, bound: float) -> np.ndarray:
    """f (..., 3) scaled down where its magnitude exceeds bound (m/s^2): the clamp of every learned
    prediction (the compiled passes, `downwash.fused.clamped`, apply the same bound)."""
    norm = np.sqrt(dot(f, f))
    return f * np.minimum(1.0, bound / np.maximum(norm, 1e-300))[..., None]
