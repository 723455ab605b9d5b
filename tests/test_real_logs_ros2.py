"""ROS 2 bags to flight logs, on bags the tests write with rosbags' own writer (both storages).

A known flight: vehicle cf1 on a circle (PoseStamped, a world-frame TwistStamped, a setpoint, a
thrust in N on a headerless Float32 at another rate, an IMU), vehicle cf2 on another circle
(an Odometry whose twist is in the body frame, four PWMs and the battery voltage through its kind's
thrust map), their topics at other rates and starts. Read back through a TOML mapping: positions,
velocities, the grid, ``u_cmd = R e3 T / m - g e3`` against the analytic attitude (no project code),
the source's digests; the labels of a known thrust and motion are the known force. Errors name the
bag and the topic, a bad mapping names the key; any flipped or cut byte of the storage file is a
named error, or reads what was written, or (only inside a message's serialised bytes, which
neither storage checksums) changes a value without dropping any message.
"""

import hashlib
import json
import math
import sys
import tomllib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from downwash_core.errors import ConfigError, DataError
from downwash_core.params import GRAVITY
from downwash_core.vehicles import ThrustMap, get_vehicle
from downwash.labels import labels_from_log
from downwash.real_logs.mapping import UnitMismatchError, load_mapping, parse_mapping
from downwash.real_logs.ros2_bag import BagFormatError, read_bag_flight

rosbags = pytest.importorskip("rosbags")  # the logs extra
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
T0 = 1_700_000_000  # s since the epoch: the flight's first stamp
R, W, TILT = 0.5, 2 * math.pi * 0.2, 0.1  # m, rad/s, rad: the circle and the roll
MASS1 = 0.04  # kg
PLUGINS = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}

MAPPING = """
format = "ros2-bag"
rate_hz = 100

[vehicles.cf1]
mass = 0.04
pose = "/cf1/pose"
twist = "/cf1/twist"
imu = "/cf1/imu"
setpoint = "/cf1/setpoint"
thrust = "/cf1/thrust"

[vehicles.cf2]
kind = "crazyflie_2_1"
pose = "/cf2/odom"
pwm = { topic = "/cf2/pwm", field = "data[0:4]" }
battery = "/cf2/battery"
"""


def load_mapping_text(text):
    return tomllib.loads(text)


def _value(v):
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + " }"
    return json.dumps(v)  # strings, numbers and lists of them are JSON and TOML alike


def _to_toml(data):
    """The mapping's TOML: the top level's values, then a [section.name] per table of tables."""
    lines = [f"{k} = {_value(v)}" for k, v in data.items() if not isinstance(v, dict) or not all(
        isinstance(x, dict) for x in v.values()) or not v]
    for key, tables in data.items():
        if isinstance(tables, dict) and tables and all(isinstance(x, dict) for x in tables.values()):
            for name, table in tables.items():
                lines += [f"[{key}.{name}]", *(f"{k} = {_value(v)}" for k, v in table.items())]
    return "\n".join(lines) + "\n"


def _msg(name, **kw):
    return TS.types[name](**kw)


def _header(t):
    sec = math.floor(t)
    return _msg("std_msgs/msg/Header", stamp=_msg("builtin_interfaces/msg/Time", sec=sec,
                                                  nanosec=int(round((t - sec) * 1e9))), frame_id="world")


def _point(name, p):
    return _msg(name, x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _quat(q):
    return _msg("geometry_msgs/msg/Quaternion", w=float(q[0]), x=float(q[1]), y=float(q[2]), z=float(q[3]))


def circle(t, centre, phase=0.0):
    """Position, velocity (world), attitude (w, x, y, z) and R e3 of a vehicle on the circle at times
    t (N,) s: heading psi = W t + phase, rolled by TILT; R e3 written out (Rz(psi) Rx(TILT) e3)."""
    psi = W * t + phase
    pos = np.stack([centre[0] + R * np.cos(psi), centre[1] + R * np.sin(psi), np.full_like(t, centre[2])], 1)
    vel = np.stack([-R * W * np.sin(psi), R * W * np.cos(psi), np.zeros_like(t)], 1)
    c, s = np.cos(TILT / 2), np.sin(TILT / 2)
    quat = np.stack([np.cos(psi / 2) * c, np.cos(psi / 2) * s, np.sin(psi / 2) * s, np.sin(psi / 2) * c], 1)
    e3 = np.stack([np.sin(psi) * np.sin(TILT), -np.cos(psi) * np.sin(TILT), np.full_like(t, np.cos(TILT))], 1)
    return pos, vel, quat, e3


def thrust1(t):
    return MASS1 * (GRAVITY + 0.3) + 0.01 * t  # N: linear in time, so interpolation is exact


PWM2, VBAT2 = 40_000.0, 3.9


def flight_messages(duration=4.0, pos_scale=1.0):
    """(topic, type, receive ns, message) of the known flight, in receive order."""
    out = []

    def add(topic, msgtype, t, msg):
        out.append((topic, msgtype, int(round((T0 + t) * 1e9)), msg))

    for t in np.arange(0.0, duration, 0.01):  # cf1 at 100 Hz
        pos, vel, quat, _ = (a[0] for a in circle(np.array([t]), (0.0, 0.0, 1.0)))
        pose = _msg("geometry_msgs/msg/Pose", position=_point("geometry_msgs/msg/Point", pos * pos_scale),
                    orientation=_quat(quat))
        add("/cf1/pose", "geometry_msgs/msg/PoseStamped", t, _msg("geometry_msgs/msg/PoseStamped",
                                                                  header=_header(T0 + t), pose=pose))
        twist = _msg("geometry_msgs/msg/Twist", linear=_point("geometry_msgs/msg/Vector3", vel),
                     angular=_point("geometry_msgs/msg/Vector3", [0, 0, W]))
        add("/cf1/twist", "geometry_msgs/msg/TwistStamped", t, _msg("geometry_msgs/msg/TwistStamped",
                                                                    header=_header(T0 + t), twist=twist))
        target = _msg("geometry_msgs/msg/Pose", position=_point("geometry_msgs/msg/Point", [0.5, 0.0, 1.0]),
                      orientation=_quat([1, 0, 0, 0]))
        add("/cf1/setpoint", "geometry_msgs/msg/PoseStamped", t, _msg("geometry_msgs/msg/PoseStamped",
                                                                      header=_header(T0 + t), pose=target))
    for t in np.arange(0.0, duration, 0.02):  # the thrust at 50 Hz, no header: its receive time
        add("/cf1/thrust", "std_msgs/msg/Float32", t, _msg("std_msgs/msg/Float32", data=float(thrust1(t))))
    for t in np.arange(0.05, duration, 1 / 120):  # cf2 at 120 Hz from 0.05 s
        pos, vel, quat, _ = (a[0] for a in circle(np.array([t]), (2.0, 0.0, 1.5), phase=1.0))
        body = (np.linalg.inv(_rot(quat)) @ vel)  # nav_msgs/Odometry: the twist in the child (body) frame
        odom = _msg("nav_msgs/msg/Odometry", header=_header(T0 + t), child_frame_id="cf2",
                    pose=_msg("geometry_msgs/msg/PoseWithCovariance", covariance=np.zeros(36),
                              pose=_msg("geometry_msgs/msg/Pose", position=_point("geometry_msgs/msg/Point", pos),
                                        orientation=_quat(quat))),
                    twist=_msg("geometry_msgs/msg/TwistWithCovariance", covariance=np.zeros(36),
                               twist=_msg("geometry_msgs/msg/Twist", linear=_point("geometry_msgs/msg/Vector3", body),
                                          angular=_point("geometry_msgs/msg/Vector3", [0, 0, 0]))))
        add("/cf2/odom", "nav_msgs/msg/Odometry", t, odom)
    for t in np.arange(0.0, duration, 0.01):
        layout = _msg("std_msgs/msg/MultiArrayLayout", dim=[], data_offset=0)
        add("/cf2/pwm", "std_msgs/msg/Float32MultiArray", t, _msg("std_msgs/msg/Float32MultiArray", layout=layout,
                                                                  data=np.full(4, PWM2, np.float32)))
        add("/cf2/battery", "sensor_msgs/msg/BatteryState", t, _battery(t, VBAT2))
    for t in np.arange(0.0, duration, 0.005):
        add("/cf1/imu", "sensor_msgs/msg/Imu", t, _imu(t))
    return sorted(out, key=lambda m: m[2])


def _rot(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _battery(t, volts):
    return _msg("sensor_msgs/msg/BatteryState", header=_header(T0 + t), voltage=volts, temperature=20.0,
                current=-1.0, charge=0.2, capacity=0.25, design_capacity=0.25, percentage=0.8,
                power_supply_status=2, power_supply_health=1, power_supply_technology=3, present=True,
                cell_voltage=np.array([volts], np.float32), cell_temperature=np.array([20.0], np.float32),
                location="", serial_number="")


def _imu(t):
    v3 = _point("geometry_msgs/msg/Vector3", [0.0, 0.0, GRAVITY])
    return _msg("sensor_msgs/msg/Imu", header=_header(T0 + t), orientation=_quat([1, 0, 0, 0]),
                orientation_covariance=np.zeros(9), angular_velocity=v3, angular_velocity_covariance=np.zeros(9),
                linear_acceleration=v3, linear_acceleration_covariance=np.zeros(9))


def write_bag(path, plugin, messages, empty=()):
    """A bag of (topic, type, receive ns, message), and topics with no message (topic, type); plugin
    "mcap-zstd": MCAP with zstd-compressed chunks."""
    writer = Writer(path, version=9, storage_plugin=PLUGINS[plugin.split("-")[0]])
    if plugin == "mcap-zstd":
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        connections = {}
        for topic, msgtype, _, _ in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=TS)
        for topic, msgtype in empty:
            writer.add_connection(topic, msgtype, typestore=TS)
        for topic, msgtype, stamp, msg in messages:
            writer.write(connections[topic], stamp, TS.serialize_cdr(msg, msgtype))
    return path


@pytest.fixture(scope="module")
def known_bags(tmp_path_factory):
    messages = flight_messages()
    root = tmp_path_factory.mktemp("bags")
    (root / "mapping.toml").write_text(MAPPING)
    return {p: write_bag(root / p, p, messages) for p in PLUGINS}, root / "mapping.toml"


def storage_file(bag):
    return next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))


@pytest.mark.parametrize("plugin", PLUGINS)
def test_a_known_flight_reads_back(known_bags, plugin):
    bags, mapping = known_bags
    log = read_bag_flight(bags[plugin], mapping)
    assert log.real and log.meta["vehicles"] == ["cf1", "cf2"] and log.meta["masses"] == [MASS1, 0.0319]
    assert "kinds" not in log.meta  # cf1 names no kind
    # the grid: 100 Hz from the latest first stamp (cf2's, 0.05 s) to the earliest last one (the thrust's, 3.98 s)
    assert log.meta["config"]["start_s"] == pytest.approx(T0 + 0.05, abs=1e-6)
    np.testing.assert_allclose(np.diff(log["t"]), 0.01, atol=1e-9)
    assert log["t"][0] == 0.0 and log["t"][-1] == pytest.approx(3.93, abs=1e-9)
    t = log["t"] + 0.05
    for v, centre, phase in ((0, (0.0, 0.0, 1.0), 0.0), (1, (2.0, 0.0, 1.5), 1.0)):
        pos, vel, quat, _ = circle(t, centre, phase)
        np.testing.assert_allclose(log["pos_est"][:, v], pos, atol=3e-5)  # 120 Hz interpolated: r W^2 dt^2 / 8
        np.testing.assert_allclose(log["vel_est"][:, v], vel, atol=3e-5)
        np.testing.assert_allclose(np.abs(np.sum(log["quat_est"][:, v] * quat, axis=1)), 1.0, atol=1e-8)
    np.testing.assert_allclose(log["ref_pos"][:, 0], [[0.5, 0.0, 1.0]] * len(log), atol=1e-12)
    np.testing.assert_allclose(log["ref_vel"][:, 0], 0.0, atol=1e-12)
    assert np.isnan(log["ref_pos"][:, 1]).all() and np.isnan(log["f_hat"]).all()


@pytest.mark.parametrize("plugin", PLUGINS)
def test_u_is_the_thrust_along_the_body_axis_less_gravity(known_bags, plugin):
    bags, mapping = known_bags
    log = read_bag_flight(bags[plugin], mapping)
    t = log["t"] + 0.05
    g = np.array([0.0, 0.0, GRAVITY])
    _, _, _, e3 = circle(t, (0.0, 0.0, 1.0))
    np.testing.assert_allclose(log["u_cmd"][:, 0], e3 * (thrust1(t) / MASS1)[:, None] - g, atol=1e-6)
    m = get_vehicle("crazyflie_2_1").thrust_map  # grams-force per rotor, written out
    p, v = PWM2 / 65536, VBAT2 / 4.2
    thrust2 = 4 * (m.c00 + m.c10 * p + m.c01 * v + m.c20 * p * p + m.c11 * p * v) * 1e-3 * GRAVITY
    _, _, _, e3 = circle(t, (2.0, 0.0, 1.5), 1.0)
    np.testing.assert_allclose(log["u_cmd"][:, 1], e3 * thrust2 / 0.0319 - g, atol=2e-4)  # 120 Hz attitude
    doubled = ThrustMap(2 * m.c00, 2 * m.c10, 2 * m.c01, 2 * m.c20, 2 * m.c11, source="test")
    other = read_bag_flight(bags[plugin], mapping, thrust_maps={"cf2": doubled})
    np.testing.assert_allclose(other["u_cmd"][:, 1] + g, 2 * (log["u_cmd"][:, 1] + g), atol=1e-9)


def test_the_source_names_every_file_with_its_digest_and_what_each_stream_gave(known_bags):
    bags, mapping = known_bags
    log = read_bag_flight(bags["mcap"], load_mapping(mapping))
    src = log.meta["source"]
    assert src["format"] == "ros2-bag-mcap" and src["mapping"]["sha256"] == hashlib.sha256(
        mapping.read_bytes()).hexdigest()
    files = {f["file"]: f for f in src["files"]}
    assert set(files) == {str(p) for p in bags["mcap"].iterdir()}
    for name, entry in files.items():
        assert entry["sha256"] == hashlib.sha256(open(name, "rb").read()).hexdigest()
    assert src["topics"]["/cf1/thrust"] == {"type": "std_msgs/msg/Float32", "messages": 200, "stamps": "receive"}
    assert src["topics"]["/cf1/pose"]["stamps"] == "header" and "/cf1/imu" not in src["topics"]
    streams = log.meta["config"]["streams"]
    assert streams["cf1"]["velocity"] == "/cf1/twist (world frame)" and "not used" in streams["cf1"]["imu"]
    assert streams["cf2"]["velocity"] == "/cf2/odom (body frame)" and streams["cf2"]["setpoint"].startswith("not")
    assert "through the thrust map of Neural-Swarm" in streams["cf2"]["thrust"]
    single = read_bag_flight(storage_file(bags["mcap"]), mapping)  # the storage file alone reads the same
    for name in log.arrays:
        np.testing.assert_array_equal(single[name], log[name])


def test_without_a_twist_the_velocity_is_the_differenced_positions(tmp_path, known_bags):
    bags, _ = known_bags
    (tmp_path / "m.toml").write_text(MAPPING.replace('twist = "/cf1/twist"\n', ""))
    log = read_bag_flight(bags["sqlite3"], tmp_path / "m.toml")
    assert log.meta["config"]["streams"]["cf1"]["velocity"] == "differenced positions (no twist topic)"
    _, vel, _, _ = circle(log["t"] + 0.05, (0.0, 0.0, 1.0))
    np.testing.assert_allclose(log["vel_est"][:, 0], vel, atol=2e-4)  # central differences: r W^3 dt^2 / 6


def _tilted_for(d):
    """Unit quaternions (N, 4) taking e3 to the unit vectors d (N, 3) by the shortest arc (no yaw)."""
    q = np.concatenate([1.0 + d[:, 2:3], -d[:, 1:2], d[:, 0:1], np.zeros((len(d), 1))], axis=1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_labels_of_a_known_thrust_and_motion_are_the_known_force(tmp_path):
    """Analytic: a vehicle on a circle (acceleration -r W^2 e_r) whose thrust is m |a + g e3 - f| along
    (a + g e3 - f) feels f = (0.1, 0, -0.8) m/s^2, and the labels find it."""
    f = np.array([0.1, 0.0, -0.8])
    t = np.arange(0.0, 20.0, 0.01)
    pos, _, _, _ = circle(t, (0.0, 0.0, 1.0))
    acc = -R * W**2 * np.stack([np.cos(W * t), np.sin(W * t), np.zeros_like(t)], 1)
    d = acc + [0.0, 0.0, GRAVITY] - f
    quat, thrust = _tilted_for(d / np.linalg.norm(d, axis=1, keepdims=True)), MASS1 * np.linalg.norm(d, axis=1)
    messages = []
    for k, tk in enumerate(t):
        stamp = int(round((T0 + tk) * 1e9))
        pose = _msg("geometry_msgs/msg/Pose", position=_point("geometry_msgs/msg/Point", pos[k]),
                    orientation=_quat(quat[k]))
        messages.append(("/a/pose", "geometry_msgs/msg/PoseStamped", stamp,
                         _msg("geometry_msgs/msg/PoseStamped", header=_header(T0 + tk), pose=pose)))
        messages.append(("/a/thrust", "std_msgs/msg/Float64", stamp, _msg("std_msgs/msg/Float64", data=thrust[k])))
    bag = write_bag(tmp_path / "bag", "mcap", messages)
    mapping = parse_mapping({"format": "ros2-bag", "vehicles": {"a": {"mass": MASS1, "pose": "/a/pose",
                                                                      "thrust": "/a/thrust"}}})
    log = read_bag_flight(bag, mapping)
    lab = labels_from_log(log, targets="all")
    assert len(lab["y"]) > 1900
    # the grid is the stamps (no interpolation): what is left is the label filter's bias on the circle
    # (a 4th-order fit over 0.19 s of a 0.2 Hz motion), 1e-4 of its 0.79 m/s^2
    np.testing.assert_allclose(lab["y"], np.broadcast_to(f, lab["y"].shape), atol=1e-4)


# ----------------------------------------------------------------------------- errors


def _small_flight(pos_scale=1.0):
    return flight_messages(duration=0.5, pos_scale=pos_scale)


@pytest.mark.parametrize("plugin", PLUGINS)
@pytest.mark.parametrize("edit,error,message", [
    (lambda m: m.replace('"/cf2/odom"', '"/cf3/odom"'), BagFormatError,
     r"topic /cf3/odom: not in the bag \(vehicles.cf2.pose; its topics: /cf1/imu, /cf1/pose"),
    (lambda m: m.replace('thrust = "/cf1/thrust"', 'thrust = "/cf1/setpoint"'), BagFormatError,
     r"topic /cf1/setpoint: type geometry_msgs/msg/PoseStamped, vehicles.cf1.thrust takes std_msgs/msg/Float32, "
     r"std_msgs/msg/Float64 \(or give a field\)"),
    (lambda m: m.replace('pose = "/cf1/pose"', 'pose = "/cf1/imu"'), BagFormatError,
     r"topic /cf1/imu: type sensor_msgs/msg/Imu, vehicles.cf1.pose takes geometry_msgs/msg/PoseStamped"),
    (lambda m: m.replace('field = "data[0:4]"', 'field = "data[1:4]"'), BagFormatError,
     r"topic /cf2/pwm: message 0: vehicles.cf2 pwm takes 4 numbers"),
    (lambda m: m.replace('field = "data[0:4]"', 'field = "msg.values"'), ConfigError,
     r"vehicles.cf2: topic /cf2/pwm \(std_msgs/msg/Float32MultiArray\): no field 'values' \(there: layout, data\)"),
    (lambda m: m.replace('battery = "/cf2/battery"', 'battery = { topic = "/cf2/battery", scale = 1000.0 }'),
     UnitMismatchError, r"topic /cf2/battery: unit mismatch: battery reaches 3900; in V it stays within 60 V: is it "
                        r"in mV\?"),
    (lambda m: m.replace('thrust = "/cf1/thrust"', 'thrust = { topic = "/cf1/thrust", scale = 1000.0 }'),
     UnitMismatchError, r"topic /cf1/thrust: unit mismatch: thrust reaches"),
])  # fmt: skip
def test_a_bag_that_is_not_what_the_mapping_says_is_named(tmp_path, plugin, edit, error, message):
    bag = write_bag(tmp_path / "bag", plugin, _small_flight())
    (tmp_path / "m.toml").write_text(edit(MAPPING))
    with pytest.raises(error, match=rf"^(\S*bag: )?{message}"):
        read_bag_flight(bag, tmp_path / "m.toml")


@pytest.mark.parametrize("plugin", PLUGINS)
def test_positions_in_mm_are_a_unit_mismatch(tmp_path, plugin):
    bag = write_bag(tmp_path / "bag", plugin, _small_flight(pos_scale=1000.0))
    with pytest.raises(UnitMismatchError, match=rf"^{tmp_path / 'bag'}: topic /cf1/pose: unit mismatch: position "
                                                r"reaches 1\d\d\d(\.\d+)?; in m it stays within 100 m: is it in mm\?"):
        read_bag_flight(bag, parse_mapping(load_mapping_text(MAPPING)))


@pytest.mark.parametrize("plugin", PLUGINS)
def test_empty_topics_and_stamps_that_do_not_increase_are_named(tmp_path, plugin):
    flight = _small_flight()
    bag = write_bag(tmp_path / "empty", plugin, [m for m in flight if m[0] != "/cf1/twist"],
                    empty=[("/cf1/twist", "geometry_msgs/msg/TwistStamped")])
    with pytest.raises(BagFormatError, match=r"empty: topic /cf1/twist: no messages$"):
        read_bag_flight(bag, parse_mapping(load_mapping_text(MAPPING)))
    poses = [i for i, m in enumerate(flight) if m[0] == "/cf1/pose"]
    swapped = list(flight)
    a, b = swapped[poses[3]], swapped[poses[4]]
    swapped[poses[3]], swapped[poses[4]] = (a[0], a[1], a[2], b[3]), (b[0], b[1], b[2], a[3])  # stamps out of order
    bag = write_bag(tmp_path / "order", plugin, swapped)
    stamp = lambda msg: rf"{msg.header.stamp.sec}\.{msg.header.stamp.nanosec:09d}"  # noqa: E731
    with pytest.raises(BagFormatError, match=rf"order: topic /cf1/pose: header stamp of message 4 \({stamp(a[3])} s\) "
                                             rf"does not increase \(the one before: {stamp(b[3])} s\)$"):
        read_bag_flight(bag, parse_mapping(load_mapping_text(MAPPING)))


def test_unset_header_stamps_are_named_and_receive_time_reads_them(tmp_path):
    flight = _small_flight()
    for topic, msgtype, stamp, msg in flight:
        if hasattr(msg, "header"):
            msg.header.stamp.sec, msg.header.stamp.nanosec = 0, 0
    bag = write_bag(tmp_path / "zero", "mcap", flight)
    with pytest.raises(BagFormatError, match=r"topic /cf1/pose: every header stamp is 0 \(unset\): read it with "
                                             r"stamps = \"receive\""):
        read_bag_flight(bag, parse_mapping(load_mapping_text(MAPPING)))
    log = read_bag_flight(bag, parse_mapping({**load_mapping_text(MAPPING), "stamps": "receive"}))
    assert log.meta["config"]["stamps"] == "receive" and len(log) > 40


@pytest.mark.parametrize("edit,message", [
    (lambda d: d["vehicles"]["cf1"].update(thurst="/cf1/thrust"),
     r"vehicles.cf1: unknown key 'thurst'; allowed: kind, mass, pose, twist, twist_frame, imu, setpoint, thrust, "
     r"pwm, battery"),
    (lambda d: d.pop("vehicles"), r"\[vehicles\]: missing section"),
    (lambda d: d.update(vehicles={}), r"\[vehicles\]: no vehicle; add a section \[vehicles.<name>\]"),
    (lambda d: d.update(colour="red"), r"unknown key 'colour'; allowed: format, rate_hz, stamps, vehicles"),
    (lambda d: d.update(format="ros1-bag"), r"format: got 'ros1-bag'; allowed: 'ros2-bag', 'crazyflie-usd-events'"),
    (lambda d: d.update(rate_hz=1000), r"rate_hz: got 1000; allowed: a number 10-500"),
    (lambda d: d.update(stamps="sent"), r"stamps: got 'sent'; allowed: header, receive"),
    (lambda d: d["vehicles"]["cf1"].pop("pose"), r"vehicles.cf1: pose: missing"),
    (lambda d: d["vehicles"]["cf1"].pop("mass"), r"vehicles.cf1: neither kind nor mass"),
    (lambda d: d["vehicles"]["cf1"].update(kind="blimp"), r"vehicles.cf1: kind: vehicle: unknown 'blimp'; allowed"),
    (lambda d: d["vehicles"]["cf2"].pop("battery"), r"vehicles.cf2: pwm needs battery"),
    (lambda d: d["vehicles"]["cf1"].update(pwm="/cf1/pwm"), r"vehicles.cf1: give exactly one of thrust"),
    (lambda d: d["vehicles"]["cf1"].update(twist_frame="map"),
     r"vehicles.cf1: twist_frame: got 'map'; allowed: world, body"),
    (lambda d: d["vehicles"]["cf1"].update(twist="cf1/twist"), r"vehicles.cf1.twist: topic: expected a topic name"),
    (lambda d: d["vehicles"]["cf2"].update(pwm={"topic": "/p", "field": "data[0:4"}),
     r"vehicles.cf2.pwm: field: 'data\[0:4' is not a field path"),
    (lambda d: d["vehicles"]["cf2"].update(pwm={"topic": "/p", "colour": 1}),
     r"vehicles.cf2.pwm: unknown key 'colour'; allowed: topic, field, scale$"),
    (lambda d: d["vehicles"]["cf1"].update(mass=-1), r"vehicles.cf1: mass: got -1; allowed: a number > 0"),
])  # fmt: skip
def test_a_bad_mapping_names_the_key_and_what_is_allowed(tmp_path, edit, message):
    data = load_mapping_text(MAPPING)
    edit(data)
    path = tmp_path / "m.toml"
    path.write_text(_to_toml(data))
    with pytest.raises(ConfigError, match=rf"^{path}: {message}"):
        load_mapping(path)


# ----------------------------------------------------------------------------- damaged bags


STORAGES = ("sqlite3", "mcap", "mcap-zstd")


def _receive_times(raw, plugin, at, stamp):
    """Where a message's receive time (ns) lies in a storage file, its serialised bytes at `at`: MCAP's
    message record holds it (its log time, little-endian) 16 bytes before them; sqlite3 holds it twice, as
    a big-endian integer before the row's blob and in the timestamp index, which the query reads."""
    if plugin == "mcap":
        return [(at - 16, at - 8)]
    key = stamp.to_bytes(8, "big")
    found, i = [], raw.find(key)
    while i >= 0:
        found.append((i, i + 8))
        i = raw.find(key, i + 1)
    return found


class _Written:
    """A small bag of one storage: its storage file's bytes, the bytes no reader can check (each message's
    serialised bytes, and the receive time of each message read on that clock: one without a header),
    and its flight as read (a short repr for hypothesis' reports)."""

    def __init__(self, folder, plugin):
        messages = flight_messages(duration=0.3)
        self.plugin, self.bag = plugin, write_bag(folder / "bag", plugin, messages)
        self.storage = storage_file(self.bag)
        self.raw = self.storage.read_bytes()
        self.unchecked = []
        for _, msgtype, stamp, msg in messages:
            data = bytes(TS.serialize_cdr(msg, msgtype))
            at = self.raw.find(data)
            while at >= 0:  # identical messages (the PWM's) each lie somewhere
                self.unchecked.append((at, at + len(data)))
                if not hasattr(msg, "header"):
                    self.unchecked += _receive_times(self.raw, plugin, at, stamp)
                at = self.raw.find(data, at + 1)
        self.mapping = parse_mapping(load_mapping_text(MAPPING))
        self.flight = read_bag_flight(self.bag, self.mapping)

    def checked(self, i):
        """Whether a changed byte i is one a reader can see: outside every message's bytes and receive
        time (a compressed file: none, as far as the messages' data goes, but their count)."""
        return self.plugin != "mcap-zstd" and not any(a <= i < b for a, b in self.unchecked)

    def __repr__(self):
        return f"<a {self.storage.suffix} bag of {len(self.raw)} bytes>"


@pytest.fixture(scope="module")
def small_bags(tmp_path_factory):
    return {p: _Written(tmp_path_factory.mktemp(p), p) for p in STORAGES}


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(plugin=st.sampled_from(STORAGES), at=st.floats(0.0, 1.0), bits=st.integers(1, 255), cut=st.booleans())
def test_a_flipped_or_cut_byte_is_named_or_changes_only_a_messages_value(tmp_path_factory, small_bags, plugin, at,
                                                                       bits, cut):
    """Any cut: a named error (sqlite3: the file's size is not its header's pages; MCAP: its end magic
    is gone). Any flip: a named error, or the flight read is exactly the one written, or (a flip inside a
    message's serialised bytes, or in the receive time of a message without a header: neither storage
    as rosbags writes it checksums them) every message was still read, one of them as damaged."""
    bag = small_bags[plugin]
    i = int(at * (len(bag.raw) - 1))
    folder = tmp_path_factory.mktemp("damaged") / "bag"
    folder.mkdir()
    (folder / "metadata.yaml").write_bytes((bag.bag / "metadata.yaml").read_bytes())
    (folder / bag.storage.name).write_bytes(bag.raw[:i] if cut else bag.raw[:i] + bytes([bag.raw[i] ^ bits])
                                            + bag.raw[i + 1:])
    try:
        log = read_bag_flight(folder, bag.mapping)
    except DataError as e:
        assert str(e).startswith(str(folder)), str(e)
        return
    except ConfigError as e:  # a damaged type name or field: the mapping no longer fits
        assert str(e).startswith(str(folder)), str(e)
        return
    assert not cut, f"a bag cut at byte {i} was read"
    if bag.checked(i):
        for name in bag.flight.arrays:
            np.testing.assert_array_equal(log[name], bag.flight[name], err_msg=f"byte {i}: {name} changed")
    assert log.meta["source"]["topics"] == bag.flight.meta["source"]["topics"]  # every message read


def test_an_mcap_bag_with_chunk_crcs_has_a_damaged_message_caught(tmp_path):
    """The mcap library writes a CRC-32 per chunk by default (rosbags writes 0: none), and rosbags checks it:
    the one damage a rosbags-written bag cannot show is caught in such a file."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    messages = [m for m in flight_messages(duration=0.3) if m[0].startswith("/cf1/")]
    path = tmp_path / "crc.mcap"
    with path.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        channels = {}
        for topic, msgtype, _, _ in messages:
            if topic not in channels:
                definition = TS.generate_msgdef(msgtype, ros_version=2)[0].encode()
                schema = writer.register_schema(msgtype, "ros2msg", definition)
                channels[topic] = writer.register_channel(topic, "cdr", schema)
        for topic, msgtype, stamp, msg in messages:
            writer.add_message(channels[topic], stamp, bytes(TS.serialize_cdr(msg, msgtype)), stamp)
        writer.finish()
    mapping = parse_mapping({"format": "ros2-bag", "vehicles": {"cf1": {
        "mass": MASS1, "pose": "/cf1/pose", "twist": "/cf1/twist", "thrust": "/cf1/thrust"}}})
    assert len(read_bag_flight(path, mapping)) == 29
    raw = bytearray(path.read_bytes())
    first = bytes(TS.serialize_cdr(messages[0][3], messages[0][1]))
    raw[raw.find(first) + 30] ^= 0x01  # a low bit of the first pose's x: a value that still looks right
    path.write_bytes(bytes(raw))
    with pytest.raises(BagFormatError, match=rf"^{path}: damaged bag, reading its messages: ReaderError: Chunk "
                                             "checksum mismatch"):
        read_bag_flight(path, mapping)


def test_without_rosbags_the_install_hint_is_given(tmp_path, monkeypatch, known_bags):
    bags, mapping = known_bags
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(ConfigError, match=r'reading ROS 2 bags needs rosbags .*pip install "downwash-testbed\[logs\]"'):
        read_bag_flight(bags["mcap"], mapping)


def test_not_a_bag_is_named(tmp_path, known_bags):
    _, mapping = known_bags
    with pytest.raises(BagFormatError, match=r"nothing: no such bag"):
        read_bag_flight(tmp_path / "nothing", mapping)
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagFormatError, match=r"empty: no storage file \(.mcap or .db3\) in it"):
        read_bag_flight(tmp_path / "empty", mapping)
    (tmp_path / "text.db3").write_text("not a database")
    with pytest.raises(BagFormatError, match=r"text.db3: byte 0: not a sqlite3 database"):
        read_bag_flight(tmp_path / "text.db3", mapping)
    (tmp_path / "text.mcap").write_text("not an mcap file")
    with pytest.raises(BagFormatError, match=r"text.mcap: not a readable ROS 2 bag: AnyReaderError: File magic is "
                                             "invalid"):
        read_bag_flight(tmp_path / "text.mcap", mapping)
    usd = tmp_path / "usd.toml"
    usd.write_text('format = "crazyflie-usd-events"\n[usd]\nmass = 0.03\nposition = { variables = ["x", "y", "z"] }\n'
                   'quaternion = { compressed = "q" }\nthrust = { variables = ["T"] }\n')
    with pytest.raises(ConfigError, match=r"usd.toml: format: a ROS 2 bag needs a mapping of format 'ros2-bag'"):
        read_bag_flight(tmp_path / "text.mcap", usd)


def test_a_receive_time_that_is_not_an_integer_is_named(tmp_path, known_bags):
    """sqlite hands back whatever a damaged row holds: a text where the receive time goes is named."""
    import sqlite3
    bag = tmp_path / "bag"
    write_bag(bag, "sqlite3", _small_flight())
    with sqlite3.connect(storage_file(bag)) as db:
        db.execute("UPDATE messages SET timestamp = 'late' WHERE id = (SELECT MIN(messages.id) FROM messages JOIN "
                   "topics ON topics.id = messages.topic_id WHERE topics.name = '/cf1/thrust')")
    db.close()
    with pytest.raises(BagFormatError, match=r"topic /cf1/thrust: message \d+: receive time 'late' is not an "
                                             "integer: damaged bag"):
        read_bag_flight(bag, known_bags[1])


def test_pwm_needs_a_thrust_map(known_bags, tmp_path):
    bags, mapping = known_bags
    (tmp_path / "m.toml").write_text(MAPPING.replace('kind = "crazyflie_2_1"', 'kind = "x500"'))
    with pytest.raises(ConfigError, match=r"vehicles.cf2: pwm needs a thrust map: kind 'x500' has none \(kinds with "
                                          r"one: crazyflie_2_1, crazyflie_large\)"):
        read_bag_flight(bags["mcap"], tmp_path / "m.toml")
    with pytest.raises(ConfigError, match=r"thrust_maps: no vehicle \['cf9'\] in the mapping \(its vehicles: cf1, "
                                          r"cf2\)"):
        read_bag_flight(bags["mcap"], mapping, thrust_maps={"cf9": get_vehicle("crazyflie_2_1").thrust_map})


def test_a_pose_takes_no_field(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(MAPPING.replace('pose = "/cf1/pose"', 'pose = { topic = "/cf1/pose", field = "pose" }'))
    with pytest.raises(ConfigError, match=rf"^{path}: vehicles.cf1.pose: unknown key 'field'; allowed: topic, scale$"):
        load_mapping(path)


def test_a_compressed_mcap_bag_reads_the_same_flight(small_bags):
    plain, compressed = small_bags["mcap"], small_bags["mcap-zstd"]
    assert len(compressed.raw) < len(plain.raw)
    for name in plain.flight.arrays:
        np.testing.assert_array_equal(compressed.flight[name], plain.flight[name], err_msg=name)
