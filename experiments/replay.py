"""Replay a flight log in MuJoCo's interactive viewer: the vehicles as logged, the leaders' wakes, the references.

    python -m experiments.replay PATH.npz [--speed 0.5] [--loop]

PATH is a flight log (`sim.logs`, e.g. a collection's ``stage_*/train/flight_000.npz``).
The scene is rebuilt from the log's vehicles and roles (`sim.scene.build_scene`; a log
without them gets a leader and followers), and the window shows what the videos show
(`downwash_envs.video`): leaders orange, followers cyan, each leader's wake (the width of
the logged field; none for a flight without downwash), the moving reference paths in
green with their current points, and the time. Playback is paced to real time times
`--speed`, dropping rows rather than falling behind; it ends with the log (a flight that
ended early stops at its last row) or, with `--loop`, starts again until the window is
closed. Every argument and the log are checked before the window opens; the window needs a
display (see `downwash_envs.viewer`; headless: ``xvfb-run -a python -m experiments.replay ...``,
or an mp4 through an experiment's ``--video``).
"""

from __future__ import annotations

import argparse
import math
from typing import Any, Sequence

from experiments.common import OneLineParser, run_main

__all__ = ["MAX_FPS", "build_parser", "replay_log", "main"]

MAX_FPS = 60.0  # window syncs per second at most: a fast replay skips rows instead


def _speed(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a playback rate > 0 (1 = real time), got {text!r}") from None
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"expected a playback rate > 0 (1 = real time), got {text!r}")
    return x


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(  # one-line usage errors, as every experiment's
        prog="python -m experiments.replay",
        description="Replay a flight log (.npz) in MuJoCo's interactive viewer, the leaders' wakes and the "
                    "reference paths drawn, paced to real time.")
    parser.add_argument("log", metavar="PATH", help="a flight log written by sim.logs.save_log (.npz)")
    parser.add_argument("--speed", type=_speed, default=1.0,
                        help="playback rate: 1 real time, 0.25 four times slower, 4 four times faster (default: 1)")
    parser.add_argument("--loop", action="store_true", help="start again at the end until the window is closed")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an expected error (a bad option or log) instead of one line")
    return parser


def replay_log(log: Any, speed: float = 1.0, loop: bool = False, what: str = "experiments.replay") -> int:
    """Play `log` (a `sim.logs.FlightLog`) in a `downwash_envs.viewer.Viewer` at `speed` times real time,
    once or (`loop`) until the window is closed; returns the number of window syncs. ConfigError,
    before the window opens, for a log the scene cannot show or when there is no display."""
    import time
    from types import SimpleNamespace

    import numpy as np

    from downwash_core.errors import ConfigError
    from downwash_core.params import RATES
    from downwash_envs.video import _PATH_POINTS, CameraView, Trajectory, _check_trajectories, wake_width
    from downwash_envs.viewer import Viewer, check_display
    from sim.scene import build_scene

    speed = float(speed)
    if not (math.isfinite(speed) and speed > 0):
        raise ConfigError(f"speed: expected a playback rate > 0 (1 = real time), got {speed!r}")
    meta = dict(getattr(log, "meta", {}) or {})
    pos = np.asarray(log["pos"], float)
    V = pos.shape[1] if pos.ndim == 3 else 0
    names, roles = meta.get("vehicles"), meta.get("roles")
    try:
        if isinstance(names, list) and isinstance(roles, list) and len(names) == len(roles) == V:
            scene = build_scene(list(zip(names, roles)))
        else:  # a log without the scene's record: the first vehicle leads
            scene = build_scene([f"vehicle{v}" for v in range(V)])
    except ValueError as e:  # ConfigError, DataError, or a role the code does not know
        raise ConfigError(f"log: its vehicles {names} with roles {roles} do not make a scene: {e}") from e
    (tr,) = _check_trajectories(scene, [Trajectory("log", pos, np.asarray(log["quat"], float))])
    t = np.asarray(log["t"], float)[: len(tr.pos)]
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ConfigError("log: its times 't' must be finite and increasing")
    rel = t - t[0]
    ref = np.asarray(log["ref_pos"], float)[: len(tr.pos)]
    ref_ok = np.all(np.isfinite(ref), axis=-1)  # (T, V)
    moving = [v for v in range(V) if ref_ok[:, v].all() and np.ptp(ref[:, v], axis=0).max() > 0.01]
    keep = np.unique(np.linspace(0, len(ref) - 1, min(len(ref), _PATH_POINTS + 1)).round().astype(int))
    paths = [ref[keep, v] for v in moving]
    field = meta.get("field") if isinstance(meta.get("field"), dict) else {}
    wake = wake_width(SimpleNamespace(width0=field.get("width0"), width_slope=field.get("width_slope")))
    draw_wake = bool(meta.get("field_enabled", True))
    dt = float(np.median(np.diff(t))) if len(t) > 1 else RATES.control_dt
    points = np.concatenate([tr.pos.reshape(-1, 3), ref[ref_ok]])

    check_display(what)
    syncs = 0
    with Viewer(scene, wake=wake, what=what) as viewer:
        viewer.set_view(CameraView.framing(points, 4 / 3))
        start, last_row = time.perf_counter(), -1
        while viewer.is_running():
            played = (time.perf_counter() - start) * speed  # s of flight time
            i = min(int(np.searchsorted(rel, played, side="right")) - 1, len(rel) - 1)
            if i != last_row:
                ended = " (ended)" if i == len(rel) - 1 and meta.get("status", 0) != 0 else ""
                ref_now = ref[i, moving] if moving else None
                if not viewer.show(tr.pos[i], tr.quat[i], ref_now, paths, draw_wake,
                                   f"t = {rel[i]:.2f} s  x{speed:g}{ended}"):
                    break
                syncs, last_row = syncs + 1, i
            if i == len(rel) - 1:
                if not loop:
                    time.sleep(max(dt / speed, 1.0 / MAX_FPS))  # the last row stays up for one row's time
                    break
                time.sleep(max(dt / speed, 1.0 / MAX_FPS))  # hold the last row, then from the start
                start, last_row = time.perf_counter(), -1
                continue
            next_wall = start + rel[i + 1] / speed
            time.sleep(max(next_wall - time.perf_counter(), 1.0 / MAX_FPS, 0.0))
    return syncs


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the arguments, load the log, replay it; returns the number of window syncs. Bad arguments
    or a bad log exit with status 2 and a message naming the argument, before any window opens."""
    parser = build_parser()
    args = parser.parse_args(argv)
    from downwash_core.errors import ConfigError, LogError
    from sim.logs import load_log

    try:
        log = load_log(args.log)
    except LogError as e:
        if args.debug:
            raise
        parser.error(f"argument PATH: {e}")
    try:
        return replay_log(log, args.speed, args.loop, what=parser.prog)
    except ConfigError as e:
        if args.debug:
            raise
        parser.exit(2, f"{parser.prog}: error: {e}\n")


if __name__ == "__main__":
    run_main(main)
