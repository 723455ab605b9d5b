"""Training every model kind: MSE on all three world axes, Adam, mini-batches, early stopping by flight.

One trainer for the per-neighbour models (`downwash.models`, trained on `Dataset.pairs`)
and the models of sets (`downwash.set_models`, trained on the padded neighbour sets):
a model encodes a data set once (`encode_samples`), fits its scaling (`fit_samples`) and
runs its networks on indexed slices of the encoding (`decode_samples`).

Fast path: the features (and the equivariant output basis) do not depend on the
weights, so they are computed once for the whole data set; each step only runs
the network on indexed tensors (no DataLoader). The equivariant model trains on
~51,000 samples (17 min at 50 Hz) in a few seconds on 2 CPU cores.

Each step costs far more in torch's per-op overhead than in arithmetic, so the
defaults are large batches (2048), fused Adam, one gather per epoch and a single
intra-op thread (with two threads on two busy cores, small ops ran 3-8x slower
in our measurements; run independent trainings in separate processes instead).
A cosine decay from a high peak learning rate reaches in 60 epochs what a
constant 3e-3 reached in 300.

The same bits on every CPU (``TrainConfig.portable``, the default): torch picks its kernels
per CPU (ATen's loops vectorised for AVX2 or AVX-512, MKL's code path per vendor and
instruction set), and kernels that sum in another order train other bits, which a staged
collection carries into every later stage, model and result (the docs' design notes, "What
is bit-identical across machines"). So training asks for the kernels of
`downwash_core.numerics.PORTABLE_TORCH`: ATen's AVX2 loops and MKL's AVX2
path in its reproducible mode (Intel's Conditional Numerical Reproducibility), which give
the same checkpoint on every x86-64 CPU with AVX2 (since 2013-2015), AVX-512 ones included.
(ATen's loops without vector instructions and MKL's "COMPATIBLE" path would reach older
CPUs too, but then an ensemble no longer trains each member's bits, `downwash.ensemble`.)
Torch reads the request at its first operation in a process, so it must come first (the
experiments make it before any work); where torch ran before, or on a CPU without AVX2,
training warns once and goes on with this CPU's kernels. Each history records the kernels
it trained with (``kernels``, `torch_kernels`).

Deterministic for a seed: the weights are initialised under
``torch.random.fork_rng`` seeded with ``config.seed`` (the global RNG is left as
it was), mini-batches are shuffled by a seeded ``torch.Generator``, and the split
by flight uses ``numpy.random.default_rng(config.seed)``. Same seed and thread
count: bit-identical weights.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from downwash_core.errors import ConfigError, DataError
from downwash_core.numerics import PORTABLE_TORCH, request_portable_torch
from downwash_core.validate import count
from downwash.datasets import Dataset, merge_provenance, split_by_flight
from downwash.checkpoint import save_checkpoint
from downwash.registry import MODEL_KINDS, make_model, trainable_kinds

__all__ = ["TrainConfig", "train_model", "rmse", "predict", "save_trained", "torch_kernels", "training_kernels"]

logger = logging.getLogger(__name__)




@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (all validated on construction)."""

    lr: float | None = None  # peak Adam learning rate; None: the model kind's ``default_lr``
    lr_final: float = 0.01  # final learning rate as a fraction of lr (cosine decay over the run)
    batch_size: int = 2048  # samples per mini-batch
    max_epochs: int = 60  # passes over the training part (raised to reach min_steps on small data)
    min_steps: int = 1500  # at least this many mini-batch steps, so small data sets are trained as long
    patience: int = 20  # epochs (of a max_epochs run; scaled with it) without a new best val loss before stopping
    min_delta: float = 1e-4  # relative improvement of the validation loss that counts as a new best
    val_fraction: float = 0.2  # share of training flights held out for early stopping when no val set is given
    seed: int = 0  # weight init, shuffling and the flight split
    weight_decay: float = 0.0  # Adam L2 penalty
    num_threads: int | None = 1  # torch intra-op threads while training (None: leave as is); see module doc
    portable: bool = True  # train with kernels that give the same bits on every x86-64 CPU; see module doc

    def __post_init__(self) -> None:
        checks = {
            "lr": self.lr is None or self.lr > 0,
            "lr_final": 0 < self.lr_final <= 1,
            "batch_size": isinstance(self.batch_size, int) and self.batch_size >= 1,
            "max_epochs": isinstance(self.max_epochs, int) and self.max_epochs >= 1,
            "min_steps": isinstance(self.min_steps, int) and self.min_steps >= 0,
            "patience": isinstance(self.patience, int) and self.patience >= 1,
            "min_delta": 0 <= self.min_delta < 1,
            "val_fraction": 0 < self.val_fraction < 1,
            "seed": isinstance(self.seed, int) and self.seed >= 0,
            "weight_decay": self.weight_decay >= 0,
            "num_threads": self.num_threads is None or (isinstance(self.num_threads, int) and self.num_threads >= 1),
            "portable": isinstance(self.portable, bool),
        }
        allowed = {
            "lr": "None or > 0", "lr_final": "in (0, 1]", "batch_size": "an int >= 1", "max_epochs": "an int >= 1",
            "min_steps": "an int >= 0", "patience": "an int >= 1", "min_delta": "in [0, 1)",
            "val_fraction": "in (0, 1)", "seed": "an int >= 0", "weight_decay": ">= 0",
            "num_threads": "None or an int >= 1", "portable": "True or False",
        }  # fmt: skip
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"TrainConfig.{name}: expected {allowed[name]}, got {getattr(self, name)!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def peak_lr(self, kind: str) -> float:
        """The learning rate used for a model kind."""
        return MODEL_KINDS[kind].default_lr if self.lr is None else float(self.lr)


def torch_kernels() -> dict[str, str]:
    """The kernels torch runs in this process: ATen's vector instructions ("AVX2", "AVX512",
    "DEFAULT": none) and MKL's reproducibility mode (``MKL_CBWR``; "": its per-CPU default)."""
    return {"aten": torch.backends.cpu.get_cpu_capability(), "mkl_cbwr": os.environ.get("MKL_CBWR", "")}


_warned_kernels = False


def training_kernels(config: "TrainConfig") -> dict[str, str]:
    """The kernels a training with `config` runs (`torch_kernels`), after asking for the portable
    ones when ``config.portable`` (module doc); warns once per process when torch runs others."""
    global _warned_kernels
    if not config.portable:
        return torch_kernels()
    request_portable_torch()
    kernels = torch_kernels()
    portable = (kernels["aten"].lower() == PORTABLE_TORCH["ATEN_CPU_CAPABILITY"]
                and kernels["mkl_cbwr"] == PORTABLE_TORCH["MKL_CBWR"])
    if not portable and not _warned_kernels:
        _warned_kernels = True
        logger.warning("training with this CPU's torch kernels (%s), not the portable ones: torch ran in this "
                       "process before they were asked for, or the environment sets others, so the weights have "
                       "this CPU's bits; set %s before torch runs for the same bits on every CPU",
                       kernels, " ".join(f"{k}={v}" for k, v in PORTABLE_TORCH.items()))
    return kernels


def check_dataset(data: Any, name: str) -> None:
    if not isinstance(data, Dataset):
        raise TypeError(f"{name}: expected a downwash.datasets.Dataset, got {type(data).__name__}")
    if len(data) == 0:
        raise ValueError(f"{name}: no samples")
    for key in ("dp", "v_a", "v_b", "R_a", "y"):
        if not np.all(np.isfinite(getattr(data, key))):
            raise ValueError(f"{name}.{key}: contains non-finite values")


def train_model(
    kind: str,
    train: Dataset,
    val: Dataset | None = None,
    config: TrainConfig | None = None,
    progress: bool = False,
    seed: int | None = None,
    **architecture: Any,
) -> tuple[torch.nn.Module, dict[str, Any]]:
    """Train a fresh model of ``kind`` (a trainable name of `downwash.registry.MODEL_KINDS`).

    train, val: `Dataset`s of one neighbour set and provenance (else DataError naming the
      difference). A per-neighbour kind trains on their real (target, neighbour) pairs, a
      model of sets on the padded sets. With no ``val``, a ``config.val_fraction`` share of
      the training FLIGHTS is held out for early stopping (never single samples of a flight).
    seed: weight init, shuffling and the flight split (default ``config.seed``).
    architecture: constructor arguments of the kind (e.g. ``feature_set="6"``).
    Input normalisation is fitted on the training part and stored in the model.
    Loss: mean squared error over samples and the three world axes, (m/s^2)^2.
    The weights of the epoch with the lowest validation loss are restored.

    Schedule: ``max(max_epochs, ceil(min_steps / steps per epoch))`` epochs with
    the learning rate decaying along a cosine from ``config.peak_lr(kind)`` to
    ``lr_final`` of it; early stopping after ``patience`` epochs (scaled by the
    same factor as the epochs) without improvement.

    Returns (model in eval mode, history) with history keys: train_loss, val_loss
    (per epoch, (m/s^2)^2), best_epoch, best_val_loss, epochs, planned_epochs,
    steps, lr, seconds, n_train, n_val, train_flights, val_flights, kind,
    architecture, seed, config, neighbours, provenance (of the training data), kernels
    (`torch_kernels`: the portable ones but where the module doc says).
    """
    if not MODEL_KINDS[kind].trainable:  # (an unknown kind: the registry's error, naming the kinds)
        raise ConfigError(f"model kind {kind!r} has no training of its own: wrap a trained per-neighbour model with "
                          f"downwash.checkpoint.wrap_pairwise; trainable kinds: {list(trainable_kinds())}")
    config = TrainConfig() if config is None else config
    if not isinstance(config, TrainConfig):
        raise TypeError(f"config: expected a downwash.train.TrainConfig, got {type(config).__name__}")
    seed = config.seed if seed is None else count("seed", seed, 0)
    check_dataset(train, "train")
    if val is None:
        train, val = split_by_flight(train, config.val_fraction, np.random.default_rng(seed))
    check_dataset(val, "val")
    if val.neighbours != train.neighbours:
        raise DataError(f"val: neighbour set {val.neighbours.describe()}, the training set has "
                        f"{train.neighbours.describe()}")
    merge_provenance([train.provenance, val.provenance], ["train", "val"])  # DataError if they differ
    kernels = training_kernels(config)
    old_threads = torch.get_num_threads()
    if config.num_threads is not None:
        torch.set_num_threads(config.num_threads)
    try:
        model, history = _train(kind, train, val, config, seed, progress, architecture)
        history["kernels"] = kernels
        return model, history
    finally:
        if config.num_threads is not None:
            torch.set_num_threads(old_threads)


def _train(kind: str, train: Dataset, val: Dataset, config: TrainConfig, seed: int, progress: bool,
           architecture: dict[str, Any]):
    start = time.perf_counter()
    level = logging.INFO if progress else logging.DEBUG
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = make_model(kind, **architecture)
    enc, y = model.encode_samples(train)
    enc_v, yv = model.encode_samples(val)
    model.fit_samples(enc, y)

    n, bs = y.shape[0], min(config.batch_size, y.shape[0])
    steps_per_epoch = math.ceil(n / bs)
    n_epochs = max(config.max_epochs, math.ceil(config.min_steps / steps_per_epoch))
    patience = math.ceil(config.patience * n_epochs / config.max_epochs)
    total_steps = n_epochs * steps_per_epoch
    lr = config.peak_lr(kind)
    opt = _adam(model, lr, config.weight_decay)
    gen = torch.Generator().manual_seed(seed)
    history: dict[str, Any] = {"train_loss": [], "val_loss": []}
    best, best_epoch, best_state, step = math.inf, -1, None, 0
    for epoch in range(n_epochs):
        model.train()
        perm = torch.randperm(n, generator=gen)
        shuffled, ys = enc.index(perm), y[perm]  # one gather per epoch, then contiguous slices
        total = torch.zeros(())
        for i in range(0, n, bs):
            for group in opt.param_groups:  # cosine decay from lr to lr * lr_final
                group["lr"] = lr * (config.lr_final + (1 - config.lr_final) * 0.5 * (1 + math.cos(math.pi * step / total_steps)))
            step += 1
            pred = model.decode_samples(shuffled.index(slice(i, i + bs)))
            loss = torch.mean((pred - ys[i : i + bs]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += loss.detach() * pred.shape[0]
        model.eval()
        with torch.no_grad():
            val_loss = float(torch.mean((model.decode_samples(enc_v) - yv) ** 2))
        train_loss = float(total) / n
        history["train_loss"].append(train_loss)
        history["val_loss"].append(val_loss)
        if not math.isfinite(val_loss):
            raise FloatingPointError(f"{kind}: validation loss is {val_loss} at epoch {epoch} (lr {lr} too high?)")
        if val_loss < best * (1.0 - config.min_delta):
            best, best_epoch = val_loss, epoch
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        logger.log(level, "%s epoch %3d/%d  train rmse %.4f  val rmse %.4f  best %.4f @ %d", kind, epoch, n_epochs,
                   math.sqrt(train_loss), math.sqrt(val_loss), math.sqrt(best), best_epoch)
        if epoch - best_epoch >= patience:
            break
    model.load_state_dict(best_state)
    if model.spectral_layers():
        model.settle_spectral_norm()  # eval mode then bounds every layer exactly
        with torch.no_grad():
            best = float(torch.mean((model.decode_samples(enc_v) - yv) ** 2))
    model.eval()
    history.update(
        best_epoch=best_epoch, best_val_loss=best, epochs=len(history["val_loss"]), planned_epochs=n_epochs,
        steps=step, lr=lr, seconds=time.perf_counter() - start, n_train=int(n), n_val=int(yv.shape[0]),
        train_flights=[int(f) for f in train.flights], val_flights=[int(f) for f in val.flights], kind=kind,
        architecture=model.architecture(), seed=seed, config=config.to_dict(),
        neighbours=train.neighbours.describe(), provenance=train.provenance,
    )  # fmt: skip
    if hasattr(model, "feature_set"):
        history["feature_set"] = model.feature_set
    logger.log(level, "%s: best val rmse %.4f at epoch %d of %d, %.2f s", kind, math.sqrt(best), best_epoch,
               history["epochs"], history["seconds"])
    return model, history


def _adam(model: torch.nn.Module, lr: float, weight_decay: float) -> torch.optim.Adam:
    """Fused Adam (one kernel per step: the cheapest on CPU), plain Adam where torch lacks it (< 2.4)."""
    try:
        return torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay, fused=True)
    except (RuntimeError, TypeError):  # pragma: no cover - old torch
        return torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)


def predict(model: torch.nn.Module, data: Dataset, batch_size: int = 65536) -> np.ndarray:
    """Model predictions (N, 3) m/s^2, float64 NumPy, for the samples the model is trained on: the
    real pairs of ``data`` for a per-neighbour kind, its targets for a model of sets (sets eval mode)."""
    return _decoded(model, model.encode_samples(data)[0], batch_size)


def _decoded(model: torch.nn.Module, enc: Any, batch_size: int = 65536) -> np.ndarray:
    """The model's predictions on an encoding, in batches, float64 NumPy (sets eval mode)."""
    model.eval()
    n = enc.x.shape[0]
    out = np.empty((n, 3))
    with torch.inference_mode():
        for i in range(0, n, batch_size):
            out[i : i + batch_size] = model.decode_samples(enc.index(slice(i, i + batch_size))).double().numpy()
    return out


def rmse(model: torch.nn.Module, data: Dataset) -> tuple[float, np.ndarray]:
    """(overall, per_axis (3,)) root-mean-square error in m/s^2 of the model on ``data`` (labels y).

    overall = sqrt(mean over samples and the three axes): the training loss's root.
    """
    enc, y = model.encode_samples(data)  # encoded once, for the predictions and their labels
    err = _decoded(model, enc) - y.double().numpy()
    return float(np.sqrt(np.mean(err**2))), np.sqrt(np.mean(err**2, axis=0))

def save_trained(path: str | os.PathLike, model: torch.nn.Module, history: dict[str, Any], train: Dataset) -> dict[str, Any]:
    """Checkpoint a trained model with the training record (without the per-epoch losses), the
    training data's summary and, for a model of sets, its neighbour set and the data's provenance
    (field, aggregation law)."""
    training = {k: v for k, v in history.items() if k not in ("train_loss", "val_loss", "provenance", "neighbours")}
    return save_checkpoint(path, model, {"training": training, "data": train.summary()},
                           neighbours=train.neighbours, provenance=train.provenance)
