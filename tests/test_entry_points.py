"""The project's import names are its own: decoy `envs/`, `core/` and `trajectories/`
folders in the working directory (which Python puts first on the path) change nothing."""

import json
import subprocess
import sys
import textwrap

DECOYS = ("envs", "core", "trajectories")


def _decoys(root):
    for name in DECOYS:
        (root / name).mkdir()
        (root / name / "__init__.py").write_text(f"raise ImportError('the decoy {name} package was imported')\n")


def test_main_entry_points_run_beside_decoy_packages(tmp_path):
    _decoys(tmp_path)
    code = textwrap.dedent("""
        import json, sys
        import gymnasium as gym
        env = gym.make("downwash_envs:downwash/Follower-v2")
        obs, _ = env.reset(seed=0)
        env.step(env.action_space.sample())
        from downwash_envs.swarm import parallel_env
        swarm = parallel_env(preset="stack3", duration=0.2)
        swarm.reset(seed=0)
        print(json.dumps([obs.shape[0], sorted(swarm.agents), [m for m in ("envs", "core", "trajectories") if m in sys.modules]]))
    """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    dim, agents, imported = json.loads(proc.stdout.strip().splitlines()[-1])
    assert dim == 30 and agents == ["follower_0", "follower_1"] and imported == []
    proc = subprocess.run([sys.executable, "-m", "experiments.lemniscate", "--quick", "--duration", "2",
                           "--conditions", "no_downwash,baseline,oracle", "--out", "lem"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((tmp_path / "lem" / "results.json").read_text())
    assert set(results["conditions"]) == {"no_downwash", "baseline", "oracle"}


def test_the_packages_are_the_design_cards_and_our_own():
    """Top-level packages: the design card's folders and names that start with `downwash_`;
    the install includes exactly them."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    packages = {p.parent.name for p in root.glob("*/__init__.py")}
    card = {"sim", "controllers", "downwash", "experiments"}
    assert packages - card and all(p.startswith("downwash_") for p in packages - card), packages
    assert not packages & set(DECOYS)
    include = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    assert {pattern.rstrip("*") for pattern in include} == packages
