"""Fitted fields: a registered field with parameters fitted to real labels, read from its JSON.

A field spec ``fitted:PATH`` names the JSON that `downwash.field_fit.write_fitted` wrote: the
registered base field (``base``, e.g. ``so2`` or ``momentum``), the fitted parameters
(``params``), every other parameter as it was during the fit (``fixed``), their bootstrap
intervals, the digest of the real data the fit saw (``data_digest``), the code version and a
``digest`` of the record itself. `resolve_fitted_spec` reads it (strictly: a missing key, a
record whose digest does not match its content, an unknown base field or parameter is a
DataError naming the file and what is wrong) and builds the base field with exactly those
parameters, so the field flies what was fitted even if a default changes later.

Provenance. The field is an instance of a subclass of the base field's class made once per
fitted record (`fitted_class`): it adds nothing but a `describe()` that is the base field's
description plus ``fitted: {base, data_digest, record_digest}`` (not the path: moving a file
does not change what it holds). A subclass rather than a wrapper object because

- the fused tick and `sim.vehicle_params.KindPairs` take a `DownwashField` whose `pairwise` and
  `__call__` are `DownwashField`'s (`sim.plan._packed_field`): a subclass that overrides neither
  stays on the compiled path, a wrapper would leave it;
- `sim.vehicle_params.pair_field` and the envs' domain randomisation copy a field with
  `dataclasses.replace`, which keeps the class, so the digest survives in every copy (an
  instance attribute would be dropped);
- `isinstance(field, DownwashField)` (the envs' knobs and randomisation) still holds.

The class is found again by (base class, record) in a cache, so two reads of one file give
equal fields, and instances pickle by rebuilding it (`__reduce__`). Only sim is imported here:
`sim` may not import `downwash`, which writes these files through `fitted_record`.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from downwash_core.errors import ConfigError, DataError
from downwash_core.io import to_json
from sim.fields.registry import FIELDS

__all__ = ["FITTED_PREFIX", "FITTED_SCHEMA", "REQUIRED_KEYS", "FittedInfo", "fitted_class", "record_digest",
           "fitted_record", "read_fitted", "build_fitted", "resolve_fitted_spec"]

FITTED_PREFIX = "fitted"  # the spec's head: fitted:PATH
FITTED_SCHEMA = "downwash-fitted-field/1"
# what every record must hold (the writer may add more: bootstrap replicates, optimiser, source text)
REQUIRED_KEYS = ("schema", "base", "params", "fixed", "intervals", "data_digest", "source", "code", "digest")
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


@dataclass(frozen=True)
class FittedInfo:
    """What a fitted field's provenance adds to its base field's: the registered base field's name,
    the SHA-256 of the data it was fitted to and of the record that holds it (hex)."""

    base: str
    data_digest: str
    record_digest: str

    def describe(self) -> dict[str, str]:
        return {"base": self.base, "data_digest": self.data_digest, "record_digest": self.record_digest}


def _describe(self: Any) -> dict[str, Any]:
    """The base class's description (its own `describe()`, else its type and fields) plus ``fitted``."""
    from downwash_core.provenance import describe

    cls = type(self)
    base_cls = cls.__mro__[1]
    own = getattr(base_cls, "describe", None)
    if callable(own):
        out = dict(own(self))
    else:
        out = {"type": f"{base_cls.__module__}.{base_cls.__qualname__}",
               **{f.name: describe(getattr(self, f.name)) for f in dataclasses.fields(self)}}
    out["fitted"] = cls.fitted.describe()
    return out


def _reduce(self: Any) -> tuple[Any, tuple[Any, ...]]:
    """Pickle as (base class, init fields, info): the class is rebuilt (found in the cache) on load."""
    cls = type(self)
    kwargs = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}
    return _rebuild, (cls.__mro__[1], kwargs, cls.fitted)


def _rebuild(base_cls: type, kwargs: dict[str, Any], info: FittedInfo) -> Any:
    return fitted_class(base_cls, info)(**kwargs)


@functools.lru_cache(maxsize=None)
def fitted_class(base_cls: type, info: FittedInfo) -> type:
    """The subclass of a field dataclass `base_cls` for one fitted record (module doc); cached, so one
    record gives one class. ConfigError unless `base_cls` is a dataclass."""
    if not dataclasses.is_dataclass(base_cls):
        raise ConfigError(f"fitted field: {base_cls.__qualname__} is not a dataclass of parameters; only such "
                          "fields can be fitted and rebuilt from a record")
    name = f"Fitted{base_cls.__name__}"
    return type(name, (base_cls,), {"fitted": info, "describe": _describe, "__reduce__": _reduce,
                                    "__module__": __name__, "__qualname__": name,
                                    "__doc__": f"{base_cls.__qualname__} with fitted parameters (sim.fields.fitted)."})


def record_digest(record: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of a record's canonical JSON (sorted keys), without its own ``digest``."""
    body = {k: v for k, v in record.items() if k != "digest"}
    text = to_json(json.loads(to_json(body)))  # as read back: tuples are lists, NumPy numbers plain
    return hashlib.sha256(text.encode()).hexdigest()


def fitted_record(**entries: Any) -> dict[str, Any]:
    """A record for a file (`downwash.field_fit.write_fitted`): `entries` (REQUIRED_KEYS but schema and
    digest, and any more) with the schema and the digest set; ConfigError when one is missing."""
    missing = [k for k in REQUIRED_KEYS if k not in ("schema", "digest") and k not in entries]
    if missing:
        raise ConfigError(f"fitted record: missing {missing}")
    record = json.loads(to_json({"schema": FITTED_SCHEMA, **entries}))
    record["digest"] = record_digest(record)
    return record


def _check_record(record: Any, where: str) -> dict[str, Any]:
    """The record if it is one (REQUIRED_KEYS, types, digest); DataError naming the first fault."""
    if not isinstance(record, dict):
        raise DataError(f"{where}: expected a JSON object (a fitted field), got {type(record).__name__}")
    missing = [k for k in REQUIRED_KEYS if k not in record]
    if missing:
        raise DataError(f"{where}: not a fitted field record: missing key(s) {missing}; expected {list(REQUIRED_KEYS)}")
    if record["schema"] != FITTED_SCHEMA:
        raise DataError(f"{where}: schema {record['schema']!r}; this code reads {FITTED_SCHEMA!r}")
    for key in ("data_digest", "digest"):
        if not isinstance(record[key], str) or not _HEX64.match(record[key]):
            raise DataError(f"{where}: {key}: expected 64 lowercase hex digits (SHA-256), got {record[key]!r}")
    for key in ("params", "fixed"):
        if not isinstance(record[key], dict):
            raise DataError(f"{where}: {key}: expected an object of parameters, got {type(record[key]).__name__}")
    bad = {k: v for k, v in record["params"].items()
           if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)}
    if bad or not record["params"]:
        raise DataError(f"{where}: params: expected finite numbers (the fitted parameters), got {bad or 'none'}")
    actual = record_digest(record)
    if actual != record["digest"]:
        raise DataError(f"{where}: digest mismatch: the file says {record['digest'][:12]}..., its content hashes to "
                        f"{actual[:12]}...: edited or corrupted since it was written (refit, or restore it)")
    return record


def read_fitted(path: str | Path, data_digest: str | None = None) -> dict[str, Any]:
    """The checked record of a fitted-field JSON (module doc); DataError for a missing, unreadable or
    malformed file, a digest mismatch, or a ``data_digest`` other than the one asked for."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise DataError(f"{path}: cannot read the fitted field: {e.strerror or e}") from None
    try:
        record = json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: not JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    record = _check_record(record, str(path))
    if data_digest is not None and record["data_digest"] != data_digest:
        raise DataError(f"{path}: fitted to data {record['data_digest'][:12]}..., not the data asked for "
                        f"({data_digest[:12]}...)")
    return record


def build_fitted(record: Mapping[str, Any], where: str = "fitted field") -> Any:
    """The field of a checked record: the registered base field built with ``fixed`` and ``params``,
    as an instance of its `fitted_class`; DataError for an unknown base field or parameter."""
    base = record["base"]
    if base not in FIELDS:
        raise DataError(f"{where}: base field {base!r} is not registered here (registered: {', '.join(FIELDS)})")
    entry = FIELDS[base]
    values = {**record["fixed"], **record["params"]}
    unknown = sorted(set(values) - set(entry.params))
    if unknown:
        raise DataError(f"{where}: field {base!r} has no parameter(s) {unknown} (this code's: "
                        f"{', '.join(entry.params)}): written by another version")
    try:
        field = entry.make(**{k: entry.params[k](v) for k, v in values.items()})
    except (ConfigError, TypeError) as e:
        raise DataError(f"{where}: field {base!r} rejects the recorded parameters: {e}") from None
    if not dataclasses.is_dataclass(field):
        raise DataError(f"{where}: field {base!r} builds a {type(field).__name__}, not a dataclass of parameters")
    info = FittedInfo(base, record["data_digest"], record["digest"])
    cls = fitted_class(type(field), info)
    return cls(**{f.name: getattr(field, f.name) for f in dataclasses.fields(field) if f.init})


def resolve_fitted_spec(path: str, label: str = "field") -> Any:
    """The field of a spec ``fitted:PATH`` (PATH: the JSON of `downwash.field_fit.write_fitted`); ConfigError
    for an empty path, DataError (prefixed with `label`) for a bad file (`read_fitted`, `build_fitted`)."""
    if not isinstance(path, str) or not path.strip():
        raise ConfigError(f"{label}: expected {FITTED_PREFIX}:PATH, the JSON of a fitted field, got {path!r}")
    try:
        return build_fitted(read_fitted(path.strip()), path.strip())
    except DataError as e:
        raise DataError(f"{label}: {e}") from None
