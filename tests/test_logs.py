"""Flight logs: round trip, atomic writes, clear errors for truncated or foreign files."""

import json

import numpy as np
import pytest

from downwash_core.io import atomic_write_json
from sim.logs import ARRAY_SPECS, SCHEMA_VERSION, FlightLog, LogError, load_log, save_log


def _log(T=20, V=2):
    rng = np.random.default_rng(0)
    arrays = {}
    for name, (trail, _) in ARRAY_SPECS.items():
        shape = (T,) + tuple(V if d == "V" else d for d in trail)
        arrays[name] = rng.normal(size=shape)
    return FlightLog(arrays, {"seed": 3, "config": {"a": 1}, "status": 0})


def test_round_trip(tmp_path):
    log = _log()
    path = tmp_path / "f.npz"
    save_log(path, log)
    back = load_log(path)
    for k in ARRAY_SPECS:
        np.testing.assert_array_equal(back[k], log[k])
    assert back.meta["seed"] == 3 and back.meta["schema_version"] == SCHEMA_VERSION
    assert [p.name for p in tmp_path.iterdir()] == ["f.npz"]  # no temp files left


def test_truncated_file(tmp_path):
    path = tmp_path / "f.npz"
    save_log(path, _log())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(LogError, match="f.npz.*truncated or foreign"):
        load_log(path)


def test_foreign_files(tmp_path):
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(LogError, match="other.npz: not a flight log"):
        load_log(other)
    text = tmp_path / "text.npz"
    text.write_text("hello")
    with pytest.raises(LogError, match="text.npz"):
        load_log(text)
    with pytest.raises(LogError, match="no such log file"):
        load_log(tmp_path / "missing.npz")


def test_wrong_schema_and_shapes(tmp_path):
    log = _log()
    path = tmp_path / "f.npz"
    meta = dict(log.meta, schema_version=SCHEMA_VERSION + 1)
    np.savez(path, __meta__=np.frombuffer(json.dumps(meta).encode(), np.uint8), **log.arrays)
    with pytest.raises(LogError, match="schema version"):
        load_log(path)
    bad = _log()
    bad.arrays["u_cmd"] = bad.arrays["u_cmd"][:-1]
    with pytest.raises(LogError, match="u_cmd"):
        save_log(tmp_path / "g.npz", bad)


def test_atomic_json_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "r.json"
    atomic_write_json(path, {"a": 1})
    with pytest.raises(TypeError):
        atomic_write_json(path, {"a": object()})
    assert json.loads(path.read_text()) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]
