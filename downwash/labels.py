"""Force labels ``f = a - u`` from flight logs (paper section 4.C).

Every target vehicle's acceleration ``a`` (the pair's follower; every vehicle but the
leader of a swarm) comes from its motion-capture positions through an offline Savitzky-Golay second-derivative filter; ``u`` is the commanded
acceleration actually applied (compensation included, gravity excluded), so the
label is the FULL downwash also when a model was compensating during the flight.

Smoothing of ``u``. ``a`` is smoothed by the filter, ``u`` is not, so ``a - u``
would mix a smoothed and a raw signal. The Savitzky-Golay second-derivative
coefficients factor exactly as ``c = D2 * K / dt^2`` with ``D2 = [1, -2, 1]`` the
second difference and ``K`` a kernel of ``window - 2`` taps summing to 1
(`command_kernel`). So the filtered acceleration is ``K`` applied to the
second difference of the positions (~ x''), and we apply the same ``K`` to ``u``:
the label is ``K * (x'' - u) = K * f``, a consistently smoothed force, not a
smoothed acceleration minus a raw command.

Inputs paired with each label are what the vehicles know: the Kalman-filtered
positions and velocities (``pos_est``, ``vel_est``) of the target and of its neighbour
set (`sim.neighbours`, padded to a fixed count with a mask) and the neighbours'
attitudes (``quat_est``): what a lab measures. The truth (``quat``, ``field_*``) is only
carried along for diagnostics.
"""

from __future__ import annotations

import functools
import os
from fractions import Fraction
from typing import Iterable, Sequence

import numpy as np
from scipy.ndimage import convolve1d
from scipy.signal import savgol_filter

from downwash_core.errors import ConfigError
from downwash_core.geometry import quat_to_mat
from downwash_core.vehicles import DEFAULT_VEHICLE
from downwash.features import HISTORY_LAGS, KIND_FEATURES, kind_descriptors, neighbour_history, neighbour_kinds
from sim.logs import FlightLog, load_log
from sim.neighbours import NeighbourSet, gather_neighbours, select_neighbours

__all__ = [
    "DEFAULT_WINDOW",
    "DEFAULT_POLYORDER",
    "FAIL_MARGIN_S",
    "SAMPLE_SCHEMA",
    "MODEL_INPUTS",
    "PAIR",
    "sample_period",
    "follower_acceleration",
    "second_derivative_coeffs",
    "command_kernel",
    "smooth_command",
    "log_targets",
    "log_kinds",
    "past_positions",
    "labels_from_log",
    "label_noise_floor",
    "LABEL_ARRAYS",
    "finite_rows",
]

# Filter choice (50 Hz controller ticks, 0.5 mm motion-capture noise). Measured on a
# wake-like pulse x'' = exp(-t^2 / 2 tau^2) (tau = 0.1 s: a 1 m/s pass through a
# ~0.16 m wide wake at 0.5 m separation) and on white position noise:
#   window, polyorder   noise std (m/s^2)   peak bias, tau = 0.1 s   tau = 0.05 s
#   11, 2               0.085               7.6 %                     24 %
#   15, 4               0.141               1.3 %                     11 %
#   19, 4               0.077               3.1 %                     19 %
#   21, 4               0.059               4.3 %                     24 %
# 19 / 4 (0.38 s) beats 11 / 2 on both noise and bias; the noise (0.077 m/s^2 per
# axis) is well under the paper's ~0.22 m/s^2 validation RMSE. The filter is
# symmetric (zero phase), so there is no lag, only this smoothing bias.
DEFAULT_WINDOW = 19  # samples at 50 Hz (0.38 s)
DEFAULT_POLYORDER = 4
FAIL_MARGIN_S = 0.5  # s, dropped before the end of a flight that ended early (collision, divergence)

# One labelled sample, the schema of the one data set (`downwash.datasets.Dataset`): name ->
# (trailing shape with K = the neighbour set's max_neighbours, meaning). For target j and
# neighbour i (estimated states): the pair is K = 1 with the leader as the one neighbour.
SAMPLE_SCHEMA: dict[str, tuple[tuple[str | int, ...], str]] = {
    "dp": (("K", 3), "m, p_target - p_neighbour (estimates), world frame; 0 in padding"),
    "v_a": (("K", 3), "m/s, neighbour velocity (estimate), world frame; 0 in padding"),
    "v_b": ((3,), "m/s, target velocity (estimate), world frame"),
    "R_a": (("K", 3, 3), "neighbour body-to-world rotation (motion capture); identity in padding"),
    "mask": (("K",), "True for a real neighbour, False for padding"),
    "kind_a": (("K", len(KIND_FEATURES)), "the neighbour's vehicle kind (`downwash.features.KIND_FEATURES`); 0 in padding"),
    "kind_b": ((len(KIND_FEATURES),), "the target's vehicle kind (`downwash.features.KIND_FEATURES`)"),
    "hist": (("K", len(HISTORY_LAGS), 3), "m, the neighbour's displacement over each lag of "
                                          "`downwash.features.HISTORY_LAGS` (estimates); 0 in padding"),
    "neighbour": (("K",), "vehicle index of each neighbour in the log, -1 in padding"),
    "vehicle": ((), "vehicle index of the target in the log"),
    "y": ((3,), "m/s^2, label f = a - u on the target, world frame"),
    "t": ((), "s, tick time within the flight"),
    "row": ((), "row index in the log"),
    "field_mean": ((3,), "m/s^2, true mean field on the target (diagnostics only)"),
    "field_applied": ((3,), "m/s^2, true applied field, mean + turbulence (diagnostics only)"),
}
PAIR = NeighbourSet(max_neighbours=1)  # the two-vehicle samples: the nearest other vehicle, the leader of a pair
MODEL_INPUTS = ("dp", "v_a", "v_b", "R_a")  # what every model takes, in the order of its call


def _check_filter(window: int, polyorder: int) -> None:
    if int(window) != window or window < 3 or window % 2 != 1:
        raise ConfigError(f"window: expected an odd integer >= 3 (samples), got {window!r}")
    if int(polyorder) != polyorder or not 2 <= polyorder < window:
        raise ConfigError(f"polyorder: expected an integer in [2, window - 1] = [2, {window - 1}], got {polyorder!r}")


def sample_period(t: np.ndarray, rtol: float = 1e-3) -> float:
    """The uniform sample period of times t (T,) in s; ValueError if the spacing is not uniform."""
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1 or t.size < 2:
        raise ConfigError(f"t: expected a 1-D array of at least 2 times, got shape {t.shape}")
    d = np.diff(t)
    dt = float(np.median(d))
    if not dt > 0 or np.max(np.abs(d - dt)) > rtol * dt:
        raise ConfigError(f"t: samples must be uniformly spaced (median step {dt:.6g} s, worst {d.min():.6g}..{d.max():.6g} s)")
    return dt


def follower_acceleration(
    t: np.ndarray, mocap_pos: np.ndarray, window: int = DEFAULT_WINDOW, polyorder: int = DEFAULT_POLYORDER
) -> np.ndarray:
    """Acceleration (T, ..., 3) m/s^2 from positions (T, ..., 3) m sampled at times t (T,) s.

    Savitzky-Golay second derivative (``scipy.signal.savgol_filter(deriv=2,
    delta=dt, mode='interp')``): exact for polynomials of degree <= polyorder,
    zero phase. The default window 19 / polyorder 4 (0.38 s at 50 Hz) amplifies
    0.5 mm position noise to 0.077 m/s^2 and under-reads the peak of a 0.1 s wide
    force pulse by 3 % (see the table in this module). The first and last
    ``window // 2`` rows come from a one-sided fit and are less reliable (and, made by
    LAPACK, may differ in their last bits per CPU); the rows between, which the labels use,
    convolve the positions with `second_derivative_coeffs`, the same bits on every CPU.
    """
    _check_filter(window, polyorder)
    mocap_pos = np.asarray(mocap_pos, dtype=np.float64)
    if mocap_pos.shape[0] != np.shape(t)[0] or mocap_pos.shape[-1] != 3:
        raise ConfigError(f"mocap_pos: expected shape ({np.shape(t)[0]}, ..., 3), got {mocap_pos.shape}")
    if mocap_pos.shape[0] < window:
        raise ConfigError(f"mocap_pos: {mocap_pos.shape[0]} samples is shorter than the filter window {window}")
    dt = sample_period(t)
    acc = convolve1d(mocap_pos, second_derivative_coeffs(window, polyorder), axis=0, mode="constant") / dt**2
    # the ends: the one-sided fits of mode "interp", which use the first and last `window` samples only
    h = window // 2
    fit = dict(window_length=window, polyorder=polyorder, deriv=2, delta=dt, axis=0, mode="interp")
    acc[:h] = savgol_filter(mocap_pos[:window], **fit)[:h]
    acc[-h:] = savgol_filter(mocap_pos[-window:], **fit)[-h:]
    return acc


def second_derivative_coeffs(window: int = DEFAULT_WINDOW, polyorder: int = DEFAULT_POLYORDER) -> np.ndarray:
    """The Savitzky-Golay second-derivative coefficients (window,) for dt = 1, in convolution order
    (what ``scipy.signal.savgol_coeffs(deriv=2, use="conv")`` gives, to float64 round-off), solved
    in exact rational arithmetic: scipy solves them with LAPACK, whose kernels differ per CPU in
    their last bits, and these coefficients make every label, so the labels and what is trained
    on them have the same bits on every CPU."""
    _check_filter(window, polyorder)
    return np.array(_exact_second_derivative(int(window), int(polyorder)))


@functools.lru_cache(maxsize=None)
def _exact_second_derivative(window: int, polyorder: int) -> tuple[float, ...]:
    """The least-squares polynomial of degree `polyorder` through samples at -h..h (h = window // 2)
    has second derivative at 0 ``sum_i c_i x_i`` with ``c_i = 2 sum_k (M^-1)[2, k] i^k``, M the normal
    equations' matrix ``M[j][k] = sum_i i^(j + k)``; each c_i is rational, then rounded once to float64."""
    h, n = window // 2, polyorder + 1
    points = range(-h, h + 1)
    # Gauss-Jordan on [M | I] in fractions: row 2 of M^-1 (M is symmetric positive definite: no pivoting needed)
    rows = [[Fraction(sum(i ** (j + k) for i in points)) for k in range(n)] + [Fraction(int(j == k)) for k in range(n)]
            for j in range(n)]
    for j in range(n):
        pivot = rows[j][j]
        rows[j] = [x / pivot for x in rows[j]]
        for r in range(n):
            if r != j and rows[r][j] != 0:
                factor = rows[r][j]
                rows[r] = [a - factor * b for a, b in zip(rows[r], rows[j])]
    inverse_row = rows[2][n:]
    c = [2 * sum(inverse_row[k] * Fraction(i) ** k for k in range(n)) for i in points]
    return tuple(float(x) for x in reversed(c))  # convolution order (symmetric for the second derivative)


def command_kernel(window: int = DEFAULT_WINDOW, polyorder: int = DEFAULT_POLYORDER) -> np.ndarray:
    """The smoothing kernel K (window - 2,) that the second-derivative filter applies to x''.

    Savitzky-Golay second-derivative coefficients ``c`` (for dt = 1) factor as
    ``c = [1, -2, 1] * K`` (convolution); K is symmetric and sums to 1.
    """
    c = second_derivative_coeffs(window, polyorder)
    K, rem = np.polydiv(c, [1.0, -2.0, 1.0])
    if np.max(np.abs(rem)) > 1e-8 or abs(K.sum() - 1.0) > 1e-8:  # pragma: no cover - a property of savgol
        raise RuntimeError("Savitzky-Golay coefficients did not factor through the second difference")
    return K


def smooth_command(u: np.ndarray, window: int = DEFAULT_WINDOW, polyorder: int = DEFAULT_POLYORDER) -> np.ndarray:
    """The command u (T, ..., 3) smoothed by `command_kernel` along time (same units).

    Rows within ``window // 2`` of either end use a clamped edge and are dropped by
    `labels_from_log`.
    """
    return convolve1d(np.asarray(u, dtype=np.float64), command_kernel(window, polyorder), axis=0, mode="nearest")


def _empty(K: int) -> dict[str, np.ndarray]:
    out = {}
    for name, (shape, _) in SAMPLE_SCHEMA.items():
        dtype = bool if name == "mask" else np.int64 if name in ("neighbour", "vehicle", "row") else np.float64
        out[name] = np.zeros((0, *(K if d == "K" else d for d in shape)), dtype=dtype)
    return out


def log_targets(log: FlightLog, targets: Sequence[int] | str | None = None) -> list[int]:
    """The vehicles labelled in a log: ``None`` every vehicle but the leader (``log.meta['leader']``;
    the pair's follower), ``"all"`` every vehicle, or a sequence of distinct vehicle indices."""
    V = log.n_vehicles
    if targets is None:
        leader = int(log.meta.get("leader", -1))
        return [v for v in range(V) if v != leader]
    if isinstance(targets, str):
        if targets != "all":
            raise ConfigError(f"targets: expected None (every vehicle but the leader), 'all' or vehicle indices, got {targets!r}")
        return list(range(V))
    out = [int(v) for v in targets]
    if not out or any(not 0 <= v < V for v in out) or len(set(out)) != len(out):
        raise ConfigError(f"targets: expected distinct vehicle indices in [0, {V - 1}], got {list(targets)}")
    return out


def log_kinds(log: FlightLog) -> list[str]:
    """Each vehicle's kind in a log (``meta['kinds']``; a simulated log without it flew paper quads only,
    a real flight without it is a ConfigError)."""
    V = log.n_vehicles
    if log.real and not log.meta.get("kinds"):  # a lab's vehicles are not paper quads unless it says so
        raise ConfigError(f"{log.meta['source'].get('file', 'a real flight')}: names no registered vehicle kinds "
                          f"(meta 'kinds'; its frames: {log.meta.get('frames')}), so models of kinds cannot read it")
    kinds = list(log.meta.get("kinds") or [DEFAULT_VEHICLE] * V)
    if len(kinds) != V:
        raise ConfigError(f"log meta 'kinds': expected {V} vehicle kinds, got {kinds}")
    return kinds


def past_positions(t: np.ndarray, pos: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(H, R, V, 3): the positions pos (T, V, 3) at times t (T,) (uniform) each lag of
    `downwash.features.HISTORY_LAGS` before the given rows, linear between samples, the first
    sample before the flight's start: what the loop's history holds (`downwash.predictor`)."""
    dt = sample_period(t)
    at = np.maximum((t[rows][None, :] - t[0] - np.asarray(HISTORY_LAGS)[:, None]) / dt, 0.0)  # (H, R) in samples
    i0 = np.minimum(np.floor(at).astype(np.int64), len(t) - 1)
    i1 = np.minimum(i0 + 1, len(t) - 1)
    frac = (at - i0)[..., None, None]
    return (1.0 - frac) * pos[i0] + frac * pos[i1]


def labels_from_log(
    log: FlightLog,
    neighbours: NeighbourSet = PAIR,
    window: int = DEFAULT_WINDOW,
    polyorder: int = DEFAULT_POLYORDER,
    fail_margin_s: float = FAIL_MARGIN_S,
    source: str | os.PathLike | None = None,
    targets: Sequence[int] | str | None = None,
) -> dict[str, np.ndarray]:
    """Model inputs and labels of the target vehicles of one flight, each with its neighbour set.

    neighbours: which vehicles each sample holds (`sim.neighbours.NeighbourSet`); the default
      `PAIR` holds the nearest other vehicle, the leader of a two-vehicle flight.
    targets: the labelled vehicles (`log_targets`; default every vehicle but the leader).
    Returns the arrays of `SAMPLE_SCHEMA` for N = (targets) x (kept rows), target-major
    (each target's samples in time order):

      dp, v_a (N, K, 3)  p_target - p_neighbour and the neighbour's velocity (estimates)
      v_b (N, 3)         the target's velocity (estimate)
      R_a (N, K, 3, 3)   the neighbour's body-to-world rotation (motion-capture quat_est)
      mask, neighbour (N, K), vehicle (N,)   real slots and vehicle indices in the log
      kind_a (N, K, D), kind_b (N, D)        the neighbour's and target's kinds (`log_kinds`,
                                             as `downwash.features.kind_descriptors`)
      hist (N, K, H, 3)  the neighbour's displacement over each lag (`past_positions`)
      y (N, 3) m/s^2     label f = a - u on the target (module doc), world frame
      t, row (N,)        the tick time and row index in the log
      field_mean, field_applied (N, 3) m/s^2   the true field on the target (NaN in a real flight)

    Dropped: the first and last ``window // 2`` rows (filter edges); for a flight that
    ended early (status != 0) the last ``fail_margin_s`` seconds too (contact or
    divergence forces that no downwash model explains); every row from the first
    non-finite value on, on any vehicle (`finite_rows`). Too short a flight gives N = 0.
    """
    _check_filter(window, polyorder)
    if not isinstance(neighbours, NeighbourSet):
        raise ConfigError(f"neighbours: expected a NeighbourSet, got {type(neighbours).__name__}")
    arr = log.arrays
    try:
        targets = log_targets(log, targets)
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}" if source is not None else str(e)) from None
    T, K = len(arr["t"]), neighbours.max_neighbours
    if T < 2:
        return _empty(K)
    dt = sample_period(arr["t"])
    end = T
    if log.meta.get("status", 0) != 0:
        end -= int(round(fail_margin_s / dt))
    end = min(end, finite_rows(arr))
    if end < window:
        return _empty(K)
    h = window // 2
    rows = np.arange(h, end - h)
    pos, vel = arr["pos_est"][rows], arr["vel_est"][rows]
    rot = quat_to_mat(arr["quat_est"][rows].astype(np.float64))
    index, mask = select_neighbours(pos, neighbours)  # (R, V, K)
    inputs = gather_neighbours(pos, vel, rot, index, mask)
    # a real flight whose vehicles are no registered kinds: NaN kinds (only models of kinds read them)
    unregistered = log.real and not log.meta.get("kinds")
    kinds = np.full((log.n_vehicles, len(KIND_FEATURES)), np.nan) if unregistered else kind_descriptors(log_kinds(log))
    kind_a = neighbour_kinds(kinds, index, mask)  # (R, V, K, D)
    hist = neighbour_history(pos, past_positions(arr["t"], arr["pos_est"], rows), index, mask)  # (R, V, K, H, 3)
    parts = []
    for v in targets:  # one vehicle at a time: each target's filter runs over its own column
        acc = follower_acceleration(arr["t"][:end], arr["mocap_pos"][:end, v], window, polyorder)
        u = smooth_command(arr["u_cmd"][:end, v], window, polyorder)
        parts.append({
            "dp": inputs["dp"][:, v], "v_a": inputs["v_a"][:, v], "v_b": inputs["v_b"][:, v].astype(np.float64),
            "R_a": inputs["R_a"][:, v], "mask": mask[:, v], "neighbour": index[:, v],
            "kind_a": kind_a[:, v], "kind_b": np.broadcast_to(kinds[v], (rows.size, kinds.shape[1])),
            "hist": hist[:, v],
            "vehicle": np.full(rows.size, v, dtype=np.int64), "y": acc[rows] - u[rows],
            "t": arr["t"][rows].astype(np.float64), "row": rows.astype(np.int64),
            "field_mean": _truth(arr, "field_mean", rows, v), "field_applied": _truth(arr, "field_applied", rows, v),
        })  # fmt: skip
    return {name: np.concatenate([p[name] for p in parts]) for name in SAMPLE_SCHEMA}


def _truth(arr: dict[str, np.ndarray], name: str, rows: np.ndarray, v: int) -> np.ndarray:
    """A truth array's rows of vehicle v, float64; NaN where the log has none (a real flight)."""
    if name not in arr:
        return np.full((rows.size, 3), np.nan)
    return arr[name][rows, v].astype(np.float64)


def label_noise_floor(
    logs: Iterable[FlightLog | str | os.PathLike],
    window: int = DEFAULT_WINDOW,
    polyorder: int = DEFAULT_POLYORDER,
) -> dict[str, float | list[float] | int]:
    """RMSE of the labels against the logged true field: the floor a perfect model reaches.

    Returns (m/s^2) ``rmse`` and ``rmse_axis`` (x, y, z) against ``field_applied``
    (mean + turbulence, what acted on the vehicle), ``rmse_mean`` and
    ``rmse_axis_mean`` against ``field_mean`` (what a model can predict), and
    ``n_samples``. RMSE over all three axes is ``sqrt(mean over samples and axes)``.
    """
    errs_applied, errs_mean = [], []
    for item in logs:
        log, source = (item, None) if isinstance(item, FlightLog) else (load_log(item), item)
        if log.real:
            raise ConfigError(f"label_noise_floor: {source or 'a log'} is a real flight: it has no true field to "
                              "compare the labels with")
        lab = labels_from_log(log, window=window, polyorder=polyorder, source=source)
        errs_applied.append(lab["y"] - lab["field_applied"])
        errs_mean.append(lab["y"] - lab["field_mean"])
    if not errs_applied or sum(len(e) for e in errs_applied) == 0:
        raise ConfigError("label_noise_floor: no labelled samples in the given logs")
    ea, em = np.concatenate(errs_applied), np.concatenate(errs_mean)
    return {
        "rmse": float(np.sqrt(np.mean(ea**2))),
        "rmse_axis": np.sqrt(np.mean(ea**2, axis=0)).tolist(),
        "rmse_mean": float(np.sqrt(np.mean(em**2))),
        "rmse_axis_mean": np.sqrt(np.mean(em**2, axis=0)).tolist(),
        "n_samples": int(len(ea)),
    }


LABEL_ARRAYS = ("mocap_pos", "u_cmd", "pos_est", "vel_est", "quat_est")  # the log arrays labels and inputs use


def finite_rows(arr: dict[str, np.ndarray]) -> int:
    """How many leading rows of a log are finite in every array labels are made from
    (`LABEL_ARRAYS`), over ALL vehicles: a flight is cut at its first non-finite value, whichever
    vehicle it is on. One rule for the pair's labels and the swarm's (they had diverged)."""
    T = len(arr["t"])
    bad = np.zeros(T, dtype=bool)
    for name in LABEL_ARRAYS:
        bad |= ~np.isfinite(arr[name].reshape(T, -1)).all(axis=1)
    return int(np.argmax(bad)) if bad.any() else T
