"""Regenerate the docs' picture: a short flight drawn by the project's own video code.

    python docs/make_figures.py            # writes docs/assets/flight.png

Flies the lemniscate experiment (the follower 0.6 m beneath a hovering leader) for a few
seconds under two conditions on one seed, the LQR with no model (`baseline`) and the LQR
compensating with the true mean field (`oracle`), as one batch of worlds, and renders
one frame of both side by side with `downwash_envs.video.render_frames`: the leader in
orange with its wake drawn, the follower in cyan, the reference path in green. No model
is trained, so this takes seconds. Needs an OpenGL backend for offscreen rendering (on a
headless Linux machine, Mesa's EGL; see the install page).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "assets" / "flight.png"

CONDITIONS = ("baseline", "oracle")
SEPARATION = 0.6  # m, the lemniscate experiment's
DURATION = 20.0  # s of flight: one period of the lemniscate, so its whole path is drawn
SHOW_AT = 5.0  # s: the frame shown (the follower close to the point beneath the leader)
TILE = (480, 360)  # pixels, width x height of one tile


def fly_flight():
    """The logs of one seed per condition, and the scene."""
    from downwash.conditions import fly_conditions
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, make_reference, stack
    from sim.field import DownwashField
    from sim.scene import build_scene

    scene = build_scene()
    W = len(CONDITIONS)
    leader = np.asarray(LEADER_POSITION, float)
    follower = make_reference("lemniscate", leader - np.array([0.0, 0.0, SEPARATION]), W)
    reference = stack([Hover(leader, n_worlds=W), follower])
    logs = fly_conditions(scene, CONDITIONS, reference, [0], DURATION, DownwashField(), {})
    return scene, {c: clogs[0] for c, clogs in logs.items()}


def render(out: Path = OUT) -> Path:
    from PIL import Image

    from downwash_envs.video import Trajectory, render_frames

    scene, logs = fly_flight()
    trajectories = [Trajectory(c, np.asarray(log["pos"]), np.asarray(log["quat"])) for c, log in logs.items()]
    first = next(iter(logs.values()))
    t = np.asarray(first["t"], float)
    dt = float(np.median(np.diff(t)))
    fps = 1.0 / dt  # one frame per log row, so frame k is row k
    frames = render_frames(scene, trajectories, np.asarray(first["ref_pos"]), dt=dt, fps=fps,
                           width=TILE[0], height=TILE[1])
    k = int(round(SHOW_AT / dt))
    for i, frame in enumerate(frames):
        if i == k:
            break
    else:
        raise RuntimeError(f"the flight is shorter than {SHOW_AT} s")
    frames.close()  # release the renderer
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(frame).save(out, optimize=True)
    return out


def main() -> None:
    path = render(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
