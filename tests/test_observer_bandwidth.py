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


def test_the_default_is_the_committed_choice_and_the_rule_holds():
    r = json.loads((ROOT / "results" / "observer_bandwidth.json").read_text())
    assert DEFAULT_BANDWIDTH == r["chosen"] == DisturbanceObserver().bandwidth
    by_bandwidth = {e["bandwidth"]: e for e in r["candidates"]}
    best = min(r["candidates"], key=lambda e: e["pos_err_3d_mean"])
    assert r["best"] == best["bandwidth"]
    # the chosen one is the lowest that is not significantly worse than the best
    assert by_bandwidth[r["chosen"]]["minus_best_ci95"][0] <= 0.0
    assert all(e["minus_best_ci95"][0] > 0.0 for e in r["candidates"] if e["bandwidth"] < r["chosen"])


def test_quick_run_writes_the_choice(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "experiments.observer_bandwidth", "--quick", "--out", "o"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads((tmp_path / "o" / "results.json").read_text())
    assert [e["bandwidth"] for e in r["candidates"]] == [1.0, 2.0] and r["chosen"] in (1.0, 2.0)
    assert all(e["pos_err_3d_mean"] > 0 and e["crashes"] == 0 for e in r["candidates"])


@pytest.mark.parametrize("bad", ["", "a,b", "0,1", "2,2", "-1", "nan"])
def test_bad_candidates_are_refused(bad):
    with pytest.raises(ConfigError, match="--candidates"):
        _candidates(bad)
