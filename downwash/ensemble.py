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

How the members are batched
---------------------------
The weights of the active members are stacked, ``W (M, out, in)``, ``b (M, out)``.
One global step advances every active member by one of ITS OWN steps: at each of
its epochs a member draws its permutation and gathers its (normalised) rows as
`train_model` does, and the step's batch ``x (M, B, k)`` stacks each member's next
slice; B is the largest batch of the step, rounded up to a multiple of 16. A
member with a shorter batch (its epoch's last one, or a smaller data set) is
padded with zero rows of loss weight 0. Each layer is one ``baddbmm`` over the
members (`_BatchedLinear`); the loss ``sum_m sum_rows w (pred - y)^2`` with
``w = 1 / (3 b_m)`` on the member's own rows is the sum of the members' batch
means, so one backward gives every member its own gradient. Adam is torch's own
fused kernel (`torch.optim.adam.adam`, as in `train_model`) on per-member views
of the stacked tensors, one call per group of members that share a learning rate
and weight decay at this step. Validation runs at each member's epoch ends, as
one batched eval-mode forward for the members whose epochs end at that step, each
member's mean taken over its own rows. A member that stops (early stopping or the
end of its schedule) gets its best epoch's state dict, as in `train_model`, and
leaves the stacks.

* ``shallow``, ``equivariant`` (and ``equivariant_general``): two batched layers; the
  output basis of an equivariant model is gathered with the rows and applied with
  `features.assemble`, as in `DownwashModel.decode`.
* ``deep``: 8 spectrally normalised layers. torch's parametrisation runs one power
  iteration per training forward on its ``u, v`` and divides the weight by
  ``sigma = vdot(u, mv(W, v))``, the gradient flowing through ``sigma``. Here
  ``u, v`` are stacked ``(M, out)``, ``(M, in)`` buffers. The BLAS calls run per
  member with exactly torch's operations (``torch.mv`` of the power iteration and
  of ``sigma``, ``torch.vdot``); ``F.normalize`` runs over the stack (the norm of a
  row of the stack is the norm of that vector alone, measured bit for bit; the
  rest is elementwise) and ``gamma * (W / sigma)`` is one custom autograd function
  (`_SpectralWeights`) whose backward applies torch's derivative formulas for that
  graph over the stack, only the reduction to ``sigma``'s gradient per member.
  Eval mode (validation) uses the stored ``u, v``, as torch does. At the end each
  member is a real `DeepSNMLP` with its best state, whose spectral norms are
  settled as `DeepSNMLP.settle_spectral_norm` does after `train_model` (the same
  chunks of iterations and stopping test per member, the members side by side:
  `_settle_members`). A power iteration by ``bmm`` on the stacked weights would
  save the per-member ``mv`` calls, but would not be bit-identical: ``bmm`` and
  ``mv``/``vdot`` accumulate in different orders.

Equivalence
-----------
Every batched operation was chosen to do, per member, the arithmetic that
`train_model` does, and this was checked operation by operation:

* ``baddbmm`` per member is the ``gemm`` of ``addmm`` (forward and input
  gradient); the weight gradient is ``g^T x`` as autograd computes it for
  ``F.linear`` (``x^T g``, transposed, rounds differently); the bias gradient is a
  sum over rows; ``1 / (3 b)`` is ``mean``'s backward factor to the bit;
  normalisation, ReLU, the output scaling, `features.assemble` and Adam are
  elementwise or per sample.
* Padding: a reduction over rows of a padded batch is blocked differently by MKL
  (measured: 1e-5 relative differences), so a member padded in a step gets its
  weight and bias gradients recomputed from its own rows (one small ``mm`` per
  layer).
* Alignment: MKL's ``mv``, ``vdot`` and small ``gemm`` round differently when an
  operand or output is not 64-byte aligned (measured for 3x25 and 25x40 matrices),
  and torch's own tensors always are; so each member's slice of every stacked
  tensor starts on a 64-byte boundary (`_aligned_stack`, batch rows in multiples
  of 16).

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

import dataclasses
import inspect
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn
from torch.optim.adam import adam as _adam_functional

from downwash_core.errors import ConfigError
from downwash.datasets import split_by_flight
from downwash.features import assemble
from downwash.models import PAIRWISE_KINDS, DeepSNMLP, DownwashModel, _SpectralLinear, settle_spectral_norm
from downwash.registry import make_model
from downwash.train import TrainConfig, _check

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


class _BatchedLinear(torch.autograd.Function):
    """``x (M, B, in) @ W (M, out, in)^T + b (M, out)``: one ``F.linear`` per member, batched.

    Backward as autograd does it for ``F.linear`` of one member (``addmm``):
    ``gx = g W``, ``gW = g^T x``, ``gb = sum_rows g``; for the members in ``short``
    (``(j, rows)``: a batch padded beyond its ``rows`` real rows) ``gW`` and ``gb``
    are recomputed from the real rows only, so that the reduction over rows has
    the member's own length (see the module doc); when most members are short (small
    data sets, one batch per epoch), every member's ``gW`` is its own ``mm`` instead
    of a batched product that would mostly be redone.
    """

    @staticmethod
    def forward(ctx, x, weight, bias, short):
        ctx.save_for_backward(x, weight)
        ctx.short = short
        return torch.baddbmm(bias.unsqueeze(1), x, weight.transpose(1, 2))

    @staticmethod
    def backward(ctx, g):
        x, weight = ctx.saved_tensors
        gx = g.bmm(weight) if ctx.needs_input_grad[0] else None
        gb = g.sum(1)
        m = g.shape[0]
        if 2 * len(ctx.short) < m:
            gw = torch.bmm(g.transpose(1, 2), x, out=_aligned_empty(weight.shape, g.dtype))
            rows_of = ctx.short
        else:  # mostly padded batches (small data sets): every member's own product, no batched one to redo
            gw = _aligned_empty(weight.shape, g.dtype)
            rows_of = [(j, dict(ctx.short).get(j, g.shape[1])) for j in range(m)]
        for j, rows in rows_of:
            gw[j] = g[j, :rows].t().mm(x[j, :rows])
        for j, rows in ctx.short:
            gb[j] = g[j, :rows].sum(0)
        return gx, gw, gb, None


@dataclass
class _Layer:
    """One layer of the network: ``relu``, ``linear`` or ``spectral`` (index into the parameter list)."""

    kind: str
    weight: int = -1  # index of the weight in the member's parameter list
    bias: int = -1
    u: int = -1  # spectral: index of u, v in the member's buffer list
    v: int = -1
    gamma: float = 1.0
    eps: float = 1e-12
    n_power_iterations: int = 1


def _layers(model: DownwashModel) -> tuple[list[_Layer], list[torch.Tensor], list[torch.Tensor]]:
    """The layer plan of a model, its trainable tensors and its power-iteration buffers (in plan order)."""
    plan: list[_Layer] = []
    params: list[torch.Tensor] = []
    buffers: list[torch.Tensor] = []
    for m in model.net:
        if isinstance(m, nn.ReLU):
            plan.append(_Layer("relu"))
        elif isinstance(m, nn.Linear):
            plan.append(_Layer("linear", len(params), len(params) + 1))
            params += [m.weight, m.bias]
        elif isinstance(m, _SpectralLinear):
            param = m.linear.parametrizations.weight[0]
            plan.append(_Layer("spectral", len(params), len(params) + 1, len(buffers), len(buffers) + 1,
                               m.gamma, param.eps, param.n_power_iterations))
            params += [m.linear.parametrizations.weight.original, m.linear.bias]
            buffers += [param._u, param._v]
        else:  # pragma: no cover - guards future architectures
            raise TypeError(f"train_ensemble: unsupported layer {type(m).__name__}")
    if len(params) != len(list(model.parameters())):  # pragma: no cover - guards future architectures
        raise TypeError(f"train_ensemble: {model.kind} has parameters outside its layers")
    for name in ("decode", "output_targets"):  # the batched network mirrors these two
        if getattr(type(model), name) is not getattr(DownwashModel, name):  # pragma: no cover
            raise TypeError(f"train_ensemble: {type(model).__name__} overrides DownwashModel.{name}")
    return plan, params, buffers


@dataclass
class _Member:
    """One member's schedule, data and bookkeeping (its weights live in the stacks)."""

    index: int
    config: TrainConfig
    model: DownwashModel
    params: list[torch.Tensor]  # the model's own tensors, in plan order (eval copies and final state)
    buffers: list[torch.Tensor]
    train: Any
    val: Any
    xv: torch.Tensor  # validation features, basis, labels
    basis_v: torch.Tensor | None
    yv: torch.Tensor
    n: int
    bs: int
    steps_per_epoch: int
    n_epochs: int
    patience: int
    total_steps: int
    lr: float
    gen: torch.Generator
    x: torch.Tensor | None = None  # normalised training features (n, k), targets (n, 3), basis (n, m, 3)
    xv_n: torch.Tensor | None = None  # normalised validation features
    y: torch.Tensor | None = None
    basis: torch.Tensor | None = None
    epoch: int = 0
    batch: int = 0
    step: int = 0
    best: float = math.inf
    best_epoch: int = -1
    best_state: dict | None = None
    epoch_data: tuple | None = None  # this epoch's shuffled x, y, basis as (steps_per_epoch, width, ...) zero-padded
    history: dict = field(default_factory=lambda: {"train_loss": [], "val_loss": []})

    def batch_rows(self) -> int:
        return min(self.bs, self.n - self.batch * self.bs)

    def shuffle(self, width: int) -> None:
        """Start an epoch: train_model's permutation and gather, laid out one batch per row of slots."""
        perm = torch.randperm(self.n, generator=self.gen)
        self.epoch_data = tuple(
            None if t is None else _batch_slots(t.index_select(0, perm), self.steps_per_epoch, self.bs, width)
            for t in (self.x, self.y, self.basis)
        )  # index_select: the same rows as train_model's x[perm], three times faster

    def current_lr(self) -> float:
        """The cosine schedule of `train_model`, term for term."""
        c = self.config
        return self.lr * (c.lr_final + (1 - c.lr_final) * 0.5 * (1 + math.cos(math.pi * self.step / self.total_steps)))


class _Stacks:
    """The active members' weights, Adam state and power-iteration vectors, stacked on dim 0."""

    def __init__(self, params: list[torch.Tensor], exp_avg, exp_avg_sq, steps, buffers, out_std, out_mean, totals):
        self.params = [p.requires_grad_(True) for p in params]
        self.exp_avg, self.exp_avg_sq, self.steps = exp_avg, exp_avg_sq, steps
        self.buffers, self.out_std, self.out_mean, self.totals = buffers, out_std, out_mean, totals
        # per-member views for Adam and the power iteration (in-place updates reach the stacks)
        m = params[0].shape[0]
        detached = [p.detach() for p in self.params]
        self.p_views = _per_member(detached, m)
        self.ea_views = _per_member(exp_avg, m)
        self.eas_views = _per_member(exp_avg_sq, m)
        self.step_views = [list(row.unbind(0)) for row in steps.unbind(0)]
        self.buf_views = _per_member(buffers, m)

    @classmethod
    def from_members(cls, members: list[_Member]) -> "_Stacks":
        with torch.no_grad():
            params = [_aligned_stack([mb.params[i].detach() for mb in members]) for i in range(len(members[0].params))]
            buffers = [_aligned_stack([mb.buffers[i] for mb in members]) for i in range(len(members[0].buffers))]
            out_std = torch.stack([mb.model.out_std for mb in members])[:, None, :]
            out_mean = torch.stack([mb.model.out_mean for mb in members])[:, None, :]
        exp_avg = [torch.zeros_like(p) for p in params]
        exp_avg_sq = [torch.zeros_like(p) for p in params]
        steps = torch.zeros(len(members), len(params), dtype=torch.float32)
        totals = torch.zeros(len(members), dtype=params[0].dtype)
        return cls(params, exp_avg, exp_avg_sq, steps, buffers, out_std, out_mean, totals)

    def keep(self, index: list[int]) -> "_Stacks":
        """The stacks of the members at positions ``index`` (copies)."""
        ix = torch.as_tensor(index, dtype=torch.long)
        with torch.no_grad():
            sel = lambda ts: [_aligned_stack(t.detach().unbind(0), index) for t in ts]  # noqa: E731
            return _Stacks(sel(self.params), sel(self.exp_avg), sel(self.exp_avg_sq), self.steps.index_select(0, ix),
                           sel(self.buffers), self.out_std.index_select(0, ix), self.out_mean.index_select(0, ix),
                           self.totals.index_select(0, ix))


_ALIGN_BYTES = 64  # torch's CPU allocator aligns every tensor to 64 bytes
_ROW_ALIGN = 16  # batch rows are padded to a multiple of this: 64 bytes of float32 per feature column


def _aligned_stack(tensors: Sequence[torch.Tensor], index: Sequence[int] | None = None) -> torch.Tensor:
    """``torch.stack(tensors[index])`` with every member's slice starting on a 64-byte boundary.

    MKL rounds differently for an operand or output that is not 64-byte aligned
    (measured: ``mv`` of a 3x25 matrix, ``vdot`` of length 25, the 3x25 weight
    gradient of ``bmm``), and a standalone tensor always is aligned; so each
    member's slice gets a padded stride.
    """
    if index is not None:
        tensors = [tensors[i] for i in index]
    out = _aligned_empty((len(tensors), *tensors[0].shape), tensors[0].dtype)
    for dst, src in zip(out.unbind(0), tensors):
        dst.copy_(src)
    return out


def _aligned_stride(numel: int, element_size: int) -> int:
    """``numel`` rounded up to a whole number of 64-byte blocks (in elements)."""
    per = max(1, _ALIGN_BYTES // element_size)
    return -(-numel // per) * per


def _aligned_empty(shape: Sequence[int], dtype: torch.dtype) -> torch.Tensor:
    """An uninitialised (M, ...) tensor whose member slices are contiguous and 64-byte aligned."""
    inner = shape[1:]
    numel = math.prod(inner)
    contiguous = [math.prod(inner[d + 1 :]) for d in range(len(inner))]
    stride = _aligned_stride(numel, torch.empty((), dtype=dtype).element_size())
    return torch.empty_strided(tuple(shape), (stride, *contiguous), dtype=dtype)


def _batch_slots(t: torch.Tensor, steps: int, bs: int, width: int) -> torch.Tensor:
    """Rows t (n, ...) as (steps, width, ...): batch i in slot i, zero rows after its end."""
    n = t.shape[0]
    out = t.new_zeros((steps, width, *t.shape[1:]))
    if steps * bs == n:
        out[:, :bs] = t.view(steps, bs, *t.shape[1:])
    else:
        out[:-1, :bs] = t[: (steps - 1) * bs].view(steps - 1, bs, *t.shape[1:])
        out[-1, : n - (steps - 1) * bs] = t[(steps - 1) * bs :]
    return out


def _per_member(stacked: list[torch.Tensor], m: int) -> list[list[torch.Tensor]]:
    """``[[t[j] for t in stacked] for j in range(m)]`` as views."""
    columns = [t.unbind(0) for t in stacked]
    return [[c[j] for c in columns] for j in range(m)]


def _member_configs(n: int, configs: Any, seeds: Sequence[int] | None) -> list[TrainConfig]:
    if configs is None:
        configs = [TrainConfig()] * n
    elif isinstance(configs, TrainConfig):
        configs = [configs] * n
    else:
        try:
            configs = list(configs)
        except TypeError as e:
            raise ConfigError(f"configs: expected a TrainConfig or a list of them (one per member), got {configs!r}") from e
        if len(configs) != n:
            raise ConfigError(f"configs: got {len(configs)} configs for {n} data sets (need one per member)")
        for i, c in enumerate(configs):
            if not isinstance(c, TrainConfig):
                raise ConfigError(f"configs[{i}]: expected a TrainConfig, got {type(c).__name__}")
    if seeds is not None:
        seeds = list(seeds)
        if len(seeds) != n:
            raise ConfigError(f"seeds: got {len(seeds)} seeds for {n} data sets (need one per member)")
        out = []
        for i, (c, s) in enumerate(zip(configs, seeds)):
            if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0:
                raise ConfigError(f"seeds[{i}]: expected an int >= 0, got {s!r}")
            out.append(dataclasses.replace(c, seed=int(s)))
        configs = out
    threads = {c.num_threads for c in configs}
    if len(threads) > 1:
        raise ConfigError(f"configs: num_threads must be the same for all members (one process), got {sorted(threads, key=str)}")
    return list(configs)


def _member_vals(n: int, val: Any) -> list[Any]:
    if val is None or not isinstance(val, (list, tuple)):
        return [val] * n
    if len(val) != n:
        raise ConfigError(f"val: got {len(val)} validation sets for {n} data sets (need one per member, or one for all)")
    return list(val)


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
      ``TrainConfig()``); ``num_threads`` must agree.
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
    if kind not in PAIRWISE_KINDS:
        raise ConfigError(f"model kind: expected one of the per-neighbour kinds {sorted(PAIRWISE_KINDS)}, got {kind!r}")
    if not isinstance(datasets, (list, tuple)):
        raise ConfigError(f"datasets: expected a list of data sets (one per member), got {type(datasets).__name__}")
    if not datasets:
        raise ConfigError("datasets: empty list, need at least one data set (one per member)")
    n = len(datasets)
    configs = _member_configs(n, configs, seeds)
    vals = _member_vals(n, val)

    threads = configs[0].num_threads
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _train(kind, list(datasets), vals, configs, progress, feature_set)
    finally:
        if threads is not None:
            torch.set_num_threads(old_threads)


def _prepare(i: int, kind: str, train: Any, val: Any, config: TrainConfig, feature_set, shared_val: dict) -> _Member:
    """A member as `train_model` sets it up: split, model, encoding, normalisation, schedule."""
    _check(train, f"datasets[{i}]")
    given = val is not None
    if not given:
        train, val = split_by_flight(train, config.val_fraction, np.random.default_rng(config.seed))
    elif id(val) not in shared_val:
        _check(val, f"val[{i}]")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = make_model(kind, feature_set)
    (x, basis), y = model.encode_samples(train)
    if given and id(val) in shared_val:  # a validation set given for several members: encoded once
        xv, basis_v, yv = shared_val[id(val)]
    else:
        (xv, basis_v), yv = model.encode_samples(val)
        if given:
            shared_val[id(val)] = (xv, basis_v, yv)
    model.fit_normalization(x, model.output_targets(y, basis))
    nrows, bs = x.shape[0], min(config.batch_size, x.shape[0])
    steps_per_epoch = math.ceil(nrows / bs)
    n_epochs = max(config.max_epochs, math.ceil(config.min_steps / steps_per_epoch))
    patience = math.ceil(config.patience * n_epochs / config.max_epochs)
    _, params, buffers = _layers(model)
    member = _Member(
        index=i, config=config, model=model, params=params, buffers=buffers, train=train, val=val,
        xv=xv, basis_v=basis_v, yv=yv, n=int(nrows), bs=int(bs), steps_per_epoch=steps_per_epoch,
        n_epochs=n_epochs, patience=patience, total_steps=n_epochs * steps_per_epoch, lr=config.peak_lr(kind),
        gen=torch.Generator().manual_seed(config.seed),
    )  # fmt: skip
    with torch.no_grad():  # decode's normalisation, elementwise: the same values as train_model's
        member.x = (x - model.in_mean) / model.in_std
        member.xv_n = (xv - model.in_mean) / model.in_std
    member.y, member.basis = y, basis
    return member


def _train(kind, datasets, vals, configs, progress, feature_set):
    start = time.perf_counter()
    level = logging.INFO if progress else logging.DEBUG
    shared_val: dict[int, tuple] = {}
    members = [_prepare(i, kind, train, val, config, feature_set, shared_val)
               for i, (train, val, config) in enumerate(zip(datasets, vals, configs))]
    plan, _, _ = _layers(members[0].model)
    # rows per step are padded to a multiple of 16, so that every member's slice of every
    # (M, rows, width) activation starts on a 64-byte boundary (see _aligned_stack)
    width = _round_rows(max(mb.bs for mb in members))
    dtype = members[0].x.dtype

    active = list(members)
    stacks = _Stacks.from_members(active)
    step = 0
    while active:
        # -- this step's rows: each member's next batch of its own epoch order ------------------
        sizes = []
        for mb in active:
            if mb.batch == 0:  # new epoch: the same permutation and gather as train_model
                mb.shuffle(width)
            sizes.append(mb.batch_rows())
        m_act, b_max = len(active), _round_rows(max(sizes))
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
        pred = _forward(plan, stacks.params, stacks.p_views, stacks.buf_views, xb, short, training=True,
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


def _round_rows(rows: int) -> int:
    return -(-rows // _ROW_ALIGN) * _ROW_ALIGN


def _forward(plan: list[_Layer], params: Sequence[torch.Tensor], p_views, buf_views, x: torch.Tensor, short,
             training: bool, buffers: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
    """The stacked network on x (M, B, k): (M, B, m), normalised outputs.

    params: the members' stacked weights and biases (plan order); p_views, buf_views:
    per member, views of its weights and of its power-iteration vectors (the deep
    model); buffers: those vectors stacked (training mode: the power iteration
    updates them in place).
    """
    h = x
    for layer in plan:
        if layer.kind == "relu":
            h = torch.relu_(h) if training else torch.relu(h)  # in place: the linear's backward does not need it
            continue
        w, b = params[layer.weight], params[layer.bias]
        if layer.kind == "spectral":
            w = _spectral_weights(layer, w, p_views, buf_views, training, buffers)
        h = _BatchedLinear.apply(h, w, b, short)
    return h


def _spectral_weights(layer: _Layer, w: torch.Tensor, p_views, buf_views, training: bool,
                      buffers: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
    """``gamma W_m / sigma_m`` for every member, with torch's `spectral_norm` arithmetic per member.

    Training mode first runs ``n_power_iterations`` of torch's ``_power_method`` on
    the member's ``u, v`` (in place, no gradient); ``sigma = vdot(u, mv(W, v))``
    then carries the gradient through W, as in the parametrisation's forward
    (eval mode: the stored u, v, no iteration).
    """
    us = [views[layer.u] for views in buf_views]
    vs = [views[layer.v] for views in buf_views]
    if training:
        with torch.no_grad():
            ws = [views[layer.weight] for views in p_views]
            for _ in range(layer.n_power_iterations):
                _normalize_rows([torch.mv(wm, v) for wm, v in zip(ws, vs)], layer.eps, buffers[layer.u])
                _normalize_rows([torch.mv(wm.H, u) for wm, u in zip(ws, us)], layer.eps, buffers[layer.v])
    u_all = _aligned_stack(us)  # the parametrisation's clones of u, v
    v_all = _aligned_stack(vs)
    return _SpectralWeights.apply(w, u_all, v_all, layer.gamma)


def _normalize_rows(rows: list[torch.Tensor], eps: float, out: torch.Tensor) -> None:
    """``F.normalize(rows[m], dim=0, eps=eps, out=out[m])`` for every member, as a few ops on the stack.

    F.normalize is ``x / x.norm(2, 0, keepdim=True).clamp_min_(eps)``: the norm of each
    row of the stack equals the norm of that vector alone (measured bit for bit for
    the widths 3-100; the ensemble tests check it end to end), the rest is elementwise.
    """
    x = _aligned_stack(rows)
    denom = torch.linalg.vector_norm(x, 2, dim=1, keepdim=True).clamp_min_(eps)
    torch.div(x, denom, out=out)


class _SpectralWeights(torch.autograd.Function):
    """``gamma W_m / sigma_m``, ``sigma_m = vdot(u_m, mv(W_m, v_m))``, for the stacked members.

    Forward: ``mv`` and ``vdot`` per member (BLAS calls, as the parametrisation
    makes them), the division and the scaling as one elementwise op each over the
    stack. Backward: the gradient autograd computes for the member's graph
    ``gamma * (W / vdot(u, mv(W, v)))``, formula by formula (torch's
    derivatives.yaml): ``MulBackward0`` ``g gamma``; ``DivBackward0``
    ``g / sigma`` for W and ``-g ((W / sigma) / sigma)`` summed to a scalar for
    sigma (that sum per member, a reduction); ``VdotBackward0`` ``g_sigma u``;
    ``MvBackward0`` ``outer(g_mv, v)``; the two gradients of W added. Elementwise
    ops give the same value per element batched or not; only the reductions
    (``mv``, ``vdot``, the sum) run per member. The output's member slices are
    64-byte aligned (see `_aligned_stack`), as the batched layer's weights must be.
    """

    @staticmethod
    def forward(ctx, w, u_all, v_all, gamma):
        sigma = torch.stack([torch.vdot(u, torch.mv(wm, v)) for wm, u, v in zip(w.unbind(0), u_all.unbind(0),
                                                                                 v_all.unbind(0))])
        s = sigma.view(-1, 1, 1)
        out = _aligned_empty(w.shape, w.dtype)
        torch.div(w, s, out=out)
        out.mul_(gamma)
        ctx.save_for_backward(w, sigma, u_all, v_all)
        ctx.gamma = gamma
        return out

    @staticmethod
    def backward(ctx, g):
        w, sigma, u_all, v_all = ctx.saved_tensors
        s = sigma.view(-1, 1, 1)
        gq = g * ctx.gamma
        grad = gq / s
        r = _aligned_empty(w.shape, w.dtype)
        torch.mul(-gq, (w / s) / s, out=r)
        g_sigma = torch.stack([rm.sum() for rm in r.unbind(0)])
        g_mv = g_sigma.view(-1, 1) * u_all
        grad += g_mv.unsqueeze(2) * v_all.unsqueeze(1)
        return grad, None, None, None


def _adam_step(active: list[_Member], stacks: _Stacks, grads: Sequence[torch.Tensor]) -> None:
    """torch's Adam (fused where available, as `downwash.train`) on each member's views.

    Members that share a learning rate and weight decay at this step go in one call.
    """
    global _FUSED
    if _FUSED is None:
        _FUSED = _fused_adam_available()
    grad_views = _per_member(list(grads), len(active))
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


def _load(mb: _Member, stacks: _Stacks, j: int) -> None:
    """Copy member j's current weights and power-iteration vectors into its model."""
    with torch.no_grad():
        for dst, src in zip(mb.params, stacks.p_views[j]):
            dst.copy_(src)
        for dst, src in zip(mb.buffers, stacks.buf_views[j]):
            dst.copy_(src)


def _validate(plan: list[_Layer], stacks: _Stacks, active: list[_Member], ending: list[int]) -> list[float]:
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
            params = [_aligned_stack([views[i] for views in p_views]) for i in range(len(p_views[0]))]
            ix = torch.as_tensor(ending, dtype=torch.long)
            out_std, out_mean = stacks.out_std.index_select(0, ix), stacks.out_mean.index_select(0, ix)
        rows = _round_rows(max(mb.xv_n.shape[0] for mb in members))
        x = torch.stack([_pad_rows(mb.xv_n, rows) for mb in members])
        pred = _forward(plan, params, p_views, buf_views, x, [], training=False) * out_std + out_mean
        if members[0].basis_v is not None:
            pred = assemble(pred, torch.stack([_pad_rows(mb.basis_v, rows) for mb in members]))
        return [float(torch.mean((pred[e, : mb.yv.shape[0]] - mb.yv) ** 2)) for e, mb in enumerate(members)]


def _pad_rows(t: torch.Tensor, rows: int) -> torch.Tensor:
    return t if t.shape[0] == rows else torch.cat([t, t.new_zeros((rows - t.shape[0], *t.shape[1:]))])


def _end_epoch(kind: str, mb: _Member, stacks: _Stacks, j: int, val_loss: float) -> bool:
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


def _finish(kind: str, mb: _Member, level: int, size: int) -> None:
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


def _log_member(kind: str, mb: _Member, level: int) -> None:
    logger.log(level, "%s member %d: best val rmse %.4f at epoch %d of %d", kind, mb.index,
               math.sqrt(mb.history["best_val_loss"]), mb.best_epoch, mb.history["epochs"])


def _settle_members(members: list[_Member], level: int) -> None:
    """`DeepSNMLP.settle_spectral_norm` of every member, then its validation loss, as `train_model` ends.

    The power iterations of one layer run for all members side by side, chunk by
    chunk as in `settle_spectral_norm` (20 iterations, then the float32 estimate
    ``dot(u, mv(W, v))`` against the previous chunk's), each member stopping at its
    own chunk: ``mv`` and ``dot`` per member, the normalisation over the stack
    (`_normalize_rows`).
    """
    models = [mb.model for mb in members]
    for i in range(len(models[0].spectral_layers())):
        _settle_layer([m.spectral_layers()[i] for m in models])
    for mb in members:
        with torch.no_grad():
            mb.history["best_val_loss"] = float(torch.mean((mb.model.decode(mb.xv, mb.basis_v) - mb.yv) ** 2))
        mb.xv = mb.yv = mb.basis_v = None
        _log_member(mb.model.kind, mb, level)


_SETTLE = inspect.signature(settle_spectral_norm).parameters  # its max_iterations and rtol
_SETTLE_CHUNK = 20  # power iterations between two tests of convergence, as in DeepSNMLP.settle_spectral_norm


def _settle_layer(layers: list[_SpectralLinear], max_iterations: int = _SETTLE["max_iterations"].default,
                  rtol: float = _SETTLE["rtol"].default, chunk: int = _SETTLE_CHUNK) -> None:
    """`DeepSNMLP.settle_spectral_norm` for one layer of several models, side by side (the ensemble
    tests compare the settled vectors with those of `train_model`, bit for bit)."""
    params = [layer.linear.parametrizations.weight[0] for layer in layers]
    ws = [layer.linear.parametrizations.weight.original.detach() for layer in layers]
    with torch.no_grad():
        u = _aligned_stack([p._u for p in params])
        v = _aligned_stack([p._v for p in params])
        us, vs = u.unbind(0), v.unbind(0)
        eps = params[0].eps
        active, prev = list(range(len(layers))), [None] * len(layers)
        for _ in range(0, max_iterations, chunk):
            uu, vv = _aligned_stack([us[j] for j in active]), _aligned_stack([vs[j] for j in active])
            uus, vvs = uu.unbind(0), vv.unbind(0)
            aws = [ws[j] for j in active]
            for _ in range(chunk):
                _normalize_rows([torch.mv(w, x) for w, x in zip(aws, vvs)], eps, uu)
                _normalize_rows([torch.mv(w.H, x) for w, x in zip(aws, uus)], eps, vv)
            still = []
            for k, j in enumerate(active):
                us[j].copy_(uus[k])
                vs[j].copy_(vvs[k])
                sigma = float(torch.dot(uus[k], torch.mv(ws[j], vvs[k])))
                if prev[j] is None or abs(sigma - prev[j]) > rtol * abs(sigma):
                    still.append(j)
                prev[j] = sigma
            active = still
            if not active:
                break
        for p, uj, vj in zip(params, us, vs):
            p._u.copy_(uj)
            p._v.copy_(vj)
