"""`python -m experiments.replay LOG --video OUT.mp4` (`downwash-replay`): a flown log written as an mp4
headless, read back; every bad input one line and exit status 2 before any frame; the file written
atomically.

Rendering runs in this process through `downwash_envs.rendering.ensure_gl_backend` (EGL when headless);
a missing backend is a failure here, as in tests/test_video.py.
"""

import math
import sys
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from sim.logs import TRUTH_ARRAYS, FlightLog, load_log, save_log

ROOT = Path(__file__).resolve().parent.parent
W, H = 160, 120  # small frames: fast with software EGL
SECONDS = 0.4  # flown: 20 rows at 50 Hz
LEADER = np.array([0.0, 0.0, 2.5])


@pytest.fixture(scope="module")
def flight_log(tmp_path_factory):
    """A short flight flown by the simulator: a hovering leader, a follower on a lemniscate beneath."""
    from downwash_trajectories import Hover, Lemniscate, stack
    from sim.flight import fly
    from sim.scene import build_scene

    reference = stack([Hover(LEADER, n_worlds=1), Lemniscate(LEADER - [0.0, 0.0, 0.6], n_worlds=1)])
    (log,) = fly(build_scene(), reference, [0], SECONDS)
    path = tmp_path_factory.mktemp("replay") / "flight.npz"
    save_log(path, log)
    return path


@pytest.fixture
def headless(monkeypatch):
    """No display, and no window may open: the video renders offscreen."""
    import downwash_envs.viewer as viewer

    for k in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(k, raising=False)

    def refuse(*args, **kwargs):
        raise AssertionError("a window was opened")

    monkeypatch.setattr(viewer, "_launch", refuse)


def _read(path):
    return np.stack(list(iio.imiter(path, plugin="FFMPEG")))


def _leftovers(folder, keep):
    """Files in `folder` other than `keep` (a temporary file left behind shows here)."""
    return sorted(p.name for p in Path(folder).iterdir() if p.name not in keep)


def _video_args(log, out, *extra):
    return [str(log), "--video", str(out), "--width", str(W), "--height", str(H), *extra]


# ----------------------------------------------------------------------------- the video


def test_video_of_a_flown_log_headless(flight_log, headless, tmp_path, capsys):
    from experiments.replay import main

    out = tmp_path / "flight.mp4"
    n = main(_video_args(flight_log, out, "--fps", "25"))
    rows = len(load_log(flight_log))
    assert n == math.ceil(rows * 0.02 * 25 - 1e-9) == 10
    frames = _read(out)
    assert frames.shape == (n, H, W, 3)
    assert frames[:, H // 5:].std() > 10  # a scene, not a blank frame
    assert np.abs(frames[-1].astype(int) - frames[0].astype(int)).sum(-1).max() > 60  # the follower moved
    assert f"wrote {out} ({n} frames" in capsys.readouterr().out
    assert _leftovers(tmp_path, {"flight.mp4"}) == []


def test_speed_and_fps_set_the_frame_count(flight_log, headless, tmp_path):
    """At --speed s each frame advances s / fps s of flight: ceil(T dt fps / s) frames."""
    from experiments.replay import main

    rows = len(load_log(flight_log))
    for speed, fps in (("0.5", "20"), ("2", "30")):
        out = tmp_path / f"x{speed}.mp4"
        n = main(_video_args(flight_log, out, "--speed", speed, "--fps", fps))
        assert n == math.ceil(rows * 0.02 * float(fps) / float(speed) - 1e-9)
        assert _read(out).shape == (n, H, W, 3)


def test_video_frames_are_the_video_modules(flight_log, headless, tmp_path):
    """The replay renders through `downwash_envs.video` (no renderer of its own): the same log through
    `logs_video` gives the same frames, up to the label."""
    from downwash_envs.video import logs_video
    from experiments.replay import main
    from sim.scene import build_scene

    log = load_log(flight_log)
    main(_video_args(flight_log, tmp_path / "replay.mp4", "--quality", "10"))
    field = type("Field", (), {k: log.meta["field"][k] for k in ("width0", "width_slope")})()
    logs_video(tmp_path / "direct.mp4", build_scene(list(zip(log.meta["vehicles"], log.meta["roles"]))),
               {"flight": log}, field=field, width=W, height=H, quality=10)
    a, b = _read(tmp_path / "replay.mp4"), _read(tmp_path / "direct.mp4")
    assert a.shape == b.shape
    below_label = (slice(None), slice(H // 5, None))
    assert np.abs(a[below_label].astype(int) - b[below_label].astype(int)).mean() < 2.0


def test_real_flight_without_truth_shows_its_estimates(flight_log, headless, tmp_path):
    from experiments.replay import main

    log = load_log(flight_log)
    arrays = {k: v for k, v in log.arrays.items() if k not in TRUTH_ARRAYS}
    real = tmp_path / "real.npz"
    save_log(real, FlightLog(arrays, {**log.meta, "source": "a lab's flight"}))
    assert main(_video_args(real, tmp_path / "real.mp4")) == 10


def test_interrupted_video_leaves_no_file(flight_log, headless, tmp_path, monkeypatch):
    """Stopped mid-video: no partial mp4 at the path, no temporary file, and a video already there is kept."""
    import downwash_envs.video as video
    from experiments.replay import main

    frames = video.render_frames

    def stopped(*args, **kwargs):
        for i, f in enumerate(frames(*args, **kwargs)):
            if i == 3:
                raise KeyboardInterrupt
            yield f

    monkeypatch.setattr(video, "render_frames", stopped)
    out = tmp_path / "flight.mp4"
    with pytest.raises(KeyboardInterrupt):
        main(_video_args(flight_log, out))
    assert _leftovers(tmp_path, set()) == []
    out.write_bytes(b"the previous video")
    with pytest.raises(KeyboardInterrupt):
        main(_video_args(flight_log, out))
    assert out.read_bytes() == b"the previous video" and _leftovers(tmp_path, {"flight.mp4"}) == []


# ----------------------------------------------------------------------------- bad input


@pytest.fixture
def no_rendering(monkeypatch, headless):
    """Rendering or writing anything fails the test: bad input must stop before."""
    import downwash_envs.video as video

    def refuse(*args, **kwargs):
        raise AssertionError("rendering started")

    monkeypatch.setattr(video, "TiledRenderer", refuse)
    monkeypatch.setattr(video, "write_video", refuse)


def _fails(argv, capsys, *needles):
    from experiments.replay import main

    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("python -m experiments.replay: error: "), err
    for needle in needles:
        assert needle in err, err


def test_bad_logs_are_one_line(flight_log, no_rendering, tmp_path, capsys):
    text = tmp_path / "notes.npz"
    text.write_text("hello")
    foreign = tmp_path / "other.npz"
    np.savez(foreign, x=np.zeros(3))
    out = tmp_path / "out.mp4"
    _fails(_video_args(tmp_path / "missing.npz", out), capsys, "argument PATH", "missing.npz", "no such log file")
    _fails(_video_args(text, out), capsys, "argument PATH", "notes.npz", "truncated or foreign")
    _fails(_video_args(foreign, out), capsys, "argument PATH", "other.npz", "not a flight log")
    assert not out.exists()


def test_bad_video_paths_are_one_line_before_the_log_is_read(flight_log, no_rendering, tmp_path, capsys,
                                                              monkeypatch):
    import sim.logs

    def unread(*args, **kwargs):
        raise AssertionError("the log was read before the output was checked")

    monkeypatch.setattr(sim.logs, "load_log", unread)
    _fails(_video_args(flight_log, tmp_path / "nowhere" / "out.mp4"), capsys, "argument --video", "nowhere",
           "does not exist")
    assert not (tmp_path / "nowhere").exists()
    _fails(_video_args(flight_log, tmp_path / "out.avi"), capsys, "argument --video", "out.avi", ".mp4")
    _fails(_video_args(flight_log, tmp_path / "out"), capsys, "argument --video", ".mp4")
    (tmp_path / "folder.mp4").mkdir()
    _fails(_video_args(flight_log, tmp_path / "folder.mp4"), capsys, "argument --video", "is a folder")
    _fails(_video_args(flight_log, tmp_path / "out.mp4", "--loop"), capsys, "argument --loop")
    assert _leftovers(tmp_path, {"folder.mp4"}) == []


@pytest.mark.parametrize("flag, value", [("--fps", "0"), ("--fps", "121"), ("--fps", "nan"), ("--width", "8"),
                                         ("--height", "5000"), ("--width", "1.5"), ("--quality", "11"),
                                         ("--speed", "0")])
def test_bad_video_options_name_the_flag(flight_log, no_rendering, tmp_path, capsys, flag, value):
    _fails(_video_args(flight_log, tmp_path / "out.mp4", flag, value), capsys, f"argument {flag}", repr(value))
    assert not (tmp_path / "out.mp4").exists()


def test_video_extra_missing_says_what_to_install(flight_log, no_rendering, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # `import imageio_ffmpeg` raises ImportError
    _fails(_video_args(flight_log, tmp_path / "out.mp4"), capsys, "argument --video", 'pip install -e ".[video]"')
    assert not (tmp_path / "out.mp4").exists()


# ----------------------------------------------------------------------------- the console script


def test_downwash_replay_resolves_and_exits_0_after_a_video(flight_log, headless, tmp_path, monkeypatch):
    from experiments.replay import cli

    value = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]["downwash-replay"]
    entry = EntryPoint("downwash-replay", value, "console_scripts").load()
    assert entry is cli
    out = tmp_path / "flight.mp4"
    monkeypatch.setattr(sys, "argv", ["downwash-replay", *_video_args(flight_log, out)])
    assert entry() is None  # sys.exit(None): exit status 0
    assert _read(out).shape[1:] == (H, W, 3)
    monkeypatch.setattr(sys, "argv", ["downwash-replay", str(tmp_path / "missing.npz"), "--video", str(out)])
    with pytest.raises(SystemExit) as e:
        entry()
    assert e.value.code == 2
