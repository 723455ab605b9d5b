"""Training the models for many vehicles, as `downwash.train` trains the pair models.

MSE on the three world axes, fused Adam, mini-batches, a cosine learning-rate decay and
early stopping on held-out FLIGHTS (the settings are `downwash.train.TrainConfig`). The
features, output bases and masks do not depend on the weights, so they are computed
once for the whole data set (`SwarmModel.encode`); a step runs only the networks.

Deterministic for a seed on the CPU: the weights are initialised under
``torch.random.fork_rng`` seeded with ``seed`` (the global RNG is left as it was),
mini-batches are shuffled by a seeded ``torch.Generator`` and the split by flight uses
``numpy.random.default_rng(seed)``. Same seed and thread count: bit-identical weights.

``summed_pairwise`` has no training of its own: wrap a trained two-vehicle model with
`downwash.swarm_models.wrap_pairwise`.
"""

from __future__ import annotations

import logging
import math
import os
import time
from typing import Any

import numpy as np
import torch

from downwash_core.errors import ConfigError, DataError
from downwash_core.validate import count
from downwash.datasets import split_by_flight
from downwash.swarm_data import SwarmDataset, merge_provenance
from downwash.swarm_models import (
    SWARM_MODEL_KINDS,
    TRAINABLE_SWARM_KINDS,
    SwarmModel,
    make_swarm_model,
    save_swarm_checkpoint,
)
from downwash.train import TrainConfig, _adam

__all__ = ["SWARM_DEFAULT_LR", "train_swarm_model", "predict_swarm", "swarm_rmse", "save_trained"]

logger = logging.getLogger(__name__)

# Peak learning rate per kind, picked on 3-vehicle flight data (four 30 s flights, a hovering
# leader and two followers on transects 0.5 and 1.0 m below; two more for validation; the
# TrainConfig defaults): validation RMSE (m/s^2) at lr 2e-3, 5e-3, 1e-2, 3e-2 was
# deepsets_equivariant 0.127, 0.119, 0.118, 0.119 and deepsets 0.149, 0.144, 0.146, 0.166
# (label-noise floor 0.105).
SWARM_DEFAULT_LR = {"deepsets_equivariant": 1e-2, "deepsets": 5e-3}


def _check(data: Any, name: str) -> None:
    if not isinstance(data, SwarmDataset):
        raise TypeError(f"{name}: expected a SwarmDataset, got {type(data).__name__}")
    if len(data) == 0:
        raise ValueError(f"{name}: no samples")
    for key in ("dp", "v_a", "v_b", "R_a", "y"):
        if not np.all(np.isfinite(getattr(data, key))):
            raise ValueError(f"{name}.{key}: contains non-finite values")


def train_swarm_model(
    kind: str,
    train_set: SwarmDataset,
    val_set: SwarmDataset | None = None,
    config: TrainConfig | None = None,
    seed: int | None = None,
    progress: bool = False,
    **architecture: Any,
) -> tuple[SwarmModel, dict[str, Any]]:
    """Train a fresh model of ``kind`` (a trainable name of `SWARM_MODEL_KINDS`).

    train_set, val_set: `SwarmDataset`s of one neighbour set and provenance (else
      DataError naming the difference). With no val_set, a ``config.val_fraction`` share
      of the training flights is held out for early stopping.
    seed: weight init, shuffling and the flight split (default ``config.seed``).
    architecture: constructor arguments of the kind (e.g. ``feature_set="5"``).
    Loss: mean squared error over targets and the three world axes, (m/s^2)^2; the
    weights of the best validation epoch are restored; the schedule is `downwash.train`'s.

    Returns (model in eval mode, history) with history keys: train_loss, val_loss (per
    epoch), best_epoch, best_val_loss, epochs, planned_epochs, steps, lr, seconds, n_train,
    n_val, train_flights, val_flights, kind, architecture, seed, config, neighbours,
    provenance (of the training data: field, aggregation law, ...).
    """
    if kind not in SWARM_MODEL_KINDS:
        raise ConfigError(f"swarm model kind: expected one of {sorted(SWARM_MODEL_KINDS)}, got {kind!r}")
    if kind not in TRAINABLE_SWARM_KINDS:
        raise ConfigError(f"swarm model kind {kind!r} has no training of its own: wrap a trained two-vehicle model "
                          f"with downwash.swarm_models.wrap_pairwise; trainable kinds: {list(TRAINABLE_SWARM_KINDS)}")
    config = TrainConfig() if config is None else config
    if not isinstance(config, TrainConfig):
        raise TypeError(f"config: expected a downwash.train.TrainConfig, got {type(config).__name__}")
    seed = config.seed if seed is None else count("seed", seed, 0)
    _check(train_set, "train_set")
    if val_set is None:
        train_set, val_set = split_by_flight(train_set, config.val_fraction, np.random.default_rng(seed))
    _check(val_set, "val_set")
    if val_set.neighbours != train_set.neighbours:
        raise DataError(f"val_set: neighbour set {val_set.neighbours.describe()}, the training set has "
                        f"{train_set.neighbours.describe()}")
    merge_provenance([train_set.provenance, val_set.provenance], ["train_set", "val_set"])  # DataError if they differ
    old_threads = torch.get_num_threads()
    if config.num_threads is not None:
        torch.set_num_threads(config.num_threads)
    try:
        return _train(kind, train_set, val_set, config, seed, progress, architecture)
    finally:
        if config.num_threads is not None:
            torch.set_num_threads(old_threads)


def _encode(model: SwarmModel, data: SwarmDataset):
    with torch.no_grad():
        enc = model.encode(data.dp, data.v_a, data.v_b, data.R_a, data.mask)
    return enc, torch.as_tensor(np.asarray(data.y), dtype=enc.x.dtype)


def _train(kind: str, train: SwarmDataset, val: SwarmDataset, config: TrainConfig, seed: int, progress: bool,
           architecture: dict[str, Any]):
    start = time.perf_counter()
    level = logging.INFO if progress else logging.DEBUG
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = make_swarm_model(kind, **architecture)
    enc, y = _encode(model, train)
    enc_v, yv = _encode(model, val)
    model.fit_normalization(enc, y)

    n, bs = y.shape[0], min(config.batch_size, y.shape[0])
    steps_per_epoch = math.ceil(n / bs)
    n_epochs = max(config.max_epochs, math.ceil(config.min_steps / steps_per_epoch))
    patience = math.ceil(config.patience * n_epochs / config.max_epochs)
    total_steps = n_epochs * steps_per_epoch
    lr = float(config.lr) if config.lr is not None else SWARM_DEFAULT_LR[kind]
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
                cosine = 0.5 * (1 + math.cos(math.pi * step / total_steps))
                group["lr"] = lr * (config.lr_final + (1 - config.lr_final) * cosine)
            step += 1
            pred = model.decode(shuffled.index(slice(i, i + bs)))
            loss = torch.mean((pred - ys[i : i + bs]) ** 2)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += loss.detach() * pred.shape[0]
        model.eval()
        with torch.no_grad():
            val_loss = float(torch.mean((model.decode(enc_v) - yv) ** 2))
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
    model.settle_spectral_norm()  # eval mode then bounds every layer exactly
    model.eval()
    with torch.no_grad():
        best = float(torch.mean((model.decode(enc_v) - yv) ** 2))
    history.update(
        best_epoch=best_epoch, best_val_loss=best, epochs=len(history["val_loss"]), planned_epochs=n_epochs,
        steps=step, lr=lr, seconds=time.perf_counter() - start, n_train=int(n), n_val=int(yv.shape[0]),
        train_flights=[int(f) for f in train.flights], val_flights=[int(f) for f in val.flights], kind=kind,
        architecture=model.architecture(), seed=seed, config=config.to_dict(),
        neighbours=train.neighbours.describe(), provenance=train.provenance,
    )  # fmt: skip
    logger.log(level, "%s: best val rmse %.4f at epoch %d of %d, %.2f s", kind, math.sqrt(best), best_epoch,
               history["epochs"], history["seconds"])
    return model, history


def predict_swarm(model: SwarmModel, data: SwarmDataset, batch_size: int = 65536) -> np.ndarray:
    """Model predictions (N, 3) m/s^2, float64 NumPy, for the samples of ``data`` (sets eval mode)."""
    model.eval()
    out = np.empty((len(data), 3))
    with torch.inference_mode():
        for i in range(0, len(data), batch_size):
            s = slice(i, i + batch_size)
            out[s] = model(data.dp[s], data.v_a[s], data.v_b[s], data.R_a[s], data.mask[s]).double().numpy()
    return out


def swarm_rmse(model: SwarmModel, data: SwarmDataset) -> tuple[float, np.ndarray]:
    """(overall, per_axis (3,)) root-mean-square error in m/s^2 on ``data`` (labels y)."""
    err = predict_swarm(model, data) - np.asarray(data.y, dtype=np.float64)
    return float(np.sqrt(np.mean(err**2))), np.sqrt(np.mean(err**2, axis=0))


def save_trained(path: str | os.PathLike, model: SwarmModel, history: dict[str, Any],
                 train_set: SwarmDataset) -> dict[str, Any]:
    """Checkpoint a trained model with its neighbour set, the training data's provenance (field,
    aggregation law) and summary, and the training record (without the per-epoch losses)."""
    training = {k: v for k, v in history.items() if k not in ("train_loss", "val_loss", "provenance", "neighbours")}
    return save_swarm_checkpoint(path, model, train_set.neighbours, train_set.provenance,
                                 meta={"training": training, "data": train_set.summary()})
