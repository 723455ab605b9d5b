"""Model checkpoints that load without executing code.

One file (``torch.save`` of plain containers: the state dict's tensors and a JSON
string) carries the weights, the normalisation buffers and the metadata: model
kind, feature set, architecture, parameter count, plus whatever the caller adds
(training config, data summary, seed). A human-readable copy of the metadata is
written beside it as ``<name>.json``; loading reads only the weights file.

Loading uses ``torch.load(..., weights_only=True)``: a file holding any pickled
object other than tensors and plain containers is refused. Writes are atomic
(temporary file, then ``os.replace``).
"""

from __future__ import annotations

import io
import json
import os
import pickle
import struct
import zipfile
from pathlib import Path
from typing import Any

import torch

from downwash_core.errors import CheckpointError
from downwash_core.io import atomic_write_bytes, to_json
from downwash.models import MODEL_KINDS, DownwashModel, make_model

__all__ = [
    "CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "CheckpointError", "save_checkpoint", "load_checkpoint",
    "read_metadata", "read_payload", "write_checkpoint", "sidecar_path",
]

CHECKPOINT_FORMAT = "downwash-model"
CHECKPOINT_VERSION = 1


def _unpickling_reason(e: Exception) -> str:
    """The informative line of torch's long weights-only error message."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    for ln in lines:
        if "Unsupported" in ln:
            return ln
    return lines[0] if lines else type(e).__name__


def sidecar_path(path: str | os.PathLike) -> Path:
    """The JSON metadata copy written beside a checkpoint: ``model.pt`` -> ``model.json``."""
    return Path(path).with_suffix(".json")


def save_checkpoint(path: str | os.PathLike, model: DownwashModel, meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write ``model`` and metadata to ``path`` (conventionally ``*.pt``) atomically.

    meta: JSON-serialisable extras (NumPy values, paths and dataclasses such as
    TrainConfig are converted); the key "model" is reserved. The stored record is
    ``{**meta, "model": model.describe() + normalisation + dtype}``; it is returned.
    """
    meta = dict(meta or {})
    if "model" in meta:
        raise ValueError("meta: the key 'model' is reserved for the model description")
    if not isinstance(model, DownwashModel):
        raise TypeError(f"model: expected a DownwashModel, got {type(model).__name__}")
    record = dict(meta)
    record["model"] = {
        **model.describe(),
        "normalization": model.normalization(),
        "dtype": str(model.in_mean.dtype).replace("torch.", ""),
    }
    return write_checkpoint(path, model, record, CHECKPOINT_FORMAT, CHECKPOINT_VERSION)


def write_checkpoint(path: str | os.PathLike, model: torch.nn.Module, record: dict, fmt: str, version: int) -> dict:
    """Atomically write `model`'s tensors and `record` (JSON-safe, also as a `.json` sidecar) to `path`;
    returns the record as stored. Shared by the pair and the swarm checkpoints."""
    try:
        meta_json = to_json(record)
    except TypeError as e:
        raise TypeError(f"checkpoint metadata: {e}") from e
    record = json.loads(meta_json)
    payload = {
        "format": fmt,
        "version": version,
        "meta_json": meta_json,
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
    }
    buf = io.BytesIO()
    torch.save(payload, buf)
    path = Path(path)
    atomic_write_bytes(sidecar_path(path), (json.dumps(record, indent=2, sort_keys=True) + "\n").encode())
    atomic_write_bytes(path, buf.getvalue())
    return record


# What torch's weights-only unpickler raises on corrupt bytes besides UnpicklingError (found by the
# property tests: an empty pickle stack, an unknown memo key, a bad zip record, ...).
_CORRUPT_PICKLE_ERRORS = (
    RuntimeError, EOFError, OSError, ValueError, zipfile.BadZipFile, IndexError, KeyError, TypeError, AttributeError,
    struct.error, UnicodeDecodeError, OverflowError, MemoryError,
)
MAX_WIDTH = 4096  # the widest layer a checkpoint may ask for: a larger one is corrupt, not a model


def _check_payload(path: Path, desc: Any, state: Any) -> tuple[str, str, dict]:
    """(kind, feature set, architecture) of well-typed metadata and a state dict of tensors; else CheckpointError."""
    if not isinstance(desc, dict):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: 'model' is not a record")
    kind, feature_set, architecture = desc.get("kind"), desc.get("feature_set"), desc.get("architecture", {})
    if not isinstance(kind, str) or not isinstance(feature_set, str) or not isinstance(architecture, dict):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: kind {kind!r}, feature set {feature_set!r}, "
                              f"architecture {architecture!r}")
    widths = [v for v in architecture.values() for v in (v if isinstance(v, list) else [v])
              if isinstance(v, int) and not isinstance(v, bool)]
    if any(not 1 <= w <= MAX_WIDTH for w in widths):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: architecture {architecture} "
                              f"(layer widths must lie in 1-{MAX_WIDTH})")
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise CheckpointError(f"{path}: corrupt checkpoint: the state dict must map names to tensors")
    return kind, feature_set, architecture


def read_payload(path: Path, fmt: str, version: int, hints: dict[str, str] | None = None) -> tuple[dict, dict]:
    """(payload, metadata record) of a checkpoint that `write_checkpoint` wrote in format `fmt`,
    version `version`, through the safe loader; CheckpointError naming the file otherwise.
    hints: format -> what to say when the file holds that other format instead."""
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        is_zip = zipfile.is_zipfile(path)  # torch.save writes a zip archive
    except (zipfile.BadZipFile, OSError, ValueError) as e:  # e.g. a zip64 record naming a second disk
        raise CheckpointError(f"{path}: not a readable torch checkpoint (truncated or foreign file): {e}") from e
    if not is_zip:
        raise CheckpointError(f"{path}: not a readable torch checkpoint (truncated or foreign file)")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise CheckpointError(
            f"{path}: refused by the safe loader (weights_only=True): it holds objects other than tensors "
            f"and plain containers ({_unpickling_reason(e)})"
        ) from e
    except _CORRUPT_PICKLE_ERRORS as e:
        raise CheckpointError(f"{path}: not a readable torch checkpoint (truncated or foreign file): "
                              f"{type(e).__name__}: {e}") from e
    found = payload.get("format") if isinstance(payload, dict) else None
    if found in (hints or {}) and found != fmt:
        raise CheckpointError(f"{path}: {hints[found]}")
    if found != fmt:
        raise CheckpointError(f"{path}: not a {fmt!r} checkpoint of this project")
    if payload.get("version") != version:
        raise CheckpointError(f"{path}: checkpoint version {payload.get('version')!r}, this code reads {version}")
    try:
        record = json.loads(payload["meta_json"])
    except (KeyError, TypeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: {e!r}") from e
    if not isinstance(record, dict):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: not a record")
    return payload, record


def _read(path: Path) -> tuple[dict, dict]:
    """(payload, metadata record) of a two-vehicle model checkpoint (`read_payload`)."""
    return read_payload(path, CHECKPOINT_FORMAT, CHECKPOINT_VERSION)


def read_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The metadata record of a checkpoint (kind, feature set, provenance, training), read safely
    without rebuilding the model; CheckpointError naming the file when it is not a checkpoint."""
    return _read(Path(path))[1]


def load_checkpoint(
    path: str | os.PathLike,
    expect_kind: str | None = None,
    expect_feature_set: str | None = None,
) -> tuple[DownwashModel, dict[str, Any]]:
    """Rebuild a model from ``path``; returns (model in eval mode, metadata record).

    Raises CheckpointError naming the file when it is missing or unreadable, holds
    anything but tensors and plain containers, is not a checkpoint of this
    project, or its kind / feature set / tensor names and shapes differ from what
    was expected (each difference is named).
    """
    path = Path(path)
    payload, record = _read(path)
    kind, feature_set, architecture = _check_payload(path, record.get("model"), payload.get("state_dict"))
    state = payload["state_dict"]
    desc = record["model"]

    if expect_kind is not None and kind != expect_kind:
        raise CheckpointError(f"{path}: model kind is {kind!r}, expected {expect_kind!r}")
    if expect_feature_set is not None and feature_set != expect_feature_set:
        raise CheckpointError(f"{path}: feature set is {feature_set!r}, expected {expect_feature_set!r}")
    if kind not in MODEL_KINDS:
        raise CheckpointError(f"{path}: unknown model kind {kind!r} (known: {sorted(MODEL_KINDS)})")
    try:
        model = make_model(kind, feature_set, **architecture)
    except (ValueError, TypeError, RuntimeError) as e:
        raise CheckpointError(f"{path}: cannot rebuild the model: {e}") from e
    if desc.get("dtype") == "float64":
        model = model.double()

    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in state.items()} if isinstance(state, dict) else {}
    problems = [f"missing tensor {k!r} (expected shape {s})" for k, s in expected.items() if k not in found]
    problems += [f"unexpected tensor {k!r}" for k in found if k not in expected]
    problems += [
        f"tensor {k!r} has shape {found[k]}, expected {s}" for k, s in expected.items() if k in found and found[k] != s
    ]
    if problems:
        raise CheckpointError(f"{path}: weights do not match a {kind!r} model with feature set {feature_set!r}: " + "; ".join(problems))
    model.load_state_dict(state, strict=True)
    model.eval()
    return model, record
