"""The resumable sweep (`downwash.sweep`, `python -m experiments.sweep`): cells, cache, Ray, statistics.

One quick staged collection and one local Ray of 2 CPUs serve the whole module.
The first sweep computes every cell; a second run must compute none and give the
same results; deleting (and corrupting) some cache files must recompute exactly
those, with the numbers of the first run bit for bit although they are batched
differently; a two-node Ray cluster driven through the command line must give the
same numbers too. The statistics are checked on numbers whose answer is known.
"""

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError
from downwash.sweep import run_sweep
from downwash.sweep_cells import FULL, SweepGrid, plan_cells
from downwash.sweep_stats import Claim, bootstrap_ci, paired_comparison
from experiments.common import PipelineArgs, parse_args, resolve_pipeline

ROOT = Path(__file__).resolve().parent.parent
MODELS, MINUTES, SEEDS = ("shallow", "equivariant"), (0.1, 0.2), (0, 1, 2)
CLAIM = Claim("equivariant", FULL, ("shallow",), FULL)  # quick data hold no 5 and 15 min points


# -- bad input ----------------------------------------------------------------------------------

@pytest.mark.parametrize(
    "change, message",
    [
        ({"fields": ("nope",)}, "nope"),
        ({"fields": ()}, "fields: empty"),
        ({"models": ("huge",)}, "models: unknown 'huge'; allowed: .*equivariant"),
        ({"models": ()}, "models: empty"),
        ({"minutes": (1.0, 0.0)}, "minutes: .*> 0"),
        ({"minutes": (-2.0,)}, "minutes: .*> 0"),
        ({"minutes": (math.nan,)}, "minutes: .*finite"),
        ({"seeds": ()}, "seeds: empty"),
        ({"seeds": (0, -1)}, "seeds: expected integers >= 0"),
        ({"seeds": (1, 1)}, "repeats a seed"),
    ],
)
def test_bad_grid_raises_config_error(change, message):
    with pytest.raises(ConfigError, match=message):
        SweepGrid(**{"models": MODELS, "minutes": MINUTES, "seeds": SEEDS, **change})


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--field", "so2;nope"], "nope"),
        (["--models", "shallow,huge"], "unknown 'huge'"),
        (["--minutes", "1,0"], "> 0"),
        (["--minutes", "a,b"], "comma list"),
        (["--seeds", ""], "seeds: empty"),
    ],
)
def test_bad_command_line_fails_before_any_work(argv, message, tmp_path, monkeypatch):
    from experiments.sweep import SweepArgs, run

    monkeypatch.chdir(tmp_path)
    args = parse_args(SweepArgs, "sweep", [*argv, "--out", "out", "--cache-dir", "cells"])
    with pytest.raises(ConfigError, match=message):
        run(args)
    assert sorted(os.listdir(tmp_path)) == []  # no collection, no cache, no results


@pytest.mark.parametrize("argv, message", [(["--workers", "-1"], "--workers: expected"), (["--batch", "0"], "--batch: expected")])
def test_bad_numbers_are_usage_errors_naming_the_flag(argv, message, tmp_path, monkeypatch, capsys):
    from experiments.sweep import SweepArgs

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        parse_args(SweepArgs, "sweep", [*argv, "--out", "out", "--cache-dir", "cells"])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == []


# -- statistics ---------------------------------------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.01, 1.0), min_size=5, max_size=12).filter(lambda v: max(v) - min(v) > 1e-3))
def test_bootstrap_ci_contains_the_mean_and_shrinks_with_more_trials(values):
    """(Five trials or more: with three, e.g. [0.02, 0.02, 0.75], the resampled means take four
    values only, and four times the trials narrow the interval by just 20 %.)"""
    low, high = bootstrap_ci(values)
    mean = float(np.mean(values))
    assert low <= mean <= high and low < high
    # the same spread over four times the trials: the interval of the mean narrows (about by half)
    low4, high4 = bootstrap_ci(np.tile(values, 4))
    assert low4 <= mean <= high4
    assert high4 - low4 < 0.8 * (high - low)
    assert bootstrap_ci(values) == (low, high)  # a fixed seed: the same interval every time


def test_bootstrap_ci_of_no_spread_is_the_value():
    assert bootstrap_ci([0.25]) == (0.25, 0.25)
    assert bootstrap_ci([0.25] * 6) == (0.25, 0.25)
    with pytest.raises(ConfigError, match="non-empty"):
        bootstrap_ci([])


def test_paired_comparison_known_answers():
    # the target beats the best baseline by exactly 0.125 on every seed; which baseline is
    # best changes from seed to seed (the mean of the minima, not the minimum of the means)
    a = {0: 0.5, 1: 0.75, 2: 0.5, 3: 1.0}
    b = {0: 1.0, 1: 0.25, 2: 0.75, 3: 0.5}
    target = {s: min(a[s], b[s]) - 0.125 for s in a}
    r = paired_comparison(target, [a, b])
    assert r["n"] == 4 and r["seeds"] == [0, 1, 2, 3]
    assert r["differences"] == [-0.125] * 4 and r["mean_difference"] == -0.125
    assert (r["ci_low"], r["ci_high"]) == (-0.125, -0.125) and r["fraction_holds"] == 1.0
    # against the minimum of the MEANS (0.625) the target (mean 0.3125) would look better by 0.3125
    assert np.mean(list(target.values())) - min(np.mean(list(a.values())), np.mean(list(b.values()))) == -0.3125

    # known differences; a seed missing from a baseline is no pair and is left out
    d = {0: -0.2, 1: -0.1, 2: 0.1, 3: 0.2, 4: -0.3}
    base = {s: 1.0 for s in d}
    r = paired_comparison({**{s: 1.0 + v for s, v in d.items()}, 9: 0.0}, [base])
    assert r["seeds"] == [0, 1, 2, 3, 4] and r["fraction_holds"] == pytest.approx(0.6)
    assert r["mean_difference"] == pytest.approx(-0.06)
    assert r["ci_low"] < -0.06 < r["ci_high"] and r["ci_low"] >= -0.3 and r["ci_high"] <= 0.2
    with pytest.raises(ConfigError, match="no seed"):
        paired_comparison({0: 1.0}, [{1: 1.0}])
    with pytest.raises(ConfigError, match="no baseline"):
        paired_comparison({0: 1.0}, [])


def test_cell_keys_name_what_determines_a_result():
    grid = SweepGrid(models=MODELS, minutes=MINUTES, seeds=SEEDS, quick=True)
    cells = plan_cells(grid, {"": ("collection-a", 0.3)})
    assert len(cells) == len(MODELS) * (len(MINUTES) + 1) * len(SEEDS)
    assert len({c.key for c in cells}) == len(cells)
    # the field's spelling is not in the key (the collection key names the field)...
    again = plan_cells(dataclasses.replace(grid, fields=("so2",)), {"so2": ("collection-a", 0.3)})
    assert [c.key for c in again] == [c.key for c in cells]
    # ...the collection and the training config are
    other = plan_cells(grid, {"": ("collection-b", 0.3)})
    assert not {c.key for c in other} & {c.key for c in cells}
    slow = plan_cells(dataclasses.replace(grid, quick=False), {"": ("collection-a", 0.3)})
    assert not {c.key for c in slow} & {c.key for c in cells}
    # a minute point at or beyond the collection's length is left to the full set
    assert {c.minutes for c in plan_cells(grid, {"": ("collection-a", 0.15)})} == {0.1, FULL}


# -- the sweep on Ray ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def ray_local():
    import ray  # a test dependency (pyproject's test extra): a missing Ray fails, never skips

    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A folder laid out as the command line's defaults: runs/pipeline/<field>-<key>/ under it."""
    return tmp_path_factory.mktemp("sweep")


@pytest.fixture(scope="module")
def pipeline(workdir):
    p = resolve_pipeline(PipelineArgs(quick=True))
    return dataclasses.replace(p, collection_dir=workdir / p.collection_dir, models_dir=workdir / p.models_dir)


def _sweep(pipeline, cache, batch=4):
    grid = SweepGrid(models=MODELS, minutes=MINUTES, seeds=SEEDS, quick=True)
    return run_sweep(grid, {"": pipeline}, cache, batch=batch, claim=CLAIM)


def _files(cache):
    return {p: p.stat().st_mtime_ns for p in sorted(Path(cache).rglob("*.json"))}


@pytest.fixture(scope="module")
def first(ray_local, pipeline, workdir):
    cache = workdir / "cells"
    results = _sweep(pipeline, cache)
    return cache, results, _files(cache)


def test_first_run_computes_every_cell(first, workdir):
    cache, results, files = first
    n = len(MODELS) * (len(MINUTES) + 1) * len(SEEDS)
    assert results["cells"] == {"total": n, "cached": 0, "computed": n}
    assert len(files) == n and results["workers"] == 2
    r = results["fields"][""]
    assert r["minutes"][:2] == list(MINUTES) and r["minutes"][2] > MINUTES[-1]  # the full set, in minutes
    assert r["seeds"] == list(SEEDS) and 0 < r["noise_floor"] < 1
    for kind in MODELS:
        m = r["models"][kind]
        runs = np.array(m["rmse_runs"])
        assert runs.shape == (3, 3) and np.all(runs > 0)
        assert np.allclose(m["rmse_mean"], runs.mean(axis=1))
        assert all(lo <= mu <= hi for lo, mu, hi in zip(m["rmse_ci_low"], m["rmse_mean"], m["rmse_ci_high"]))
    c = r["claim"]
    expected = [e - s for e, s in zip(r["models"]["equivariant"]["rmse_runs"][2], r["models"]["shallow"]["rmse_runs"][2])]
    assert c["differences"] == expected and c["n"] == 3
    assert c["fraction_holds"] == np.mean(np.array(expected) < 0)
    # paired: every kind of one (minutes, seed) trained on the same subset with the same early-stopping
    # split; longer points hold more rows
    cells = [json.loads(p.read_text()) for p in files]
    rows = {}
    for cell in cells:
        rec, h = cell["record"], cell["history"]
        rows.setdefault((rec["minutes"], rec["seed"]), set()).add((h["n_train"], h["n_val"]))
    assert all(len(v) == 1 for v in rows.values())
    for s in SEEDS:
        assert sum(rows[(0.1, s)].pop()) < sum(rows[(0.2, s)].pop()) < sum(rows[(FULL, s)].pop())
    assert all(cell["compute"]["ensemble_size"] <= 4 for cell in cells)


def test_full_set_cells_are_the_collections_own_models(first, pipeline):
    """The whole training set with the collection's seed is exactly how the staged collection trains
    its final models: the cell (one member of an ensemble) must score what the checkpoint scores."""
    from downwash.checkpoint import load_checkpoint
    from downwash.sweep_cells import load_collection
    from downwash.train import rmse

    _, results, _ = first
    _, val, _ = load_collection(pipeline.collection_dir)
    for kind in MODELS:
        model, _ = load_checkpoint(pipeline.models_dir / f"{kind}.pt", expect_kind=kind)
        assert results["fields"][""]["models"][kind]["rmse_runs"][-1][0] == rmse(model, val)[0]


def test_second_run_computes_nothing_and_gives_the_same_results(first, pipeline):
    cache, results, files = first
    again = _sweep(pipeline, cache)
    assert again["cells"] == {"total": len(files), "cached": len(files), "computed": 0} and again["workers"] == 0
    assert again["fields"] == results["fields"]
    assert _files(cache) == files  # no file rewritten


def test_a_partial_sweep_recomputes_only_the_missing_cells(first, pipeline):
    cache, results, files = first
    paths = list(files)
    gone = paths[::5]  # a few cells of each kind, of several minute points and seeds
    for p in gone[1:]:
        p.unlink()
    gone[0].write_text('{"truncated')  # a half-written file from another writer counts as missing
    again = _sweep(pipeline, cache, batch=1)  # other batches than the first run: one cell per task
    assert again["cells"]["computed"] == len(gone)
    now = _files(cache)
    assert set(now) == set(files)
    assert [p for p in paths if now[p] != files[p]] == gone  # only the missing ones were written
    assert again["fields"] == results["fields"]  # bit for bit, whatever the batching


def test_two_node_cluster_gives_the_same_results(first, ray_local, pipeline, workdir):
    """``address``: the same sweep on a running cluster of two nodes of one CPU each."""
    from ray.cluster_utils import Cluster

    _, results, _ = first
    ray_local.shutdown()  # this process's own Ray; run_sweep connects to the cluster's
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        grid = SweepGrid(models=MODELS, minutes=MINUTES, seeds=SEEDS, quick=True)
        got = run_sweep(grid, {"": pipeline}, workdir / "cluster_cells", address=cluster.address, batch=3, claim=CLAIM)
        assert not ray_local.is_initialized()  # connected for the sweep only
    finally:
        cluster.shutdown()
    assert got["cells"]["computed"] == got["cells"]["total"] and got["workers"] == 2
    assert got["fields"] == results["fields"]
    nodes = {json.loads(p.read_text())["compute"]["ray_node"] for p in (workdir / "cluster_cells").rglob("*.json")}
    assert len(nodes) == 2  # both nodes trained cells


def test_command_line_on_a_cached_sweep(first, workdir):
    """`python -m experiments.sweep` over the cells of the first run: no Ray, the same numbers, all files."""
    _, results, files = first
    cmd = [sys.executable, "-m", "experiments.sweep", "--quick", "--models", ",".join(MODELS),
           "--minutes", ",".join(map(str, MINUTES)), "--seeds", ",".join(map(str, SEEDS)), "--cache-dir", "cells",
           "--out", "cli"]
    proc = subprocess.run(cmd, cwd=workdir, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads((workdir / "cli" / "results.json").read_text())
    assert out["cells"] == {"total": len(files), "cached": len(files), "computed": 0}
    assert out["fields"][""]["models"] == results["fields"][""]["models"]
    assert out["fields"][""]["claim"] is None and "not in the grid" in out["fields"][""]["claim_skipped"]
    assert out["provenance"]["pipelines"][""]["pipeline_key"] == results["fields"][""]["collection_key"]
    assert "| equivariant |" in (workdir / "cli" / "results.md").read_text()
    assert (workdir / "cli" / "sweep.png").stat().st_size > 0
