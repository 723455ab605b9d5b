"""The ensemble's batched network: the members' layers stacked, each member's arithmetic its own.

`downwash.ensemble.train_ensemble` trains the members of an ensemble as ONE network
whose tensors stack theirs on dim 0: weights ``W (M, out, in)``, biases ``b (M, out)``,
a step's batch ``x (M, B, k)``. This module holds that network: the layer plan of a
model (`member_layers`), the batched forward (`forward_members`) with its two custom autograd
functions, and the aligned stacks every member's slice lives in (`aligned_stack`).

* ``shallow``, ``equivariant`` (and ``equivariant_general``): two batched layers, each
  one ``baddbmm`` over the members (`_BatchedLinear`); the output basis of an
  equivariant model is gathered with the rows and applied with `features.assemble`,
  as in `DownwashModel.decode`.
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
  Eval mode (validation) uses the stored ``u, v``, as torch does. A power iteration
  by ``bmm`` on the stacked weights would save the per-member ``mv`` calls, but
  would not be bit-identical: ``bmm`` and ``mv``/``vdot`` accumulate in different
  orders.

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
  tensor starts on a 64-byte boundary (`aligned_stack`, batch rows in multiples
  of 16).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import nn

from downwash.models import DownwashModel, SpectralLinear

_ALIGN_BYTES = 64  # torch's CPU allocator aligns every tensor to 64 bytes
_ROW_ALIGN = 16  # batch rows are padded to a multiple of this: 64 bytes of float32 per feature column


def aligned_stack(tensors: Sequence[torch.Tensor], index: Sequence[int] | None = None) -> torch.Tensor:
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


def round_rows(rows: int) -> int:
    return -(-rows // _ROW_ALIGN) * _ROW_ALIGN


def batch_slots(t: torch.Tensor, steps: int, bs: int, width: int) -> torch.Tensor:
    """Rows t (n, ...) as (steps, width, ...): batch i in slot i, zero rows after its end."""
    n = t.shape[0]
    out = t.new_zeros((steps, width, *t.shape[1:]))
    if steps * bs == n:
        out[:, :bs] = t.view(steps, bs, *t.shape[1:])
    else:
        out[:-1, :bs] = t[: (steps - 1) * bs].view(steps - 1, bs, *t.shape[1:])
        out[-1, : n - (steps - 1) * bs] = t[(steps - 1) * bs :]
    return out


def pad_rows(t: torch.Tensor, rows: int) -> torch.Tensor:
    return t if t.shape[0] == rows else torch.cat([t, t.new_zeros((rows - t.shape[0], *t.shape[1:]))])


def per_member(stacked: list[torch.Tensor], m: int) -> list[list[torch.Tensor]]:
    """``[[t[j] for t in stacked] for j in range(m)]`` as views."""
    columns = [t.unbind(0) for t in stacked]
    return [[c[j] for c in columns] for j in range(m)]


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
class Layer:
    """One layer of the network: ``relu``, ``linear`` or ``spectral`` (index into the parameter list)."""

    kind: str
    weight: int = -1  # index of the weight in the member's parameter list
    bias: int = -1
    u: int = -1  # spectral: index of u, v in the member's buffer list
    v: int = -1
    gamma: float = 1.0
    eps: float = 1e-12
    n_power_iterations: int = 1


def member_layers(model: DownwashModel) -> tuple[list[Layer], list[torch.Tensor], list[torch.Tensor]]:
    """The layer plan of a model, its trainable tensors and its power-iteration buffers (in plan order)."""
    plan: list[Layer] = []
    params: list[torch.Tensor] = []
    buffers: list[torch.Tensor] = []
    for m in model.net:
        if isinstance(m, nn.ReLU):
            plan.append(Layer("relu"))
        elif isinstance(m, nn.Linear):
            plan.append(Layer("linear", len(params), len(params) + 1))
            params += [m.weight, m.bias]
        elif isinstance(m, SpectralLinear):
            param = m.linear.parametrizations.weight[0]
            plan.append(Layer("spectral", len(params), len(params) + 1, len(buffers), len(buffers) + 1,
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


def forward_members(plan: list[Layer], params: Sequence[torch.Tensor], p_views, buf_views, x: torch.Tensor, short,
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


def _spectral_weights(layer: Layer, w: torch.Tensor, p_views, buf_views, training: bool,
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
                normalize_rows([torch.mv(wm, v) for wm, v in zip(ws, vs)], layer.eps, buffers[layer.u])
                normalize_rows([torch.mv(wm.H, u) for wm, u in zip(ws, us)], layer.eps, buffers[layer.v])
    u_all = aligned_stack(us)  # the parametrisation's clones of u, v
    v_all = aligned_stack(vs)
    return _SpectralWeights.apply(w, u_all, v_all, layer.gamma)


def normalize_rows(rows: list[torch.Tensor], eps: float, out: torch.Tensor) -> None:
    """``F.normalize(rows[m], dim=0, eps=eps, out=out[m])`` for every member, as a few ops on the stack.

    F.normalize is ``x / x.norm(2, 0, keepdim=True).clamp_min_(eps)``: the norm of each
    row of the stack equals the norm of that vector alone (measured bit for bit for
    the widths 3-100; the ensemble tests check it end to end), the rest is elementwise.
    """
    x = aligned_stack(rows)
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
    64-byte aligned (see `aligned_stack`), as the batched layer's weights must be.
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
