"""MuJoCo's interactive viewer: the envs' ``render_mode="human"`` and flight replays.

`Viewer` opens MuJoCo's passive viewer (`mujoco.viewer.launch_passive`) on a tinted copy of
a scene's model (leaders orange, followers cyan, as in the videos) with a state of its own:
each `show` copies the vehicles' poses in, draws the leaders' wakes, the reference paths and
the current reference points as user geoms (`viewer.user_scn`, the same geometry as
`downwash_envs.video`) and syncs the window. The viewer never writes to the physics: a
mouse perturbation in the window moves nothing in the simulation.

In the env (``render_mode="human"``, see `downwash_envs.base`) the window is opened at the
first `render()`, synced after every `reset()` and `step()` as Gymnasium's MuJoCo envs do,
paced to real time (one env step per control period; no waiting once the window is
closed) and closed by `env.close()`. A vector env shows its world 0. The window first
frames the leader and the vehicle farthest from it (as the offscreen camera) and marks every
follower's current reference; the follower env draws the leader's wake, the swarm env
(`downwash_envs.swarm`) every vehicle's, since there every vehicle's wake acts on the others.

A window needs a display. On Linux without one (``DISPLAY`` and ``WAYLAND_DISPLAY`` unset)
`check_display` raises ConfigError before any work, saying what to do instead: run where
there is a display, under a virtual one (``xvfb-run -a python ...``), or render offscreen
(``render_mode="rgb_array"``, or the experiments' ``--video`` mp4). On macOS the passive
viewer runs only under ``mjpython``.
"""

from __future__ import annotations

import functools
import math
import os
import sys
import threading
import time
from typing import Any, Sequence

import mujoco
import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.roles import Role
from downwash_envs.rendering import REF_RGBA
from downwash_envs.video_tiles import (  # add_wake: the viewer draws the wake as the videos do
    PATH_RGBA, REF_RADIUS, CameraView, add_geom, add_line, add_wake, decorated, wake_width,
)
from sim.scene import Scene
from sim.simulator import Simulator

__all__ = ["HUMAN", "DISPLAY_VARIABLES", "OPEN_TIMEOUT", "check_display", "add_wake", "Viewer", "render_on_step"]

HUMAN = "human"  # the Gymnasium render mode that opens the viewer
DISPLAY_VARIABLES = ("DISPLAY", "WAYLAND_DISPLAY")  # either one set means a display on Linux
OPEN_TIMEOUT = 30.0  # s to wait for the window: launch_passive waits forever when its window thread fails
_LINE_PX = 2.0  # reference path line width, pixels
_ENV_CAMERA = (135.0, -20.0)  # deg azimuth and elevation of the env's first view (as downwash_envs.rendering)


def check_display(what: str) -> None:
    """ConfigError naming `what` and the ways out when MuJoCo's viewer cannot open a window here:
    Linux without ``DISPLAY``/``WAYLAND_DISPLAY``, or macOS outside ``mjpython``. Cheap: no window is made."""
    if sys.platform.startswith("linux") and not any(os.environ.get(k) for k in DISPLAY_VARIABLES):
        raise ConfigError(
            f"{what} opens MuJoCo's interactive viewer, which needs a display, and neither DISPLAY nor "
            "WAYLAND_DISPLAY is set. Run it where there is a display, or under a virtual one "
            "(xvfb-run -a python ...; apt-get install xvfb), or render offscreen instead: "
            "render_mode='rgb_array' for frames, or an experiment's --video PATH.mp4 for a video."
        )
    if sys.platform == "darwin":
        import mujoco.viewer

        if getattr(mujoco.viewer, "_MJPYTHON", None) is None:
            raise ConfigError(f"{what} opens MuJoCo's passive viewer, which on macOS runs only under mjpython: "
                              "run the script with mjpython instead of python, or use render_mode='rgb_array'")


class Viewer:
    """A passive MuJoCo viewer of `scene`'s vehicles, decorated as the videos are; see the module docstring.

    wake: (width0 m, width_slope -) of the drawn wakes (default `wake_width()`); wake_vehicles:
    the indices whose wake is drawn (default: the scene's leaders). ConfigError, before anything
    opens, when there is no display; ConfigError when the window does not open within `OPEN_TIMEOUT`.
    """

    def __init__(self, scene: Scene, wake: tuple[float, float] | None = None,
                 wake_vehicles: Sequence[int] | None = None, what: str = "the viewer"):
        check_display(what)
        model, self.wake_vehicles, self.wake = decorated(scene, wake_vehicles, wake)
        self.scene = scene
        self.model, self.data = model, mujoco.MjData(model)
        self._last_sync: float | None = None
        self._handle, self._threads = _launch(model, self.data, what)

    @classmethod
    def of_simulator(cls, sim: Simulator, wake_vehicles: Sequence[int] | None = None,
                     what: str = "the viewer") -> "Viewer":
        """A viewer of `sim`'s scene whose wakes have the width of `sim`'s field (`wake_width`);
        wake_vehicles as in the constructor (default: the leaders)."""
        return cls(sim.scene, wake=wake_width(sim.field), wake_vehicles=wake_vehicles, what=what)

    def is_running(self) -> bool:
        """False once the window is closed (by the user or by `close`)."""
        return self._handle is not None and self._handle.is_running()

    def set_view(self, view: CameraView) -> None:
        """Point the window's free camera (the user can move it afterwards)."""
        if self._handle is None:
            return
        with self._handle.lock():
            cam = self._handle.cam
            cam.type = mujoco.mjtCamera.mjCAMERA_FREE
            cam.lookat[:] = view.lookat
            cam.distance, cam.azimuth, cam.elevation = view.distance, view.azimuth, view.elevation

    def show(self, pos: np.ndarray, quat: np.ndarray, ref_now: np.ndarray | None = None,
             paths: Sequence[np.ndarray] = (), draw_wake: bool = True, text: str = "") -> bool:
        """Show the vehicles at pos (V, 3) m with attitudes quat (V, 4) (w, x, y, z); ref_now (P, 3) m
        points marked now; paths (N, 3) m polylines; `text` in the top-left corner. Returns `is_running()`."""
        m, d = self.model, self.data
        d.qpos[:] = m.qpos0
        for v in range(self.scene.n_vehicles):
            a = int(self.scene.qpos_adr[v])
            d.qpos[a:a + 3] = pos[v]
            d.qpos[a + 3:a + 7] = quat[v]
        return self._sync(ref_now, paths, draw_wake, text)

    def show_data(self, src: mujoco.MjData, ref_now: np.ndarray | None = None, paths: Sequence[np.ndarray] = (),
                  draw_wake: bool = True, text: str = "") -> bool:
        """As `show`, the poses copied from `src` (an MjData of the scene's model, e.g. a simulator world's)."""
        self.data.qpos[:] = src.qpos
        return self._sync(ref_now, paths, draw_wake, text)

    def show_world(self, sim: Simulator, w: int, pace: float = 0.0) -> bool:
        """Show world `w` of `sim` (true state, every follower's current reference, the wakes when the
        world flies with downwash), at most one sync per `pace` s (0: no waiting). Returns `is_running()`."""
        scene = self.scene
        followers = [v for v, r in enumerate(scene.roles) if r == Role.FOLLOWER]
        ref = sim.reference(sim.t).pos[w, followers]  # (F, 3) m
        if self._last_sync is None and self.is_running():
            self.set_view(_first_view(sim.true_states().pos[w], scene.leader))
        self.wait(pace)
        ref = ref[np.all(np.isfinite(ref), axis=-1)]
        ref_now = ref if len(ref) else None
        return self.show_data(sim.physics.mjdata(w), ref_now, (), bool(sim.field_enabled[w]), f"t = {sim.t[w]:.2f} s")

    def wait(self, period: float) -> None:
        """Sleep until `period` s after the last sync (real-time pacing); no wait once the window is closed."""
        if period > 0 and self._last_sync is not None and self.is_running():
            delay = self._last_sync + period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)

    def _sync(self, ref_now: np.ndarray | None, paths: Sequence[np.ndarray], draw_wake: bool, text: str) -> bool:
        m, d = self.model, self.data
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        h = self._handle
        if h is None or not h.is_running():
            return False
        with h.lock():
            scn = h.user_scn
            scn.ngeom = 0
            if draw_wake:
                for v in self.wake_vehicles:
                    b = self.scene.body_ids[v]
                    add_wake(scn, d.xpos[b].copy(), d.xmat[b].reshape(3, 3).copy(), self.wake)
            for path in paths:
                for a, b in zip(path[:-1], path[1:]):
                    add_line(scn, a, b, _LINE_PX, PATH_RGBA)
            if ref_now is not None:
                for p in np.asarray(ref_now, float).reshape(-1, 3):
                    add_geom(scn, mujoco.mjtGeom.mjGEOM_SPHERE, (REF_RADIUS, 0, 0), p, np.eye(3), REF_RGBA)
        if text and hasattr(h, "set_texts"):
            h.set_texts((None, None, text, None))
        h.sync()
        self._last_sync = time.perf_counter()
        return h.is_running()

    def close(self) -> None:
        """Close the window and wait for its thread (an interpreter that exits while the window is
        being torn down can crash)."""
        h, self._handle = self._handle, None
        if h is not None:
            h.close()
        for t in self._threads:
            t.join(timeout=10.0)
        self._threads = []

    def __enter__(self) -> "Viewer":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _first_view(pos: np.ndarray, leader: int) -> CameraView:
    """The env's first view, as its offscreen camera: the midpoint of the leader and the vehicle farthest
    from it (pos (V, 3) m), from a distance that grows with their separation."""
    p_l = pos[leader]
    dist = np.linalg.norm(pos - p_l, axis=-1)
    far = int(np.nanargmax(dist)) if np.isfinite(dist).any() else leader
    mid, d = 0.5 * (p_l + pos[far]), float(dist[far])
    return CameraView(tuple(float(x) for x in (mid if np.all(np.isfinite(mid)) else np.zeros(3))),
                      0.6 + 1.3 * (d if math.isfinite(d) else 1.0), *_ENV_CAMERA)


def _launch(model: mujoco.MjModel, data: mujoco.MjData, what: str) -> tuple[Any, list[threading.Thread]]:
    """(the passive viewer's handle, the threads it started). launch_passive blocks until its window
    thread hands back the handle, and forever when that thread fails (no GL, an unreachable X server):
    it runs in a helper thread here so that a failure becomes a ConfigError after `OPEN_TIMEOUT`."""
    import mujoco.viewer

    before = set(threading.enumerate())
    result: dict[str, Any] = {}

    def launch() -> None:
        try:
            result["handle"] = mujoco.viewer.launch_passive(model, data, show_left_ui=False, show_right_ui=False)
        except BaseException as e:  # handed to the caller below
            result["error"] = e

    helper = threading.Thread(target=launch, name="downwash-viewer-launch", daemon=True)
    helper.start()
    helper.join(OPEN_TIMEOUT)
    if "handle" not in result:
        e = result.get("error")
        why = f"{type(e).__name__}: {e}" if e is not None else f"no window after {OPEN_TIMEOUT:g} s"
        raise ConfigError(
            f"{what}: MuJoCo's viewer could not open a window on display "
            f"{os.environ.get('DISPLAY') or os.environ.get('WAYLAND_DISPLAY') or '<none>'} ({why}). Check that the "
            "display is reachable and has OpenGL (glxinfo), or render offscreen: render_mode='rgb_array', or an "
            "experiment's --video PATH.mp4."
        ) from e
    new = [t for t in threading.enumerate() if t not in before and t is not helper]
    window = [t for t in new if "_launch_internal" in t.name]  # Python names a thread after its target
    return result["handle"], window or new


def render_on_step(env: Any) -> None:
    """Make `env.reset` and `env.step` call `env.render()` after they return, as Gymnasium's MuJoCo envs
    do in human mode (bound on this instance only: envs of other render modes are untouched)."""
    for name in ("reset", "step"):
        method = getattr(env, name)

        @functools.wraps(method)
        def rendered(*args: Any, _method: Any = method, **kwargs: Any) -> Any:
            out = _method(*args, **kwargs)
            env.render()
            return out

        setattr(env, name, rendered)
