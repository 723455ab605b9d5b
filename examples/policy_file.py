"""What the examples share about the trained policy and its training logs: `--save PATH`
(default `<--out>/policy.zip`, written atomically at the end of training), `--load PATH`
(skip training, load that policy and evaluate it) and `--tensorboard DIR` (default
`<--out>/tensorboard`). Imports nothing heavy, so a missing `--load` file is refused before
torch loads."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import Callable, NoReturn

import numpy as np


def add_policy_arguments(p: argparse.ArgumentParser, file: str = "policy.zip", kind: str = "an SB3 zip") -> None:
    """`--save PATH` and `--load PATH` (one or the other) on an example's parser; `file` is the
    default name under --out, `kind` what it holds."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--save", type=Path, default=None,
                   help=f"where to write the trained policy, {kind} (default: <--out>/{file})")
    g.add_argument("--load", type=Path, default=None,
                   help="skip training: load this policy (a --save file) and evaluate it")


def add_tensorboard_arguments(p: argparse.ArgumentParser) -> None:
    """`--tensorboard DIR` or `--no-tensorboard`. On by default: a training of minutes is worth
    watching live, and a forgotten flag would cost a rerun; every run gets its own folder."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--tensorboard", type=Path, default=None, metavar="DIR",
                   help="write TensorBoard logs of the training here, one PPO_<n> folder per run "
                        "(default: <--out>/tensorboard; `tensorboard --logdir DIR` shows them)")
    g.add_argument("--no-tensorboard", action="store_true", help="write no TensorBoard logs")


def tensorboard_dir(prog: str, args: argparse.Namespace) -> Path | None:
    """Where this run's TensorBoard logs go: None when switched off or when only evaluating
    (--load). Without TensorBoard installed, the default is None, said in one line (the run is
    worth more than its logs), and an explicit --tensorboard DIR is refused."""
    import importlib.util

    if args.no_tensorboard or args.load is not None:
        return None
    if importlib.util.find_spec("tensorboard") is None:
        if args.tensorboard is not None:
            refuse(prog, f"--tensorboard {args.tensorboard}: TensorBoard is not installed (pip install tensorboard)")
        print("TensorBoard is not installed: no training logs (pip install tensorboard, or --no-tensorboard)")
        return None
    return args.tensorboard if args.tensorboard is not None else args.out / "tensorboard"


def refuse(prog: str, message: str) -> NoReturn:
    """Exit with status 2 (a usage error, as argparse's) and `message` as one line on stderr."""
    print(f"{prog}: {message}", file=sys.stderr)
    sys.exit(2)


def refuse_missing(prog: str, load: Path | None) -> None:
    """Exit with one line naming `load` when it is given and is not a file (before the slow imports)."""
    if load is not None and not load.is_file():
        refuse(prog, f"--load {load}: no such policy file")


def refuse_foreign(prog: str, load: Path, algo: str, error: BaseException) -> NoReturn:
    """Exit with one line naming `load` and why it is no `algo` policy for this env (`error`, shortened)."""
    reason = " ".join(str(error).split()) or type(error).__name__
    reason = reason if len(reason) <= 200 else reason[:197] + "..."
    refuse(prog, f"--load {load}: not a {algo} policy for this env ({reason})")


def write_atomically(path: Path, write: Callable[[str], object], suffix: str = ".tmp") -> Path:
    """Call `write(tmp)` on a temporary file in `path`'s folder, then `os.replace` it onto `path`,
    so a reader never sees half a file and a kill leaves the old one. `suffix` ends the temporary
    name (SB3 appends .zip to a name without it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would otherwise outlive the rename
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def save_policy(model, path: Path) -> Path:
    """Write `model` (an SB3 algorithm, or anything whose `save(file)` writes exactly that file)
    to `path` atomically (`write_atomically`) and say where."""
    write_atomically(path, model.save, suffix=".tmp.zip")  # ends in .zip: SB3 writes exactly this file
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
        refuse_foreign(prog, path, algo.__name__, e)


def evaluation(path: Path, title: str, lines: dict[str, list[float]],
               position_errors: dict[str, list[float]] | None = None) -> dict:
    """Print each line's mean return and its spread (population standard deviation) over its
    evaluation episodes, with its mean position error (m) where `position_errors` gives each
    episode's; returns the record."""
    record = {"title": title, "policy": str(path),
              "evaluation": {label: {"mean": float(np.mean(v)), "std": float(np.std(v)),
                                     "returns": [float(x) for x in v]} for label, v in lines.items()}}
    for label, errors in (position_errors or {}).items():
        record["evaluation"][label]["position_error"] = float(np.mean(errors))
    print(f"{title}: evaluating {path}")
    for label, v in record["evaluation"].items():
        error = f", mean position error {v['position_error']:.4f} m" if "position_error" in v else ""
        print(f"  {label}: mean return {v['mean']:.1f} +- {v['std']:.1f} (std) over {len(v['returns'])} episodes"
              + error)
    return record
