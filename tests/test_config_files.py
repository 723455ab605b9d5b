"""Config files: tables of the library's settings, arrays for list options, precedence, and the resolved
config.toml every run writes, which `--config` reruns to the same results.

The tables' keys are static copies (`experiments.config_file.TABLES`, so that a bad file answers
before the heavy imports): the first tests tie them to the settings classes they map onto.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from experiments import common, components, config_file
from experiments.common import ConfigError, parse_args
from experiments.config_file import RESERVED, TABLES, dumps, list_separator, read_file

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "numba", "mujoco", "matplotlib", "ray")
QUICK_FLIGHT = ["--quick", "--conditions", "baseline,oracle"]  # two conditions, no model: no collection, no training
# results.json keys that differ between two runs of the same config: where it was written, how long it took,
# and the code version (the checkout may change between the runs)
RUN_SPECIFIC = {("args", "out"), ("wall_seconds",), ("flight_wall_seconds",), ("provenance", "code")}


def _lemniscate_args():
    from experiments.tracking import args_class

    return args_class("lemniscate")


def _toml(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _usage_error(capsys, cls, name: str, argv: list[str]) -> str:
    with pytest.raises(SystemExit) as e:
        parse_args(cls, name, argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


# ----------------------------------------------------------------------------- the tables' static copies


def test_each_table_maps_onto_the_fields_of_its_settings_class():
    from controllers.lqr import LQRConfig
    from downwash.guard import GUARD_DEFAULTS, GuardedPredictor
    from downwash.train import TrainConfig
    from sim.simulator import SimConfig

    classes = {"lqr": LQRConfig, "sim": SimConfig, "training": TrainConfig}
    for name, cls in classes.items():
        table = TABLES[name]
        assert table.source == f"{cls.__module__}.{cls.__name__}"
        fields = [f.name for f in dataclasses.fields(cls)]
        assert sorted([*table.keys, *table.left_out]) == sorted(fields), name
        assert not set(table.keys) & set(table.left_out), name
        defaults = cls()
        for key, spec in table.keys.items():
            value = getattr(defaults, key)
            if value is None:  # unset by default (training's lr, num_threads): the key takes the number
                continue
            if spec.kind is tuple:
                assert len(value) == spec.length, (name, key)
            else:
                assert type(value) is spec.kind, (name, key, type(value))
        given_defaults = {k: (list(map(float, v)) if isinstance(v, tuple) else v)
                          for k in table.keys if (v := getattr(defaults, k)) is not None}
        assert config_file.check_table(name, given_defaults)  # every default lies within the copy's range
    plain = [f.name for f in dataclasses.fields(SimConfig)
             if isinstance(getattr(SimConfig(), f.name), (int, float, str, bool))]
    assert sorted(TABLES["sim"].keys) == sorted(plain)  # [sim]: exactly the plain numbers
    assert list(TABLES["guard"].keys) == list(GUARD_DEFAULTS)
    guard_keywords = set(inspect.signature(GuardedPredictor).parameters)
    assert set(TABLES["guard"].keys) | set(TABLES["guard"].left_out) <= guard_keywords
    assert TABLES["guard"].source == "downwash.guard.GuardedPredictor"


def test_the_safety_table_maps_onto_the_safety_layer_and_needs_safety_on():
    """[safety] sets `sim.safety.SafetyConfig` (every key one of its fields) and turns the layer on, as --safety does."""
    import dataclasses

    from experiments.tracking import args_class
    from sim.safety import SafetyConfig

    assert "safety" in TABLES and not RESERVED
    assert set(TABLES["safety"].keys) == {f.name for f in dataclasses.fields(SafetyConfig)}
    cls = args_class("lemniscate")
    assert components.safety_config(cls()) is None
    assert components.safety_config(cls(safety=True)) == SafetyConfig()
    on = cls(safety=True, tables={"safety": {"inflation": 2.0, "k1": 20.0}})
    assert components.safety_config(on) == SafetyConfig(inflation=2.0, k1=20.0)
    assert components.flight_components(on)["safety"] == SafetyConfig(inflation=2.0, k1=20.0)
    # a [safety] table turns it on (TOML cannot hold safety = true beside it), and the config written says so
    assert components.safety_config(cls(tables={"safety": {"inflation": 2.0}})) == SafetyConfig(inflation=2.0)
    text = dumps({}, {"safety": {"inflation": 2.0}}, "")
    assert "[safety]" in text and "safety = " not in text
    with pytest.raises(ConfigError, match=r"\[safety\]: SafetyConfig.k1"):  # the class's own check, named by table
        components.safety_config(cls(safety=True, tables={"safety": {"k0": 100.0, "k1": 1.0}}))


def test_the_range_of_each_table_is_the_settings_class_own():
    """A value the static copy refuses, the class refuses too (or cannot fly): the copy is no stricter
    than needed, and what it lets through the class takes."""
    from controllers.lqr import FeedbackLinearisedLQR, LQRConfig
    from downwash.train import TrainConfig

    for bad in ({"max_tilt_deg": 90.0}, {"min_thrust_g": 1.0}):
        with pytest.raises(ConfigError):
            LQRConfig(**bad)
        with pytest.raises(ConfigError):
            config_file.check_table("lqr", bad)
    with pytest.raises(ConfigError):
        FeedbackLinearisedLQR(LQRConfig(r=(0.0, 0.8, 0.8, 1.0)))  # R must be definite
    for bad in ({"lr_final": 0.0}, {"val_fraction": 1.0}, {"batch_size": 0}, {"min_delta": 1.0}):
        with pytest.raises(ValueError):
            TrainConfig(**bad)
        with pytest.raises(ConfigError):
            config_file.check_table("training", bad)


# ----------------------------------------------------------------------------- reading tables


def test_tables_are_read_checked_and_normalised(tmp_path):
    path = _toml(tmp_path, 'seeds = 2\n[lqr]\nq = [1, 1, 8, 0.01, 0.01, 0.1, 1]\nmax-tilt-deg = 30\n'
                           '[sim]\nground_clearance = 0\nnoise_block = 64\n')
    args = parse_args(_lemniscate_args(), "lemniscate", ["--config", str(path), "--out", str(tmp_path / "o")])
    assert args.seeds == 2
    assert args.tables == {"lqr": {"q": (1.0, 1.0, 8.0, 0.01, 0.01, 0.1, 1.0), "max_tilt_deg": 30.0},
                           "sim": {"ground_clearance": 0.0, "noise_block": 64}}
    assert type(args.tables["lqr"]["max_tilt_deg"]) is float and type(args.tables["sim"]["noise_block"]) is int
    lqr, sim = components.lqr_config(args), components.sim_config(args)
    assert lqr.max_tilt_deg == 30.0 and lqr.q[2] == 8.0 and lqr.min_thrust_g == 0.25  # the rest: defaults
    assert sim.ground_clearance == 0.0 and sim.noise_block == 64 and sim.max_distance == 100.0
    assert components.flight_components(args)["controller"].config == lqr


@pytest.mark.parametrize("text, expected", [
    ("[lqr]\nmax_tilt = 30\n", ["[lqr] unknown key 'max_tilt'", "allowed: q, r, max_tilt_deg, min_thrust_g"]),
    ("[sim]\nrates = 1\n", ["[sim] unknown key 'rates' (not a plain number)", "allowed: ground_clearance"]),
    ('[lqr]\nmax_tilt_deg = "30"\n', ["[lqr] max_tilt_deg = '30': expected a number, got a TOML string",
                                      "controllers.lqr.LQRConfig.max_tilt_deg"]),
    ("[lqr]\nmax_tilt_deg = true\n", ["expected a number, got a TOML boolean"]),
    ("[lqr]\nq = [1, 2]\n", ["[lqr] q = [1, 2]: expected an array of 7 numbers, got 2 items"]),
    ("[lqr]\nq = 1.0\n", ["expected an array of 7 numbers, got a TOML float"]),
    ('[lqr]\nr = [0.8, 0.8, "a", 1]\n', ["expected an array of 4 numbers"]),
    ("[lqr]\nr = [0.8, 0.8, 0, 1]\n", ["[lqr] r = [0.8, 0.8, 0, 1]: expected each a finite number > 0"]),
    ("[lqr]\nmax_tilt_deg = 95\n", ["[lqr] max_tilt_deg = 95: expected a finite number in (0, 90)"]),
    ("[lqr]\nmax_tilt_deg = nan\n", ["expected a finite number in (0, 90)"]),
    ("[sim]\nnoise_block = 2.5\n", ["[sim] noise_block = 2.5: expected an integer, got a TOML float"]),
    ("[sim]\nnoise_block = 0\n", ["expected an integer in [1, 4096]"]),
    ("[sim]\nmax_distance = " + "9" * 400 + "\n", ["expected a finite number > 0"]),
    ("[lqr]\nmax_tilt_deg = 30\nmax-tilt-deg = 31\n", ["[lqr] key 'max-tilt-deg' given twice"]),
    ("lqr = 3\n", ["lqr = 3: expected a table [lqr] of controllers.lqr.LQRConfig settings, got a TOML integer"]),
    ("[lqr]\n[lqr.inner]\nx = 1\n", ["[lqr] unknown key 'inner'"]),
    ("[guard]\nbound = 0\n", ["[guard] bound = 0: expected a finite number > 0"]),
    ("[guard]\nrecover = 2\n", ["[guard] unknown key 'recover'", "allowed: recovery, bound"]),
    ("[training]\nmax_epochs = 5\n", ["[training]: this experiment does not apply downwash.train.TrainConfig",
                                     "refused rather than ignored", "the tables it applies: [lqr], [sim], [guard], [safety]"]),
    ("[safety]\nmin_separation = 0.3\n", ["[safety] unknown key 'min_separation'", "allowed: inflation"]),
    ("[controller]\nq = 1\n", ["controller = {'q': 1}: expected a string, got a TOML table", "--controller"]),
])
def test_a_bad_table_is_one_line_naming_the_table_the_key_and_what_is_allowed(tmp_path, capsys, text, expected):
    path = _toml(tmp_path, text)
    err = _usage_error(capsys, _lemniscate_args(), "lemniscate", ["--config", str(path), "--out", str(tmp_path / "o")])
    assert f"--config {path}: " in err
    for part in expected:
        assert part in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("module, cls_name, text, applies", [
    ("staged_collection", "StagedArgs", "[lqr]\nmax_tilt_deg = 30\n", "none"),
    ("staged_collection", "StagedArgs", "[training]\nmax_epochs = 5\n", "none"),
    ("fields", "FieldsArgs", "[sim]\nnoise_block = 64\n", "none"),
    ("sweep", "SweepArgs", "[guard]\nbound = 5\n", "[training]"),
    ("train", "TrainArgs", "[lqr]\nmax_tilt_deg = 30\n", "[training]"),
    ("sample_efficiency", "EfficiencyArgs", "[guard]\nbound = 5\n", "[training]"),
    ("outdoor", "OutdoorArgs", "[training]\nmax_epochs = 5\n", "[lqr], [sim], [guard], [safety]"),
    ("swarm", "SwarmArgs", "[training]\nlr = 0.001\n", "[lqr], [sim], [guard], [safety]"),
    ("staged_collection", "StagedArgs", "[safety]\nk0 = 1\n", "none"),
])
def test_each_experiment_refuses_the_tables_it_does_not_apply(tmp_path, capsys, module, cls_name, text, applies):
    import importlib

    cls = getattr(importlib.import_module(f"experiments.{module}"), cls_name)
    err = _usage_error(capsys, cls, module, ["--config", str(_toml(tmp_path, text)), "--out", str(tmp_path / "o")])
    assert "refused rather than ignored" in err and err.endswith(f"the tables it applies: {applies}"), err


def test_a_bad_table_stops_the_script_before_any_work_or_heavy_import(tmp_path):
    _toml(tmp_path, 'out = "o"\n[lqr]\nmax_tilt_deg = 120\n')
    code = ("import sys, runpy; sys.argv = ['lemniscate', '--config', 'c.toml']\n"
            "try:\n    runpy.run_module('experiments.lemniscate', run_name='__main__')\n"
            "finally:\n    print('HEAVY=' + ','.join(m for m in %r if m in sys.modules), file=sys.stderr)\n" % (HEAVY,))
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    *lines, heavy = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-3000:]
    assert "[lqr] max_tilt_deg = 120: expected a finite number in (0, 90)" in lines[0], lines[0]
    assert heavy == "HEAVY=", heavy
    assert sorted(os.listdir(tmp_path)) == ["c.toml"]


def test_tables_built_in_python_are_checked_and_a_table_not_applied_is_refused():
    from experiments.train import TrainArgs

    cls = _lemniscate_args()
    with pytest.raises(ConfigError, match=r"\[lqr\] max_tilt_deg = 95: expected a finite number in \(0, 90\)"):
        common.check_options(cls(tables={"lqr": {"max_tilt_deg": 95}}))
    with pytest.raises(ConfigError, match=r"\[training\]: this experiment does not apply"):
        common.check_options(cls(tables={"training": {"max_epochs": 5}}))
    with pytest.raises(ConfigError, match="unknown table 'lqrs'"):
        common.check_options(cls(tables={"lqrs": {}}))
    with pytest.raises(ConfigError, match=r"\[lqr\]: this experiment does not apply"):
        components.lqr_config(TrainArgs())  # an experiment asking for a table it does not declare
    assert components.lqr_config(cls(tables={"lqr": {"min_thrust_g": 0.5}})).min_thrust_g == 0.5


def test_the_builders_apply_the_training_and_guard_tables():
    from downwash.guard import GUARD_DEFAULTS
    from downwash.staged import train_config
    from experiments.sample_efficiency import EfficiencyArgs, grid_of
    from experiments.swarm import SwarmArgs
    from experiments.train import TrainArgs

    args = TrainArgs(seed=4, quick=True, tables={"training": {"max_epochs": 7, "lr": 0.002, "portable": True}})
    assert components.training_config(args) == dataclasses.replace(train_config(4, True), max_epochs=7, lr=0.002)
    assert components.training_config(TrainArgs(seed=4)) == train_config(4, False)
    grid = grid_of(EfficiencyArgs(seed=3, quick=True, trials=2, tables={"training": {"batch_size": 64}}))
    assert [grid.config(s).batch_size for s in grid.seeds] == [64, 64] and grid.config(5).seed == 5
    assert grid.config(5) == dataclasses.replace(train_config(5, True), batch_size=64)
    assert components.guard_config(SwarmArgs(tables={"guard": {"bound": 4.0, "skeptic": math.inf}})) == {
        **GUARD_DEFAULTS, "bound": 4.0, "skeptic": math.inf}


def test_train_trains_with_the_training_table(tmp_path, monkeypatch):
    """experiments.train hands train_model the [training] settings (the data loading stubbed out)."""
    import downwash.datasets
    import downwash.train
    from experiments.train import TrainArgs, run

    class Trained(Exception):
        pass

    def train_model(kind, train, val, config, **kw):
        raise Trained(config)

    monkeypatch.setattr(downwash.datasets, "load_dataset", lambda *a, **k: SimpleNamespace(provenance={}))
    monkeypatch.setattr(downwash.datasets, "find_logs", lambda *a, **k: [])
    monkeypatch.setattr(downwash.train, "train_model", train_model)
    (tmp_path / "logs").mkdir()
    args = TrainArgs(out=str(tmp_path / "o"), seed=2, logs=str(tmp_path / "logs"), val_logs=str(tmp_path / "logs"),
                     tables={"training": {"max_epochs": 9, "weight_decay": 0.001}})
    with pytest.raises(Trained) as e:
        run(args)
    config = e.value.args[0]
    assert (config.max_epochs, config.weight_decay, config.seed, config.min_steps) == (9, 0.001, 2, 1500)


def test_swarm_guards_its_conditions_with_the_guard_table(monkeypatch):
    """experiments.swarm builds its guarded conditions with the [guard] settings (the models stubbed out)."""
    import downwash.checkpoint
    import downwash.conditions
    import downwash.predictor
    from experiments.swarm import SwarmArgs, _predictors

    made = []
    monkeypatch.setattr(downwash.checkpoint, "wrap_pairwise", lambda *a, **k: "pairwise")
    monkeypatch.setattr(downwash.predictor, "LearnedPredictor", lambda model, **k: ("learned", model))
    # the one condition-to-predictor factory the swarm uses (downwash.conditions.make_predictor) guards with it
    monkeypatch.setattr(downwash.conditions, "GuardedPredictor", lambda p, **kw: made.append(kw) or ("guarded", p))
    guard = components.guard_config(SwarmArgs(tables={"guard": {"recovery": 2.0}}))
    out = _predictors(["baseline", "summed_pairwise", "summed_pairwise_guarded"], None, None,
                      {"summed_pairwise": Path("p.pt")}, None, guard)
    assert out[2] == ("guarded", ("learned", "pairwise")) and made == [guard] and guard["recovery"] == 2.0


# what a tracking run wrote before it applied [guard]: a default run keeps these keys
TRACKING_KEYS = {"args", "experiment", "separation", "duration", "seeds", "conditions", "guard", "wall_seconds",
                 "flight_wall_seconds", "provenance"}


def test_the_lemniscate_guards_its_conditions_with_the_guard_table(tmp_path, monkeypatch):
    """[guard] reaches every GuardedPredictor of a lemniscate run and its results; without the table the
    guard flies its defaults, and the results keep their keys, record and pipeline key (the model and
    the guard stubbed out: no collection, no training)."""
    import downwash.conditions
    import downwash.staged
    from downwash.guard import GUARD_DEFAULTS, GuardedPredictor, guard_settings
    from experiments.lemniscate import main
    from sim.predictor import ZeroPredictor

    made: list[dict] = []
    monkeypatch.setattr(downwash.staged, "ensure_models", lambda d, kinds, *a, **k: {c: Path(f"{c}.pt") for c in kinds})
    monkeypatch.setattr(downwash.conditions, "LearnedPredictor",
                        SimpleNamespace(from_checkpoint=lambda path, **k: ("learned", path)))
    monkeypatch.setattr(downwash.conditions, "GuardedPredictor", lambda p, **kw: made.append(kw) or ZeroPredictor())
    monkeypatch.setattr(downwash.conditions, "kinds_in_data", lambda conditions, *a: {})  # (no checkpoint to read)
    monkeypatch.chdir(tmp_path)
    flight = ["--quick", "--conditions", "baseline,equivariant_guarded"]
    main([*flight, "--out", "default"])
    assert made == [GUARD_DEFAULTS]  # the GuardedPredictor's own defaults: default runs fly the same bits
    defaults = inspect.signature(GuardedPredictor).parameters
    assert all(defaults[k].default == v for k, v in GUARD_DEFAULTS.items())
    made.clear()
    _toml(tmp_path, "[guard]\nrecovery = 2.0\nbound = 4\n", "guard.toml")
    main(["--config", "guard.toml", *flight, "--out", "guarded"])
    assert made == [{**GUARD_DEFAULTS, "recovery": 2.0, "bound": 4.0}]
    default, guarded = (json.loads(Path(f"{d}/results.json").read_text()) for d in ("default", "guarded"))
    assert set(default) == set(guarded) == TRACKING_KEYS
    assert default["guard"] == guard_settings()  # the record as before
    assert guarded["guard"] == {**guard_settings(), "recovery": 2.0, "bound": 4.0}
    assert default["args"]["tables"]["guard"] == GUARD_DEFAULTS  # resolved, as every applied table
    assert guarded["args"]["tables"]["guard"] == {**GUARD_DEFAULTS, "recovery": 2.0, "bound": 4.0}
    assert tomllib.loads(Path("guarded/config.toml").read_text())["guard"]["recovery"] == 2.0
    assert default["provenance"]["pipeline_key"] == guarded["provenance"]["pipeline_key"]
    assert _without(default, RUN_SPECIFIC | {("args",), ("guard",)}) == _without(guarded, RUN_SPECIFIC | {
        ("args",), ("guard",)})  # (the stub flies no model: the same flights)


def test_transect_and_outdoor_take_the_guard_table(tmp_path):
    from experiments.outdoor import OutdoorArgs
    from experiments.tracking import args_class

    path = _toml(tmp_path, "[guard]\nskeptic = inf\nmonitor = 0.5\n")
    for cls, name in ((args_class("transect"), "transect"), (OutdoorArgs, "outdoor")):
        args = parse_args(cls, name, ["--config", str(path), "--out", str(tmp_path / "o")])
        assert components.guard_config(args) == {**components.guard_config(cls()), "skeptic": math.inf, "monitor": 0.5}


def test_the_sweep_trains_its_cells_with_the_training_table(tmp_path, monkeypatch):
    """[training] reaches the grid the sweep runs; without it the cells' settings, and so their cache
    keys, are those of the grid it built before."""
    import downwash.sweep
    from downwash.staged import train_config
    from downwash.sweep import grid_from_text
    from experiments import sweep

    class Swept(Exception):
        pass

    def run_sweep(grid, *a, **k):
        raise Swept(grid)

    path = _toml(tmp_path, 'seeds = [3, 4]\nmodels = ["equivariant"]\nminutes = [1]\n'
                           "[training]\nmax_epochs = 7\nbatch_size = 64\n")
    args = parse_args(sweep.SweepArgs, "sweep", ["--config", str(path), "--quick", "--out", str(tmp_path / "o"),
                                                 "--cache-dir", str(tmp_path / "cells")])
    monkeypatch.setattr(sweep, "resolve_pipeline", lambda a: None)
    monkeypatch.setattr(downwash.sweep, "run_sweep", run_sweep)
    with pytest.raises(Swept) as e:
        sweep.run(args)
    grid = e.value.args[0]
    assert grid.config(4) == dataclasses.replace(train_config(4, True), max_epochs=7, batch_size=64)
    plain = dataclasses.replace(args, tables={})
    before = grid_from_text(plain.field, plain.models, plain.minutes, plain.seeds, plain.quick)
    assert before.training is None
    assert [sweep.grid_of(plain).config(s) for s in (3, 4)] == [before.config(s) for s in (3, 4)]
    assert sweep.grid_of(plain).describe() == before.describe()


# ----------------------------------------------------------------------------- arrays for list options


def test_a_list_option_takes_an_array_joined_with_its_separator(tmp_path):
    from experiments.outdoor import OutdoorArgs
    from experiments.sweep import SweepArgs

    path = _toml(tmp_path, 'models = ["equivariant", "deep"]\nseeds = [0, 1, 2]\nminutes = [1, 2.5]\n'
                           'field = ["so2", "momentum:thrust_scale=1.2"]\n')
    args = parse_args(SweepArgs, "sweep", ["--config", str(path), "--out", str(tmp_path / "o")])
    assert (args.models, args.seeds, args.minutes, args.field) == (
        "equivariant,deep", "0,1,2", "1,2.5", "so2;momentum:thrust_scale=1.2")
    path = _toml(tmp_path, 'conditions = ["baseline", "oracle"]\nsweep_winds = ["off", "light:mean=2,0,0"]\n'
                           'sweep_speeds = [1, 1.5]\ntrained = ["indoor"]\n')
    args = parse_args(OutdoorArgs, "outdoor", ["--config", str(path), "--out", str(tmp_path / "o")])
    assert (args.conditions, args.sweep_winds, args.sweep_speeds, args.trained) == (
        "baseline,oracle", "off;light:mean=2,0,0", "1,1.5", "indoor")
    # the flag still wins, and the joined list is checked as the flag's string is
    args = parse_args(SweepArgs, "sweep", ["--config", str(path := _toml(tmp_path, "seeds = [4, 5]\n")),
                                           "--seeds", "7", "--out", str(tmp_path / "o")])
    assert args.seeds == "7"


@pytest.mark.parametrize("text, expected", [
    ('conditions = ["baseline", "nonsense"]\n', ["--conditions: unknown ['nonsense']", "(from --config"]),
    ("conditions = [[\"baseline\"]]\n", ["expected a string or an array of strings and numbers (joined with ',')",
                                         "got a TOML array"]),
    ("conditions = [true]\n", ["expected a string or an array of strings and numbers"]),
    ("seeds = [1, 2]\n", ["seeds = [1, 2]: expected an integer, got a TOML array", "--seeds"]),
    ("separation = [0.5]\n", ["expected a number, got a TOML array", "--separation"]),
    ('wind = ["light"]\n', ["expected a string, got a TOML array", "--wind"]),
])
def test_an_array_where_no_list_is_taken_or_a_bad_item_is_refused(tmp_path, capsys, text, expected):
    path = _toml(tmp_path, text)
    err = _usage_error(capsys, _lemniscate_args(), "lemniscate", ["--config", str(path), "--out", str(tmp_path / "o")])
    for part in expected:
        assert part in err, err


def _args_classes() -> list[type]:
    import importlib

    from experiments.tracking import TRACKS, args_class

    classes = [args_class(t) for t in TRACKS]
    for name in ("staged_collection", "sample_efficiency", "sweep", "force_maps", "train", "fields", "outdoor", "swarm",
                 "benchmark", "vehicles", "real_flights"):
        module = importlib.import_module(f"experiments.{name}")
        classes += [obj for obj in vars(module).values() if isinstance(obj, type) and dataclasses.is_dataclass(obj)
                    and issubclass(obj, common.CommonArgs) and obj.__module__ == module.__name__]
    return classes


def test_every_option_of_several_values_takes_an_array_of_its_default(tmp_path):
    """An option is a list when its help says so (a comma list, or ';'-separated); an array of its
    default's items reads back as its default."""
    seen = 0
    for cls in _args_classes():
        for f in common.option_fields(cls):
            text = f.metadata.get("help", "")
            sep = list_separator(f)
            assert (sep is not None) == (common.option_type(f) is str and ("comma list" in text or "';'" in text)), f.name
            if sep is None or not f.default:
                continue
            items = ", ".join(json.dumps(x) for x in f.default.split(sep))
            values, _ = read_file(_toml(tmp_path, f"{f.name} = [{items}]\n"), cls)
            assert values == {f.name: f.default}, (cls.__name__, f.name)
            seen += 1
    assert seen >= 10


# ----------------------------------------------------------------------------- precedence


def test_flags_override_the_file_and_the_file_overrides_the_defaults(tmp_path):
    cls = _lemniscate_args()
    defaults = parse_args(cls, "lemniscate", ["--out", str(tmp_path / "o")])
    path = _toml(tmp_path, 'seeds = 3\nseparation = 0.8\nconditions = ["baseline", "oracle"]\nquick = true\n'
                           '[lqr]\nmax_tilt_deg = 25\n')
    from_file = parse_args(cls, "lemniscate", ["--config", str(path), "--out", str(tmp_path / "o")])
    both = parse_args(cls, "lemniscate", ["--separation", "0.7", "--config", str(path), "--no-quick",
                                          "--conditions", "oracle", "--out", str(tmp_path / "o")])
    assert (defaults.seeds, defaults.separation, defaults.quick, defaults.tables) == (10, 0.6, False, {})
    assert (from_file.seeds, from_file.separation, from_file.conditions, from_file.quick) == (3, 0.8, "baseline,oracle",
                                                                                             True)
    assert from_file.duration == 2.0  # --quick (from the file) fills what neither gives
    assert (both.seeds, both.separation, both.conditions, both.quick, both.duration) == (3, 0.7, "oracle", False, 0.0)
    assert both.half_width == defaults.half_width == 0.5 and both.tables == {"lqr": {"max_tilt_deg": 25.0}}
    assert components.lqr_config(defaults).max_tilt_deg == 35.0 and components.lqr_config(both).max_tilt_deg == 25.0


# ----------------------------------------------------------------------------- writing config.toml


def test_the_writer_round_trips_what_options_and_tables_hold():
    values = {"text": 'a "quoted" \\ path\twith\nlines \x00\x7f é ✓', "empty": "", "n": -3, "big": 2**63 - 1,
              "x": 0.1, "tiny": 5e-324, "huge": 1.7976931348623157e308, "neg": -0.0, "yes": True, "no": False,
              "list": [1.0, 2.5, 1e-7], "odd key": 1}
    tables = {"lqr": {"q": [1.0, 1.0, 8.0, 0.01, 0.01, 0.1, 1.0], "max_tilt_deg": 35.0}, "guard": {"skeptic": math.inf}}
    data = tomllib.loads(dumps(values, tables, "a header\nof two lines"))
    assert data == {**values, **tables}
    assert math.copysign(1.0, data["neg"]) == -1.0 and type(data["n"]) is int and type(data["x"]) is float


_TEXT = st.text(st.characters(blacklist_categories=("Cs",)))  # any text but lone surrogates (no UTF-8)


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(_TEXT.filter(bool), st.one_of(_TEXT, st.integers(-2**63, 2**63 - 1), st.floats(allow_nan=False),
                                                     st.booleans(), st.lists(st.floats(allow_nan=False), max_size=4)),
                       max_size=6))
def test_the_writer_round_trips_any_such_values(values):
    assert tomllib.loads(dumps(values)) == values


def test_a_value_config_toml_cannot_hold_is_refused_before_any_work(tmp_path, capsys):
    """A path with bytes that are no UTF-8 (from the command line) cannot go into a TOML file."""
    out = str(tmp_path / "o\udcff")
    err = _usage_error(capsys, _lemniscate_args(), "lemniscate", ["--out", out])
    assert "--out:" in err and "config.toml (UTF-8 TOML) cannot hold it" in err, err
    assert sorted(os.listdir(tmp_path)) == []


def test_config_toml_goes_beside_the_run_results_only(tmp_path):
    from experiments.fields import FieldsArgs

    args = FieldsArgs(out=str(tmp_path / "run"))
    common.write_results(tmp_path / "run" / "part", {}, args)  # a folder per part (the swarm's presets)
    assert not (tmp_path / "run" / "part" / "config.toml").exists()
    common.write_results(tmp_path / "run", {}, args)
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["config.toml", "part", "results.json"]
    assert tomllib.loads((tmp_path / "run" / "config.toml").read_text()) == {
        "out": str(tmp_path / "run"), "seed": 0, "quick": False, "field": "", "run": False, "only": "", "fresh": False}
    assert "tables" not in json.loads((tmp_path / "run" / "results.json").read_text())["args"]


def _without(record: dict, paths: set[tuple[str, ...]]) -> dict:
    out = json.loads(json.dumps(record))
    for path in paths:
        node = out
        for key in path[:-1]:
            node = node.get(key, {})
        node.pop(path[-1], None)
    return out


def test_a_run_reruns_from_its_config_toml_to_the_same_results(tmp_path, monkeypatch):
    """lemniscate --quick (two conditions without a model: no collection) into A; then --config A/config.toml
    into B: the same results, apart from the folder, the timings and the code version."""
    from experiments.lemniscate import main

    monkeypatch.chdir(tmp_path)
    main([*QUICK_FLIGHT, "--separation", "0.7", "--out", "A"])
    a_config = tomllib.loads(Path("A/config.toml").read_text())
    assert a_config["separation"] == 0.7 and a_config["quick"] is True and a_config["seeds"] == 1
    assert a_config["duration"] == 2.0  # what --quick gave, resolved
    assert a_config["lqr"]["max_tilt_deg"] == 35.0 and a_config["sim"]["noise_block"] == 256  # the defaults
    assert not [p for p in Path("A").iterdir() if p.name.startswith(".")]  # written atomically: no temporary left
    main(["--config", "A/config.toml", "--out", "B"])
    a, b = (json.loads(Path(f"{d}/results.json").read_text()) for d in "AB")
    assert a["args"]["out"] == "A" and b["args"]["out"] == "B"
    assert _without(a, RUN_SPECIFIC) == _without(b, RUN_SPECIFIC)
    assert a["args"]["tables"] == {k: a_config[k] for k in ("lqr", "sim", "guard")}
    b_config = tomllib.loads(Path("B/config.toml").read_text())
    assert b_config == {**a_config, "out": "B"}


def test_the_tables_change_the_flights(tmp_path, monkeypatch):
    """[lqr] and [sim] reach the lemniscate's flights: other weights fly other errors, and a ground
    clearance above the vehicles ends every flight at once."""
    from experiments.lemniscate import main

    monkeypatch.chdir(tmp_path)
    main([*QUICK_FLIGHT, "--out", "default"])
    _toml(tmp_path, "[lqr]\nq = [0.2, 0.2, 0.5, 0.01, 0.01, 0.1, 1]\n", "soft.toml")
    main(["--config", "soft.toml", *QUICK_FLIGHT, "--out", "soft"])
    _toml(tmp_path, "[sim]\nground_clearance = 3.0\n", "ground.toml")
    main(["--config", "ground.toml", *QUICK_FLIGHT, "--out", "ground"])
    default, soft, ground = (json.loads(Path(f"{d}/results.json").read_text()) for d in ("default", "soft", "ground"))
    for c in ("baseline", "oracle"):
        assert soft["conditions"][c]["pos_err_3d_mean"] != default["conditions"][c]["pos_err_3d_mean"]
        assert default["conditions"][c]["crash_rate"] == 0.0 and ground["conditions"][c]["crash_rate"] == 1.0
    assert soft["args"]["tables"]["lqr"]["q"] == [0.2, 0.2, 0.5, 0.01, 0.01, 0.1, 1.0]
    assert soft["args"]["tables"]["sim"] == default["args"]["tables"]["sim"]
    assert tomllib.loads(Path("ground/config.toml").read_text())["sim"]["ground_clearance"] == 3.0


def test_a_listing_reruns_from_its_config_toml(tmp_path, monkeypatch):
    """An experiment that applies no table writes its options alone, and reruns from them."""
    from experiments.fields import main

    monkeypatch.chdir(tmp_path)
    main(["--seed", "3", "--field", "so2:strength=8", "--out", "A"])
    config = tomllib.loads(Path("A/config.toml").read_text())
    assert config["field"] == "so2:strength=8" and not any(isinstance(v, dict) for v in config.values())  # no table
    main(["--config", "A/config.toml", "--out", "B"])
    a, b = (json.loads(Path(f"{d}/results.json").read_text()) for d in "AB")
    assert _without(a, RUN_SPECIFIC) == _without(b, RUN_SPECIFIC) and b["args"]["seed"] == 3


def test_help_names_the_tables_an_experiment_applies():
    text = " ".join(common.build_parser(_lemniscate_args(), "lemniscate").format_help().split())
    assert "tables: [lqr], [sim], [guard]" in text and "config.toml" in text
    from experiments.staged_collection import StagedArgs

    assert "tables:" not in " ".join(common.build_parser(StagedArgs, "staged_collection").format_help().split())


def test_a_comma_list_option_is_its_stripped_items_and_a_non_number_is_named():
    """The one reading of an option's comma list (`experiments.options.comma_items`, `comma_numbers`)."""
    from experiments.options import comma_items, comma_numbers

    assert comma_items(" so2, momentum ,,shed,") == ["so2", "momentum", "shed"] and comma_items(" , ") == []
    assert comma_numbers("0.5, 2,1e-3") == [0.5, 2.0, 0.001]
    with pytest.raises(ValueError, match="'fast'"):
        comma_numbers("1,fast")
