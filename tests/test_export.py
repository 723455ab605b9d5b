"""experiments.export: flight logs to the tabular CSV/Parquet layout and to MCAP, read back by each format's own library."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from downwash.real_logs.convert import real_flight, vehicle_arrays
from downwash.real_logs.tabular import COLUMNS, read_tabular_flight, write_csv_flight
from downwash_core.errors import ConfigError, DataError, LogError
from downwash_core.params import GRAVITY
from downwash_core.vehicles import VEHICLES
from experiments import export
from sim.logs import ARRAY_SPECS, FlightLog, save_log

DT = 0.02  # s, the simulator's controller period
T, V = 40, 2
NAMES = ("leader", "follower")


def _sim_log(kinds=None) -> FlightLog:
    """A log as the simulator writes it (every array of ARRAY_SPECS), random but physical shapes."""
    rng = np.random.default_rng(1)
    arrays = {}
    for name, (trail, _) in ARRAY_SPECS.items():
        arrays[name] = rng.normal(size=(T,) + tuple(V if d == "V" else d for d in trail))
    arrays["t"] = np.arange(T) * DT
    for q in ("quat", "quat_est"):
        arrays[q] /= np.linalg.norm(arrays[q], axis=-1, keepdims=True)
    meta = {"seed": 3, "config": {"a": 1}, "status": 0, "vehicles": list(NAMES), "roles": ["leader", "follower"]}
    if kinds:
        meta["kinds"] = kinds
    return FlightLog(arrays, meta)


@pytest.fixture
def sim_npz(tmp_path):
    path = tmp_path / "flight_000.npz"
    save_log(path, _sim_log(kinds=["crazyflie_2_1", "x500"]))
    return path


def _expected_thrust(log, v, mass):
    from downwash_core.geometry import quat_to_mat

    b3 = quat_to_mat(log["quat_est"][:, v])[..., 2]
    return mass * np.sum((log["u_cmd"][:, v] + [0.0, 0.0, GRAVITY]) * b3, axis=1)


def test_thrust_level_hover_is_weight_and_inverts_a_real_flights_u_cmd():
    log = _sim_log()
    log.arrays["quat_est"][:] = [1.0, 0.0, 0.0, 0.0]
    log.arrays["u_cmd"][:] = [0.3, -0.2, 0.5]
    s = export.vehicle_signals(log)
    m = VEHICLES["paper_quad"].mass
    np.testing.assert_allclose(s["leader"]["thrust"], m * (GRAVITY + 0.5), rtol=1e-12)  # level: the z part only
    # a real flight's u_cmd is derived from its thrust: the export gives that thrust back
    rng = np.random.default_rng(2)
    t = np.arange(T) * DT
    thrust = 0.3 + rng.uniform(size=T)
    quat = rng.normal(size=(T, 4)) * 0.1 + [1, 0, 0, 0]
    arrays = vehicle_arrays(t, t, pos=rng.normal(size=(T, 3)), vel=rng.normal(size=(T, 3)), quat=quat,
                            ref_pos=rng.normal(size=(T, 3)), ref_vel=rng.normal(size=(T, 3)), thrust=thrust, mass=0.05)
    real = real_flight(t, [arrays], {"source": {"format": "x"}, "vehicles": ["cf"], "masses": [0.05]})
    np.testing.assert_allclose(export.vehicle_signals(real)["cf"]["thrust"], thrust, rtol=1e-12)


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_tabular_export_is_the_documented_layout_and_round_trips(tmp_path, sim_npz, fmt):
    (path,) = export.export_logs([sim_npz], fmt, tmp_path / "out")
    assert path == tmp_path / "out" / f"flight_000.{fmt}"
    if fmt == "csv":
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        header = list(rows[0])
        col = lambda rows, name: np.array([float(r[name]) for r in rows])  # noqa: E731
        vehicles, kinds = [r["vehicle"] for r in rows], [r["kind"] for r in rows]
    else:
        import pyarrow.parquet as pq

        table = pq.read_table(path)
        header = table.column_names
        data = table.to_pydict()
        rows = [dict(zip(data, values)) for values in zip(*data.values())]
        col = lambda rows, name: np.array([r[name] for r in rows], float)  # noqa: E731
        vehicles, kinds = data["vehicle"], data["kind"]
    for name, unit in COLUMNS.items():
        assert (f"{name}[{unit}]" if unit else name) in header
    assert len(rows) == T * V and vehicles == [NAMES[0]] * T + [NAMES[1]] * T
    assert kinds == ["crazyflie_2_1"] * T + ["x500"] * T
    log = _sim_log()
    for v, name in enumerate(NAMES):
        mine = [r for r in rows if r["vehicle"] == name]
        np.testing.assert_array_equal(col(mine, "t[s]"), log["t"])
        for i, a in enumerate("xyz"):
            np.testing.assert_array_equal(col(mine, f"{a}[m]"), log["pos_est"][:, v, i])
            np.testing.assert_array_equal(col(mine, f"v{a}[m/s]"), log["vel_est"][:, v, i])
            np.testing.assert_array_equal(col(mine, f"ref_{a}[m]"), log["ref_pos"][:, v, i])
            np.testing.assert_array_equal(col(mine, f"ref_v{a}[m/s]"), log["ref_vel"][:, v, i])
        for i, a in enumerate("wxyz"):
            np.testing.assert_array_equal(col(mine, f"q{a}"), log["quat_est"][:, v, i])
        mass = VEHICLES[["crazyflie_2_1", "x500"][v]].mass
        np.testing.assert_array_equal(col(mine, "mass[kg]"), mass)
        np.testing.assert_allclose(col(mine, "thrust[N]"), _expected_thrust(log, v, mass), rtol=1e-12)
    # the project's own reader takes it: the same estimates, and u_cmd rebuilt from the thrust
    back = read_tabular_flight(path, rate_hz=1 / DT)
    assert back.meta["vehicles"] == list(NAMES) and back.meta["kinds"] == ["crazyflie_2_1", "x500"]
    assert len(back) == T
    for name in ("pos_est", "vel_est", "ref_pos", "ref_vel", "u_cmd"):
        np.testing.assert_allclose(back[name], _projected(log)[name], atol=1e-9, err_msg=name)
    np.testing.assert_allclose(np.abs(np.sum(back["quat_est"] * log["quat_est"], axis=-1)), 1.0, atol=1e-12)
    # and exporting what was read gives the same file's numbers again
    (again,) = export.export_logs([path], fmt, tmp_path / "again")
    twice = read_tabular_flight(again, rate_hz=1 / DT)
    np.testing.assert_allclose(twice["u_cmd"], back["u_cmd"], atol=1e-9)


def _projected(log):
    """The log's arrays as the tabular layout keeps them: u_cmd only along the body z axis."""
    from downwash_core.geometry import quat_to_mat

    b3 = quat_to_mat(log["quat_est"])[..., 2]
    g = np.array([0.0, 0.0, GRAVITY])
    along = np.sum((log["u_cmd"] + g) * b3, axis=-1, keepdims=True) * b3 - g
    return {**log.arrays, "u_cmd": along}


def test_mcap_export_channels_schemas_numbers_and_metadata(tmp_path, sim_npz):
    from mcap.reader import make_reader

    (path,) = export.export_logs([sim_npz], "mcap", tmp_path)
    log = _sim_log()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {f"/{n}/{k}" for n in NAMES for k in ("pose", "twist", "setpoint", "thrust")}
        for c in topics.values():
            schema = summary.schemas[c.schema_id]
            assert c.message_encoding == "json" and schema.encoding == "jsonschema"
            json.loads(schema.data)
        assert summary.schemas[topics["/leader/pose"].schema_id].name == "foxglove.PoseInFrame"
        got: dict[str, list] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            body = json.loads(message.data)
            ns = body["timestamp"]["sec"] * 10**9 + body["timestamp"]["nsec"]
            assert ns == message.log_time == message.publish_time
            got.setdefault(channel.topic, []).append((message.log_time, body))
        f.seek(0)
        (record,) = list(make_reader(f).iter_metadata())
    assert record.name == "downwash.flight" and record.metadata["layout"] == export.MCAP_LAYOUT
    meta = json.loads(record.metadata["meta"])
    assert meta["seed"] == 3 and meta["kinds"] == ["crazyflie_2_1", "x500"]
    assert record.metadata["source_file"] == str(sim_npz)
    for v, name in enumerate(NAMES):
        pose = sorted(got[f"/{name}/pose"], key=lambda x: x[0])
        assert [ns for ns, _ in pose] == [round(t * 1e9) for t in log["t"]]
        p = np.array([[b["pose"]["position"][a] for a in "xyz"] for _, b in pose])
        q = np.array([[b["pose"]["orientation"][a] for a in "wxyz"] for _, b in pose])
        np.testing.assert_array_equal(p, log["pos_est"][:, v])
        np.testing.assert_array_equal(q, log["quat_est"][:, v])
        assert all(b["frame_id"] == "world" for _, b in pose)
        twist = [b for _, b in sorted(got[f"/{name}/twist"], key=lambda x: x[0])]
        np.testing.assert_array_equal([[b["linear"][a] for a in "xyz"] for b in twist], log["vel_est"][:, v])
        sp = [b for _, b in sorted(got[f"/{name}/setpoint"], key=lambda x: x[0])]
        for key, arr in (("position", "ref_pos"), ("velocity", "ref_vel"), ("acceleration", "ref_acc")):
            np.testing.assert_array_equal([[b[key][a] for a in "xyz"] for b in sp], log[arr][:, v])
        th = [b for _, b in sorted(got[f"/{name}/thrust"], key=lambda x: x[0])]
        mass = VEHICLES[["crazyflie_2_1", "x500"][v]].mass
        assert all(b["mass"] == mass for b in th)
        np.testing.assert_allclose([b["thrust"] for b in th], _expected_thrust(log, v, mass), rtol=1e-12)


# ----------------------------------------------------------------------------- bad input, before any write


def test_bad_inputs_are_one_error_naming_them_and_nothing_is_written(tmp_path, sim_npz):
    out = tmp_path / "out"
    with pytest.raises(DataError, match="missing.npz: no such log file"):
        export.export_logs([sim_npz, tmp_path / "missing.npz"], "csv", out)
    with pytest.raises(ConfigError, match=r"--format: unknown format 'hdf5'; allowed: csv, parquet, mcap"):
        export.export_logs([sim_npz], "hdf5", out)
    other = tmp_path / "results.json"
    other.write_text("{}")
    with pytest.raises(LogError, match=r"results.json: a log of another kind \(suffix '.json'\)"):
        export.export_logs([sim_npz, other], "mcap", out)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, x=np.zeros(3))
    with pytest.raises(LogError, match=r"foreign.npz: not a flight log of this project"):
        export.export_logs([sim_npz, foreign], "parquet", out)
    broken = tmp_path / "broken.csv"
    broken.write_text("t[s],vehicle\n0,a\n")
    with pytest.raises(LogError, match=r"broken.csv: line 1: no column x\[m\]"):
        export.export_logs([sim_npz, broken], "parquet", out)
    assert not out.exists()
    # an existing output is kept unless --force; the first of two logs is not written either
    out.mkdir()
    (out / "flight_001.csv").write_text("mine")
    second = tmp_path / "flight_001.npz"
    save_log(second, _sim_log())
    with pytest.raises(ConfigError, match=r"flight_001.csv: exists; --force overwrites it"):
        export.export_logs([sim_npz, second], "csv", out)
    assert sorted(p.name for p in out.iterdir()) == ["flight_001.csv"] and (out / "flight_001.csv").read_text() == "mine"
    export.export_logs([sim_npz, second], "csv", out, force=True)
    assert sorted(p.name for p in out.iterdir()) == ["flight_000.csv", "flight_001.csv"]
    assert read_tabular_flight(out / "flight_001.csv", rate_hz=1 / DT).meta["kinds"] == ["paper_quad"] * 2


def test_a_real_flight_without_masses_or_kinds_and_non_finite_values_are_refused(tmp_path):
    t = np.arange(T) * DT
    z = np.zeros((T, 3))
    arrays = vehicle_arrays(t, t, pos=z, vel=z, quat=np.tile([1.0, 0, 0, 0], (T, 1)), ref_pos=z, ref_vel=z,
                            thrust=np.ones(T), mass=0.05)
    real = real_flight(t, [arrays], {"source": {"format": "x"}, "vehicles": ["cf"]})
    with pytest.raises(LogError, match="without 'masses' or 'kinds'"):
        export.vehicle_signals(real, "r.npz")
    log = _sim_log()
    log.arrays["pos_est"][5, 1, 0] = np.nan
    with pytest.raises(LogError, match=r"bad.npz: array 'pos_est' holds non-finite values at rows \[5\]"):
        export.vehicle_signals(log, "bad.npz")


# ----------------------------------------------------------------------------- the command line


def test_command_line_exports_and_answers_bad_input_with_one_line(tmp_path, sim_npz, capsys):
    csv_in = tmp_path / "lab.csv"
    write_csv_flight(csv_in, {"cf": {"t": np.arange(T) * DT, **{k: np.ones(T) for k in COLUMNS if k != "t"}}})
    written = export.main([str(sim_npz), str(csv_in), "--format", "mcap", "--out", str(tmp_path / "o")])
    assert [p.name for p in written] == ["flight_000.mcap", "lab.mcap"]
    assert "wrote" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        export.main([str(sim_npz), "--out", str(tmp_path / "o")])
    assert e.value.code == 2 and "--format" in capsys.readouterr().err
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "experiments.export", str(sim_npz), "--format", "mcap", "--out",
                           str(tmp_path / "o")], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 2 and proc.stderr.strip() == f"error: {tmp_path / 'o' / 'flight_000.mcap'}: exists; " \
                                                           "--force overwrites it"
