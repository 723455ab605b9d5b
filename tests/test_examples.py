"""Every examples/*.py runs with --quick, writes its learning curve, its TensorBoard logs and its
policy (--save), and evaluates that policy again without training (--load)."""

import importlib.util
import json
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="the rl extra (stable-baselines3) is not installed")
pytest.importorskip("supersuit", reason="the rl extra (supersuit) is not installed")

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCRIPTS = sorted(p.name for p in EXAMPLES.glob("*.py") if p.name not in ("learning_curve.py", "policy_file.py"))
EVALUATED = re.compile(r"PPO, deterministic: mean return (-?[\d.]+) \+- ([\d.]+) \(std\) over 2 episodes")
POLICY_FILE = {"torchrl_follower.py": "policy.pt"}  # the others write SB3 zips, policy.zip
TENSORBOARD = ["ppo_follower.py", "ppo_follower_vector.py", "ppo_swarm.py", "torchrl_follower.py"]  # the scripts with --tensorboard
NEEDS_TORCHRL = pytest.mark.skipif(importlib.util.find_spec("torchrl") is None,
                                   reason="the rl extra (torchrl) is not installed")
NEEDS_TENSORBOARD = pytest.mark.skipif(importlib.util.find_spec("tensorboard") is None,
                                       reason="the rl extra (tensorboard) is not installed")


def _scripts(names):
    """`names` as pytest parameters, the TorchRL example skipped without TorchRL."""
    return [pytest.param(n, marks=NEEDS_TORCHRL) if n.startswith("torchrl") else n for n in names]


def _run(script, *args, cwd, timeout=600):
    return subprocess.run([sys.executable, str(EXAMPLES / script), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def test_every_example_is_covered():
    assert SCRIPTS == ["ppo_follower.py", "ppo_follower_vector.py", "ppo_swarm.py", "torchrl_follower.py"]


@pytest.mark.parametrize("script", _scripts(SCRIPTS))
def test_example_runs_quick_saves_and_loads_its_policy(script, tmp_path):
    policy = "p" + Path(POLICY_FILE.get(script, "policy.zip")).suffix
    quiet = ["--no-tensorboard"] if script in TENSORBOARD else []
    proc = _run(script, "--quick", "--out", "out", "--save", f"policies/{policy}", *quiet, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # the policy where --save said, and nothing else in its folder (the temporary file was renamed)
    assert [p.name for p in (tmp_path / "policies").iterdir()] == [policy]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["learning_curve.json", "learning_curve.png"]
    record = json.loads((tmp_path / "out" / "learning_curve.json").read_text())
    assert record["timesteps"] == 256 and len(record["episodes"]) >= 1
    assert all(e["length"] > 0 for e in record["episodes"])
    # the trained policy and the plain LQR, measured on the same evaluation episodes
    assert set(record["evaluation"]) == {"LQR alone (action 0)", "PPO, deterministic"}
    assert all(len(v["returns"]) == 2 for v in record["evaluation"].values())
    assert (tmp_path / "out" / "learning_curve.png").stat().st_size > 1000

    # --load: no training, the same policy on the same evaluation episodes earns the same returns
    loaded = _run(script, "--quick", "--load", f"policies/{policy}", "--out", "again", cwd=tmp_path)
    assert loaded.returncode == 0, loaded.stderr[-3000:]
    assert not (tmp_path / "again").exists()
    m = EVALUATED.search(loaded.stdout)
    assert m, loaded.stdout
    assert m.group(1) == f"{record['evaluation']['PPO, deterministic']['mean']:.1f}"
    assert float(m.group(2)) == pytest.approx(float(np.std(record["evaluation"]["PPO, deterministic"]["returns"])),
                                              abs=0.051)


@NEEDS_TENSORBOARD
def test_example_saves_under_out_by_default(tmp_path):
    proc = _run("ppo_follower.py", "--quick", "--out", "out", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["learning_curve.json", "learning_curve.png",
                                                                     "policy.zip", "tensorboard"]
    assert "--load out/policy.zip" in proc.stdout
    # one folder per run, as SB3 names them: a rerun logs beside the first
    assert [p.name for p in (tmp_path / "out" / "tensorboard").iterdir()] == ["PPO_1"]


def _scalars(run: Path, tag: str) -> list[tuple[int, float]]:
    """(step, value) of `tag` in the one TensorBoard events file of `run`, read back as TensorBoard does."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    [events] = run.glob("events.out.tfevents.*")
    accumulator = EventAccumulator(str(events))
    accumulator.Reload()
    assert tag in accumulator.Tags()["scalars"], accumulator.Tags()["scalars"]
    return [(e.step, e.value) for e in accumulator.Scalars(tag)]


@NEEDS_TENSORBOARD
@pytest.mark.parametrize("script", _scripts(TENSORBOARD))
def test_example_writes_tensorboard_logs(script, tmp_path):
    proc = _run(script, "--quick", "--out", "out", "--tensorboard", "tb", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert not (tmp_path / "out" / "tensorboard").exists()
    assert [p.name for p in (tmp_path / "tb").iterdir()] == ["PPO_1"]
    # the mean return of the recent episodes, by SB3's name, at the step it was measured
    returns = _scalars(tmp_path / "tb" / "PPO_1", "rollout/ep_rew_mean")
    assert returns and returns[-1][0] == 256
    assert all(np.isfinite(v) and v <= 50 + 1e-6 for _, v in returns)  # at most +1 a step, 50-step episodes


@NEEDS_TORCHRL
def test_torchrl_builds_the_env_by_its_id_without_warnings():
    import torchrl.envs  # first: its own import-time notices are not about the env

    import downwash_envs  # noqa: F401  (registers the ids)
    from downwash_envs.follower import DownwashFollowerEnv

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env = torchrl.envs.GymEnv("downwash/Follower-v2", max_episode_steps=5)  # probes frameskip, falls back
        env.set_seed(0)
        steps = env.rollout(10)  # random actions for 0.1 s stay in the tracking box: the time limit ends it
        env.close()
    assert [f"{w.category.__name__}: {w.message}" for w in caught] == []
    assert isinstance(env._env.unwrapped, DownwashFollowerEnv)
    assert steps.shape == (5,) and steps["next", "truncated"][-1].item()
    assert steps["next", "observation"].shape == (5, 30) and steps["action"].abs().max() <= 1


@NEEDS_TORCHRL
def test_torchrl_example_measures_position_errors_again_on_load(tmp_path):
    proc = _run("torchrl_follower.py", "--quick", "--out", "out", "--no-tensorboard", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Warning" not in proc.stderr, proc.stderr[-3000:]
    assert "--load out/policy.pt" in proc.stdout
    record = json.loads((tmp_path / "out" / "learning_curve.json").read_text())
    errors = record["position_error"]
    assert set(errors) == {"LQR alone (action 0)", "PPO, deterministic"}
    assert all(0 < v < 1 for v in errors.values())  # m; the tracking box (1 m) ends an episode first
    for label, v in errors.items():
        assert f"{label}: mean position error {v:.4f} m over 2 evaluation episodes" in proc.stdout

    loaded = _run("torchrl_follower.py", "--quick", "--load", "out/policy.pt", cwd=tmp_path)
    assert loaded.returncode == 0, loaded.stderr[-3000:]
    assert "Warning" not in loaded.stderr, loaded.stderr[-3000:]
    for label, v in errors.items():  # the same policy on the same seeded episodes: the same errors
        line = next(s for s in loaded.stdout.splitlines() if s.strip().startswith(f"{label}:"))
        assert line.endswith(f"mean position error {v:.4f} m"), loaded.stdout


@pytest.mark.parametrize("script", _scripts(SCRIPTS))
def test_example_refuses_a_missing_policy(script, tmp_path):
    proc = _run(script, "--quick", "--load", "nowhere/policy.zip", cwd=tmp_path, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"{script}: --load nowhere/policy.zip: no such policy file"


@pytest.mark.parametrize("script", _scripts(SCRIPTS))
def test_example_refuses_a_file_that_is_no_policy(script, tmp_path):
    (tmp_path / "notes.zip").write_text("not a zip\n")
    proc = _run(script, "--quick", "--load", "notes.zip", cwd=tmp_path, timeout=300)
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{script}: --load notes.zip: not a PPO policy for this env"), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr


def test_example_refuses_save_with_load(tmp_path):
    proc = _run("ppo_follower.py", "--save", "a.zip", "--load", "b.zip", cwd=tmp_path, timeout=120)
    assert proc.returncode == 2 and "--load" in proc.stderr and "not allowed with" in proc.stderr


@pytest.mark.parametrize("script", _scripts(SCRIPTS))
def test_example_refuses_a_bad_budget(script, tmp_path):
    proc = subprocess.run([sys.executable, str(EXAMPLES / script), "--timesteps", "0"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--timesteps" in proc.stderr


class _Model:
    """Stands for an SB3 algorithm: `save` writes the given bytes, then fails when told to (a kill mid-write)."""

    def __init__(self, payload: bytes, fail: bool = False):
        self.payload, self.fail = payload, fail

    def save(self, path):
        Path(path).write_bytes(self.payload[: len(self.payload) // 2] if self.fail else self.payload)
        if self.fail:
            raise KeyboardInterrupt


def test_save_policy_is_atomic(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLES))
    from policy_file import save_policy

    target = tmp_path / "runs" / "policy.zip"
    assert save_policy(_Model(b"first policy"), target) == target
    assert target.read_bytes() == b"first policy"
    with pytest.raises(KeyboardInterrupt):
        save_policy(_Model(b"second policy", fail=True), target)
    # the interrupted save left the old policy whole and no temporary file beside it
    assert target.read_bytes() == b"first policy"
    assert [p.name for p in target.parent.iterdir()] == ["policy.zip"]
    save_policy(_Model(b"second policy"), target)
    assert target.read_bytes() == b"second policy"
