"""Replay a flight log in MuJoCo's interactive viewer, or write it as an mp4: the vehicles as logged,
the leaders' wakes, the references.

    python -m experiments.replay PATH.npz [--speed 0.5] [--loop]
    python -m experiments.replay PATH.npz --video flight.mp4 [--fps 25] [--width 640 --height 480] [--speed 0.5]

PATH is a flight log (`sim.logs`, e.g. a collection's ``stage_*/train/flight_000.npz``; a real
flight's, which has no truth arrays, shows its estimates).
The scene is rebuilt from the log's vehicles and roles (`sim.scene.build_scene`; a log
without them gets a leader and followers), and the window shows what the videos show
(`downwash_envs.video`): leaders orange, followers cyan, each leader's wake (the width of
the logged field; none for a flight without downwash), the moving reference paths in
green with their current points, and the time. Playback is paced to real time times
`--speed`, dropping rows rather than falling behind; it ends with the log (a flight that
ended early stops at its last row) or, with `--loop`, starts again until the window is
closed. The window needs a display (see `downwash_envs.viewer`; headless:
``xvfb-run -a python -m experiments.replay ...``, or ``--video``).

``--video PATH.mp4`` renders the same scene offscreen instead (no display needed: EGL is picked
when there is none, `downwash_envs.rendering`) through `downwash_envs.video`, one camera framing
the whole flight: `--fps` frames per second, each showing the flight `--speed` / `--fps` s after
the last, `--width` x `--height` pixels. The file is written under a temporary name in its folder
and renamed when complete, so an interrupted run leaves no partial video at PATH.

Every argument and the log are checked before the window opens or the first frame is rendered;
a bad one (a missing or foreign log, a video path whose folder does not exist or that does not
end in .mp4, the video extra not installed, no OpenGL) is one line and exit status 2.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Any, Callable, NoReturn, Sequence

from experiments.common import OneLineParser, run_main, script

__all__ = ["MAX_FPS", "VIDEO_FPS", "VIDEO_SIZE", "command_parser", "replay_log", "replay_video", "main", "cli"]

MAX_FPS = 60.0  # window syncs per second at most: a fast replay skips rows instead
VIDEO_FPS = 25.0  # frames per second of --video by default
VIDEO_SIZE = (640, 480)  # pixels of --video by default: one tile, larger than the experiments' side-by-side ones


def _speed(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a playback rate > 0 (1 = real time), got {text!r}") from None
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"expected a playback rate > 0 (1 = real time), got {text!r}")
    return x


def _bounded(kind: Callable[[str], Any], lo: float, hi: float, what: str) -> Callable[[str], Any]:
    """An argparse type: `kind(text)` within [lo, hi], else a message naming the range."""

    def parse(text: str) -> Any:
        try:
            x = kind(text)
        except ValueError:
            x = None
        if x is None or not (math.isfinite(x) and lo <= x <= hi):
            raise argparse.ArgumentTypeError(f"expected {what} in [{lo:g}, {hi:g}], got {text!r}")
        return x

    return parse


def command_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(  # one-line usage errors, as every experiment's
        prog="python -m experiments.replay", allow_abbrev=False,
        description="Replay a flight log (.npz) in MuJoCo's interactive viewer, or write it as an mp4 with "
                    "--video, the leaders' wakes and the reference paths drawn.")
    parser.add_argument("log", metavar="PATH", help="a flight log written by sim.logs.save_log (.npz)")
    parser.add_argument("--speed", type=_speed, default=1.0,
                        help="playback rate: 1 real time, 0.25 four times slower, 4 four times faster (default: 1)")
    parser.add_argument("--loop", action="store_true", help="start again at the end until the window is closed")
    video = parser.add_argument_group("video", "write an mp4 instead of opening a window (no display needed)")
    video.add_argument("--video", metavar="OUT.mp4", default=None,
                       help="the mp4 to write (its folder must exist; needs pip install -e '.[video]')")
    video.add_argument("--fps", type=_bounded(float, 1, 120, "frames per second"), default=VIDEO_FPS,
                       help=f"video frames per second, 1-120 (default: {VIDEO_FPS:g})")
    video.add_argument("--width", type=_bounded(int, 16, 4096, "pixels"), default=VIDEO_SIZE[0],
                       help=f"video width, pixels, 16-4096; an odd one is padded by one (default: {VIDEO_SIZE[0]})")
    video.add_argument("--height", type=_bounded(int, 16, 4096, "pixels"), default=VIDEO_SIZE[1],
                       help=f"video height, pixels, 16-4096; an odd one is padded by one (default: {VIDEO_SIZE[1]})")
    video.add_argument("--quality", type=_bounded(int, 0, 10, "a quality"), default=7,
                       help="H.264 quality, 0-10, 10 best and largest (default: 7)")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an expected error (a bad option or log) instead of one line")
    return parser


def _flight(log: Any) -> Any:
    """What the window and the video show of `log`: its scene, trajectory, times, references, paths
    and wake. ConfigError for a log the scene cannot show."""
    from types import SimpleNamespace

    import numpy as np

    from downwash_core.errors import ConfigError
    from downwash_core.params import RATES
    from downwash_envs.video import PATH_POINTS, Trajectory, check_trajectories, wake_width
    from sim.scene import build_scene

    meta = dict(getattr(log, "meta", {}) or {})
    truth = "pos" in log.arrays and "quat" in log.arrays  # a real flight logs estimates only
    pos = np.asarray(log["pos" if truth else "pos_est"], float)
    quat = np.asarray(log["quat" if truth else "quat_est"], float)
    V = pos.shape[1] if pos.ndim == 3 else 0
    names, roles = meta.get("vehicles"), meta.get("roles")
    try:
        if isinstance(names, list) and isinstance(roles, list) and len(names) == len(roles) == V:
            scene = build_scene(list(zip(names, roles)))
        else:  # a log without the scene's record: the first vehicle leads
            scene = build_scene([f"vehicle{v}" for v in range(V)])
    except ValueError as e:  # ConfigError, DataError, or a role the code does not know
        raise ConfigError(f"log: its vehicles {names} with roles {roles} do not make a scene: {e}") from e
    (tr,) = check_trajectories(scene, [Trajectory("log", pos, quat, bool(meta.get("field_enabled", True)))])
    t = np.asarray(log["t"], float)[: len(tr.pos)]
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ConfigError("log: its times 't' must be finite and increasing")
    ref = np.asarray(log["ref_pos"], float)[: len(tr.pos)]
    ref_ok = np.all(np.isfinite(ref), axis=-1)  # (T, V)
    moving = [v for v in range(V) if ref_ok[:, v].all() and np.ptp(ref[:, v], axis=0).max() > 0.01]
    keep = np.unique(np.linspace(0, len(ref) - 1, min(len(ref), PATH_POINTS + 1)).round().astype(int))
    field = meta.get("field") if isinstance(meta.get("field"), dict) else {}
    return SimpleNamespace(
        meta=meta, scene=scene, tr=tr, rel=t - t[0], ref=ref, ref_ok=ref_ok, moving=moving,
        paths=[ref[keep, v] for v in moving],
        wake=wake_width(SimpleNamespace(width0=field.get("width0"), width_slope=field.get("width_slope"))),
        dt=float(np.median(np.diff(t))) if len(t) > 1 else RATES.control_dt,
        points=np.concatenate([tr.pos.reshape(-1, 3), ref[ref_ok]]))


def replay_log(log: Any, speed: float = 1.0, loop: bool = False, what: str = "experiments.replay") -> int:
    """Play `log` (a `sim.logs.FlightLog`) in a `downwash_envs.viewer.Viewer` at `speed` times real time,
    once or (`loop`) until the window is closed; returns the number of window syncs. ConfigError,
    before the window opens, for a log the scene cannot show or when there is no display."""
    import time

    import numpy as np

    from downwash_core.errors import ConfigError
    from downwash_envs.video import CameraView
    from downwash_envs.viewer import Viewer, check_display

    speed = float(speed)
    if not (math.isfinite(speed) and speed > 0):
        raise ConfigError(f"speed: expected a playback rate > 0 (1 = real time), got {speed!r}")
    f = _flight(log)
    rel, tr, last = f.rel, f.tr, len(f.rel) - 1
    check_display(what)
    syncs = 0
    with Viewer(f.scene, wake=f.wake, what=what) as viewer:
        viewer.set_view(CameraView.framing(f.points, 4 / 3))
        start, last_row = time.perf_counter(), -1
        while viewer.is_running():
            played = (time.perf_counter() - start) * speed  # s of flight time
            i = min(int(np.searchsorted(rel, played, side="right")) - 1, last)
            if i != last_row:
                ended = " (ended)" if i == last and f.meta.get("status", 0) != 0 else ""
                ref_now = f.ref[i, f.moving] if f.moving else None
                if not viewer.show(tr.pos[i], tr.quat[i], ref_now, f.paths, tr.wake_on,
                                   f"t = {rel[i]:.2f} s  x{speed:g}{ended}"):
                    break
                syncs, last_row = syncs + 1, i
            if i == last:
                if not loop:
                    time.sleep(max(f.dt / speed, 1.0 / MAX_FPS))  # the last row stays up for one row's time
                    break
                time.sleep(max(f.dt / speed, 1.0 / MAX_FPS))  # hold the last row, then from the start
                start, last_row = time.perf_counter(), -1
                continue
            next_wall = start + rel[i + 1] / speed
            time.sleep(max(next_wall - time.perf_counter(), 1.0 / MAX_FPS, 0.0))
    return syncs


def replay_video(log: Any, path: str | os.PathLike, fps: float = VIDEO_FPS, width: int = VIDEO_SIZE[0],
                 height: int = VIDEO_SIZE[1], speed: float = 1.0, quality: int = 7, label: str = "") -> int:
    """Write `log` as an mp4 at `path` (see the module docstring), atomically; returns the number of
    frames. ConfigError, before any frame, for a bad argument, a log the scene cannot show, a missing
    writer or no OpenGL backend."""
    import dataclasses

    from downwash_envs.video import check_video_output, write_conditions_video

    f = _flight(log)
    check_video_output(path, f.scene)  # the writer and an OpenGL context, before the first frame
    # The video takes only a finite reference: a vehicle's with gaps (never drawn, as in the window)
    # becomes one constant point, its first finite one, or its first position.
    ref = f.ref.copy()
    for v in range(f.scene.n_vehicles):
        if v not in f.moving and not f.ref_ok[:, v].all():
            ref[:, v] = f.ref[f.ref_ok[:, v], v][0] if f.ref_ok[:, v].any() else f.tr.pos[0, v]
    trajectory = dataclasses.replace(f.tr, label=label) if label else f.tr
    return write_conditions_video(path, f.scene, [trajectory], ref, f.dt, fps, width, height, wake=f.wake,
                                  quality=quality, speed=speed)


def _check_video_path(text: str) -> Path:
    """The --video path, checked before the log is read: ConfigError naming what is wrong."""
    from downwash_core.errors import ConfigError
    from downwash_envs.video import check_writer

    path = Path(text)
    if path.suffix.lower() != ".mp4":
        raise ConfigError(f"argument --video: {text!r} must end in .mp4")
    if path.is_dir():
        raise ConfigError(f"argument --video: {text!r} is a folder; give a file name ending in .mp4")
    folder = path.parent
    if not folder.is_dir():
        raise ConfigError(f"argument --video: its folder {str(folder)!r} does not exist; make it first")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"argument --video: its folder {str(folder)!r} is not writable")
    try:
        check_writer()
    except ConfigError as e:
        raise ConfigError(f"argument --video: {e}") from e
    return path


def main(argv: Sequence[str] | None = None) -> int:
    """Parse the arguments, load the log, replay it in the window (returns the number of window syncs)
    or write it with --video (returns the number of frames). Bad arguments or a bad log exit with
    status 2 and one line naming the argument, before any window opens or frame is rendered."""
    parser = command_parser()
    args = parser.parse_args(argv)
    from downwash_core.errors import ConfigError, LogError
    from sim.logs import load_log

    def fail(e: Exception) -> NoReturn:
        if args.debug:
            raise e
        parser.exit(2, f"{parser.prog}: error: {e}\n")

    video = None
    if args.video is not None:
        if args.loop:
            parser.error("argument --loop: a video plays once; leave out --loop with --video")
        try:
            video = _check_video_path(args.video)
        except ConfigError as e:
            fail(e)
    try:
        log = load_log(args.log)
    except LogError as e:
        if args.debug:
            raise
        parser.error(f"argument PATH: {e}")
    try:
        if video is None:
            return replay_log(log, args.speed, args.loop, what=parser.prog)
        import time

        start = time.perf_counter()
        n = replay_video(log, video, args.fps, args.width, args.height, args.speed, args.quality,
                         label=Path(args.log).stem)
        print(f"wrote {video} ({n} frames, {time.perf_counter() - start:.1f} s)")
        return n
    except ConfigError as e:
        fail(e)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
