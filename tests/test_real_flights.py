"""The real-flights experiment on a small data set in the Neural-Swarm layout that the test writes itself.

Two days of flights: a small vehicle hovering 0.4 m above a large one that it pushes down by a
known 1 m/s^2 (swaps), and a small one alone in free air (random walks). The experiment reads
every file, types each sample by who flies above, trains the models on one day and judges them
on the other; the known force shows in the no-model error of each type. A swap whose logs
start 0.3 s apart is rejected by name; a crash ends a vehicle's samples, ground effect is typed.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY
from downwash_core.provenance import describe
from downwash.real_logs.crazyflie_usd import UsdFormatError, compress_quaternions, write_usd_sync
from downwash.real_logs.flights import find_flights, labelled_samples, read_flights
from downwash.real_logs.neural_swarm import NEURAL_SWARM_VEHICLES
from experiments.real_flights import main
from sim.fields.registry import resolve_field_spec
from test_real_logs import _neural_swarm_columns  # tests/ is on sys.path under pytest

ROOT = Path(__file__).resolve().parent.parent
PUSH = -1.0  # m/s^2, what the small vehicle's wake does to the large one below it
T = np.arange(1200) / 100.0  # 12 s at 100 Hz


def _vehicle(folder: Path, name: str, z: float, force: float, tick0: int, frame: str, **changes) -> None:
    """A level vehicle of `frame` hovering at height z while a force (m/s^2, vertical) acts on it."""
    thrust = NEURAL_SWARM_VEHICLES[frame].mass * (GRAVITY - force)
    cols = _neural_swarm_columns(T, np.full(T.size, z), np.full(T.size, thrust), np.full(T.size, 3.9), tick0, frame)
    cols.update(changes)
    folder.mkdir(parents=True, exist_ok=True)
    write_usd_sync(folder / name, cols)


def _swap(folder: Path, number: str, late_s: float = 0.0) -> None:
    """cf50 (small) 0.4 m above cf101 (large), both starting a move of their setpoints at 5 s."""
    for name, z, force, frame, late in (("cf50", 1.0, 0.0, "small", 0.0), ("cf101", 0.6, PUSH, "large", late_s)):
        move = ("h", np.where((T + late > 5) & (T + late < 7), 200, 0))
        _vehicle(folder, f"{name}_{number}", z, force, 1_000_000 * int(number) + 77, frame, **{"ctrltargetZ.vx": move})


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("neural_swarm") / "data" / "training"
    for day in ("datacollection90_01_01_2020", "datacollection91_01_02_2020"):
        for n in ("00", "01"):
            _swap(root / day / "swap_sl", n)
        _vehicle(root / day / "randomwalk_s", "cf51_00", 0.8, 0.0, 5, "small")
    _swap(root / "datacollection91_01_02_2020" / "swap_sl", "02", late_s=0.3)  # logging started late on one
    return root.parent.parent  # the clone's root


def test_the_experiment_trains_on_one_day_and_judges_on_the_other(data, tmp_path):
    results = main(["--data", str(data), "--train", "datacollection90*/*", "--test", "datacollection91*/*",
                    "--models", "shallow,equivariant", "--curve-fractions", "0.5,1", "--fit-fields", "so2,pybullet",
                    "--quick", "--out", str(tmp_path / "rf")])
    written = json.loads((tmp_path / "rf" / "results.json").read_text())
    assert {k: written[k] for k in results} == json.loads(json.dumps(results)) and written["args"]["quick"]
    assert results["files"] == 5 + 7 and results["flights"] == {"train": 3, "test": 3}
    assert results["records"] == 1200 * (5 + 5)  # every vehicle's 12 s at 100 Hz, resampled from t = 0
    rejected = results["rejected"]
    assert [r["flight"] for r in rejected] == ["datacollection91_01_02_2020/swap_sl/02"]
    assert "setpoints offset by 0.30 s" in rejected[0]["reason"] and rejected[0]["role"] == "test"
    per = results["per_type"]
    assert set(per) == {"S2L", "none2S"} and per["S2L"]["n_test"] > 0 and per["none2S"]["n_test"] > 0
    # no model: the push on the large vehicle, to the floor of 1 mm position steps; none in free air
    assert per["S2L"]["rmse"]["none"] == pytest.approx(abs(PUSH) / np.sqrt(3), abs=0.1)
    assert per["none2S"]["rmse"]["none"] < 0.2
    names = {"shallow", "equivariant", "deepsets_equivariant_kinds", "deepsets_kinds"}  # the models of sets read kinds
    assert set(results["models"]) == names and all(np.isfinite(per["S2L"]["rmse"][k]) for k in names)
    assert results["pairs_to_triples"] == {"skipped": "no test samples with two vehicles above"}
    curves = results["learning_curves"]
    assert [p["flights"] for p in curves["curves"]["equivariant"]] == [2, 2]  # of the two swaps (one flight: 2)
    assert all(len(p["rmse"]) == 2 for k in ("shallow", "equivariant") for p in curves["curves"][k])
    claim = curves["claim"]  # equivariant on the share nearest a third against shallow on all, seed by seed
    assert claim["fraction"] == 0.5 and claim["baselines"] == ["shallow"] and claim["n"] == 2
    assert results["published"] is None  # the clone holds no learning/log.txt
    # the wakes fitted on one day and judged on the other (the same geometry): the fit does no worse than
    # the default constants, its intervals hold the fitted value, and fitted:PATH flies it
    for name, f in results["fitted_fields"].items():
        test, fit = f["test"], f["fit"]
        assert test["fitted"]["rmse"] <= test["default"]["rmse"] + 1e-9 and fit["bootstrap"]["n_boot"] == 10
        # (both training flights are one flight's copies: every refit lands on the fit, within its tolerance)
        assert all(lo * (1 - 1e-6) <= fit["params"][p] <= hi * (1 + 1e-6) for p, (lo, hi) in fit["intervals"].items())
        field = resolve_field_spec(f"fitted:{f['file']}")
        assert describe(field)["fitted"]["data_digest"] == fit["data_digest"] == test["fitted"]["data_digest"]
        assert f["ranges"]["absolute"] == {p: list(v) for p, v in fit["intervals"].items()}
    # the test day's swaps flown in the simulator under the fitted so2 field, with both gains: the real side is
    # the same read of the same flights; the equivariant model trained here flies in the loop
    replays = results["replays"]
    assert replays["flights"] == 2 and set(replays["tracking"]) == {"fitted-so2|default", "fitted-so2|crazyflie"}
    real = [t["pooled"]["under"]["real"] for t in replays["tracking"].values()]
    assert real[0] == real[1] and real[0]["rows"] > 0
    for key, loop in replays["in_loop"].items():
        assert loop["conditions"] == ["baseline", "oracle", "equivariant-real"] and key in replays["tracking"]
        assert loop["under_rms"]["baseline"] == pytest.approx(replays["tracking"][key]["pooled"]["under"]["sim"]["pos"]["rms"])
    assert (tmp_path / "rf" / "models" / "equivariant.pt").is_file()
    with pytest.raises(ConfigError, match="--replay-fields: fitted-momentum needs momentum in --fit-fields"):
        main(["--data", str(data), "--train", "datacollection90*/*", "--test", "datacollection91*/*", "--fit-fields",
              "so2", "--replay-fields", "fitted-momentum", "--quick", "--out", str(tmp_path / "rf2")])
    # the upper vehicle of a swap has a neighbour (below it) and feels nothing: a model must learn that too
    assert per["none2S"]["n_test"] > 1200
    free = results["free_air_label"]
    assert free["n"] > 0 and abs(free["mean"][2]) < 0.05


def test_samples_end_at_a_crash(tmp_path):
    """A vehicle that goes down into ground effect (0.2 m) and back, then tips over for half a second at
    8 s and flies on level: its samples are typed free air and ground effect, and end 0.3 s before the
    crash, whatever follows it."""
    folder = tmp_path / "day" / "randomwalk_s"
    z = np.interp(T, [0, 3, 4, 6, 7, 12], [0.8, 0.8, 0.2, 0.2, 0.8, 0.8])
    cols = _neural_swarm_columns(T, z, np.full(T.size, NEURAL_SWARM_VEHICLES["small"].mass * GRAVITY),
                                 np.full(T.size, 3.9))
    roll = np.where((T >= 8.0) & (T < 8.5), np.radians(60.0), 0.0)
    quat = np.stack([np.cos(roll / 2), np.sin(roll / 2), 0 * roll, 0 * roll], axis=1)
    cols["stateEstimateZ.quat"] = ("I", compress_quaternions(quat))
    folder.mkdir(parents=True)
    write_usd_sync(folder / "cf50_00", cols)
    flights, rejected = read_flights(find_flights(tmp_path, ["day/*"]))
    ds, types = labelled_samples(flights, stride=1)
    assert not rejected and set(types) == {"none2S", "Ge2S"}
    assert 8.0 - 0.3 - 0.02 < ds.t.max() <= 8.0 - 0.3 + 1e-9
    assert np.all(ds.t[types == "Ge2S"] > 3.5) and np.all(ds.t[types == "Ge2S"] < 6.7)


def test_bad_input_is_named(data, tmp_path):
    with pytest.raises(ConfigError, match="--data: the folder of the data set is needed"):
        main(["--out", str(tmp_path / "a")])
    with pytest.raises(ConfigError, match=r"'nowhere\*/\*': matches no folder of flights"):
        main(["--data", str(data), "--train", "nowhere*/*", "--out", str(tmp_path / "b"), "--quick"])
    with pytest.raises(ConfigError, match="--train and --test share 3 flights"):
        main(["--data", str(data), "--train", "datacollection9*/*", "--test", "datacollection90*/*",
              "--out", str(tmp_path / "c"), "--quick"])
    proc = subprocess.run([sys.executable, "-m", "experiments.real_flights", "--train", "/abs/*"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "--train: expected globs relative to --data" in proc.stderr


def test_decode_writes_the_records_with_the_logs_own_names(data, tmp_path):
    log = data / "data" / "training" / "datacollection90_01_01_2020" / "swap_sl" / "cf50_00"
    out = tmp_path / "cf50_00.csv"
    proc = subprocess.run([sys.executable, "-m", "experiments.real_flights", "decode", str(log), "--csv", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    rows = out.read_text().splitlines()
    assert rows[0].startswith("tick,stateEstimateZ.x,stateEstimateZ.y,stateEstimateZ.z,") and len(rows) == 1 + 1200
    first = dict(zip(rows[0].split(","), rows[1].split(",")))
    assert first["tick"] == "77" and first["stateEstimateZ.z"] == "1000" and first["pm.vbatMV"] == "3900"
    proc = subprocess.run([sys.executable, "-m", "experiments.real_flights", "decode", str(tmp_path / "none")],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "the following arguments are required: --csv" in proc.stderr


def test_decode_writes_one_file_per_event_of_an_event_log(tmp_path):
    from test_real_logs import EVENTS, _event_records
    from downwash.real_logs.crazyflie_usd import encode_usd_events

    log = tmp_path / "log07"
    log.write_bytes(encode_usd_events(EVENTS, _event_records(9)))
    written = main(["decode", str(log), "--csv", str(tmp_path / "out" / "log07.csv")])
    assert [p.name for p in written] == ["log07.fixedFrequency.csv", "log07.estTDOA.csv"]
    rows = written[1].read_text().splitlines()
    assert rows[0] == "timestamp,idA,idB,distanceDiff,motor.m1" and rows[1] == "1000017,0,1,0.0,60000" and len(rows) == 4
    with pytest.raises(UsdFormatError, match="missing: cannot read it"):
        main(["decode", str(tmp_path / "missing"), "--csv", str(tmp_path / "m.csv")])


def test_flights_a_days_summary_leaves_out_are_rejected(data, tmp_path):
    """The data set's summary of a day lists the flights it keeps per task: the others are rejected by name,
    a task it does not name is kept whole; both of its line styles parse."""
    from downwash.real_logs.neural_swarm import summary_flights

    summary = tmp_path / "datacollection90_summary"
    summary.write_text("Experiment ...\n# (1) ./swap_sl; cf 50 & 101\n# ['01']\n\n# L-S swap; cf102 & cf50\n"
                       "# ./swap_ls/\n# 00(LS) 01(SL)\n# 59.79s 59.80s\n")
    listed = summary_flights(summary)
    assert listed == {"swap_sl": {"01"}, "swap_ls": {"00", "01"}}
    flights, rejected = read_flights(find_flights(data / "data" / "training", ["datacollection90*/*"]),
                                     listed={"datacollection90": listed})
    assert [ref.name for ref, _ in flights] == ["datacollection90_01_01_2020/randomwalk_s/00",
                                                "datacollection90_01_01_2020/swap_sl/01"]
    assert [r["flight"] for r in rejected] == ["datacollection90_01_01_2020/swap_sl/00"]
    assert "left out by the data set's summary of the day (it keeps 01 of swap_sl)" in rejected[0]["reason"]
