"""The first-compile notice and `python -m experiments.warmup`."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTICE = "compiling the simulator's kernels"

FLIGHT = """
import numpy as np
from downwash_core.params import LEADER_POSITION
from downwash_trajectories import Hover, Transect, stack
from sim.flight import fly
from sim.scene import build_scene
leader = np.array(LEADER_POSITION)
ref = stack([Hover(leader, n_worlds=1), Transect(leader - [0, 0, 0.6], x_offset=0.1)])
fly(build_scene(), ref, [0], 0.1)
"""


def _python(code: list[str], cache: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "XDG_CACHE_HOME": str(cache)}  # the marker's home; numba's own cache is untouched
    return subprocess.run([sys.executable, *code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)


def test_a_first_flight_says_it_compiles_once_and_not_again(tmp_path):
    first = _python(["-c", FLIGHT], tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    assert first.stderr.count(NOTICE) == 1  # one line, once per process, however many ticks
    markers = list((tmp_path / "downwash-testbed").glob("kernels-*.compiled"))
    assert len(markers) == 1
    second = _python(["-c", FLIGHT], tmp_path)
    assert second.returncode == 0, second.stderr[-2000:]
    assert NOTICE not in second.stderr


def test_an_unwritable_cache_only_repeats_the_notice(tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")  # the marker's folder cannot be made under a file
    run = _python(["-c", FLIGHT], blocker)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stderr.count(NOTICE) == 1


def test_warmup_compiles_what_it_lists_and_records_it(tmp_path):
    run = _python(["-m", "experiments.warmup", "--quick"], tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "pair flight, equivariant guarded:" in run.stdout and "envs:" in run.stdout
    assert "compiled and cached in" in run.stdout
    assert list((tmp_path / "downwash-testbed").glob("kernels-*.compiled"))
    after = _python(["-c", FLIGHT], tmp_path)
    assert NOTICE not in after.stderr


def test_warmup_refuses_unknown_options(tmp_path):
    run = _python(["-m", "experiments.warmup", "--quik"], tmp_path)
    assert run.returncode == 2 and "unrecognized arguments: --quik" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
