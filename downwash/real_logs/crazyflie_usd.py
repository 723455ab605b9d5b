"""The Crazyflie micro-SD card deck's log formats, read and written exactly: the synchronous one of
2019-2020 and the current event-based one (version 2).

This is the format of the Crazyflie firmware's uSD deck in 2019-2020 (logging in the
stabilizer loop, "mode 1: synchronous"), the one the Neural-Swarm data set's onboard
binaries are in. Written from the format's layout (all little-endian):

    header   [n: u8]  n entries ``name(t),`` in ASCII, t a struct type code   [CRC-32: 4 bytes]
    blocks   [count: u8]  count records, each the n fields in header order    [CRC-32: 4 bytes]
             ... to the end of the file

Each CRC-32 covers the bytes of its header or block (the block's count byte included)
and is stored as the one's complement of zlib's CRC-32, little-endian, so that the
CRC-32 of the bytes followed by it is 0xFFFFFFFF.

`read_usd_sync` reads a whole file or nothing: a truncated file, a CRC mismatch, an
unknown field type or a malformed header raises `UsdFormatError` naming the file, the
byte offset and, for a block, its index; values are returned raw, with the log's own
field names and types. The format has no record count or end mark, so a file cut exactly
between two blocks (power lost while logging) reads as the shorter log it then is.
`write_usd_sync` writes the same format, for tests and for tools that make such files.

The current firmware's event-based format (version 2, the layout the firmware's uSD deck driver
writes, bitcraze/crazyflie-firmware `src/deck/drivers/src/usddeck.c` as of 2026-08; all little-endian):

    header   [0xBC: u8] [version 2: u16] [n event types: u16]
             per type: [id: u16] [name, NUL-terminated] [m: u16] m entries ``name(t)`` each NUL-terminated
    records  [event id: u16] [timestamp: u64, microseconds] the event's m values in header order
             ... then [CRC-32 of every byte before it: u32] as the last 4 bytes (zlib's CRC-32)

`read_usd_events` reads it whole or raises `UsdFormatError` naming the file and byte offset
(a bad magic or version, a malformed header, an event id the header does not declare, a
record cut short, a CRC mismatch); `encode_usd_events` writes it.

The firmware logs an attitude as one uint32 (a "compressed quaternion": the index of the
largest component in the top 2 bits, then for each other component, in order, a sign bit
and 9 bits of its magnitude over 1/sqrt(2)); `decompress_quaternions` and
`compress_quaternions` convert, between that and the (w, x, y, z) order used here.
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from downwash_core.errors import LogError
from downwash_core.io import atomic_write_bytes

__all__ = ["USD_SYNC_FORMAT", "USD_EVENTS_FORMAT", "FIELD_TYPES", "UsdFormatError", "UsdLog", "read_usd_sync",
           "encode_usd_sync", "write_usd_sync", "read_usd_events", "encode_usd_events", "decompress_quaternions",
           "compress_quaternions"]

USD_SYNC_FORMAT = "crazyflie-usd-sync"
USD_EVENTS_FORMAT = "crazyflie-usd-events-v2"
_EVENTS_MAGIC, _EVENTS_VERSION = 0xBC, 2
# the struct type codes the firmware's log variables use, with their NumPy types (little-endian)
FIELD_TYPES: dict[str, str] = {"b": "<i1", "B": "<u1", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4",
                               "q": "<i8", "Q": "<u8", "e": "<f2", "f": "<f4", "d": "<f8"}
_MAX_BLOCK = 255  # records in one block: its count is one byte


class UsdFormatError(LogError):
    """A uSD log that is not exactly the format: the message names the file and byte offset."""


@dataclass(frozen=True)
class UsdLog:
    """One decoded file: ``fields[name]`` (N,) raw values in the log's own types, in header order;
    ``types[name]`` the struct code; ``source`` the file, format and SHA-256; ``blocks`` how many."""

    fields: dict[str, np.ndarray]
    types: dict[str, str]
    source: dict[str, Any] = field(default_factory=dict)
    blocks: int = 0

    def __len__(self) -> int:
        return len(next(iter(self.fields.values()))) if self.fields else 0


def _crc(data: bytes) -> bytes:
    """What the format stores after `data`: its CRC-32's complement, little-endian."""
    return ((~zlib.crc32(data)) & 0xFFFFFFFF).to_bytes(4, "little")


def _parse_header(raw: bytes, where: str) -> tuple[list[str], list[str], int]:
    """(names, type codes, offset of the first block) of a file's bytes; UsdFormatError otherwise."""
    if not raw:
        raise UsdFormatError(f"{where}: empty file (no header)")
    n, offset, names, codes = raw[0], 1, [], []
    if n == 0:
        raise UsdFormatError(f"{where}: byte 0: the header declares 0 fields")
    for i in range(n):
        end = raw.find(b",", offset)
        if end < 0:
            raise UsdFormatError(f"{where}: byte {offset}: truncated header (field {i + 1} of {n} has no ',')")
        entry = raw[offset:end]
        try:
            text = entry.decode("ascii")
        except UnicodeDecodeError:
            raise UsdFormatError(f"{where}: byte {offset}: field {i + 1} of the header is not ASCII: {entry[:40]!r}") from None
        if len(text) < 4 or text[-3] != "(" or text[-1] != ")" or not text[:-3].strip():
            raise UsdFormatError(f"{where}: byte {offset}: header field {text!r} is not 'name(t)'")
        name, code = text[:-3].strip(), text[-2]
        if code not in FIELD_TYPES:
            raise UsdFormatError(f"{where}: byte {end - 2}: unknown field type {code!r} of {name!r} (known: "
                                 f"{''.join(FIELD_TYPES)})")
        if name in names:
            raise UsdFormatError(f"{where}: byte {offset}: field {name!r} appears twice in the header")
        names.append(name)
        codes.append(code)
        offset = end + 1
    if len(raw) < offset + 4:
        raise UsdFormatError(f"{where}: byte {offset}: truncated header (its CRC-32 is cut off)")
    if raw[offset:offset + 4] != _crc(raw[:offset]):
        raise UsdFormatError(f"{where}: byte {offset}: CRC mismatch in the header")
    return names, codes, offset + 4


def read_usd_sync(path: str | os.PathLike) -> UsdLog:
    """Decode a synchronous-mode uSD log (module doc). UsdFormatError, naming the file and the byte
    offset, on a truncated file, a CRC mismatch, an unknown field type or a malformed header."""
    path = Path(path)
    raw = _read_file(path)
    names, codes, offset = _parse_header(raw, str(path))
    dtype = np.dtype([(f"f{i}", FIELD_TYPES[c]) for i, c in enumerate(codes)])  # packed: no padding
    size = dtype.itemsize
    chunks, block = [], 0
    while offset < len(raw):
        count = raw[offset]
        end = offset + 1 + count * size
        if end + 4 > len(raw):
            raise UsdFormatError(f"{path}: byte {offset}: truncated block {block} ({count} records need "
                                 f"{end + 4 - offset} bytes, {len(raw) - offset} are left)")
        if raw[end:end + 4] != _crc(raw[offset:end]):
            raise UsdFormatError(f"{path}: byte {offset}: CRC mismatch in block {block}")
        chunks.append(raw[offset + 1:end])
        offset, block = end + 4, block + 1
    records = np.frombuffer(b"".join(chunks), dtype=dtype)
    fields = {name: records[f"f{i}"].astype(FIELD_TYPES[c][1:]) for i, (name, c) in enumerate(zip(names, codes))}
    source = {"file": str(path), "format": USD_SYNC_FORMAT, "sha256": hashlib.sha256(raw).hexdigest()}
    return UsdLog(fields, dict(zip(names, codes)), source, block)


def encode_usd_sync(columns: Mapping[str, tuple[str, Any]], block_records: int = 4) -> bytes:
    """The bytes of a synchronous-mode log of `columns` (name -> (type code, values (N,))), the
    records in blocks of `block_records` (1-255; the last block holds the rest)."""
    if not columns:
        raise ValueError("columns: at least one field is needed")
    if not 1 <= block_records <= _MAX_BLOCK:
        raise ValueError(f"block_records: allowed 1-{_MAX_BLOCK}, got {block_records}")
    unknown = {n: c for n, (c, _) in columns.items() if c not in FIELD_TYPES}
    if unknown:
        raise ValueError(f"columns: unknown type codes {unknown} (known: {''.join(FIELD_TYPES)})")
    if len(columns) > 255:
        raise ValueError(f"columns: at most 255 fields, got {len(columns)}")
    values = {n: np.asarray(v) for n, (_, v) in columns.items()}
    lengths = {len(v) for v in values.values()}
    if len(lengths) != 1:
        raise ValueError(f"columns: every field needs the same number of values, got {sorted(lengths)}")
    header = bytes([len(columns)]) + b"".join(f"{n}({c}),".encode("ascii") for n, (c, _) in columns.items())
    dtype = np.dtype([(f"f{i}", FIELD_TYPES[c]) for i, (_, (c, _)) in enumerate(columns.items())])
    records = np.zeros(lengths.pop(), dtype=dtype)
    for i, v in enumerate(values.values()):
        records[f"f{i}"] = v
    out = [header, _crc(header)]
    for start in range(0, len(records), block_records):
        chunk = records[start:start + block_records]
        block = bytes([len(chunk)]) + chunk.tobytes()
        out += [block, _crc(block)]
    return b"".join(out)


def write_usd_sync(path: str | os.PathLike, columns: Mapping[str, tuple[str, Any]], block_records: int = 4) -> None:
    """Write `encode_usd_sync(columns, block_records)` to `path` atomically."""
    atomic_write_bytes(path, encode_usd_sync(columns, block_records))


def _read_file(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as e:
        raise UsdFormatError(f"{path}: cannot read it: {e.strerror or e}") from e


def _descriptor(raw: bytes, offset: int, where: str, what: str) -> tuple[str, str, int]:
    """(name, type code, offset after) of a NUL-terminated ``name(t)`` entry of an event header."""
    end = raw.find(b"\0", offset)
    if end < 0:
        raise UsdFormatError(f"{where}: byte {offset}: truncated header ({what} has no end)")
    text = raw[offset:end].decode("ascii", errors="replace")
    if len(text) < 4 or text[-3] != "(" or text[-1] != ")" or not text[:-3].strip():
        raise UsdFormatError(f"{where}: byte {offset}: {what} {text!r} is not 'name(t)'")
    if text[-2] not in FIELD_TYPES:
        raise UsdFormatError(f"{where}: byte {end - 2}: unknown field type {text[-2]!r} of {text[:-3]!r} (known: "
                             f"{''.join(FIELD_TYPES)})")
    return text[:-3], text[-2], end + 1


def read_usd_events(path: str | os.PathLike) -> dict[str, UsdLog]:
    """Decode an event-based uSD log (version 2, module doc): event name -> its records, with the
    ``timestamp`` (us) first and then its values raw; UsdFormatError naming the file and byte offset."""
    path = Path(path)
    raw, where = _read_file(path), str(path)
    if len(raw) < 9:
        raise UsdFormatError(f"{where}: byte 0: truncated file ({len(raw)} bytes; a header and a CRC-32 need 9)")
    if raw[0] != _EVENTS_MAGIC:
        raise UsdFormatError(f"{where}: byte 0: not an event-based uSD log (magic 0x{raw[0]:02X}, expected 0xBC)")
    version, n_types = struct.unpack_from("<HH", raw, 1)
    if version != _EVENTS_VERSION:
        raise UsdFormatError(f"{where}: byte 1: version {version}, this reader reads {_EVENTS_VERSION}")
    if int.from_bytes(raw[-4:], "little") != zlib.crc32(raw[:-4]):
        raise UsdFormatError(f"{where}: byte {len(raw) - 4}: CRC mismatch of the file (or a file cut short)")
    body, offset = raw[:-4], 5
    types: dict[int, tuple[str, list[str], list[str], struct.Struct]] = {}
    for i in range(n_types):
        if offset + 2 > len(body):
            raise UsdFormatError(f"{where}: byte {offset}: truncated header (event type {i + 1} of {n_types})")
        (event_id,) = struct.unpack_from("<H", body, offset)
        end = body.find(b"\0", offset + 2)
        if end < 0 or end + 3 > len(body):
            raise UsdFormatError(f"{where}: byte {offset + 2}: truncated header (event type {i + 1}'s name)")
        name = body[offset + 2:end].decode("ascii", errors="replace")
        (m,) = struct.unpack_from("<H", body, end + 1)
        offset, names, codes = end + 3, [], []
        for j in range(m):
            var, code, offset = _descriptor(body, offset, where, f"variable {j + 1} of event {name!r}")
            names.append(var)
            codes.append(code)
        if event_id in types or name in {t[0] for t in types.values()}:
            raise UsdFormatError(f"{where}: byte {offset}: event {event_id} ({name!r}) declared twice")
        types[event_id] = (name, names, codes, struct.Struct("<Q" + "".join(codes)))
    rows: dict[int, list[tuple]] = {k: [] for k in types}
    while offset < len(body):
        if offset + 2 > len(body):
            raise UsdFormatError(f"{where}: byte {offset}: truncated record (its event id is cut short)")
        (event_id,) = struct.unpack_from("<H", body, offset)
        if event_id not in types:
            raise UsdFormatError(f"{where}: byte {offset}: event id {event_id} is not declared in the header "
                                 f"(declared: {sorted(types)})")
        record = types[event_id][3]
        if offset + 2 + record.size > len(body):
            raise UsdFormatError(f"{where}: byte {offset}: truncated record of event {types[event_id][0]!r} "
                                 f"({record.size + 2} bytes needed, {len(body) - offset} left)")
        rows[event_id].append(record.unpack_from(body, offset + 2))
        offset += 2 + record.size
    source = {"file": where, "format": USD_EVENTS_FORMAT, "sha256": hashlib.sha256(raw).hexdigest()}
    out = {}
    for event_id, (name, names, codes, _) in types.items():
        columns = list(zip(*rows[event_id])) or [()] * (len(names) + 1)
        fields = {"timestamp": np.asarray(columns[0], dtype=np.uint64)}
        fields.update({n: np.asarray(c, dtype=FIELD_TYPES[t][1:]) for n, t, c in zip(names, codes, columns[1:])})
        out[name] = UsdLog(fields, {"timestamp": "Q", **dict(zip(names, codes))}, {**source, "event": name}, 0)
    return out


def encode_usd_events(events: Mapping[str, tuple[int, Mapping[str, str]]],
                      records: list[tuple[str, int, tuple]]) -> bytes:
    """The bytes of an event-based log: events maps a name to (id, {variable: type code}); records are
    (event name, timestamp us, values in the event's variable order), written in the order given."""
    header = bytearray(struct.pack("<BHH", _EVENTS_MAGIC, _EVENTS_VERSION, len(events)))
    layout = {}
    for name, (event_id, variables) in events.items():
        unknown = {v: c for v, c in variables.items() if c not in FIELD_TYPES}
        if unknown:
            raise ValueError(f"events: {name}: unknown type codes {unknown} (known: {''.join(FIELD_TYPES)})")
        header += struct.pack("<H", event_id) + name.encode("ascii") + b"\0" + struct.pack("<H", len(variables))
        header += b"".join(f"{v}({c})".encode("ascii") + b"\0" for v, c in variables.items())
        layout[name] = (event_id, struct.Struct("<Q" + "".join(variables.values())))
    body = bytes(header) + b"".join(struct.pack("<H", layout[n][0]) + layout[n][1].pack(t, *values)
                                    for n, t, values in records)
    return body + zlib.crc32(body).to_bytes(4, "little")


_MAG = (1 << 9) - 1  # a compressed component's magnitude: 9 bits over [0, 1/sqrt(2)]
_XYZW = (1, 2, 3, 0)  # the firmware's component order (x, y, z, w) in this project's (w, x, y, z)


def decompress_quaternions(packed: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z) of the firmware's compressed ones (N,) uint32 (module doc);
    the largest component comes out positive (q and -q are one rotation)."""
    packed = np.asarray(packed, dtype=np.uint64)
    largest = (packed >> 30).astype(np.int64)
    q = np.zeros((packed.size, 4))  # firmware order x, y, z, w
    rest = packed.copy()
    for i in (3, 2, 1, 0):  # the last component written is in the lowest bits
        value = (rest & _MAG).astype(np.float64) / _MAG * math.sqrt(0.5)
        value = np.where((rest >> 9) & 1, -value, value)
        rest = np.where(largest != i, rest >> 10, rest)
        q[:, i] = np.where(largest != i, value, 0.0)
    q[np.arange(packed.size), largest] = np.sqrt(np.maximum(1.0 - np.sum(q**2, axis=1), 0.0))
    return q[:, [3, 0, 1, 2]]


def compress_quaternions(quat: np.ndarray) -> np.ndarray:
    """(N,) uint32: unit quaternions (N, 4) (w, x, y, z) compressed as the firmware logs them."""
    q = np.asarray(quat, dtype=np.float64).reshape(-1, 4)[:, list(_XYZW)]  # to x, y, z, w
    largest = np.argmax(np.abs(q), axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    packed = largest.astype(np.uint64)
    for i in range(4):
        mag = np.floor(_MAG * np.abs(q[:, i]) / math.sqrt(0.5) + 0.5).astype(np.uint64)
        bits = (((q[:, i] < 0) ^ negate).astype(np.uint64) << 9) | mag
        packed = np.where(largest != i, (packed << 10) | bits, packed)
    return packed.astype(np.uint32)
