"""What the examples share about the trained policy: `--save PATH` (default
`<--out>/policy.zip`, written atomically at the end of training) and `--load PATH` (skip
training, load that policy and evaluate it). Imports nothing heavy, so a missing `--load`
file is refused before torch loads."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np


def add_policy_arguments(p: argparse.ArgumentParser) -> None:
    """`--save PATH` and `--load PATH` (one or the other) on an example's parser."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--save", type=Path, default=None,
                   help="where to write the trained policy, an SB3 zip (default: <--out>/policy.zip)")
    g.add_argument("--load", type=Path, default=None,
                   help="skip training: load this policy (a --save file) and evaluate it")


def refuse_missing(prog: str, load: Path | None) -> None:
    """Exit with one line naming `load` when it is given and is not a file (before the slow imports)."""
    if load is not None and not load.is_file():
        sys.exit(f"{prog}: --load {load}: no such policy file")


def save_policy(model, path: Path) -> Path:
    """Write `model` (an SB3 algorithm) to `path` atomically: into a temporary file in the same
    folder, then `os.replace`, so a reader never sees half a policy and a kill leaves the old one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.zip", dir=path.parent)
    os.close(fd)
    try:
        model.save(tmp)  # ends in .zip: SB3 writes exactly this file
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would otherwise outlive the rename
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    print(f"wrote the policy to {path} (load it with --load {path})")
    return path


def load_policy(prog: str, algo, path: Path, env):
    """`algo.load(path, env=env)`, or exit with one line naming `path` when it is not a policy
    for this env (not an SB3 zip, another algorithm's, other observation or action spaces)."""
    from stable_baselines3.common.save_util import load_from_zip_file

    refuse_missing(prog, path)
    try:
        data, _, _ = load_from_zip_file(path, load_data=True, device="cpu")
        if data is None:
            raise ValueError("no SB3 data in the zip")
        for what in ("observation", "action"):  # SB3's own message prints both spaces in full
            theirs, ours = data.get(f"{what}_space"), getattr(env, f"{what}_space")
            if theirs is None or theirs.shape != ours.shape:
                raise ValueError(f"its {what}s have shape {getattr(theirs, 'shape', None)}, this env's {ours.shape}")
        return algo.load(path, env=env, device="cpu")
    except (ValueError, KeyError, RuntimeError, OSError, zipfile.BadZipFile) as e:
        reason = " ".join(str(e).split()) or type(e).__name__
        reason = reason if len(reason) <= 200 else reason[:197] + "..."
        sys.exit(f"{prog}: --load {path}: not a {algo.__name__} policy for this env ({reason})")


def evaluation(path: Path, title: str, lines: dict[str, list[float]]) -> dict:
    """Print each line's mean return and its spread (population standard deviation) over its
    evaluation episodes; returns the record."""
    record = {"title": title, "policy": str(path),
              "evaluation": {label: {"mean": float(np.mean(v)), "std": float(np.std(v)),
                                     "returns": [float(x) for x in v]} for label, v in lines.items()}}
    print(f"{title}: evaluating {path}")
    for label, v in record["evaluation"].items():
        print(f"  {label}: mean return {v['mean']:.1f} +- {v['std']:.1f} (std) over {len(v['returns'])} episodes")
    return record
