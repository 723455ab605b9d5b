"""The experiments' command line: a quick `--help` that lists the choices, `--config FILE.toml`,
and one console script per experiment.

`--help` must not load the heavy stack (torch, numba, mujoco, matplotlib, ray): checked on
`sys.modules` in a fresh interpreter, which does not depend on the machine's speed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from experiments import common
from experiments.common import parse_args, read_config, script

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ("lemniscate", "transect", "staged_collection", "sample_efficiency", "sweep", "force_maps", "train", "fields",
           "outdoor", "swarm", "benchmark", "report", "vehicles")
HEAVY = ("torch", "numba", "mujoco", "matplotlib", "ray")
TRACKING = (*common.CONDITIONS, *common.WIND_SEVERITIES)
# per script, the choices its --help lists (besides the field names, which every script lists)
CHOICES = {
    "lemniscate": TRACKING, "transect": TRACKING, "outdoor": (*TRACKING, "circle", "line"),
    "swarm": (*common.PRESETS, *common.AGGREGATIONS), "sweep": common.PAIRWISE_KINDS,
    "sample_efficiency": common.PAIRWISE_KINDS, "train": common.PAIRWISE_KINDS,
    "vehicles": ("paper_quad", "crazyflie_2_1", "x500"),
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
    ("conditions = ['baseline']\n", ["expected a string", "TOML array", "--conditions"]),
    ("seeds = 1\nseeds = 2\n", ["not valid TOML"]),
    ("seeds = \n", ["not valid TOML"]),
    ("seeds = 1\n[lemniscate]\nseeds = 2\n", ["unknown key 'lemniscate'; allowed:"]),
    ("seeds = 1\nse-eds = 2\n", ["unknown key 'se-eds'"]),
    ("half-length = 1.0\nhalf_length = 2.0\n", ["given twice"]),
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
    assert sorted(v.split(":")[0] for v in scripts.values()) == sorted(f"experiments.{n}" for n in SCRIPTS)
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
