"""Offscreen frames of the follower task, through MuJoCo's renderer.

A free camera looks at the midpoint of the two vehicles from a distance that grows
with their separation; hulls and arms are tinted (leader orange, follower cyan) and
a green sphere marks the follower's reference. Frames are (height, width, 3) uint8.

OpenGL backend. MuJoCo picks its GL context class from the environment variable
``MUJOCO_GL`` when `mujoco` is imported (``egl``, ``osmesa``, ``glfw``; unset means
glfw, which needs a display). So that rendering works on a headless Linux machine
without the user setting anything, `ensure_gl_backend` (called before the first
renderer is made) does this: when ``MUJOCO_GL`` is unset and there is no display
(``DISPLAY`` and ``WAYLAND_DISPLAY`` unset), it sets ``MUJOCO_GL=egl`` (GPU, or
Mesa's software EGL) and, since mujoco has already read the variable by then,
reloads `mujoco.rendering.classic.gl_context` so that it selects the EGL context.
An explicit ``MUJOCO_GL`` is always respected. When no backend works, making the
renderer raises a RuntimeError that names ``MUJOCO_GL=egl`` and ``MUJOCO_GL=osmesa``
and the packages they need.
"""

from __future__ import annotations

import copy
import importlib
import math
import os
import sys

import mujoco
import numpy as np

from sim.scene import Scene
from sim.simulator import Simulator

__all__ = ["ensure_gl_backend", "offscreen_renderer", "Renderer"]

LEADER_RGBA = (0.95, 0.55, 0.05, 1.0)  # orange
FOLLOWER_RGBA = (0.05, 0.8, 0.9, 1.0)  # cyan
REF_RGBA = (0.2, 0.9, 0.2, 0.5)  # translucent green sphere at the follower's reference
TINTED_GEOMS = ("hull", "arm0", "arm1", "arm2", "arm3")  # names inside assets/quad.xml


def ensure_gl_backend() -> str:
    """Choose EGL when nothing is chosen and there is no display (Linux); returns MUJOCO_GL as used."""
    headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if "MUJOCO_GL" not in os.environ and headless and sys.platform.startswith("linux"):
        os.environ["MUJOCO_GL"] = "egl"
        try:
            gl_context = importlib.import_module("mujoco.rendering.classic.gl_context")
        except ImportError:  # a mujoco without this module reads MUJOCO_GL some other way
            return "egl"
        if getattr(gl_context, "_MUJOCO_GL", "egl") != "egl":
            # mujoco chose its context class when it was imported, before this variable
            # existed: choose again (the module's selection logic, now seeing egl)
            importlib.reload(gl_context)
            if hasattr(gl_context, "GLContext"):
                mujoco.GLContext = gl_context.GLContext  # keep mujoco's top-level name in step
    return os.environ.get("MUJOCO_GL", "")


def offscreen_renderer(model: mujoco.MjModel, width: int, height: int, *, what: str,
                       error: type[Exception] = RuntimeError) -> mujoco.Renderer:
    """MuJoCo's offscreen renderer of `model` (pixels), the GL backend chosen first (`ensure_gl_backend`).
    Where no OpenGL context can be made, `error` saying that `what` needs one and naming the
    backends to set and the packages they need."""
    backend = ensure_gl_backend()
    try:
        return mujoco.Renderer(model, height=height, width=width)
    except (mujoco.FatalError, ImportError, AttributeError, OSError, RuntimeError) as e:
        raise error(
            f"{what} needs an OpenGL backend for offscreen rendering, and none could be "
            f"created (MUJOCO_GL={backend or '<unset>'!r}: {type(e).__name__}: {e}). "
            "Set MUJOCO_GL=egl (GPU, or Mesa's software EGL: apt-get install libegl1 libegl-mesa0 "
            "libgl1-mesa-dri libopengl0) or MUJOCO_GL=osmesa (apt-get install libosmesa6) in the "
            "environment before mujoco is imported."
        ) from e


class Renderer:
    """Offscreen frames of one `Simulator`'s worlds, with a camera that keeps both vehicles in view."""

    def __init__(self, scene: Scene, width: int, height: int):
        """width, height: pixels. Raises RuntimeError naming the backends when no OpenGL context can be made."""
        model = copy.copy(scene.model)  # tinted copy; the physics model is untouched
        for v, rgba in ((scene.leader, LEADER_RGBA), (scene.follower, FOLLOWER_RGBA)):
            for g in TINTED_GEOMS:
                model.geom_rgba[model.geom(f"{scene.vehicles[v]}/{g}").id] = rgba
        self.model = model
        self.leader, self.follower = scene.leader, scene.follower
        self._renderer = offscreen_renderer(model, width, height, what="render_mode='rgb_array'")
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.azimuth = 135.0  # deg
        self.camera.elevation = -20.0  # deg

    def render(
        self, data: mujoco.MjData, p_leader: np.ndarray, p_follower: np.ndarray, p_ref: np.ndarray
    ) -> np.ndarray:
        """(height, width, 3) uint8 of `data`; positions (3,) m, world frame, aim the camera and the marker."""
        mid = 0.5 * (p_leader + p_follower)
        dist = float(np.linalg.norm(p_follower - p_leader))
        cam = self.camera
        cam.lookat[:] = mid if np.all(np.isfinite(mid)) else 0.0
        cam.distance = 0.6 + 1.3 * (dist if math.isfinite(dist) else 1.0)  # m: both in a 45 deg view
        r = self._renderer
        r.update_scene(data, camera=cam)
        scn = r.scene
        if scn.ngeom < scn.maxgeom and np.all(np.isfinite(p_ref)):
            mujoco.mjv_initGeom(
                scn.geoms[scn.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, np.array([0.03, 0.0, 0.0]),
                np.asarray(p_ref, float), np.eye(3).ravel(), np.array(REF_RGBA, np.float32),
            )
            scn.ngeom += 1
        return r.render()

    def render_world(self, sim: Simulator, w: int) -> np.ndarray:
        """(height, width, 3) uint8 of world `w` of `sim` (true state; rendering changes nothing)."""
        pos = sim.true_states().pos[w]  # (V, 3) m
        ref = sim.reference(sim.t).pos[w, self.follower]
        return self.render(sim.physics.mjdata(w), pos[self.leader], pos[self.follower], ref)

    def close(self) -> None:
        self._renderer.close()
