"""Fly a batch of worlds to the end and collect one `FlightLog` per world."""

from __future__ import annotations

import logging
from typing import Any, Callable, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.provenance import code_version, describe
from downwash_core.status import Status
from downwash_core.vehicles import DEFAULT_VEHICLE
from sim.aggregation import LinearSuperposition
from sim.logs import ARRAY_SPECS, OPTIONAL_SPECS, FlightLog
from sim.rows import Row
from sim.scene import Scene
from sim.simulator import SimConfig, Simulator

__all__ = ["fly"]

log = logging.getLogger(__name__)


def fly(
    scene: Scene,
    reference: Callable,
    seeds: Sequence[int],
    duration: float,
    *,
    meta: Sequence[dict] | dict | None = None,
    progress: Callable[[int, int], None] | None = None,
    **components: Any,
) -> list[FlightLog]:
    """Fly W = len(seeds) worlds for `duration` seconds; returns their logs.

    components: the `Simulator` keywords (config, controller, autopilot, turbulence,
      field, predictor, field_enabled, n_threads, wind, aggregation, fast, safety).
    meta: extra metadata per world (a list) or shared (a dict), merged into each log.
    progress: called as progress(ticks done, ticks in all) after each controller tick.
    A world that diverges or collides ends early with its status and message in the
    log's metadata; the others fly on.
    With a wind (`wind=sim.wind.DrydenWind(...)`, not off) the logs also hold "wind" (the
    air velocity at each vehicle, (T, V, 3) m/s) and "wind_acc" (its drag, m/s^2), and
    the metadata its `describe()` under "wind". With a safety filter (`safety=sim.safety.SafetyConfig(...)`)
    the metadata holds its `describe()` under "safety". A scene of other vehicle kinds than the paper
    quad names each vehicle's kind under "kinds" (and describes each in full under "scene").
    """
    if not duration > 0:
        raise ConfigError(f"duration: must be > 0 s, got {duration}")
    config = components.get("config")
    control_dt = (config if config is not None else SimConfig()).rates.control_dt
    if round(duration / control_dt) < 1:
        raise ConfigError(f"duration: {duration} s is shorter than one controller period ({control_dt} s)")
    sim = Simulator(scene, reference, seeds, **components)
    W = sim.W
    n_ticks = int(round(duration / sim.cfg.rates.control_dt))
    # The simulator's rows are fresh arrays it never writes again, so they are kept as
    # they come and stacked once at the end (copying 15 fields per tick cost more than
    # the tick's own bookkeeping). A world's rows are those of its first tick_index
    # ticks: once a world ends it stays ended, so the later rows are cut off below.
    rows: list[dict[str, np.ndarray]] = []
    for k in range(n_ticks):
        if not sim.active.any():
            break
        rows.append(sim.tick())
        if progress is not None:
            progress(k + 1, n_ticks)
    names = list(ARRAY_SPECS) + [name for name in OPTIONAL_SPECS if rows and name in rows[0]]
    stacked = _stack_rows(rows, names, W, sim.V)  # (W, T, ...)

    if isinstance(meta, dict) or meta is None:
        meta = [dict(meta or {}) for _ in range(W)]
    if len(meta) != W:
        raise ConfigError(f"meta: expected {W} entries (one per world), got {len(meta)}")
    kind_names = list(sim.vehicle_params.names)  # each vehicle's kind, named in the meta unless all the paper quad
    kinds = {"kinds": kind_names} if any(n != DEFAULT_VEHICLE for n in kind_names) else {}
    logs = []
    for w in range(W):
        n = int(sim.tick_index[w])
        arrays = {name: stacked[name][w, :n].copy() for name in names}
        info = {
            "seed": sim.seeds[w],
            "config": sim.cfg.to_dict(),
            "vehicles": list(scene.vehicles),
            "roles": [r.value for r in scene.roles],
            "leader": scene.leader,
            "follower": scene.follower,
            "scene": scene.describe(),  # with each vehicle's kind in full unless all are the paper quad
            **kinds,
            "controller": describe(sim.controller),
            "autopilot": describe(sim.autopilot),
            "turbulence": describe(sim.turbulence),
            "field": describe(sim.field),
            # how the wakes combined (None: linear); with two vehicles every law is the pairwise field
            "aggregation": describe(sim.aggregation if sim.aggregation is not None else LinearSuperposition()),
            "field_enabled": bool(sim.field_enabled[w]),
            **({"wind": describe(sim.wind)} if sim.wind is not None else {}),
            **({"safety": describe(sim.safety)} if sim.safety is not None else {}),  # the CBF filter's settings
            "predictor": _predictor_name(components.get("predictor")),
            "code": code_version(),
            "duration": duration,
            "status": int(sim.status[w]),
            "status_name": Status(int(sim.status[w])).label,
            "message": sim.message[w],
        }
        info.update(meta[w])
        if info["status"] != Status.OK:
            log.warning("%s", info["message"])
        logs.append(FlightLog(arrays, info))
    return logs


def _stack_rows(rows: list, names: list[str], W: int, V: int) -> dict[str, np.ndarray]:
    """{name: (W, T, ...) float64} from T rows; the fused path's `Row`s (views of one flat array
    each, all with one layout) are stacked once and sliced, any other rows name by name."""
    if rows and all(type(row) is Row for row in rows) and all(row.layout is rows[0].layout for row in rows):
        flat = np.stack([row.flat for row in rows])  # (T, size)
        out = {}
        for name in names:
            offset, shape = rows[0].layout[name]
            block = flat[:, offset:offset + int(np.prod(shape))].reshape((len(rows),) + shape)
            out[name] = np.moveaxis(block, 0, 1)
        return out
    if not rows:
        return {name: np.zeros((W, 0) + _trailing(name, V)) for name in names}
    return {name: np.stack([row[name] for row in rows], axis=1).astype(np.float64, copy=False) for name in names}


def _trailing(name: str, V: int) -> tuple[int, ...]:
    trail = {**ARRAY_SPECS, **OPTIONAL_SPECS}[name][0]
    return tuple(V if d == "V" else d for d in trail)


def _predictor_name(predictor: Any) -> str | None:
    """The predictor's class (a learned model's provenance travels with its checkpoint, named in `meta`)."""
    return None if predictor is None else type(predictor).__name__
