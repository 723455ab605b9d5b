"""Settling the deep members' spectral norms after an ensemble's training, the members side by side.

After `train_model`, a `DeepSNMLP` settles the power-iteration estimates of its
spectral norms (`DeepSNMLP.settle_spectral_norm`). `downwash.ensemble.train_ensemble`
does the same for its deep members at the end, each a real `DeepSNMLP` with its best
state: the power iterations of one layer run for all members side by side, chunk by
chunk as in `settle_spectral_norm` (the same chunks of iterations and stopping test
per member), ``mv`` and ``dot`` per member and the normalisation over the stack
(`downwash.ensemble_network.normalize_rows`), so that each member's settled vectors
are bit-identical to those of its own training.
"""

from __future__ import annotations

import inspect

import torch

from downwash.ensemble_network import aligned_stack, normalize_rows
from downwash.models import DeepSNMLP, SpectralLinear, settle_spectral_norm

_SETTLE = inspect.signature(settle_spectral_norm).parameters  # its max_iterations and rtol
_SETTLE_CHUNK = 20  # power iterations between two tests of convergence, as in DeepSNMLP.settle_spectral_norm


def settle_models(models: list[DeepSNMLP]) -> None:
    """`DeepSNMLP.settle_spectral_norm` of every model, layer by layer, the models side by side."""
    for i in range(len(models[0].spectral_layers())):
        _settle_layer([m.spectral_layers()[i] for m in models])


def _settle_layer(layers: list[SpectralLinear], max_iterations: int = _SETTLE["max_iterations"].default,
                  rtol: float = _SETTLE["rtol"].default, chunk: int = _SETTLE_CHUNK) -> None:
    """`DeepSNMLP.settle_spectral_norm` for one layer of several models, side by side (the ensemble
    tests compare the settled vectors with those of `train_model`, bit for bit)."""
    params = [layer.linear.parametrizations.weight[0] for layer in layers]
    ws = [layer.linear.parametrizations.weight.original.detach() for layer in layers]
    with torch.no_grad():
        u = aligned_stack([p._u for p in params])
        v = aligned_stack([p._v for p in params])
        us, vs = u.unbind(0), v.unbind(0)
        eps = params[0].eps
        active, prev = list(range(len(layers))), [None] * len(layers)
        for _ in range(0, max_iterations, chunk):
            uu, vv = aligned_stack([us[j] for j in active]), aligned_stack([vs[j] for j in active])
            uus, vvs = uu.unbind(0), vv.unbind(0)
            aws = [ws[j] for j in active]
            for _ in range(chunk):
                normalize_rows([torch.mv(w, x) for w, x in zip(aws, vvs)], eps, uu)
                normalize_rows([torch.mv(w.H, x) for w, x in zip(aws, uus)], eps, vv)
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
