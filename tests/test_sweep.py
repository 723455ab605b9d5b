"""The resumable sweep (`downwash.sweep`, `python -m experiments.sweep`): cells, cache, Ray, statistics.

One quick staged collection and one local Ray of 2 CPUs serve the whole module.
The first sweep computes every cell; a second run must compute none and give the
same results; deleting (and corrupting) some cache files must recompute exactly
those, with the numbers of the first run bit for bit although they are batched
differently; a two-node Ray cluster driven through the command line must give the
same numbers too. The statistics are checked on numbers whose answer is known. A bad
--workers, --address or grid is refused before any work, and a sweep stopped by
SIGTERM shuts its local Ray down.
"""

import dataclasses
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError
from downwash.sweep import run_sweep
from downwash.sweep_cells import FULL, SweepGrid, plan_cells
from downwash.sweep_stats import Claim, bootstrap_ci, paired_comparison
from experiments.common import PAIRWISE_KINDS, PipelineArgs, parse_args, resolve_pipeline

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


def _no_work(*args, **kwargs):
    raise AssertionError("the sweep began its work (the collection) before refusing the command line")


def _free_loopback_port() -> int:
    """A loopback port nothing listens on (bound, then let go)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_workers_beyond_the_usable_cores_is_a_usage_error(tmp_path, monkeypatch, capsys):
    """--workers sizes a local Ray: more CPUs than this process may use would start that many workers
    (--workers 1000000000 asked Ray for 10^9). One line, exit 2, before any work; the help states it."""
    from downwash.sweep import check_execution
    from experiments.sweep import SweepArgs
    from sim.physics import usable_cores

    cores = usable_cores()
    monkeypatch.chdir(tmp_path)
    for workers in (cores + 1, 1_000_000_000):
        for address in ([], ["--address", "127.0.0.1:6379"]):  # unused with --address, bounded the same
            with pytest.raises(SystemExit) as exit_info:
                parse_args(SweepArgs, "sweep", ["--workers", str(workers), *address, "--out", "out"])
            err = capsys.readouterr().err
            assert exit_info.value.code == 2 and err.count("\n") == 1
            assert f"--workers: expected 0 (all usable cores) or 1..{cores}" in err and f"got {workers}" in err
    assert parse_args(SweepArgs, "sweep", ["--workers", str(cores), "--out", "out"]).workers == cores
    with pytest.raises(ConfigError, match=rf"--workers: .*1\.\.{cores}"):
        check_execution(cores + 1, 1)  # the library's own check (run_sweep, map_on_ray, sample_efficiency)
    # the command line of the report: one line on stderr, at once, nothing written
    proc = subprocess.run([sys.executable, "-m", "experiments.sweep", "--workers", "1000000000"], cwd=tmp_path,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "--workers" in proc.stderr, proc.stderr
    assert sorted(os.listdir(tmp_path)) == []


@pytest.mark.parametrize("address", ["nonsense", "nonsense:", ":6379", "host:0", "host:65536", "host:port",
                                     "host:-1", "a b:6379", "http://host:6379", "host:6379/x"])
def test_malformed_address_is_a_usage_error(address, tmp_path, monkeypatch, capsys):
    from experiments.sweep import SweepArgs

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        parse_args(SweepArgs, "sweep", ["--address", address, "--out", "out"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1
    assert "--address: expected HOST:PORT" in err and "port 1-65535" in err and repr(address) in err
    assert sorted(os.listdir(tmp_path)) == []
    for good in ("auto", "127.0.0.1:6379", "head-node.cluster:6379", "ray://head:10001", "[::1]:6379"):
        assert parse_args(SweepArgs, "sweep", ["--address", good, "--out", "out"]).address == good


def test_address_where_nothing_answers_fails_at_once_before_any_work(tmp_path, monkeypatch):
    """Ray retries an address where nothing answers for minutes, silently; the sweep tries a TCP
    connection first (a few seconds at most), before the collection, and names the address."""
    import experiments.sweep as cli
    from experiments.sweep import SweepArgs

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli, "resolve_pipeline", _no_work)
    address = f"127.0.0.1:{_free_loopback_port()}"
    args = parse_args(SweepArgs, "sweep", ["--quick", "--address", address, "--out", "out", "--cache-dir", "cells"])
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=rf"^--address {re.escape(address)}: no Ray cluster answers there "
                                          r"\(connection refused\)"):
        cli.run(args)
    assert time.perf_counter() - t0 < 15  # a refusal comes at once (the grid's imports included)
    assert sorted(os.listdir(tmp_path)) == []

    from downwash.sweep import check_address

    with socket.socket() as listening:  # something answering there passes
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        check_address(f"127.0.0.1:{listening.getsockname()[1]}")
    check_address("auto")  # looked up by Ray when it starts


def test_a_grid_too_large_for_one_sweep_is_refused_naming_its_size(tmp_path, monkeypatch):
    """Nothing bounded the seeds: a million of them planned millions of cells (and a bootstrap of a
    million trials) after the collection. Each seed must also fit a generator's seed."""
    import experiments.sweep as cli
    from experiments.sweep import SweepArgs

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli, "resolve_pipeline", _no_work)
    seeds = ",".join(map(str, range(1_000_000)))
    args = parse_args(SweepArgs, "sweep", ["--seeds", seeds, "--out", "out", "--cache-dir", "cells"])
    with pytest.raises(ConfigError, match="seeds: 1000000 seeds make 24000000 cells"):
        cli.run(args)
    assert sorted(os.listdir(tmp_path)) == []

    from downwash.sweep_cells import MAX_CELLS, MAX_SEEDS, SEED_MAX

    with pytest.raises(ConfigError, match=rf"seeds: {MAX_SEEDS + 1} seeds make {24 * (MAX_SEEDS + 1)} cells \(1 field "
                                          rf"x 3 models x 8 minute points x {MAX_SEEDS + 1} seeds\)"):
        SweepGrid(seeds=tuple(range(MAX_SEEDS + 1)))
    with pytest.raises(ConfigError, match=rf"grid: 100800 cells \(1 field x 6 models x 21 minute points x 800 "
                                          rf"seeds\); a sweep takes at most {MAX_SEEDS} seeds and {MAX_CELLS} cells"):
        SweepGrid(models=PAIRWISE_KINDS, minutes=tuple(range(1, 21)), seeds=tuple(range(800)))
    with pytest.raises(ConfigError, match=rf"seeds: expected integers in 0\.\.{SEED_MAX}"):
        SweepGrid(seeds=(0, SEED_MAX + 1))
    assert SweepGrid(seeds=tuple(range(MAX_SEEDS - 1)) + (SEED_MAX,)).seeds[-1] == SEED_MAX


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


def _alive(process) -> bool:
    import psutil

    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def test_sigterm_ends_the_sweep_and_its_local_ray(first, workdir):
    """A sweep killed by SIGTERM (kill, a scheduler's time limit) must shut its local Ray down and say so:
    Ray's core answered the signal by aborting the process, which left the cluster's processes (``ray::``
    workers, children of no one) running in the project folder. A rerun resumes from the cached cells."""
    import ray  # noqa: F401  (its copy of psutil comes on the path with it)
    import psutil

    seeds = ",".join(map(str, range(300)))  # far more cells than land in the few seconds before the signal
    cmd = [sys.executable, "-m", "experiments.sweep", "--quick", "--models", ",".join(MODELS), "--minutes",
           ",".join(map(str, MINUTES)), "--seeds", seeds, "--cache-dir", "sigterm_cells", "--out", "sigterm",
           "--batch", "1"]
    proc = subprocess.Popen(cmd, cwd=workdir, env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    driver, seen = psutil.Process(proc.pid), []
    try:
        deadline = time.monotonic() + 120
        while not any((workdir / "sigterm_cells").rglob("*.json")):  # Ray is up and computing
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1][-3000:]
            time.sleep(0.2)
        seen = driver.children(recursive=True)
        assert any("ray::" in " ".join(p.cmdline()) for p in seen if _alive(p))
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
        assert "sweep stopped by SIGTERM" in err and "the same command computes the rest" in err
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in seen) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = [" ".join(p.cmdline())[:80] for p in seen if _alive(p)]
        assert not left, left
        strays = []  # ray:: processes of this run that began after the list was taken
        for p in psutil.process_iter(["cmdline", "cwd"]):
            if "ray::" in " ".join(p.info["cmdline"] or []) and p.info["cwd"] == str(workdir) and _alive(p):
                strays.append(p.info["cmdline"][0])
        assert not strays, strays
    finally:  # a failing run leaves nothing behind either
        for p in [driver, *seen]:
            if _alive(p):
                p.kill()
        proc.communicate()
