"""Model checkpoints of every kind, loaded without executing code.

One file (``torch.save`` of plain containers: the state dict's tensors and a JSON
string) carries the weights, the normalisation buffers and the metadata: model
kind, feature set, architecture, parameter count, plus whatever the caller adds
(training config, data summary, seed). A model of sets also records what it was
made for: its neighbour set, the aggregation law and the field of its training data;
asking for another set or law raises `CheckpointError` before any flight. A human-readable copy of the metadata is
written beside it as ``<name>.json``; loading reads only the weights file.

Loading uses ``torch.load(..., weights_only=True)``: a file holding any pickled
object other than tensors and plain containers is refused. Writes are atomic
(temporary file, then ``os.replace``).

Integrity. torch ignores the zip's CRC-32s, so a flipped bit in a weight would load and
fly. Each file therefore carries the SHA-256 of its metadata and of every tensor's name,
dtype, shape and bytes (`content_digest`), also written in the sidecar; every load
(`load_checkpoint`, `read_metadata`) recomputes it and raises `CheckpointError` naming the
file when it differs. A collection's manifest records the same digest of each model it
made (`downwash.manifest`), so a model swapped for another valid one is found too.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import struct
import zipfile
from pathlib import Path
import copy
from typing import Any, NamedTuple

import torch
from torch import nn

from downwash_core.errors import CheckpointError, ConfigError
from downwash_core.io import atomic_write_bytes, to_json
from downwash_core.provenance import differences
from downwash.datasets import aggregation_record
from downwash.models import MAX_WIDTH, DownwashModel
from downwash.registry import MODEL_KINDS, make_model
from downwash.set_models import SetModel, SummedPairwise
from sim.neighbours import NeighbourSet

__all__ = [
    "CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "Checkpoint", "CheckpointError", "save_checkpoint", "load_checkpoint",
    "wrap_pairwise", "check_expectations", "read_metadata", "sidecar_path", "content_digest", "checkpoint_digest",
]

CHECKPOINT_FORMAT = "downwash-model"
CHECKPOINT_VERSION = 2  # 2: the content's SHA-256, checked on every load; 1 (no digest) is refused
_OLD_SET_FORMAT = "downwash-swarm-model"  # models of sets were written in a format of their own; still read


class Checkpoint(NamedTuple):
    """A model (eval mode) with its record (kind, provenance, training, and for a model of sets
    its ``neighbours``, ``aggregation`` and ``field``); unpacks as ``model, record``."""

    model: nn.Module
    record: dict[str, Any]

    @property
    def neighbours(self) -> NeighbourSet:
        """The neighbour set a model of sets was trained for; a per-neighbour model sees every
        other vehicle (`NeighbourSet()`)."""
        stored = self.record.get("neighbours")
        return NeighbourSet() if stored is None else NeighbourSet.from_record(stored)


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


def save_checkpoint(path: str | os.PathLike, model: nn.Module, meta: dict[str, Any] | None = None, *,
                    neighbours: NeighbourSet | None = None, provenance: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write ``model`` and metadata to ``path`` (conventionally ``*.pt``) atomically.

    meta: JSON-serialisable extras (NumPy values, paths and dataclasses such as TrainConfig
      are converted); the keys "model", "neighbours", "aggregation", "field" are reserved.
    neighbours, provenance: required for a model of sets: the neighbour set it was trained
      for and what its data was flown with (`Dataset.provenance`, or a `Checkpoint.record`);
      its ``aggregation`` (a law or its record, or None for two-vehicle data only) and
      ``field`` are stored at the top of the record, where the loader checks them.
    The stored record is ``{**meta, "model": model.describe() + normalisation + dtype, ...}``;
    it is returned.
    """
    meta = dict(meta or {})
    reserved = sorted({"model", "neighbours", "aggregation", "field"} & set(meta))
    if reserved:
        raise ValueError(f"meta: the keys {reserved} are reserved")
    if not isinstance(model, (DownwashModel, SetModel)):
        raise TypeError(f"model: expected a model of downwash.registry.MODEL_KINDS, got {type(model).__name__}")
    record = dict(meta)
    record["model"] = {
        **model.describe(),
        "normalization": model.normalization(),
        "dtype": str(next(model.buffers()).dtype).replace("torch.", ""),
    }
    if isinstance(model, SetModel):
        if not isinstance(neighbours, NeighbourSet):
            raise TypeError(f"neighbours: a model of sets needs its NeighbourSet, got {type(neighbours).__name__}")
        provenance = dict(provenance or {})
        if "aggregation" not in provenance:
            raise ValueError("provenance: must name the aggregation law of the training data ('aggregation')")
        record.update(
            provenance={k: v for k, v in provenance.items() if k not in ("aggregation", "field")} or None,
            neighbours=neighbours.describe(),
            aggregation=None if provenance["aggregation"] is None else aggregation_record(provenance["aggregation"]),
            field=provenance.get("field"),
        )
    return write_checkpoint(path, model, record, CHECKPOINT_FORMAT, CHECKPOINT_VERSION)


def content_digest(meta_json: str, state: dict[str, torch.Tensor]) -> str:
    """The SHA-256 (hex) of a checkpoint's content: its metadata text and, in name order, every
    tensor's name, dtype, shape and bytes. Independent of how torch lays out the zip."""
    h = hashlib.sha256(meta_json.encode())
    for name in sorted(state):
        t = state[name].detach().cpu().contiguous()
        h.update(f"\0{name}:{t.dtype}:{tuple(t.shape)}\0".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def write_checkpoint(path: str | os.PathLike, model: torch.nn.Module, record: dict, fmt: str, version: int) -> dict:
    """Atomically write `model`'s tensors, `record` (JSON-safe) and their `content_digest` to `path`, with
    the record and the digest (``content_sha256``) as a `.json` sidecar; returns the record as stored."""
    try:
        meta_json = to_json(record)
    except TypeError as e:
        raise TypeError(f"checkpoint metadata: {e}") from e
    record = json.loads(meta_json)
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    digest = content_digest(meta_json, state)
    payload = {"format": fmt, "version": version, "meta_json": meta_json, "state_dict": state, "content_sha256": digest}
    buf = io.BytesIO()
    torch.save(payload, buf)
    path = Path(path)
    sidecar = {**record, "content_sha256": digest}
    atomic_write_bytes(sidecar_path(path), (json.dumps(sidecar, indent=2, sort_keys=True) + "\n").encode())
    atomic_write_bytes(path, buf.getvalue())
    return record


# What torch's weights-only unpickler raises on corrupt bytes besides UnpicklingError (found by the
# property tests: an empty pickle stack, an unknown memo key, a bad zip record, ...).
_CORRUPT_PICKLE_ERRORS = (
    RuntimeError, EOFError, OSError, ValueError, zipfile.BadZipFile, IndexError, KeyError, TypeError, AttributeError,
    struct.error, UnicodeDecodeError, OverflowError, MemoryError,
)
def _widths(value: Any) -> list[int]:
    """Every integer in an architecture record (layer widths, latent sizes)."""
    if isinstance(value, dict):
        return [w for v in value.values() for w in _widths(v)]
    if isinstance(value, list):
        return [w for v in value for w in _widths(v)]
    return [value] if isinstance(value, int) and not isinstance(value, bool) else []


def _check_payload(path: Path, desc: Any, state: Any) -> tuple[str, str | None, dict]:
    """(kind, feature set (None for a model of sets), architecture) of well-typed metadata and a state
    dict of tensors; else CheckpointError."""
    if not isinstance(desc, dict):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: 'model' is not a record")
    kind, feature_set, architecture = desc.get("kind"), desc.get("feature_set"), desc.get("architecture", {})
    pairwise = isinstance(kind, str) and isinstance(MODEL_KINDS.get(kind), type) and issubclass(MODEL_KINDS[kind], DownwashModel)
    if (not isinstance(kind, str) or not isinstance(architecture, dict)
            or not (isinstance(feature_set, str) if pairwise else feature_set is None)):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: kind {kind!r}, feature set {feature_set!r}, "
                              f"architecture {architecture!r}")
    if any(not 1 <= w <= MAX_WIDTH for w in _widths(architecture)):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: architecture {architecture} "
                              f"(sizes must lie in 1-{MAX_WIDTH})")
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()):
        raise CheckpointError(f"{path}: corrupt checkpoint: the state dict must map names to tensors")
    return kind, feature_set, architecture


def _read(path: Path) -> tuple[dict, dict]:
    """(payload, metadata record) of a checkpoint that `write_checkpoint` wrote (or an old model of
    sets' file), through the safe loader; CheckpointError naming the file otherwise."""
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
    if found not in (CHECKPOINT_FORMAT, _OLD_SET_FORMAT):
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT!r} checkpoint of this project")
    if payload.get("version") == 1:
        raise CheckpointError(f"{path}: a checkpoint of an older format (version 1) that carries no digest of its "
                              "weights, so a corrupted copy cannot be told apart; delete it and rerun to train it "
                              "again")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {payload.get('version')!r}, this code reads "
                              f"{CHECKPOINT_VERSION}")
    meta_json, state, recorded = payload.get("meta_json"), payload.get("state_dict"), payload.get("content_sha256")
    if (not isinstance(meta_json, str) or not isinstance(recorded, str) or not isinstance(state, dict)
            or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items())):
        raise CheckpointError(f"{path}: corrupt checkpoint: its metadata text, state dict of tensors or digest is "
                              "missing or of the wrong type")
    found = content_digest(meta_json, state)
    if found != recorded:
        raise CheckpointError(f"{path}: corrupt checkpoint: its content's SHA-256 is {found[:12]}..., the file "
                              f"records {recorded[:12]}... (altered since it was written); restore it, or delete it "
                              "and rerun to train it again")
    try:
        record = json.loads(meta_json)
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: {e!r}") from e
    if not isinstance(record, dict):
        raise CheckpointError(f"{path}: corrupt checkpoint metadata: not a record")
    return payload, record


def checkpoint_digest(path: str | os.PathLike) -> str:
    """The content SHA-256 that the checkpoint at `path` records, after checking that its content has it
    (CheckpointError naming the file otherwise): what a manifest records of a model."""
    return _read(Path(path))[0]["content_sha256"]


def read_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The metadata record of a checkpoint (kind, feature set, provenance, training), read safely
    without rebuilding the model; CheckpointError naming the file when it is not a checkpoint."""
    return _read(Path(path))[1]


def check_expectations(where: Any, neighbours: NeighbourSet, record: dict[str, Any],
                       expect_neighbours: NeighbourSet | None = None, expect_aggregation: Any = None) -> None:
    """CheckpointError when a model's neighbour set or aggregation law is not the one asked for.

    expect_aggregation: a registered name, a law object or a stored record (`aggregation_record`).
    """
    if expect_neighbours is not None and neighbours != expect_neighbours:
        raise CheckpointError(f"{where}: trained for the neighbour set {neighbours.describe()}, but the flight "
                              f"asks for {expect_neighbours.describe()}; train or wrap a model for that set")
    if expect_aggregation is not None:
        want = aggregation_record(expect_aggregation)
        have = record.get("aggregation")
        if have is None:
            raise CheckpointError(f"{where}: trained on two-vehicle flights only (where every law is the pairwise "
                                  f"force), not for the flight's aggregation law {want}")
        diffs = differences(have, want)
        if diffs:
            raise CheckpointError(f"{where}: trained for another aggregation law than the flight's:\n  "
                                  + "\n  ".join(diffs))


def load_checkpoint(
    path: str | os.PathLike,
    expect_kind: str | None = None,
    expect_feature_set: str | None = None,
    expect_neighbours: NeighbourSet | None = None,
    expect_aggregation: Any = None,
) -> Checkpoint:
    """Rebuild a model from ``path``; returns its `Checkpoint` (model in eval mode, metadata record).

    Raises CheckpointError naming the file when it is missing or unreadable, holds
    anything but tensors and plain containers, is not a checkpoint of this project, or
    its kind, feature set, tensor names and shapes, neighbour set or aggregation law
    (a model of sets) differ from what was expected (each difference is named).
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
    if issubclass(MODEL_KINDS[kind], SetModel):
        try:
            neighbours = NeighbourSet.from_record(record.get("neighbours"))
        except ConfigError as e:
            raise CheckpointError(f"{path}: corrupt checkpoint metadata: {e}") from e
        if "aggregation" not in record or not isinstance(record["aggregation"], (dict, type(None))):
            raise CheckpointError(f"{path}: corrupt checkpoint metadata: no aggregation law record")
        check_expectations(path, neighbours, record, expect_neighbours, expect_aggregation)
    try:
        model = make_model(kind, **architecture) if feature_set is None else make_model(kind, feature_set, **architecture)
    except (ValueError, TypeError, RuntimeError) as e:
        raise CheckpointError(f"{path}: cannot rebuild the model: {e}") from e
    if desc.get("dtype") == "float64":
        model = model.double()

    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in state.items()}
    problems = [f"missing tensor {k!r} (expected shape {s})" for k, s in expected.items() if k not in found]
    problems += [f"unexpected tensor {k!r}" for k in found if k not in expected]
    problems += [
        f"tensor {k!r} has shape {found[k]}, expected {s}" for k, s in expected.items() if k in found and found[k] != s
    ]
    if problems:
        what = f"a {kind!r} model" + (f" with feature set {feature_set!r}" if feature_set is not None else "")
        raise CheckpointError(f"{path}: weights do not match {what}: " + "; ".join(problems))
    model.load_state_dict(state, strict=True)
    model.eval()
    return Checkpoint(model, record)


def _field_of(record: dict[str, Any]) -> Any:
    """The field a per-neighbour checkpoint's data was flown on (staged: provenance.field;
    experiments.train: provenance.flights.field), or None when it does not say."""
    prov = record.get("provenance")
    if not isinstance(prov, dict):
        return None
    if "field" in prov:
        return prov["field"]
    flights = prov.get("flights")
    return flights.get("field") if isinstance(flights, dict) else None


def wrap_pairwise(pairwise: DownwashModel | Checkpoint | str | os.PathLike, neighbours: NeighbourSet | None = None,
                  expect_kind: str | None = None) -> Checkpoint:
    """``summed_pairwise`` from a trained per-neighbour model, its `Checkpoint` or its checkpoint file.

    The aggregation law recorded is the linear sum (what summing pairs assumes); the field is
    that of the pair model's data when its checkpoint says, and the checkpoint's data summary
    (its support, which the guard reads) is kept. neighbours: default `NeighbourSet()` (every
    other vehicle).
    """
    neighbours = NeighbourSet() if neighbours is None else neighbours
    record: dict[str, Any] = {}
    path = None
    if isinstance(pairwise, (str, os.PathLike)):
        path = pairwise
        pairwise = load_checkpoint(path, expect_kind=expect_kind)
    if isinstance(pairwise, Checkpoint):
        pairwise, stored = pairwise
        if not isinstance(pairwise, DownwashModel):
            raise CheckpointError(f"{path or 'checkpoint'}: a {pairwise.kind!r} model of sets, not a per-neighbour "
                                  "model to wrap")
        record = {"pairwise_checkpoint": None if path is None else str(path), "pairwise_provenance":
                  stored.get("provenance"), "field": _field_of(stored), "data": stored.get("data")}
    if expect_kind is not None and getattr(pairwise, "kind", None) != expect_kind:
        raise ConfigError(f"pairwise: model kind is {getattr(pairwise, 'kind', None)!r}, expected {expect_kind!r}")
    model = SummedPairwise(copy.deepcopy(pairwise)).eval()  # the caller's model stays as it is
    record = {**record, "model": {**model.describe(), "dtype": str(model.dtype).replace("torch.", "")},
              "neighbours": neighbours.describe(), "aggregation": aggregation_record("linear")}
    record.setdefault("field", None)
    return Checkpoint(model, record)
