"""Readers of real onboard logs, tested on files this project's own writers make (no data set needed).

The uSD deck's synchronous format: a round trip of every field type and block size, the CRC
convention checked by hand (zlib over the bytes and the stored value gives 0xFFFFFFFF), and any
byte flipped or any cut of a file refused with the file and a byte offset named, never a crash
or a partial read.
"""

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import LogError
from downwash.real_logs.crazyflie_usd import (FIELD_TYPES, USD_SYNC_FORMAT, UsdFormatError, encode_usd_sync,
                                              read_usd_sync, write_usd_sync)


def _columns(n: int = 37, seed: int = 0) -> dict:
    """Every field type the format knows, with values across each type's range."""
    rng = np.random.default_rng(seed)
    cols = {}
    for code, np_type in FIELD_TYPES.items():
        dt = np.dtype(np_type)
        if dt.kind in "iu":
            info = np.iinfo(dt)
            values = rng.integers(info.min, info.max, size=n, dtype=dt, endpoint=True)
        else:
            values = rng.normal(scale=1e3, size=n).astype(dt)
        cols[f"group.v_{code}"] = (code, values)
    return cols


@pytest.mark.parametrize("block_records", [1, 3, 4, 255])
def test_a_written_log_reads_back_bit_for_bit(tmp_path, block_records):
    cols = _columns()
    path = tmp_path / "cf1_00"
    write_usd_sync(path, cols, block_records)
    log = read_usd_sync(path)
    assert list(log.fields) == list(cols) and log.types == {n: c for n, (c, _) in cols.items()}
    assert len(log) == 37 and log.blocks == -(-37 // block_records)
    for name, (code, values) in cols.items():
        assert log.fields[name].dtype == np.dtype(FIELD_TYPES[code]).newbyteorder("=")
        np.testing.assert_array_equal(log.fields[name], values)
    assert log.source["format"] == USD_SYNC_FORMAT and log.source["file"] == str(path)
    assert len(log.source["sha256"]) == 64


def test_the_layout_and_crc_convention_by_hand():
    """One uint32 and one int16 field, two records in one block: every byte where the format says."""
    raw = encode_usd_sync({"tick": ("I", [1000, 11000]), "z": ("h", [-5, 900])}, block_records=4)
    header = b"\x02tick(I),z(h),"
    assert raw.startswith(header)
    assert zlib.crc32(raw[:len(header) + 4]) == 0xFFFFFFFF
    block = raw[len(header) + 4:]
    assert block[0] == 2 and struct.unpack("<IhIh", block[1:13]) == (1000, -5, 11000, 900)
    assert zlib.crc32(block) == 0xFFFFFFFF and len(block) == 1 + 12 + 4


def test_an_empty_log_has_no_records(tmp_path):
    write_usd_sync(tmp_path / "e", {"tick": ("I", [])})
    log = read_usd_sync(tmp_path / "e")
    assert len(log) == 0 and log.blocks == 0 and log.fields["tick"].dtype == np.uint32


@pytest.mark.parametrize("raw,message", [
    (b"", "empty file"),
    (b"\x00", "byte 0: the header declares 0 fields"),
    (b"\x02tick(I),z(h)", r"byte 9: truncated header \(field 2 of 2 has no ','\)"),
    (b"\x01tick(I),\x00\x00", r"byte 9: truncated header \(its CRC-32 is cut off\)"),
    (b"\x01tick(I),\x00\x00\x00\x00", "byte 9: CRC mismatch in the header"),
    (b"\x01tick(Z),", r"byte 6: unknown field type 'Z' of 'tick'"),
    (b"\x01tick,", r"byte 1: header field 'tick' is not 'name\(t\)'"),
    (b"\x02a(I),a(h),", r"byte 6: field 'a' appears twice"),
    (b"\x01\xfftick(I),", "byte 1: field 1 of the header is not ASCII"),
])  # fmt: skip
def test_malformed_headers_are_named(tmp_path, raw, message):
    path = tmp_path / "bad"
    path.write_bytes(raw)
    with pytest.raises(UsdFormatError, match=rf"^{path}: {message}"):
        read_usd_sync(path)


def test_block_errors_name_the_block_and_its_offset(tmp_path):
    raw = bytearray(encode_usd_sync({"tick": ("I", np.arange(10)), "z": ("h", np.arange(10))}, block_records=4))
    first = len(b"\x02tick(I),z(h),") + 4  # blocks of 1 + 4 * 6 + 4 = 29 bytes
    path = tmp_path / "cf"
    bad = raw.copy()
    bad[first + 29 + 5] ^= 0x01  # a value in block 1
    path.write_bytes(bytes(bad))
    with pytest.raises(UsdFormatError, match=rf"^{path}: byte {first + 29}: CRC mismatch in block 1$"):
        read_usd_sync(path)
    path.write_bytes(bytes(raw[:-3]))  # the last block's CRC cut
    with pytest.raises(UsdFormatError, match=rf"byte {first + 58}: truncated block 2 \(2 records need 17 bytes, 14 are left\)"):
        read_usd_sync(path)
    with pytest.raises(LogError, match="cannot read it"):  # a named error of the log family, not an OSError
        read_usd_sync(tmp_path / "missing")


@settings(max_examples=200, deadline=None)
@given(at=st.floats(0.0, 1.0), bits=st.integers(1, 255), cut=st.booleans())
def test_a_flipped_byte_or_a_cut_is_refused_never_read_in_part(tmp_path_factory, at, bits, cut):
    """Every byte is covered by a CRC (the header's or a block's), so any change is refused with a
    byte offset, as is any cut that is not at a block boundary; a cut at a boundary is a shorter
    log of whole blocks, every value as written."""
    cols = _columns(n=40, seed=1)
    raw = encode_usd_sync(cols, block_records=7)
    i = int(at * (len(raw) - 1))
    if cut:
        data = raw[:i]
    else:
        data = bytearray(raw)
        data[i] ^= bits
        data = bytes(data)
    path = tmp_path_factory.mktemp("flip") / "cf"
    path.write_bytes(data)
    try:
        log = read_usd_sync(path)
    except UsdFormatError as e:
        assert str(e).startswith(f"{path}: ") and ("byte " in str(e) or "empty file" in str(e))
        return
    assert cut, "a changed byte was read"
    n = len(log)
    assert n % 7 == 0 and n < 40  # whole blocks only
    for name, (_, values) in cols.items():
        np.testing.assert_array_equal(log.fields[name], values[:n])


def test_writer_arguments_are_checked():
    with pytest.raises(ValueError, match="unknown type codes"):
        encode_usd_sync({"a": ("Z", [1])})
    with pytest.raises(ValueError, match="block_records: allowed 1-255"):
        encode_usd_sync({"a": ("I", [1])}, block_records=0)
    with pytest.raises(ValueError, match="the same number of values"):
        encode_usd_sync({"a": ("I", [1]), "b": ("I", [1, 2])})
