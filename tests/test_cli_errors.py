"""Command-line errors come before any work, in one line that names the option.

Every number an experiment takes is checked (finite, within the range its dataclass field
declares) and every output folder is checked for writing before any flight; an expected
error prints `error: ...` (or argparse's `prog: error: ...`) without a traceback unless
`--debug`; a vector env refuses a world count whose memory would not fit before allocating.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import os
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from experiments import common
from experiments.common import CommonArgs, arg, check_writable, parse_args

ROOT = Path(__file__).resolve().parents[1]
# every experiment built on the argument dataclasses (replay has its own positional parser)
EXPERIMENTS = ("lemniscate", "transect", "staged_collection", "sample_efficiency", "sweep", "force_maps", "train",
               "fields", "outdoor", "swarm", "benchmark", "report", "vehicles", "real_flights")
HEAVY = ("torch", "numba", "mujoco", "matplotlib", "ray")


def _run(name: str, *argv: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", f"experiments.{name}", *argv], cwd=cwd, capture_output=True,
                          text=True, timeout=300, env=env)


def _one_line_error(proc: subprocess.CompletedProcess, flag: str) -> str:
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-3000:])
    assert "Traceback" not in proc.stderr, proc.stderr
    assert len(err.splitlines()) == 1, err
    assert "error:" in err and flag in err, err
    return err


# ----------------------------------------------------------------------------- numbers

BAD_NUMBERS = [
    ("lemniscate", ["--duration", "inf"], "--duration"),
    ("lemniscate", ["--duration", "nan"], "--duration"),
    ("lemniscate", ["--duration", "-1"], "--duration"),
    ("lemniscate", ["--seed", "-1"], "--seed"),
    ("lemniscate", ["--seeds", "-3"], "--seeds"),
    ("lemniscate", ["--separation", "5"], "--separation"),
    ("transect", ["--x-offset", "nan"], "--x-offset"),
    ("outdoor", ["--duration", "inf"], "--duration"),
    ("outdoor", ["--seeds", "0"], "--seeds"),
    ("outdoor", ["--speed=-inf"], "--speed"),  # argparse takes -inf for an option unless joined with =
    ("swarm", ["--duration", "nan"], "--duration"),
    ("swarm", ["--swarm-minutes", "0"], "--swarm-minutes"),
    ("force_maps", ["--resolution", "2"], "--resolution"),
    ("staged_collection", ["--batch-flights", "-1"], "--batch-flights"),
    ("staged_collection", ["--threads", "100000"], "--threads"),
    ("staged_collection", ["--stage-minutes", "inf"], "--stage-minutes"),
    ("sample_efficiency", ["--trials", "-2"], "--trials"),
    ("sweep", ["--workers", "-1"], "--workers"),
    ("sweep", ["--batch", "0"], "--batch"),
    ("train", ["--seed", "-1"], "--seed"),
    ("train", ["--minutes", "nan"], "--minutes"),
    ("benchmark", ["--seconds", "inf"], "--seconds"),
    ("benchmark", ["--repeats", "0"], "--repeats"),
    ("fields", ["--seed", "-5"], "--seed"),
    ("report", ["--seed", "-5"], "--seed"),
    ("vehicles", ["--seed", "-5"], "--seed"),
    # counts of flights or trials fly or train as one batch: a huge one is refused here, not after the training
    ("lemniscate", ["--seeds", "1000000000"], "--seeds"),
    ("transect", ["--seeds", "1001"], "--seeds"),
    ("outdoor", ["--seeds", "1000000000"], "--seeds"),
    ("swarm", ["--seeds", "1000000000"], "--seeds"),
    ("sample_efficiency", ["--trials", "1000000000"], "--trials"),
    ("lemniscate", ["--seeds", "9" * 400], "--seeds"),  # an integer beyond any float
]


@pytest.mark.parametrize("name, argv, flag", BAD_NUMBERS, ids=[f"{n}{'='.join(a)}"[:50] for n, a, _ in BAD_NUMBERS])
def test_bad_number_is_one_line_naming_the_flag_before_any_work(tmp_path, name, argv, flag):
    proc = _run(name, *argv, "--out", "o", cwd=tmp_path)
    err = _one_line_error(proc, flag)
    assert f"{flag}: expected " in err and "got " in err, err
    assert sorted(os.listdir(tmp_path)) == []  # no output folder, no runs/, nothing


def test_bad_number_imports_nothing_heavy(tmp_path):
    """Refused while parsing: the stack (torch, mujoco, ...) is not even imported."""
    code = ("import sys, runpy; sys.argv = ['lemniscate', '--duration', 'inf']\n"
            "try:\n    runpy.run_module('experiments.lemniscate', run_name='__main__')\n"
            "finally:\n    print('HEAVY=' + ','.join(m for m in %r if m in sys.modules), file=sys.stderr)\n" % (HEAVY,))
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2 and proc.stderr.strip().endswith("HEAVY="), proc.stderr


def test_numbers_from_the_config_file_are_checked_too(tmp_path, capsys):
    from experiments.tracking import args_class

    (tmp_path / "c.toml").write_text("duration = inf\n")  # TOML has inf and nan
    with pytest.raises(SystemExit) as e:
        parse_args(args_class("lemniscate"), "lemniscate", ["--config", str(tmp_path / "c.toml"), "--out",
                                                            str(tmp_path / "o")])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "--duration: expected a finite number" in err and "got inf" in err and "c.toml" in err, err
    (tmp_path / "c.toml").write_text("seeds = -4\n")
    with pytest.raises(SystemExit):
        parse_args(args_class("lemniscate"), "lemniscate", ["--config", str(tmp_path / "c.toml")])
    assert "--seeds: expected >= 1, got -4" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_bad_condition_name_is_refused_while_parsing(tmp_path):
    proc = _run("lemniscate", "--conditions", "baseline,oracel", "--out", "o", cwd=tmp_path)
    assert "unknown ['oracel']" in _one_line_error(proc, "--conditions")
    assert sorted(os.listdir(tmp_path)) == []


# every option that takes names, each with a name no registry holds
BAD_NAMES = [
    ("swarm", ["--models", "nonsense"], "unrecognized arguments: --models"),  # was --models-dir, by abbreviation
    ("outdoor", ["--models", "nonsense"], "unrecognized arguments: --models"),
    ("swarm", ["--presets", "stack3,nonsense"], "--presets: preset: unknown 'nonsense'"),
    ("swarm", ["--aggregations", "nonsense"], "--aggregations: aggregation: unknown 'nonsense'"),
    ("sample_efficiency", ["--models", "nonsense"], "--models: unknown ['nonsense']"),
    ("sample_efficiency", ["--minutes", "nonsense"], "--minutes: expected a comma list of numbers"),
    ("outdoor", ["--leader", "nonsense"], "--leader: unknown 'nonsense'"),
    ("outdoor", ["--trained", "nonsense"], "--trained: expected a comma list of indoor, outdoor"),
    ("outdoor", ["--wind", "nonsense"], "--wind: unknown 'nonsense'"),
    ("outdoor", ["--sweep-winds", "off;nonsense"], "--sweep-winds: --wind: unknown 'nonsense'"),
    ("outdoor", ["--sweep-fields", "nonsense"], "--sweep-fields: --field: unknown field 'nonsense'"),
    ("outdoor", ["--sweep-speeds", "nonsense"], "--sweep-speeds: expected a comma list of distinct speeds"),
    ("lemniscate", ["--wind", "nonsense"], "--wind: unknown 'nonsense'"),
    ("transect", ["--field", "nonsense"], "--field: unknown field 'nonsense'"),
    ("train", ["--model", "nonsense"], "--model: unknown 'nonsense'"),
    ("fields", ["--run", "--only", "nonsense"], "--only: unknown fields ['nonsense']"),
]
NAMES_RUN = """
import runpy, sys, time
sys.argv = [{name!r}, *{argv!r}]
t0 = time.perf_counter()
try:
    runpy.run_module("experiments.{name}", run_name="__main__")
except SystemExit as e:
    code = e.code
else:
    code = 0
print("HEAVY=" + ",".join(m for m in {heavy!r} if m in sys.modules), file=sys.stderr)
sys.exit(code)
"""


@pytest.mark.parametrize("name, argv, message", BAD_NAMES, ids=[f"{n}{' '.join(a)}" for n, a, _ in BAD_NAMES])
def test_bad_name_is_one_line_naming_the_flag_before_any_import_of_the_stack(tmp_path, name, argv, message):
    """The registries' names are checked while parsing, from their static copies: at once, not after the
    heavy imports (15-30 s), naming the flag the user typed."""
    code = NAMES_RUN.format(name=name, argv=[*argv, "--out", "o"], heavy=HEAVY)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    *lines, heavy = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert message in lines[0] and "error:" in lines[0], lines[0]
    assert heavy == "HEAVY=", heavy
    assert sorted(os.listdir(tmp_path)) == []


def test_every_option_that_takes_names_states_its_check():
    """A new list option without a `check` would be refused only after the heavy imports."""
    from experiments.sweep import SweepArgs  # another's; its lists are checked by downwash.sweep

    free = {"out", "collection_dir", "models_dir", "video", "logs", "val_logs", "checkpoint", "cache_dir",
            "address",  # paths and a cluster address: not names
            "feature_set"}  # its names depend on --model: checked with the model, before any work
    exempt = {"vehicles.VehiclesArgs.only"}  # checked in run(), at once: the listing imports nothing heavy
    for label, cls in _args_classes().items():
        if cls is SweepArgs or label.startswith("report."):
            continue
        for f in dataclasses.fields(cls):
            if common.option_type(f) is str and f.name not in free and f"{label}.{f.name}" not in exempt:
                assert f.metadata.get("check"), f"{label}.{f.name}: give it a check= that names what is allowed"


@pytest.mark.parametrize("argv, where", [(["--out", ""], ""), (["--out", "  "], ""),
                                         (["--config", "c.toml"], " (from --config c.toml)")])
def test_an_empty_out_is_refused(tmp_path, monkeypatch, capsys, argv, where):
    """`--out ''` would silently mean runs/<experiment>."""
    from experiments.tracking import args_class

    monkeypatch.chdir(tmp_path)
    (tmp_path / "c.toml").write_text('out = ""\n')
    with pytest.raises(SystemExit) as e:
        parse_args(args_class("lemniscate"), "lemniscate", argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m experiments.lemniscate: error: --out: expected a folder path (without --out: "
                          "runs/lemniscate), got '") and err.endswith("'" + where), err
    assert sorted(os.listdir(tmp_path)) == ["c.toml"]


def test_a_module_factory_that_makes_no_field_is_one_line_naming_the_field_option(tmp_path, monkeypatch):
    """MODULE:FACTORY is the user's code: one that needs arguments, exits, or returns something that fails
    when called as a field is a bad --field, not a traceback."""
    (tmp_path / "not_fields.py").write_text(
        "def needs_args(x):\n    return x\n\n"
        "def bad_field():\n    return lambda p_a, v_a, R_a, p_b, v_b: {}['no such key']\n\n"
        "def exits():\n    raise SystemExit(0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for spec, detail in [("os:system", "TypeError: system() missing required argument"),
                         ("not_fields:needs_args", "TypeError"), ("not_fields:bad_field", "KeyError"),
                         ("not_fields:exits", "SystemExit")]:
        with pytest.raises(ConfigError) as e:
            common.load_field(spec)
        message = str(e.value)
        assert message.startswith(f"--field {spec}: expected MODULE:FACTORY to name a function that takes no "
                                  "arguments and returns a field; it failed with "), message
        assert detail in message and "\n" not in message, message


# ----------------------------------------------------------------------------- every field has a range


def _args_classes() -> dict[str, type]:
    from experiments.tracking import TRACKS, args_class

    classes: dict[str, type] = {f"tracking.{t}": args_class(t) for t in TRACKS}
    for name in EXPERIMENTS:
        module = importlib.import_module(f"experiments.{name}")
        for attr, obj in vars(module).items():
            if (isinstance(obj, type) and dataclasses.is_dataclass(obj) and issubclass(obj, CommonArgs)
                    and obj.__module__ == module.__name__):
                classes[f"{name}.{attr}"] = obj
    return classes


def _undeclared(cls: type) -> list[str]:
    """The numeric options of `cls` that state no range (neither bounds nor a check)."""
    return [f.name for f in dataclasses.fields(cls)
            if common.option_type(f) in (int, float) and not (f.metadata.get("bounds") or f.metadata.get("check"))]


def test_every_numeric_option_of_every_experiment_declares_its_range():
    classes = _args_classes()
    modules = {k.split(".")[0] for k in classes}
    assert modules >= set(EXPERIMENTS) - {"lemniscate", "transect"} | {"tracking"}, modules
    for label, cls in classes.items():
        assert _undeclared(cls) == [], f"{label}: give these options a range in arg(..., ge=/gt=/le=/lt=/check=)"
        for f in dataclasses.fields(cls):  # and every default, and what --quick gives, lies within it
            assert common._out_of_range(f, f.default) is None, f"{label}.{f.name}: default {f.default!r} out of range"
            if "quick" in f.metadata:
                assert common._out_of_range(f, f.metadata["quick"]) is None, f"{label}.{f.name}: --quick value"


def test_an_option_without_a_range_fails_the_check():
    @dataclasses.dataclass(frozen=True)
    class NewArgs(CommonArgs):
        steps: int = arg(10, "a new option someone forgot to bound")
        gain: float = arg(1.0, "bounded", gt=0.0)

    assert _undeclared(NewArgs) == ["steps"]


def test_help_states_each_range():
    from experiments.tracking import args_class

    text = common.build_parser(args_class("lemniscate"), "lemniscate").format_help()
    assert "--debug" in text
    flat = " ".join(text.split())
    assert "default: 10; >= 1" in flat and "in [0, 3600]" in flat, flat


def test_allowed_range_in_words():
    @dataclasses.dataclass(frozen=True)
    class A:
        a: int = arg(1, "", ge=1)
        b: float = arg(1.0, "", gt=0.0, le=60.0)
        c: float = arg(1.0, "", lt=2.0)
        d: int = arg(1, "", ge=0, lt=10)

    words = [common.allowed_range(f) for f in dataclasses.fields(A)]
    assert words == [">= 1", "a finite number in (0, 60]", "a finite number < 2", "an integer in [0, 10)"]
    b = dataclasses.fields(A)[1]
    assert [common._out_of_range(b, v) is None for v in (0.0, 1e-9, 60.0, 60.1, math.inf, math.nan)] == [
        False, True, True, False, False, False]


# ----------------------------------------------------------------------------- output folders


def _chmod_blocks_writes(tmp_path: Path) -> bool:
    """False as root (or on a file system that ignores modes): chmod 0o500 does not stop writes there."""
    probe = tmp_path / "probe"
    probe.mkdir()
    probe.chmod(0o500)
    try:
        (probe / "x").write_text("x")
    except OSError:
        return True
    finally:
        probe.chmod(0o700)
    return False


def _unwritable(tmp_path: Path) -> tuple[Path, Path]:
    """(an --out that cannot be written, the folder to look in afterwards)."""
    if _chmod_blocks_writes(tmp_path):
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
        return locked / "out", locked
    (tmp_path / "a_file").write_text("not a folder")
    return tmp_path / "a_file" / "out", tmp_path


@pytest.mark.parametrize("name", ["lemniscate", "outdoor", "benchmark", "fields", "vehicles"])
def test_unwritable_out_is_refused_at_once(tmp_path, name):
    out, where = _unwritable(tmp_path)
    before = sorted(os.listdir(where))
    try:
        proc = _run(name, "--out", str(out), cwd=tmp_path)
        err = _one_line_error(proc, "--out")
        assert err.startswith("error: --out: cannot write to"), err
        assert sorted(os.listdir(where)) == before
    finally:
        where.chmod(0o700)


def test_out_whose_parent_is_a_file_and_other_outputs(tmp_path):
    (tmp_path / "f").write_text("x")
    proc = _run("lemniscate", "--out", "f/sub/deeper", cwd=tmp_path)
    assert "f is a file, not a folder" in _one_line_error(proc, "--out")
    proc = _run("lemniscate", "--out", "o", "--video", "f/v.mp4", cwd=tmp_path)
    _one_line_error(proc, "--video")
    proc = _run("sweep", "--out", "o", "--cache-dir", "f/cells", cwd=tmp_path)
    _one_line_error(proc, "--cache-dir")
    proc = _run("train", "--out", "o", "--checkpoint", "f/m.pt", cwd=tmp_path)
    _one_line_error(proc, "--checkpoint")
    assert sorted(os.listdir(tmp_path)) == ["f"]


def test_check_writable_leaves_nothing_behind(tmp_path):
    target = tmp_path / "a" / "b" / "c"
    assert check_writable("--out", target) == target
    assert sorted(os.listdir(tmp_path)) == []  # the folders it made to try are gone again
    (tmp_path / "d").mkdir()
    check_writable("--out", tmp_path / "d")
    assert os.listdir(tmp_path / "d") == []  # nor its temporary file
    check_writable("--video", tmp_path / "new" / "v.mp4", "file")
    assert sorted(os.listdir(tmp_path)) == ["d"]
    with pytest.raises(ConfigError, match="--video: .* is a folder"):
        check_writable("--video", tmp_path / "d", "file")
    (tmp_path / "d" / "x").write_text("")
    with pytest.raises(ConfigError, match=r"--out: cannot write to .*x is a file, not a folder"):
        check_writable("--out", tmp_path / "d" / "x")


def test_check_writable_reports_a_refused_write_and_cleans_up(tmp_path, monkeypatch):
    """What a read-only folder does for a user who is not root (tests may run as root, where chmod
    does not stop writes): the write is refused, named, and the folders made to try are removed."""

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(common.tempfile, "mkstemp", refuse)
    with pytest.raises(ConfigError, match=r"^--out: cannot write to .*new/out \(Permission denied\)$"):
        check_writable("--out", tmp_path / "new" / "out")
    assert os.listdir(tmp_path) == []


def test_pipeline_folders_are_checked_only_when_the_run_may_write_there(tmp_path):
    from experiments.common import PipelineArgs, resolve_pipeline

    (tmp_path / "f").write_text("x")
    bad = PipelineArgs(out=str(tmp_path / "o"), collection_dir=str(tmp_path / "f" / "c"),
                       models_dir=str(tmp_path / "f" / "m"))
    with pytest.raises(ConfigError, match="--collection-dir: cannot write to"):
        resolve_pipeline(bad)
    resolve_pipeline(bad, models=())  # a run that needs no model (baseline, oracle) writes nothing there
    models = tmp_path / "shared"
    models.mkdir()
    for kind in common.PAIRWISE_KINDS:
        (models / f"{kind}.pt").write_text("")
    ok = PipelineArgs(out=str(tmp_path / "o"), collection_dir=str(tmp_path / "f" / "c"), models_dir=str(models))
    assert resolve_pipeline(ok).models_dir == models  # every model there: read only


# ----------------------------------------------------------------------------- one line, exit status, --debug


def test_expected_errors_after_parsing_are_one_line_and_debug_shows_the_traceback(tmp_path):
    proc = _run("train", "--logs", "nope", "--val-logs", "nope", "--out", "o", cwd=tmp_path)
    assert _one_line_error(proc, "--logs") == "error: --logs: nope: no such file or folder"
    proc = _run("train", "--logs", "nope", "--val-logs", "nope", "--out", "o", "--debug", cwd=tmp_path)
    assert proc.returncode == 1 and "Traceback" in proc.stderr and "ConfigError: --logs" in proc.stderr
    (tmp_path / "f").write_text("x")
    proc = _run("lemniscate", "--out", "f/o", "--debug", cwd=tmp_path)
    assert "Traceback" in proc.stderr and "ConfigError: --out" in proc.stderr


def _run_main(body: str, *argv: str) -> subprocess.CompletedProcess:
    code = ("import sys\nfrom experiments.common import run_main\nfrom downwash_core.errors import *\n"
            f"sys.argv = ['x', *{list(argv)!r}]\ndef main():\n    {body}\nrun_main(main)\n")
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_run_main_exit_status_by_kind():
    proc = _run_main("raise ConfigError('--x: bad')")
    assert (proc.returncode, proc.stderr) == (2, "error: --x: bad\n")
    proc = _run_main("raise LogError('flight.npz: truncated')")
    assert (proc.returncode, proc.stderr) == (1, "error: flight.npz: truncated\n")
    proc = _run_main("raise ConfigError('--x: bad')", "--debug")
    assert proc.returncode == 1 and "Traceback" in proc.stderr
    proc = _run_main("raise ZeroDivisionError('a bug')")  # a bug keeps its traceback
    assert proc.returncode == 1 and "Traceback" in proc.stderr and "ZeroDivisionError" in proc.stderr
    proc = _run_main("return {'results': 1}")
    assert (proc.returncode, proc.stderr) == (0, "")
    proc = _run_main("raise KeyboardInterrupt")  # Ctrl-C: one line, the shell's 128 + SIGINT
    assert proc.returncode == 130 and proc.stderr.startswith("stopped: interrupted;") and proc.stderr.count("\n") == 1
    proc = _run_main("raise KeyboardInterrupt", "--debug")
    assert proc.returncode != 130 and "Traceback" in proc.stderr


def test_every_experiment_runs_main_through_run_main():
    """One code path: `python -m experiments.X` and the console scripts both go through run_main."""
    for path in sorted((ROOT / "experiments").glob("*.py")):
        text = path.read_text()
        if 'if __name__ == "__main__":' in text:
            tail = text.split('if __name__ == "__main__":', 1)[1]
            assert "run_main(main)" in tail, path.name


# ----------------------------------------------------------------------------- worlds in memory


def test_world_memory_bound_with_a_given_amount_of_memory():
    from sim.physics import MEMORY_FRACTION, check_world_memory, world_bytes

    gib = 1 << 30
    per = world_bytes(2)
    fits = int(gib * MEMORY_FRACTION) // per
    assert check_world_memory(fits, 2, available=gib) == fits * per
    with pytest.raises(ConfigError) as e:
        check_world_memory(fits + 1, 2, name="num_envs", available=gib)
    message = str(e.value)
    assert message.startswith(f"num_envs: {fits + 1} worlds") and f"num_envs <= {fits}" in message
    assert "512.0 MB" in message and "1.0 GB available" in message  # the bound and what it is half of
    assert world_bytes(5) > world_bytes(2)  # more vehicles, more memory per world


def test_the_simulator_checks_its_worlds_memory_before_allocating(monkeypatch):
    import sim.physics as physics
    from sim.scene import build_scene
    from sim.simulator import Simulator
    from downwash_trajectories import Hover, stack

    monkeypatch.setattr(physics, "available_memory", lambda: 64 * physics.world_bytes(2))  # room for 32 worlds
    W = 33
    reference = stack([Hover(np.array([0.0, 0.0, 2.5]), n_worlds=W), Hover(np.array([0.0, 0.0, 1.9]), n_worlds=W)])
    with pytest.raises(ConfigError, match="worlds: 33 worlds of 2 vehicles .* use worlds <= 32"):
        Simulator(build_scene(), reference, list(range(W)))


def test_huge_num_envs_is_refused_before_allocating():
    import gymnasium as gym

    import downwash_envs  # noqa: F401  (registers the envs)

    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(ConfigError, match=r"num_envs: 1000000000 worlds .* bound .*; use num_envs <= \d+"):
            gym.make_vec("downwash/Follower-v2", num_envs=10**9, vectorization_mode="vector_entry_point")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 5.0
    assert peak < 16 << 20  # nothing per world was allocated


def test_huge_swarm_world_count_is_refused_before_allocating():
    pytest.importorskip("pettingzoo")
    from downwash_envs.swarm import SwarmVectorEnv

    with pytest.raises(ConfigError, match=r"n_worlds: 1000000000 worlds of 5 vehicles"):
        SwarmVectorEnv(10**9, preset="formation5")
