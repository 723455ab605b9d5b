"""Readers of real onboard logs, tested on files this project's own writers make (no data set needed).

The uSD deck's synchronous format: a round trip of every field type and block size, the CRC
convention checked by hand (zlib over the bytes and the stored value gives 0xFFFFFFFF), and any
byte flipped or any cut of a file refused with the file and a byte offset named, never a crash
or a partial read. The compressed quaternions, by hand and over random rotations. The
Neural-Swarm layout: files written as the firmware logs them give flight logs in SI units whose
labels are an analytic force (a known thrust map and a known motion), save and load without
truth, are grouped into flights and aligned at their first ticks, and name what is wrong.
"""

import math
import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError, LogError
from downwash_core.params import GRAVITY
from downwash.features import kind_descriptors
from downwash.labels import label_noise_floor, labels_from_log, log_kinds, second_derivative_coeffs
from downwash.real_logs.crazyflie_usd import (FIELD_TYPES, USD_EVENTS_FORMAT, USD_SYNC_FORMAT, UsdFormatError,
                                              compress_quaternions, decompress_quaternions, encode_usd_events,
                                              encode_usd_sync, read_usd_events, read_usd_sync, write_usd_sync)
from downwash.real_logs.neural_swarm import NEURAL_SWARM_VEHICLES, flight_files, motor_lag, read_flight, setpoint_offset
from downwash.real_logs.tabular import CSV_LAYOUT, TabularFormatError, read_csv_flight, write_csv_flight
from sim.logs import TRUTH_ARRAYS, FlightLog, load_log, save_log


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


# ----------------------------------------------------------------------------- compressed quaternions


def test_quaternions_survive_compression_to_the_formats_resolution():
    """9 bits over [0, 1/sqrt(2)] per small component: each within half a step (plus what the largest
    one, rebuilt from the unit norm, inherits), the largest made positive (q and -q are one rotation)."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=(20_000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    packed = compress_quaternions(q)
    back = decompress_quaternions(packed)
    assert np.allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)
    same = q * np.sign(np.sum(back * q, axis=1))[:, None]
    assert np.abs(back - same).max() < 2e-3 and np.median(np.abs(back - same)) < 7e-4
    largest = ((packed >> 30).astype(int) + 1) % 4  # the firmware's x, y, z, w index in (w, x, y, z)
    assert np.all(back[np.arange(len(back)), largest] > 0) and np.all(np.argmax(np.abs(q), axis=1) == largest)


def test_compressed_quaternion_layout_by_hand():
    """The identity is w largest (firmware index 3, x y z w order) and three zero components."""
    assert compress_quaternions(np.array([[1.0, 0, 0, 0]]))[0] == 3 << 30
    assert np.array_equal(decompress_quaternions(np.array([3 << 30], np.uint32)), [[1.0, 0, 0, 0]])
    # x largest (index 0), then y = -1/sqrt(2) exactly: sign bit and full magnitude in the first slot
    packed = (0 << 30) | ((1 << 9 | 511) << 20)
    q = decompress_quaternions(np.array([packed], np.uint32))[0]
    np.testing.assert_allclose(q, [0.0, math.sqrt(0.5), -math.sqrt(0.5), 0.0], atol=1e-15)


# ----------------------------------------------------------------------------- the data set's layout


MASS = NEURAL_SWARM_VEHICLES["small"].mass
MAP = NEURAL_SWARM_VEHICLES["small"].thrust_map


def _pwm_for(grams: np.ndarray, vbat: np.ndarray, frame: str = "small") -> np.ndarray:
    """The PWM (0-65535) at which one rotor of a frame gives `grams` at battery `vbat` V."""
    m, v = NEURAL_SWARM_VEHICLES[frame].thrust_map, vbat / 4.2
    a, b, c = m.c20, m.c10 + m.c11 * v, m.c00 + m.c01 * v - grams
    return (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a) * 65536


def _neural_swarm_columns(t: np.ndarray, z: np.ndarray, thrust: np.ndarray, vbat: np.ndarray,
                          tick0: int = 123_456, frame: str = "small") -> dict:
    """A level vehicle of a frame at (0.1, -0.2, z) m with total thrust `thrust` N, as the firmware logs it."""
    n = len(t)
    pwm = np.round(_pwm_for(thrust / 4 / GRAVITY * 1e3, vbat, frame)).astype(np.uint32)
    cols = {"tick": ("I", (tick0 + np.round(t * 1e6)).astype(np.int64) % 2**32)}
    for axis, value in zip("xyz", (np.full(n, 100), np.full(n, -200), np.round(z * 1e3))):
        cols[f"stateEstimateZ.{axis}"] = ("h", value)
    for axis in ("vx", "vy", "vz"):
        cols[f"stateEstimateZ.{axis}"] = ("h", np.zeros(n))
    cols["stateEstimateZ.quat"] = ("I", compress_quaternions(np.tile([1.0, 0, 0, 0], (n, 1))))
    for axis in ("x", "y", "z"):  # the setpoint: where it is
        cols[f"ctrltargetZ.{axis}"] = cols[f"stateEstimateZ.{axis}"]
    for axis in ("vx", "vy", "vz"):
        cols[f"ctrltargetZ.{axis}"] = ("h", np.zeros(n))
    for i in range(1, 5):
        cols[f"pwm.m{i}_pwm"] = ("I", pwm)
    cols["pm.vbatMV"] = ("H", np.round(vbat * 1e3))
    return cols


def test_labels_of_a_known_thrust_and_motion_are_the_known_force(tmp_path):
    """Analytic: a vehicle moving z = 1 + 0.2 sin(2 pi 0.3 t) whose rotors give T = m (g + z'' - f) at a
    falling battery voltage (PWM from the thrust map's inverse, rounded as logged) feels f = (0, 0, -0.8)
    m/s^2; the labels find it through the int16 mm positions, the PWM and the clock's wrap."""
    rate, f_z = 101.3, -0.8  # the data set's logs run at about 101 Hz
    t = np.arange(int(40 * rate)) / rate
    w = 2 * np.pi * 0.3
    z, zdd = 1.0 + 0.2 * np.sin(w * t), -0.2 * w**2 * np.sin(w * t)
    vbat = np.linspace(4.0, 3.6, t.size)
    thrust = MASS * (GRAVITY + zdd - f_z)
    path = tmp_path / "cf50_07"
    write_usd_sync(path, _neural_swarm_columns(t, z, thrust, vbat, tick0=2**32 - 5_000_000), block_records=3)
    log = read_flight([path])
    assert log.real and log.n_vehicles == 1 and log.meta["frames"] == ["small"] and log.meta["vehicles"] == ["cf50"]
    assert log.meta["source"]["files"][0]["file"] == str(path)
    np.testing.assert_allclose(np.diff(log["t"]), 0.01, atol=1e-12)  # resampled onto 100 Hz from the start
    np.testing.assert_allclose(log["pos_est"][:, 0, :2], [[0.1, -0.2]] * len(log), atol=1e-12)
    lab = labels_from_log(log, targets="all")
    assert len(lab["y"]) > 3500 and np.isnan(lab["field_mean"]).all()
    assert log_kinds(log) == ["crazyflie_2_1"]  # the registered kind of the small frame, its thrust map's
    np.testing.assert_array_equal(lab["kind_b"], np.broadcast_to(kind_descriptors(["crazyflie_2_1"])[0], lab["kind_b"].shape))
    del log.meta["kinds"]  # a lab's log that names no registered kind: no kind inputs, and models of kinds refuse it
    assert np.isnan(labels_from_log(log, targets="all")["kind_b"]).all()
    with pytest.raises(ConfigError, match=r"names no registered vehicle kinds .*its frames: \['small'\]"):
        log_kinds(log)
    np.testing.assert_allclose(lab["y"][:, :2], 0.0, atol=1e-9)
    err = lab["y"][:, 2] - f_z
    # the floor of 1 mm position steps (uniform, sd 1 mm / sqrt 12) through the filter: sd |c| / dt^2
    floor = 1e-3 / math.sqrt(12) * np.linalg.norm(second_derivative_coeffs()) / 0.01**2
    assert abs(err.mean()) < 0.01 and np.sqrt(np.mean(err**2)) < 1.2 * floor


def test_a_real_flight_saves_and_loads_without_truth(tmp_path):
    t = np.arange(300) / 100.0
    path = tmp_path / "cf101_03"
    write_usd_sync(path, _neural_swarm_columns(t, np.full(t.size, 0.5), np.full(t.size, 0.3), np.full(t.size, 3.9)))
    flight = read_flight([path])
    save_log(tmp_path / "f.npz", flight)
    back = load_log(tmp_path / "f.npz")
    assert back.real and not set(TRUTH_ARRAYS) & set(back.arrays) and back.meta["frames"] == ["large"]
    for name, value in flight.arrays.items():
        np.testing.assert_array_equal(back[name], value)
    with pytest.raises(LogError, match="holds simulator truth arrays"):
        save_log(tmp_path / "g.npz", FlightLog({**flight.arrays, "pos": flight["pos_est"]}, flight.meta))
    with pytest.raises(ConfigError, match="is a real flight: it has no true field"):
        label_noise_floor([back])


def test_the_data_sets_errors_are_named(tmp_path):
    t = np.arange(300) / 100.0
    cols = _neural_swarm_columns(t, np.full(t.size, 0.5), np.full(t.size, 0.3), np.full(t.size, 3.9))
    write_usd_sync(tmp_path / "cf7_00", cols)
    with pytest.raises(ConfigError, match=r"cf7_00: not a vehicle of the data set \(known: cf50 \(small\)"):
        read_flight([tmp_path / "cf7_00"])
    ms = dict(cols, tick=("I", np.round(t * 1e3)))  # a tick in ms, as the data set's CSV headers say
    write_usd_sync(tmp_path / "cf50_00", ms)
    with pytest.raises(UsdFormatError, match=r"cf50_00: unit mismatch: 'tick' steps by 10 per record; expected "
                                             "microseconds"):
        read_flight([tmp_path / "cf50_00"])
    write_usd_sync(tmp_path / "cf51_00", {k: v for k, v in cols.items() if k != "pm.vbatMV"})
    with pytest.raises(UsdFormatError, match=r"cf51_00: not a Neural-Swarm onboard log: no \['pm.vbatMV'\]"):
        read_flight([tmp_path / "cf51_00"])


def test_flights_are_grouped_by_number_and_aligned_at_their_first_tick(tmp_path):
    """Two vehicles whose clocks differ (their first ticks 3 s apart) and whose setpoints start moving at
    the same moment after it: one flight, aligned, the setpoints' residual offset 0 (and 0.2 s when one
    log starts 0.2 s late)."""
    t = np.arange(1000) / 100.0
    for ident, tick0, late in ((50, 1_000_000, 0.0), (101, 4_000_000, 0.0), (51, 9_000_000, 0.2)):
        cols = _neural_swarm_columns(t, np.full(t.size, 0.5), np.full(t.size, 0.4), np.full(t.size, 3.9), tick0)
        cols["ctrltargetZ.vx"] = ("h", np.where((t + late > 4) & (t + late < 6), 300, 0))
        folder = tmp_path / ("one" if ident != 51 else "two")
        folder.mkdir(exist_ok=True)
        write_usd_sync(folder / f"cf{ident}_04", cols)
    (tmp_path / "one" / "cf50_04.csv").write_text("not a log")
    flights = flight_files(tmp_path / "one")
    assert list(flights) == ["04"] and [p.name for p in flights["04"]] == ["cf50_04", "cf101_04"]
    log = read_flight(flights["04"])
    assert log.meta["frames"] == ["small", "large"] and setpoint_offset(log, 0, 1) == 0.0
    late = read_flight([tmp_path / "one" / "cf50_04", tmp_path / "two" / "cf51_04"])
    assert setpoint_offset(late, 0, 1) == pytest.approx(-0.2)


def test_the_motor_lag_is_a_first_order_response(tmp_path):
    """A thrust step through the lag: 1 - exp(-t / tau) of it at time t (exact at the samples), and
    nothing changes without a time constant."""
    dt, tau = 0.01, 0.057
    step = np.r_[np.zeros(5), np.ones(100)]
    lagged = motor_lag(step, dt, tau)
    t = (np.arange(100) - 1) * dt  # the step is held from sample 5 and acts from sample 6
    np.testing.assert_allclose(lagged[6:], 1.0 - np.exp(-(t[1:] + dt) / tau), atol=1e-12)
    assert np.array_equal(lagged[:6], np.zeros(6)) and motor_lag(step, dt, None) is step
    times = np.arange(300) / 100.0
    cols = _neural_swarm_columns(times, np.full(300, 0.5), np.r_[np.full(150, 0.3), np.full(150, 0.4)],
                                 np.full(300, 3.9))
    path = tmp_path / "cf50_00"
    write_usd_sync(path, cols)
    fast, slow = read_flight([path]), read_flight([path], motor_time_constant=tau)
    assert slow.meta["config"]["motor_time_constant"] == tau
    jump = np.flatnonzero(np.diff(fast["u_cmd"][:, 0, 2]) > 1.0)[0] + 1
    np.testing.assert_allclose(slow["u_cmd"][:jump], fast["u_cmd"][:jump], atol=1e-9)
    assert fast["u_cmd"][jump, 0, 2] - slow["u_cmd"][jump, 0, 2] > 2.0  # the lag holds it back
    np.testing.assert_allclose(slow["u_cmd"][-1], fast["u_cmd"][-1], atol=1e-6)
    with pytest.raises(ConfigError, match=r"motor_time_constant: allowed \(0, 1\] s or None"):
        read_flight([path], motor_time_constant=0.0)


# ----------------------------------------------------------------------------- the documented CSV layout


def _csv_vehicle(t, z, force, mass=0.05, kind=None, yaw=0.3):
    """A vehicle hovering at (0.2, 0.1, z) with heading `yaw` while `force` (m/s^2, vertical) acts on it."""
    n = len(t)
    cols = {"t": t, "x": 0.2, "y": 0.1, "z": z, "vx": 0.0, "vy": 0.0, "vz": 0.0,
            "qw": np.cos(yaw / 2), "qx": 0.0, "qy": 0.0, "qz": np.sin(yaw / 2),
            "ref_x": 0.2, "ref_y": 0.1, "ref_z": z, "ref_vx": 0.0, "ref_vy": 0.0, "ref_vz": 0.0,
            "thrust": np.full(n, mass * (GRAVITY - force)), "mass": mass}
    return {**cols, **({"kind": kind} if kind else {})}


def test_a_csv_flight_reads_back_and_labels_the_known_force(tmp_path):
    """Two vehicles on one clock, sampled at other rates and times (120 Hz and 90 Hz, starting 0.1 s
    apart): one grid from the later start, the heading and u from the thrust, and the labels the force."""
    ta, tb = np.arange(0.0, 20.0, 1 / 120), np.arange(0.1, 19.0, 1 / 90)
    path = tmp_path / "flight.csv"
    write_csv_flight(path, {"top": _csv_vehicle(ta, 1.2, 0.0, kind="crazyflie_2_1"),
                            "low": _csv_vehicle(tb, 0.7, -0.6, mass=0.07, kind="crazyflie_2_1")})
    log = read_csv_flight(path)
    assert log.real and log.meta["vehicles"] == ["top", "low"] and log.meta["kinds"] == ["crazyflie_2_1"] * 2
    assert log.meta["source"]["files"][0]["format"] == CSV_LAYOUT and log.meta["config"]["start_s"] == 0.1
    end = math.floor((min(ta[-1], tb[-1]) - 0.1) * 100 + 1e-9) / 100  # the earlier last sample, from the later start
    assert log["t"][0] == 0.0 and log["t"][-1] == pytest.approx(end) and np.allclose(np.diff(log["t"]), 0.01)
    np.testing.assert_allclose(log["yaw_est"], 0.3, atol=1e-12)
    np.testing.assert_allclose(log["u_cmd"][:, 1], [[0.0, 0.0, 0.6]] * len(log), atol=1e-12)  # T/m - g = -f
    lab = labels_from_log(log, targets="all")
    np.testing.assert_allclose(lab["y"][lab["vehicle"] == 1], [[0.0, 0.0, -0.6]] * int(np.sum(lab["vehicle"] == 1)),
                               atol=1e-9)
    assert np.isfinite(lab["kind_b"]).all() and log_kinds(log) == ["crazyflie_2_1"] * 2


@pytest.mark.parametrize("edit,message", [
    (lambda h, r: (h.replace("x[m]", "x[mm]"), r), r"line 1: unit mismatch: column 'x\[mm\]' is in mm; this layout takes x\[m\]"),
    (lambda h, r: (h.replace(",thrust[N]", ",push[N]"), r), r"line 1: no column thrust\[N\]"),
    (lambda h, r: (h, [r[0].replace("0.2,", "abc,", 1), *r[1:]]), r"line 2: column 'x\[m\]': not a finite number: 'abc'"),
    (lambda h, r: (h, [r[0].replace("0.2,", "nan,", 1), *r[1:]]), r"line 2: column 'x\[m\]': not a finite number"),
    (lambda h, r: (h, [r[1], r[0], *r[2:]]), r"line 3: vehicle 'a': time 0 s does not increase \(the last was 0.01 s\)"),
    (lambda h, r: (h, [r[0].rsplit(",", 2)[0] + ",0.09,", *r[1:]]), r"line 3: vehicle 'a' changes its mass or kind \(\(0.09, None\) before"),
    (lambda h, r: (h, [",".join(r[0].split(",")[:5]), *r[1:]]), r"line 2: 5 values, the header has"),
])  # fmt: skip
def test_a_csv_flight_that_is_not_the_layout_is_named(tmp_path, edit, message):
    path = tmp_path / "f.csv"
    write_csv_flight(path, {"a": _csv_vehicle(np.arange(0.0, 1.0, 0.01), 1.0, 0.0)})
    header, *rows = path.read_text().splitlines()
    header, rows = edit(header, rows)
    path.write_text("\n".join([header, *rows]) + "\n")
    with pytest.raises(TabularFormatError, match=rf"^{path}: {message}"):
        read_csv_flight(path)


def test_a_csv_flight_with_an_unknown_kind_or_no_overlap_is_named(tmp_path):
    write_csv_flight(tmp_path / "k.csv", {"a": _csv_vehicle(np.arange(0.0, 1.0, 0.01), 1.0, 0.0, kind="blimp")})
    with pytest.raises(TabularFormatError, match=r"vehicle 'a': unknown kind 'blimp' \(registered: paper_quad"):
        read_csv_flight(tmp_path / "k.csv")
    write_csv_flight(tmp_path / "o.csv", {"a": _csv_vehicle(np.arange(0.0, 1.0, 0.01), 1.0, 0.0),
                                          "b": _csv_vehicle(np.arange(2.0, 3.0, 0.01), 1.0, 0.0)})
    with pytest.raises(TabularFormatError, match="do not overlap in time"):
        read_csv_flight(tmp_path / "o.csv")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe")
    with pytest.raises(TabularFormatError, match=r"bin.csv: byte 0: not UTF-8 text"):
        read_csv_flight(tmp_path / "bin.csv")


# ----------------------------------------------------------------------------- the event-based format (v2)

EVENTS = {"fixedFrequency": (0xFFFF, {"stateEstimate.x": "f", "stateEstimate.z": "f", "pm.vbatMV": "H"}),
          "estTDOA": (7, {"idA": "B", "idB": "B", "distanceDiff": "e", "motor.m1": "I"})}


def _event_records(n: int = 50) -> list:
    rng = np.random.default_rng(4)
    out = []
    for k in range(n):
        out.append(("fixedFrequency", 1_000_000 + 10_000 * k, (float(np.float32(rng.normal())),
                                                               float(np.float32(0.5 + k / 100)), 3700 - k)))
        if k % 3 == 0:
            out.append(("estTDOA", 1_000_000 + 10_000 * k + 17, (k % 8, (k + 1) % 8, float(np.float16(0.25 * k)),
                                                                 60_000 + k)))
    return out


def test_an_event_log_reads_back_exactly(tmp_path):
    path = tmp_path / "log00"
    records = _event_records()
    path.write_bytes(encode_usd_events(EVENTS, records))
    events = read_usd_events(path)
    assert list(events) == ["fixedFrequency", "estTDOA"]
    ff, tdoa = events["fixedFrequency"], events["estTDOA"]
    assert list(ff.fields) == ["timestamp", "stateEstimate.x", "stateEstimate.z", "pm.vbatMV"] and len(ff) == 50
    assert ff.fields["timestamp"].dtype == np.uint64 and ff.fields["pm.vbatMV"].dtype == np.uint16
    assert ff.source["format"] == USD_EVENTS_FORMAT and ff.source["event"] == "fixedFrequency"
    mine = [r for r in records if r[0] == "estTDOA"]
    np.testing.assert_array_equal(tdoa.fields["timestamp"], [r[1] for r in mine])
    np.testing.assert_array_equal(tdoa.fields["distanceDiff"], np.array([r[2][2] for r in mine], np.float16))
    np.testing.assert_array_equal(ff.fields["stateEstimate.z"], np.array([r[2][1] for r in records
                                                                          if r[0] == "fixedFrequency"], np.float32))


def test_the_event_layout_by_hand():
    raw = encode_usd_events({"fixedFrequency": (0xFFFF, {"a.b": "h"})}, [("fixedFrequency", 5, (-2,))])
    assert raw[:5] == bytes([0xBC, 2, 0, 1, 0])  # magic, version 2, one event type
    assert raw[5:7] == b"\xff\xff" and raw[7:22] == b"fixedFrequency\0" and raw[22:24] == b"\x01\x00"
    assert raw[24:31] == b"a.b(h)\0"
    assert raw[31:43] == struct.pack("<HQh", 0xFFFF, 5, -2)
    assert raw[43:] == zlib.crc32(raw[:43]).to_bytes(4, "little") and len(raw) == 47


def _restamped(body: bytes) -> bytes:
    return body + zlib.crc32(body).to_bytes(4, "little")


@pytest.mark.parametrize("make,message", [
    (lambda raw: b"\xbb" + raw[1:], "not an event-based uSD log"),
    (lambda raw: _restamped(raw[:1] + b"\x03\x00" + raw[3:-4]), "version 3, this reader reads 2"),
    (lambda raw: raw[:-1], "CRC mismatch of the file"),
    (lambda raw: _restamped(raw[:-4] + b"\x09\x00"), "event id 9 is not declared in the header"),
    (lambda raw: _restamped(raw[:-4] + b"\x07\x00\x01"), "truncated record of event 'estTDOA'"),
    (lambda raw: _restamped(raw[:24] + raw[24:60].replace(b"(f)", b"(Z)", 1) + raw[60:-4]), "unknown field type 'Z'"),
])  # fmt: skip
def test_a_malformed_event_log_is_named(tmp_path, make, message):
    path = tmp_path / "log01"
    path.write_bytes(make(encode_usd_events(EVENTS, _event_records(5))))
    with pytest.raises(UsdFormatError, match=rf"^{path}: byte \d+: .*{message}"):
        read_usd_events(path)


@settings(max_examples=150, deadline=None)
@given(at=st.floats(0.0, 1.0), bits=st.integers(1, 255), cut=st.booleans())
def test_any_flipped_byte_or_cut_of_an_event_log_is_refused(tmp_path_factory, at, bits, cut):
    """The file's CRC-32 covers every byte before it: any change or cut is refused, with an offset."""
    raw = encode_usd_events(EVENTS, _event_records(12))
    i = int(at * (len(raw) - 1))
    data = raw[:i] if cut else raw[:i] + bytes([raw[i] ^ bits]) + raw[i + 1:]
    path = tmp_path_factory.mktemp("ev") / "log"
    path.write_bytes(data)
    with pytest.raises(UsdFormatError, match=rf"^{path}: byte \d+: "):
        read_usd_events(path)


def test_published_errors_are_read_with_their_units(tmp_path):
    """The data set's per-type errors, a training log's lines: gram-force squared of the vertical force,
    as the target's vertical acceleration (the large frame 67 g, the small 32 g); other lines ignored."""
    from downwash.real_logs.neural_swarm import published_errors

    path = tmp_path / "log.txt"
    path.write_text("S2L loss b4 training 9.0\nS2L loss after training 4.0\nGe2S loss after training 0.25\n"
                    "[3] loss: 27767.791\nmean:\n6.5\n")
    got = published_errors(path)
    assert set(got) == {"S2L", "Ge2S"} and got["S2L"]["mse_gf2"] == 4.0
    assert got["S2L"]["z_rmse"] == pytest.approx(2.0e-3 * GRAVITY / 0.067, rel=1e-12)
    assert got["Ge2S"]["z_rmse"] == pytest.approx(0.5e-3 * GRAVITY / 0.032, rel=1e-12)
    path.write_text("nothing here\n")
    assert published_errors(path) == {}
