"""Record the golden results that `tests/test_golden.py` compares against, bit for bit.

    python tests/golden/record.py            # writes tests/golden/pipeline.json

What it records: a quick staged collection (`--quick`: every flight log's arrays,
every checkpoint's tensors, as SHA-256 digests, and the numbers of its
results.json) and a quick lemniscate with all six conditions on one seed (the
per-seed metrics of its results.json, exact floats; 6 s, so that the follower
passes beneath the leader), both run through the public
command lines. Re-record only when a change is MEANT to move numbers, and say so
in the commit message: the file is the proof that a refactor changed none.
Re-recorded so far: once, for issue 9 (motion capture measures the attitude with
noise; each collection flight draws from its own generator; lemniscates in both the
training and the validation flights of a stage). Edited once by hand without moving a
number: the last stage's model (never deployed; the same data as the final
equivariant model) is no longer trained, so its checkpoint left the record.

Digests of floating-point results are specific to the CPU's instruction set
(numba, torch and NumPy pick kernels per ISA); a failure on a new kind of machine
with an otherwise clean tree means re-recording there, not a bug.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parent / "pipeline.json"
LOG_ARRAYS = (
    "t", "pos", "vel", "quat", "pos_est", "vel_est", "quat_est", "yaw_est", "mocap_pos", "ref_pos", "ref_vel",
    "ref_acc", "u_cmd", "f_hat", "field_mean", "field_applied",
)  # fmt: skip


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


def run_pipeline(workdir: Path) -> None:
    """The two command lines whose results are golden (run in `workdir`)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for args in (
        ["experiments.staged_collection", "--quick", "--out", "staged", "--collection-dir", "staged",
         "--models-dir", "models"],
        ["experiments.lemniscate", "--quick", "--duration", "6", "--out", "lem", "--collection-dir", "staged",
         "--models-dir", "models"],
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
            logs[str(path.relative_to(workdir / "staged"))] = _digest({k: z[k] for k in LOG_ARRAYS})
    checkpoints = {}
    for path in sorted(list((workdir / "staged").rglob("*.pt")) + list((workdir / "models").glob("*.pt"))):
        payload = torch.load(path, map_location="cpu", weights_only=True)
        state = {k: v.numpy() for k, v in payload["state_dict"].items()}
        checkpoints[str(path.relative_to(workdir))] = _digest(state)
    return {
        "staged": {
            "logs": logs,
            "checkpoints": checkpoints,
            "stages": [{k: s[k] for k in ("samples", "deployed_val_rmse")} for s in staged["stages"]],
            "val_rmse": {k: m["val_rmse"] for k, m in staged["models"].items()},
            "noise_floor": staged["noise_floor"],
        },
        "lemniscate": {c: e["per_seed"] for c, e in lem["conditions"].items()},
    }


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        run_pipeline(Path(tmp))
        record = summarize(Path(tmp))
    GOLDEN.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}")


if __name__ == "__main__":
    main()
