"""The learned predictor as compiled passes: neighbour sets, networks, pooling and clamp in one loop.

`LearnedPredictor(backend="compiled")`, the default for every kind of
`downwash.registry.MODEL_KINDS`, evaluates a model in the 45 Hz slot with these kernels (a
per-neighbour model as ``summed_pairwise``), and the simulator's fused tick calls them as C
functions of `sim.predictor.PREDICTOR_SIGNATURE` (`LearnedPredictor.compiled()`), so a
flight with a learned model stays in compiled code. Per world and target vehicle each kernel

1. selects the neighbour set as `sim.neighbours.select_neighbours` does (its compiled twin `sim.neighbours.select_into`): the
   other vehicles at a finite squared distance ``(dx dx + dy dy) + dz dz`` (the same sum),
   within the radius if one is set, nearest first by a stable insertion sort (ties by vehicle
   index), at most K;
2. gathers each neighbour's inputs as `sim.neighbours.gather_neighbours` does
   (``dp = p_target - p_neighbour``, the neighbour's velocity and attitude, the target's velocity);
3. evaluates the model: ``summed_pairwise`` with the pair kernel's own pieces
   (`downwash.fused.pair_inputs`, `mlp_inplace`, `pair_force`: the depth gate included), the deep
   sets with the same features (`pair_inputs`), their normalisation, phi per neighbour, the sums
   over the real neighbours, and rho;
4. bounds each vehicle's magnitude (`downwash.fused.clamped`, the bits of
   `downwash.predictor.clamp_magnitude`).

One kernel and one C function per kind serve every model of that kind: a model's constants
travel in ``(params float64, iparams int64)`` (`pack_model`), never as compile-time constants::

    params  = [clamp (<= 0: none), radius^2 (inf: none), extra..., w1..., b1..., w2..., b2...]
    iparams = [K, feature code, L, G, n_basis, len(extra), len(w1), len(b1), len(widths1),
               len(w2), len(b2), len(widths2), D, V_kinds, widths1..., widths2...]

with the networks as `downwash.fused.pack_layers` lays them out (net 1: the pair network or
phi; net 2: rho) and ``extra`` the normalisation (deepsets_equivariant: in_mean, in_std,
out_scale; deepsets: in_mean, in_std, out_mean, out_std; summed_pairwise: none, folded into
the layers as for the pair predictor), then, for a model that reads the vehicle kinds
(D = len(`downwash.features.KIND_FEATURES`), else 0), each vehicle's kind (V_kinds, D): the
scene's (`LearnedPredictor.for_vehicles`), or none (V_kinds = 0: every vehicle a paper quad, 0).
A table of another vehicle count than the call's gives NaN: a loud flight, never a silent one.

The readable reference is each model's float64 NumPy twin (`SetModel.numpy_forward`,
`LearnedPredictor(backend="numpy")`). The kernels agree with it to float64 rounding, not bit
for bit: the twin's networks are BLAS products (another summation order, FMA on some CPUs)
and the pair force is assembled as the pair kernel assembles it (``f1 px / r`` where the twin
has ``f1 (px / r)``); `tests/test_set_fused.py` bounds the difference. numba checks a cached
kernel against its own file only: after editing `downwash/fused.py` delete the caches (see
`downwash_core.jit`), or these kernels keep the old pieces.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numba
import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash.features import KIND_FEATURES
from downwash.fused import clamped, feature_code, mlp_inplace, pack_layers, pair_force, pair_inputs
from sim.neighbours import NeighbourSet, select_into
from sim.predictor import PREDICTOR_SIGNATURE, CompiledPredictor

__all__ = [
    "COMPILED_KINDS",
    "KindKernel",
    "summed_pairwise_into",
    "deepsets_equivariant_into",
    "deepsets_into",
    "pack_model",
]

# iparams header: see the module docstring
_I_K, _I_CODE, _I_LATENT, _I_VECTORS, _I_BASIS = 0, 1, 2, 3, 4
_I_EXTRA, _I_W1, _I_B1, _I_L1, _I_W2, _I_B2, _I_L2 = 5, 6, 7, 8, 9, 10, 11
_I_KIND_D, _I_KIND_V = 12, 13
_N_IHEADER = 14
_P_CLAMP, _P_RADIUS2 = 0, 1  # params header
_N_FHEADER = 2


# -- the pieces every kind shares ---------------------------------------------------------------


@njit
def _unpack(params, iparams):
    """(extra, w1, b1, widths1, w2, b2, widths2): views of the packed constants (module docstring)."""
    n_extra, n_w1, n_b1, n_l1 = iparams[_I_EXTRA], iparams[_I_W1], iparams[_I_B1], iparams[_I_L1]
    n_w2, n_b2, n_l2 = iparams[_I_W2], iparams[_I_B2], iparams[_I_L2]
    o = _N_FHEADER
    extra = params[o:o + n_extra]
    o += n_extra
    w1 = params[o:o + n_w1]
    o += n_w1
    b1 = params[o:o + n_b1]
    o += n_b1
    w2 = params[o:o + n_w2]
    o += n_w2
    b2 = params[o:o + n_b2]
    widths1 = iparams[_N_IHEADER:_N_IHEADER + n_l1]
    widths2 = iparams[_N_IHEADER + n_l1:_N_IHEADER + n_l1 + n_l2]
    return extra, w1, b1, widths1, w2, b2, widths2


@njit
def _kind_table(extra, start, iparams):
    """(D, kinds (V_kinds, D)): the vehicles' kinds that follow the normalisation at extra[start:]."""
    D, n = iparams[_I_KIND_D], iparams[_I_KIND_V]
    return D, extra[start:start + n * D].reshape((n, D))


@njit
def _kinds_into(x, start, D, kinds, i, j, V):
    """x[start:start + 2 D] = neighbour i's kind, then target j's (0 without a table: paper quads;
    NaN for a table of another vehicle count than V). False when x holds NaN."""
    for q in range(D):
        if kinds.shape[0] == 0:
            x[start + q], x[start + D + q] = 0.0, 0.0
        elif kinds.shape[0] == V:
            x[start + q], x[start + D + q] = kinds[i, q], kinds[j, q]
        else:
            x[start + q], x[start + D + q] = np.nan, np.nan


@njit
def _max_width(widths1, widths2):
    width = 1
    for k in range(widths1.shape[0]):
        width = max(width, widths1[k])
    for k in range(widths2.shape[0]):
        width = max(width, widths2[k])
    return width


# -- the kernels, one per kind: (pos, vel, rot, params, iparams, out), all C-contiguous float64 / int64 ----


@njit
def summed_pairwise_into(pos, vel, rot, params, iparams, out):
    """``summed_pairwise`` on every vehicle into out (W, V, 3) m/s^2 from estimated pos, vel (W, V, 3)
    and rot (W, V, 3, 3): the pair network (`downwash.fused`'s pieces) on each (neighbour, target)
    pair of the neighbour set, nearest first, 0 where the target is not below the neighbour, summed."""
    W, V = pos.shape[0], pos.shape[1]
    K, code = iparams[_I_K], iparams[_I_CODE]
    clamp, radius2 = params[_P_CLAMP], params[_P_RADIUS2]
    _, weights, biases, widths, _, _, widths2 = _unpack(params, iparams)
    width = _max_width(widths, widths2)
    x, y = np.empty(width), np.empty(width)
    key, idx = np.empty(max(V - 1, 1)), np.empty(max(V - 1, 1), np.int64)
    for w in range(W):
        for j in range(V):  # target
            n = select_into(pos, w, j, radius2, K, key, idx)
            fx, fy, fz = 0.0, 0.0, 0.0
            for s in range(n):
                i = idx[s]  # neighbour
                nx, ny, nz = rot[w, i, 0, 2], rot[w, i, 1, 2], rot[w, i, 2, 2]
                dx, dy, dz = pos[w, j, 0] - pos[w, i, 0], pos[w, j, 1] - pos[w, i, 1], pos[w, j, 2] - pos[w, i, 2]
                dp_n = dx * nx + dy * ny + dz * nz
                if not -dp_n > 0.0:  # the depth gate
                    continue
                px, py, pz, r_soft = pair_inputs(dx, dy, dz, nx, ny, nz, dp_n, vel[w, j, 0], vel[w, j, 1], vel[w, j, 2],
                                                 vel[w, i, 0], vel[w, i, 1], vel[w, i, 2], code, x)
                mlp_inplace(x, y, weights, biases, widths)
                gx, gy, gz = pair_force(x, code, px, py, pz, r_soft, nx, ny, nz, 0.0, 0.0, 0.0)
                fx, fy, fz = fx + gx, fy + gy, fz + gz
            out[w, j, 0], out[w, j, 1], out[w, j, 2] = clamped(fx, fy, fz, clamp)


@njit
def deepsets_equivariant_into(pos, vel, rot, params, iparams, out):
    """``deepsets_equivariant`` (`downwash.set_models.DeepSetsEquivariant.decode`, step for step)
    on every vehicle into out (W, V, 3) m/s^2: per neighbour the invariant features and basis rows,
    phi -> (z_i, a_i); S = sum z_i, U_g = sum_i,c a_i,g,c b_i,c; rho(z_i, S, U . b_i) -> c_i;
    F = out_scale sum_i,c c_i,c b_i,c."""
    W, V = pos.shape[0], pos.shape[1]
    K, code = iparams[_I_K], iparams[_I_CODE]
    L, G, nb = iparams[_I_LATENT], iparams[_I_VECTORS], iparams[_I_BASIS]
    clamp, radius2 = params[_P_CLAMP], params[_P_RADIUS2]
    extra, w_phi, b_phi, widths_phi, w_rho, b_rho, widths_rho = _unpack(params, iparams)
    k = widths_phi[0]
    mean, std, scale = extra[:k], extra[k:2 * k], extra[2 * k]
    D, kinds = _kind_table(extra, 2 * k + 1, iparams)
    width = _max_width(widths_phi, widths_rho)
    x, y = np.empty(width), np.empty(width)
    key, idx = np.empty(max(V - 1, 1)), np.empty(max(V - 1, 1), np.int64)
    n_h = L + G * nb
    h = np.empty((max(K, 1), n_h))  # phi's outputs per neighbour
    basis = np.empty((max(K, 1), 3, 3))  # basis rows per neighbour: r_hat, d = -n (, t_hat = n x r_hat)
    pooled = np.empty(L)
    vec = np.empty((G, 3))
    for w in range(W):
        for j in range(V):  # target
            n = select_into(pos, w, j, radius2, K, key, idx)
            for q in range(L):
                pooled[q] = 0.0
            for s in range(n):
                i = idx[s]
                nx, ny, nz = rot[w, i, 0, 2], rot[w, i, 1, 2], rot[w, i, 2, 2]
                dx, dy, dz = pos[w, j, 0] - pos[w, i, 0], pos[w, j, 1] - pos[w, i, 1], pos[w, j, 2] - pos[w, i, 2]
                dp_n = dx * nx + dy * ny + dz * nz
                px, py, pz, r_soft = pair_inputs(dx, dy, dz, nx, ny, nz, dp_n, vel[w, j, 0], vel[w, j, 1], vel[w, j, 2],
                                                 vel[w, i, 0], vel[w, i, 1], vel[w, i, 2], code, x)
                rx, ry, rz = px / r_soft, py / r_soft, pz / r_soft  # as downwash.features: r_hat = P dp / r_soft
                basis[s, 0, 0], basis[s, 0, 1], basis[s, 0, 2] = rx, ry, rz
                basis[s, 1, 0], basis[s, 1, 1], basis[s, 1, 2] = -nx, -ny, -nz
                if nb == 3:
                    basis[s, 2, 0] = ny * rz - nz * ry
                    basis[s, 2, 1] = nz * rx - nx * rz
                    basis[s, 2, 2] = nx * ry - ny * rx
                _kinds_into(x, k - 2 * D, D, kinds, i, j, V)
                for q in range(k):
                    x[q] = (x[q] - mean[q]) / std[q]
                mlp_inplace(x, y, w_phi, b_phi, widths_phi)
                for q in range(n_h):
                    h[s, q] = x[q]
                for q in range(L):
                    pooled[q] += x[q]
            for g in range(G):  # U_g: world vectors
                for t in range(3):
                    acc = 0.0
                    for s in range(n):
                        for c in range(nb):
                            acc += h[s, L + g * nb + c] * basis[s, c, t]
                    vec[g, t] = acc
            fx, fy, fz = 0.0, 0.0, 0.0
            for s in range(n):
                for q in range(L):
                    x[q] = h[s, q]
                    x[L + q] = pooled[q]
                for g in range(G):  # U_g . b_i,c: invariant in each neighbour's frame
                    for c in range(nb):
                        x[2 * L + g * nb + c] = (basis[s, c, 0] * vec[g, 0] + basis[s, c, 1] * vec[g, 1]
                                                 + basis[s, c, 2] * vec[g, 2])
                mlp_inplace(x, y, w_rho, b_rho, widths_rho)
                for c in range(nb):
                    coef = x[c] * scale
                    fx += coef * basis[s, c, 0]
                    fy += coef * basis[s, c, 1]
                    fz += coef * basis[s, c, 2]
            out[w, j, 0], out[w, j, 1], out[w, j, 2] = clamped(fx, fy, fz, clamp)


@njit
def deepsets_into(pos, vel, rot, params, iparams, out):
    """``deepsets`` (Neural-Swarm2's, `downwash.set_models.DeepSets.decode`) on every vehicle into
    out (W, V, 3) m/s^2: rho(sum_i phi(([dp_i, v_i, v_b] - in_mean) / in_std)) out_std + out_mean,
    0 for a target without neighbours."""
    W, V = pos.shape[0], pos.shape[1]
    K = iparams[_I_K]
    clamp, radius2 = params[_P_CLAMP], params[_P_RADIUS2]
    extra, w_phi, b_phi, widths_phi, w_rho, b_rho, widths_rho = _unpack(params, iparams)
    k, L = widths_phi[0], widths_rho[0]
    mean, std, out_mean, out_std = extra[:k], extra[k:2 * k], extra[2 * k:2 * k + 3], extra[2 * k + 3:2 * k + 6]
    D, kinds = _kind_table(extra, 2 * k + 6, iparams)
    width = _max_width(widths_phi, widths_rho)
    x, y = np.empty(width), np.empty(width)
    key, idx = np.empty(max(V - 1, 1)), np.empty(max(V - 1, 1), np.int64)
    pooled = np.empty(L)
    for w in range(W):
        for j in range(V):  # target
            n = select_into(pos, w, j, radius2, K, key, idx)
            for q in range(L):
                pooled[q] = 0.0
            for s in range(n):
                i = idx[s]
                for t in range(3):
                    x[t] = pos[w, j, t] - pos[w, i, t]
                    x[3 + t] = vel[w, i, t]
                    x[6 + t] = vel[w, j, t]
                _kinds_into(x, 9, D, kinds, i, j, V)
                for q in range(k):
                    x[q] = (x[q] - mean[q]) / std[q]
                mlp_inplace(x, y, w_phi, b_phi, widths_phi)
                for q in range(L):
                    pooled[q] += x[q]
            fx, fy, fz = 0.0, 0.0, 0.0
            if n > 0:
                for q in range(L):
                    x[q] = pooled[q]
                mlp_inplace(x, y, w_rho, b_rho, widths_rho)
                fx = x[0] * out_std[0] + out_mean[0]
                fy = x[1] * out_std[1] + out_mean[1]
                fz = x[2] * out_std[2] + out_mean[2]
            out[w, j, 0], out[w, j, 1], out[w, j, 2] = clamped(fx, fy, fz, clamp)


# -- the C functions of PREDICTOR_SIGNATURE, one per kind ----------------------------------------


@njit
def _views(n_worlds, n_veh, pos, vel, rot, params, iparams, out):
    """The C signature's pointers as the kernels' arrays (estimated states; the truth is not used)."""
    n_floats = (_N_FHEADER + iparams[_I_EXTRA] + iparams[_I_W1] + iparams[_I_B1] + iparams[_I_W2]
                + iparams[_I_B2])
    n_ints = _N_IHEADER + iparams[_I_L1] + iparams[_I_L2]
    return (numba.carray(pos, (n_worlds, n_veh, 3)), numba.carray(vel, (n_worlds, n_veh, 3)),
            numba.carray(rot, (n_worlds, n_veh, 3, 3)), numba.carray(params, (n_floats,)),
            numba.carray(iparams, (n_ints,)), numba.carray(out, (n_worlds, n_veh, 3)))


@numba.cfunc(PREDICTOR_SIGNATURE, cache=True, nopython=True)
def _summed_pairwise_c(n_worlds, n_veh, pos, vel, rot, true_pos, true_vel, true_rot, params, iparams, out):
    p, v, r, f, i, o = _views(n_worlds, n_veh, pos, vel, rot, params, iparams, out)
    summed_pairwise_into(p, v, r, f, i, o)


@numba.cfunc(PREDICTOR_SIGNATURE, cache=True, nopython=True)
def _deepsets_equivariant_c(n_worlds, n_veh, pos, vel, rot, true_pos, true_vel, true_rot, params, iparams, out):
    p, v, r, f, i, o = _views(n_worlds, n_veh, pos, vel, rot, params, iparams, out)
    deepsets_equivariant_into(p, v, r, f, i, o)


@numba.cfunc(PREDICTOR_SIGNATURE, cache=True, nopython=True)
def _deepsets_c(n_worlds, n_veh, pos, vel, rot, true_pos, true_vel, true_rot, params, iparams, out):
    p, v, r, f, i, o = _views(n_worlds, n_veh, pos, vel, rot, params, iparams, out)
    deepsets_into(p, v, r, f, i, o)


class KindKernel(NamedTuple):
    """A kind's compiled form: kernel(pos, vel, rot, params, iparams, out) (C-contiguous float64
    arrays; iparams int64) and the address of the same as a C function of `PREDICTOR_SIGNATURE`."""

    kernel: Any
    address: int


# kind -> its kernel and C function (every kind of SET_KINDS; a new kind needs its own, and its
# constants in `pack_model`); `LearnedPredictor` looks them up by kind, so an unpickled one finds them
COMPILED_KINDS: dict[str, KindKernel] = {
    "summed_pairwise": KindKernel(summed_pairwise_into, _summed_pairwise_c.address),
    "deepsets_equivariant": KindKernel(deepsets_equivariant_into, _deepsets_equivariant_c.address),
    "deepsets": KindKernel(deepsets_into, _deepsets_c.address),
}


# -- packing a model's constants -----------------------------------------------------------------

_NO_NET = (np.zeros(0), np.zeros(0), np.zeros(0, np.int64))


def _in_out(layers: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`pack_layers` of `downwash.set_models.numpy_set_layers`' [(W (in, out), b), ...] (the NumPy twin's
    own float64 weights)."""
    return pack_layers([(w.T, b) for w, b in layers])


def _abi(K: int, code: int, L: int, G: int, nb: int, neighbours: NeighbourSet, clamp: float | None,
         extra: np.ndarray, net1: tuple, net2: tuple, kinds: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """kinds: None for a model that reads no kinds (D = 0), else the vehicles' (V_kinds, D) table."""
    (w1, b1, l1), (w2, b2, l2) = net1, net2
    table = np.zeros((0, 0)) if kinds is None else np.asarray(kinds, dtype=np.float64)
    D = table.shape[1]
    radius2 = np.inf if neighbours.radius is None else neighbours.radius**2  # as select_neighbours squares it
    params = np.concatenate([[0.0 if clamp is None else float(clamp), radius2], extra, table.ravel(), w1, b1, w2, b2])
    iparams = np.concatenate([[K, code, L, G, nb, extra.size + table.size, w1.size, b1.size, l1.size, w2.size,
                               b2.size, l2.size, D, table.shape[0]], l1, l2])
    return np.ascontiguousarray(params, dtype=np.float64), np.ascontiguousarray(iparams, dtype=np.int64)


def pack_model(model: Any, neighbours: NeighbourSet, clamp: float | None = None,
               kinds: np.ndarray | None = None) -> tuple[KindKernel, CompiledPredictor]:
    """A model's compiled form: (its kind's `KindKernel`, `CompiledPredictor(address, params,
    iparams)`) with the model's constants as its NumPy twin has them (eval mode, float64).

    model: a `downwash.set_models.SetModel` of a kind in `COMPILED_KINDS`, in eval mode;
    neighbours: its neighbour set; clamp: m/s^2 bound on each vehicle's magnitude, or None;
    kinds: (V, D) the vehicles' kinds (`downwash.features.kind_descriptors`) for a model that reads
    them (None: every vehicle a paper quad); a model that does not ignores them.
    KeyError for a kind without a compiled form.
    """
    from downwash.set_models import numpy_set_layers  # the twin's own weights

    kind = model.kind
    entry = COMPILED_KINDS[kind]
    K = neighbours.max_neighbours
    f64 = lambda t: t.detach().double().numpy().ravel()  # noqa: E731
    if not getattr(model, "kinds", False):
        table = None
    elif kinds is None:
        table = np.zeros((0, len(KIND_FEATURES)))
    else:
        table = np.asarray(kinds, dtype=np.float64)
        if table.ndim != 2 or table.shape[1] != len(KIND_FEATURES):
            raise ConfigError(f"kinds: expected (V, {len(KIND_FEATURES)}) vehicle kinds (kind_descriptors), "
                              f"got shape {table.shape}")
    if kind == "summed_pairwise":
        pair = model.pairwise  # the folded float64 layers of its NumPy twin
        abi = _abi(K, feature_code(pair.feature_set), 0, 0, 0, neighbours, clamp, np.zeros(0),
                   pack_layers(pair.folded_layers()), _NO_NET)
    elif kind == "deepsets_equivariant":
        extra = np.concatenate([f64(model.in_mean), f64(model.in_std), [float(model.out_scale)]])
        abi = _abi(K, feature_code(model.feature_set), model.latent, model.vectors, model.n_basis, neighbours, clamp,
                   extra, _in_out(numpy_set_layers(model.phi)), _in_out(numpy_set_layers(model.rho)), table)
    elif kind == "deepsets":
        extra = np.concatenate([f64(model.in_mean), f64(model.in_std), f64(model.out_mean), f64(model.out_std)])
        abi = _abi(K, 0, model.latent, 0, 0, neighbours, clamp, extra, _in_out(numpy_set_layers(model.phi)),
                   _in_out(numpy_set_layers(model.rho)), table)
    else:  # pragma: no cover - COMPILED_KINDS and this function list the same kinds
        raise KeyError(kind)
    return entry, CompiledPredictor(entry.address, *abi)
