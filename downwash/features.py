"""Model inputs: the one place where they are computed, for NumPy and torch alike.

Every function here is written once against an array namespace ``xp`` (``numpy``
or ``torch``, picked from the arguments): NumPy arrays in give NumPy arrays out,
torch tensors in give torch tensors out (differentiable). Only operations with the
same meaning in both libraries are used (``xp.sqrt``, ``xp.stack``,
``xp.concatenate``, arithmetic, indexing); the two primitives that differ are
wrapped once: `downwash_core.geometry.dot` (a component-by-component sum, the same bits on every CPU) and `_sqrt0` (a square
root whose torch gradient stays finite at 0).

Raw per-sample inputs (leader ``a`` = Alpha, follower ``b`` = Bravo)::

    dp  (..., 3)    m     p_b - p_a, world frame (MuJoCo: z up)
    v_a (..., 3)    m/s   leader velocity, world frame
    v_b (..., 3)    m/s   follower velocity, world frame
    R_a (..., 3, 3) -     leader body-to-world rotation; n = R_a[..., :, 2] is its
                          body "up" axis (world +z for a level leader)

NED mapping (written here once). The paper works in North-East-Down with the
leader's body axis ``a3`` pointing DOWN. In our z-up world ``a3 = -n``, so

* the paper's ``[R dp]_3`` is ``s = -(dp . n)``: the depth of the follower below
  the leader along its axis, POSITIVE BELOW the leader;
* the paper's ``[R v_b]_3`` is ``w = -(v_b . n)``: the follower's axial speed,
  positive when it moves DOWN (away from the leader);
* the network's second output ``f2`` is the paper's ``[F]_3`` component along
  NED-down, so the world-frame axial force is ``-f2 n``: a positive ``f2`` pushes
  the follower toward the ground (our negative z for a level leader).

The generalised set "general" adds the signed angles of ``P v_b`` and ``P v_a``
about ``n`` (sines, so a model can tell left from right) and the leader's lateral and
axial speed, and a third basis row ``t_hat = n x r_hat``: with them an equivariant
model can represent swirl and wakes skewed by the leader's velocity. Its symmetry is
SO(2) about ``n`` acting on dp, v_b AND v_a (a rotation of the whole configuration),
not reflections.

Models with memory (feature sets "general_memory" and "raw_memory") also read the neighbour's
recent past, ``hist (..., H, 3)``: its displacement over each lag of `HISTORY_LAGS`,
``p_a(t) - p_a(t - lag)`` (estimates, world frame; `neighbour_history`). A wake met now was shed a
moment earlier somewhere else, and these say where. The equivariant set reads each displacement's
components along the output basis rows (radial, NED-down, tangential), which a rotation about ``n``
of the whole configuration, history included, leaves unchanged; the raw set reads them in world
axes.

Equivariant output (paper eq. 5): ``F = f1 r_hat + f2 d`` with the basis rows
``r_hat = P dp / sqrt(|P dp|^2 + R_EPS^2)`` (the radial direction in the leader's
rotor plane, smoothly 0 at r = 0) and ``d = -n`` (the leader's NED-down axis),
where ``P = I - n n^T``. Both rows rotate with any rotation about ``n`` and the
features are invariant under it, so ``F`` is SO(2)-equivariant (the paper's
theorem 1) for any network ``(f1, f2) = f(h)``.
"""

from __future__ import annotations

import math
from types import ModuleType
from typing import Any

import numpy as np
import torch

from downwash_core.geometry import dot
from downwash_core.vehicles import PAPER_QUAD, get_vehicle

__all__ = [
    "R_EPS",
    "V_EPS",
    "FEATURE_SETS",
    "EQUIVARIANT_FEATURE_SETS",
    "N_BASIS",
    "RAW_FEATURE_SETS",
    "HISTORY_LAGS",
    "MEMORY_FEATURE_SETS",
    "neighbour_history",
    "leader_axis",
    "depth",
    "invariant_features",
    "raw_features",
    "equivariant_basis",
    "assemble",
    "project_onto_basis",
    "model_inputs",
    "KIND_FEATURES",
    "kind_descriptors",
    "neighbour_kinds",
]

R_EPS = 1e-3  # m, softening of the radial unit vector and of the cosine near the wake axis
V_EPS = 1e-3  # m/s, softening of the cosine feature near zero lateral follower speed

# feature-set name -> feature names, in column order
FEATURE_SETS: dict[str, tuple[str, ...]] = {
    # paper eq. 4 without |P v_a| (level, near-hover leader, paper section 5.D)
    "5": ("cos_dp_vb", "r_lateral", "vb_lateral", "depth", "vb_axial_down"),
    # paper eq. 4, all six features
    "6": ("cos_dp_vb", "r_lateral", "vb_lateral", "depth", "vb_axial_down", "va_lateral"),
    # the generalised equivariant model: also the signed angles of v_b and v_a about the axis
    # (sin, so it can tell left from right: swirl) and the leader's velocity (skewed wakes)
    "general": ("cos_dp_vb", "sin_dp_vb", "r_lateral", "vb_lateral", "depth", "vb_axial_down",
                "va_lateral", "cos_dp_va", "sin_dp_va", "va_axial_down"),
    # non-equivariant baselines: [dp, v_b] in the world frame
    "raw": ("dp_x", "dp_y", "dp_z", "vb_x", "vb_y", "vb_z"),
}
# The lags of the models with memory (s): every third prediction of the loop's 45 Hz, the last 0.27 s.
HISTORY_LAGS = (3 / 45, 6 / 45, 9 / 45, 12 / 45)
_LAG_NAMES = [f"{1000 * lag:.0f}ms" for lag in HISTORY_LAGS]
FEATURE_SETS["general_memory"] = FEATURE_SETS["general"] + tuple(
    f"moved_{axis}_{lag}" for lag in _LAG_NAMES for axis in ("radial", "down", "tangential"))
FEATURE_SETS["raw_memory"] = FEATURE_SETS["raw"] + tuple(f"moved_{axis}_{lag}" for lag in _LAG_NAMES for axis in "xyz")
MEMORY_FEATURE_SETS = ("general_memory", "raw_memory")  # they read the neighbour's history
EQUIVARIANT_FEATURE_SETS = ("5", "6", "general", "general_memory")
# output basis rows: r_hat, d (and t_hat = n x r_hat for "general")
N_BASIS = {"5": 2, "6": 2, "general": 3, "general_memory": 3}
RAW_FEATURE_SETS = ("raw", "raw_memory")


def _namespace(*arrays: Any) -> tuple[ModuleType, list[Any]]:
    """torch if any argument is a tensor (the others are converted to it), else numpy."""
    tensors = [a for a in arrays if isinstance(a, torch.Tensor)]
    if not tensors:
        return np, [np.asarray(a) for a in arrays]
    ref = tensors[0]
    out = [a if isinstance(a, torch.Tensor) else torch.as_tensor(a, dtype=ref.dtype, device=ref.device) for a in arrays]
    return torch, out


def _sqrt0(xp: ModuleType, sq):
    """sqrt of a non-negative array, with gradient 0 (not inf) at 0 under torch.

    NumPy needs no guard (no gradients; sqrt(0) = 0). torch uses the "double
    where": the square root only ever sees positive arguments.
    """
    if xp is np:
        return np.sqrt(sq)
    pos = sq > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, sq, 1.0)), 0.0)


def _stack(xp: ModuleType, arrays: list, axis: int):
    """``xp.stack(arrays, axis)`` for axis -1 or -2 (NumPy: a C concatenate, not Python np.stack)."""
    if xp is not np:
        return torch.stack(arrays, axis)
    index = (Ellipsis, None) if axis == -1 else (Ellipsis, None, slice(None))
    return np.concatenate([a[index] for a in arrays], axis)


def leader_axis(R_a):
    """The leader's body up axis ``n = R_a[..., :, 2]`` (..., 3), world frame, unit."""
    return R_a[..., :, 2]


def depth(dp, R_a):
    """Depth of the follower below the leader along the leader's axis (...,), m.

    ``s = -(dp . n)``, the paper's ``[R dp]_3`` in NED: +1 for a follower 1 m
    directly below a level leader, negative above it.
    """
    xp, (dp, R_a) = _namespace(dp, R_a)
    return -dot(dp, leader_axis(R_a), xp)


def _check_equivariant_set(feature_set: str) -> None:
    if feature_set not in EQUIVARIANT_FEATURE_SETS:
        raise ValueError(
            f"feature_set: expected one of {list(EQUIVARIANT_FEATURE_SETS)} for invariant features, got {feature_set!r}"
        )


def _cross(xp: ModuleType, a, b):
    """a x b over the last axis (..., 3), written out: the same operations in NumPy and torch."""
    return _stack(xp, [a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                       a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)


def _equivariant_inputs(xp: ModuleType, dp, v_a, v_b, R_a, feature_set: str, want_features: bool = True):
    """Invariant features (..., k) (or None) and output basis (..., N_BASIS, 3), sharing intermediates."""
    n = leader_axis(R_a)
    dp_n = dot(dp, n, xp)
    pdp = dp - dp_n[..., None] * n
    r2 = dot(pdp, pdp, xp)
    r_soft = xp.sqrt(r2 + R_EPS**2)
    r_hat = pdp / r_soft[..., None]
    rows = [r_hat, -n] if N_BASIS[feature_set] == 2 else [r_hat, -n, _cross(xp, n, r_hat)]
    basis = _stack(xp, rows, -2)
    if not want_features:
        return None, basis
    vb_n = dot(v_b, n, xp)
    pvb = v_b - vb_n[..., None] * n
    q2 = dot(pvb, pvb, xp)
    c = dot(pdp, pvb, xp) / (r_soft * xp.sqrt(q2 + V_EPS**2))
    if N_BASIS[feature_set] == 2:
        cols = [c, _sqrt0(xp, r2), _sqrt0(xp, q2), -dp_n, -vb_n]
        if feature_set == "6":
            pva = v_a - dot(v_a, n, xp)[..., None] * n
            cols.append(_sqrt0(xp, dot(pva, pva, xp)))
        return _stack(xp, cols, -1), basis
    # signed angles about n: sin = n . (P dp x P v) / (|P dp| |P v|), softened like the cosines
    va_n = dot(v_a, n, xp)
    pva = v_a - va_n[..., None] * n
    qa2 = dot(pva, pva, xp)
    den_b = r_soft * xp.sqrt(q2 + V_EPS**2)
    den_a = r_soft * xp.sqrt(qa2 + V_EPS**2)
    cols = [
        c, dot(n, _cross(xp, pdp, pvb), xp) / den_b, _sqrt0(xp, r2), _sqrt0(xp, q2), -dp_n, -vb_n,
        _sqrt0(xp, qa2), dot(pdp, pva, xp) / den_a, dot(n, _cross(xp, pdp, pva), xp) / den_a, -va_n,
    ]
    return _stack(xp, cols, -1), basis


def invariant_features(dp, v_a, v_b, R_a, feature_set: str = "5"):
    """The paper's invariant features h(x) (eq. 4), (..., 5) or (..., 6).

    Columns (see FEATURE_SETS), with ``P = I - n n^T``:

    0. ``c``: cosine of the angle between ``P dp`` and ``P v_b``, softened as
       ``(P dp . P v_b) / sqrt((|P dp|^2 + R_EPS^2) (|P v_b|^2 + V_EPS^2))`` so that
       it is smooth, lies in (-1, 1), and goes to 0 when either vector vanishes;
    1. ``|P dp|`` (m), the lateral offset from the leader's axis;
    2. ``|P v_b|`` (m/s), the follower's lateral speed;
    3. ``s = -(dp . n)`` (m), depth below the leader (paper ``[R dp]_3``, NED);
    4. ``w = -(v_b . n)`` (m/s), axial speed, positive downward (paper ``[R v_b]_3``);
    5. ``|P v_a|`` (m/s), the leader's lateral speed (feature set "6" only).

    All are invariant under rotations about ``n`` applied to dp and v_b, with
    finite values and gradients everywhere (also at r = 0 and v = 0).
    """
    _check_equivariant_set(feature_set)
    if feature_set in MEMORY_FEATURE_SETS:
        raise ValueError(f"feature_set {feature_set!r} also reads the neighbour's history: use model_inputs")
    xp, (dp, v_a, v_b, R_a) = _namespace(dp, v_a, v_b, R_a)
    return _equivariant_inputs(xp, dp, v_a, v_b, R_a, feature_set)[0]


def raw_features(dp, v_b):
    """Baseline inputs ``[dp, v_b]`` (..., 6), world frame (m, m/s)."""
    xp, (dp, v_b) = _namespace(dp, v_b)
    return xp.concatenate([dp, v_b], -1)


def equivariant_basis(dp, R_a, feature_set: str = "5"):
    """Output basis (..., 2, 3), world frame: rows ``r_hat`` and ``d = -n`` (and, for the
    "general" feature set, a third row ``t_hat = n x r_hat``, the tangential direction).

    ``r_hat = P dp / sqrt(|P dp|^2 + R_EPS^2)``: the radial unit vector in the
    leader's rotor plane, smoothly 0 on the axis (finite gradient there);
    ``d = -n``: the leader's NED-down axis (world -z for a level leader).
    """
    xp, (dp, R_a) = _namespace(dp, R_a)
    return _equivariant_inputs(xp, dp, None, None, R_a, feature_set, want_features=False)[1]


def assemble(f, basis):
    """World-frame force ``F = f1 r_hat + f2 d`` (..., 3) from outputs f (..., 2) and basis (..., 2, 3)."""
    xp, (f, basis) = _namespace(f, basis)
    return xp.einsum("...k,...kj->...j", f, basis)


def project_onto_basis(y, basis):
    """Components ``(y . r_hat, y . d)`` (..., 2) of world vectors y (..., 3): radial and NED-down."""
    xp, (y, basis) = _namespace(y, basis)
    return xp.einsum("...kj,...j->...k", basis, y)


def model_inputs(feature_set: str, dp, v_a, v_b, R_a, hist=None):
    """Network inputs for a feature set: ``(x (..., k), basis (..., 2, 3) or None)``.

    Equivariant sets ("5", "6", "general") give invariant features and the equivariant basis;
    "raw" gives ``[dp, v_b]`` and no basis (the network outputs world axes). The sets with
    memory (`MEMORY_FEATURE_SETS`) append the neighbour's history ``hist (..., H, 3)`` (module
    doc): along the basis rows for "general_memory", in world axes for "raw_memory". The other
    sets ignore ``hist``.
    """
    if feature_set not in FEATURE_SETS:
        raise ValueError(f"feature_set: expected one of {sorted(FEATURE_SETS)}, got {feature_set!r}")
    memory = feature_set in MEMORY_FEATURE_SETS
    if memory and hist is None:
        raise ValueError(f"feature set {feature_set!r} reads the neighbour's history: pass hist (..., "
                         f"{len(HISTORY_LAGS)}, 3), its displacement over each of HISTORY_LAGS")
    if feature_set in EQUIVARIANT_FEATURE_SETS:
        xp, (dp, v_a, v_b, R_a) = _namespace(dp, v_a, v_b, R_a)
        x, basis = _equivariant_inputs(xp, dp, v_a, v_b, R_a, feature_set)
    else:
        x, basis = raw_features(dp, v_b), None
    if not memory:
        return x, basis
    xp, (x, hist) = _namespace(x, hist)
    if hist.shape[-2:] != (len(HISTORY_LAGS), 3):
        raise ValueError(f"hist: expected shape (..., {len(HISTORY_LAGS)}, 3), got {tuple(hist.shape)}")
    moved = hist if basis is None else xp.einsum("...hj,...kj->...hk", hist, basis)  # (..., H, 3)
    return xp.concatenate([x, moved.reshape(*moved.shape[:-2], -1)], -1), basis


# Vehicle kinds as model inputs (Neural-Swarm2's heterogeneous sets): each vehicle's kind as a few
# scalars. Scalars do not rotate, so a model that appends them to its invariant features stays
# equivariant. Log-ratios to the paper quad: 0 for the paper quad, so data of paper quads alone
# carries zeros. Mass sets how hard a vehicle pushes (its thrust) and how little a push moves
# it; the rotor radius sets its disc area (the wake's speed and width, `downwash_core.vehicles`).
KIND_FEATURES = ("log_mass", "log_rotor_radius")


def kind_descriptors(kinds: Any) -> np.ndarray:
    """(V, len(KIND_FEATURES)) float64: each vehicle's kind (a `VehicleKind` or a registered name of
    `downwash_core.vehicles.VEHICLES`) as `KIND_FEATURES`, log-ratios to the paper quad."""
    out = np.zeros((len(kinds), len(KIND_FEATURES)))
    for v, kind in enumerate(kinds):
        q = get_vehicle(kind)  # ConfigError naming the registered kinds
        out[v] = math.log(q.mass / PAPER_QUAD.mass), math.log(q.rotor_radius / PAPER_QUAD.rotor_radius)
    return out


def neighbour_history(pos, past, index: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(W, V, K, H, 3): each neighbour slot's displacement over each lag, ``pos - past`` of the
    neighbour (positions pos (W, V, 3) now and past (H, W, V, 3) at each of `HISTORY_LAGS` ago;
    index, mask (W, V, K) of `sim.neighbours.select_neighbours`), 0 in padding."""
    moved = np.moveaxis(np.asarray(pos)[None] - np.asarray(past), 0, -2)  # (W, V, H, 3)
    gathered = moved[np.arange(index.shape[0])[:, None, None], np.maximum(index, 0)]  # (W, V, K, H, 3)
    return np.where(mask[..., None, None], gathered, 0.0)


def neighbour_kinds(kinds: np.ndarray, index: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(..., K, D): the kinds (V, D) of each neighbour slot (index, mask (..., K) of
    `sim.neighbours.select_neighbours`), 0 in padding."""
    return np.where(mask[..., None], kinds[np.maximum(index, 0)], 0.0)
