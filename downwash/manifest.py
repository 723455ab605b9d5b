"""A staged collection's manifest: what it records of every flight log, and the check of the logs
against it (`downwash.staged` writes it; training, the sweep and reruns check it).

As each stage's flights are done, the manifest records every log of the stage: its
SHA-256 (of the file, read in 1 MiB chunks), the digest of its arrays, its rows,
labelled samples and status; as each model is trained (each stage's deployed model, the final
models), it records the model's content digest (`downwash.checkpoint.checkpoint_digest`).
Before anything is trained or flown on a collection, its logs and models are checked
against that record (`verify_collection`): a missing, altered or unlisted log, or a model
altered or replaced, stops the run with a DataError naming the file and what to do. The check reads
every log each time: about 0.05 s for a full collection (72 logs, 54 MB) in the page
cache. `collection_digest` keys the sweep's cells by the data they train on.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from downwash_core.errors import DataError
from downwash_core.errors import CheckpointError
from downwash_core.io import atomic_write_json, to_json
from downwash_core.provenance import fingerprint
from downwash.checkpoint import checkpoint_digest
from downwash.labels import labels_from_log
from sim.logs import FlightLog, load_log

__all__ = ["MANIFEST_VERSION", "file_sha256", "log_record", "read_manifest", "verify_collection", "check_logs",
           "integrity_error", "listed_logs", "recorded_models", "check_models", "write_manifest", "load_manifest_file", "stage_folder", "finished_stages", "collection_logs", "collection_digest", "rerun_command"]

MANIFEST_VERSION = 4  # 4: every model's digest; 3: every log's digests and sample count; 2: provenance, resume
_CHUNK = 1 << 20  # bytes read at a time when hashing a log
_DIGEST_KEY = "manifest_sha256"  # the manifest's digest of the rest of itself
_RERUN = "python -m experiments.staged_collection"


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file, read in 1 MiB chunks (a log is never held twice in memory)."""
    h, buf = hashlib.sha256(), bytearray(_CHUNK)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as f:
        while n := f.readinto(buf):
            h.update(view[:n])
    return h.hexdigest()


def _data_sha256(log: FlightLog) -> str:
    """The digest of a log's arrays (names, dtypes, shapes, values), not of its metadata: a log re-flown
    by a later commit holds the same data in a file whose metadata (the code version) differ."""
    h = hashlib.sha256()
    for name in sorted(log.arrays):
        a = np.ascontiguousarray(log.arrays[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def log_record(path: Path) -> dict[str, Any]:
    """What the manifest records of one log: digests, size, rows, labelled samples, how the flight ended."""
    log_ = load_log(path)
    return {"sha256": file_sha256(path), "bytes": path.stat().st_size, "data_sha256": _data_sha256(log_),
            "rows": len(log_), "samples": int(len(labels_from_log(log_, source=path)["y"])),
            "status": log_.meta.get("status_name"), "message": log_.meta.get("message", "")}


def stage_folder(key: int | str) -> str:
    """The folder of a manifest's stage: stage<k> for a numbered stage, else its name (e.g. kinds-heavy)."""
    return f"stage{key}" if str(key).isdigit() else str(key)


def finished_stages(manifest: dict) -> list[tuple[int | str, dict]]:
    """(stage, entry) of every stage whose logs the manifest records: numbered stages in order, then
    named ones (the swarm's stages of other vehicle kinds) in name order."""
    done = [(int(k) if k.isdigit() else k, e) for k, e in manifest.get("stages", {}).items() if e.get("flights_done")]
    return sorted(done, key=lambda ke: (isinstance(ke[0], str), str(ke[0]).zfill(9)))


def listed_logs(out: Path, manifest: dict) -> dict[Path, dict]:
    """Every log the manifest records (finished stages), by path, in stage and flight order."""
    return {out / stage_folder(k) / rel: info for k, entry in finished_stages(manifest)
            for rel, info in sorted(entry.get("files", {}).items())}


def check_logs(out: Path, manifest: dict, scope: Sequence[Path] | None = None) -> list[tuple[str, Path, str]]:
    """(problem, path, detail) for every recorded log under `scope` (folders; default: every finished
    stage) that is missing or altered, and every .npz file there that the manifest does not list."""
    listed = listed_logs(out, manifest)
    if scope is None:
        scope = [out / stage_folder(k) for k, _ in finished_stages(manifest)]
    problems = []
    for path, info in listed.items():
        if not any(path.is_relative_to(s) for s in scope):
            continue
        if not path.is_file():
            problems.append(("missing", path, "missing (it was flown and recorded in the manifest)"))
            continue
        size = path.stat().st_size
        digest = file_sha256(path) if size == info["bytes"] else None
        if size != info["bytes"]:
            problems.append(("altered", path, f"altered since it was flown ({size} bytes, the manifest records "
                                              f"{info['bytes']})"))
        elif digest != info["sha256"]:
            problems.append(("altered", path, f"altered since it was flown (SHA-256 {digest[:12]}..., the manifest "
                                              f"records {info['sha256'][:12]}...)"))
    for s in scope:
        for path in sorted(s.rglob("*.npz")) if s.is_dir() else []:
            if path not in listed:
                problems.append(("extra", path, "not a log of this collection (the manifest does not list it)"))
    return problems


def recorded_models(out: Path, manifest: dict, models_dir: Path | None) -> dict[Path, str]:
    """The content digest the manifest records of every model it made, by path: each stage's deployed
    model (``model_sha256`` of its stage entry) and, with `models_dir`, the final models."""
    models = {out / stage_folder(k) / e["model_file"]: e["model_sha256"]
              for k, e in manifest.get("stages", {}).items() if "model_sha256" in e}
    if models_dir is not None:
        models.update({models_dir / f"{kind}.pt": e["sha256"] for kind, e in manifest.get("final_models", {}).items()
                       if "sha256" in e})
    return models


def check_models(out: Path, manifest: dict, models_dir: Path | None) -> list[tuple[str, Path, str]]:
    """("model", path, detail) for every recorded model that is there but is not the model recorded: its
    content does not match its own digest (a corrupt file), or it is another model. (A missing model is
    trained again by the collection, bit for bit the one it was.)"""
    problems = []
    for path, recorded in recorded_models(out, manifest, models_dir).items():
        if not path.is_file():
            continue
        try:
            found = checkpoint_digest(path)
        except CheckpointError as e:
            problems.append(("model", path, str(e).removeprefix(f"{path}: ")))
            continue
        if found != recorded:
            problems.append(("model", path, f"not the model this collection trained (content SHA-256 {found[:12]}..., "
                                            f"the manifest records {recorded[:12]}...)"))
    return problems


def integrity_error(out: Path, problems: list[tuple[str, Path, str]], rerun: str) -> DataError:
    """The DataError for `problems`: each file and what is wrong, then how to re-fly or remove it."""
    kinds = {p[0] for p in problems}
    lines = [f"{path}: {detail}" for _, path, detail in problems[:20]]
    if len(problems) > 20:
        lines.append(f"... and {len(problems) - 20} more")
    advice = []
    if kinds & {"missing", "altered"}:
        advice.append(("Delete the altered logs and rerun" if "altered" in kinds else "Rerun")
                      + f" `{rerun}` with the options that made this collection (its manifest's provenance): "
                      "a rerun re-flies only what is missing, with the seeds of the original flights.")
    if "model" in kinds:
        advice.append(f"Delete the altered models and rerun `{rerun}`: it trains them again, as they were.")
    if "extra" in kinds:
        advice.append("Move the unlisted files out of the stage folders (a collection holds only the logs it flew).")
    what = "logs and models" if "model" in kinds else "logs"
    return DataError(f"{out}: the collection's {what} do not match its manifest ({out / 'manifest.json'}), so nothing "
                     "is trained on them:\n  " + "\n  ".join(lines) + "\n" + " ".join(advice))


def rerun_command(collection_dir: Path, models_dir: Path | None = None) -> str:
    return f"{_RERUN} --collection-dir {collection_dir}" + (f" --models-dir {models_dir}" if models_dir else "")


def verify_collection(collection_dir: str | Path, manifest: dict | None = None, models_dir: str | Path | None = None,
                      scope: Sequence[Path] | None = None) -> None:
    """DataError, naming each file and how to re-fly it, unless every log that the manifest of
    `collection_dir` records is there unaltered (its SHA-256), no unlisted .npz lies in a stage folder,
    and every model it records that is there (its stage models; with `models_dir` its final models) is
    the one it trained.

    Reads every log (streaming): about 0.05 s for a full collection in the page cache.
    scope: only these folders (stage or train/val folders; default every finished stage).
    """
    out = Path(collection_dir)
    manifest = read_manifest(out / "manifest.json") if manifest is None else manifest
    problems = check_logs(out, manifest, scope) + check_models(out, manifest, None if models_dir is None
                                                               else Path(models_dir))
    if problems:
        raise integrity_error(out, problems, rerun_command(out, Path(models_dir) if models_dir else None))


def collection_logs(collection_dir: str | Path, role: str, manifest: dict | None = None) -> list[list[Path]]:
    """The logs of a role ("train" or "val") of a collection, per stage, as its manifest lists them (not checked)."""
    out = Path(collection_dir)
    manifest = read_manifest(out / "manifest.json") if manifest is None else manifest
    return [[out / stage_folder(k) / rel for rel in sorted(e.get("files", {})) if rel.startswith(f"{role}/")]
            for k, e in finished_stages(manifest)]


def collection_digest(collection_dir: str | Path, manifest: dict | None = None) -> str:
    """A digest of a collection's data: every log's data digest (its arrays) by stage and name, training
    and validation, as the manifest records them. Keys the sweep's cells: other data, other cells."""
    out = Path(collection_dir)
    manifest = read_manifest(out / "manifest.json") if manifest is None else manifest
    data = {f"{stage_folder(k)}/{rel}": info["data_sha256"] for k, e in manifest.get("stages", {}).items()
            for rel, info in e.get("files", {}).items()}
    if not data:
        raise DataError(f"{out / 'manifest.json'}: records no logs; run `{rerun_command(out)}` to collect them")
    return fingerprint(data, length=16)


def _manifest_digest(manifest: dict) -> str:
    """The SHA-256 of a manifest's content (canonical JSON: sorted keys, no spacing), less its own digest."""
    return hashlib.sha256(to_json({k: v for k, v in manifest.items() if k != _DIGEST_KEY}).encode()).hexdigest()


def write_manifest(path: Path, manifest: dict) -> None:
    """Write a collection's manifest atomically, stamped with the digest of its content (in place)."""
    manifest[_DIGEST_KEY] = _manifest_digest(manifest)
    atomic_write_json(path, manifest)


def load_manifest_file(path: Path, check: Callable[[dict], None] = lambda manifest: None) -> dict:
    """A manifest as `write_manifest` wrote it, its digest checked: DataError naming the file when it is
    unreadable, not a JSON object, or altered since it was written (or has no digest: an older
    version's). check(manifest): a caller's check of the format, before the digest's."""
    try:
        manifest = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: unreadable collection manifest ({e}); delete the folder to start afresh") from e
    if not isinstance(manifest, dict):
        raise DataError(f"{path}: unreadable collection manifest (not a JSON object); delete the folder to start "
                        "afresh")
    check(manifest)
    recorded = manifest.get(_DIGEST_KEY)
    if recorded is None:
        raise DataError(f"{path}: a collection manifest with no digest of itself (written by an older version); "
                        "delete the folder to collect afresh")
    found = _manifest_digest(manifest)
    if found != recorded:
        raise DataError(f"{path}: the collection manifest was altered since it was written (its content's SHA-256 "
                        f"is {found[:12]}..., it records {str(recorded)[:12]}...); restore it, or delete the folder to "
                        "collect afresh")
    return manifest


def read_manifest(path: Path) -> dict:
    """A collection manifest of this format; DataError naming the file otherwise."""
    if not path.is_file():
        raise DataError(f"{path}: no collection manifest here, so this is no staged collection (or an unfinished "
                        f"one); run `{rerun_command(path.parent)}` to collect it")

    def check(manifest: dict) -> None:
        if manifest.get("version") != MANIFEST_VERSION or "provenance" not in manifest:
            raise DataError(f"{path}: a collection of an older format (manifest version {manifest.get('version')!r}; "
                            f"this code records and checks every log's and model's digest, version "
                            f"{MANIFEST_VERSION}); delete the folder (and its models folder) to collect afresh, or use "
                            "another --collection-dir")

    manifest = load_manifest_file(path, check)
    return manifest
