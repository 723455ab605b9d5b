"""Real flights flown again in the simulator: tracking side by side, and a real-trained model in the loop.

`replay_in_sim` flies a real flight's logged setpoints (``ref_pos``, ``ref_vel``; the setpoint's
acceleration is not logged, so the feed-forward is the central differences of ``ref_vel``) in the
simulator, each vehicle of its own registered kind (``meta["kinds"]``) and starting where the real
one was at the first logged tick (the reference's first sample is the logged state: the simulator
starts each vehicle at its reference's t = 0 state; from the next logged sample on it is the
recorded setpoint). `tracking_summary` reads real and simulated logs with one code path: the
error is ``pos_est - ref_pos`` (the real log has no truth; the simulated estimate follows the simulated
truth to about a millimetre: 0.7 mm RMS on a replayed swap). `compare_tracking` puts them side by side
per flight and pooled by interaction; `fly_real_model` flies held-out flights' setpoints with no
model, the field's oracle and a model trained on real flights.

What differs, measured rather than hidden (`DIFFERENCES`, stored with every result):

- the real vehicles flew the Crazyflie firmware's Mellinger controller onboard with the lab's gains;
  the simulator flies this project's feedback-linearised LQR (`controllers.lqr`, weights of the
  paper's Freyja LQG) at 50 Hz over its attitude autopilot. A tracking error that differs between
  real and simulated flights mixes the field's error with the controllers'. The firmware's default
  Mellinger gains (kp_z 1.25 N/m for 0.032 kg: 39 s^-2) are about 12 times stiffer in height than the
  default LQR's (sqrt(8 / 0.8) = 3.2 s^-2), so a wake sags a simulated vehicle far more: give
  `controller` (any `sim.flight.fly` controller) to compare like with like;
- the simulated vehicles are the registry's ``crazyflie_2_1`` and ``crazyflie_large`` (mass,
  inertia, rotor limits), with a level hover at the first logged position and velocity;
- the simulated wake is ``field`` (a registered law or a fitted one), not the air; ground effect,
  battery sag and the real estimator are not simulated.

"Under another" (`under_another`): another vehicle's SETPOINT is above the vehicle's setpoint within
`downwash.real_logs.flights.WAKE_RADIUS` laterally and `WAKE_DEPTH` vertically (the data set's own
typing, on the setpoints): real and simulated logs of one flight are pooled over the same instants.
A simulated world that ends early (collision, divergence) is reported with its status and how long
it flew; its statistics cover the rows it flew, and `fly_real_model` also gives the RMS with the ticks
it did not fly at `sim.metrics`' crash penalty.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from torch import nn

from downwash_core.errors import ConfigError
from downwash_core.provenance import describe
from downwash_core.status import Status
from downwash_core.vehicles import DEFAULT_VEHICLE
from downwash.checkpoint import read_metadata, save_checkpoint
from downwash.conditions import fly_conditions
from downwash.real_logs.flights import WAKE_DEPTH, WAKE_RADIUS
from downwash_trajectories import Recorded, StackedReference, stack
from sim.fields.registry import resolve_field_spec
from sim.flight import fly
from sim.logs import FlightLog
from sim.metrics import CRASH_PENALTY, planned_ticks
from sim.scene import Scene, build_scene

__all__ = ["DIFFERENCES", "CRAZYFLIE_PD", "crazyflie_stiff_lqr", "flight_reference", "replay_in_sim", "under_another", "tracking_summary", "error_stats",
           "compare_tracking", "fly_real_model"]

# The Crazyflie firmware's Mellinger controller's default position gains (bitcraze/crazyflie-firmware,
# src/modules/src/controller/controller_mellinger.c: kp_xy 0.4, kd_xy 0.2, kp_z 1.25, kd_z 0.4, in N per m
# and per m/s, for its 0.032 kg vehicle; the Neural-Swarm flights flew these, without the integral terms)
# as the accelerations of a PD law: s^-2, s^-1 per axis.
CRAZYFLIE_PD = {"kp": (0.4 / 0.032, 0.4 / 0.032, 1.25 / 0.032), "kd": (0.2 / 0.032, 0.2 / 0.032, 0.4 / 0.032)}


def crazyflie_stiff_lqr() -> Any:
    """The project's LQR with the weights whose gain is the Crazyflie firmware's default position PD
    (`CRAZYFLIE_PD`; `controllers.lqr.LQRConfig.from_pd`): as stiff as the real vehicles flew, without
    Mellinger's attitude loop or integral terms."""
    from controllers.lqr import FeedbackLinearisedLQR, LQRConfig

    return FeedbackLinearisedLQR(LQRConfig.from_pd(CRAZYFLIE_PD["kp"], CRAZYFLIE_PD["kd"]))


DIFFERENCES = (
    "real: the Crazyflie firmware's Mellinger controller with the lab's gains, onboard at 500 Hz; simulated: this "
    "project's feedback-linearised LQR (Freyja LQG weights) at 50 Hz over its autopilot, the registry's vehicle kinds, "
    "the given field as the only wake (no ground effect, battery sag or real estimator); the acceleration feed-forward "
    "is the central differences of the logged setpoint velocity (the real one is not logged); errors are "
    "pos_est - ref_pos in both; 'under' is by the setpoints (WAKE_RADIUS, WAKE_DEPTH of downwash.real_logs.flights)"
)


def _field(field: Any) -> Any:
    """A field object from an object or a spec string (`sim.fields.registry`, e.g. "so2", "fitted:PATH")."""
    return resolve_field_spec(field) if isinstance(field, str) else field


def _kinds(flight: FlightLog) -> list[str]:
    """Each vehicle's registered kind: the meta's ``kinds`` (a real flight's), else the paper quad."""
    kinds = flight.meta.get("kinds") or [DEFAULT_VEHICLE] * flight.n_vehicles
    if len(kinds) != flight.n_vehicles:
        raise ConfigError(f"flight: meta 'kinds' names {len(kinds)} vehicles, the log holds {flight.n_vehicles}")
    return list(kinds)


def _name(flight: FlightLog, default: str = "flight") -> str:
    """The flight's name: its meta's ``name``, else its source files, else `default`."""
    source = flight.meta.get("source") or {}
    files = source.get("files") if isinstance(source, dict) else None
    return flight.meta.get("name") or (",".join(str(f.get("file")) for f in files) if files else default)


def flight_reference(flight: FlightLog, n_worlds: int = 1, start_at_log: bool = True) -> StackedReference:
    """The flight's setpoints as a stacked `Recorded` (one per vehicle) over `n_worlds` worlds, on the
    simulator's clock (t - t[0]); with `start_at_log` the first sample is the logged state (pos_est,
    vel_est), so that the simulator starts each vehicle where the real one was."""
    t = flight["t"] - flight["t"][0]
    refs = []
    for v in range(flight.n_vehicles):
        pos, vel = flight["ref_pos"][:, v].copy(), flight["ref_vel"][:, v].copy()
        acc = np.gradient(vel, t, axis=0)  # of the setpoints, before the start is replaced
        if start_at_log:
            pos[0], vel[0] = flight["pos_est"][0, v], flight["vel_est"][0, v]
        refs.append(Recorded(t, pos, vel, acc, n_worlds=n_worlds))
    return stack(refs)


def _duration(flight: FlightLog, duration: float | None) -> float:
    """s to fly: the whole flight by default; ConfigError beyond it."""
    length = float(flight["t"][-1] - flight["t"][0])
    if duration is None:
        return length
    if not 0.0 < duration <= length + 1e-9:
        raise ConfigError(f"duration: allowed (0, {length:.3f}] s, the flight's length; got {duration!r}")
    return float(duration)


def _scene(flight: FlightLog) -> Scene:
    """A scene of the flight's vehicles (its names), each of its kind."""
    names = flight.meta.get("vehicles") or [f"v{i}" for i in range(flight.n_vehicles)]
    return build_scene([str(n) for n in names], kinds=_kinds(flight))


def replay_in_sim(flight: FlightLog, field: Any, *, predictor: Any = None, seeds: Sequence[int] = (0,),
                  duration: float | None = None, controller: Any = None, **components: Any) -> list[FlightLog]:
    """Fly `flight`'s setpoints in the simulator against `field` (an object or a spec string), one world
    per seed, each vehicle of its kind and starting at its first logged position (module doc); returns
    the simulated logs. duration: s from the flight's start (default all of it). predictor, controller
    and further `Simulator` components (config, turbulence, wind, ...) as `sim.flight.fly`'s; the
    controller defaults to the project's LQR (not the Mellinger controller that flew: `DIFFERENCES`)."""
    seeds = list(seeds)
    extra = {k: v for k, v in (("predictor", predictor), ("controller", controller)) if v is not None}
    meta = {"replay_of": {"flight": _name(flight), "source": flight.meta.get("source")}}
    return fly(_scene(flight), flight_reference(flight, len(seeds)), seeds, _duration(flight, duration),
               field=_field(field), meta=meta, **extra, **components)


def under_another(log: FlightLog) -> np.ndarray:
    """(T, V) bool: another vehicle's setpoint is above this one's, within WAKE_RADIUS (m) laterally and
    WAKE_DEPTH (m) vertically (module doc: by the setpoints, so real and simulated logs agree)."""
    return _under(log["ref_pos"])


def _under(ref: np.ndarray) -> np.ndarray:
    """`under_another` of setpoints ref (T, V, 3) m."""
    rel = ref[:, None, :, :] - ref[:, :, None, :]  # (T, target, other, 3): the other from the target
    over = ((np.linalg.norm(rel[..., :2], axis=-1) < WAKE_RADIUS) & (rel[..., 2] > WAKE_DEPTH[0])
            & (rel[..., 2] < WAKE_DEPTH[1]))
    V = ref.shape[1]
    over[:, np.arange(V), np.arange(V)] = False
    return over.any(axis=2)


def _rows(log: FlightLog, duration: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(|p - p_ref| (T, V) m, p_z - p_ref,z (T, V) m, under (T, V) bool) over the rows before `duration`
    s from the log's start (None: all)."""
    keep = slice(None) if duration is None else (log["t"] - log["t"][0]) < duration - 1e-9
    e = (log["pos_est"] - log["ref_pos"])[keep]
    return np.linalg.norm(e, axis=-1), e[..., 2], under_another(log)[keep]


def error_stats(dist: np.ndarray, dz: np.ndarray) -> dict[str, Any]:
    """The distribution of position errors |p - p_ref| (N,) m (rms, median, p95, max) and of the vertical
    error p_z - p_ref,z (N,) m (signed mean; rms, median, p95, max of its magnitude); None without rows."""
    n = int(dist.size)
    if n == 0:
        return {"rows": 0, "pos": None, "z": None}
    az = np.abs(dz)
    return {
        "rows": n,
        "pos": {"rms": float(np.sqrt(np.mean(dist**2))), "median": float(np.median(dist)),
                "p95": float(np.percentile(dist, 95)), "max": float(dist.max())},
        "z": {"mean": float(dz.mean()), "rms": float(np.sqrt(np.mean(dz**2))), "median": float(np.median(az)),
              "p95": float(np.percentile(az, 95)), "max": float(az.max())},
    }


def tracking_summary(log: FlightLog, duration: float | None = None) -> dict[str, Any]:
    """Tracking errors of every vehicle of a real or simulated log, by one code path (module doc):
    per vehicle its name, kind and `error_stats` over all rows, the rows under another and the rows
    alone; with the log's status, how long it covers (s) and whether it ended early. duration: only
    the rows before it (s from the log's start)."""
    dist, dz, under = _rows(log, duration)
    names = log.meta.get("vehicles") or [f"v{i}" for i in range(log.n_vehicles)]
    vehicles = []
    for v, (name, kind) in enumerate(zip(names, _kinds(log))):
        u = under[:, v]
        vehicles.append({"vehicle": str(name), "kind": kind, "all": error_stats(dist[:, v], dz[:, v]),
                         "under": error_stats(dist[u, v], dz[u, v]), "alone": error_stats(dist[~u, v], dz[~u, v])})
    t = log["t"]
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0
    status = int(log.meta.get("status", Status.OK))
    return {"status": Status(status).label, "ended_early": status != Status.OK, "message": log.meta.get("message", ""),
            "seconds": float(t[-1] - t[0] + dt) if len(t) else 0.0, "vehicles": vehicles}


def _named(flights: Sequence[Any]) -> list[tuple[str, FlightLog]]:
    """(name, log) pairs from logs or (FlightRef, log) pairs (as `read_flights` returns them)."""
    out = []
    for i, item in enumerate(flights):
        ref, flight = item if isinstance(item, tuple) else (None, item)
        if not isinstance(flight, FlightLog):
            raise ConfigError(f"flights[{i}]: expected a FlightLog or a (FlightRef, FlightLog) pair, got "
                              f"{type(flight).__name__}")
        out.append((getattr(ref, "name", None) or _name(flight, f"flight {i}"), flight))
    return out


def _unflown(log: FlightLog, flight: FlightLog, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(|e| (M, V) m, under (M, V)) of the M ticks that a simulated world which ended early did not fly:
    each at max(CRASH_PENALTY["pos"], the vehicle's largest error before), the crash rule of
    `sim.metrics`, and under another by the flight's setpoints at those ticks' times."""
    rates = log.meta["config"]["rates"]
    dt = float(rates["physics_dt"] * rates["physics_per_autopilot"] * rates["autopilot_per_control"])
    t = np.arange(len(log), planned_ticks(log)) * dt  # s on the simulator's clock
    grid = flight["t"] - flight["t"][0]
    ref = np.stack([np.stack([np.interp(t, grid, flight["ref_pos"][:, v, k]) for k in range(3)], axis=-1)
                    for v in range(flight.n_vehicles)], axis=1)  # (M, V, 3): what Recorded plays there
    worst = np.nan_to_num(dist, nan=np.inf).max(axis=0, initial=0.0)  # (V,) m
    return np.broadcast_to(np.maximum(CRASH_PENALTY["pos"], worst), (t.size, flight.n_vehicles)), _under(ref)


class _Pool:
    """Per-row errors gathered by key ("under", "alone", "<kind>/under", ...) to pool over flights; given
    the real flight, also the position errors with the ticks a crashed world did not fly (`_unflown`)."""

    def __init__(self) -> None:
        self.parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        self.penalised: dict[str, list[np.ndarray]] = {}

    def add(self, log: FlightLog, duration: float | None, flight: FlightLog | None = None) -> None:
        dist, dz, under = _rows(log, duration)
        extra = _unflown(log, flight, dist) if flight is not None and not log.ok else None
        for v, kind in enumerate(_kinds(log)):
            for where, flip in (("under", False), ("alone", True)):
                mask = under[:, v] ^ flip
                for key in (where, f"{kind}/{where}"):
                    self.parts.setdefault(key, []).append((dist[mask, v], dz[mask, v]))
                    if flight is not None:
                        more = () if extra is None else (extra[0][extra[1][:, v] ^ flip, v],)
                        self.penalised.setdefault(key, []).extend((dist[mask, v], *more))

    def stats(self) -> dict[str, Any]:
        return {k: error_stats(np.concatenate([d for d, _ in p]), np.concatenate([z for _, z in p]))
                for k, p in sorted(self.parts.items())}

    def penalised_rms(self) -> dict[str, float | None]:
        """{key: position RMS (m) with the unflown ticks at the crash penalty}; None without rows."""
        out = {}
        for k, parts in sorted(self.penalised.items()):
            d = np.concatenate(parts)
            out[k] = float(np.sqrt(np.mean(d**2))) if d.size else None
        return out


def _ended(name: str, seed: int, errors: dict[str, Any], condition: str | None = None) -> dict[str, Any]:
    """The record of a simulated world that ended early, from its `tracking_summary`."""
    out = {"flight": name, "seed": seed, "status": errors["status"], "message": errors["message"],
           "seconds": errors["seconds"]}
    return out if condition is None else {"condition": condition, **out}


def compare_tracking(real_flights: Sequence[Any], field: Any, *, predictor: Any = None, seeds: Sequence[int] = (0,),
                     duration: float | None = None, controller: Any = None, **components: Any) -> dict[str, Any]:
    """Real against simulated tracking, per flight and pooled: each real flight (a `FlightLog` or a
    (FlightRef, FlightLog) pair) is replayed (`replay_in_sim`, one world per seed) against `field`, and
    `tracking_summary` of the real log and of every simulated one are given side by side, over the same
    window (the first `duration` s; default each flight's whole length). ``pooled`` holds, for "under"
    and "alone" (and per kind, "<kind>/under"), the distribution over every row of every vehicle of
    every flight (and seed): {"real": ..., "sim": ...}. Worlds that ended early are listed under
    ``ended_early`` (their rows count up to the end). JSON-ready."""
    field = _field(field)
    real_pool, sim_pool, per_flight, ended = _Pool(), _Pool(), [], []
    for name, flight in _named(real_flights):
        window = _duration(flight, duration)
        logs = replay_in_sim(flight, field, predictor=predictor, seeds=seeds, duration=window, controller=controller,
                             **components)
        real_pool.add(flight, window)
        sims = []
        for seed, L in zip(seeds, logs):
            sim_pool.add(L, window)
            errors = tracking_summary(L, window)
            sims.append({"seed": int(seed), **errors})
            if errors["ended_early"]:
                ended.append(_ended(name, int(seed), errors))
        per_flight.append({"flight": name, "kinds": _kinds(flight), "seconds": window,
                           "real": tracking_summary(flight, window), "sim": sims})
    real, sim = real_pool.stats(), sim_pool.stats()
    pooled = {k: {"real": real.get(k), "sim": sim.get(k)} for k in sorted(set(real) | set(sim))}
    return {"field": describe(field), "controller": describe(controller) if controller is not None else "LQR (default)",
            "seeds": [int(s) for s in seeds], "differences": DIFFERENCES, "flights": per_flight, "pooled": pooled,
            "ended_early": ended}


def _checkpoint(model: Any, folder: str) -> tuple[Path, str]:
    """(a checkpoint path, the model's kind) for a path or a trained per-neighbour model; a model is
    written to `folder`, because the conditions load learned models from checkpoint paths only
    (`downwash.conditions.make_predictor`)."""
    if isinstance(model, (str, os.PathLike)):
        return Path(model), read_metadata(model)["model"]["kind"]
    if not isinstance(model, nn.Module):
        raise ConfigError(f"model_or_checkpoint: expected a trained per-neighbour model or a checkpoint path, got "
                          f"{type(model).__name__}")
    path = Path(folder) / "model.pt"
    save_checkpoint(path, model)
    return path, model.kind


def fly_real_model(flights: Sequence[Any], field: Any, model_or_checkpoint: Any, *, seeds: Sequence[int] = (0,),
                   duration: float | None = None, controller: Any = None, **components: Any) -> dict[str, Any]:
    """Held-out real flights' setpoints flown in the simulator against `field` under three conditions of
    `downwash.conditions` on the same seeds: ``baseline`` (no prediction), ``oracle`` (the field's own
    mean force) and the model (a trained per-neighbour model, e.g. ``equivariant`` trained on
    `labelled_samples` of other flights, or its checkpoint path; the condition is ``<kind>-real``). Holding
    the flights out of the model's training is the caller's part.

    Returns per condition the pooled `error_stats` of the rows flown under another and alone
    (``pooled``), the position RMS under another over the rows flown (``under_rms``) and with the
    ticks a crashed world did not fly at `sim.metrics`' crash penalty (``under_rms_penalised``: a
    condition that crashes more does not look better for flying less), the RMS per flight, the worlds
    that ended early, and ``oracle_gain_kept`` of both RMS: (baseline - model) / (baseline - oracle)
    (1: all of the oracle's gain, 0: none; None when the oracle gains nothing). JSON-ready."""
    field = _field(field)
    extra = {"controller": controller} if controller is not None else {}
    pools: dict[str, _Pool] = {}
    per_flight, ended = [], []
    with tempfile.TemporaryDirectory(prefix="real_model_") as folder:
        path, kind = _checkpoint(model_or_checkpoint, folder)
        record = read_metadata(path)
        about = {"kind": kind, "checkpoint": str(path) if isinstance(model_or_checkpoint, (str, os.PathLike)) else None,
                 **{k: record[k] for k in ("model", "data") if k in record}}
        model = f"{kind}-real"  # the kind trained on other data, as the conditions name it (equivariant-real)
        conditions = ["baseline", "oracle", model]
        for name, flight in _named(flights):
            window = _duration(flight, duration)
            reference = flight_reference(flight, len(conditions) * len(seeds))
            logs = fly_conditions(_scene(flight), conditions, reference, list(seeds), window, field, {model: path},
                                  meta={"replay_of": {"flight": name, "source": flight.meta.get("source")}},
                                  **extra, **components)
            per_flight.append(_score(name, flight, window, logs, seeds, pools, ended))
    flown = {c: _rms(pools[c].stats().get("under")) for c in conditions}
    penalised = {c: pools[c].penalised_rms().get("under") for c in conditions}
    return {"field": describe(field), "model": about, "conditions": conditions, "seeds": [int(s) for s in seeds],
            "differences": DIFFERENCES, "pooled": {c: pools[c].stats() for c in conditions}, "under_rms": flown,
            "under_rms_penalised": penalised,
            "oracle_gain_kept": {"flown": _gain(flown, conditions), "penalised": _gain(penalised, conditions)},
            "flights": per_flight, "ended_early": ended}


def _score(name: str, flight: FlightLog, window: float, logs: dict[str, list[FlightLog]], seeds: Sequence[int],
           pools: dict[str, _Pool], ended: list) -> dict[str, Any]:
    """One flight's conditions into the pools (and `ended`); returns its position RMS under another per
    condition, over the rows flown."""
    row: dict[str, Any] = {"flight": name}
    for c, condition_logs in logs.items():
        one = _Pool()
        for seed, L in zip(seeds, condition_logs):
            one.add(L, window)
            pools.setdefault(c, _Pool()).add(L, window, flight)
            errors = tracking_summary(L, window)
            if errors["ended_early"]:
                ended.append(_ended(name, int(seed), errors, c))
        row[c] = _rms(one.stats().get("under"))
    return row


def _gain(rms: dict[str, float | None], conditions: Sequence[str]) -> float | None:
    """(baseline - model) / (baseline - oracle) of `rms`; None without rows or without the oracle's gain."""
    base, oracle, model = (rms[c] for c in conditions)
    return None if None in (base, oracle, model) or base - oracle <= 0 else (base - model) / (base - oracle)


def _rms(stats: dict[str, Any] | None) -> float | None:
    """The position RMS (m) of `error_stats`, None without rows."""
    return None if not stats or stats["pos"] is None else stats["pos"]["rms"]
