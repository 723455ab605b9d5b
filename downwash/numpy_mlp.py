"""The NumPy twins' network: an MLP of (spectral) linear layers and ReLUs as float64 arrays, and its forward pass.

`numpy_layers` reads a torch MLP's layers as eval mode evaluates them (a spectral layer's weight
``gamma W / (u . W v)`` from its stored estimates, in float64: `effective_weight64`); `numpy_mlp`
runs them on rows in blocks of `MLP_ROWS`. The models of sets' float64 twins
(`downwash.set_models`, `SetModel.numpy_forward`) are built from them, and the compiled pass
(`downwash.set_fused`) packs the same arrays.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from downwash.models import SpectralLinear

__all__ = ["effective_weight64", "numpy_layers", "numpy_mlp", "MLP_ROWS"]


@torch.no_grad()
def effective_weight64(layer: SpectralLinear) -> torch.Tensor:
    """The eval-mode weight ``gamma W / (u . W v)`` computed in float64 from the stored estimates
    (as the float64 copy of the torch model computes it)."""
    param = layer.linear.parametrizations.weight[0]
    w = layer.linear.parametrizations.weight.original.double()
    sigma = torch.dot(param._u.double(), torch.mv(w, param._v.double()))
    return layer.gamma * w / sigma


@torch.no_grad()
def numpy_layers(net: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(W_i (in, out), b_i (out,)), ...] float64 of an MLP of (spectral) linear layers and ReLUs, as in eval mode."""
    layers = []
    for m in net:
        if isinstance(m, SpectralLinear):
            w, b = effective_weight64(m), m.linear.bias
        elif isinstance(m, nn.Linear):
            w, b = m.weight, m.bias
        elif isinstance(m, nn.ReLU):
            continue
        else:  # pragma: no cover - guards future architectures
            raise TypeError(f"numpy_forward: unsupported layer {type(m).__name__}")
        layers.append((np.ascontiguousarray(w.detach().double().numpy().T), b.detach().double().numpy().copy()))
    return layers


MLP_ROWS = 128  # rows per matrix product: small enough that OpenBLAS stays on the calling thread


def numpy_mlp(layers: list[tuple[np.ndarray, np.ndarray]], h: np.ndarray) -> np.ndarray:
    """The MLP on h (..., in) -> (..., out), in blocks of `MLP_ROWS` rows.

    Why blocks: one product over all rows is large enough for OpenBLAS to split it over its
    threads, and on two busy cores those threads waited their turn for milliseconds (we
    measured 5 ms a call instead of 0.3 ms at 192 targets); a batched (..., in) @ (in, out)
    instead runs one tiny product per leading index.
    """
    lead = h.shape[:-1]
    h = h.reshape(-1, h.shape[-1])
    out = np.empty((h.shape[0], layers[-1][1].shape[0]))
    for i in range(0, h.shape[0], MLP_ROWS):
        x = h[i : i + MLP_ROWS]
        for w, b in layers[:-1]:
            x = x @ w
            x += b
            np.maximum(x, 0.0, out=x)
        w, b = layers[-1]
        out[i : i + MLP_ROWS] = x @ w + b
    return out.reshape(*lead, -1)
