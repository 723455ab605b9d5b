"""Every examples/*.py runs with --quick, writes its learning curve and its policy (--save), and
evaluates that policy again without training (--load)."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="the rl extra (stable-baselines3) is not installed")
pytest.importorskip("supersuit", reason="the rl extra (supersuit) is not installed")

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCRIPTS = sorted(p.name for p in EXAMPLES.glob("*.py") if p.name not in ("learning_curve.py", "policy_file.py"))
EVALUATED = re.compile(r"PPO, deterministic: mean return (-?[\d.]+) \+- ([\d.]+) \(std\) over 2 episodes")


def _run(script, *args, cwd, timeout=600):
    return subprocess.run([sys.executable, str(EXAMPLES / script), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout)


def test_every_example_is_covered():
    assert SCRIPTS == ["ppo_follower.py", "ppo_follower_vector.py", "ppo_swarm.py"]


@pytest.mark.parametrize("script", SCRIPTS)
def test_example_runs_quick_saves_and_loads_its_policy(script, tmp_path):
    proc = _run(script, "--quick", "--out", "out", "--save", "policies/p.zip", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # the policy where --save said, and nothing else in its folder (the temporary file was renamed)
    assert [p.name for p in (tmp_path / "policies").iterdir()] == ["p.zip"]
    assert not (tmp_path / "out" / "policy.zip").exists()
    record = json.loads((tmp_path / "out" / "learning_curve.json").read_text())
    assert record["timesteps"] == 256 and len(record["episodes"]) >= 1
    assert all(e["length"] > 0 for e in record["episodes"])
    # the trained policy and the plain LQR, measured on the same evaluation episodes
    assert set(record["evaluation"]) == {"LQR alone (action 0)", "PPO, deterministic"}
    assert all(len(v["returns"]) == 2 for v in record["evaluation"].values())
    assert (tmp_path / "out" / "learning_curve.png").stat().st_size > 1000

    # --load: no training, the same policy on the same evaluation episodes earns the same returns
    loaded = _run(script, "--quick", "--load", "policies/p.zip", "--out", "again", cwd=tmp_path)
    assert loaded.returncode == 0, loaded.stderr[-3000:]
    assert not (tmp_path / "again").exists()
    m = EVALUATED.search(loaded.stdout)
    assert m, loaded.stdout
    assert m.group(1) == f"{record['evaluation']['PPO, deterministic']['mean']:.1f}"
    assert float(m.group(2)) == pytest.approx(float(np.std(record["evaluation"]["PPO, deterministic"]["returns"])),
                                              abs=0.051)


def test_example_saves_under_out_by_default(tmp_path):
    proc = _run("ppo_follower.py", "--quick", "--out", "out", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["learning_curve.json", "learning_curve.png",
                                                                     "policy.zip"]
    assert "--load out/policy.zip" in proc.stdout


@pytest.mark.parametrize("script", SCRIPTS)
def test_example_refuses_a_missing_policy(script, tmp_path):
    proc = _run(script, "--quick", "--load", "nowhere/policy.zip", cwd=tmp_path, timeout=120)
    assert proc.returncode != 0
    assert proc.stderr.strip() == f"{script}: --load nowhere/policy.zip: no such policy file"


@pytest.mark.parametrize("script", SCRIPTS)
def test_example_refuses_a_file_that_is_no_policy(script, tmp_path):
    (tmp_path / "notes.zip").write_text("not a zip\n")
    proc = _run(script, "--quick", "--load", "notes.zip", cwd=tmp_path, timeout=300)
    assert proc.returncode != 0
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"{script}: --load notes.zip: not a PPO policy for this env"), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr


def test_example_refuses_save_with_load(tmp_path):
    proc = _run("ppo_follower.py", "--save", "a.zip", "--load", "b.zip", cwd=tmp_path, timeout=120)
    assert proc.returncode == 2 and "--load" in proc.stderr and "not allowed with" in proc.stderr


@pytest.mark.parametrize("script", SCRIPTS)
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
