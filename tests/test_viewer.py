"""MuJoCo's interactive viewer: render_mode="human" (the follower and swarm envs) and `python -m experiments.replay`.

Headless: asking for a window without a display fails before any work with a ConfigError
that says what to do, and bad replay arguments fail before any window. A stand-in for the
passive viewer's handle (`FakeWindow`) checks what the envs draw and sync without a display.
Under Xvfb (when `xvfb-run` is installed) a subprocess opens the passive viewer for a few
env steps, of the follower env and of the swarm env, and a short replay.
"""

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from sim.logs import ARRAY_SPECS, FlightLog, save_log

ROOT = Path(__file__).resolve().parent.parent
LINUX = sys.platform.startswith("linux")


def _synthetic_log(T=30, leader=(0.0, 0.0, 2.5), sep=0.6, meta=None):
    """A two-vehicle log: a hovering leader, a follower circling `sep` m below it, level attitudes."""
    t = np.arange(T) * 0.02
    arrays = {}
    for name, (trail, _) in ARRAY_SPECS.items():
        arrays[name] = np.zeros((T,) + tuple(2 if d == "V" else d for d in trail))
    arrays["t"] = t
    pos = np.zeros((T, 2, 3))
    pos[:, 0] = leader
    pos[:, 1] = np.asarray(leader) + np.stack([0.2 * np.cos(t), 0.2 * np.sin(t), np.full(T, -sep)], axis=-1)
    arrays["pos"] = arrays["ref_pos"] = pos
    arrays["quat"] = arrays["quat_est"] = np.tile([1.0, 0.0, 0.0, 0.0], (T, 2, 1))
    base = {"vehicles": ["leader", "follower"], "roles": ["leader", "follower"], "status": 0,
            "field": {"width0": 0.1, "width_slope": 0.12}, "field_enabled": True}
    return FlightLog(arrays, {**base, **(meta or {})})


@pytest.fixture
def headless(monkeypatch):
    for k in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(k, raising=False)


@pytest.fixture
def no_window(monkeypatch):
    """Any attempt to open a window fails the test (a fake display: the checks must stop first)."""
    import downwash_envs.viewer as viewer

    monkeypatch.setenv("DISPLAY", ":12345")

    def refuse(*args, **kwargs):
        raise AssertionError("a window was opened")

    monkeypatch.setattr(viewer, "_launch", refuse)


@pytest.fixture
def human_env(monkeypatch):
    """DownwashFollowerEnv (and the vector env) with "human" among their render modes: the classes list
    it once their metadata does; until then it is added here, as the class attribute gym.make reads."""
    from downwash_envs.follower import DownwashFollowerEnv, DownwashFollowerVectorEnv

    for cls in (DownwashFollowerEnv, DownwashFollowerVectorEnv):
        modes = list(cls.metadata["render_modes"])
        if "human" not in modes:
            monkeypatch.setattr(cls, "metadata", {**cls.metadata, "render_modes": [*modes, "human"]})
    return DownwashFollowerEnv, DownwashFollowerVectorEnv


class FakeWindow:
    """What `Viewer` uses of `mujoco.viewer.launch_passive`'s handle, without a window: the camera, the
    user scene the decorations go into, and a count of syncs."""

    def __init__(self, model):
        import threading

        import mujoco

        self.cam = mujoco.MjvCamera()
        self.user_scn = mujoco.MjvScene(model, maxgeom=1000)
        self.syncs, self.texts, self.running = 0, None, True
        self._lock = threading.Lock()

    def is_running(self):
        return self.running

    def lock(self):
        return self._lock

    def set_texts(self, texts):
        self.texts = texts

    def sync(self):
        self.syncs += 1

    def close(self):
        self.running = False


@pytest.fixture
def fake_window(monkeypatch):
    """The viewer opens a `FakeWindow` (a display is pretended); returns the windows opened."""
    import downwash_envs.viewer as viewer

    monkeypatch.setenv("DISPLAY", ":12345")
    opened = []

    def launch(model, data, what):
        opened.append(FakeWindow(model))
        return opened[-1], []

    monkeypatch.setattr(viewer, "_launch", launch)
    return opened


# ----------------------------------------------------------------------------- headless


@pytest.mark.skipif(not LINUX, reason="the display variables are Linux's")
def test_no_display_says_what_to_do(headless):
    from downwash_envs.viewer import check_display

    with pytest.raises(ConfigError) as e:
        check_display("render_mode='human'")
    msg = str(e.value)
    for needle in ("render_mode='human'", "DISPLAY", "WAYLAND_DISPLAY", "xvfb-run", "render_mode='rgb_array'", "--video"):
        assert needle in msg, msg


@pytest.mark.skipif(not LINUX, reason="the display variables are Linux's")
def test_env_human_without_display_fails_before_any_work(headless, human_env, monkeypatch):
    import gymnasium as gym

    import downwash_envs
    import downwash_envs.base as base

    def no_work(*args, **kwargs):
        raise AssertionError("the task was built before the display was checked")

    monkeypatch.setattr(base, "FollowerWorlds", no_work)
    monkeypatch.setattr(base, "make_config", no_work)
    single, vector = human_env
    with pytest.raises(ConfigError, match="render_mode='human'.*xvfb-run"):
        gym.make(downwash_envs.ENV_IDS[0], render_mode="human")
    with pytest.raises(ConfigError, match="render_mode='human'.*xvfb-run"):
        vector(2, render_mode="human")


def test_swarm_envs_list_human():
    from downwash_envs.swarm import SwarmEnv, SwarmVectorEnv

    for cls in (SwarmEnv, SwarmVectorEnv):
        assert cls.metadata["render_modes"] == ["rgb_array", "human"]


@pytest.mark.skipif(not LINUX, reason="the display variables are Linux's")
def test_swarm_human_without_display_fails_before_any_work(headless, monkeypatch):
    import downwash_envs.swarm as swarm

    def no_work(*args, **kwargs):
        raise AssertionError("the task was built before the display was checked")

    monkeypatch.setattr(swarm, "SwarmWorlds", no_work)
    monkeypatch.setattr(swarm, "make_swarm_config", no_work)
    with pytest.raises(ConfigError, match="render_mode='human'.*xvfb-run.*render_mode='rgb_array'"):
        swarm.parallel_env(preset="stack3", render_mode="human")
    with pytest.raises(ConfigError, match="render_mode='human'.*xvfb-run"):
        swarm.SwarmVectorEnv(2, preset="stack3", render_mode="human")


def test_swarm_human_draws_every_wake_and_syncs_each_step(fake_window):
    """The window opens at reset and syncs after it and after every step, paced to real time; every
    vehicle's wake is drawn (12 segments each) and every follower's reference marked; close closes it."""
    import time

    from downwash_envs.swarm import SwarmVectorEnv, parallel_env
    from downwash_envs.viewer import Viewer

    env = parallel_env(preset="stack3", render_mode="human")
    assert not fake_window  # no window before the first reset
    env.reset(seed=0)
    viewer = env._renderer
    assert isinstance(viewer, Viewer) and len(fake_window) == 1
    window = fake_window[0]
    assert window.syncs == 1 and sorted(viewer.wake_vehicles) == [0, 1, 2]
    start = time.perf_counter()
    for _ in range(3):
        env.step({a: np.zeros(3, np.float32) for a in env.agents})
    assert time.perf_counter() - start >= 3 * env.dt * 0.9  # paced: one control period per step
    assert window.syncs == 4 and env.render() is None and window.syncs == 5
    assert window.user_scn.ngeom == 3 * 12 + 2  # three wakes, two followers' references
    assert window.texts[2].startswith("t = ")
    sim = env.simulator
    leader, bottom = sim.true_states().pos[0, 0], sim.true_states().pos[0, 2]
    np.testing.assert_allclose(window.cam.lookat, 0.5 * (leader + bottom), atol=0.05)  # frames the whole stack
    np.testing.assert_allclose(viewer.data.qpos, sim.physics.mjdata(0).qpos)  # the world as it is
    env.close()
    assert env._renderer is None and not window.is_running()

    vec = SwarmVectorEnv(2, preset="stack3", render_mode="human")
    vec.reset(seed=0)
    vec.step({a: np.zeros((2, 3), np.float32) for a in vec.agents})
    assert vec.render() is None
    window = fake_window[1]
    assert window.syncs == 3 and window.user_scn.ngeom == 3 * 12 + 2
    np.testing.assert_allclose(vec._renderer.data.qpos, vec.simulator.physics.mjdata(0).qpos)  # world 0
    vec.close()
    assert not window.is_running()


def test_follower_human_draws_the_leaders_wake(fake_window, human_env):
    """The follower env's window, through the viewer the swarm shares: the leader's wake, the
    follower's reference, the camera on the midpoint of the two."""
    single, _ = human_env
    env = single(render_mode="human")
    env.reset(seed=0)
    window = fake_window[0]
    p_leader, p_follower = env.simulator.true_states().pos[0]
    np.testing.assert_allclose(window.cam.lookat, 0.5 * (p_leader + p_follower))
    assert window.cam.distance == pytest.approx(0.6 + 1.3 * np.linalg.norm(p_follower - p_leader))
    env.step(np.zeros(3, np.float32))
    assert window.syncs == 2 and window.user_scn.ngeom == 13  # 12 wake segments, the reference
    assert env._renderer.wake_vehicles == [0]
    env.close()
    assert not window.is_running()


def test_render_mode_is_checked_against_the_class_metadata():
    from downwash_envs.follower import DownwashFollowerEnv

    with pytest.raises(ValueError, match="render_mode: got 'bogus'; allowed: None, rgb_array"):
        DownwashFollowerEnv(render_mode="bogus")


@pytest.mark.skipif(not LINUX, reason="the display variables are Linux's")
def test_replay_without_display_fails_before_any_window(headless, tmp_path, capsys):
    from experiments.replay import main

    path = tmp_path / "flight.npz"
    save_log(path, _synthetic_log())
    with pytest.raises(SystemExit) as e:
        main([str(path)])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "python -m experiments.replay" in err and "DISPLAY" in err and "xvfb-run" in err, err


@pytest.mark.parametrize("speed", ["0", "-1", "nan", "inf", "fast"])
def test_replay_bad_speed_names_the_flag(no_window, tmp_path, capsys, speed):
    from experiments.replay import main

    path = tmp_path / "flight.npz"
    save_log(path, _synthetic_log())
    with pytest.raises(SystemExit) as e:
        main([str(path), "--speed", speed])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "argument --speed" in err and "> 0" in err, err


def test_replay_bad_logs_name_the_file(no_window, tmp_path, capsys):
    from experiments.replay import main

    text = tmp_path / "notes.npz"
    text.write_text("hello")
    foreign = tmp_path / "other.npz"
    np.savez(foreign, x=np.zeros(3))
    for path, needle in ((tmp_path / "missing.npz", "no such log file"), (text, "truncated or foreign"),
                         (foreign, "not a flight log")):
        with pytest.raises(SystemExit) as e:
            main([str(path)])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "argument PATH" in err and path.name in err and needle in err, err
    # a valid log the viewer cannot show: its first row is not finite
    bad = _synthetic_log()
    bad.arrays["pos"][0, 0] = np.nan
    save_log(tmp_path / "nan.npz", bad)
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "nan.npz")])
    assert e.value.code == 2
    assert "empty (no rows, or its first row is not finite)" in capsys.readouterr().err


def test_replay_help_is_fast_and_light():
    """--help answers without importing mujoco or numpy (they are imported inside main)."""
    code = ("import sys, experiments.replay as r; heavy = [m for m in ('mujoco', 'numpy') if m in sys.modules];"
            "print(heavy); sys.exit(1 if heavy else 0)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    proc = subprocess.run([sys.executable, "-m", "experiments.replay", "--help"], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0 and "--speed" in proc.stdout and "--loop" in proc.stdout, proc.stderr


def test_the_viewers_wake_is_the_videos():
    """`add_wake` draws the geoms `TiledRenderer` draws into a video frame (no window, no OpenGL needed)."""
    import mujoco

    from downwash_envs.video import TiledRenderer
    from downwash_envs.viewer import add_wake
    from sim.scene import build_scene

    model = build_scene().model
    a, b = mujoco.MjvScene(model, 100), mujoco.MjvScene(model, 100)
    p = np.array([0.1, -0.2, 2.5])
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    add_wake(a, p, R, (0.1, 0.12))
    TiledRenderer._add_wake(SimpleNamespace(wake=(0.1, 0.12)), b, p, R)
    assert a.ngeom == b.ngeom > 0
    for i in range(a.ngeom):
        for attr in ("type", "size", "pos", "mat", "rgba"):
            np.testing.assert_array_equal(getattr(a.geoms[i], attr), getattr(b.geoms[i], attr))


# ----------------------------------------------------------------------------- a window, under Xvfb


@pytest.mark.skipif(not LINUX or shutil.which("xvfb-run") is None,
                    reason="needs xvfb-run (apt-get install xvfb) for a virtual display")
def test_passive_viewer_under_xvfb(tmp_path):
    """The follower env and the swarm env open the passive viewer at reset, sync it every step with the
    wakes and the references drawn, and close it; the replay plays a short log and returns. Software
    OpenGL is slow, so few steps."""
    save_log(tmp_path / "flight.npz", _synthetic_log(T=20))
    script = textwrap.dedent(f"""
        import sys
        import numpy as np
        import gymnasium as gym
        import downwash_envs
        from downwash_envs.follower import DownwashFollowerEnv
        from downwash_envs.viewer import Viewer
        if "human" not in DownwashFollowerEnv.metadata["render_modes"]:
            DownwashFollowerEnv.metadata = {{**DownwashFollowerEnv.metadata,
                                            "render_modes": [*DownwashFollowerEnv.metadata["render_modes"], "human"]}}
        env = gym.make(downwash_envs.ENV_IDS[0], render_mode="human")
        env.reset(seed=0)
        viewer = env.unwrapped._renderer
        assert isinstance(viewer, Viewer) and viewer.is_running()
        for _ in range(3):
            env.step(np.zeros(3, np.float32))
        assert env.render() is None
        assert viewer._handle.user_scn.ngeom == 13, viewer._handle.user_scn.ngeom  # 12 wake segments, the reference
        env.close()
        assert env.unwrapped._renderer is None and not viewer.is_running()
        from downwash_envs.swarm import parallel_env
        swarm = parallel_env(preset="stack3", render_mode="human")
        swarm.reset(seed=0)
        window = swarm._renderer
        assert isinstance(window, Viewer) and window.is_running()
        swarm.step({{a: np.zeros(3, np.float32) for a in swarm.agents}})
        assert window._handle.user_scn.ngeom == 38, window._handle.user_scn.ngeom  # 3 wakes, 2 references
        swarm.close()
        assert swarm._renderer is None and not window.is_running()
        from experiments.replay import main
        syncs = main([{str(tmp_path / "flight.npz")!r}, "--speed", "4"])
        assert syncs >= 1, syncs
        print("viewer ok", syncs)
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY",
                                                             "WAYLAND_DISPLAY")}
    proc = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", sys.executable, "-c", script],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "viewer ok" in proc.stdout, proc.stdout[-3000:] + proc.stderr[-3000:]
