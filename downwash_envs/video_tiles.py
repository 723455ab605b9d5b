"""The frames of the videos, drawn: one tile per condition, each a logged state with its wakes,
reference paths and label, from one camera (`TiledRenderer`), and the drawing that the viewer shares.

A tile is an `MjData` set to the logged positions and attitudes, `mj_forward`, and MuJoCo's offscreen
renderer, with decorations added to its scene: each wake-casting vehicle's wake (`add_wake`: translucent
cylinders along the vehicle's body -z axis from 0.05 m to `WAKE_VIEW_DEPTH`, of radius
sigma(s) = width0 + width_slope s, `wake_width` of the field), the reference paths (green lines) and the
current reference point (a green sphere); the condition's name and the time in a corner. `decorated` tints
the vehicles by role (leaders orange, followers cyan) on a copy of the scene's model. `CameraView.framing`
frames every point of the whole video. `downwash_envs.video` turns these frames into an mp4 (and
re-exports everything here); `downwash_envs.viewer` draws its window with `decorated`, `add_wake`,
`add_geom` and `add_line`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any, Sequence

import mujoco
import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.roles import Role
from downwash_core.validate import count, positive_float
from downwash_envs.rendering import FOLLOWER_RGBA, LEADER_RGBA, REF_RGBA, TINTED_GEOMS, offscreen_renderer
from sim.field import DownwashField
from sim.scene import Scene

__all__ = ["WAKE_VIEW_DEPTH", "PATH_RGBA", "REF_RADIUS", "CameraView", "TiledRenderer", "wake_width", "decorated",
           "add_wake", "add_geom", "add_line"]

WAKE_VIEW_DEPTH = 1.5  # m below the leader along its axis: the on-axis push is down to ~0.8 m/s^2 there
_WAKE_START = 0.05  # m, where the field's fade-in w(s) begins
_WAKE_SEGMENTS = 12  # cylinders per wake: a stepped cone
_WAKE_RGB = (0.35, 0.6, 1.0)
_WAKE_ALPHA = (0.28, 0.06)  # at the top and at the bottom of the wake: it weakens with depth
PATH_RGBA = (0.2, 0.9, 0.2, 1.0)  # a reference path's lines
REF_RADIUS = 0.03  # m, the current reference point (as downwash_envs.rendering)
_BACKGROUND = 40  # grey level of an unused grid cell
_GROUND = "ground"  # the scene's floor (sim.scene)
_HORIZON = 100.0  # m, half size of the drawn floor
_HAZE_RGBA = (0.78, 0.84, 0.9, 1.0)
_SAMPLES = 0  # no multisampling: 4x made a frame three times slower with software EGL


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
        rgba = LEADER_RGBA if role == Role.LEADER else FOLLOWER_RGBA
        for g in TINTED_GEOMS:
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
                add_line(scn, a, b, self._line_px, PATH_RGBA)
        if ref_now is not None:
            for p in np.asarray(ref_now).reshape(-1, 3):
                add_geom(scn, mujoco.mjtGeom.mjGEOM_SPHERE, (REF_RADIUS, 0, 0), p, np.eye(3), REF_RGBA)
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
    viewer draw it: a stepped cone along -R[:, 2] from `_WAKE_START` to `WAKE_VIEW_DEPTH`, radius
    width0 + width_slope s, fading with depth. wake: (width0 m, width_slope -)."""
    n = R[:, 2]
    w0, slope = wake
    edges = np.linspace(_WAKE_START, WAKE_VIEW_DEPTH, _WAKE_SEGMENTS + 1)
    for i in range(_WAKE_SEGMENTS):
        s = 0.5 * (edges[i] + edges[i + 1])
        alpha = _WAKE_ALPHA[0] + (_WAKE_ALPHA[1] - _WAKE_ALPHA[0]) * i / (_WAKE_SEGMENTS - 1)
        half = 0.5 * (edges[i + 1] - edges[i])
        add_geom(scn, mujoco.mjtGeom.mjGEOM_CYLINDER, (w0 + slope * s, half, 0.0), p - s * n, R, (*_WAKE_RGB, alpha))


def add_geom(scn: Any, kind: int, size: Sequence[float], pos: np.ndarray, mat: np.ndarray,
              rgba: Sequence[float]) -> None:
    if scn.ngeom >= scn.maxgeom:  # a full scene drops decorations, never the vehicles
        return
    mujoco.mjv_initGeom(scn.geoms[scn.ngeom], kind, np.asarray(size, float), np.asarray(pos, float),
                        np.asarray(mat, float).ravel(), np.asarray(rgba, np.float32))
    scn.ngeom += 1


def add_line(scn: Any, a: np.ndarray, b: np.ndarray, width_px: float, rgba: Sequence[float]) -> None:
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
