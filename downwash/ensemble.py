"""Ensemble training: many models of one kind trained as ONE batched network.

    results = train_ensemble("deep", [data_a, data_b, data_c], seeds=[0, 1, 2])
    for model, history in results: ...       # ordinary DownwashModel instances

Each member is trained with the semantics of `downwash.train.train_model`, and
with one intra-op thread its weights and history are bit-identical to that
member's own `train_model` (see "Equivalence"):

* its own split by flight for early stopping (``split_by_flight`` with
  ``numpy.random.default_rng(seed)``) when no validation set is given;
* its own model, initialised under ``torch.random.fork_rng`` seeded with its seed,
  and its own input normalisation fitted on its own training part;
* its own mini-batch order (a ``torch.Generator`` seeded with its seed, one
  ``randperm`` per epoch), batch size, number of epochs (``min_steps``), cosine
  learning-rate schedule, patience and early stopping;
* MSE on all three world axes, fused Adam, best-epoch restore, and for the deep
  model the spectral-norm estimates settled after training.

This module holds the training loop; the batched network is
`downwash.ensemble_network`, the members' set-up and stacked state `downwash.ensemble_members`,
the deep members' final settling `downwash.ensemble_settle`.

How the members are batched
---------------------------
The weights of the active members are stacked, ``W (M, out, in)``, ``b (M, out)``.
One global step advances every active member by one of ITS OWN steps: at each of
its epochs a member draws its permutation and gathers its (normalised) rows as
`train_model` does, and the step's batch ``x (M, B, k)`` stacks each member's next
slice; B is the largest batch of the step, rounded up to a multiple of 16. A
member with a shorter batch (its epoch's last one, or a smaller data set) is
padded with zero rows of loss weight 0. Each layer is one ``baddbmm`` over the
members (`downwash.ensemble_network`: the layers of every kind, the deep model's
spectral normalisation); the loss ``sum_m sum_rows w (pred - y)^2`` with
``w = 1 / (3 b_m)`` on the member's own rows is the sum of the members' batch
means, so one backward gives every member its own gradient. Adam is torch's own
fused kernel (`torch.optim.adam.adam`, as in `train_model`) on per-member views
of the stacked tensors, one call per group of members that share a learning rate
and weight decay at this step. Validation runs at each member's epoch ends, as
one batched eval-mode forward for the members whose epochs end at that step, each
member's mean taken over its own rows. A member that stops (early stopping or the
end of its schedule) gets its best epoch's state dict, as in `train_model`, and
leaves the stacks. At the end each deep member is a real `DeepSNMLP` with its best
state, whose spectral norms are settled as `DeepSNMLP.settle_spectral_norm` does
after `train_model`, the members side by side (`downwash.ensemble_settle`).

Equivalence
-----------
Every batched operation was chosen to do, per member, the arithmetic that
`train_model` does, and this was checked operation by operation (the list, with
padding and alignment, is in `downwash.ensemble_network`).
`tests/test_ensemble.py` checks bit-identity of weights, spectral-norm vectors and
histories for every model kind, for ensembles of one and of several members of
different sizes, configs and early-stopping epochs. This holds for one intra-op
thread (the default `TrainConfig.num_threads`; more threads split reductions
differently in both trainings) on x86-64 with torch's MKL build. It rests on the
behaviour of the BLAS, not on the algorithm: with another BLAS a batched product
could round differently from the single one, and a member would then differ from
its own training by float32 rounding per step, amplified over the training like
any change of operation order (the tests would then fail rather than hide it).

Speed: a step's cost is mostly arithmetic and memory traffic on the (M, B, width)
activations, not per-operation overhead, so an ensemble is cheaper than its
members one after another by what it saves on overhead (measured on 2 cores:
about 1.4-1.6x for the one-hidden-layer models, 1.1-1.3x for the deep model);
independent ensembles in separate processes use further cores. For the deep model
about 5 members is the fastest per member (measured per member-step: 14 ms alone,
8 ms with 2, 6.6 ms with 5, 7.1 ms with 10, 8 ms with 20: beyond that the
activations outgrow the caches). Where most members of a step have padded batches
(small data sets, one batch per epoch) every member's weight gradient is its own
``mm`` instead of a batched product that would mostly be recomputed.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any, Sequence

import torch
from torch.optim.adam import adam as _adam_functional

from downwash_core.errors import ConfigError
from downwash.ensemble_members import Member, Stacks, member_configs, member_vals, prepare_member
from downwash.ensemble_network import aligned_stack, forward_members, Layer, member_layers, pad_rows, per_member, round_rows
from downwash.ensemble_settle import settle_models
from downwash.features import assemble
from downwash.models import PAIRWISE_KINDS, DeepSNMLP, DownwashModel
from downwash.registry import MODEL_KINDS
from downwash.train import TrainConfig, training_kernels

__all__ = ["train_ensemble"]

logger = logging.getLogger(__name__)

# torch.optim.Adam's defaults, which `downwash.train` uses
_BETA1, _BETA2, _ADAM_EPS = 0.9, 0.999, 1e-8


def _fused_adam_available() -> bool:
    """Whether torch has the fused CPU Adam that `downwash.train` prefers (torch >= 2.4)."""
    try:
        torch.optim.Adam([torch.zeros(1, requires_grad=True)], fused=True)
        return True
    except (RuntimeError, TypeError):  # pragma: no cover - old torch
        return False


_FUSED: bool | None = None


def train_ensemble(
    kind: str,
    datasets: Sequence[Any],
    configs: TrainConfig | Sequence[TrainConfig] | None = None,
    val: Any | Sequence[Any] | None = None,
    *,
    seeds: Sequence[int] | None = None,
    feature_set: str | None = None,
    progress: bool = False,
) -> list[tuple[DownwashModel, dict[str, Any]]]:
    """Train one model of ``kind`` per data set, all as one batched network.

    datasets: one training set per member (objects like `datasets.Dataset`, as for
      `train_model`; sizes may differ).
    configs: one `TrainConfig` for all members, or one per member (default
      ``TrainConfig()``); ``num_threads`` and ``portable`` must agree.
    val: None (each member holds out a ``val_fraction`` of its own flights, split
      with its own seed), one validation set for all members, or one per member.
    seeds: one seed per member, replacing the configs' ``seed``.

    Returns ``[(model, history), ...]`` in member order: exactly what `train_model`
    returns for that member's data and config (see the module doc), with history
    keys added: ``ensemble_size`` and ``member``; ``seconds`` is the wall time of
    the whole ensemble. Raises `ConfigError` for an unknown kind, an empty list or
    lists of mismatched lengths; the data checks and errors of `train_model`
    (naming ``datasets[i]``); FloatingPointError naming the member whose
    validation loss is not finite (which ends the whole ensemble).
    """
    if kind not in PAIRWISE_KINDS and MODEL_KINDS[kind]:  # (an unknown kind: the registry's error)
        raise ConfigError(f"model kind {kind!r}: an ensemble is of per-neighbour kinds, one of "
                          f"{', '.join(PAIRWISE_KINDS)}")
    if not isinstance(datasets, (list, tuple)):
        raise ConfigError(f"datasets: expected a list of data sets (one per member), got {type(datasets).__name__}")
    if not datasets:
        raise ConfigError("datasets: empty list, need at least one data set (one per member)")
    n = len(datasets)
    configs = member_configs(n, configs, seeds)
    vals = member_vals(n, val)

    kernels = training_kernels(configs[0])
    threads = configs[0].num_threads
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        out = _train(kind, list(datasets), vals, configs, progress, feature_set)
        for _, history in out:
            history["kernels"] = kernels
        return out
    finally:
        if threads is not None:
            torch.set_num_threads(old_threads)


def _train(kind, datasets, vals, configs, progress, feature_set):
    start = time.perf_counter()
    level = logging.INFO if progress else logging.DEBUG
    shared_val: dict[int, tuple] = {}
    members = [prepare_member(i, kind, train, val, config, feature_set, shared_val)
               for i, (train, val, config) in enumerate(zip(datasets, vals, configs))]
    plan, _, _ = member_layers(members[0].model)
    # rows per step are padded to a multiple of 16, so that every member's slice of every
    # (M, rows, width) activation starts on a 64-byte boundary (see aligned_stack)
    width = round_rows(max(mb.bs for mb in members))
    dtype = members[0].x.dtype

    active = list(members)
    stacks = Stacks.from_members(active)
    step = 0
    while active:
        # -- this step's rows: each member's next batch of its own epoch order ------------------
        sizes = []
        for mb in active:
            if mb.batch == 0:  # new epoch: the same permutation and gather as train_model
                mb.shuffle(width)
            sizes.append(mb.batch_rows())
        m_act, b_max = len(active), round_rows(max(sizes))
        short = [(j, s) for j, s in enumerate(sizes) if s < b_max]
        xb, yb, bb = (
            None if active[0].epoch_data[i] is None
            else torch.stack([mb.epoch_data[i][mb.batch, :b_max] for mb in active])
            for i in range(3)
        )  # fmt: skip
        # 1 / (3 b) per member: mean's backward factor, to the bit (same-precision division);
        # 0 on padding rows
        sizes_t = torch.tensor(sizes, dtype=dtype)
        inv = torch.ones(m_act, dtype=dtype) / (3.0 * sizes_t)
        real = torch.arange(b_max)[None, :] < sizes_t[:, None]
        weight = torch.where(real, inv[:, None], 0.0)[..., None]

        # -- forward, loss, backward -------------------------------------------------------------
        pred = forward_members(plan, stacks.params, stacks.p_views, stacks.buf_views, xb, short, training=True,
                        buffers=stacks.buffers)
        pred = pred * stacks.out_std + stacks.out_mean
        if bb is not None:
            pred = assemble(pred, bb)
        sq = (pred - yb) ** 2
        grads = torch.autograd.grad((sq * weight).sum(), stacks.params)

        with torch.no_grad():
            # the recorded training loss: each member's batch mean, as train_model accumulates it
            losses = sq.mean((1, 2))
            for j, s in short:
                losses[j] = sq[j, :s].mean()
            stacks.totals += losses * sizes_t
            _adam_step(active, stacks, grads)

        # -- epoch ends, early stopping ----------------------------------------------------------
        for mb in active:
            mb.step += 1
            mb.batch += 1
        ending = [j for j, mb in enumerate(active) if mb.batch == mb.steps_per_epoch]
        done = []
        if ending:
            for j, val_loss in zip(ending, _validate(plan, stacks, active, ending)):
                if _end_epoch(kind, active[j], stacks, j, val_loss):
                    done.append(j)
                else:
                    stacks.totals[j] = 0.0
        step += 1
        if done:
            for j in done:
                _finish(kind, active[j], level, len(members))
            keep = [j for j in range(len(active)) if j not in done]
            active = [active[j] for j in keep]
            if active:
                stacks = stacks.keep(keep)
    deep = [mb for mb in members if isinstance(mb.model, DeepSNMLP)]
    if deep:
        _settle_members(deep, level)
    seconds = time.perf_counter() - start
    for mb in members:
        mb.history["seconds"] = seconds
    logger.log(level, "%s ensemble of %d: %d steps, %.2f s", kind, len(members), step, seconds)
    return [(mb.model, mb.history) for mb in members]


def _adam_step(active: list[Member], stacks: Stacks, grads: Sequence[torch.Tensor]) -> None:
    """torch's Adam (fused where available, as `downwash.train`) on each member's views.

    Members that share a learning rate and weight decay at this step go in one call.
    """
    global _FUSED
    if _FUSED is None:
        _FUSED = _fused_adam_available()
    grad_views = per_member(list(grads), len(active))
    groups: dict[tuple[float, float], list[int]] = {}
    for j, mb in enumerate(active):
        groups.setdefault((mb.current_lr(), mb.config.weight_decay), []).append(j)
    for (lr, weight_decay), js in groups.items():
        params, gs, ea, eas, steps = [], [], [], [], []
        for j in js:
            params += stacks.p_views[j]
            gs += grad_views[j]
            ea += stacks.ea_views[j]
            eas += stacks.eas_views[j]
            steps += stacks.step_views[j]
        _adam_functional(
            params, gs, ea, eas, [], steps, fused=True if _FUSED else None,
            amsgrad=False, beta1=_BETA1, beta2=_BETA2, lr=lr, weight_decay=weight_decay, eps=_ADAM_EPS, maximize=False,
        )  # fmt: skip


def _load(mb: Member, stacks: Stacks, j: int) -> None:
    """Copy member j's current weights and power-iteration vectors into its model."""
    with torch.no_grad():
        for dst, src in zip(mb.params, stacks.p_views[j]):
            dst.copy_(src)
        for dst, src in zip(mb.buffers, stacks.buf_views[j]):
            dst.copy_(src)


def _validate(plan: list[Layer], stacks: Stacks, active: list[Member], ending: list[int]) -> list[float]:
    """Validation losses of the members at positions ``ending``, as `train_model` computes them.

    ``mean((decode(xv, basis_v) - yv)^2)`` in eval mode, one batched forward for all of
    them: the forward is row by row (padding rows change nothing), and each member's
    mean is taken over its own rows.
    """
    members = [active[j] for j in ending]
    with torch.no_grad():
        if len(ending) == len(active):
            params, p_views, buf_views = stacks.params, stacks.p_views, stacks.buf_views
            out_std, out_mean = stacks.out_std, stacks.out_mean
        else:
            p_views = [stacks.p_views[j] for j in ending]
            buf_views = [stacks.buf_views[j] for j in ending]
            params = [aligned_stack([views[i] for views in p_views]) for i in range(len(p_views[0]))]
            ix = torch.as_tensor(ending, dtype=torch.long)
            out_std, out_mean = stacks.out_std.index_select(0, ix), stacks.out_mean.index_select(0, ix)
        rows = round_rows(max(mb.xv_n.shape[0] for mb in members))
        x = torch.stack([pad_rows(mb.xv_n, rows) for mb in members])
        pred = forward_members(plan, params, p_views, buf_views, x, [], training=False) * out_std + out_mean
        if members[0].basis_v is not None:
            pred = assemble(pred, torch.stack([pad_rows(mb.basis_v, rows) for mb in members]))
        return [float(torch.mean((pred[e, : mb.yv.shape[0]] - mb.yv) ** 2)) for e, mb in enumerate(members)]


def _end_epoch(kind: str, mb: Member, stacks: Stacks, j: int, val_loss: float) -> bool:
    """Bookkeeping and early stopping at the end of one of the member's epochs; True when it stops."""
    epoch = mb.epoch
    train_loss = float(stacks.totals[j]) / mb.n
    mb.history["train_loss"].append(train_loss)
    mb.history["val_loss"].append(val_loss)
    if not math.isfinite(val_loss):
        raise FloatingPointError(
            f"{kind} member {mb.index}: validation loss is {val_loss} at epoch {epoch} (lr {mb.lr} too high?)"
        )
    if val_loss < mb.best * (1.0 - mb.config.min_delta):
        mb.best, mb.best_epoch = val_loss, epoch
        _load(mb, stacks, j)
        mb.best_state = {k: v.detach().clone() for k, v in mb.model.state_dict().items()}
    logger.debug(
        "%s member %d epoch %3d/%d  train rmse %.4f  val rmse %.4f  best %.4f @ %d",
        kind, mb.index, epoch, mb.n_epochs, math.sqrt(train_loss), math.sqrt(val_loss), math.sqrt(mb.best), mb.best_epoch,
    )  # fmt: skip
    mb.epoch += 1
    mb.batch = 0
    return epoch - mb.best_epoch >= mb.patience or mb.epoch >= mb.n_epochs


def _finish(kind: str, mb: Member, level: int, size: int) -> None:
    """Best-epoch restore and history, as at the end of `train_model`; the deep model's
    spectral norms are settled later, for all members at once (`_settle_members`)."""
    model = mb.model
    model.eval()  # as train_model's model is after its last validation (no power iteration in decode)
    model.load_state_dict(mb.best_state)
    mb.history.update(
        best_epoch=mb.best_epoch, best_val_loss=mb.best, epochs=len(mb.history["val_loss"]), planned_epochs=mb.n_epochs,
        steps=mb.step, lr=mb.lr, n_train=int(mb.n), n_val=int(mb.xv.shape[0]),
        train_flights=[int(f) for f in mb.train.flights], val_flights=[int(f) for f in mb.val.flights],
        kind=model.kind, architecture=model.architecture(), seed=mb.config.seed, config=mb.config.to_dict(),
        neighbours=mb.train.neighbours.describe(), provenance=mb.train.provenance, feature_set=model.feature_set,
        ensemble_size=size, member=mb.index,
    )  # fmt: skip
    mb.train = mb.val = None  # free the member's data (the deep model keeps its validation set)
    mb.xv_n = mb.x = mb.y = mb.basis = mb.epoch_data = mb.best_state = None
    if isinstance(model, DeepSNMLP):
        return
    mb.xv = mb.yv = mb.basis_v = None
    _log_member(kind, mb, level)


def _log_member(kind: str, mb: Member, level: int) -> None:
    logger.log(level, "%s member %d: best val rmse %.4f at epoch %d of %d", kind, mb.index,
               math.sqrt(mb.history["best_val_loss"]), mb.best_epoch, mb.history["epochs"])


def _settle_members(members: list[Member], level: int) -> None:
    """`DeepSNMLP.settle_spectral_norm` of every member, then its validation loss, as `train_model` ends.

    The power iterations of one layer run for all members side by side, chunk by
    chunk as in `settle_spectral_norm` (20 iterations, then the float32 estimate
    ``dot(u, mv(W, v))`` against the previous chunk's), each member stopping at its
    own chunk: ``mv`` and ``dot`` per member, the normalisation over the stack
    (`downwash.ensemble_settle`).
    """
    settle_models([mb.model for mb in members])
    for mb in members:
        with torch.no_grad():
            mb.history["best_val_loss"] = float(torch.mean((mb.model.decode(mb.xv, mb.basis_v) - mb.yv) ** 2))
        mb.xv = mb.yv = mb.basis_v = None
        _log_member(mb.model.kind, mb, level)
