"""Record the golden results that `tests/test_golden.py` compares against.

    python tests/golden/record.py            # writes tests/golden/pipeline.json

What it records: a quick staged collection (`--quick`: every flight log's arrays and
every checkpoint's tensors, as SHA-256 digests and as summaries, and the numbers of
its results.json) and a quick lemniscate with all six conditions on one seed (the
per-seed metrics of its results.json; 6 s, so that the follower passes beneath the
leader), both run through the public command lines, and the machine and package
versions they were made on (`machine`). Re-record only when a change is MEANT to
move numbers, and say so in the commit message: the file is the proof that a
refactor changed none.

What holds on which machine (`compare`, with the tolerances and why):
- A flight with no learned model in its loop is bit-identical on every CPU: the
  flight stack calls no BLAS per step and rounds its set-up gains
  (`downwash_core.numerics`). Stage 0's logs must match their digests exactly.
- Training is float32 torch, whose kernels are picked per CPU unless asked for: the
  experiments ask for the portable ones (`downwash.train`: ATen's AVX2 loops, MKL's
  AVX2 path in its reproducible mode), and the labels' Savitzky-Golay coefficients are
  exact rationals. So on every x86-64 CPU with AVX2 the checkpoints, the flights they fly
  in and every metric must match their digests too (`tests/test_golden.py` requires
  it, and under another CPU's BLAS and NumPy kernels). A CPU without AVX2 trains
  other bits: there each is compared by its digest first and, when that differs, by
  its summary within the tolerances below.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_spec = importlib.util.spec_from_file_location("golden_machine", Path(__file__).parent / "machine.py")
machine = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(machine)

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parent / "pipeline.json"
LOG_ARRAYS = (
    "t", "pos", "vel", "quat", "pos_est", "vel_est", "quat_est", "yaw_est", "mocap_pos", "ref_pos", "ref_vel",
    "ref_acc", "u_cmd", "f_hat", "field_mean", "field_applied",
)  # fmt: skip
EXACT_LOGS = "stage0/"  # flights with no learned model in the loop: the same bits on every CPU

# Two tiers. When every checkpoint matches its digest, this CPU's torch trained the same
# bits, and every flight must match too (the flight stack is CPU-independent); the RMSEs
# against labels are allowed LABEL_RTOL. When a checkpoint differs, torch ran other
# kernels (a CPU without AVX2), and what the models fly is compared within tolerances
# measured, before training asked for portable kernels, by emulating another CPU
# (torch's non-vectorised ATen kernels, SSE-only MKL and OpenBLAS kernels): the deep
# model moved the most, its tensor norms by 1.8e-4, its lemniscate errors by 1.8e-4 m
# (0.16 %) and its validation RMSE by 3e-5, relative; the logs' array means moved by
# 2e-6. The bounds leave about ten times that.
LABEL_RTOL = 1e-9  # RMSEs against labels, same torch bits
LOG_RTOL = 2e-5  # per-array means of a flight log with a learned model in its loop
CHECKPOINT_RTOL = 2e-3  # per-tensor norms of a trained model
MODEL_RTOL = 1e-3  # validation RMSEs of models trained by another CPU's torch
FLIGHT_RTOL, FLIGHT_ATOL = 2e-2, 2e-3  # tracking metrics (m, m/s, fractions) flown by those models
ATOL = 1e-9  # for values that are zero in the record


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


def _summary(arrays: dict[str, np.ndarray]) -> dict[str, list[float]]:
    """Per array: the mean and the mean magnitude over its finite values (a log may end in NaN)."""
    out = {}
    for name in sorted(arrays):
        a = np.asarray(arrays[name], dtype=np.float64)
        a = a[np.isfinite(a)]
        out[name] = [float(a.mean()), float(np.abs(a).mean())] if a.size else [0.0, 0.0]
    return out


# the lemniscate's conditions the record holds (the default list has grown since: the guarded twins)
GOLDEN_CONDITIONS = ("no_downwash", "baseline", "oracle", "shallow", "deep", "equivariant", "equivariant_general")


def run_pipeline(workdir: Path, env: dict | None = None) -> None:
    """The two command lines whose results are golden (run in `workdir`, with extra `env`)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
    for args in (
        ["experiments.staged_collection", "--quick", "--out", "staged", "--collection-dir", "staged",
         "--models-dir", "models"],
        ["experiments.lemniscate", "--quick", "--duration", "6", "--out", "lem", "--collection-dir", "staged",
         "--models-dir", "models", "--conditions", ",".join(GOLDEN_CONDITIONS)],
    ):
        proc = subprocess.run([sys.executable, "-m", *args], cwd=workdir, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{args} failed:\n{proc.stderr[-3000:]}")


def summarize(workdir: Path) -> dict:
    """The golden record of a pipeline run in `workdir`."""
    import torch

    staged = json.loads((workdir / "staged" / "results.json").read_text())
    lem = json.loads((workdir / "lem" / "results.json").read_text())
    logs = {}
    for path in sorted((workdir / "staged").rglob("*.npz")):
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in LOG_ARRAYS}
        logs[str(path.relative_to(workdir / "staged"))] = {"digest": _digest(arrays), "summary": _summary(arrays)}
    checkpoints = {}
    for path in sorted(list((workdir / "staged").rglob("*.pt")) + list((workdir / "models").glob("*.pt"))):
        payload = torch.load(path, map_location="cpu", weights_only=True)
        state = {k: v.numpy() for k, v in payload["state_dict"].items()}
        checkpoints[str(path.relative_to(workdir))] = {
            "digest": _digest(state), "norms": {k: float(np.linalg.norm(v.astype(np.float64))) for k, v in state.items()}}
    return {
        "machine": machine.machine(),
        "staged": {
            "logs": logs,
            "checkpoints": checkpoints,
            "stages": [{k: s[k] for k in ("samples", "deployed_val_rmse")} for s in staged["stages"]],
            "val_rmse": {k: m["val_rmse"] for k, m in staged["models"].items()},
            "noise_floor": staged["noise_floor"],
        },
        "lemniscate": {c: e["per_seed"] for c, e in lem["conditions"].items()},
    }


def _close(got, want, rtol: float, atol: float = ATOL) -> bool:
    if isinstance(want, bool) or want is None or isinstance(want, str):
        return got == want
    if isinstance(want, (int, float)):
        return isinstance(got, (int, float)) and math.isclose(got, want, rel_tol=rtol, abs_tol=atol)
    if isinstance(want, list):
        return isinstance(got, list) and len(got) == len(want) and all(_close(g, w, rtol, atol) for g, w in zip(got, want))
    if isinstance(want, dict):
        return (isinstance(got, dict) and got.keys() == want.keys()
                and all(_close(got[k], want[k], rtol, atol) for k in want))
    return got == want


def compare(got: dict, want: dict) -> tuple[list[str], bool]:
    """(what differs beyond its tolerance, whether this CPU's torch trained the recorded bits)."""
    problems = []
    g, w = got["staged"], want["staged"]
    for what in ("logs", "checkpoints"):
        if g[what].keys() != w[what].keys():
            problems.append(f"{what}: got {sorted(g[what])}, recorded {sorted(w[what])}")
    same_torch = all(g["checkpoints"][n]["digest"] == w["checkpoints"][n]["digest"]
                     for n in w["checkpoints"].keys() & g["checkpoints"].keys())
    for name in sorted(w["checkpoints"].keys() & g["checkpoints"].keys()):
        if not _close(g["checkpoints"][name]["norms"], w["checkpoints"][name]["norms"], CHECKPOINT_RTOL):
            problems.append(f"{name}: tensor norms differ by more than rtol {CHECKPOINT_RTOL}")
    for name in sorted(w["logs"].keys() & g["logs"].keys()):
        if g["logs"][name]["digest"] == w["logs"][name]["digest"]:
            continue
        if name.startswith(EXACT_LOGS):
            problems.append(f"{name}: no learned model flies in it, so its bits must match on every CPU")
        elif same_torch:
            problems.append(f"{name}: every model has the recorded bits, so the flight must too")
        elif not _close(g["logs"][name]["summary"], w["logs"][name]["summary"], LOG_RTOL):
            problems.append(f"{name}: array means differ by more than rtol {LOG_RTOL}")
    if g["stages"] != w["stages"] and not _close(g["stages"], w["stages"], LABEL_RTOL if same_torch else MODEL_RTOL):
        problems.append(f"staged stages: {g['stages']} against {w['stages']}")
    if not _close(g["noise_floor"], w["noise_floor"], LABEL_RTOL if same_torch else MODEL_RTOL):
        problems.append(f"noise floor: {g['noise_floor']} against {w['noise_floor']}")
    if not _close(g["val_rmse"], w["val_rmse"], LABEL_RTOL if same_torch else MODEL_RTOL):
        problems.append(f"validation RMSE: {g['val_rmse']} against {w['val_rmse']}")
    lem_got, lem_want = got["lemniscate"], want["lemniscate"]
    if same_torch:
        bad = [c for c in lem_want if lem_got.get(c) != lem_want[c]]
    else:
        bad = [c for c in lem_want if not _close(lem_got.get(c), lem_want[c], FLIGHT_RTOL, FLIGHT_ATOL)]
    if bad or lem_got.keys() != lem_want.keys():
        problems.append(f"lemniscate metrics differ ({'exactly' if same_torch else 'beyond tolerance'}): {bad}")
    return problems, same_torch


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        run_pipeline(Path(tmp))
        record = summarize(Path(tmp))
    GOLDEN.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}")


if __name__ == "__main__":
    main()
