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
    """A quick staged collection: models in workdir/models, logs in workdir/staged."""
    _run(["experiments.staged_collection", "--quick", "--out", "staged", "--models-dir", "models"], workdir)
    return workdir


def test_staged_collection_results(collection):
    r = json.loads((collection / "staged" / "results.json").read_text())
    assert [s["stage"] for s in r["stages"]] == [0, 1, 2]
    assert r["stages"][0]["separation"] == [1.35, 1.75] and r["stages"][2]["separation"][0] < 0.6
    assert r["stages"][0]["deployed_val_rmse"] is None and r["stages"][1]["deployed_val_rmse"] > 0
    for kind in ("shallow", "deep", "equivariant"):
        assert r["models"][kind]["val_rmse"] > 0
        assert (collection / "models" / f"{kind}.pt").is_file()
    assert r["validation_minutes"] > 0 and r["wall_seconds"] > 0
    manifest = json.loads((collection / "staged" / "manifest.json").read_text())
    assert manifest["complete"] is True


def test_lemniscate_all_conditions(collection):
    _run(["experiments.lemniscate", "--quick", "--out", "lem", "--models-dir", "models"], collection)
    r = json.loads((collection / "lem" / "results.json").read_text())
    assert set(r["conditions"]) == {"no_downwash", "baseline", "oracle", "shallow", "deep", "equivariant"}
    for name, c in r["conditions"].items():
        assert c["pos_err_3d_mean"] >= 0 and len(c["per_seed"]["pos_err_3d_mean"]) == 1
        assert ("improvement_pos_3d" in c) == (name not in ("baseline", "no_downwash"))
    for fig in ("errors_over_time.png", "error_distributions.png", "paths.png"):
        assert (collection / "lem" / fig).stat().st_size > 1000


def test_transect_and_custom_field(workdir):
    field_mod = workdir / "my_field.py"
    field_mod.write_text("from sim.field import DownwashField\n\ndef make():\n    return DownwashField(strength=5.0, swirl=0.2)\n")
    _run(["experiments.transect", "--quick", "--out", "tr", "--conditions", "baseline,oracle",
          "--field", "my_field:make"], workdir)
    r = json.loads((workdir / "tr" / "results.json").read_text())
    assert r["args"]["field"] == "my_field:make" and set(r["conditions"]) == {"baseline", "oracle"}


def test_train_sample_efficiency_force_maps(collection):
    _run(["experiments.train", "--quick", "--model", "equivariant", "--logs", "staged/stage0/train",
          "--val-logs", "staged/stage0/val", "--out", "train"], collection)
    r = json.loads((collection / "train" / "results.json").read_text())
    assert r["model"] == "equivariant" and r["n_params"] == 258
    assert r["val_rmse"] > 0 and len(r["val_rmse_axis"]) == 3 and r["noise_floor"] > 0
    _run(["experiments.sample_efficiency", "--quick", "--collection", "staged", "--out", "se", "--minutes", "0.1"],
         collection)
    r = json.loads((collection / "se" / "results.json").read_text())
    assert len(r["minutes"]) == 2 and set(r["models"]) == {"shallow", "deep", "equivariant"}
    assert all(len(m["rmse_mean"]) == 2 for m in r["models"].values())
    _run(["experiments.force_maps", "--quick", "--models-dir", "models", "--out", "fm"], collection)
    assert (collection / "fm" / "force_maps_down.png").is_file()
    assert set(json.loads((collection / "fm" / "results.json").read_text())["maps"]) == {"equivariant", "deep", "shallow"}


def test_benchmark_quick(workdir):
    _run(["experiments.benchmark", "--quick", "--out", "bench"], workdir)
    r = json.loads((workdir / "bench" / "results.json").read_text())
    for key in ("bare_mj_step_per_s", "closed_loop_serial_steps_per_s", "real_time_factor_serial",
                "closed_loop_batched_world_steps_per_s", "batched_over_bare"):
        assert r[key] > 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["experiments.lemniscate", "--conditions", "baseline,wind"], "unknown.*wind.*allowed"),
        (["experiments.lemniscate", "--separation", "0.1"], "separation.*allowed 0.3-2.0"),
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


def test_staged_collection_resumes_after_kill(tmp_path):
    """Kill the collection mid-stage 1; the rerun keeps stage 0 untouched and completes."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "experiments.staged_collection", "--quick", "--out", "s", "--models-dir", "m"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    manifest = tmp_path / "s" / "manifest.json"
    deadline = time.time() + 300
    while time.time() < deadline:
        if manifest.is_file() and json.loads(manifest.read_text()).get("stages", {}).get("0", {}).get("model_done"):
            break
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    state = json.loads(manifest.read_text())
    assert state["stages"]["0"]["model_done"] and not state.get("complete")
    stage0 = {p: p.stat().st_mtime_ns for p in (tmp_path / "s" / "stage0").rglob("*") if p.is_file()}
    _run(["experiments.staged_collection", "--quick", "--out", "s", "--models-dir", "m"], tmp_path)
    assert json.loads(manifest.read_text())["complete"] is True
    for p, mtime in stage0.items():
        assert p.stat().st_mtime_ns == mtime, f"{p} was redone"
    from sim.logs import load_log

    for p in (tmp_path / "s").rglob("*.npz"):
        load_log(p)  # every log on disk is whole
    assert all((tmp_path / "m" / f"{k}.pt").is_file() for k in ("shallow", "deep", "equivariant"))
