"""Smoke runs of every `python -m experiments.*` with a tiny budget, plus their bad-input errors.

One staged collection (quick) is shared by the experiments that need trained models.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from downwash.models import STAGED_KINDS

ROOT = Path(__file__).resolve().parent.parent


def _run(args, cwd, check=True, timeout=600):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"{args} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("experiments")


@pytest.fixture(scope="module")
def collection(workdir):
    """A quick staged collection: models in workdir/models, logs in workdir/staged, results in workdir/sc."""
    _run(["experiments.staged_collection", "--quick", "--out", "sc", "--collection-dir", "staged",
          "--models-dir", "models"], workdir)
    return workdir


def test_staged_collection_results(collection):
    r = json.loads((collection / "sc" / "results.json").read_text())
    assert [s["stage"] for s in r["stages"]] == [0, 1, 2]
    assert r["stages"][0]["separation"] == [1.35, 1.75] and r["stages"][2]["separation"][0] < 0.6
    assert r["stages"][0]["deployed_val_rmse"] is None and r["stages"][1]["deployed_val_rmse"] > 0
    assert set(r["models"]) == set(STAGED_KINDS)  # the models with memory are trained when asked for
    for kind in STAGED_KINDS:
        assert r["models"][kind]["val_rmse"] > 0
        assert (collection / "models" / f"{kind}.pt").is_file()
    assert r["validation_minutes"] > 0 and r["wall_seconds"] > 0
    manifest = json.loads((collection / "staged" / "manifest.json").read_text())
    assert manifest["complete"] is True


def test_lemniscate_all_conditions(collection):
    _run(["experiments.lemniscate", "--quick", "--out", "lem", "--collection-dir", "staged", "--models-dir", "models"],
         collection)
    r = json.loads((collection / "lem" / "results.json").read_text())
    assert set(r["conditions"]) == {"no_downwash", "baseline", "oracle", "integral", "dob", *STAGED_KINDS,
                                    *(f"{k}_guarded" for k in STAGED_KINDS), *(f"{k}_dob" for k in STAGED_KINDS)}
    for name, c in r["conditions"].items():
        assert c["pos_err_3d_mean"] >= 0 and len(c["per_seed"]["pos_err_3d_mean"]) == 1
        assert c["crash_rate"] == 0.0 and c["per_seed"]["crashed"] == [False]
        assert ("improvement_pos_3d" in c) == (name not in ("baseline", "no_downwash"))
        assert ("compensation" in c) == name.endswith("_guarded")  # the guard's shares of full, partial, none
    assert r["guard"]["recovery"] > 0
    assert r["provenance"]["models_dir"] == "models" and r["provenance"]["code"]["version"]
    for fig in ("errors_over_time.png", "error_distributions.png", "paths.png"):
        assert (collection / "lem" / fig).stat().st_size > 1000


def _tracking(workdir, field_spec, out, experiment="transect"):
    args = [f"experiments.{experiment}", "--quick", "--duration", "6", "--out", out,
            "--conditions", "no_downwash,baseline,oracle"]
    _run(args + (["--field", field_spec] if field_spec else []), workdir)
    return json.loads((workdir / out / "results.json").read_text())["conditions"]


def test_a_custom_field_changes_the_tracking_outcome(workdir):
    """The --field object is the one that flies: a zero field makes baseline equal no_downwash
    exactly, and a stronger field raises the baseline error."""
    (workdir / "my_fields.py").write_text(
        "import numpy as np\nfrom sim.field import DownwashField\n\n"
        "def zero():\n    return lambda p_a, v_a, R_a, p_b, v_b: np.zeros(np.broadcast_shapes(p_a.shape, p_b.shape))\n\n"
        "def strong():\n    return DownwashField(strength=30.0)\n"
    )
    default = _tracking(workdir, "", "tr_default")
    zero = _tracking(workdir, "my_fields:zero", "tr_zero")
    strong = _tracking(workdir, "my_fields:strong", "tr_strong")
    assert zero["baseline"]["per_seed"] == {**zero["no_downwash"]["per_seed"]}
    assert default["baseline"]["pos_err_3d_mean"] > 2 * default["no_downwash"]["pos_err_3d_mean"]
    assert strong["baseline"]["pos_err_3d_mean"] > 1.5 * default["baseline"]["pos_err_3d_mean"]
    # the field the oracle compensates is the custom one too: it removes most of the strong field's error
    assert strong["oracle"]["pos_err_3d_mean"] < 0.5 * strong["baseline"]["pos_err_3d_mean"]


def test_a_custom_field_changes_the_staged_collection_and_force_maps(workdir):
    """The collection's labels and the force maps' truth come from the --field object."""
    _run(["experiments.force_maps", "--quick", "--field", "my_fields:zero", "--out", "fm_zero"], workdir)
    _run(["experiments.force_maps", "--quick", "--field", "my_fields:strong", "--out", "fm_strong"], workdir)
    zero = json.loads((workdir / "fm_zero" / "results.json").read_text())
    strong = json.loads((workdir / "fm_strong" / "results.json").read_text())
    assert zero["truth"]["down_top_max"] == 0.0 and strong["truth"]["down_top_max"] > 5.0
    z_floor = zero["provenance"]["pipeline"]["field"]
    assert z_floor["type"] == "callable" or "lambda" in json.dumps(z_floor)
    # each field got its own collection, keyed by its provenance
    assert zero["provenance"]["models_dir"] != strong["provenance"]["models_dir"]
    sc_zero = json.loads((Path(workdir / zero["provenance"]["collection_dir"]) / "manifest.json").read_text())
    assert sc_zero["complete"] and sc_zero["provenance"]["field"] == zero["provenance"]["pipeline"]["field"]


def test_train_sample_efficiency_force_maps(collection):
    _run(["experiments.train", "--quick", "--model", "equivariant", "--logs", "staged/stage0/train",
          "--val-logs", "staged/stage0/val", "--out", "train"], collection)
    r = json.loads((collection / "train" / "results.json").read_text())
    assert r["model"] == "equivariant" and r["n_params"] == 258
    assert r["val_rmse"] > 0 and len(r["val_rmse_axis"]) == 3 and r["noise_floor"] > 0
    _run(["experiments.sample_efficiency", "--quick", "--collection-dir", "staged", "--models-dir", "models",
          "--out", "se", "--minutes", "0.1", "--workers", "2"], collection)
    r = json.loads((collection / "se" / "results.json").read_text())
    assert len(r["minutes"]) == 2 and set(r["models"]) == {"shallow", "deep", "equivariant"} and r["trials"] == 2
    for m in r["models"].values():
        assert len(m["rmse_mean"]) == 2 and all(lo <= mu <= hi for lo, mu, hi in
                                                 zip(m["rmse_ci_low"], m["rmse_mean"], m["rmse_ci_high"]))
    assert r["cells"] == {"total": 12, "cached": 0, "computed": 12} and r["claim"] is None
    assert (collection / "se" / "sample_efficiency.png").is_file() and (collection / "se" / "results.md").is_file()
    _run(["experiments.force_maps", "--quick", "--collection-dir", "staged", "--models-dir", "models", "--out", "fm"],
         collection)
    assert (collection / "fm" / "force_maps_down.png").is_file()
    assert set(json.loads((collection / "fm" / "results.json").read_text())["maps"]) == set(STAGED_KINDS)


def test_benchmark_quick(workdir):
    _run(["experiments.benchmark", "--quick", "--out", "bench"], workdir)
    r = json.loads((workdir / "bench" / "results.json").read_text())
    for key in ("bare_mj_step_per_s", "closed_loop_serial_steps_per_s", "real_time_factor_serial",
                "closed_loop_batched_world_steps_per_s", "batched_over_bare", "serial_over_bare_guarded",
                "batched_over_bare_guarded", "guarded_over_unguarded_serial", "guarded_over_unguarded_batched",
                "mujoco_rollout_world_steps_per_s", "batched_over_mujoco_rollout",
                "formation5_mujoco_rollout_world_steps_per_s", "formation5_batched_over_mujoco_rollout",
                "compiled_controller_over_builtin_serial", "compiled_field_over_builtin_batched",
                "mellinger_over_builtin_serial"):
        assert r[key] > 0
    # the user's components of docs/extending.md flew: their rates are their own, not the built-in ones'
    assert r["closed_loop_serial_steps_per_s_pd_recipe"] != r["closed_loop_serial_steps_per_s_oracle"]
    if "swarm_agent_steps_per_s_native" in r:  # the swarm is measured with the `rl` extra only
        assert r["swarm_mujoco_rollout_world_steps_per_s"] > 0 and r["swarm_native_over_mujoco_rollout"] > 0
    assert {"batched_over_mujoco_rollout", "formation5_batched_over_mujoco_rollout",
            "compiled_field_over_builtin_serial"} <= set(r["targets"])
    # one round: no interval of a median, for every simulation ratio aimed for
    intervals = r["ratio_intervals"]
    assert {"serial_over_bare", "batched_over_mujoco_rollout", "compiled_controller_over_builtin_batched",
            "guarded_over_unguarded_serial"} <= set(intervals) and set(intervals.values()) == {None}


def test_the_benchmarks_interval_of_a_median_holds_it_as_often_as_it_says():
    """`median_interval`: order statistics x_(4), x_(12) of 15 rounds; the interval holds the sample median; over
    many draws of skewed rounds it holds the true median at least 95 % of the time (96.5 % for 15 rounds)."""
    import numpy as np

    from experiments.benchmark import median_interval

    rng = np.random.default_rng(0)
    x = rng.permutation(np.arange(15.0))
    assert median_interval(x) == [3.0, 11.0] and median_interval(x[:5]) is None and median_interval(x[:6]) == [
        float(np.sort(x[:6])[0]), float(np.sort(x[:6])[5])]
    held = 0
    for _ in range(4000):
        rounds = rng.lognormal(0.0, 0.5, size=15)  # true median 1
        lo, hi = median_interval(rounds)
        assert lo <= np.median(rounds) <= hi
        held += lo <= 1.0 <= hi
    assert 0.95 <= held / 4000 <= 0.98


@pytest.mark.parametrize(
    "args, message",
    [
        (["experiments.lemniscate", "--conditions", "baseline,wind"], "unknown.*wind.*allowed"),
        (["experiments.lemniscate", "--separation", "0.1"], "--separation: expected a finite number in \\[0.3, 2\\]"),
        (["experiments.transect", "--seeds", "0"], "seeds"),
        (["experiments.lemniscate", "--field", "nope"], "MODULE:FACTORY"),
        (["experiments.lemniscate", "--field", "no_such_module:make"], "cannot import"),
        (["experiments.train", "--model", "huge", "--logs", ".", "--val-logs", "."], "unknown 'huge'"),
        (["experiments.staged_collection", "--stage-minutes", "0"], "stage-minutes"),
        (["experiments.sample_efficiency", "--minutes", "a,b"], "comma list"),
    ],
)
def test_bad_input_fails_before_work(args, message, tmp_path):
    proc = _run(args + ["--out", str(tmp_path / "o")], tmp_path, check=False, timeout=120)
    assert proc.returncode != 0
    import re

    assert re.search(message, proc.stderr), proc.stderr[-2000:]
    assert not (tmp_path / "o" / "results.json").exists()


def test_train_rejects_empty_and_foreign_logs(tmp_path):
    (tmp_path / "empty").mkdir()
    proc = _run(["experiments.train", "--logs", "empty", "--val-logs", "empty"], tmp_path, check=False, timeout=120)
    assert proc.returncode != 0 and "empty" in proc.stderr
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "x.npz").write_text("not a log")
    proc = _run(["experiments.train", "--logs", "foreign", "--val-logs", "foreign"], tmp_path, check=False, timeout=120)
    assert proc.returncode != 0 and "x.npz" in proc.stderr


def _digests(folder):
    """SHA-256 of every flight log's arrays and every checkpoint's tensors under `folder`, by relative path."""
    import hashlib

    import numpy as np
    import torch

    out = {}
    for path in sorted(folder.rglob("*.npz")):
        with np.load(path, allow_pickle=False) as z:
            out[str(path.relative_to(folder))] = hashlib.sha256(
                b"".join(z[k].tobytes() for k in sorted(z.files) if k != "__meta__")).hexdigest()
    for path in sorted(folder.rglob("*.pt")):
        state = torch.load(path, weights_only=True)["state_dict"]
        out[str(path.relative_to(folder))] = hashlib.sha256(
            b"".join(state[k].numpy().tobytes() for k in sorted(state))).hexdigest()
    return out


def test_staged_collection_resumes_after_a_kill_mid_stage(collection, tmp_path):
    """SIGKILL the collection at a random moment in the middle of a random stage (flights in batches
    of one), rerun it: no finished flight is redone or lost, and every log and model equals those
    of the uninterrupted run (the `collection` fixture, flown in batches of twelve)."""
    import random

    rng = random.Random()  # a different moment each run; the choice is in every failure message
    stage, after = rng.randrange(3), rng.randrange(1, 4)  # kill once `after` of the stage's 4 flights are on disk
    where = f"killed in stage {stage} after {after} flights"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "experiments.staged_collection", "--quick", "--batch-flights", "1", "--out", "o",
           "--collection-dir", "s", "--models-dir", "m"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stage_dir = tmp_path / "s" / f"stage{stage}"
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if len(list(stage_dir.glob("*/flight_*.npz"))) >= after:
            break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = {p: p.stat().st_mtime_ns for p in (tmp_path / "s").rglob("*.npz")}
    manifest = json.loads((tmp_path / "s" / "manifest.json").read_text())
    assert not manifest.get("complete"), where
    assert not manifest["stages"].get(str(stage), {}).get("flights_done"), f"{where}: the stage had already finished"
    assert len(list(stage_dir.glob("*/flight_*.npz"))) < 4, where
    _run(cmd[2:], tmp_path)
    assert json.loads((tmp_path / "s" / "manifest.json").read_text())["complete"] is True
    for p, mtime in done.items():
        assert p.stat().st_mtime_ns == mtime, f"{where}: {p} was flown again"
    resumed, uninterrupted = _digests(tmp_path / "s"), _digests(collection / "staged")
    assert resumed == uninterrupted, f"{where}: results differ from the uninterrupted run"
    assert _digests(tmp_path / "m") == _digests(collection / "models"), where


@pytest.mark.parametrize(
    "case, extra, message",
    [
        ("another field", ["--field", "my_fields:strong"], r"field\.strength: 10\.6 here, 30\.0 asked for"),
        ("another seed base", ["--seed", "1"], r"seed: 0 here, 1 asked for"),
        ("another config", [], r"collection\.clamp: 5\.0 here, 6\.0 asked for"),
        ("another kind under the name", [], r"holds a 'shallow' model, not the 'equivariant' model"),
    ],
)
def test_stale_models_are_never_reused(collection, workdir, tmp_path, case, extra, message):
    """Models trained on the default field (seed 0, default config) are refused, before any flight,
    for a run that asks for something else, with an error that names the difference and how to
    proceed. (Leaving the folders out collects afresh into a folder keyed by the new setup:
    test_a_custom_field_changes_the_staged_collection_and_force_maps.)"""
    import shutil

    (tmp_path / "my_fields.py").write_text(
        "from sim.field import DownwashField\n\ndef strong():\n    return DownwashField(strength=30.0)\n")
    models = tmp_path / "models"
    if case == "another config":
        _run(["experiments.staged_collection", "--quick", "--clamp", "5.0", "--out", "sc", "--collection-dir", "staged",
              "--models-dir", "models"], tmp_path)
    else:
        shutil.copytree(collection / "models", models)
    if case == "another kind under the name":
        shutil.copy(models / "shallow.pt", models / "equivariant.pt")
    args = ["experiments.lemniscate", "--quick", "--conditions", "baseline,equivariant", "--models-dir", "models",
            "--collection-dir", "staged", "--out", "lem", *extra]
    proc = _run(args, tmp_path, check=False, timeout=300)
    assert proc.returncode == 1  # a bad file (DataError): one line, no traceback
    import re

    assert re.search(message, proc.stderr), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and not (tmp_path / "lem" / "results.json").exists()
    if case == "another kind under the name":
        assert "delete it or point --models-dir elsewhere" in proc.stderr
    else:
        assert "Leave out --models-dir" in proc.stderr and "runs/pipeline/" in proc.stderr
