"""Fitting registered fields to labels (`downwash.field_fit`) and flying the fit (`sim.fields.fitted`).

No real data: labels are made by a known field with known parameters plus Gaussian noise over random
geometry, so the fit must find the parameters within what the noise allows (standard errors from
the Jacobian, sigma^2 (J^T J)^-1), and the bootstrap's intervals must cover them in most data sets.
"""

from __future__ import annotations

import dataclasses
import json
import pickle

import numpy as np
import pytest

from downwash_core.errors import ConfigError, DataError
from downwash_core.geometry import quat_to_mat
from downwash_core.provenance import describe
from downwash_core.vehicles import VEHICLES, get_vehicle
from downwash.field_fit import (ENV_SCALABLE, ENV_FACTOR_RANGE, FittedField, PairStates, bootstrap_fit,
                                compare_forces, fit_field, load_fitted, pair_states, field_forces, randomization_ranges,
                                write_fitted)
from downwash.real_logs.convert import real_flight, vehicle_arrays
from sim.field import DownwashField
from sim.fields.fitted import resolve_fitted_spec
from sim.fields.registry import make_field, parse_field_spec, register_field, resolve_field_spec
from sim.vehicle_params import pair_field

SMALL = "crazyflie_2_1"
LARGE = "crazyflie_large" if "crazyflie_large" in VEHICLES else SMALL  # (registered by the real-flight readers)
NOISE = 0.05  # m/s^2, per axis
TRUE = {"so2": {"strength": 6.0, "width0": 0.06}, "momentum": {"thrust_scale": 0.7, "spreading_rate": 0.12},
        "jet": {"decay_constant": 8.0, "spreading_rate": 0.09}, "pybullet": {"dw_coeff_1": 1800.0, "dw_coeff_2": 0.2}}


def _tilt(rng: np.random.Generator, n: int, degrees: float = 5.0) -> np.ndarray:
    """(n, 3, 3) rotations within a few degrees of level."""
    q = np.concatenate([np.ones((n, 1)), rng.normal(0.0, np.radians(degrees) / 2, (n, 3))], axis=1)
    return quat_to_mat(q)


def synthetic_states(name: str, seed: int, n_flights: int = 12, per_flight: int = 250, truth=None) -> PairStates:
    """Followers 0.15-1.4 m below a leader, 0-0.4 m off its axis, moving slowly; labels from `name` with
    the true parameters, scaled per pair of kinds, plus NOISE."""
    rng = np.random.default_rng(seed)
    n = n_flights * per_flight
    p_a = rng.uniform(-1, 1, (n, 3)) + [0, 0, 2.0]
    depth, radius, angle = rng.uniform(0.15, 1.4, n), 0.4 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 7, n)
    p_b = p_a + np.stack([radius * np.cos(angle), radius * np.sin(angle), -depth], axis=1)
    kind_a, kind_b = rng.integers(0, 2, n), rng.integers(0, 2, n)
    states = PairStates(
        p_a=p_a, v_a=rng.normal(0, 0.2, (n, 3)), R_a=_tilt(rng, n), p_b=p_b, v_b=rng.normal(0, 0.3, (n, 3)),
        y=np.zeros((n, 3)), kind_a=kind_a, kind_b=kind_b, flight=np.repeat(np.arange(n_flights), per_flight),
        row=np.tile(np.arange(per_flight), n_flights), vehicle=np.zeros(n, int), types=np.full(n, "S2S"),
        kinds=(SMALL, LARGE), flight_names=tuple(f"f{i}" for i in range(n_flights)),
        flight_digests=tuple(f"{i:064x}" for i in range(n_flights)), selection={"synthetic": seed})
    y = field_forces(make_field(name, **(truth or TRUE[name])), states) + rng.normal(0, NOISE, (n, 3))
    return PairStates(**{**_fields(states), "y": y})


def _fields(states: PairStates) -> dict:
    return {f.name: getattr(states, f.name) for f in dataclasses.fields(states)}


def _standard_errors(name: str, states: PairStates, truth: dict) -> dict:
    """sigma sqrt(diag((J^T J)^-1)) at the truth, J by central differences of the prediction."""
    cols = []
    for p, v in truth.items():
        hi, lo = (field_forces(make_field(name, **{**truth, p: v * (1 + s)}), states) for s in (1e-4, -1e-4))
        cols.append(((hi - lo) / (2e-4 * v)).ravel())
    J = np.stack(cols, axis=1)
    return dict(zip(truth, NOISE * np.sqrt(np.diag(np.linalg.inv(J.T @ J)))))


@pytest.mark.parametrize("name", ["so2", "momentum", "jet", "pybullet"])
def test_fit_recovers_parameters_within_the_noise(name):
    states = synthetic_states(name, seed=1, n_flights=6, per_flight=200)
    fit = fit_field(name, states)
    se = _standard_errors(name, states, TRUE[name])
    for p, v in TRUE[name].items():
        assert abs(fit.params[p] - v) < 5 * se[p], (p, fit.params[p], v, se[p])
    assert fit.rmse_after < fit.rmse_before
    assert fit.rmse_after == pytest.approx(NOISE, rel=0.1)  # the noise floor, three axes
    assert fit.n_samples == len(states) and fit.n_flights == 6 and fit.data_digest == states.data_digest


def test_fit_with_a_robust_loss_ignores_outliers():
    states = synthetic_states("so2", seed=2, n_flights=6, per_flight=200)
    y = states.y.copy()
    y[::50, 2] -= 8.0  # a crash's spikes, down
    spiked = PairStates(**{**_fields(states), "y": y})
    plain, robust = fit_field("so2", spiked), fit_field("so2", spiked, loss="soft_l1", f_scale=0.1)
    err = lambda f: abs(f.params["strength"] / TRUE["so2"]["strength"] - 1)  # noqa: E731
    assert err(robust) < 0.02 and err(plain) > 3 * err(robust), (err(robust), err(plain))


def test_bootstrap_intervals_cover_the_truth_in_most_data_sets():
    covered = []
    for seed in range(10):  # (over 30 data sets: 95 % of the intervals cover)
        states = synthetic_states("so2", seed=10 + seed, n_flights=8, per_flight=150)
        boot = bootstrap_fit("so2", states, n_boot=40, seed=seed)
        covered += [lo <= TRUE["so2"][p] <= hi for p, (lo, hi) in boot.intervals.items()]
        assert len(boot.bootstrap["replicates"]) == 40
    assert np.mean(covered) >= 0.7, covered
    # as wide as the noise makes them: +-1.96 standard errors, within what 40 replicates of 8 flights resolve
    se = _standard_errors("so2", states, TRUE["so2"])
    for p, (lo, hi) in boot.intervals.items():
        assert 0.5 < (hi - lo) / (2 * 1.96 * se[p]) < 2.0, (p, hi - lo, se[p])


def test_refit_on_a_subsample_agrees_with_refit_on_all():
    states = synthetic_states("so2", seed=3, n_flights=10, per_flight=200)
    full = fit_field("so2", states)
    every = bootstrap_fit("so2", states, n_boot=30, seed=1, full=full)
    sub = bootstrap_fit("so2", states, n_boot=30, seed=1, full=full, max_samples=1000)
    assert every.bootstrap["n_informative"] <= len(states) and sub.bootstrap["max_samples"] == 1000
    for p in full.params:  # the subsample adds its scatter: wider, not narrower, and still about the fit
        w_every, w_sub = (b.intervals[p][1] - b.intervals[p][0] for b in (every, sub))
        assert 0.8 * w_every < w_sub < 4 * w_every, (p, sub.intervals, every.intervals)
        assert sub.intervals[p][0] < full.params[p] < sub.intervals[p][1]
    with pytest.raises(ConfigError, match="full: a fit of 'so2' to data"):
        bootstrap_fit("so2", synthetic_states("so2", seed=4, n_flights=2), full=full)


def test_fitted_spec_round_trip(tmp_path):
    states = synthetic_states("so2", seed=5)
    fit = bootstrap_fit("so2", states, n_boot=20)
    path = write_fitted(tmp_path / "so2.json", fit)
    field = resolve_fitted_spec(str(path))
    plain = make_field("so2", **fit.params)
    test = synthetic_states("so2", seed=6, n_flights=2)
    np.testing.assert_array_equal(field_forces(field, test), field_forces(plain, test))
    assert isinstance(field, DownwashField) and field == resolve_fitted_spec(str(path))  # one class per record
    info = describe(field)["fitted"]
    assert info["data_digest"] == states.data_digest and info["base"] == "so2"
    # the digest survives the copies the kinds and the envs make, and pickling
    paired = pair_field(field, get_vehicle(LARGE), get_vehicle(SMALL))
    assert describe(paired)["fitted"] == info
    assert describe(pickle.loads(pickle.dumps(field))) == describe(field)
    # the fused tick still takes it (DownwashField's own pairwise and __call__)
    from sim.plan import _packed_field

    assert _packed_field(field, None) is not None
    loaded = load_fitted(path, data_digest=states.data_digest)
    assert loaded.params == fit.params and loaded.intervals == fit.intervals and loaded.data_digest == fit.data_digest
    assert describe(loaded.make()) == describe(field)  # the file's record, its code version included
    record = json.loads(path.read_text())
    assert {"base", "params", "intervals", "data_digest", "source", "code", "digest"} <= set(record)


def test_fitted_spec_through_the_registry(tmp_path):
    assert parse_field_spec("fitted:x.json") == ("fitted", "x.json", None)
    with pytest.raises(ConfigError, match="expected fitted:PATH"):
        parse_field_spec("fitted:")
    with pytest.raises(ConfigError, match="'fitted' is the spec grammar's"):
        register_field("fitted", make_field, "x", "y")
    fit = fit_field("momentum", synthetic_states("momentum", seed=7, n_flights=3, per_flight=100))
    path = write_fitted(tmp_path / "m.json", fit)
    field = resolve_field_spec(f"fitted:{path}")
    test = synthetic_states("momentum", seed=8, n_flights=1, per_flight=50)
    np.testing.assert_array_equal(field_forces(field, test), field_forces(make_field("momentum", **fit.params), test))


def test_randomization_ranges():
    fit = bootstrap_fit("so2", synthetic_states("so2", seed=9), n_boot=20)
    out = randomization_ranges(fit, spec="fitted:so2.json")
    assert out["field"] == "fitted:so2.json"
    for p, (lo, hi) in out["field_randomization"].items():
        assert ENV_FACTOR_RANGE[0] <= lo < 1.0 < hi <= ENV_FACTOR_RANGE[1]
        assert lo * fit.params[p] == pytest.approx(out["absolute"][p][0])
    momentum = bootstrap_fit("momentum", synthetic_states("momentum", seed=9, n_flights=4, per_flight=80), n_boot=10)
    ranges = randomization_ranges(momentum)  # factors for every field now, not only so2's
    assert set(ranges["field_randomization"]) == set(ranges["absolute"]) == set(momentum.params)
    for p, (lo, hi) in ranges["field_randomization"].items():
        assert ENV_FACTOR_RANGE[0] <= lo <= hi <= ENV_FACTOR_RANGE[1]
        assert (lo * momentum.params[p], hi * momentum.params[p]) == pytest.approx(tuple(ranges["absolute"][p]))
    def with_origin(value, interval):  # a fitted parameter that may be negative or 0: the virtual origin, m
        return dataclasses.replace(momentum, params={**momentum.params, "virtual_origin": value},
                                   intervals={**momentum.intervals, "virtual_origin": interval})

    negative = randomization_ranges(with_origin(-0.5, (-0.6, -0.45)))["field_randomization"]
    assert negative["virtual_origin"] == pytest.approx((0.9, 1.2))  # ordered low, high
    assert randomization_ranges(with_origin(0.0, (-0.1, 0.1)))["field_randomization"] is None  # no factor says it
    with pytest.raises(ConfigError, match="no intervals"):
        randomization_ranges(fit_field("so2", synthetic_states("so2", seed=9, n_flights=2)))


def test_env_scalable_constants_are_the_envs():
    from downwash_envs.config import FIELD_RANDOMIZABLE, FIELD_SCALE_RANGE, FollowerConfig

    assert tuple(ENV_SCALABLE) == tuple(FIELD_RANDOMIZABLE) and tuple(ENV_FACTOR_RANGE) == tuple(FIELD_SCALE_RANGE)
    fit = bootstrap_fit("so2", synthetic_states("so2", seed=11), n_boot=20)
    FollowerConfig(field_randomization=randomization_ranges(fit)["field_randomization"])  # accepted as it is


def test_compare_forces_bins_and_flights():
    states = synthetic_states("so2", seed=12, n_flights=3)
    out = compare_forces(make_field("so2", **TRUE["so2"]), states)
    assert out["rmse"] == pytest.approx(NOISE, rel=0.1) and out["rmse_zero"] > out["rmse"]
    assert [f["n"] for f in out["per_flight"]] == [250] * 3
    bins = out["vertical"]
    assert sum(b["n"] for b in bins) == np.sum(np.linalg.norm(states.p_a[:, :2] - states.p_b[:, :2], axis=1) < 0.35)
    filled = [b for b in bins if b["n"] > 30]
    assert all(abs(b["z_measured"] - b["z_predicted"]) < 4 * NOISE / np.sqrt(b["n"]) + 1e-9 for b in filled)
    json.dumps(out)  # JSON-ready
    with pytest.raises(ConfigError, match="increasing edges"):
        compare_forces(make_field("so2"), states, bins={"vertical": [0.5, 0.2]})
    with pytest.raises(ConfigError, match=r"bins\[.depth.\]"):
        compare_forces(make_field("so2"), states, bins={"depth": [0.0, 1.0]})


def _flight(frames, z, x, seconds=3.0, digest="ab"):
    """A hover of len(frames) vehicles at heights z and x offsets (m) as a real flight's log."""
    grid = np.arange(int(seconds * 100)) / 100.0
    per = []
    for frame, zi, xi in zip(frames, z, x):
        mass = {"small": 0.032, "large": 0.067}[frame]
        pos = np.tile([xi, 0.0, zi], (grid.size, 1))
        per.append(vehicle_arrays(grid, grid, pos=pos, vel=np.zeros_like(pos), quat=np.tile([1.0, 0, 0, 0], (grid.size, 1)),
                                  ref_pos=pos, ref_vel=np.zeros_like(pos), thrust=np.full(grid.size, mass * 9.81),
                                  mass=mass))
    files = [{"file": f"cf{i}", "sha256": digest * 32} for i in range(len(frames))]
    return real_flight(grid, per, {"source": {"format": "test", "files": files}, "frames": list(frames)})


def test_pair_states_of_real_flights():
    class Ref:
        def __init__(self, name):
            self.name = name

    # vehicle 0 over 1 and 2, vehicle 3 over 2 and 0 (over: within 0.35 m laterally): 2 is under two
    # vehicles (dropped); 3 has none above
    z, x = [2.0, 1.4, 1.5, 2.2], [0.0, -0.2, 0.2, 0.3]
    flights = [(Ref("a"), _flight(["small"] * 4, z, x)), (Ref("alone"), _flight(["small"], z=[1.0], x=[0.0]))]
    states = pair_states(flights)
    by_vehicle = {v: np.flatnonzero(states.vehicle == v) for v in range(4)}
    assert by_vehicle[2].size == 0 and all(by_vehicle[v].size for v in (0, 1, 3))
    assert np.allclose(states.p_a[by_vehicle[1]], [0.0, 0.0, 2.0])  # laterally nearest above: 0, not 2 or 3
    assert np.allclose(states.p_a[by_vehicle[0]], [0.3, 0.0, 2.2])
    assert np.allclose(states.p_a[by_vehicle[3]], [0.0, 0.0, 2.0])  # none above: the nearest
    assert states.kinds == (SMALL,) and set(states.flight) == {0} and len(states.flight_names) == 2
    assert np.allclose(states.y, 0.0, atol=1e-9)  # a steady hover at m g: no residual
    assert pair_states(flights, stride=3).data_digest != states.data_digest
    other = [(flights[0][0], _flight(["small"] * 4, z, x, digest="cd"))]
    assert pair_states(other).data_digest != pair_states(flights[:1]).data_digest
    with pytest.raises(DataError, match="no labelled sample with another vehicle"):
        pair_states(flights[1:])
    bare = _flight(["small"] * 2, [2.0, 1.4], [0.0, 0.0])
    bare.meta["source"] = {"format": "test"}
    with pytest.raises(DataError, match="no source digests"):
        pair_states([(Ref("bare"), bare)])


def test_bad_input_is_named(tmp_path):
    states = synthetic_states("so2", seed=13, n_flights=2, per_flight=50)
    with pytest.raises(ConfigError, match="unknown name 'nope'"):
        fit_field("nope", states)
    with pytest.raises(ConfigError, match="'n_rotors' is int, not float"):
        fit_field("momentum", states, params=["n_rotors"])
    with pytest.raises(ConfigError, match="'leader_mass' is set by the vehicle kinds"):
        fit_field("momentum", states, params=["leader_mass"])
    with pytest.raises(ConfigError, match="has memory"):
        fit_field("shed", states)
    with pytest.raises(ConfigError, match=r"bounds\['width0'\]"):
        fit_field("so2", states, bounds={"width0": (0.2, 0.1)})
    with pytest.raises(ConfigError, match="loss .l2., f_scale 1.0: allowed"):
        fit_field("so2", states, loss="l2")
    with pytest.raises(DataError, match="no samples"):
        fit_field("so2", states.subset(np.zeros(len(states), bool)))
    with pytest.raises(DataError, match="1 flight"):
        bootstrap_fit("so2", states.subset(states.flight == 0))
    with pytest.raises(ConfigError, match=r"PairStates.R_a: expected shape \(100, 3, 3\)"):
        PairStates(**{**_fields(states), "R_a": np.zeros((100, 3))})
    path = write_fitted(tmp_path / "f.json", bootstrap_fit("so2", states, n_boot=10))
    record = json.loads(path.read_text())
    edited = {**record, "params": {**record["params"], "strength": 1.0}}
    (tmp_path / "edited.json").write_text(json.dumps(edited))
    with pytest.raises(DataError, match="digest mismatch"):
        resolve_fitted_spec(str(tmp_path / "edited.json"))
    (tmp_path / "missing.json").write_text(json.dumps({k: v for k, v in record.items() if k != "data_digest"}))
    with pytest.raises(DataError, match=r"missing key\(s\) \['data_digest'\]"):
        load_fitted(tmp_path / "missing.json")
    with pytest.raises(DataError, match="not the data asked for"):
        load_fitted(path, data_digest="0" * 64)
    with pytest.raises(DataError, match="cannot read"):
        resolve_fitted_spec(str(tmp_path / "absent.json"))
    with pytest.raises(ConfigError, match="fitted:PATH"):
        resolve_fitted_spec(" ")
    with pytest.raises(ConfigError, match="expected a FittedField"):
        write_fitted(tmp_path / "x.json", record)
    assert isinstance(load_fitted(path), FittedField)
