"""Videos of flights: one tile per condition, side by side, the leaders' wakes drawn, written as mp4.

    from downwash_envs.video import Trajectory, logs_video
    logs_video("runs/lemniscate/flight.mp4", scene, {c: clogs[0] for c, clogs in per_condition.items()})

Each tile renders one condition's logged state (an `MjData` set to the logged positions
and attitudes, `mj_forward`, MuJoCo's offscreen renderer) from one fixed camera shared by
all tiles, framed on every vehicle and reference point of the whole video, so the tiles
compare like for like. Drawn into each tile's scene: every wake-casting vehicle's wake
(translucent cylinders along the vehicle's body -z axis from 0.05 m to `WAKE_VIEW_DEPTH`,
of radius sigma(s) = width0 + width_slope s, the field's own width when it has one),
the reference paths (green lines) with the current reference point (a green sphere), and the
condition's name and the time in a corner. Leaders are orange, followers cyan.

Timing: log rows are `dt` apart (the 50 Hz controller ticks); a video of `fps` frames per
second has ceil(T dt fps) frames, frame j showing the last row at or before time j / fps.
At a playback `speed` other than 1 (a slow-motion or fast replay) frame j shows flight time
j speed / fps instead: ceil(T dt fps / speed) frames, the labels in flight time.
A condition whose log is shorter (a flight that ended early) holds its last row and is
labelled "(ended)"; a trajectory ends at its first non-finite row.

The writer is imageio's ffmpeg plugin (libx264, yuv420p: frames are padded to even sizes),
imported only when a video is written (`pip install -e ".[video]"`); the file is written
under a temporary name in the same folder, then renamed. Bad input (shapes, fps, sizes,
the path, no writer, no OpenGL backend) raises ConfigError before any frame is rendered.

The tiles are drawn by `downwash_envs.video_tiles` (`TiledRenderer`, the camera, the wake; re-exported
here); this module times the frames, checks the input and writes the file.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.io import atomic_path
from downwash_core.params import RATES
from downwash_core.validate import count, positive_float
from downwash_envs.video_tiles import WAKE_VIEW_DEPTH, CameraView, TiledRenderer, add_wake, wake_width
from sim.scene import Scene

__all__ = [
    "WAKE_VIEW_DEPTH", "Trajectory", "CameraView", "TiledRenderer", "wake_width", "add_wake", "frame_rows", "render_frames",
    "check_writer", "check_video_output", "write_video", "write_conditions_video", "logs_video",
]

PATH_POINTS = 120  # line segments per reference path
_SUFFIXES = (".mp4",)


@dataclass(frozen=True)
class Trajectory:
    """One condition's flight, as logged: `label` names its tile.

    pos: (T, V, 3) m, world frame; quat: (T, V, 4) (w, x, y, z), body to world; rows `dt` apart.
    wake_on: False for a flight without downwash (no wake is drawn in its tile).
    """

    label: str
    pos: np.ndarray
    quat: np.ndarray
    wake_on: bool = True


def frame_rows(n_rows: int, dt: float, fps: float) -> np.ndarray:
    """(n_frames,) int: the log row each video frame shows. n_frames = ceil(n_rows dt fps) (every
    frame starts inside the logged span); frame j shows the last row at or before j / fps."""
    n_rows = count("n_rows", n_rows, lo=1)
    dt = positive_float("dt", dt, "s")
    fps = _check_fps(fps)
    n_frames = max(1, math.ceil(n_rows * dt * fps - 1e-9))
    rows = np.floor(np.arange(n_frames) / (fps * dt) + 1e-9).astype(int)
    return np.minimum(rows, n_rows - 1)


def _check_fps(fps: Any) -> float:
    try:
        f = float(fps)
    except (TypeError, ValueError):
        raise ConfigError(f"fps: expected a number of frames per second in [1, 120], got {fps!r}") from None
    if not (math.isfinite(f) and 1.0 <= f <= 120.0):
        raise ConfigError(f"fps: got {fps!r}; allowed [1, 120] frames per second")
    return f


def check_trajectories(scene: Scene, trajectories: Sequence[Trajectory]) -> list[Trajectory]:
    """Each (T, V, 3) / (T, V, 4), V = the scene's vehicles, cut at its first non-finite row."""
    if len(trajectories) == 0:
        raise ConfigError("trajectories: expected one or more conditions, got none")
    V = scene.n_vehicles
    out = []
    for tr in trajectories:
        if not isinstance(tr, Trajectory):
            raise ConfigError(f"trajectories: expected Trajectory items, got {type(tr).__name__}")
        pos, quat = np.asarray(tr.pos, float), np.asarray(tr.quat, float)
        if pos.ndim != 3 or pos.shape[1:] != (V, 3):
            raise ConfigError(f"trajectory {tr.label!r}: pos must be (T, {V}, 3) for the scene's {V} vehicles, "
                              f"got {pos.shape}")
        if quat.shape != pos.shape[:2] + (4,):
            raise ConfigError(f"trajectory {tr.label!r}: quat must be {pos.shape[:2] + (4,)} (as pos, (w, x, y, z)), "
                              f"got {quat.shape}")
        finite = np.all(np.isfinite(pos), axis=(1, 2)) & np.all(np.isfinite(quat), axis=(1, 2))
        n = int(np.argmin(finite)) if not finite.all() else len(finite)
        if n == 0:
            raise ConfigError(f"trajectory {tr.label!r}: empty (no rows, or its first row is not finite)")
        norms = np.linalg.norm(quat[:n], axis=-1)
        if np.any(norms < 1e-6):
            raise ConfigError(f"trajectory {tr.label!r}: a quaternion of zero length")
        out.append(Trajectory(str(tr.label), pos[:n], quat[:n] / norms[..., None], bool(tr.wake_on)))
    return out


def _check_path(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.suffix.lower() not in _SUFFIXES:
        raise ConfigError(f"video path: {str(path)!r} must end in {', '.join(_SUFFIXES)}")
    if path.is_dir():
        raise ConfigError(f"video path: {str(path)!r} is a folder; give a file name ending in .mp4")
    return path


def check_writer() -> None:
    """ConfigError naming the extra to install when imageio or its ffmpeg plugin is missing."""
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as e:
        raise ConfigError(f"writing a video needs imageio and imageio-ffmpeg ({type(e).__name__}: {e}); "
                          "install them with: pip install -e \".[video]\"") from e


def check_video_output(path: str | os.PathLike, scene: Scene) -> Path:
    """Before any work: the path ends in .mp4 and is not a folder, imageio and its ffmpeg plugin are
    installed, and an OpenGL context can render `scene` (ConfigError naming what is missing)."""
    path = _check_path(path)
    check_writer()
    TiledRenderer(scene, 1, 16, 16).close()
    return path


def render_frames(scene: Scene, trajectories: Sequence[Trajectory], reference: np.ndarray | None = None,
                  dt: float = RATES.control_dt, fps: float = 25.0, width: int = 320, height: int = 240,
                  columns: int | None = None, wake_vehicles: Sequence[int] | None = None,
                  wake: tuple[float, float] | None = None, speed: float = 1.0) -> Iterator[np.ndarray]:
    """The video's frames, one at a time: (H, W, 3) uint8, tiles in the order of `downwash_trajectories`.

    reference: (T_ref, V, 3) m, the vehicles' references on the same `dt` rows (e.g. a log's
    `ref_pos`), or None. The path of every vehicle whose reference moves is drawn, with its
    current point. speed: flight seconds per video second (module docstring). Everything is
    checked before the first frame (ConfigError).
    """
    trajectories = check_trajectories(scene, trajectories)
    speed = positive_float("speed", speed, "-")
    dt = positive_float("dt", dt, "s")
    rows = frame_rows(max(len(t.pos) for t in trajectories), dt / speed, fps)  # rows dt / speed apart in video time
    ref, moving = None, np.zeros(0, int)
    if reference is not None:
        ref = np.asarray(reference, float)
        if ref.ndim != 3 or ref.shape[1:] != (scene.n_vehicles, 3):
            raise ConfigError(f"reference: expected (T, {scene.n_vehicles}, 3) m, got {ref.shape}")
        if len(ref) == 0 or not np.all(np.isfinite(ref)):
            raise ConfigError(f"reference: expected one or more rows, all finite ({len(ref)} rows given)")
        moving = np.flatnonzero(np.ptp(ref, axis=0).max(axis=-1) > 0.01)  # a hover's reference is not drawn
    renderer = TiledRenderer(scene, len(trajectories), width, height, columns, wake_vehicles, wake)
    return _frames(renderer, trajectories, rows, dt, ref, moving, f"  x{speed:g}" if speed != 1.0 else "")


def _frames(renderer: TiledRenderer, trajectories: list[Trajectory], rows: np.ndarray, dt: float,
            ref: np.ndarray | None, moving: np.ndarray, rate: str = "") -> Iterator[np.ndarray]:
    points = [t.pos.reshape(-1, 3) for t in trajectories]
    paths: list[np.ndarray] = []
    if ref is not None:
        points.append(ref.reshape(-1, 3))
        keep = np.unique(np.linspace(0, len(ref) - 1, min(len(ref), PATH_POINTS + 1)).round().astype(int))
        paths = [ref[keep, v] for v in moving]
    with renderer:
        renderer.set_view(CameraView.framing(np.concatenate(points), renderer.width / renderer.height, renderer.fovy))
        for k in rows:
            ref_now = ref[min(int(k), len(ref) - 1), moving] if ref is not None and len(moving) else None
            tiles = []
            for tr in trajectories:
                i = min(int(k), len(tr.pos) - 1)
                ended = " (ended)" if k >= len(tr.pos) else ""
                tiles.append(renderer.tile(tr.pos[i], tr.quat[i], ref_now, paths,
                                           f"{tr.label}{ended}  t = {k * dt:.2f} s{rate}", tr.wake_on))
            yield renderer.frame(tiles)


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float = 25.0, quality: int = 7) -> int:
    """Write `frames` ((H, W, 3) uint8, all one size, H and W even) as an H.264 mp4 at `fps`,
    atomically; returns the number of frames. quality: imageio's 0-10 (10 is best)."""
    path = _check_path(path)
    fps = _check_fps(fps)
    quality = count("quality", quality, lo=0, hi=10)
    check_writer()
    import imageio.v2 as imageio

    n, shape, writer = 0, None, None
    with atomic_path(path, suffix=path.suffix) as tmp:
        try:
            # macro_block_size 2: yuv420p needs even sizes, and the frames are made even, so none is resized
            writer = imageio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=quality,
                                        pixelformat="yuv420p", macro_block_size=2, ffmpeg_log_level="error")
            for f in frames:
                f = np.asarray(f)
                if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3 or f.shape[0] % 2 or f.shape[1] % 2:
                    raise ConfigError(f"frame {n}: expected (H, W, 3) uint8 with H and W even, got {f.shape} {f.dtype}")
                if shape is not None and f.shape != shape:
                    raise ConfigError(f"frame {n}: size {f.shape} differs from the first frame's {shape}")
                shape = f.shape
                writer.append_data(f)
                n += 1
            writer.close()
            if n == 0:
                raise ConfigError("frames: expected one or more frames, got none")
        except BaseException:
            # close now: imageio's writer left open would finish the file when it is garbage-collected
            if writer is not None:
                with contextlib.suppress(Exception):
                    writer.close()
            raise
    return n


def write_conditions_video(path: str | os.PathLike, scene: Scene, trajectories: Sequence[Trajectory],
                           reference: np.ndarray | None = None, dt: float = RATES.control_dt, fps: float = 25.0,
                           width: int = 320, height: int = 240, columns: int | None = None,
                           wake_vehicles: Sequence[int] | None = None, wake: tuple[float, float] | None = None,
                           quality: int = 7, speed: float = 1.0) -> int:
    """Render the conditions side by side (see `render_frames`) into an mp4 at `path`; returns the
    number of frames. Every argument, the writer and the OpenGL backend are checked first."""
    path = _check_path(path)
    _check_fps(fps)
    count("quality", quality, lo=0, hi=10)
    check_writer()
    frames = render_frames(scene, trajectories, reference, dt, fps, width, height, columns, wake_vehicles, wake,
                           speed)
    return write_video(path, frames, fps, quality)


def logs_video(path: str | os.PathLike, scene: Scene, logs: Mapping[str, Any], fps: float = 25.0,
               field: Any = None, **options: Any) -> int:
    """`write_conditions_video` of one flight log per condition (label -> `sim.logs.FlightLog`, or any
    mapping with `t`, `pos`, `quat` and `ref_pos`); the reference is the longest log's, the wake
    width is `field`'s (`wake_width`), and a log whose meta says `field_enabled: False` has no wake
    drawn. Returns the number of frames."""
    if not logs:
        raise ConfigError("logs: expected one or more conditions, got none")
    trajectories = [Trajectory(label, np.asarray(log["pos"]), np.asarray(log["quat"]),
                               bool(getattr(log, "meta", {}).get("field_enabled", True)))
                    for label, log in logs.items()]
    longest = max(logs.values(), key=lambda log: len(log["t"]))
    t = np.asarray(longest["t"], float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else RATES.control_dt
    return write_conditions_video(path, scene, trajectories, np.asarray(longest["ref_pos"]), dt, fps,
                                  wake=options.pop("wake", None) or wake_width(field), **options)
