"""The Crazyflie firmware's event-based uSD log (version 2) to flight logs, on files the tests write
with `encode_usd_events`.

A vehicle on a circle logged as the firmware's float variables (``stateEstimate.*``, ``motor.*``,
``pm.vbat``) and as its compressed ones (``stateEstimateZ.*`` in mm, the packed quaternion,
``pwm.*``, ``pm.vbatMV``): the default mapping picks whichever is logged, and the flight has the
known positions, velocities, grid and ``u_cmd = R e3 T / m - g e3`` (T from the kind's thrust map,
written out); the labels of a known thrust and motion are the known force. A lab's own mapping
(another event, a thrust in N), two vehicles aligned at their first records or on their clocks,
and the errors: a missing event or variable, positions or stamps in other units, stamps that do
not increase, a damaged file, a bad mapping.
"""

import hashlib
import math

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY
from downwash_core.vehicles import ThrustMap, get_vehicle
from downwash.labels import labels_from_log
from downwash.real_logs.crazyflie_events import EventsMappingError, read_events_flight
from downwash.real_logs.crazyflie_usd import USD_EVENTS_FORMAT, UsdFormatError, compress_quaternions, encode_usd_events
from downwash.real_logs.mapping import UnitMismatchError, UsdMapping, default_usd_mapping, load_mapping

R, W, TILT = 0.4, 2 * math.pi * 0.25, 0.08  # m, rad/s, rad
PWM, VBAT = 42_000, 3.8
FLOAT_VARIABLES = {**{f"stateEstimate.{a}": "f" for a in ("x", "y", "z", "vx", "vy", "vz", "qw", "qx", "qy", "qz")},
                   **{f"ctrltarget.{a}": "f" for a in ("x", "y", "z", "vx", "vy", "vz")},
                   **{f"motor.m{i}": "H" for i in range(1, 5)}, "pm.vbat": "f"}
PACKED_VARIABLES = {**{f"stateEstimateZ.{a}": "h" for a in ("x", "y", "z", "vx", "vy", "vz")},
                    "stateEstimateZ.quat": "I", **{f"ctrltargetZ.{a}": "h" for a in ("x", "y", "z", "vx", "vy", "vz")},
                    **{f"pwm.m{i}_pwm": "I" for i in range(1, 5)}, "pm.vbatMV": "H"}


def circle(t, centre=(0.0, 0.0, 1.0)):
    """Position, velocity, attitude (w, x, y, z) and R e3 on the circle (heading W t, rolled by TILT),
    R e3 written out as Rz(W t) Rx(TILT) e3."""
    psi = W * t
    pos = np.stack([centre[0] + R * np.cos(psi), centre[1] + R * np.sin(psi), np.full_like(t, centre[2])], 1)
    vel = np.stack([-R * W * np.sin(psi), R * W * np.cos(psi), np.zeros_like(t)], 1)
    c, s = np.cos(TILT / 2), np.sin(TILT / 2)
    quat = np.stack([np.cos(psi / 2) * c, np.cos(psi / 2) * s, np.sin(psi / 2) * s, np.sin(psi / 2) * c], 1)
    e3 = np.stack([np.sin(psi) * np.sin(TILT), -np.cos(psi) * np.sin(TILT), np.full_like(t, np.cos(TILT))], 1)
    return pos, vel, quat, e3


def float_log(t, boot_us=5_000_000, pwm=PWM, vbat=VBAT, pos_scale=1.0, extra=()):
    """The bytes of a log whose fixedFrequency event holds the float variables, records at t (N,) s
    after boot_us, and an unrelated event in between."""
    pos, vel, quat, _ = circle(t)
    records = []
    for k, tk in enumerate(t):
        values = (*(pos[k] * pos_scale), *vel[k], *quat[k], 0.4, 0.0, 1.0, 0.0, 0.1, 0.0, *[pwm] * 4, vbat)
        stamp = boot_us + int(round(tk * 1e6))
        records.append(("fixedFrequency", stamp, values))
        if k % 10 == 0:
            records.append(("estTDOA", stamp + 3, (k % 8,)))
    events = {"fixedFrequency": (0xFFFF, FLOAT_VARIABLES), "estTDOA": (7, {"idA": "B"}), **dict(extra)}
    return encode_usd_events(events, records)


def packed_log(t, boot_us=1_000):
    pos, vel, quat, _ = circle(t)
    quats = compress_quaternions(quat)
    records = [("fixedFrequency", boot_us + int(round(tk * 1e6)),
                (*np.round(pos[k] * 1e3).astype(int), *np.round(vel[k] * 1e3).astype(int), int(quats[k]),
                 400, 0, 1000, 0, 100, 0, *[PWM] * 4, int(VBAT * 1e3)))
               for k, tk in enumerate(t)]
    return encode_usd_events({"fixedFrequency": (0xFFFF, PACKED_VARIABLES)}, records)


def thrust_of_map(m, pwm=PWM, vbat=VBAT):
    """N, four rotors of a thrust map at one PWM and voltage, grams-force written out."""
    p, v = pwm / 65536, vbat / 4.2
    return 4 * (m.c00 + m.c10 * p + m.c01 * v + m.c20 * p * p + m.c11 * p * v) * 1e-3 * GRAVITY


def test_float_variables_read_through_the_default_mapping(tmp_path):
    t = np.arange(0.0, 6.0, 0.01)
    path = tmp_path / "log03"
    path.write_bytes(float_log(t))
    log = read_events_flight(path)
    assert log.real and log.meta["vehicles"] == ["log03"] and log.meta["kinds"] == ["crazyflie_2_1"]
    assert log.meta["masses"] == [get_vehicle("crazyflie_2_1").mass]
    src = log.meta["source"]
    assert src["format"] == USD_EVENTS_FORMAT and src["event"] == "fixedFrequency"
    assert src["files"] == [{"file": str(path), "format": USD_EVENTS_FORMAT,
                             "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}]
    assert src["mapping"]["file"].endswith("mappings/crazyflie_usd.toml")
    used = log.meta["config"]["variables"]["log03"]
    assert used["position"] == ["stateEstimate.x", "stateEstimate.y", "stateEstimate.z"]
    assert used["pwm"] == ["motor.m1", "motor.m2", "motor.m3", "motor.m4"] and used["battery"] == ["pm.vbat"]
    np.testing.assert_allclose(np.diff(log["t"]), 0.01, atol=1e-9)
    assert log["t"][-1] == pytest.approx(5.99)
    pos, vel, quat, e3 = circle(log["t"])
    np.testing.assert_allclose(log["pos_est"][:, 0], pos, atol=1e-6)  # float32 logged
    np.testing.assert_allclose(log["vel_est"][:, 0], vel, atol=1e-6)
    np.testing.assert_allclose(log["ref_pos"][:, 0], [[0.4, 0.0, 1.0]] * len(log), atol=1e-6)
    np.testing.assert_allclose(log["ref_vel"][:, 0], [[0.0, 0.1, 0.0]] * len(log), atol=1e-6)
    thrust = thrust_of_map(get_vehicle("crazyflie_2_1").thrust_map, vbat=float(np.float32(VBAT)))
    u = e3 * thrust / get_vehicle("crazyflie_2_1").mass - [0.0, 0.0, GRAVITY]
    np.testing.assert_allclose(log["u_cmd"][:, 0], u, atol=1e-5)


def test_the_firmwares_compressed_variables_read_through_the_same_mapping(tmp_path):
    t = np.arange(0.0, 3.0, 0.01)
    path = tmp_path / "log04"
    path.write_bytes(packed_log(t))
    log = read_events_flight(path)
    used = log.meta["config"]["variables"]["log04"]
    assert used["position"][0] == "stateEstimateZ.x" and used["quaternion"] == ["stateEstimateZ.quat"]
    assert used["battery"] == ["pm.vbatMV"] and used["pwm"][0] == "pwm.m1_pwm"
    pos, vel, quat, _ = circle(log["t"])
    np.testing.assert_allclose(log["pos_est"][:, 0], pos, atol=5e-4)  # 1 mm steps
    np.testing.assert_allclose(log["vel_est"][:, 0], vel, atol=5e-4)
    np.testing.assert_allclose(log["ref_pos"][:, 0], [[0.4, 0.0, 1.0]] * len(log), atol=1e-12)
    # the packed quaternion: 9 bits per component over 1/sqrt(2)
    assert np.abs(np.sum(log["quat_est"][:, 0] * quat, axis=1)).min() > 1 - 1e-5


def test_labels_of_a_known_thrust_and_motion_are_the_known_force(tmp_path):
    """Analytic: a vehicle on a circle whose thrust (a variable in N, a lab's mapping) is m |a + g e3 - f|
    along a + g e3 - f feels f = (0, 0.2, -0.5) m/s^2, and the labels find it."""
    f, mass = np.array([0.0, 0.2, -0.5]), 0.05
    t = np.arange(0.0, 20.0, 0.01)
    pos = circle(t)[0]
    acc = -R * W**2 * np.stack([np.cos(W * t), np.sin(W * t), np.zeros_like(t)], 1)
    d = acc + [0.0, 0.0, GRAVITY] - f
    n = d / np.linalg.norm(d, axis=1, keepdims=True)
    quat = np.concatenate([1.0 + n[:, 2:3], -n[:, 1:2], n[:, 0:1], np.zeros((len(n), 1))], axis=1)
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)  # the shortest arc from e3 to n
    variables = {"x": "d", "y": "d", "z": "d", "qw": "d", "qx": "d", "qy": "d", "qz": "d", "T": "d"}
    records = [("state", 10_000 * k, (*pos[k], *quat[k], mass * np.linalg.norm(d[k]))) for k in range(len(t))]
    path = tmp_path / "lab"
    path.write_bytes(encode_usd_events({"state": (3, variables)}, records))
    mapping = tmp_path / "lab.toml"
    mapping.write_text('format = "crazyflie-usd-events"\n[usd]\nevent = "state"\nmass = 0.05\n'
                       'position = { variables = ["x", "y", "z"] }\n'
                       'quaternion = { variables = ["qw", "qx", "qy", "qz"] }\nthrust = { variables = ["T"] }\n')
    log = read_events_flight(path, mapping)
    assert "kinds" not in log.meta and log.meta["config"]["variables"]["lab"]["velocity"] == "differenced positions"
    assert log.meta["source"]["mapping"]["sha256"] == hashlib.sha256(mapping.read_bytes()).hexdigest()
    lab = labels_from_log(log, targets="all")
    assert len(lab["y"]) > 1900
    # stamps on the grid: what is left is the label filter's bias on the circle (4th order over 0.19 s)
    np.testing.assert_allclose(lab["y"], np.broadcast_to(f, lab["y"].shape), atol=2e-4)


def test_two_vehicles_align_at_their_first_records_or_on_their_clocks(tmp_path):
    t = np.arange(0.0, 4.0, 0.01)
    (tmp_path / "a").write_bytes(float_log(t, boot_us=5_000_000))
    (tmp_path / "b").write_bytes(float_log(t[:300], boot_us=90_000_000, pwm=30_000))  # booted 85 s later
    log = read_events_flight([tmp_path / "a", tmp_path / "b"], names=["cf1", "cf2"])
    assert log.meta["vehicles"] == ["cf1", "cf2"] and log.meta["config"]["align"] == "start"
    assert log["t"][-1] == pytest.approx(2.99)  # b's 300 records, from its first
    np.testing.assert_allclose(log["pos_est"][:, 0], log["pos_est"][:, 1], atol=1e-12)  # one circle from each start
    thrust = [thrust_of_map(get_vehicle("crazyflie_2_1").thrust_map, p, float(np.float32(VBAT))) for p in (PWM, 30_000)]
    u_z = log["u_cmd"][:, :, 2] + GRAVITY
    np.testing.assert_allclose(u_z[:, 1] / u_z[:, 0], thrust[1] / thrust[0], rtol=1e-6)
    with pytest.raises(EventsMappingError, match=r"the logs do not overlap in time .*align='clock'"):
        read_events_flight([tmp_path / "a", tmp_path / "b"], align="clock")
    doubled = ThrustMap(*(2 * getattr(get_vehicle("crazyflie_2_1").thrust_map, c) for c in
                          ("c00", "c10", "c01", "c20", "c11")), source="test")
    other = read_events_flight(tmp_path / "a", thrust_map=doubled)
    assert other.meta["config"]["thrust_map"] == "test"
    np.testing.assert_allclose(other["u_cmd"][: len(log), 0, 2] + GRAVITY, 2 * u_z[:, 0], rtol=1e-9)


def test_what_the_file_lacks_is_named(tmp_path):
    t = np.arange(0.0, 1.0, 0.01)
    path = tmp_path / "log"
    path.write_bytes(float_log(t))
    lab = default_usd_mapping()
    other_event = UsdMapping(**{**lab.__dict__, "event": "periodic"})
    with pytest.raises(EventsMappingError, match=rf"^{path}: no event 'periodic' \(its events: fixedFrequency, "
                                                 r"estTDOA\)"):
        read_events_flight(path, other_event)
    no_battery = UsdMapping(**{**lab.__dict__, "battery": lab.battery[1:]})
    with pytest.raises(EventsMappingError, match=r"event 'fixedFrequency': no battery: none of \(pm.vbatMV\) is "
                                                 r"logged \(its variables: stateEstimate.x, "):
        read_events_flight(path, no_battery)
    path.write_bytes(float_log(t[:1]))
    with pytest.raises(EventsMappingError, match=r"event 'fixedFrequency': 1 records, a flight needs two or more"):
        read_events_flight(path)


def test_other_units_and_stamps_that_do_not_increase_are_named(tmp_path):
    t = np.arange(0.0, 1.0, 0.01)
    path = tmp_path / "log"
    path.write_bytes(float_log(t, pos_scale=1000.0))  # mm in the float variables
    with pytest.raises(UnitMismatchError, match=rf"^{path}: event 'fixedFrequency': unit mismatch: position reaches "
                                                r"1\d\d\d(\.\d+)?; in m it stays within 100 m: is it in mm\?"):
        read_events_flight(path)
    path.write_bytes(float_log(t, vbat=3800.0))  # mV in pm.vbat
    with pytest.raises(UnitMismatchError, match=r"unit mismatch: battery reaches 3800; in V"):
        read_events_flight(path)
    path.write_bytes(float_log(t / 1000.0))  # stamps that step by 10 us: ms taken for us
    with pytest.raises(UnitMismatchError, match=r"unit mismatch: the timestamp steps by 10 per record; expected "
                                                r"microseconds"):
        read_events_flight(path)
    path.write_bytes(float_log(np.r_[t[:5], t[3], t[6:]]))
    with pytest.raises(EventsMappingError, match=r"the timestamp of record 5 \(5030000 us\) does not increase \(the "
                                                 r"one before: 5040000 us\)"):
        read_events_flight(path)
    raw = bytearray(float_log(t))
    raw[200] ^= 0x10
    path.write_bytes(bytes(raw))
    with pytest.raises(UsdFormatError, match=rf"^{path}: byte \d+: CRC mismatch"):
        read_events_flight(path)


@pytest.mark.parametrize("text,message", [
    ('[usd]\nkind = "crazyflie_2_1"\n', r"usd: position: missing"),
    ('[usd]\nkind = "crazyflie_2_1"\ncolour = 1\n', r"usd: unknown key 'colour'; allowed: event, kind, mass, "
                                                    r"position, velocity, quaternion"),
    ('[usd]\nmass = 0.03\nposition = { variables = ["x", "y"] }\n', r"usd.position: variables: expected 3 variable "
                                                                    r"names, got \['x', 'y'\]"),
    ('[usd]\nmass = 0.03\nposition = { variables = ["x", "y", "z"], unit = "mm" }\n',
     r"usd.position: unknown key 'unit'; allowed: variables, scale"),
    ('[usd]\nmass = 0.03\nposition = { variables = ["x", "y", "z"], scale = 0 }\n',
     r"usd.position: scale: got 0; allowed: a number > 0"),
    ('[usd]\nmass = 0.03\nposition = { variables = ["x", "y", "z"] }\n'
     'quaternion = { variables = ["a", "b", "c", "d"], compressed = "q" }\n', r"usd.quaternion: give variables"),
    ('[usd]\nmass = 0.03\nposition = { variables = ["x", "y", "z"] }\nquaternion = { compressed = "q" }\n',
     r"usd: give exactly one of thrust \(a variable in N\) and pwm"),
    ('[usd]\nmass = 0.03\nposition = { variables = ["x", "y", "z"] }\nquaternion = { compressed = "q" }\n'
     'pwm = { variables = ["a", "b", "c", "d"] }\n', r"usd: pwm needs battery"),
    ('', r"\[usd\]: missing section"),
])  # fmt: skip
def test_a_bad_usd_mapping_names_the_key_and_what_is_allowed(tmp_path, text, message):
    path = tmp_path / "m.toml"
    path.write_text('format = "crazyflie-usd-events"\n' + text)
    with pytest.raises(ConfigError, match=rf"^{path}: {message}"):
        load_mapping(path)


def test_a_bag_mapping_or_an_unknown_argument_is_refused(tmp_path):
    (tmp_path / "m.toml").write_text('format = "ros2-bag"\n[vehicles.a]\nmass = 0.03\npose = "/p"\nthrust = "/t"\n')
    (tmp_path / "log").write_bytes(float_log(np.arange(0.0, 1.0, 0.01)))
    with pytest.raises(ConfigError, match=r"m.toml: format: an event-based uSD log needs a mapping of format "
                                          r"'crazyflie-usd-events'"):
        read_events_flight(tmp_path / "log", tmp_path / "m.toml")
    with pytest.raises(ConfigError, match=r"align: got 'boot'; allowed: start, clock"):
        read_events_flight(tmp_path / "log", align="boot")
    with pytest.raises(ConfigError, match=r"names: one distinct name per file \(1 files\), got \['a', 'b'\]"):
        read_events_flight(tmp_path / "log", names=["a", "b"])
    no_map = UsdMapping(**{**default_usd_mapping().__dict__, "kind": "x500"})
    with pytest.raises(ConfigError, match=r"pwm needs a thrust map: kind 'x500' has none"):
        read_events_flight(tmp_path / "log", no_map)
