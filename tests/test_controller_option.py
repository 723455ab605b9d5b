"""`--controller lqr|mellinger|pid|indi` on the experiments that fly: smoke runs with --quick, the record of
the controller in results.json, and the refusals before any work (an [lqr] table or the integral condition
with another controller)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from downwash_core.errors import ConfigError
from experiments import components
from experiments.common import parse_args
from experiments.components import flight_components

ROOT = Path(__file__).resolve().parent.parent
CONDITIONS = "no_downwash,baseline,oracle"  # no trained model: no collection, no training
TYPES = {"lqr": "FeedbackLinearisedLQR", "mellinger": "MellingerController", "pid": "CrazyfliePID",
         "indi": "INDIController"}


def _lemniscate(argv):
    from experiments.tracking import args_class

    return parse_args(args_class("lemniscate"), "lemniscate", argv)


@pytest.mark.parametrize("name", ["mellinger", "pid", "indi"])
def test_a_quick_lemniscate_flies_the_controller_and_records_it(tmp_path, name):
    proc = subprocess.run([sys.executable, "-m", "experiments.lemniscate", "--quick", "--controller", name,
                           "--conditions", CONDITIONS, "--out", "lem"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads((tmp_path / "lem" / "results.json").read_text())
    assert r["args"]["controller"] == name
    assert r["provenance"]["controller"]["name"] == name and r["provenance"]["controller"]["type"] == TYPES[name]
    for c in r["conditions"].values():
        assert c["crash_rate"] == 0.0 and 0.0 <= c["pos_err_3d_mean"] < 0.25  # the PID trails a moving reference
    config = tomllib.loads((tmp_path / "lem" / "config.toml").read_text())
    assert config["controller"] == name and "lqr" not in config  # no LQR flew: a rerun of it is not refused
    rerun = _lemniscate(["--config", str(tmp_path / "lem" / "config.toml"), "--out", str(tmp_path / "again")])
    again = json.loads(json.dumps(flight_components(rerun)["controller"].describe()))
    assert rerun.controller == name and again == {k: v for k, v in r["provenance"]["controller"].items() if k != "name"}


def test_the_default_is_todays_lqr_and_the_registry_builds_the_others(tmp_path):
    from controllers.lqr import FeedbackLinearisedLQR, LQRConfig

    default = _lemniscate(["--out", str(tmp_path / "o")])
    assert default.controller == "lqr"
    controller = flight_components(default)["controller"]
    assert type(controller) is FeedbackLinearisedLQR and controller.config == LQRConfig()  # the same bits as before
    assert components.controller_record(default, controller) == {"name": "lqr", **controller.describe()}
    for name, kind in TYPES.items():
        args = _lemniscate(["--controller", name, "--out", str(tmp_path / "o")])
        assert type(flight_components(args)["controller"]).__name__ == kind


def test_help_lists_the_controllers():
    from experiments.common import build_parser
    from experiments.tracking import args_class

    text = " ".join(build_parser(args_class("lemniscate"), "lemniscate").format_help().split())
    assert "--controller CONTROLLER" in text and "lqr, mellinger, pid, indi" in text


def test_a_bad_controller_name_is_a_usage_error_naming_the_allowed(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        _lemniscate(["--controller", "lqg", "--out", str(tmp_path / "o")])
    assert e.value.code == 2
    assert "--controller: unknown 'lqg'; allowed: lqr, mellinger, pid, indi" in capsys.readouterr().err


@pytest.mark.parametrize("experiment", ["lemniscate", "outdoor"])
def test_integral_with_another_controller_is_refused_before_any_work(tmp_path, experiment):
    import importlib

    main = importlib.import_module(f"experiments.{experiment}").main
    with pytest.raises(ConfigError, match="integral adds integral action to the LQR, but --controller is pid"):
        main(["--controller", "pid", "--conditions", "baseline,integral", "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_the_default_conditions_with_another_controller_leave_integral_out(tmp_path):
    from downwash.conditions import parse_conditions
    from experiments.tracking import _validate

    lqr = _lemniscate(["--out", str(tmp_path / "o")])
    pid = _lemniscate(["--controller", "pid", "--out", str(tmp_path / "o")])
    assert _validate(lqr) == parse_conditions(lqr.conditions)  # the LQR flies them all
    assert _validate(pid) == [c for c in parse_conditions(pid.conditions) if c != "integral"]
    for name in ("dob", "baseline"):  # the predictors fly with any controller
        args = _lemniscate(["--controller", "indi", "--conditions", f"{name},oracle", "--out", str(tmp_path / "o")])
        assert _validate(args) == [name, "oracle"]


@pytest.mark.parametrize("experiment, cls", [("tracking", None), ("outdoor", "OutdoorArgs"), ("swarm", "SwarmArgs")])
def test_an_lqr_table_with_another_controller_is_refused_naming_both(tmp_path, experiment, cls):
    import importlib

    module = importlib.import_module(f"experiments.{experiment}")
    options = module.args_class("lemniscate") if cls is None else getattr(module, cls)
    path = tmp_path / "c.toml"
    path.write_text("[lqr]\nmax_tilt_deg = 30\n")
    args = parse_args(options, experiment, ["--config", str(path), "--controller", "mellinger", "--out",
                                            str(tmp_path / "o")])
    for check in (module._validate, flight_components):
        with pytest.raises(ConfigError, match=r"\[lqr\]: sets the LQR's max_tilt_deg, but --controller is mellinger"):
            check(args)
    with_lqr = parse_args(options, experiment, ["--config", str(path), "--out", str(tmp_path / "o")])
    assert flight_components(with_lqr)["controller"].config.max_tilt_deg == 30.0


def test_the_controller_leaves_the_pipeline_key_alone(tmp_path):
    """The models are trained on the staged collection, which flies the LQR whatever --controller says."""
    from experiments.common import resolve_pipeline

    dirs = ["--collection-dir", str(tmp_path / "c"), "--models-dir", str(tmp_path / "m")]
    records = [resolve_pipeline(_lemniscate(["--controller", name, "--out", str(tmp_path / "o"), *dirs]), models=())
               .provenance() for name in ("lqr", "indi")]
    assert records[0] == records[1]


def test_the_controller_table_flies_each_controller_and_renders(tmp_path):
    """python -m experiments.controller_table --quick: each track under each controller asked for, integral
    only under the LQR, the table rendered with each controller's column."""
    import json
    import subprocess
    import sys

    from experiments.report.baselines import render_controller_table

    proc = subprocess.run([sys.executable, "-m", "experiments.controller_table", "--quick", "--controllers", "lqr,indi",
                           "--conditions", "baseline,oracle,integral,dob", "--out", "ct"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads((tmp_path / "ct" / "results.json").read_text())
    assert list(r["table"]) == ["indi", "lqr"] or set(r["table"]) == {"lqr", "indi"}
    for track in ("lemniscate", "transect"):
        assert set(r["table"]["lqr"][track]["conditions"]) == {"baseline", "oracle", "integral", "dob"}
        assert set(r["table"]["indi"][track]["conditions"]) == {"baseline", "oracle", "dob"}
        flown = json.loads((tmp_path / "ct" / f"{track}-indi" / "results.json").read_text())
        assert flown["provenance"]["controller"]["name"] == "indi"
    text = render_controller_table(r, "ct/results.json")
    assert "| condition | `lqr` | `indi` |" in text and "| `integral` |" in text
