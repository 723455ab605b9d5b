"""The report's results files: which experiments it reads, the copy from runs/, the machine, stale files.

`copy_results` copies every `runs/<name>/results.json` (for the names in
`EXPERIMENTS`) to `results/<name>.json` and records the machine and the dates in
`results/report.json`; `load_results` reads them back; `stale_results` names the
files made by code older than the last commit that moved a golden number.

Results files carry no digest: a file that parses and holds its experiment's keys is
rendered as it is. What is checked is that each one is UTF-8 JSON of the right shape, and
anything else is a ConfigError naming the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import subprocess
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

from downwash_core.errors import ConfigError
from downwash_core.io import atomic_write_json, to_json
from experiments.report.sections import render_one

__all__ = ["EXPERIMENTS", "GOLDEN_FILES", "load_results", "code_commit", "stale_results", "machine", "copy_results",
           "read_runs", "write_copies", "write_path"]

# name -> (title, keys its results.json must hold)
EXPERIMENTS = {  # (in the results page's order: speed first, what users ask first)
    "benchmark": ("Speed", ("cpu_count",)),
    "staged_collection": ("Staged collection", ("stages", "models", "noise_floor")),
    "sample_efficiency": ("Validation RMSE against minutes of training data", ("minutes", "models", "noise_floor")),
    "observer_bandwidth": ("The disturbance observer's bandwidth, chosen on the training flights under each controller",
                           ("controllers",)),
    "lemniscate": ("Tracking: lemniscate", ("conditions", "seeds")),
    "transect": ("Tracking: transect", ("conditions", "seeds")),
    "force_maps": ("Force maps", ("maps",)),
    "controller_table": ("Tracking under the controllers labs fly", ("table", "tracks")),
    "outdoor": ("Outdoor: a moving leader in wind", ("conditions", "seeds", "leader", "leader_airspeed")),
    "swarm": ("Many vehicles: summed pairwise models against models of sets", ("summary", "conditions", "laws")),
    "swarm_safety": ("The safety layer: the swarm flown with it", ("summary", "conditions", "seeds")),
    "field_table": ("Field x model: the lemniscate experiment on every registered field", ("fields", "table")),
    "real_flights": ("Real flights: the Neural-Swarm data set", ("per_type", "models", "files", "args")),
}


def _read(path: Path) -> Any:
    # bytes, then UTF-8 explicitly: the locale's encoding would read the same file differently elsewhere
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError) as e:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise ConfigError(f"{path}: not a readable JSON results file: {' '.join(str(e).split())}") from e


def _check_shape(name: str, data: Any, path: Path) -> dict:
    """`data` when it is a dict with the keys `name`'s results hold; ConfigError naming `path` otherwise."""
    missing = [k for k in EXPERIMENTS[name][1] if not isinstance(data, dict) or k not in data]
    if missing:
        raise ConfigError(f"{path}: not a {name} results file (missing {', '.join(missing)})")
    return data


def _check_record(data: Any, path: Path) -> dict:
    """The report.json record: {"files": {name: {source, written, copied, machine}}}."""
    files = data.get("files", {}) if isinstance(data, dict) else None
    if not isinstance(files, dict) or not all(isinstance(f, dict) and isinstance(f.get("machine", {}), dict)
                                              for f in files.values()):
        raise ConfigError(f"{path}: not the report's record (expected an object whose \"files\" maps each "
                          "experiment's name to an object with its source, dates and machine)")
    return data


def load_results(results_dir: str | Path, skip: tuple[str, ...] = ()) -> tuple[dict[str, dict], dict]:
    """({name: results} for the files present in results_dir but those in `skip`, the report.json
    record or {}), each checked for its shape (ConfigError naming the file)."""
    found = {n: _check_shape(n, _read(p), p) for n in EXPERIMENTS
             if n not in skip and (p := Path(results_dir) / f"{n}.json").is_file()}
    record = Path(results_dir) / "report.json"
    return found, (_check_record(_read(record), record) if record.is_file() else {})


def write_path(path: str | Path, option: str) -> Path:
    """Where rewriting `path` writes: the file itself, or for a symlink the file it points to, so that the
    link stays a link and the file replaced keeps its own mode (what `open(path, "w")` would do). A link to
    nothing is a ConfigError naming `option`: writing would create a file somewhere the user did not name."""
    path = Path(path)
    if not path.is_symlink():
        return path
    if not path.exists():
        raise ConfigError(f"{option}: {path} is a link to {os.readlink(path)}, which does not exist")
    return Path(os.path.realpath(path))


# The reference records (tests/golden/): the commit that last changed one moved a number of the
# pipeline on purpose, and results made by older code no longer describe this code.
GOLDEN_FILES = ("tests/golden/pipeline.json", "tests/golden/env_digests.json")
REPO = Path(__file__).resolve().parents[2]


def _git(repo: Path, *args: str) -> subprocess.CompletedProcess | None:
    try:
        return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None


def code_commit(results: Any) -> str | None:
    """The commit recorded in a results file's provenance (`code.commit`, wherever it sits)."""
    if isinstance(results, dict):
        code = results.get("code")
        if isinstance(code, dict) and code.get("commit"):
            return str(code["commit"])
        for value in results.values():
            if (found := code_commit(value)) is not None:
                return found
    return None


def stale_results(found: dict[str, dict], repo: Path = REPO) -> list[str]:
    """The results files made by code older than the last commit that moved a golden number:
    "<name>: why". Empty outside a git checkout or in a shallow clone (no history to compare)."""
    shallow = _git(repo, "rev-parse", "--is-shallow-repository")
    last = _git(repo, "log", "-1", "--format=%H", "--", *GOLDEN_FILES)
    if shallow is None or shallow.stdout.strip() != "false" or last is None or last.returncode != 0 \
            or not last.stdout.strip():
        return []
    golden = last.stdout.strip()
    stale = []
    for name, results in found.items():
        commit = code_commit(results)
        if commit is None:
            stale.append(f"{name}: records no code commit")
            continue
        rc = _git(repo, "merge-base", "--is-ancestor", golden, commit)
        if rc is not None and rc.returncode == 1:
            stale.append(f"{name}: made at {commit[:10]}, before {golden[:10]} moved the golden numbers")
        elif rc is None or rc.returncode != 0:
            stale.append(f"{name}: its commit {commit[:10]} is not in this repository's history")
    return stale


def machine() -> dict[str, Any]:
    """The machine this runs on: CPU model, cores, OS, Python and package versions."""
    cpu = [platform.processor() or platform.machine()]
    with contextlib.suppress(OSError):
        cpu = [ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
               if ln.startswith("model name")] + cpu
    versions = {}
    for pkg in ("mujoco", "torch"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            versions[pkg] = metadata.version(pkg)
    return {"cpu": cpu[0], "cores": os.cpu_count(), "os": f"{platform.system()} {platform.machine()}",
            "python": platform.python_version(), **versions}


def _utc(timestamp: float) -> str:
    return datetime.fromtimestamp(timestamp, timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def read_runs(runs: str | Path, results_dir: str | Path) -> dict[str, tuple[Path, dict]]:
    """{name: (runs/<name>/results.json, its results)} for the files present, each checked (readable,
    its keys, renderable) before anything is written, and the copies' targets checked for writing."""
    runs, results_dir = Path(runs), Path(results_dir)
    if not runs.is_dir():
        raise ConfigError(f"--runs: {runs} is not a folder (expected {runs}/<name>/results.json for name in "
                          f"{', '.join(EXPERIMENTS)}; pass --runs '' to only render from {results_dir}/)")
    loaded = {}
    for name in EXPERIMENTS:
        if not (path := runs / name / "results.json").is_file():
            continue
        data = _check_shape(name, _read(path), path)
        render_one(name, data, {}, str(path))  # a file the report cannot render stops here, before any write
        loaded[name] = (path, data)
    if not loaded:
        raise ConfigError(f"--runs: {runs} holds no <name>/results.json for any of {', '.join(EXPERIMENTS)}; "
                          f"pass --runs '' to only render from {results_dir}/")
    for name in [*loaded, "report"]:
        write_path(results_dir / f"{name}.json", "--results")
    return loaded


def write_copies(loaded: dict[str, tuple[Path, dict]], results_dir: str | Path) -> list[str]:
    """Write each of `read_runs`' files to results/<name>.json and record the source, its date and the
    machine in results/report.json (a symlinked copy is written through). Returns the names copied."""
    results_dir = Path(results_dir)
    files, here, now = load_results(results_dir, skip=tuple(loaded))[1].get("files", {}), machine(), \
        _utc(datetime.now().timestamp())
    for name, (path, data) in loaded.items():
        target = results_dir / f"{name}.json"
        if name in files and target.is_file() and target.read_bytes() == (to_json(data, indent=2) + "\n").encode():
            continue  # unchanged: keep its record, so a rerun changes nothing
        atomic_write_json(write_path(target, "--results"), data)
        files[name] = {"source": str(path), "written": _utc(path.stat().st_mtime), "copied": now, "machine": here}
    atomic_write_json(write_path(results_dir / "report.json", "--results"), {"files": files})
    return list(loaded)


def copy_results(runs: str | Path, results_dir: str | Path) -> list[str]:
    """Copy runs/<name>/results.json to results/<name>.json (all checked before any write) and record
    the source, its date and the machine in results/report.json. Returns the names copied."""
    return write_copies(read_runs(runs, results_dir), results_dir)
