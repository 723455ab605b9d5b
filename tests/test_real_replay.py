"""Real flights replayed in the simulator (`downwash.real_logs.replay`), on synthetic real flights
made with the readers' own `vehicle_arrays` + `real_flight` (no data set needed): two Crazyflies
hovering 0.4 m apart vertically, then a swap that crosses one under the other again.

A hover replayed without downwash tracks within millimetres; `tracking_summary` of a hand-made log
gives the hand-computed numbers; the oracle beats no model under a strong field, a model that
predicts zero flies exactly the baseline; a world that crashes is reported; same seeds, same numbers.
"""

import json

import numpy as np
import pytest
import torch

from downwash_core.errors import ConfigError
from downwash.real_logs.convert import real_flight, vehicle_arrays
from downwash.real_logs.replay import (compare_tracking, error_stats, flight_reference, fly_real_model, replay_in_sim,
                                       tracking_summary, under_another)
from downwash.registry import make_model

RATE = 100.0  # Hz, the data set's grid
CF = "crazyflie_2_1"
MASS = 0.032  # kg, as the Neural-Swarm reader weighs a small Crazyflie


def _min_jerk(t, t0, t1, a, b):
    """Position (N, 3) and velocity (N, 3) of a min-jerk move from a to b over [t0, t1], held outside."""
    d = t1 - t0
    tau = np.clip((t - t0) / d, 0.0, 1.0)[:, None]
    s = tau**3 * (10 - 15 * tau + 6 * tau**2)
    ds = 30 * tau**2 * (1 - tau) ** 2 / d
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a + s * (b - a), ds * (b - a)


def _flight(refs, seconds, offset=(0.0, 0.0, 0.0), kinds=(CF, CF)):
    """A real flight's log of vehicles whose setpoints are refs[v](grid) -> (pos, vel) and whose
    estimates sit `offset` (m) from them."""
    grid = np.arange(int(round(seconds * RATE)) + 1) / RATE
    per = []
    for ref in refs:
        pos, vel = ref(grid)
        per.append(vehicle_arrays(grid, grid, pos=pos + np.asarray(offset), vel=vel, quat=np.tile([1.0, 0, 0, 0],
                                  (grid.size, 1)), ref_pos=pos, ref_vel=vel, thrust=np.full(grid.size, MASS * 9.81),
                                  mass=MASS))
    meta = {"source": {"format": "test", "files": [{"file": f"cf{50 + i}_00"} for i in range(len(refs))]},
            "vehicles": [f"cf{50 + i}" for i in range(len(refs))], "kinds": list(kinds)}
    return real_flight(grid, per, meta)


def _hover(point):
    return lambda t: (np.tile(point, (t.size, 1)), np.zeros((t.size, 3)))


def _swap():
    """A above B by 0.4 m for 1 s, apart sideways by 1 s, then crossing back with B under A at 2.75 s."""
    def move(x0, x1, x2, z):
        def ref(t):
            p1, v1 = _min_jerk(t, 1.0, 2.0, [x0, 0, z], [x1, 0, z])
            p2, v2 = _min_jerk(t, 2.0, 3.5, [x1, 0, z], [x2, 0, z])
            late = (t >= 2.0)[:, None]
            return np.where(late, p2, p1), np.where(late, v2, v1)
        return ref
    return _flight([move(0.0, 0.6, -0.6, 1.4), move(0.0, -0.6, 0.6, 1.0)], 4.0)


SWAP = _swap()


def test_a_replayed_hover_without_downwash_tracks_within_millimetres():
    flight = _flight([_hover([0.0, 0.0, 1.4]), _hover([0.0, 0.0, 1.0])], 2.0)
    (log,) = replay_in_sim(flight, "so2:strength=0", seeds=[0])
    assert log.ok and log.meta["kinds"] == [CF, CF] and log.meta["replay_of"]["flight"] == "cf50_00,cf51_00"
    errors = tracking_summary(log)
    for v in errors["vehicles"]:
        assert v["kind"] == CF and v["all"]["pos"]["max"] < 0.005  # m: motion-capture noise and rounding only
    assert errors["vehicles"][1]["under"]["rows"] == len(log) and errors["vehicles"][0]["under"]["rows"] == 0
    np.testing.assert_allclose(log["pos"][0], flight["pos_est"][0], atol=1e-12)  # it starts where the real one was


def test_the_simulated_vehicles_start_at_their_logged_state():
    flight = _flight([_hover([0.0, 0.0, 1.4]), _hover([0.0, 0.0, 1.0])], 1.0, offset=(0.02, 0.0, -0.05))
    ref = flight_reference(flight, n_worlds=2)
    s0 = ref(0.0)
    np.testing.assert_array_equal(s0.pos[1], flight["pos_est"][0])
    np.testing.assert_array_equal(ref(0.5).pos[0], flight["ref_pos"][50])  # the setpoint from the next sample on
    (log,) = replay_in_sim(flight, "so2:strength=0", seeds=[0], duration=0.5)
    np.testing.assert_allclose(log["pos"][0], flight["pos_est"][0], atol=1e-12)
    assert len(log) == 25


def test_tracking_errors_by_hand():
    flight = _flight([_hover([0.0, 0.0, 1.4]), _hover([0.0, 0.0, 1.0])], 0.04)  # 5 rows
    e = np.array([[0.03, 0.0, 0.04], [0.0, 0.0, -0.1], [0.0, 0.0, 0.0], [0.06, 0.08, 0.0], [0.0, 0.0, 0.02]])
    flight.arrays["pos_est"] = flight["ref_pos"] + e[:, None, :]  # both vehicles, the same errors
    out = tracking_summary(flight)
    # |e| = 0.05, 0.1, 0, 0.1, 0.02 (sorted 0, 0.02, 0.05, 0.1, 0.1); z = 0.04, -0.1, 0, 0, 0.02
    want_pos = {"rms": np.sqrt((0.0025 + 0.01 + 0 + 0.01 + 0.0004) / 5), "median": 0.05,
                "p95": 0.1, "max": 0.1}  # the 95th percentile lies between the two 0.1s
    want_z = {"mean": -0.008, "rms": np.sqrt((0.0016 + 0.01 + 0.0004) / 5), "median": 0.02, "p95": 0.1 - 0.2 * 0.06,
              "max": 0.1}  # |z| sorted 0, 0, 0.02, 0.04, 0.1: p95 = 0.04 + 0.8 (0.1 - 0.04)
    for v, where in ((0, "alone"), (1, "under")):
        got = out["vehicles"][v]
        assert got["all"]["rows"] == 5 and got[where]["rows"] == 5
        for key, value in want_pos.items():
            assert got["all"]["pos"][key] == pytest.approx(value, abs=1e-15)
        for key, value in want_z.items():
            assert got["all"]["z"][key] == pytest.approx(value, abs=1e-15)
    assert out["vehicles"][0]["under"] == {"rows": 0, "pos": None, "z": None}
    assert not out["ended_early"] and out["seconds"] == pytest.approx(0.05)
    assert tracking_summary(flight, duration=0.02)["vehicles"][0]["all"]["rows"] == 2  # rows at 0 and 0.01 s
    json.dumps(out)


def test_under_another_reads_the_setpoints():
    under = under_another(SWAP)
    t = SWAP["t"]
    assert under[t < 1.0, 1].all() and not under[:, 0].any()  # B under A while they hover
    assert not under[(t > 1.8) & (t < 2.4), 1].any()  # apart sideways
    assert under[np.abs(t - 2.75) < 0.02, 1].all()  # crossing back
    assert error_stats(np.zeros(0), np.zeros(0)) == {"rows": 0, "pos": None, "z": None}


def test_compare_tracking_is_deterministic_and_side_by_side():
    a = compare_tracking([SWAP], "so2:strength=2", seeds=[3, 4], duration=2.0)
    b = compare_tracking([SWAP], "so2:strength=2", seeds=[3, 4], duration=2.0)
    assert a == b  # same seeds, same numbers
    (flight,) = a["flights"]
    assert [s["seed"] for s in flight["sim"]] == [3, 4] and flight["seconds"] == 2.0
    assert flight["sim"][0] != flight["sim"][1]  # the seeds' noise differs
    under = under_another(SWAP)[SWAP["t"] < 2.0 - 1e-9, 1]  # B under A: hovering, then until 0.35 m apart
    n = int(under.sum())
    assert n > 100 and flight["real"]["vehicles"][1]["under"]["rows"] == n  # real rows at 100 Hz
    assert flight["sim"][0]["vehicles"][1]["under"]["rows"] == under[::2].sum()  # simulated rows at 50 Hz
    pooled = a["pooled"]["under"]
    assert pooled["real"]["rows"] == n and pooled["sim"]["rows"] == 2 * under[::2].sum()  # two seeds
    # the real "flight" tracks perfectly; the simulated follower sags under the field
    assert pooled["real"]["pos"]["max"] == 0.0 and pooled["sim"]["z"]["mean"] < -0.05
    assert f"{CF}/under" in a["pooled"] and a["ended_early"] == [] and "Mellinger" in a["differences"]
    json.dumps(a)


def test_a_world_that_crashes_is_reported():
    flight = _flight([_hover([0.0, 0.0, 0.75]), _hover([0.0, 0.0, 0.35])], 3.0)
    out = compare_tracking([flight], "so2:strength=40", seeds=[0])
    (ended,) = out["ended_early"]
    sim = out["flights"][0]["sim"][0]
    assert ended["flight"] == "cf50_00,cf51_00" and ended["status"] == sim["status"] != "ok"
    assert sim["ended_early"] and sim["seconds"] < 3.0 and ended["message"]


def _zero_model():
    torch.manual_seed(0)
    model = make_model("equivariant")
    model.set_normalization(torch.zeros(model.n_features), torch.ones(model.n_features),
                            torch.zeros(model.n_outputs), torch.ones(model.n_outputs))
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
    return model.eval()


def test_in_the_loop_the_oracle_beats_no_model_and_a_zero_model_is_the_baseline():
    out = fly_real_model([SWAP], "so2:strength=2", _zero_model(), seeds=[0])
    assert out["conditions"] == ["baseline", "oracle", "equivariant-real"]
    rms, under = out["under_rms"], {c: out["pooled"][c]["under"] for c in out["conditions"]}
    assert rms["oracle"] < rms["baseline"]  # the swap's lateral lag is in both: the gain is in the vertical
    assert under["oracle"]["z"]["rms"] < 0.5 * under["baseline"]["z"]["rms"]
    assert rms["equivariant-real"] == rms["baseline"]
    assert out["pooled"]["equivariant-real"] == out["pooled"]["baseline"]
    assert out["oracle_gain_kept"] == {"flown": 0.0, "penalised": 0.0} and out["ended_early"] == []
    assert out["under_rms_penalised"] == rms  # nothing crashed: nothing to penalise
    assert out["flights"][0]["baseline"] == rms["baseline"] and out["model"]["kind"] == "equivariant"
    json.dumps(out)


def test_in_the_loop_a_crash_counts_at_the_penalty_for_the_ticks_not_flown():
    """The follower 0.4 m under the leader sinks to the ground without a model (the default field pushes
    3.7 m/s^2 there); the oracle holds it. Penalised, the baseline's unflown ticks count at max(1 m, its
    largest error), sim.metrics' crash rule."""
    flight = _flight([_hover([0.0, 0.0, 0.75]), _hover([0.0, 0.0, 0.35])], 3.0)
    out = fly_real_model([flight], "so2", _zero_model(), seeds=[0])
    crashed = {e["condition"]: e for e in out["ended_early"]}
    assert set(crashed) == {"baseline", "equivariant-real"} and crashed["baseline"]["status"] == "ground_collision"
    under = out["pooled"]["baseline"]["under"]
    n, missing = under["rows"], 150 - under["rows"]  # 3 s at 50 Hz planned
    assert 0 < n < 150 and out["under_rms"]["baseline"] == under["pos"]["rms"]
    penalty = max(1.0, under["pos"]["max"])
    want = np.sqrt((n * under["pos"]["rms"] ** 2 + missing * penalty**2) / 150)
    assert out["under_rms_penalised"]["baseline"] == pytest.approx(want, rel=1e-12)
    assert out["under_rms_penalised"]["oracle"] == out["under_rms"]["oracle"] < out["under_rms"]["baseline"]
    assert out["oracle_gain_kept"]["penalised"] == pytest.approx(0.0, abs=1e-12)


def test_bad_input_is_named(tmp_path):
    with pytest.raises(ConfigError, match=r"duration: allowed \(0, 4.000\] s, the flight's length"):
        replay_in_sim(SWAP, "so2", duration=5.0)
    with pytest.raises(ConfigError, match=r"flights\[0\]: expected a FlightLog or a \(FlightRef, FlightLog\) pair"):
        compare_tracking(["not a log"], "so2")
    with pytest.raises(ConfigError, match=r"model_or_checkpoint: expected a trained per-neighbour model"):
        fly_real_model([SWAP], "so2", 3.0)
    with pytest.raises(ConfigError, match="unknown|allowed"):
        compare_tracking([SWAP], "no-such-field")
    bad = _flight([_hover([0.0, 0.0, 1.4]), _hover([0.0, 0.0, 1.0])], 0.1)
    bad.meta["kinds"] = [CF]
    with pytest.raises(ConfigError, match=r"meta 'kinds' names 1 vehicles, the log holds 2"):
        tracking_summary(bad)
