"""Fly a batch of worlds to the end and collect one `FlightLog` per world."""

from __future__ import annotations

import logging
from typing import Any, Callable, Sequence

import numpy as np

from sim.logs import ARRAY_SPECS, STATUS_CODES, FlightLog
from sim.predictor import Predictor
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
    config: SimConfig | None = None,
    field: Any | None = None,
    predictor: Predictor | None = None,
    field_enabled: np.ndarray | None = None,
    meta: Sequence[dict] | dict | None = None,
    n_threads: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> list[FlightLog]:
    """Fly W = len(seeds) worlds for `duration` seconds; returns their logs.

    meta: extra metadata per world (a list) or shared (a dict), merged into each log.
    A world that diverges or collides ends early with its status and message in the
    log's metadata; the others fly on.
    """
    if not duration > 0:
        raise ValueError(f"duration: must be > 0 s, got {duration}")
    sim = Simulator(
        scene, reference, seeds, config=config, field=field, predictor=predictor,
        field_enabled=field_enabled, n_threads=n_threads,
    )
    W = sim.W
    n_ticks = int(round(duration / sim.cfg.rates.control_dt))
    buffers: dict[str, np.ndarray] = {}
    for k in range(n_ticks):
        active = sim.active.copy()
        if not active.any():
            break
        row = sim.tick()
        if not buffers:
            buffers = {name: np.zeros((W, n_ticks) + np.shape(v)[1:]) for name, v in row.items()}
        for name, v in row.items():
            buffers[name][active, k] = v[active]
        if progress is not None:
            progress(k + 1, n_ticks)

    if isinstance(meta, dict) or meta is None:
        meta = [dict(meta or {}) for _ in range(W)]
    if len(meta) != W:
        raise ValueError(f"meta: expected {W} entries (one per world), got {len(meta)}")
    logs = []
    for w in range(W):
        n = int(sim.tick_index[w])
        arrays = {name: buffers[name][w, :n].copy() for name in ARRAY_SPECS}
        info = {
            "seed": sim.seeds[w],
            "config": sim.cfg.to_dict(),
            "vehicles": list(scene.vehicles),
            "leader": 0,
            "follower": 1,
            "field": _describe(sim.field),
            "field_enabled": bool(sim.field_enabled[w]),
            "predictor": _describe(predictor),
            "duration": duration,
            "status": int(sim.status[w]),
            "status_name": STATUS_CODES[int(sim.status[w])],
            "message": sim.message[w],
        }
        info.update(meta[w])
        if info["status"] != 0:
            log.warning("%s", info["message"])
        logs.append(FlightLog(arrays, info))
    return logs


def _describe(obj: Any) -> Any:
    if obj is None:
        return None
    if hasattr(obj, "describe"):
        return obj.describe()
    try:
        from dataclasses import asdict, is_dataclass

        if is_dataclass(obj):
            return {"type": type(obj).__name__, **asdict(obj)}
    except TypeError:
        pass
    return {"type": type(obj).__name__}
