"""The observer's bandwidth is the one its experiment chose on the training flights, and the experiment runs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from downwash_core.errors import ConfigError
from experiments.observer_bandwidth import _candidates
from sim.observer import DEFAULT_BANDWIDTH, DisturbanceObserver

ROOT = Path(__file__).resolve().parent.parent


def test_each_controllers_bandwidth_is_the_committed_choice_and_the_rule_holds():
    from controllers.registry import make_controller
    from sim.observer import bandwidth_for

    r = json.loads((ROOT / "results" / "observer_bandwidth.json").read_text())
    assert set(r["controllers"]) == {"lqr", "mellinger", "pid", "indi"}
    assert DEFAULT_BANDWIDTH == r["controllers"]["lqr"]["chosen"] == DisturbanceObserver().bandwidth
    for name, c in r["controllers"].items():
        assert bandwidth_for(make_controller(name)) == c["chosen"], name
        by_bandwidth = {e["bandwidth"]: e for e in c["candidates"]}
        best = min(c["candidates"], key=lambda e: e["pos_err_3d_mean"])
        assert c["best"] == best["bandwidth"]
        # the chosen one is the lowest that is not significantly worse than the best
        assert by_bandwidth[c["chosen"]]["minus_best_ci95"][0] <= 0.0
        assert all(e["minus_best_ci95"][0] > 0.0 for e in c["candidates"] if e["bandwidth"] < c["chosen"])


def test_the_observer_flies_at_its_controllers_bandwidth_in_every_condition_and_env():
    from controllers.crazyflie import MellingerController
    from downwash.conditions import make_predictor
    from sim.observer import bandwidth_for

    mellinger = MellingerController()
    assert bandwidth_for(mellinger) == MellingerController.observer_bandwidth != DEFAULT_BANDWIDTH
    assert make_predictor("dob", None, controller=mellinger).bandwidth == MellingerController.observer_bandwidth
    assert make_predictor("dob", None).bandwidth == DEFAULT_BANDWIDTH  # no controller: the LQR
    assert bandwidth_for(object()) == DEFAULT_BANDWIDTH  # a user's controller that states none
    from controllers.indi import INDIController
    from downwash_envs.swarm import SwarmVectorEnv

    env = SwarmVectorEnv(2, preset="stack3", controller="indi", predictor="dob")
    assert env._worlds.sim.predictor.bandwidth == INDIController.observer_bandwidth  # (the env's simulator)
    env.close()


def test_quick_run_writes_the_choice(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "experiments.observer_bandwidth", "--quick", "--controllers",
                           "lqr,indi", "--out", "o"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads((tmp_path / "o" / "results.json").read_text())
    assert set(r["controllers"]) == {"lqr", "indi"}
    for c in r["controllers"].values():
        assert [e["bandwidth"] for e in c["candidates"]] == [1.0, 2.0] and c["chosen"] in (1.0, 2.0)
        assert all(e["pos_err_3d_mean"] > 0 and e["crashes"] == 0 for e in c["candidates"])


@pytest.mark.parametrize("bad", ["", "a,b", "0,1", "2,2", "-1", "nan"])
def test_bad_candidates_are_refused(bad):
    with pytest.raises(ConfigError, match="--candidates"):
        _candidates(bad)
