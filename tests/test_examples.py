"""Every examples/*.py runs with --quick and writes its learning curve."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("stable_baselines3", reason="the rl extra (stable-baselines3) is not installed")
pytest.importorskip("supersuit", reason="the rl extra (supersuit) is not installed")

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCRIPTS = sorted(p.name for p in EXAMPLES.glob("*.py") if p.name != "learning_curve.py")


def test_every_example_is_covered():
    assert SCRIPTS == ["ppo_follower.py", "ppo_follower_vector.py", "ppo_swarm.py"]


@pytest.mark.parametrize("script", SCRIPTS)
def test_example_runs_quick(script, tmp_path):
    proc = subprocess.run([sys.executable, str(EXAMPLES / script), "--quick", "--out", "out"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads((tmp_path / "out" / "learning_curve.json").read_text())
    assert record["timesteps"] == 256 and len(record["episodes"]) >= 1
    assert all(e["length"] > 0 for e in record["episodes"])
    # the trained policy and the plain LQR, measured on the same evaluation episodes
    assert set(record["evaluation"]) == {"LQR alone (action 0)", "PPO, deterministic"}
    assert all(len(v["returns"]) == 2 for v in record["evaluation"].values())
    assert (tmp_path / "out" / "learning_curve.png").stat().st_size > 1000


@pytest.mark.parametrize("script", SCRIPTS)
def test_example_refuses_a_bad_budget(script, tmp_path):
    proc = subprocess.run([sys.executable, str(EXAMPLES / script), "--timesteps", "0"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--timesteps" in proc.stderr
