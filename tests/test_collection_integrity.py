"""A staged collection is trusted only as its manifest records it, and concurrent runs share its work.

One quick collection (the `collection` fixture) is made once; each test that changes logs
works on a copy. What is checked, on real logs and real runs:
- the manifest records every log of every stage (SHA-256, data digest, rows, samples);
- a deleted, altered or unlisted log stops every way of training on the collection
  (`load_collection`, `ensure_collection`, `ensure_models`, `collect`) with a DataError
  naming the file, before anything is written;
- a rerun of the collection re-flies only the missing flights, into the same data;
- the sweep's cell keys follow the data, not only the provenance;
- a field that ends most flights stops with the counts, not an internal error;
- two runs on one pipeline folder collect once (the second waits and reuses), and two
  sweeps on one cell cache compute each cell once.
Subprocesses have timeouts, so a lock that never lets go fails instead of hanging.
"""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from downwash_core.errors import CheckpointError, DataError
from downwash.checkpoint import checkpoint_digest, load_checkpoint
from downwash_core.locks import LOCK_NAME, holder
from downwash.models import PAIRWISE_KINDS, STAGED_KINDS
from downwash.manifest import MANIFEST_VERSION, collection_digest, file_sha256, write_manifest
from downwash.staged import CollectionConfig, collect, ensure_collection, ensure_models
from downwash.sweep_cells import SweepGrid, load_collection, plan_cells
from experiments.common import load_field
from sim.logs import load_log

ROOT = Path(__file__).resolve().parent.parent
CFG = CollectionConfig(quick=True)
RERUN = "python -m experiments.staged_collection"


@pytest.fixture(scope="module")
def field():
    return load_field("")


@pytest.fixture(scope="module")
def collection(tmp_path_factory, field):
    """A complete quick collection: base/staged (logs and manifest) and base/models."""
    base = tmp_path_factory.mktemp("integrity")
    collect(CFG, base / "staged", base / "models", field)
    return base


@pytest.fixture
def copy(collection, tmp_path):
    """A copy of the collection to change (mtimes kept, so an unchanged file keeps its mtime)."""
    shutil.copytree(collection / "staged", tmp_path / "staged")
    shutil.copytree(collection / "models", tmp_path / "models")
    return tmp_path


def _mtimes(base: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in sorted(base.rglob("*")) if p.suffix in (".npz", ".pt")}


def _manifest(base: Path) -> dict:
    return json.loads((base / "staged" / "manifest.json").read_text())


def test_the_manifest_records_every_log_of_every_stage(collection):
    m = _manifest(collection)
    assert m["version"] == MANIFEST_VERSION == 4 and m["complete"]
    logs = sorted((collection / "staged").rglob("*.npz"))
    listed = {collection / "staged" / f"stage{k}" / rel: info for k, e in m["stages"].items()
              for rel, info in e["files"].items()}
    assert sorted(listed) == logs and len(logs) == 3 * (CFG.n_train + CFG.n_val)
    for path, info in listed.items():
        log = load_log(path)
        assert info["sha256"] == file_sha256(path) and info["bytes"] == path.stat().st_size
        assert info["rows"] == len(log) and info["status"] == "ok"
    # the sample counts are the labelled samples training sees
    train, val, _ = load_collection(collection / "staged")
    assert len(train) == sum(i["samples"] for p, i in listed.items() if p.parent.name == "train")
    assert len(val) == sum(i["samples"] for p, i in listed.items() if p.parent.name == "val")
    assert [r["flights"] for r in m["runs"]] == [len(logs)]  # one run did all the work


def _train(kind: str, base: Path, field) -> None:
    """Each way of reading a collection for training (the error must come before any work)."""
    staged, models = base / "staged", base / "models"
    if kind == "load_collection":
        load_collection(staged)
    elif kind == "ensure_collection":
        ensure_collection(staged, models, CFG, field)
    elif kind == "ensure_models":
        (models / "deep.pt").unlink()  # a missing model: it would be trained on the logs
        ensure_models(models, PAIRWISE_KINDS, staged, CFG, field)
    elif kind == "collect":
        collect(CFG, staged, models, field, refly_missing=False)


ENTRY_POINTS = ["load_collection", "ensure_collection", "ensure_models", "collect"]


@pytest.mark.parametrize("kind", ENTRY_POINTS)
def test_a_deleted_log_stops_training_before_any_work(copy, field, kind):
    gone = copy / "staged" / "stage1" / "val" / "flight_002.npz"
    gone.unlink()
    before = _mtimes(copy)
    with pytest.raises(DataError) as e:
        _train(kind, copy, field)
    msg = str(e.value)
    assert f"{gone}: missing" in msg and RERUN in msg and "re-flies only what is missing" in msg
    after = _mtimes(copy)  # nothing flown, trained or rewritten (the model ensure_models lacked is still missing)
    assert set(after) <= set(before) and all(after[p] == before[p] for p in after)
    assert not gone.exists() and not (kind == "ensure_models" and (copy / "models" / "deep.pt").exists())


@pytest.mark.parametrize("kind", ENTRY_POINTS)
def test_an_altered_log_stops_training_before_any_work(copy, field, kind):
    path = copy / "staged" / "stage2" / "train" / "flight_001.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit, same size: only the digest sees it
    path.write_bytes(bytes(data))
    before = _mtimes(copy)
    with pytest.raises(DataError) as e:
        _train(kind, copy, field)
    msg = str(e.value)
    assert f"{path}: altered since it was flown (SHA-256" in msg and "Delete the altered logs and rerun" in msg
    assert RERUN in msg
    assert all(after == before[p] for p, after in _mtimes(copy).items())
    # a rerun of the collection does not overwrite it either: the user decides
    with pytest.raises(DataError, match="altered since it was flown"):
        collect(CFG, copy / "staged", copy / "models", field)


def _flip_bit(path: Path, at: float) -> None:
    """One bit flipped at the fraction `at` of the file: its size stays, only a digest sees it."""
    data = bytearray(path.read_bytes())
    data[int(at * (len(data) - 1))] ^= 0x10
    path.write_bytes(bytes(data))


def test_the_manifest_records_every_model_it_trained(collection):
    m = _manifest(collection)
    stage_models = {k: e["model_sha256"] == checkpoint_digest(collection / "staged" / f"stage{k}" / e["model_file"])
                    for k, e in m["stages"].items() if "model_sha256" in e}
    assert stage_models == {"0": True, "1": True}  # stage 2's model is the final one
    assert sorted(m["final_models"]) == sorted(STAGED_KINDS)
    for kind, entry in m["final_models"].items():
        assert entry["sha256"] == checkpoint_digest(collection / "models" / f"{kind}.pt")


def _weights_offset(path: Path) -> float:
    """The middle of a checkpoint's largest tensor's bytes (a stored zip record under data/), as a
    fraction of the file."""
    import struct
    import zipfile
    with zipfile.ZipFile(path) as z:
        info = max((i for i in z.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
    raw = path.read_bytes()
    name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26:info.header_offset + 30])
    start = info.header_offset + 30 + name_len + extra_len  # the local header, then the stored bytes
    return (start + info.file_size // 2) / (len(raw) - 1)


@pytest.mark.parametrize("which", ["stage1/equivariant.pt", "models/deep.pt"])
@pytest.mark.parametrize("kind", ["ensure_collection", "collect", "load_collection"])
def test_a_flipped_bit_in_a_model_stops_every_run_by_name(copy, field, which, kind):
    """torch ignores the zip's CRC-32s: a bit flipped in a weight loads. The digest each file carries
    refuses it, and a complete collection rereads its models (ensure_collection, collect) before work."""
    path = copy / "staged" / which if which.startswith("stage") else copy / which
    _flip_bit(path, _weights_offset(path))
    if kind == "load_collection" and which.startswith("models"):
        kind = "load_model"  # the sweep's loader reads no final model: a flight reads it
    before = _mtimes(copy)
    with pytest.raises((DataError, CheckpointError)) as e:
        if kind == "load_model":
            load_checkpoint(path)
        else:
            _train(kind, copy, field)
    assert f"{path}: " in str(e.value) and "SHA-256" in str(e.value)
    assert _mtimes(copy) == before


def test_a_model_swapped_for_another_valid_one_is_found(copy, field):
    """A stage model replaced by another well-formed checkpoint (the final equivariant model) passes its
    own digest but not the manifest's."""
    stage = copy / "staged" / "stage0" / "equivariant.pt"
    shutil.copy(copy / "models" / "equivariant.pt", stage)
    with pytest.raises(DataError, match=rf"(?s){stage}: not the model this collection trained.*Delete the altered models"):
        ensure_collection(copy / "staged", copy / "models", CFG, field)


def test_a_rerun_removes_what_killed_runs_left_half_written(copy, field):
    """A run killed while writing (SIGKILL) leaves its temporary files beside the logs and models; the next
    run on the folders removes them under their locks, and changes nothing else."""
    stale = [copy / "staged" / "stage1" / "train" / ".flight_005.npz.q1w2e3.tmp",
             copy / "staged" / ".manifest.json.r4t5y6.tmp", copy / "models" / ".deep.pt.u7i8o9.tmp"]
    for p in stale:
        p.write_bytes(b"half a file")
    before = _mtimes(copy)
    collect(CFG, copy / "staged", copy / "models", field)
    assert not any(p.exists() for p in stale) and _mtimes(copy) == before


def test_an_unlisted_log_in_a_stage_folder_is_reported(copy, field):
    extra = copy / "staged" / "stage0" / "train" / "flight_099.npz"
    shutil.copy(copy / "staged" / "stage0" / "train" / "flight_000.npz", extra)
    for kind in ("load_collection", "ensure_collection"):
        with pytest.raises(DataError) as e:
            _train(kind, copy, field)
        assert f"{extra}: not a log of this collection" in str(e.value)
        assert "Move the unlisted files out of the stage folders" in str(e.value)


def test_a_rerun_reflies_only_the_missing_flights(copy, field):
    """A stage-0 log (flown with no model: the same bytes) and a stage-2 log (flown with the
    stage-1 model, whose path in the metadata moved with the copy: the same data) are deleted;
    the rerun flies exactly those two, trains nothing, and the collection verifies again."""
    staged = copy / "staged"
    gone = [staged / "stage0" / "train" / "flight_001.npz", staged / "stage2" / "val" / "flight_003.npz"]
    digest = {p: file_sha256(p) for p in gone}
    data = {p: _manifest(copy)["stages"][p.parent.parent.name[-1]]["files"][f"{p.parent.name}/{p.name}"]["data_sha256"]
            for p in gone}
    for p in gone:
        p.unlink()
    before = _mtimes(copy)
    results = collect(CFG, copy / "staged", copy / "models", field)
    after = _mtimes(copy)
    assert sorted(set(after) - set(before)) == sorted(gone)
    assert all(after[p] == t for p, t in before.items())  # no other log, no model written again
    assert file_sha256(gone[0]) == digest[gone[0]]  # bit for bit the flight it was
    m = _manifest(copy)
    for p in gone:
        info = m["stages"][p.parent.parent.name[-1]]["files"][f"{p.parent.name}/{p.name}"]
        assert info["data_sha256"] == data[p] and info["sha256"] == file_sha256(p)
    assert m["runs"][-1]["flights"] == 2 and m["runs"][-1]["models"] == [] and len(m["runs"]) == 2
    assert [s["samples"] for s in results["stages"]] == [CFG.n_train * 182] * 3
    load_collection(copy / "staged")  # verifies


def test_a_reflown_log_with_other_data_is_refused(copy, field):
    """Models trained on the recorded log would not match a re-flown log of other data (say another
    code version that flies differently): the rerun stops and removes what it flew."""
    path = copy / "staged" / "manifest.json"
    m = json.loads(path.read_text())
    m["stages"]["1"]["files"]["train/flight_000.npz"]["data_sha256"] = "0" * 64  # as if flown by other code
    write_manifest(path, m)
    gone = copy / "staged" / "stage1" / "train" / "flight_000.npz"
    gone.unlink()
    with pytest.raises(DataError, match=r"flight_000.npz: re-flown, but the data differ .* Delete .* collect afresh"):
        collect(CFG, copy / "staged", copy / "models", field)
    assert not gone.exists()
    assert json.loads(path.read_text())["stages"]["1"]["files"]["train/flight_000.npz"]["data_sha256"] == "0" * 64


def test_a_manifest_of_the_older_format_is_refused(copy, field):
    path = copy / "staged" / "manifest.json"
    m = json.loads(path.read_text())
    m["version"] = 2
    path.write_text(json.dumps(m))  # an older version's: no digest of itself
    for kind in ("load_collection", "ensure_collection"):
        with pytest.raises(DataError, match=r"older format \(manifest version 2.*delete the folder"):
            _train(kind, copy, field)


def test_an_edited_manifest_is_refused_by_name(copy, field):
    """The manifest is what the logs are checked against, so it carries the digest of itself: a hand edit
    (a log's sample count, which no other check sees) stops every reader."""
    path = copy / "staged" / "manifest.json"
    m = json.loads(path.read_text())
    m["stages"]["0"]["files"]["train/flight_000.npz"]["samples"] += 1
    path.write_text(json.dumps(m, indent=2))
    for kind in ENTRY_POINTS:
        with pytest.raises(DataError, match=rf"{path}: the collection manifest was altered since it was written"):
            _train(kind, copy, field)


def test_sweep_cells_follow_the_data(copy, collection):
    """The same provenance with other data (a collection flown again by code that flies
    differently: its manifest records other data digests) gives other cells."""
    from downwash.sweep_cells import load_collection_with_digest

    grid = SweepGrid(models=("shallow",), minutes=(0.1,), seeds=(0, 1), quick=True)
    *_, digest = load_collection_with_digest(collection / "staged")
    assert digest == collection_digest(collection / "staged")
    path = copy / "staged" / "manifest.json"
    m = json.loads(path.read_text())
    m["stages"]["1"]["files"]["train/flight_000.npz"]["data_sha256"] = "0" * 64
    write_manifest(path, m)  # as other code would have written it
    *_, other = load_collection_with_digest(copy / "staged")  # the files still match their SHA-256
    assert other != digest
    a = plan_cells(grid, {"": ("key", 0.4, digest)})
    b = plan_cells(grid, {"": ("key", 0.4, other)})
    assert len(a) == len(b) == 4 and not {c.key for c in a} & {c.key for c in b}
    assert {c.key for c in plan_cells(grid, {"": ("key", 0.4, digest)})} == {c.key for c in a}  # stable


ARTIFACTS = {  # every kind of file a collection is trusted by, as one of this collection's files
    "log": "staged/stage1/train/flight_000.npz", "manifest": "staged/manifest.json",
    "stage model": "staged/stage0/equivariant.pt", "model": "models/equivariant.pt",
}


@pytest.fixture(scope="module")
def corruptible(collection, tmp_path_factory):
    """A copy of the collection whose files the property test flips bytes of (each restored after)."""
    base = tmp_path_factory.mktemp("corruptible")
    shutil.copytree(collection / "staged", base / "staged")
    shutil.copytree(collection / "models", base / "models")
    return base


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(artifact=st.sampled_from(sorted(ARTIFACTS)), at=st.floats(0.0, 1.0), bits=st.integers(1, 255))
@example(artifact="manifest", at=0.75, bits=45)  # (a space made a carriage return: the same JSON, found on a CI run)
def test_a_flipped_byte_in_any_artifact_is_refused_by_name(corruptible, field, artifact, at, bits):
    """Any byte of a log, the manifest, a stage model or a final model, changed: the complete collection
    is refused before any work, with the file named (or, for the few bytes that carry no content,
    such as a zip member's time stamp, its content is unchanged and it is read as it was)."""
    path = corruptible / ARTIFACTS[artifact]
    original = path.read_bytes()
    data = bytearray(original)
    data[int(at * (len(data) - 1))] ^= bits
    path.write_bytes(bytes(data))
    try:
        try:
            ensure_collection(corruptible / "staged", corruptible / "models", CFG, field)
        except (DataError, CheckpointError) as e:
            assert str(path) in str(e)
        else:  # a byte no content depends on: a model's zip records are stamped by what they hold, and JSON
            # whitespace turned into other whitespace (a space XOR 45 is a carriage return) leaves the manifest's content
            if artifact == "manifest":
                assert json.loads(bytes(data)) == json.loads(original), "a changed manifest was read as if unchanged"
                return
            assert artifact.endswith("model"), "a changed log was read as if unchanged"
            unchanged = path.with_name("unchanged.pt")
            unchanged.write_bytes(original)
            assert checkpoint_digest(path) == checkpoint_digest(unchanged)
            unchanged.unlink()
        if artifact.endswith("model"):  # a flight reads it alone: refused by its own digest, or the same model
            try:
                load_checkpoint(path)
            except CheckpointError as e:
                assert str(e).startswith(f"{path}: ")
    finally:
        path.write_bytes(original)


def nan_below(p_a, v_a, R_a, p_b, v_b):
    """The default field, NaN for a follower below 1.5 m: every stage-0 flight (0.75-1.15 m) meets it,
    though `check_field` (followers at 1.7-1.9 m) passes it."""
    from sim.field import DownwashField

    out = np.asarray(DownwashField()(p_a, v_a, R_a, p_b, v_b), dtype=float)
    return np.where((np.asarray(p_b)[..., 2] < 1.5)[..., None], np.nan, out)


def test_a_field_that_ends_most_flights_stops_with_the_counts(tmp_path):
    from sim.field import check_field

    check_field(nan_below)  # passes the check before flying
    with pytest.raises(DataError) as e:
        collect(CFG, tmp_path / "staged", tmp_path / "models", nan_below)
    msg = str(e.value)
    n = CFG.n_train + CFG.n_val
    assert "stage 0 (the follower 1.35-1.75 m below the leader) cannot train a model" in msg
    assert f"{n} of its {n} flights diverged" in msg and "0 samples could be labelled" in msg
    assert "The ground-truth field is the likely cause" in msg and "check_field" in msg
    assert not (tmp_path / "staged" / "stage0" / "equivariant.pt").exists()
    assert not list((tmp_path / "models").glob("*.pt"))
    m = json.loads((tmp_path / "staged" / "manifest.json").read_text())
    assert m["stages"]["0"]["flights_done"] and len(m["stages"]["0"]["failed"]) == n
    with pytest.raises(DataError, match=f"{n} of its {n} flights diverged"):  # a rerun says it again, flies nothing
        collect(CFG, tmp_path / "staged", tmp_path / "models", nan_below)


SLOW_FIELD = """
import time
from sim.field import DownwashField

_F = DownwashField()


def slow(p_a, v_a, R_a, p_b, v_b):
    time.sleep(0.0025)  # a collection of several seconds, so the second run surely meets the first
    return _F(p_a, v_a, R_a, p_b, v_b)


def make():
    return slow
"""


def _popen(args: list[str], cwd: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=os.pathsep.join([str(cwd), str(ROOT)]))
    return subprocess.Popen([sys.executable, "-m", *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_for_holder(lock: Path, pid: int, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while (holder(lock) or {}).get("pid") != pid:
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() < deadline, f"{pid} never took {lock}"
        time.sleep(0.02)


def test_two_runs_on_one_pipeline_folder_collect_once(tmp_path):
    """The second run starts while the first holds the folder: it waits, then finds the
    collection complete and its models there, and flies and trains nothing."""
    (tmp_path / "slow_field.py").write_text(SLOW_FIELD)
    args = ["experiments.staged_collection", "--quick", "--field", "slow_field:make", "--collection-dir", "s",
            "--models-dir", "m"]
    first = _popen([*args, "--out", "o1"], tmp_path)
    try:
        _wait_for_holder(tmp_path / "s" / LOCK_NAME, first.pid, first)
        second = _popen([*args, "--out", "o2"], tmp_path)
        try:
            out1, err1 = first.communicate(timeout=300)
            out2, err2 = second.communicate(timeout=300)
        finally:
            second.kill()
    finally:
        first.kill()
    assert first.returncode == 0, err1[-3000:]
    assert second.returncode == 0, err2[-3000:]
    assert f"waiting for pid {first.pid} on host" in err2 and "which holds s\n" in err2
    assert "flights to fly" in err1 and "training the final models" in err1
    assert "flights to fly" not in err2 and "training" not in err2
    m = json.loads((tmp_path / "s" / "manifest.json").read_text())
    assert [r["pid"] for r in m["runs"]] == [first.pid]  # one run did the work
    r1, r2 = (json.loads((tmp_path / o / "results.json").read_text()) for o in ("o1", "o2"))
    assert r1["models"] == r2["models"] and r1["stages"] == r2["stages"]


def test_two_sweeps_on_one_cell_cache_compute_each_cell_once(tmp_path):
    """Two sweeps of the same grid at once, into one cache: they share the collection (one
    collects, the other waits) and the cells (each claimed by one; the other skips or waits).
    Then a third sweep meets two cells claimed by a process that is killed: it computes them."""
    args = ["experiments.sweep", "--quick", "--models", "shallow", "--minutes", "0.1", "--seeds", "0,1,2",
            "--workers", "1", "--batch", "1", "--cache-dir", "cells"]
    procs = [_popen([*args, "--out", f"o{i}"], tmp_path) for i in range(2)]
    try:
        outs = [p.communicate(timeout=500) for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    results = [json.loads((tmp_path / f"o{i}" / "results.json").read_text()) for i in range(2)]
    n = 2 * 3  # (0.1 min, full) x 3 seeds
    assert all(r["cells"]["total"] == n for r in results)
    assert sum(r["cells"]["computed"] for r in results) == n  # each cell computed once, in one of them
    assert len(list((tmp_path / "cells").rglob("*.json"))) == n and not list((tmp_path / "cells").rglob("*.lock"))
    assert results[0]["fields"][""]["models"] == results[1]["fields"][""]["models"]
    manifests = list((tmp_path / "runs" / "pipeline").rglob("manifest.json"))
    assert len(manifests) == 1 and len(json.loads(manifests[0].read_text())["runs"]) == 1  # collected once

    # a sweep that meets cells held by a process that then dies computes them itself
    gone = sorted((tmp_path / "cells").rglob("*.json"))[:2]
    for p in gone:
        p.unlink()
    locks = [str(p.with_suffix(".lock")) for p in gone]
    code = ("import contextlib, time\nfrom downwash_core.locks import file_lock\nwith contextlib.ExitStack() as s:\n"
            f"    for p in {locks!r}:\n        s.enter_context(file_lock(p, remove=True))\n"
            "    print('held', flush=True)\n    time.sleep(600)\n")
    holder_proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                                   env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        assert holder_proc.stdout.readline().strip() == "held"
        with open(tmp_path / "third.err", "w") as err:
            third = subprocess.Popen([sys.executable, "-m", *args, "--out", "o3"], cwd=tmp_path, stderr=err,
                                     stdout=subprocess.DEVNULL, env=dict(os.environ, PYTHONPATH=str(ROOT)))
            try:
                deadline = time.monotonic() + 300
                while "being computed by other processes" not in (tmp_path / "third.err").read_text():
                    assert third.poll() is None and time.monotonic() < deadline, (tmp_path / "third.err").read_text()
                    time.sleep(0.05)
                holder_proc.kill()  # SIGKILL: its claims must not block the waiting sweep
                assert third.wait(timeout=300) == 0, (tmp_path / "third.err").read_text()[-3000:]
            finally:
                third.kill()
    finally:
        holder_proc.kill()
        holder_proc.wait(timeout=30)
    r = json.loads((tmp_path / "o3" / "results.json").read_text())
    assert r["cells"] == {"total": n, "cached": n - 2, "computed": 2} and r["computed_elsewhere"] == 0
    assert r["fields"][""]["models"] == results[0]["fields"][""]["models"]  # the same numbers, bit for bit
