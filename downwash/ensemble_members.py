"""An ensemble's members: each one set up as `downwash.train.train_model` sets up its model, and the
members' weights, Adam state and power-iteration vectors stacked for the batched network.

`prepare_member` splits a member's data, builds and encodes its model, fits the normalisation and
lays out its schedule (a `Member`: the member's data and bookkeeping; its weights live in the
stacks); `Stacks` holds the active members' tensors stacked on dim 0 (`downwash.ensemble_network`'s
64-byte-aligned slices), with per-member views for Adam and the power iteration;
`member_configs` and `member_vals` check one config and one validation set per member. The
training loop that advances them is `downwash.ensemble.train_ensemble`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch

from downwash_core.errors import ConfigError
from downwash.datasets import split_by_flight
from downwash.ensemble_network import aligned_stack, batch_slots, member_layers, per_member
from downwash.models import DownwashModel
from downwash.registry import make_model
from downwash.train import TrainConfig, check_dataset

__all__ = ["Member", "Stacks", "member_configs", "member_vals", "prepare_member"]


@dataclass
class Member:
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
            None if t is None else batch_slots(t.index_select(0, perm), self.steps_per_epoch, self.bs, width)
            for t in (self.x, self.y, self.basis)
        )  # index_select: the same rows as train_model's x[perm], three times faster

    def current_lr(self) -> float:
        """The cosine schedule of `train_model`, term for term."""
        c = self.config
        return self.lr * (c.lr_final + (1 - c.lr_final) * 0.5 * (1 + math.cos(math.pi * self.step / self.total_steps)))


class Stacks:
    """The active members' weights, Adam state and power-iteration vectors, stacked on dim 0."""

    def __init__(self, params: list[torch.Tensor], exp_avg, exp_avg_sq, steps, buffers, out_std, out_mean, totals):
        self.params = [p.requires_grad_(True) for p in params]
        self.exp_avg, self.exp_avg_sq, self.steps = exp_avg, exp_avg_sq, steps
        self.buffers, self.out_std, self.out_mean, self.totals = buffers, out_std, out_mean, totals
        # per-member views for Adam and the power iteration (in-place updates reach the stacks)
        m = params[0].shape[0]
        detached = [p.detach() for p in self.params]
        self.p_views = per_member(detached, m)
        self.ea_views = per_member(exp_avg, m)
        self.eas_views = per_member(exp_avg_sq, m)
        self.step_views = [list(row.unbind(0)) for row in steps.unbind(0)]
        self.buf_views = per_member(buffers, m)

    @classmethod
    def from_members(cls, members: list[Member]) -> "Stacks":
        with torch.no_grad():
            params = [aligned_stack([mb.params[i].detach() for mb in members]) for i in range(len(members[0].params))]
            buffers = [aligned_stack([mb.buffers[i] for mb in members]) for i in range(len(members[0].buffers))]
            out_std = torch.stack([mb.model.out_std for mb in members])[:, None, :]
            out_mean = torch.stack([mb.model.out_mean for mb in members])[:, None, :]
        exp_avg = [torch.zeros_like(p) for p in params]
        exp_avg_sq = [torch.zeros_like(p) for p in params]
        steps = torch.zeros(len(members), len(params), dtype=torch.float32)
        totals = torch.zeros(len(members), dtype=params[0].dtype)
        return cls(params, exp_avg, exp_avg_sq, steps, buffers, out_std, out_mean, totals)

    def keep(self, index: list[int]) -> "Stacks":
        """The stacks of the members at positions ``index`` (copies)."""
        ix = torch.as_tensor(index, dtype=torch.long)
        with torch.no_grad():
            sel = lambda ts: [aligned_stack(t.detach().unbind(0), index) for t in ts]  # noqa: E731
            return Stacks(sel(self.params), sel(self.exp_avg), sel(self.exp_avg_sq), self.steps.index_select(0, ix),
                           sel(self.buffers), self.out_std.index_select(0, ix), self.out_mean.index_select(0, ix),
                           self.totals.index_select(0, ix))


def member_configs(n: int, configs: Any, seeds: Sequence[int] | None) -> list[TrainConfig]:
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
    if len({c.portable for c in configs}) > 1:
        raise ConfigError("configs: portable must be the same for all members (one process's kernels), got both")
    return list(configs)


def member_vals(n: int, val: Any) -> list[Any]:
    if val is None or not isinstance(val, (list, tuple)):
        return [val] * n
    if len(val) != n:
        raise ConfigError(f"val: got {len(val)} validation sets for {n} data sets (need one per member, or one for all)")
    return list(val)


def prepare_member(i: int, kind: str, train: Any, val: Any, config: TrainConfig, feature_set, shared_val: dict) -> Member:
    """A member as `train_model` sets it up: split, model, encoding, normalisation, schedule."""
    check_dataset(train, f"datasets[{i}]")
    given = val is not None
    if not given:
        train, val = split_by_flight(train, config.val_fraction, np.random.default_rng(config.seed))
    elif id(val) not in shared_val:
        check_dataset(val, f"val[{i}]")
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
    _, params, buffers = member_layers(model)
    member = Member(
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
