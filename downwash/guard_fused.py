"""The guard's compiled pass (`downwash.guard`): support check, rate limit and bound in one loop.

`guard_into` does what `GuardedPredictor` does to its model's prediction, one world and
vehicle at a time, with the same operations in the same order, so its bits are NumPy's:

1. the vehicle's neighbour set as the model selects it (`sim.neighbours.select_into`);
2. each pair acting on it (the vehicle below its neighbour) described as the support describes
   it: the generalised invariants (`downwash.fused.pair_inputs`, feature set "general", as
   `downwash.features.model_inputs`) and both vehicles' kinds;
3. the pair's confidence, the product over features of ``clip(1 - beyond / margin, 0, 1)``
   (`downwash.support.Support.confidence`), and that of its kind features alone
   (`downwash.support.Support.kind_confidence`); the vehicle's, the lowest of each over its pairs
   (1 with none);
4. the applied fractions of the prediction's lateral (x, y) and vertical (z) parts, each
   ``min(kind confidence, max(confidence, evidence), gain, fraction + step)`` with that part's gain
   and last fraction (``gain`` and ``evidence``: the monitor's, which ``GuardedPredictor.observe``
   sets between calls), kept in the due worlds only with the model's prediction; each part scaled
   by its fraction, the whole bounded (`downwash.fused.clamped`, the bits of
   `downwash.predictor.clamp_magnitude`); the fraction of the prediction applied, |applied| / |prediction|.

The guard's state per world and vehicle (`sim.predictor.GUARD_STATE_WIDTH` float64):
``[fraction (lateral, vertical), gain (lateral, vertical), raw prediction (3), evidence]``.

`tests/test_guard.py` ties it to the NumPy reference (`GuardedPredictor.confidence` and the
guard's NumPy path) bit for bit. The C function `GUARD_FN` of `sim.predictor.GUARD_SIGNATURE` runs it in
the simulator's fused tick; its constants travel in ``(params, iparams)`` (`pack_guard`)::

    params  = [step, bound, radius^2 (inf: none), lo (F), hi (F), margin (F), kinds (V_kinds, D)]
    iparams = [K, F, D, V_kinds]
"""

from __future__ import annotations

import numba
import numpy as np
from numba import carray

from downwash_core.jit import njit
from downwash.features import KIND_FEATURES
from downwash.fused import clamped, feature_code, pair_inputs
from downwash.support import DEPTH_COLUMN, GUARD_FEATURES, SUPPORT_FEATURES, Support
from sim.neighbours import NeighbourSet, select_into
from sim.predictor import GUARD_SIGNATURE, GUARD_STATE_WIDTH, MONITOR_SIGNATURE

__all__ = ["guard_into", "monitor_into", "pack_guard", "GUARD_FN", "MONITOR_FN", "FRACTION", "GAIN", "RAW", "EVIDENCE",
           "MONITOR_WIDTH"]

_GENERAL = feature_code(GUARD_FEATURES)
_N_INVARIANTS = len(SUPPORT_FEATURES) - 2 * len(KIND_FEATURES)
_P_STEP, _P_BOUND, _P_RADIUS2, _N_FHEADER = 0, 1, 2, 3
_I_K, _I_F, _I_D, _I_VK = 0, 1, 2, 3
# the state's columns: the applied fractions and the monitor's gains (each of the lateral, then the vertical
# part), the raw prediction (3), the monitor's evidence
FRACTION, GAIN, RAW, EVIDENCE = 0, 2, 4, 7
assert GUARD_STATE_WIDTH == EVIDENCE + 1, "sim.predictor.GUARD_STATE_WIDTH must hold the columns above"


@njit
def _min(a, b):
    """np.minimum of two floats: NaN if either is."""
    if a != a or b != b:
        return np.nan
    return a if a < b else b


@njit
def _max(a, b):
    """np.maximum of two floats: NaN if either is."""
    if a != a or b != b:
        return np.nan
    return a if a > b else b


@njit
def guard_into(pos, vel, rot, due, pred, state, applied, params, iparams):
    """The guard on pred (W, V, 3) m/s^2, in place (module doc), from estimated pos, vel (W, V, 3) and
    rot (W, V, 3, 3); due (W,) bool; state (W, V, GUARD_STATE_WIDTH) and applied (W, V), advanced in
    the due worlds."""
    W, V = pos.shape[0], pos.shape[1]
    K, F, D, VK = iparams[_I_K], iparams[_I_F], iparams[_I_D], iparams[_I_VK]
    step, bound, radius2 = params[_P_STEP], params[_P_BOUND], params[_P_RADIUS2]
    o = _N_FHEADER
    lo, hi, margin = params[o:o + F], params[o + F:o + 2 * F], params[o + 2 * F:o + 3 * F]
    kinds = params[o + 3 * F:o + 3 * F + VK * D].reshape((VK, D))
    x = np.empty(max(F, _N_INVARIANTS))  # (pair_inputs writes the invariants, then the kinds follow)
    key, idx = np.empty(max(V - 1, 1)), np.empty(max(V - 1, 1), np.int64)
    for w in range(W):
        for j in range(V):  # target
            n = select_into(pos, w, j, radius2, K, key, idx)
            conf = kind_conf = 1.0
            for s in range(n):
                i = idx[s]  # neighbour
                nx, ny, nz = rot[w, i, 0, 2], rot[w, i, 1, 2], rot[w, i, 2, 2]
                dx, dy, dz = pos[w, j, 0] - pos[w, i, 0], pos[w, j, 1] - pos[w, i, 1], pos[w, j, 2] - pos[w, i, 2]
                dp_n = dx * nx + dy * ny + dz * nz
                pair_inputs(dx, dy, dz, nx, ny, nz, dp_n, vel[w, j, 0], vel[w, j, 1], vel[w, j, 2],
                            vel[w, i, 0], vel[w, i, 1], vel[w, i, 2], _GENERAL, x)
                if not x[DEPTH_COLUMN] > 0.0:  # not below its neighbour: the pair does not act
                    continue
                for q in range(D):  # the neighbour's kind, then the target's (none told: paper quads, 0)
                    x[_N_INVARIANTS + q] = kinds[i, q] if VK > 0 else 0.0
                    x[_N_INVARIANTS + D + q] = kinds[j, q] if VK > 0 else 0.0
                c = ck = 1.0  # (1 c_0 = c_0: the products' bits as np.prod's, which starts at c_0)
                for f in range(F):
                    beyond = _max(_max(lo[f] - x[f], x[f] - hi[f]), 0.0) / margin[f]
                    term = _min(_max(1.0 - beyond, 0.0), 1.0)  # np.clip
                    c = c * term
                    if f >= _N_INVARIANTS:  # a kind feature
                        ck = ck * term
                conf = _min(conf, c)
                kind_conf = _min(kind_conf, ck)
            conf = _min(kind_conf, _max(conf, state[w, j, EVIDENCE]))
            lateral = _min(_min(conf, state[w, j, GAIN]), state[w, j, FRACTION] + step)
            vertical = _min(_min(conf, state[w, j, GAIN + 1]), state[w, j, FRACTION + 1] + step)
            rx, ry, rz = pred[w, j, 0], pred[w, j, 1], pred[w, j, 2]
            ox, oy, oz = clamped(rx * lateral, ry * lateral, rz * vertical, bound)
            if due[w]:
                state[w, j, FRACTION], state[w, j, FRACTION + 1] = lateral, vertical
                state[w, j, RAW], state[w, j, RAW + 1], state[w, j, RAW + 2] = rx, ry, rz
                raw_norm = np.sqrt(rx * rx + ry * ry + rz * rz)
                out_norm = np.sqrt(ox * ox + oy * oy + oz * oz)
                applied[w, j] = out_norm / (raw_norm if raw_norm > 1e-300 else 1e-300) if raw_norm > 0.0 else 1.0
            pred[w, j, 0], pred[w, j, 1], pred[w, j, 2] = ox, oy, oz


@numba.cfunc(GUARD_SIGNATURE, cache=True, nopython=True)
def _guard_c(n_worlds, n_veh, pos, vel, rot, due, pred, state, applied, params, iparams):
    ints = carray(iparams, (4,))
    n_params = _N_FHEADER + 3 * ints[_I_F] + ints[_I_VK] * ints[_I_D]
    guard_into(carray(pos, (n_worlds, n_veh, 3)), carray(vel, (n_worlds, n_veh, 3)),
               carray(rot, (n_worlds, n_veh, 3, 3)), carray(due, (n_worlds,)), carray(pred, (n_worlds, n_veh, 3)),
               carray(state, (n_worlds, n_veh, GUARD_STATE_WIDTH)), carray(applied, (n_worlds, n_veh)),
               carray(params, (n_params,)), ints)


GUARD_FN = _guard_c

# the monitor's memory per world and vehicle (`monitor_into`): its sums (each of the lateral, then the
# vertical part), the last tick's estimated velocity and command, the prediction held through the last
# tick and the one after it, the fast sums (as the sums, over the fast memory)
NUM, DEN, VEL, CMD, HELD, NEXT, FAST_NUM, FAST_DEN = 0, 2, 4, 7, 10, 13, 16, 18
MONITOR_WIDTH = 20
assert DEN == NUM + 2 and FAST_DEN == FAST_NUM + 2, "monitor_into reads each part's |r|^2 sum two after its f.r sum"


@njit
def monitor_into(t, vel_est, u_cmd, state, seen, seen_t, memory, prior, skeptic, fast, fast_prior):
    """The monitor after a tick (`downwash.guard`, ``GuardedPredictor.observe``): from its row's t (W,),
    vel_est and u_cmd (W, V, 3), the force of the tick before each vehicle felt, paired with the
    prediction held through it; the sums of the lateral and the vertical parts (seen (W, V,
    MONITOR_WIDTH), decayed over `memory` s, and again over `fast` s), their gains (state's GAIN
    columns: the lower of the two scales, with `prior` and `fast_prior`) and the evidence of both parts
    together (its EVIDENCE column, from the slow sums, with its `skeptic`) advanced in place.
    seen_t (W,): the last tick's times (NaN: none)."""
    W, V = state.shape[0], state.shape[1]
    for w in range(W):
        dt = t[w] - seen_t[w]
        seen_t[w] = t[w]
        for j in range(V):
            m = seen[w, j]
            if dt > 0.0:  # (False where the last tick is unseen: NaN)
                fx = (vel_est[w, j, 0] - m[VEL]) / dt - m[CMD]
                fy = (vel_est[w, j, 1] - m[VEL + 1]) / dt - m[CMD + 1]
                fz = (vel_est[w, j, 2] - m[VEL + 2]) / dt - m[CMD + 2]
                rx, ry, rz = m[HELD], m[HELD + 1], m[HELD + 2]
                if np.isfinite(fx + fy + fz + rx + ry + rz):
                    for sums, tau in ((NUM, memory), (FAST_NUM, fast)):  # the slow sums, then the fast ones
                        decay = np.exp(-dt / tau)
                        m[sums] = decay * m[sums] + (fx * rx + fy * ry)
                        m[sums + 1] = decay * m[sums + 1] + fz * rz
                        m[sums + 2] = decay * m[sums + 2] + (rx * rx + ry * ry)
                        m[sums + 3] = decay * m[sums + 3] + rz * rz
            for p in range(2):  # the lateral part, the vertical part
                slow = _min(_max((m[NUM + p] + prior) / (m[DEN + p] + prior), 0.0), 1.0)
                quick = _min(_max((m[FAST_NUM + p] + fast_prior) / (m[FAST_DEN + p] + fast_prior), 0.0), 1.0)
                state[w, j, GAIN + p] = _min(slow, quick)
            state[w, j, EVIDENCE] = _min(_max((m[NUM] + m[NUM + 1]) / (m[DEN] + m[DEN + 1] + skeptic), 0.0), 1.0)
            for k in range(3):  # this tick's prediction was made before it: it is held through the next one
                m[HELD + k], m[NEXT + k] = m[NEXT + k], state[w, j, RAW + k]
                m[VEL + k], m[CMD + k] = vel_est[w, j, k], u_cmd[w, j, k]


@numba.cfunc(MONITOR_SIGNATURE, cache=True, nopython=True)
def _monitor_c(n_worlds, n_veh, t, vel_est, u_cmd, state, seen, seen_t, params, iparams):
    p = carray(params, (5,))  # memory, prior, skeptic, fast, fast_prior
    monitor_into(carray(t, (n_worlds,)), carray(vel_est, (n_worlds, n_veh, 3)), carray(u_cmd, (n_worlds, n_veh, 3)),
                 carray(state, (n_worlds, n_veh, GUARD_STATE_WIDTH)),
                 carray(seen, (n_worlds, n_veh, carray(iparams, (1,))[0])), carray(seen_t, (n_worlds,)),
                 p[0], p[1], p[2], p[3], p[4])


MONITOR_FN = _monitor_c  # the monitor as the fused tick calls it (`sim.predictor.MONITOR_SIGNATURE`)


def pack_guard(support: Support, neighbours: NeighbourSet, step: float, bound: float,
               kinds: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(params, iparams) of `guard_into` (module doc); kinds (V, D) of `downwash.features.kind_descriptors`
    or None (paper quads)."""
    D = len(KIND_FEATURES)
    table = np.zeros((0, D)) if kinds is None else np.asarray(kinds, dtype=np.float64)
    radius2 = np.inf if neighbours.radius is None else float(neighbours.radius) ** 2
    params = np.concatenate([[step, bound, radius2], support.lo, support.hi, support.margin, table.ravel()])
    iparams = np.array([neighbours.max_neighbours, len(SUPPORT_FEATURES), D, len(table)], dtype=np.int64)
    return np.ascontiguousarray(params, dtype=np.float64), iparams
