"""The documented tabular layout as a Parquet file: the same flight as its CSV, the same checks,
and a damaged file refused with the file named.

A round trip (write, read) equals the CSV's read of the same flight array for array; a column in
another unit, a missing column, a column of text where numbers go, a time that does not increase,
a changed mass, a null or non-finite value are named with the row and column; any cut of the file
and any flipped byte in it is a `TabularFormatError` (pyarrow's own errors wrapped, its pages'
CRC-32s verified) or reads exactly what was written.
"""

import hashlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY
from downwash.labels import labels_from_log
from downwash.real_logs.tabular import (CSV_LAYOUT, PARQUET_LAYOUT, TabularFormatError, read_csv_flight,
                                        read_parquet_flight, read_tabular_flight, write_csv_flight,
                                        write_parquet_flight)

pa = pytest.importorskip("pyarrow")  # the logs extra
import pyarrow.parquet as pq  # noqa: E402


def _vehicle(t, z, force, mass=0.05, kind=None, yaw=0.3):
    """A vehicle hovering at (0.2, 0.1, z) with heading `yaw` while `force` (m/s^2, vertical) acts on it."""
    cols = {"t": t, "x": 0.2, "y": 0.1, "z": z, "vx": 0.0, "vy": 0.0, "vz": 0.0,
            "qw": np.cos(yaw / 2), "qx": 0.0, "qy": 0.0, "qz": np.sin(yaw / 2),
            "ref_x": 0.2, "ref_y": 0.1, "ref_z": z, "ref_vx": 0.0, "ref_vy": 0.0, "ref_vz": 0.0,
            "thrust": np.full(len(t), mass * (GRAVITY - force)), "mass": mass}
    return {**cols, **({"kind": kind} if kind else {})}


def _flight():
    ta, tb = np.arange(0.0, 8.0, 1 / 120), np.arange(0.1, 7.0, 1 / 90)
    rng = np.random.default_rng(3)
    return {"top": _vehicle(ta, 1.2 + 0.01 * rng.normal(size=ta.size), 0.0, kind="crazyflie_2_1"),
            "low": _vehicle(tb, 0.7, -0.6, mass=0.07)}


def test_a_parquet_flight_equals_its_csv(tmp_path):
    flight = _flight()
    write_csv_flight(tmp_path / "f.csv", flight)
    write_parquet_flight(tmp_path / "f.parquet", flight)
    a, b = read_csv_flight(tmp_path / "f.csv"), read_parquet_flight(tmp_path / "f.parquet")
    assert set(a.arrays) == set(b.arrays)
    for name in a.arrays:
        np.testing.assert_array_equal(b[name], a[name], err_msg=name)
    assert {k: v for k, v in a.meta.items() if k != "source"} == {k: v for k, v in b.meta.items() if k != "source"}
    assert b.meta["vehicles"] == ["top", "low"] and "kinds" not in b.meta and b.meta["masses"] == [0.05, 0.07]
    src = b.meta["source"]
    assert src["format"] == PARQUET_LAYOUT and a.meta["source"]["format"] == CSV_LAYOUT
    assert src["files"][0]["sha256"] == hashlib.sha256((tmp_path / "f.parquet").read_bytes()).hexdigest()
    lab = labels_from_log(b, targets="all")
    low = lab["vehicle"] == 1
    np.testing.assert_allclose(lab["y"][low], [[0.0, 0.0, -0.6]] * int(low.sum()), atol=1e-9)
    for suffix, reader in ((".csv", a), (".parquet", b)):
        np.testing.assert_array_equal(read_tabular_flight(tmp_path / f"f{suffix}")["u_cmd"], reader["u_cmd"])


def test_the_file_is_the_documented_layout(tmp_path):
    write_parquet_flight(tmp_path / "f.pq", {"a": _vehicle(np.arange(0.0, 1.0, 0.01), 1.0, 0.0, kind="x500")})
    table = pq.read_table(tmp_path / "f.pq")
    assert table.column_names[:3] == ["t[s]", "vehicle", "x[m]"] and "thrust[N]" in table.column_names
    assert table.column("vehicle").to_pylist()[0] == "a" and table.column("kind").to_pylist()[0] == "x500"
    assert pa.types.is_float64(table.column("t[s]").type)
    assert read_tabular_flight(tmp_path / "f.pq").meta["kinds"] == ["x500"]


def _rewrite(path, edit):
    """The file with its table edited (a pyarrow Table -> Table), written back as plain Parquet."""
    pq.write_table(edit(pq.read_table(path)), path)


def _set(table, name, values):
    return table.set_column(table.column_names.index(name), name, values)


@pytest.mark.parametrize("edit,message", [
    (lambda t: t.rename_columns([c.replace("x[m]", "x[mm]") for c in t.column_names]),
     r"schema: unit mismatch: column 'x\[mm\]' is in mm; this layout takes x\[m\]"),
    (lambda t: t.drop_columns(["thrust[N]"]), r"schema: no column thrust\[N\]"),
    (lambda t: t.drop_columns(["vehicle"]), r"schema: no column vehicle"),
    (lambda t: _set(t, "x[m]", pa.array(["0.2"] * len(t))), r"schema: column 'x\[m\]' holds string; this layout "
                                                            r"takes numbers"),
    (lambda t: _set(t, "vehicle", pa.array(np.zeros(len(t)))), r"schema: column 'vehicle' holds double; this "
                                                               r"layout takes text"),
    (lambda t: _set(t, "x[m]", pa.array([0.2, None] + [0.2] * (len(t) - 2))), r"row 1: column 'x\[m\]': no value "
                                                                                r"\(null\)"),
    (lambda t: _set(t, "z[m]", pa.array([1.0] * 5 + [np.inf] + [1.0] * (len(t) - 6))), r"row 5: column 'z\[m\]': not "
                                                                                        r"a finite number: inf"),
    (lambda t: _set(t, "t[s]", pa.array(np.r_[0.0, 0.02, 0.01, np.arange(3, len(t)) / 100])),
     r"row 2: vehicle 'a': time 0.01 s does not increase \(the last was 0.02 s\)"),
    (lambda t: _set(t, "mass[kg]", pa.array([0.05] * 7 + [0.09] * (len(t) - 7))),
     r"row 7: vehicle 'a' changes its mass or kind \(\(0.05, None\) before, \(0.09, None\) here\)"),
    (lambda t: _set(t, "kind", pa.array(["blimp"] * len(t))), r"vehicle 'a': unknown kind 'blimp'"),
])  # fmt: skip
def test_a_parquet_flight_that_is_not_the_layout_is_named(tmp_path, edit, message):
    path = tmp_path / "f.parquet"
    write_parquet_flight(path, {"a": _vehicle(np.arange(0.0, 1.0, 0.01), 1.0, 0.0)})
    _rewrite(path, edit)
    with pytest.raises(TabularFormatError, match=rf"^{path}: {message}"):
        read_parquet_flight(path)


def test_arguments_and_suffixes_are_checked(tmp_path):
    with pytest.raises(ConfigError, match=r"f.txt: suffix '.txt': allowed .csv, .parquet, .pq"):
        read_tabular_flight(tmp_path / "f.txt")
    with pytest.raises(ConfigError, match=r"rate_hz: allowed 10-500 Hz, got 5"):
        read_parquet_flight(tmp_path / "f.parquet", rate_hz=5)
    with pytest.raises(TabularFormatError, match=r"missing.parquet: cannot read it"):
        read_parquet_flight(tmp_path / "missing.parquet")


def test_without_pyarrow_the_install_hint_is_given(tmp_path, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "pyarrow.parquet", None)
    with pytest.raises(ConfigError, match=r'Parquet flights need pyarrow .*pip install "downwash-testbed\[logs\]"'):
        read_parquet_flight(tmp_path / "f.parquet")


class _Written:
    """A small flight's Parquet bytes and its read (a short repr for hypothesis' reports)."""

    def __init__(self, folder):
        path = folder / "f.parquet"
        t = np.arange(0.0, 0.5, 0.01)
        write_parquet_flight(path, {"a": _vehicle(t, 1.0 + 0.1 * t, 0.0), "b": _vehicle(t + 0.005, 0.5, -0.2)})
        self.raw, self.flight = path.read_bytes(), read_parquet_flight(path)

    def __repr__(self):
        return f"<{len(self.raw)} bytes of Parquet>"


@pytest.fixture(scope="module")
def small_file(tmp_path_factory):
    return _Written(tmp_path_factory.mktemp("pq"))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(at=st.floats(0.0, 1.0), bits=st.integers(1, 255), cut=st.booleans())
def test_a_flipped_byte_or_a_cut_is_refused_or_changes_nothing(tmp_path_factory, small_file, at, bits, cut):
    """Every page carries a CRC-32 (verified), and a damaged footer does not parse or names no column of
    the layout: flipping each byte of this file in turn (one bit pattern each, pyarrow 26) found every
    flip refused or harmless."""
    raw, flight = small_file.raw, small_file.flight
    i = int(at * (len(raw) - 1))
    data = raw[:i] if cut else raw[:i] + bytes([raw[i] ^ bits]) + raw[i + 1:]
    path = tmp_path_factory.mktemp("bad") / "f.parquet"
    path.write_bytes(data)
    try:
        log = read_parquet_flight(path)
    except TabularFormatError as e:
        assert str(e).startswith(f"{path}: ")
        return
    assert not cut, "a cut file was read"
    for name in flight.arrays:
        np.testing.assert_array_equal(log[name], flight[name], err_msg=f"byte {i} flipped: {name} changed")
