"""`python -m experiments.swarm`: the swarm stages, the models of sets, every preset and law; resumable."""

import json
import re
import subprocess
import sys

import pytest

from downwash.checkpoint import load_checkpoint


def _run(args, cwd, check=True):
    proc = subprocess.run([sys.executable, "-m", "experiments.swarm", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"{args} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
    return proc


ARGS = ["--quick", "--presets", "stack3,swap", "--aggregations", "linear,velocity", "--collection-dir", "pc",
        "--models-dir", "pm"]


@pytest.fixture(scope="module")
def swarm_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("swarm")
    _run(ARGS + ["--out", "sw"], work)
    return work


def test_every_preset_law_and_condition_is_reported(swarm_run):
    r = json.loads((swarm_run / "sw" / "results.json").read_text())
    models = ["summed_pairwise", "deepsets_equivariant-pair", "deepsets_equivariant-mixed",
              "deepsets_equivariant-kinds", "deepsets-pair", "deepsets-mixed", "deepsets-kinds"]
    # each model also behind the guard; the LQR with integral action, the observer, each model with the observer
    names = ["baseline", "oracle", *models, *(f"{m}_guarded" for m in models), "integral", "dob",
             *(f"{m}_dob" for m in models)]
    assert r["conditions"] == names
    assert set(r["summary"]) == {"linear", "velocity"}
    for law in ("linear", "velocity"):
        assert set(r["summary"][law]) == {"stack3", "swap"}
        for preset, entry in r["summary"][law].items():
            assert set(entry) == set(names)
            # the oracle knows the wake and how the wakes combine: it beats no model
            assert entry["oracle"]["improvement_pos_3d"] > 0.2, (law, preset)
            # each model's vehicle kinds are in its data here (paper quads), and each crash rate has its interval
            assert all(entry[c]["kinds_in_data"] is True for c in names if c not in ("baseline", "oracle", "integral", "dob"))
            assert all(entry[c]["crash_rate_ci95"][0] <= entry[c]["crash_rate"] <= entry[c]["crash_rate_ci95"][1]
                       for c in names)
            shares = entry["summed_pairwise_guarded"]["compensation"]  # how much of it the guard applied
            assert sum(shares.values()) == pytest.approx(1.0) and "compensation" not in entry["summed_pairwise"]
    for preset in ("stack3", "swap"):  # a results.json and a figure per preset
        per = json.loads((swarm_run / "sw" / preset / "results.json").read_text())
        assert per["preset"] == preset and set(per["laws"]) == {"linear", "velocity"}
        assert (swarm_run / "sw" / preset / "errors.png").is_file()
    # every follower counts: stack3 has two
    assert r["presets"]["stack3"]["linear"]["preset"]["roles"] == ["leader", "follower", "follower"]


def test_each_law_has_its_own_collection_and_models_know_it(swarm_run):
    r = json.loads((swarm_run / "sw" / "results.json").read_text())
    dirs = {law: r["laws"][law]["collection_dir"] for law in ("linear", "velocity")}
    assert dirs["linear"] != dirs["velocity"]
    for law, d in dirs.items():
        mixed = load_checkpoint(swarm_run / d / "models" / "deepsets_equivariant-mixed.pt")
        assert mixed.record["aggregation"]["name"] == law  # trained on this law's many-vehicle flights
        pair = load_checkpoint(next(swarm_run.glob("swarm-pair-*/deepsets_equivariant-pair.pt")))
        assert pair.record["aggregation"] is None  # two-vehicle data: every law is the pairwise field


def test_the_stages_of_other_kinds_are_flown_and_the_kinds_models_read_them(swarm_run):
    from downwash.swarm_collection import KIND_STAGES
    from downwash_core.vehicles import DEFAULT_VEHICLE
    from sim.logs import load_log

    r = json.loads((swarm_run / "sw" / "results.json").read_text())
    d = swarm_run / r["laws"]["linear"]["collection_dir"]
    for name, kinds, _ in KIND_STAGES:
        logs = sorted((d / f"kinds-{name}" / "train").glob("*.npz"))
        assert logs, name
        assert load_log(logs[0]).meta.get("kinds", [DEFAULT_VEHICLE] * len(kinds)) == list(kinds)
    for kind in ("deepsets_equivariant", "deepsets"):
        reads = load_checkpoint(d / "models" / f"{kind}-kinds.pt").model
        blind = load_checkpoint(d / "models" / f"{kind}-mixed.pt").model
        assert reads.kinds and not blind.kinds
        # the same data: its kind columns vary (the X500 and the Crazyflies), so their spread was fitted
        assert (reads.in_std[-4:] != 1.0).all()


def test_a_rerun_reuses_the_collections_and_reproduces_the_numbers(swarm_run):
    r1 = json.loads((swarm_run / "sw" / "results.json").read_text())
    logs = sorted((swarm_run).glob("pc/../**/stage3/train/*.npz"))
    mtimes = [p.stat().st_mtime_ns for p in logs]
    assert logs
    _run(ARGS + ["--out", "sw2"], swarm_run)
    r2 = json.loads((swarm_run / "sw2" / "results.json").read_text())
    assert [p.stat().st_mtime_ns for p in logs] == mtimes  # nothing flown again
    assert r2["summary"] == r1["summary"]  # same seeds, same models: the same numbers


def test_swarm_stage_logs_are_checked_a_missing_one_reflown_an_altered_one_refused(swarm_run):
    """The swarm stages' manifest records every log, as the two-vehicle collection's: a missing log is
    flown again with the same data; an altered one stops the run, named, before any training."""
    import numpy as np

    from sim.logs import load_log

    r = json.loads((swarm_run / "sw" / "results.json").read_text())
    sdir = swarm_run / r["laws"]["linear"]["collection_dir"] / "stage3"
    manifest = json.loads((sdir.parent / "manifest.json").read_text())
    assert manifest["stages"]["3"]["flights_done"] and "train/flight_000.npz" in manifest["stages"]["3"]["files"]
    victim = sdir / "train" / "flight_000.npz"
    before = load_log(victim).arrays
    victim.unlink()
    _run(ARGS + ["--out", "sw3", "--presets", "stack3", "--aggregations", "linear"], swarm_run)
    after = load_log(victim).arrays
    assert before.keys() == after.keys() and all(np.array_equal(before[k], after[k], equal_nan=True) for k in before)
    rel = next(k for k in sorted(manifest["stages"]["3"]["files"]) if k.startswith("val/"))
    altered = sdir / rel
    original = altered.read_bytes()
    altered.write_bytes(original + b"x")
    try:
        proc = _run(ARGS + ["--out", "sw4", "--presets", "stack3", "--aggregations", "linear"], swarm_run, check=False)
        assert proc.returncode != 0 and "do not match its manifest" in proc.stderr and rel in proc.stderr
    finally:
        altered.write_bytes(original)


@pytest.mark.parametrize("args, message", [
    (["--presets", "stack:n=9"], "2-8 vehicles, got 9"),
    (["--presets", "ring"], "preset: unknown 'ring'"),
    (["--aggregations", "cubic"], "unknown.*cubic.*allowed.*linear"),
    (["--seeds", "0"], "--seeds: expected >= 1"),
])
def test_bad_input_fails_before_any_flight(args, message, tmp_path):
    proc = _run(args + ["--out", "x"], tmp_path, check=False)
    assert proc.returncode != 0 and re.search(message, proc.stderr), proc.stderr[-1000:]
    assert not (tmp_path / "x").exists() and not (tmp_path / "runs").exists()
