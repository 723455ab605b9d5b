"""Videos of flights: one tile per condition, side by side, the leaders' wakes drawn, written as mp4.

    from downwash_envs.video import Trajectory, logs_video
    logs_video("runs/lemniscate/flight.mp4", scene, {c: clogs[0] for c, clogs in per_condition.items()})

Each tile renders one condition's logged state (an `MjData` set to the logged positions
and attitudes, `mj_forward`, MuJoCo's offscreen renderer) from one fixed camera shared by
all tiles, framed on every vehicle and reference point of the whole video, so the tiles
compare like for like. Drawn into each tile's scene: every wake-casting vehicle's wake
(translucent cylinders along the vehicle's body -z axis from 0.05 m to `WAKE_DEPTH`,
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
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import mujoco
import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.io import atomic_path
from downwash_core.params import RATES
from downwash_core.roles import Role
from downwash_core.validate import count, positive_float
from downwash_envs.rendering import _FOLLOWER_RGBA, _LEADER_RGBA, _REF_RGBA, _TINTED_GEOMS, offscreen_renderer
from sim.field import DownwashField
from sim.scene import Scene

__all__ = [
    "WAKE_DEPTH", "Trajectory", "CameraView", "TiledRenderer", "wake_width", "add_wake", "frame_rows", "render_frames",
    "check_writer", "check_video_output", "write_video", "write_conditions_video", "logs_video",
]

WAKE_DEPTH = 1.5  # m below the leader along its axis: the on-axis push is down to ~0.8 m/s^2 there
_WAKE_START = 0.05  # m, where the field's fade-in w(s) begins
_WAKE_SEGMENTS = 12  # cylinders per wake: a stepped cone
_WAKE_RGB = (0.35, 0.6, 1.0)
_WAKE_ALPHA = (0.28, 0.06)  # at the top and at the bottom of the wake: it weakens with depth
_PATH_POINTS = 120  # line segments per reference path
_PATH_RGBA = (0.2, 0.9, 0.2, 1.0)
_REF_RADIUS = 0.03  # m, the current reference point (as downwash_envs.rendering)
_BACKGROUND = 40  # grey level of an unused grid cell
_SUFFIXES = (".mp4",)
_GROUND = "ground"  # the scene's floor (sim.scene)
_HORIZON = 100.0  # m, half size of the drawn floor
_HAZE_RGBA = (0.78, 0.84, 0.9, 1.0)
_SAMPLES = 0  # no multisampling: 4x made a frame three times slower with software EGL


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


@dataclass(frozen=True)
class CameraView:
    """A free camera: looks at `lookat` (3,) m from `distance` m, azimuth and elevation in degrees."""

    lookat: tuple[float, float, float]
    distance: float
    azimuth: float
    elevation: float

    @staticmethod
    def framing(points: np.ndarray, aspect: float, fovy: float = 45.0, elevation: float = -25.0,
                margin: float = 0.35) -> "CameraView":
        """A view of every finite point of `points` (..., 3) m in a tile of width/height `aspect`.

        It looks across the longer horizontal extent (so a lemniscate along x or a transect
        along y is seen broadside), 20 deg off square to show depth, from the distance at
        which the extents plus `margin` m fill the vertical field of view `fovy` (deg).
        """
        p = np.asarray(points, float).reshape(-1, 3)
        p = p[np.all(np.isfinite(p), axis=1)]
        if len(p) == 0:
            raise ConfigError("camera framing: no finite positions to frame")
        lo, hi = p.min(axis=0), p.max(axis=0)
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) + margin
        along_x = half[0] >= half[1]
        azimuth = (90.0 if along_x else 0.0) + 20.0  # camera looks along +y (sees the x extent) or +x
        across, depth = (half[0], half[1]) if along_x else (half[1], half[0])
        tan_y = math.tan(math.radians(fovy) / 2.0)
        tan_x = tan_y * aspect
        vertical = half[2] * math.cos(math.radians(elevation)) + depth * abs(math.sin(math.radians(elevation)))
        distance = max(across / tan_x, vertical / tan_y) + 0.5 * depth  # to the near side of the extents
        return CameraView(tuple(float(c) for c in centre), float(distance), azimuth, float(elevation))


def wake_width(field: Any = None) -> tuple[float, float]:
    """(width0 m, width_slope -) of `field`'s wake when it has scalar `width0` and `width_slope`
    (the SO(2) law's sigma(s) = width0 + width_slope s), else those of the default `DownwashField`."""
    default = DownwashField()
    w0, slope = getattr(field, "width0", None), getattr(field, "width_slope", None)
    try:
        w0, slope = float(np.asarray(w0, float)), float(np.asarray(slope, float))  # scalars only
    except (TypeError, ValueError):  # another field family (None), or per-world arrays
        return float(default.width0), float(default.width_slope)
    if not (math.isfinite(w0) and math.isfinite(slope) and w0 > 0 and slope >= 0):
        return float(default.width0), float(default.width_slope)
    return w0, slope


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


def _check_trajectories(scene: Scene, trajectories: Sequence[Trajectory]) -> list[Trajectory]:
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


def decorated(scene: Scene, wake_vehicles: Sequence[int] | None = None, wake: tuple[float, float] | None = None
              ) -> tuple[Any, list[int], tuple[float, float]]:
    """What the videos and the viewer draw: (a copy of the scene's model with the vehicles tinted by
    role (the physics model is untouched), the vehicles whose wake is drawn (default: the
    leaders), the wake's (width0 m, width_slope -) (default `wake_width()`)); ConfigError
    naming a bad vehicle index or width."""
    V = scene.n_vehicles
    if wake_vehicles is None:
        wake_vehicles = [v for v, r in enumerate(scene.roles) if r == Role.LEADER]
    vehicles = [int(v) for v in wake_vehicles]
    if any(not 0 <= v < V for v in vehicles):
        raise ConfigError(f"wake_vehicles: {list(wake_vehicles)} must be vehicle indices in [0, {V - 1}]")
    width = wake_width() if wake is None else (positive_float("wake width0", wake[0], "m"),
                                               positive_float("wake width_slope", wake[1], "-", allow_zero=True))
    model = copy.copy(scene.model)
    for v, role in enumerate(scene.roles):
        rgba = _LEADER_RGBA if role == Role.LEADER else _FOLLOWER_RGBA
        for g in _TINTED_GEOMS:
            model.geom_rgba[model.geom(f"{scene.vehicles[v]}/{g}").id] = rgba
    return model, vehicles, width


class TiledRenderer:
    """Frames of several conditions at once: one `width` x `height` tile each, `columns` per row.

    One MuJoCo renderer and one MjData serve every tile in turn (the states are set, not
    simulated). Frames are (rows height, columns width, 3) uint8.
    """

    def __init__(self, scene: Scene, n_tiles: int, width: int = 320, height: int = 240, columns: int | None = None,
                 wake_vehicles: Sequence[int] | None = None, wake: tuple[float, float] | None = None):
        """wake_vehicles: indices whose wake is drawn (default: the scene's leaders; () for none).
        wake: (width0 m, width_slope -) of the drawn wake (default: `wake_width()`)."""
        self.n_tiles = count("n_tiles", n_tiles, lo=1)
        self.width = count("width", width, lo=16, hi=4096)
        self.height = count("height", height, lo=16, hi=4096)
        self.columns = self.n_tiles if columns is None else count("columns", columns, lo=1)
        self.columns = min(self.columns, self.n_tiles)
        self.rows = math.ceil(self.n_tiles / self.columns)
        model, self.wake_vehicles, self.wake = decorated(scene, wake_vehicles, wake)  # + a larger offscreen buffer
        self.scene = scene

        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), self.width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), self.height)
        # No shadow map: with Mesa's software EGL it costs several times the rest of a frame, and the
        # ground the shadows would fall on lies mostly out of view below the vehicles.
        model.vis.quality.shadowsize = 0
        model.vis.quality.offsamples = _SAMPLES
        # A ground to the horizon that fades into a light haze, instead of a plane's edge on black
        ground = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, _GROUND)
        if ground >= 0:
            model.geom_size[ground, :2] = _HORIZON
        model.vis.rgba.fog[:] = _HAZE_RGBA
        model.vis.map.fogstart = 0.25 * _HORIZON / model.stat.extent  # in units of the model's extent
        model.vis.map.fogend = _HORIZON / model.stat.extent
        self.model = model
        self.data = mujoco.MjData(model)
        self._renderer = offscreen_renderer(model, self.width, self.height, what="a video", error=ConfigError)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_FOG] = True
        self._font = _font(max(10, self.height // 20))
        self._line_px = max(1.0, self.height / 120)  # path line width, pixels

    @property
    def fovy(self) -> float:
        """deg, the free camera's vertical field of view."""
        return float(self.model.vis.global_.fovy)

    def set_view(self, view: CameraView) -> None:
        self.camera.lookat[:] = view.lookat
        self.camera.distance = view.distance
        self.camera.azimuth = view.azimuth
        self.camera.elevation = view.elevation

    def tile(self, pos: np.ndarray, quat: np.ndarray, ref_now: np.ndarray | None = None,
             paths: Sequence[np.ndarray] = (), label: str = "", draw_wake: bool = True) -> np.ndarray:
        """(height, width, 3) uint8 of one state: pos (V, 3) m, quat (V, 4); ref_now (P, 3) m points
        marked now; paths: (N, 3) m polylines drawn as lines."""
        m, d, scene = self.model, self.data, self.scene
        d.qpos[:] = m.qpos0
        for v in range(scene.n_vehicles):
            a = int(scene.qpos_adr[v])
            d.qpos[a:a + 3] = pos[v]
            d.qpos[a + 3:a + 7] = quat[v]
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        r = self._renderer
        r.update_scene(d, camera=self.camera)
        scn = r.scene
        if draw_wake:
            for v in self.wake_vehicles:
                R = d.xmat[scene.body_ids[v]].reshape(3, 3)  # body to world: column 2 is the wake axis n
                self._add_wake(scn, d.xpos[scene.body_ids[v]].copy(), R)
        for path in paths:  # lines, not spheres: a hundred translucent spheres cost more than the scene
            for a, b in zip(path[:-1], path[1:]):
                _add_line(scn, a, b, self._line_px, _PATH_RGBA)
        if ref_now is not None:
            for p in np.asarray(ref_now).reshape(-1, 3):
                _add_geom(scn, mujoco.mjtGeom.mjGEOM_SPHERE, (_REF_RADIUS, 0, 0), p, np.eye(3), _REF_RGBA)
        img = r.render()
        return _label(img, label, self._font) if label else img

    def _add_wake(self, scn: Any, p: np.ndarray, R: np.ndarray) -> None:
        add_wake(scn, p, R, self.wake)

    def frame(self, tiles: Sequence[np.ndarray]) -> np.ndarray:
        """The tiles (each (height, width, 3) uint8) laid out `columns` per row, padded to even sizes."""
        H, W = self.height, self.width
        out = np.full((self.rows * H + (self.rows * H) % 2, self.columns * W + (self.columns * W) % 2, 3),
                      _BACKGROUND, np.uint8)
        for i, t in enumerate(tiles):
            r, c = divmod(i, self.columns)
            out[r * H:(r + 1) * H, c * W:(c + 1) * W] = t
        return out

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self) -> "TiledRenderer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def add_wake(scn: Any, p: np.ndarray, R: np.ndarray, wake: tuple[float, float]) -> None:
    """Into `scn`: the wake of a vehicle at p (3,) m with body-to-world R (3, 3), as the videos and the
    viewer draw it: a stepped cone along -R[:, 2] from `_WAKE_START` to `WAKE_DEPTH`, radius
    width0 + width_slope s, fading with depth. wake: (width0 m, width_slope -)."""
    n = R[:, 2]
    w0, slope = wake
    edges = np.linspace(_WAKE_START, WAKE_DEPTH, _WAKE_SEGMENTS + 1)
    for i in range(_WAKE_SEGMENTS):
        s = 0.5 * (edges[i] + edges[i + 1])
        alpha = _WAKE_ALPHA[0] + (_WAKE_ALPHA[1] - _WAKE_ALPHA[0]) * i / (_WAKE_SEGMENTS - 1)
        half = 0.5 * (edges[i + 1] - edges[i])
        _add_geom(scn, mujoco.mjtGeom.mjGEOM_CYLINDER, (w0 + slope * s, half, 0.0), p - s * n, R, (*_WAKE_RGB, alpha))


def _add_geom(scn: Any, kind: int, size: Sequence[float], pos: np.ndarray, mat: np.ndarray,
              rgba: Sequence[float]) -> None:
    if scn.ngeom >= scn.maxgeom:  # a full scene drops decorations, never the vehicles
        return
    mujoco.mjv_initGeom(scn.geoms[scn.ngeom], kind, np.asarray(size, float), np.asarray(pos, float),
                        np.asarray(mat, float).ravel(), np.asarray(rgba, np.float32))
    scn.ngeom += 1


def _add_line(scn: Any, a: np.ndarray, b: np.ndarray, width_px: float, rgba: Sequence[float]) -> None:
    if scn.ngeom >= scn.maxgeom:
        return
    g = scn.geoms[scn.ngeom]
    mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_LINE, np.zeros(3), np.zeros(3), np.eye(3).ravel(),
                        np.asarray(rgba, np.float32))
    mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_LINE, width_px, np.asarray(a, float), np.asarray(b, float))
    scn.ngeom += 1


def _font(size: int) -> Any:
    from PIL import ImageFont  # Pillow comes with matplotlib

    try:
        return ImageFont.load_default(size=size)  # scalable when Pillow has FreeType (>= 10.1)
    except (TypeError, OSError, ImportError):
        return ImageFont.load_default()


def _label(img: np.ndarray, text: str, font: Any) -> np.ndarray:
    """`img` with `text` in its top-left corner, white on a dark box."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(img)
    draw = ImageDraw.Draw(im)
    x0, y0, x1, y1 = draw.textbbox((6, 4), text, font=font)
    draw.rectangle((x0 - 4, y0 - 3, x1 + 4, y1 + 3), fill=(0, 0, 0))
    draw.text((6, 4), text, fill=(255, 255, 255), font=font)
    return np.asarray(im)


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
    trajectories = _check_trajectories(scene, trajectories)
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
        keep = np.unique(np.linspace(0, len(ref) - 1, min(len(ref), _PATH_POINTS + 1)).round().astype(int))
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
