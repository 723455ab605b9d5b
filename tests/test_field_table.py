"""`python -m experiments.fields --run`: the lemniscate experiment on registered fields, tabulated for the README."""

import json
import subprocess
import sys

import pytest

from downwash.conditions import DEFAULT_CONDITIONS
from experiments.fields import TABLE_KEYS
from experiments.report.sections import render_field_table


def _run(args, cwd, check=True):
    proc = subprocess.run([sys.executable, "-m", "experiments.fields", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=600)
    if check and proc.returncode != 0:
        raise AssertionError(f"{args} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return proc


def test_run_tabulates_every_condition_of_the_chosen_field(tmp_path):
    _run(["--run", "--quick", "--fresh", "--only", "momentum", "--out", "ft"], tmp_path)
    result = json.loads((tmp_path / "ft" / "results.json").read_text())
    assert list(result["table"]) == ["momentum"]
    entry = result["table"]["momentum"]
    assert entry["wall_seconds"] > 0 and entry["seeds"] >= 1
    assert set(entry["conditions"]) == set(DEFAULT_CONDITIONS)
    lemniscate = json.loads((tmp_path / "ft" / "momentum" / "results.json").read_text())
    for c, e in entry["conditions"].items():  # the table copies the run's numbers, nothing else
        assert e == {**{k: lemniscate["conditions"][c].get(k) for k in TABLE_KEYS},
                     "per_seed": {"pos_err_3d_mean": lemniscate["conditions"][c]["per_seed"]["pos_err_3d_mean"]}}
    assert lemniscate["provenance"]["pipeline"]["field"]["name"] == "momentum"
    assert (tmp_path / "ft" / "pipeline" / "momentum" / "models" / "equivariant.pt").is_file()  # --fresh: its own
    text = render_field_table(result, "ft/results.json")
    assert "| `momentum` |" in text and "equivariant_general" in text
    assert "What does learning add" in text and "| `momentum` | `equivariant` |" in text


@pytest.mark.parametrize("args, message", [
    (["--run", "--only", "nope"], "--only: unknown fields \\['nope'\\]; allowed: so2"),
    (["--only", "so2"], "--only: only with --run"),
    (["--run", "--field", "so2"], "--field: not with --run"),
])
def test_bad_options_fail_before_any_flight(args, message, tmp_path):
    proc = _run(args + ["--out", "x"], tmp_path, check=False)
    assert proc.returncode != 0 and __import__("re").search(message, proc.stderr), proc.stderr[-1000:]
    assert not (tmp_path / "x").exists()
