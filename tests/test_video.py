"""Videos of flights (`downwash_envs.video`): frame timing, tiles, the drawn wake, the mp4 read back,
bad inputs, atomic writes, and `--video` on the tracking experiments.

Rendering runs in this process through `downwash_envs.rendering.ensure_gl_backend` (EGL when headless);
a missing backend is a failure here, as in tests/test_env.py.
"""

import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError
from downwash_envs.video import CameraView, TiledRenderer, Trajectory, frame_rows, logs_video, render_frames, wake_width, \
    write_conditions_video, write_video
from sim.field import DownwashField
from sim.scene import build_scene

ROOT = Path(__file__).resolve().parent.parent
W, H = 160, 120  # small tiles: fast with software EGL
LEADER = np.array([0.0, 0.0, 2.5])


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _flight(T=50, dt=0.02, dz=0.0, phase=0.0):
    """(pos (T, 2, 3), quat (T, 2, 4), ref (T, 2, 3)): a hovering leader and a follower on a
    figure-eight 0.6 m below it (dz: an offset from its reference)."""
    t = np.arange(T) * dt
    ref = np.zeros((T, 2, 3))
    ref[:, 0] = LEADER
    ref[:, 1] = np.stack([np.sin(t + phase), 0.5 * np.sin(2 * (t + phase)), np.full(T, 1.9)], -1)
    pos = ref.copy()
    pos[:, 1, 2] += dz
    quat = np.zeros((T, 2, 4))
    quat[..., 0] = 1.0
    return pos, quat, ref


def _read(path):
    return np.stack(list(iio.imiter(path, plugin="FFMPEG")))


def _tile_changes(frames):
    """(n_frames,): pixels below the labels that differ clearly between the first two tiles."""
    body = frames[:, H // 5:].astype(int)
    return (np.abs(body[:, :, :W] - body[:, :, W:2 * W]).sum(-1) > 60).sum(axis=(1, 2))


# ----------------------------------------------------------------------------- timing


def test_frame_rows_analytic():
    assert frame_rows(50, 0.02, 25).tolist() == list(range(0, 50, 2))  # 1 s at 50 Hz: every other row
    assert len(frame_rows(50, 0.02, 30)) == 30 and len(frame_rows(51, 0.02, 25)) == 26
    assert frame_rows(1, 0.02, 25).tolist() == [0]


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 3000), st.sampled_from([0.01, 0.02, 0.04, 1 / 45]), st.floats(1.0, 120.0))
def test_frame_rows_cover_the_span(n_rows, dt, fps):
    """ceil(T dt fps) frames; frame j shows the last row at or before j / fps."""
    rows = frame_rows(n_rows, dt, fps)
    assert len(rows) == max(1, math.ceil(n_rows * dt * fps - 1e-9))
    assert np.all(np.diff(rows) >= 0) and rows[0] == 0 and rows[-1] <= n_rows - 1
    j = np.arange(len(rows))
    assert np.all(rows * dt <= j / fps + 1e-9)
    inner = rows < n_rows - 1
    assert np.all(j[inner] / fps < (rows[inner] + 1) * dt + 1e-9)


# ----------------------------------------------------------------------------- the mp4


def test_video_frames_size_and_content(scene, tmp_path):
    """Two conditions, 1 s of 50 Hz logs at 25 fps: 25 frames of two tiles side by side, not blank;
    the tiles differ where the flights differ and agree where they agree."""
    pos, quat, ref = _flight()
    low, _, _ = _flight(dz=-0.25)
    path = tmp_path / "two.mp4"
    n = write_conditions_video(path, scene, [Trajectory("baseline", pos, quat), Trajectory("oracle", low, quat)],
                               ref, dt=0.02, fps=25, width=W, height=H)
    frames = _read(path)
    assert n == len(frames) == 25
    assert iio.improps(path, plugin="FFMPEG").shape[1:] == (H, 2 * W, 3)
    assert frames.shape[1:] == (H, 2 * W, 3) and frames.dtype == np.uint8
    assert all(f.std() > 10.0 for f in frames)  # not blank
    assert _tile_changes(frames).min() > 30  # pixels that differ clearly, in every frame

    same = tmp_path / "same.mp4"
    write_conditions_video(same, scene, [Trajectory("a", pos, quat), Trajectory("b", pos, quat)], ref,
                           width=W, height=H)
    assert _tile_changes(_read(same)).max() < 5  # compression noise only
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_a_shorter_flight_holds_its_last_row_and_odd_sizes_are_padded(scene, tmp_path):
    pos, quat, ref = _flight(T=50)
    path = tmp_path / "odd.mp4"
    n = write_conditions_video(path, scene, [Trajectory("full", pos, quat), Trajectory("ended", pos[:20], quat[:20])],
                               ref, fps=10, width=81, height=61)
    frames = _read(path)
    assert n == len(frames) == 10  # from the longest flight
    assert frames.shape[1:] == (62, 162, 3)  # 2 x 81 by 61, padded to even sizes


def test_tiles_are_laid_out_in_rows_of_columns(scene):
    with TiledRenderer(scene, 5, 16, 16, columns=4) as r:
        f = r.frame([np.full((16, 16, 3), 100 + i, np.uint8) for i in range(5)])
    assert f.shape == (32, 64, 3)
    for i in range(5):
        row, col = divmod(i, 4)
        assert np.all(f[16 * row:16 * (row + 1), 16 * col:16 * (col + 1)] == 100 + i)
    assert len(np.unique(f[16:, 16:])) == 1 and f[16:, 16:].max() < 100  # empty cells


def test_logs_video_reads_flight_logs(scene, tmp_path):
    """From `sim.logs.FlightLog`-like records; a flight without the field has no wake drawn."""
    from sim.logs import FlightLog

    pos, quat, ref = _flight(T=25)
    t = np.arange(25) * 0.02
    logs = {c: FlightLog({"t": t, "pos": pos, "quat": quat, "ref_pos": ref}, {"field_enabled": c != "off"})
            for c in ("on", "off")}
    path = tmp_path / "logs.mp4"
    assert logs_video(path, scene, logs, fps=20, width=W, height=H) == len(_read(path)) == 10


# ----------------------------------------------------------------------------- the wake


def _orange_centroid(img):
    r, g, b = (img[..., i].astype(int) for i in range(3))
    ys, xs = np.nonzero((r > 150) & (g > 60) & (g < 170) & (b < 70))  # the leader's tinted hull
    assert len(ys) > 5
    return ys.mean(), xs.mean()


@pytest.mark.parametrize("tilt", [0.0, 0.5, -0.5])
def test_the_wake_is_drawn_below_the_leader_along_its_axis(scene, tilt):
    """The wake geoms change the frame only below the leader, and follow its body -z axis: a
    leader pitched about +y (seen from -y, image right = +x) casts its wake to the image's left."""
    pos, quat, _ = _flight(T=1)
    q = np.array([math.cos(tilt / 2), 0.0, math.sin(tilt / 2), 0.0])  # rotation about y by `tilt`
    quat[0, 0] = q
    with TiledRenderer(scene, 1, 320, 240) as r:
        r.set_view(CameraView((0.0, 0.0, 2.0), 4.0, azimuth=90.0, elevation=0.0))
        plain = r.tile(pos[0], quat[0], draw_wake=False)
        wake = r.tile(pos[0], quat[0], draw_wake=True)
    changed = np.abs(wake.astype(int) - plain.astype(int)).sum(-1) > 6
    assert changed.sum() > 500
    ys, xs = np.nonzero(changed)
    ly, lx = _orange_centroid(plain)
    assert ys.mean() > ly + 20  # below the leader
    if tilt == 0.0:
        assert abs(xs.mean() - lx) < 8
    else:  # the wake leans against the tilt: tilt > 0 puts its axis toward -x
        assert np.sign(lx - xs.mean()) == np.sign(tilt) and abs(xs.mean() - lx) > 15


def test_wake_off_and_no_wake_vehicles_render_no_wake(scene):
    pos, quat, _ = _flight(T=1)
    view = CameraView((0.0, 0.0, 2.0), 4.0, azimuth=90.0, elevation=0.0)
    with TiledRenderer(scene, 1, W, H) as r:
        r.set_view(view)
        plain, wake = r.tile(pos[0], quat[0], draw_wake=False), r.tile(pos[0], quat[0])
    with TiledRenderer(scene, 1, W, H, wake_vehicles=()) as r:
        r.set_view(view)
        none = r.tile(pos[0], quat[0])
    assert np.array_equal(none, plain) and not np.array_equal(wake, plain)
    # the tile of a flight flown without the field (wake_on=False) matches the one without wake geoms
    frames = render_frames(scene, [Trajectory("off", pos, quat, wake_on=False), Trajectory("on", pos, quat)],
                           width=W, height=H, fps=25)
    f = next(frames)[H // 5:].astype(int)
    assert np.abs(f[:, :W] - f[:, W:]).sum() > 1000


def test_every_wake_vehicle_of_a_larger_scene_casts_a_wake_of_the_fields_width():
    """N vehicles: a wake for each vehicle asked for, and a wider field draws a wider wake."""
    scene3 = build_scene(["a", "b", "c"])
    pos = np.array([[-0.8, 0.0, 2.5], [0.8, 0.0, 2.5], [0.0, 0.0, 1.6]])
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    view = CameraView((0.0, 0.0, 1.8), 5.0, azimuth=90.0, elevation=0.0)
    changed = {}
    for key, kwargs in {"one": dict(wake_vehicles=[0]), "two": dict(wake_vehicles=[0, 1]),
                        "wide": dict(wake_vehicles=[0], wake=wake_width(DownwashField(width0=0.2)))}.items():
        with TiledRenderer(scene3, 1, W, H, **kwargs) as r:
            r.set_view(view)
            diff = r.tile(pos, quat).astype(int) - r.tile(pos, quat, draw_wake=False).astype(int)
        changed[key] = np.abs(diff).sum(-1) > 6
    one, two = changed["one"], changed["two"]
    assert two.sum() > 1.6 * one.sum() and np.nonzero(one)[1].mean() < W / 2 < np.nonzero(two & ~one)[1].mean()
    assert changed["wide"].sum() > 1.3 * one.sum()
    assert wake_width(None) == wake_width(object()) == (DownwashField().width0, DownwashField().width_slope)


def test_tiles_larger_than_the_scenes_buffer_leave_the_physics_model_untouched(scene):
    """The renderer works on a copy: a bigger offscreen buffer, no shadows, a wider floor."""
    before = (scene.model.geom_size.copy(), scene.model.vis.global_.offwidth, scene.model.vis.quality.shadowsize)
    pos, quat, _ = _flight(T=1)
    with TiledRenderer(scene, 1, 700, 500) as r:
        img = r.tile(pos[0], quat[0], label="big")
    assert img.shape == (500, 700, 3) and img.std() > 10.0
    after = (scene.model.geom_size, scene.model.vis.global_.offwidth, scene.model.vis.quality.shadowsize)
    assert np.array_equal(before[0], after[0]) and before[1:] == after[1:]


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_config_error(scene, tmp_path):
    pos, quat, ref = _flight(T=10)
    ok = [Trajectory("a", pos, quat)]
    out = tmp_path / "v.mp4"
    cases = [
        (dict(trajectories=[]), "one or more conditions"),
        (dict(trajectories=[Trajectory("a", pos[..., :2], quat)]), r"pos must be \(T, 2, 3\)"),
        (dict(trajectories=[Trajectory("a", pos, quat[:5])]), "quat must be"),
        (dict(trajectories=[Trajectory("a", pos[:, :1], quat[:, :1])]), "2 vehicles"),
        (dict(trajectories=[Trajectory("a", pos[:0], quat[:0])]), "empty"),
        (dict(trajectories=[Trajectory("a", np.full_like(pos, np.nan), quat)]), "empty"),
        (dict(trajectories=[Trajectory("a", pos, 0 * quat)]), "zero length"),
        (dict(fps=0), r"fps.*\[1, 120\]"),
        (dict(fps="fast"), "fps"),
        (dict(dt=-0.02), "dt"),
        (dict(reference=ref[:, :1]), "reference"),
        (dict(reference=np.where(np.arange(10)[:, None, None] == 3, np.nan, ref)), "reference.*finite"),
        (dict(width=8), "width"),
        (dict(wake_vehicles=[5]), "wake_vehicles"),
        (dict(path=tmp_path / "v.avi"), r"\.mp4"),
        (dict(path=tmp_path), r"\.mp4|folder"),
    ]
    for kwargs, match in cases:
        args = dict(path=out, scene=scene, trajectories=ok, reference=ref, dt=0.02, fps=25, width=W, height=H)
        args.update(kwargs)
        with pytest.raises(ConfigError, match=match):
            write_conditions_video(**args)
    assert not out.exists()


def test_write_video_is_atomic_and_checks_frames(tmp_path):
    path = tmp_path / "v.mp4"
    path.write_bytes(b"old")

    def frames(n_good):
        for _ in range(n_good):
            yield np.full((32, 48, 3), 128, np.uint8)
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError, match="killed"):
        write_video(path, frames(3))
    assert path.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [path]  # untouched, no temporary
    with pytest.raises(ConfigError, match="even"):
        write_video(path, [np.zeros((31, 48, 3), np.uint8)])
    with pytest.raises(ConfigError, match="differs"):
        write_video(path, [np.zeros((32, 48, 3), np.uint8), np.zeros((32, 46, 3), np.uint8)])
    with pytest.raises(ConfigError, match="no frames|none"):
        write_video(path, [])
    assert path.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [path]
    assert write_video(path, [np.full((32, 48, 3), 200, np.uint8)] * 5, fps=10) == 5 and len(_read(path)) == 5


def _python(code, env_vars=None, cwd=ROOT):
    env = dict(os.environ, **(env_vars or {}))
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


# ----------------------------------------------------------------------------- --video on the experiments


def test_tracking_imports_no_writer_without_video_and_checks_video_before_flying(tmp_path):
    """The default run loads neither imageio nor downwash_envs.video; a bad --video path, or no OpenGL
    backend (MUJOCO_GL=disable), is a ConfigError before any flight."""
    proc = _python("""
        import json, sys
        from pathlib import Path
        import experiments.tracking as tracking
        from downwash_core.errors import ConfigError
        loaded = sorted(m for m in ("imageio", "downwash_envs.video") if m in sys.modules)
        errors = []
        for video in ("v.avi", "v.mp4"):
            try:
                tracking.main("lemniscate", ["--quick", "--conditions", "baseline", "--out", "lem", "--video", video])
            except ConfigError as e:
                errors.append(str(e))
        print(json.dumps({"loaded": loaded, "errors": errors, "flew": Path("lem").exists()}))
    """, {"MUJOCO_GL": "disable"}, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-2000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["loaded"] == [] and not res["flew"] and len(res["errors"]) == 2
    assert ".mp4" in res["errors"][0] and "v.avi" in res["errors"][0]
    assert all(k in res["errors"][1] for k in ("OpenGL", "MUJOCO_GL=egl", "MUJOCO_GL=osmesa"))


def test_lemniscate_video_smoke(tmp_path):
    """`--video` on the lemniscate writes a playable mp4: duration x fps frames, one tile per condition."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    run = ["experiments.lemniscate", "--quick", "--duration", "1", "--conditions", "baseline,no_downwash",
           "--out", "lem", "--video", "v.mp4"]
    proc = subprocess.run([sys.executable, "-m", *run], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    frames = _read(tmp_path / "v.mp4")
    assert frames.shape == (25, 240, 2 * 320, 3)  # 1 s at 25 fps; tiles 320 x 240
    assert all(f.std() > 10.0 for f in frames)
    assert (tmp_path / "lem" / "results.json").is_file() and "wrote v.mp4 (25 frames" in proc.stdout
