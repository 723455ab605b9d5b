"""Training: MSE on all three world axes, Adam, mini-batches, early stopping by flight.

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

Deterministic for a seed: the weights are initialised under
``torch.random.fork_rng`` seeded with ``config.seed`` (the global RNG is left as
it was), mini-batches are shuffled by a seeded ``torch.Generator``, and the split
by flight uses ``numpy.random.default_rng(config.seed)``. Same seed and thread
count: bit-identical weights.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from downwash.datasets import split_by_flight
from downwash.labels import MODEL_INPUTS, SAMPLE_SCHEMA
from downwash.models import DeepSNMLP, DownwashModel, make_model

__all__ = ["DEFAULT_LR", "TrainConfig", "train_model", "rmse", "predict"]

logger = logging.getLogger(__name__)

_REQUIRED = {name: SAMPLE_SCHEMA[name][0] for name in (*MODEL_INPUTS, "y")}  # name -> trailing shape


# Peak learning rate per model kind, picked on synthetic data from the true field
# (51k samples, batch 2048, 60 epochs, cosine decay): the equivariant model kept
# improving up to 0.1, the shallow MLP was best at 0.03, the deep SN-MLP at
# 0.003-0.01 and diverged at 0.03.
DEFAULT_LR = {"equivariant": 5e-2, "equivariant_general": 5e-2, "shallow": 3e-2, "deep": 5e-3}


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (all validated on construction)."""

    lr: float | None = None  # peak Adam learning rate; None: DEFAULT_LR of the model kind
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
        }
        allowed = {
            "lr": "None or > 0", "lr_final": "in (0, 1]", "batch_size": "an int >= 1", "max_epochs": "an int >= 1",
            "min_steps": "an int >= 0", "patience": "an int >= 1", "min_delta": "in [0, 1)",
            "val_fraction": "in (0, 1)", "seed": "an int >= 0", "weight_decay": ">= 0",
            "num_threads": "None or an int >= 1",
        }  # fmt: skip
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"TrainConfig.{name}: expected {allowed[name]}, got {getattr(self, name)!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def peak_lr(self, kind: str) -> float:
        """The learning rate used for a model kind."""
        return DEFAULT_LR[kind] if self.lr is None else float(self.lr)


def _check_arrays(data: Any, name: str, need_flight: bool) -> None:
    n = None
    for key, trail in _REQUIRED.items():
        a = getattr(data, key, None)
        if a is None:
            raise TypeError(f"{name}: missing array '{key}' (need {sorted(_REQUIRED)} and 'flight')")
        n = np.shape(a)[0] if n is None else n
        if tuple(np.shape(a)) != (n, *trail):
            raise ValueError(f"{name}.{key}: expected shape {(n, *trail)}, got {tuple(np.shape(a))}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}.{key}: contains non-finite values")
    if need_flight and tuple(np.shape(getattr(data, "flight", None))) != (n,):
        raise ValueError(f"{name}.flight: expected shape ({n},) of flight ids")
    if not n:
        raise ValueError(f"{name}: no samples")


def _encode(model: DownwashModel, data: Any) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    with torch.no_grad():
        x, basis = model.encode(data.dp, data.v_a, data.v_b, data.R_a)
    return x, basis, torch.as_tensor(np.asarray(data.y), dtype=x.dtype)


def train_model(
    kind: str,
    train: Any,
    val: Any | None = None,
    config: TrainConfig | None = None,
    progress: bool = False,
    feature_set: str | None = None,
) -> tuple[DownwashModel, dict[str, Any]]:
    """Train a fresh model of ``kind`` (a name of `downwash.models.MODEL_KINDS`).

    train, val: objects with arrays dp, v_a, v_b, R_a, y (see `datasets.Dataset`)
      and, for train when ``val`` is None, flight ids ``flight``: a
      ``config.val_fraction`` share of the training FLIGHTS is then held out for
      early stopping (never single samples of a flight).
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
    feature_set, config.
    """
    config = TrainConfig() if config is None else config
    _check_arrays(train, "train", need_flight=val is None)
    if val is None:
        train, val = split_by_flight(train, config.val_fraction, np.random.default_rng(config.seed))
    else:
        _check_arrays(val, "val", need_flight=False)

    old_threads = torch.get_num_threads()
    if config.num_threads is not None:
        torch.set_num_threads(config.num_threads)
    try:
        return _train(kind, train, val, config, progress, feature_set)
    finally:
        if config.num_threads is not None:
            torch.set_num_threads(old_threads)


def _train(kind, train, val, config: TrainConfig, progress: bool, feature_set):
    start = time.perf_counter()
    level = logging.INFO if progress else logging.DEBUG
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = make_model(kind, feature_set)
    x, basis, y = _encode(model, train)
    xv, basis_v, yv = _encode(model, val)
    model.fit_normalization(x, model.output_targets(y, basis))

    n, bs = x.shape[0], min(config.batch_size, x.shape[0])
    steps_per_epoch = math.ceil(n / bs)
    n_epochs = max(config.max_epochs, math.ceil(config.min_steps / steps_per_epoch))
    patience = math.ceil(config.patience * n_epochs / config.max_epochs)
    total_steps = n_epochs * steps_per_epoch
    lr = config.peak_lr(kind)
    opt = _adam(model, lr, config.weight_decay)
    gen = torch.Generator().manual_seed(config.seed)
    history: dict[str, Any] = {"train_loss": [], "val_loss": []}
    best, best_epoch, best_state, step = math.inf, -1, None, 0
    for epoch in range(n_epochs):
        model.train()
        # One gather per epoch, then contiguous slices: cheaper than indexing every batch.
        perm = torch.randperm(n, generator=gen)
        xs, ys, bases = x[perm], y[perm], None if basis is None else basis[perm]
        total = torch.zeros(())
        for i in range(0, n, bs):
            for group in opt.param_groups:  # cosine decay from lr to lr * lr_final
                group["lr"] = lr * (config.lr_final + (1 - config.lr_final) * 0.5 * (1 + math.cos(math.pi * step / total_steps)))
            step += 1
            pred = model.decode(xs[i : i + bs], None if bases is None else bases[i : i + bs])
            loss = torch.mean((pred - ys[i : i + bs]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += loss.detach() * pred.shape[0]
        model.eval()
        with torch.no_grad():
            val_loss = float(torch.mean((model.decode(xv, basis_v) - yv) ** 2))
        train_loss = float(total) / n
        history["train_loss"].append(train_loss)
        history["val_loss"].append(val_loss)
        if not math.isfinite(val_loss):
            raise FloatingPointError(f"{kind}: validation loss is {val_loss} at epoch {epoch} (lr {lr} too high?)")
        if val_loss < best * (1.0 - config.min_delta):
            best, best_epoch = val_loss, epoch
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        logger.log(
            level, "%s epoch %3d/%d  train rmse %.4f  val rmse %.4f  best %.4f @ %d",
            kind, epoch, n_epochs, math.sqrt(train_loss), math.sqrt(val_loss), math.sqrt(best), best_epoch,
        )  # fmt: skip
        if epoch - best_epoch >= patience:
            break
    model.load_state_dict(best_state)
    if isinstance(model, DeepSNMLP):
        model.settle_spectral_norm()
        with torch.no_grad():
            best = float(torch.mean((model.decode(xv, basis_v) - yv) ** 2))
    model.eval()
    history.update(
        best_epoch=best_epoch,
        best_val_loss=best,
        epochs=len(history["val_loss"]),
        planned_epochs=n_epochs,
        steps=step,
        lr=lr,
        seconds=time.perf_counter() - start,
        n_train=int(n),
        n_val=int(xv.shape[0]),
        train_flights=_flight_ids(train),
        val_flights=_flight_ids(val),
        kind=model.kind,
        feature_set=model.feature_set,
        config=config.to_dict(),
    )
    logger.log(level, "%s: best val rmse %.4f at epoch %d of %d, %.2f s", kind, math.sqrt(best), best_epoch, history["epochs"], history["seconds"])
    return model, history


def _adam(model: torch.nn.Module, lr: float, weight_decay: float) -> torch.optim.Adam:
    """Fused Adam (one kernel per step: the cheapest on CPU), plain Adam where torch lacks it (< 2.4)."""
    try:
        return torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay, fused=True)
    except (RuntimeError, TypeError):  # pragma: no cover - old torch
        return torch.optim.Adam(model.parameters(), lr=lr, weight_decay=weight_decay)


def _flight_ids(data: Any) -> list[int]:
    f = getattr(data, "flight", None)
    return [] if f is None else [int(i) for i in np.unique(f)]


def predict(model: DownwashModel, data: Any, batch_size: int = 65536) -> np.ndarray:
    """Model predictions (N, 3) m/s^2, float64 NumPy, for the samples of ``data`` (sets eval mode)."""
    model.eval()
    n = np.shape(data.dp)[0]
    out = np.empty((n, 3))
    with torch.inference_mode():
        for i in range(0, n, batch_size):
            s = slice(i, i + batch_size)
            out[s] = model(data.dp[s], data.v_a[s], data.v_b[s], data.R_a[s]).double().numpy()
    return out


def rmse(model: DownwashModel, data: Any) -> tuple[float, np.ndarray]:
    """(overall, per_axis (3,)) root-mean-square error in m/s^2 of the model on ``data`` (labels y).

    overall = sqrt(mean over samples and the three axes): the training loss's root.
    """
    err = predict(model, data) - np.asarray(data.y, dtype=np.float64)
    return float(np.sqrt(np.mean(err**2))), np.sqrt(np.mean(err**2, axis=0))
