"""The experiments' command line: a quick `--help` that lists the choices, `--config FILE.toml`,
and one console script per experiment.

`--help` must not load the heavy stack (torch, numba, mujoco, matplotlib, ray): checked on
`sys.modules` in a fresh interpreter, which does not depend on the machine's speed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import subprocess
import sys
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from experiments import common
from experiments.common import parse_args, read_config, script

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ("lemniscate", "transect", "staged_collection", "sample_efficiency", "sweep", "force_maps", "train", "fields",
           "outdoor", "swarm", "benchmark", "report", "vehicles", "real_flights", "observer_bandwidth", "controller_table", "registry")
# experiments with a parser of their own (positional files; no --config/--quick/--field): a console script each
TOOLS = ("export", "replay", "warmup")
HEAVY = ("torch", "numba", "mujoco", "matplotlib", "ray")
TRACKING = (*common.CONDITIONS, *common.WIND_SEVERITIES)
# per script, the choices its --help lists (besides the field names, which every script lists)
CHOICES = {
    "lemniscate": TRACKING, "transect": TRACKING, "outdoor": (*TRACKING, "circle", "line"),
    "swarm": (*common.PRESETS, *common.AGGREGATIONS), "sweep": common.PAIRWISE_KINDS,
    "sample_efficiency": common.PAIRWISE_KINDS, "train": common.PAIRWISE_KINDS,
    "vehicles": ("paper_quad", "crazyflie_2_1", "x500", "crazyflie_large"),
    "real_flights": ("shallow", "deep", "equivariant", "equivariant_general"),
}
HELP = """
import runpy, sys
sys.argv = [{name!r}, "--help"]
try:
    runpy.run_module("experiments.{name}", run_name="__main__")
except SystemExit as e:
    code = e.code
else:
    code = "no exit"
print("HEAVY=" + ",".join(m for m in {heavy!r} if m in sys.modules), file=sys.stderr)
sys.exit(code)
"""


def _python(code: str, cwd: Path = ROOT, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "COLUMNS": "200", **env})  # wide: no choice split across lines


@pytest.mark.parametrize("name", SCRIPTS)
def test_help_exits_0_lists_the_choices_and_imports_no_heavy_module(name):
    proc = _python(HELP.format(name=name, heavy=HEAVY))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines()[-1] == "HEAVY=", f"--help imported {proc.stderr.strip().splitlines()[-1]}"
    text = proc.stdout
    assert text.startswith(f"usage: python -m experiments.{name}")
    for choice in (*common.FIELD_NAMES, *CHOICES.get(name, ())):
        assert choice in text, f"{name} --help does not list {choice!r}"
    assert "--config FILE.toml" in text and "--quick, --no-quick" in text
    assert "python -c" not in text  # the choices are listed, not a command that prints them


def test_static_choices_match_their_registries():
    """The names `--help` lists without importing the registries are the registries' own."""
    from controllers.registry import CONTROLLER_NAMES, DEFAULT_CONTROLLER
    from downwash.conditions import CONDITIONS, DEFAULT_CONDITIONS
    from downwash.models import PAIRWISE_KINDS
    from downwash.sweep_cells import PAPER_MINUTES, PAPER_MODELS
    from sim.aggregation import AGGREGATIONS
    from sim.fields.registry import DEFAULT_FIELD, FIELDS
    from sim.presets import PRESETS
    from sim.wind import PRESETS_KT

    assert common.CONDITIONS == tuple(CONDITIONS) and common.DEFAULT_CONDITIONS == tuple(DEFAULT_CONDITIONS)
    assert common.PAIRWISE_KINDS == tuple(PAIRWISE_KINDS)
    assert common.FIELD_NAMES == tuple(FIELDS) and common.DEFAULT_FIELD == DEFAULT_FIELD
    assert common.PRESETS == tuple(PRESETS)
    assert common.AGGREGATIONS == tuple(AGGREGATIONS)
    assert common.WIND_SEVERITIES == tuple(PRESETS_KT)
    assert common.PAPER_MINUTES == tuple(PAPER_MINUTES) and common.PAPER_MODELS == tuple(PAPER_MODELS)
    assert common.CONTROLLER_NAMES == tuple(CONTROLLER_NAMES) and common.DEFAULT_CONTROLLER == DEFAULT_CONTROLLER
    from downwash_core.registry import PLUGIN_GROUP
    from experiments import options

    assert options.PLUGIN_GROUP == PLUGIN_GROUP
    from downwash.conditions import GUARDED, UNLEARNED

    assert options.GUARDED == GUARDED and options.UNLEARNED == UNLEARNED


# ----------------------------------------------------------------------------- --config


def _lemniscate_args():
    from experiments.tracking import args_class

    return args_class("lemniscate")


def _toml(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_config_values_apply_and_flags_override_them(tmp_path):
    cls = _lemniscate_args()
    path = _toml(tmp_path, 'seeds = 3\nseparation = 1\nconditions = "baseline,oracle"\nquick = true\n'
                           'half-length = 2.0\ncollection_dir = "c"\nout = "o"\n')
    args = parse_args(cls, "lemniscate", ["--config", str(path)])
    assert (args.seeds, args.separation, args.conditions, args.quick, args.half_length, args.collection_dir,
            args.out) == (3, 1.0, "baseline,oracle", True, 2.0, "c", "o")
    assert isinstance(args.separation, float)  # an integer where a float is expected is that float
    assert args.half_width == 0.5 and args.wind == "off"  # what the file leaves out keeps its default

    args = parse_args(cls, "lemniscate", ["--seeds", "7", "--config", str(path), "--no-quick", "--separation", "0.5"])
    assert (args.seeds, args.quick, args.separation, args.conditions) == (7, False, 0.5, "baseline,oracle")

    defaults = parse_args(cls, "lemniscate", [])
    assert dataclasses.asdict(defaults) == {**dataclasses.asdict(cls()), "out": str(Path("runs") / "lemniscate")}


@pytest.mark.parametrize("text, expected", [
    ("sedds = 3\n", ["unknown key 'sedds'", "allowed:", "seeds", "half-length", "collection-dir"]),
    ("config = 'other.toml'\n", ["unknown key 'config'"]),
    ('seeds = "3"\n', ["seeds = '3'", "expected an integer", "--seeds"]),
    ("seeds = 2.5\n", ["expected an integer"]),
    ("separation = true\n", ["expected a number", "--separation"]),
    ("quick = 1\n", ["expected a boolean", "--quick"]),
    ("separation = [0.5]\n", ["expected a number", "TOML array", "--separation"]),
    ("seeds = 1\nseeds = 2\n", ["not valid TOML"]),
    ("seeds = \n", ["not valid TOML"]),
    ("seeds = 1\n[lemniscate]\nseeds = 2\n", ["unknown key 'lemniscate'; allowed:"]),
    ("seeds = 1\nse-eds = 2\n", ["unknown key 'se-eds'"]),
    ("half-length = 1.0\nhalf_length = 2.0\n", ["given twice"]),
    pytest.param("separation = " + "9" * 400 + "\n", ["separation: expected a finite number", "400 digits"],
                 id="integer-beyond-a-float"),
    pytest.param("seeds = " + "1" * 5000 + "\n", ["not valid TOML"], id="integer-beyond-the-digits-limit"),
    pytest.param("seeds = " + "[" * 2000 + "]" * 2000 + "\n", ["not valid TOML"], id="nested-beyond-recursion"),
])
def test_bad_config_is_a_usage_error_naming_the_key_and_the_allowed_options(tmp_path, capsys, text, expected):
    path = _toml(tmp_path, text)
    with pytest.raises(SystemExit) as e:
        parse_args(_lemniscate_args(), "lemniscate", ["--config", str(path)])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"--config {path}" in err
    for part in expected:
        assert part in err, err


def test_a_binary_or_non_utf8_config_is_one_line_naming_the_file(tmp_path, capsys):
    """What tomllib's UTF-8 decoding raises is a bad file like any other: one line, exit 2, on the command line too."""
    for data in (b"seeds = 3\nconditions = \"caf\xe9\"\n", bytes(range(256)), b"\x89PNG\r\n\x1a\n\x00\x00"):
        path = tmp_path / "c.toml"
        path.write_bytes(data)
        with pytest.raises(SystemExit) as e:
            parse_args(_lemniscate_args(), "lemniscate", ["--config", str(path), "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and len(err.strip().splitlines()) == 1, err
        assert f"--config {path}: not a UTF-8 text file" in err, err
    proc = _python("import sys, runpy; sys.argv = ['lemniscate', '--config', 'c.toml', '--out', 'o']\n"
                   "runpy.run_module('experiments.lemniscate', run_name='__main__')", cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert proc.stderr.strip().endswith("--config c.toml: not a UTF-8 text file (invalid start byte at byte 0)")
    assert sorted(os.listdir(tmp_path)) == ["c.toml"]


VALID_CONFIG = (b'seeds = 3\nseparation = 0.8\nconditions = "baseline,oracle"\nquick = true\nhalf-length = 2.0\n'
                b'duration = 12.5\nwind = "light:mean=1,0,0"\nfield = "so2"\ncollection_dir = "c"\n')


@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, len(VALID_CONFIG) - 1), st.integers(0, 255)), min_size=1, max_size=4))
def test_a_config_with_flipped_bytes_is_refused_naming_the_file_or_parses_within_range(tmp_path, flips):
    """Any damage to a valid file: one line naming the file (exit 2), or options that pass every check."""
    data = bytearray(VALID_CONFIG)
    for at, byte in flips:
        data[at] = byte
    path = tmp_path / "c.toml"
    path.write_bytes(bytes(data))
    cls = _lemniscate_args()
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            args = parse_args(cls, "lemniscate", ["--config", str(path), "--out", str(tmp_path / "o")])
    except SystemExit as e:
        lines = err.getvalue().strip().splitlines()
        assert e.code == 2 and len(lines) == 1 and lines[0].startswith("python -m experiments.lemniscate: error: ")
        assert f"--config {path}" in lines[0], lines[0]
    except common.ConfigError as e:  # an output path from the file that cannot be written
        assert str(path) in str(e) or str(e).startswith("--"), e
    else:
        for f in dataclasses.fields(cls):
            assert common._out_of_range(f, getattr(args, f.name)) is None, (f.name, getattr(args, f.name))


def test_an_empty_config_path_is_refused(capsys):
    """`--config ''` would read no file at all, silently."""
    with pytest.raises(SystemExit) as e:
        parse_args(_lemniscate_args(), "lemniscate", ["--config", ""])
    assert e.value.code == 2
    assert capsys.readouterr().err.strip().endswith("error: --config: expected the path of a TOML file, got ''")


def test_an_abbreviated_option_is_refused_not_taken_for_a_longer_one(capsys):
    """argparse's prefix matching made `--models x` mean `--models-dir x` where no --models exists."""
    from experiments.swarm import SwarmArgs

    with pytest.raises(SystemExit) as e:
        parse_args(SwarmArgs, "swarm", ["--models", "nonsense"])
    assert e.value.code == 2
    assert capsys.readouterr().err.strip().endswith("error: unrecognized arguments: --models nonsense")


@pytest.mark.parametrize("module, patch, argv, quick, given", [
    ("lemniscate", "experiments.tracking", ["--seeds", "3"], {"seeds": 1, "duration": 2.0}, {"seeds": 3}),
    ("transect", "experiments.tracking", ["--duration", "0"], {"seeds": 1, "duration": 2.0}, {"duration": 0.0}),
    ("outdoor", "experiments.outdoor", ["--seeds", "2", "--duration", "3"], {"seeds": 1, "duration": 2.0},
     {"seeds": 2, "duration": 3.0}),
    ("swarm", "experiments.swarm", ["--seeds", "4"], {"seeds": 1}, {"seeds": 4}),
])
def test_quick_keeps_the_options_given(tmp_path, monkeypatch, module, patch, argv, quick, given):
    """--quick shrinks what is left out, never what is given, on the command line or in --config."""
    import importlib

    seen = []
    monkeypatch.setattr(importlib.import_module(patch), "run", lambda *a: seen.append(a[-1]) or {})
    main = importlib.import_module(f"experiments.{module}").main
    main(["--quick", "--out", str(tmp_path / "a")])
    assert {k: getattr(seen[-1], k) for k in quick} == quick
    main(["--quick", *argv, "--out", str(tmp_path / "b")])
    assert {k: getattr(seen[-1], k) for k in given} == given
    text = "".join(f"{k} = {v}\n" for k, v in given.items())
    main(["--quick", "--config", str(_toml(tmp_path, text)), "--out", str(tmp_path / "c")])
    assert {k: getattr(seen[-1], k) for k in given} == given


def test_missing_config_file_is_named(tmp_path):
    with pytest.raises(common.ConfigError, match=r"--config .*nope\.toml: no such file"):
        read_config(tmp_path / "nope.toml", _lemniscate_args())
    with pytest.raises(common.ConfigError, match="cannot read it"):
        read_config(tmp_path, _lemniscate_args())  # a folder


def test_bad_config_stops_the_script_before_any_work(tmp_path):
    """On the command line: exit 2 and the message, no output folder, no heavy import."""
    _toml(tmp_path, 'out = "o"\nsedds = 3\n')
    code = ("import sys, runpy; sys.argv = ['lemniscate', '--config', 'c.toml']\n"
            "try:\n    runpy.run_module('experiments.lemniscate', run_name='__main__')\n"
            "finally:\n    print('HEAVY=' + ','.join(m for m in %r if m in sys.modules), file=sys.stderr)\n" % (HEAVY,))
    proc = _python(code, cwd=tmp_path)
    assert proc.returncode == 2
    assert "unknown key 'sedds'; allowed:" in proc.stderr and proc.stderr.strip().endswith("HEAVY=")
    assert not (tmp_path / "o").exists() and not (tmp_path / "runs").exists()


def test_resolved_config_is_written_beside_the_results(tmp_path):
    """The field listing run from a config file, one value overridden: results.json holds the resolved options."""
    _toml(tmp_path, 'out = "listing"\nseed = 5\nquick = true\n')
    code = "from experiments.fields import main; main(['--config', 'c.toml', '--seed', '6'])"
    proc = _python(code, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    args = json.loads((tmp_path / "listing" / "results.json").read_text())["args"]
    assert args == {"out": "listing", "seed": 6, "quick": True, "field": "", "run": False, "only": "", "fresh": False}


# ----------------------------------------------------------------------------- console scripts


def _scripts() -> dict[str, str]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def test_one_console_script_per_experiment():
    scripts = _scripts()
    assert sorted(v.split(":")[0] for v in scripts.values()) == sorted(f"experiments.{n}" for n in (*SCRIPTS, *TOOLS))
    for name, value in scripts.items():
        module = value.split(":")[0].split(".")[1]
        assert name == "downwash-" + module.replace("_", "-")
        assert callable(EntryPoint(name, value, "console_scripts").load())


def test_console_script_answers_help_and_exits_0_after_a_run():
    name, value = "downwash-lemniscate", _scripts()["downwash-lemniscate"]
    code = (f"import sys; from importlib.metadata import EntryPoint; sys.argv = [{name!r}, '--help']; "
            f"sys.exit(EntryPoint({name!r}, {value!r}, 'console_scripts').load()())")
    proc = _python(code)
    assert proc.returncode == 0 and "--conditions" in proc.stdout, proc.stderr[-3000:]
    assert script(lambda: {"results": 1})() is None  # sys.exit(None): a finished run exits 0
