"""`python -m experiments.report`: the docs' results page and the README's headline table come from
results files, never typed.

Fake results files are written through `experiments.common.write_results` with each
experiment's own argument class, in the shapes the experiments write; one real quick
transect run catches drift between the experiment's keys and the report.
"""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from downwash_core.errors import ConfigError
from downwash_core.io import atomic_write_json
from experiments import report
from experiments.common import parse_args, write_results
from experiments.report.formatting import crash_cell
from experiments.report import BEGIN, END, HEADLINE_BEGIN, HEADLINE_END, HEADLINE_HEADING, fmt, pct, render, \
    render_headline, rewrite_section, section_of

ROOT = Path(__file__).resolve().parent.parent
MODELS = ("shallow", "deep", "equivariant")


def _conditions(names, base=0.09461):
    out = {}
    for i, c in enumerate(names):
        e = {"pos_err_3d_mean": base / (i + 1), "pos_err_xy_mean": 0.04791 / (i + 1),
             "pos_err_z_mean": 0.07412 / (i + 1), "pos_err_3d_peak": 0.5103 / (i + 1),
             "vel_err_3d_mean": 0.1213 / (i + 1), "vel_err_xy_mean": 0.08,
             "vel_err_z_mean": 0.05, "crash_rate": 0.2 if c == "shallow" else 0.0, "failed_flights": []}
        e["per_seed"] = {k: [v] for k, v in e.items() if isinstance(v, float)} | {"crashed": [False]}
        if c not in ("baseline", "no_downwash"):
            e.update(improvement_pos_3d=0.7834 - 0.1 * i, improvement_pos_z=0.9031 - 0.1 * i, improvement_vel_3d=0.5)
        if c not in ("baseline", "no_downwash", "oracle"):
            e["gap_to_oracle_pos_3d"] = 0.04412 / i
        out[c] = e
    return out


def _fakes():
    """name -> (module, args class name, results) mirroring what each experiment writes."""
    floor = {"rmse": 0.1204, "rmse_axis": [0.1, 0.1, 0.1], "rmse_mean": 0.09312, "rmse_axis_mean": [0.09, 0.09, 0.09],
             "n_samples": 50652}
    stages = [{"stage": k, "separation": sep, "minutes": 5.7, "samples": 16884 + k, "failed_flights": fails,
               "deployed_model": None if k == 0 else f"runs/pipeline/x/collection/stage{k - 1}/equivariant.pt",
               "deployed_val_rmse": rmse}
              for k, sep, rmse, fails in ((0, [1.35, 1.75], None, []), (1, [0.85, 1.35], 0.1351, []),
                                          (2, [0.45, 0.65], 0.2054, ["flight 7: ground collision at t = 3.1 s"]))]
    staged = {"stages": stages, "training_minutes": 17.1, "validation_minutes": 17.05, "noise_floor": floor,
              "models": {k: {"path": f"m/{k}.pt", "val_rmse": v, "train_seconds": t}
                         for k, v, t in zip(MODELS, (0.1603, 0.1331, 0.1052), (3.1, 21.7, 8.04))},
              "collection_dir": "c", "models_dir": "m", "provenance": {"field": {"type": "sim.field.DownwashField"}},
              "provenance_key": "0123456789ab", "wall_seconds": 95.27}
    minutes = [1.0, 3.0, 4.0, 10.0, 14.0, 16.93]
    efficiency = {"minutes": minutes, "trials": 5, "noise_floor": 0.09312, "noise_floor_applied": 0.1204,
                  "validation_minutes": 17.05, "wall_seconds": 300.0,
                  "claim": {"statement": "equivariant at 5 min < min(shallow, deep) at 15 min", "n": 10,
                            "mean_difference": -0.0123, "ci_low": -0.02, "ci_high": -0.004, "fraction_holds": 0.9},
                  "models": {k: {"rmse_mean": [0.3 - 0.01 * j - 0.02 * i for i in range(6)],
                                 "rmse_std": [0.011 + 0.001 * i for i in range(6)], "rmse_runs": [[0.3]] * 6}
                             for j, k in enumerate(MODELS)}}
    maps = {"speed": 0.5, "truth": {"down_top_max": 9.1, "down_side_max": 12.2},
            "maps": {k: {"down_top_rmse_vs_truth": 0.0521 * (j + 1), "down_side_rmse_vs_truth": 0.2361 * (j + 1),
                         "lateral_rmse_vs_truth_pos": 0.04313 * (j + 1), "lateral_rmse_vs_truth_neg": 0.04297 * (j + 1)}
                     for j, k in enumerate(MODELS)}}
    bench = {"cpu_count": 2, "mujoco": "3.3.0", "quick": False, "batched_worlds": 64, "bare_mj_step_per_s": 131912.4,
             "real_time_factor_serial": 107.26, "batched_over_bare": 1.2514, "predictor_us_per_call_batch64": 195.33,
             "train_seconds_equivariant_full": 8.012, "serial_over_bare": 0.6412, "rounds": 15,
             "targets": {"serial_over_bare": 0.6, "batched_over_bare": 1.7, "batched_over_mujoco_rollout": 0.9},
             "ratio_intervals": {"serial_over_bare": [0.62, 0.66], "batched_over_bare": None},
             "mujoco_batch_over_bare": 2.059, "mujoco_batch_world_steps_per_s": 271603.2,
             "closed_loop_batched_world_steps_per_s": 165076.3, "mujoco_rollout_world_steps_per_s": 268410.7,
             "batched_over_mujoco_rollout": 0.6149, "formation5_batched_world_steps_per_s": 98213.9,
             "formation5_mujoco_rollout_world_steps_per_s": 151932.4, "formation5_batched_over_mujoco_rollout": 0.6464}
    conds = ("no_downwash", "baseline", "oracle", "shallow", "deep", "equivariant")
    lem = {"experiment": "lemniscate", "separation": 0.6, "duration": 20.0, "seeds": [0, 1, 2, 3, 4],
           "conditions": _conditions(conds), "wall_seconds": 20.0, "flight_wall_seconds": 19.0}
    field_table = {"fields": [], "table": {
        f: {"wall_seconds": 51.3 + i, "seeds": 5, "duration": 20.0, "pipeline_key": "k",
            "conditions": {c: {"improvement_pos_3d": None if c in ("baseline", "no_downwash") else 0.6123 - 0.1 * i,
                               "improvement_pos_z": None, "pos_err_3d_mean": 0.0811,
                               "gap_to_oracle_pos_3d": None if c in ("baseline", "no_downwash", "oracle") else 0.01234,
                               "crash_rate": 0.0} for c in conds}}
        for i, f in enumerate(("momentum", "so2"))}}
    outdoor = {**lem, "experiment": "outdoor", "leader": "circle", "speed": 1.5, "lateral": 0.1,
               "leader_airspeed": {"mean": 2.31, "min": 0.5123, "max": 3.4871},
               "wind": {"mean": [2.0, 0.0, 0.0], "w20": 7.717, "sigma_u": 1.515, "L_u": 47.23}}
    swarm_names = ["baseline", "oracle", "summed_pairwise", "deepsets_equivariant-mixed"]
    swarm_summary = {law: {preset: {c: {"improvement_pos_3d": (None, 0.4, 0.2, 0.1)[j],
                                        "gap_to_oracle_pos_3d": None if j < 2 else 0.0123 * j,
                                        "pos_err_3d_mean": 0.1, "crash_rate": 0.0}
                                    for j, c in enumerate(swarm_names)} for preset in ("stack3", "swap")}
                     for law in ("linear", "velocity")}
    swarm = {"conditions": swarm_names, "seeds": [0, 1, 2], "summary": swarm_summary,
             "laws": {law: {"law": {"name": law}} for law in ("linear", "velocity")}}
    real = {"data": "ns/data/training", "files": 512, "records": 1895894, "flights": {"train": 184, "test": 43},
            "rejected": [], "read_seconds": 1.93, "samples": {"train": 470961, "test": 401096, "stride": 2},
            "free_air_label": {"n": 270902, "mean": [0.00683, 0.00545, 0.000341], "scatter": [0.318, 0.372, 0.632]},
            "no_model_rmse": 0.54, "wall_seconds": 61.0,
            "models": {k: {"rmse": 0.47, "epochs": 30, "seconds": 9.5, "n_train_pairs": 573848}
                       for k in ("shallow", "deep", "equivariant", "equivariant_general")},
            "per_type": {"L2S": {"n_train": 23371, "n_test": 19360, "rmse": {"none": 0.9332, "shallow": 0.6443,
                                                                         "deep": 0.611, "equivariant": 0.5954,
                                                                         "equivariant_general": 0.5987}}}}
    bandwidth = {"experiment": "observer_bandwidth", "flights_per_stage": 4, "seconds": 28.5, "stages": [[1.35, 1.75]],
                 "criterion": "mean 3-D tracking error of the follower",
                 "rule": "the lowest bandwidth whose paired 95 % interval against the best reaches 0",
                 "controllers": {"lqr": {"best": 16.0, "chosen": 8.0, "candidates": [
                     {"bandwidth": b, "pos_err_3d_mean": e, "minus_best_ci95": ci, "estimation_rms": rms, "crashes": 0}
                     for b, e, ci, rms in ((8.0, 0.01541, [-0.0011, 0.0014], 0.2602),
                                           (16.0, 0.01532, [0.0, 0.0], 0.4641))]}}}
    return {"staged_collection": ("experiments.staged_collection", "StagedArgs", staged),
            "observer_bandwidth": ("experiments.observer_bandwidth", "BandwidthArgs", bandwidth),
            "controller_table": ("experiments.controller_table", "ControllerTableArgs", {
                "experiment": "controller_table", "tracks": ["lemniscate"], "table": {k: {"lemniscate": {
                    "seeds": 10, "duration": 20.0, "conditions": {
                        "baseline": {"pos_err_3d_mean": 0.0948, "improvement_pos_3d": None, "crash_rate": 0.0},
                        "dob": {"pos_err_3d_mean": 0.025, "improvement_pos_3d": 0.736, "crash_rate": 0.1}}}}
                    for k in ("lqr", "indi")}}),
            "real_flights": ("experiments.real_flights", "RealFlightsArgs", real),
            "outdoor": ("experiments.outdoor", "OutdoorArgs", outdoor),
            "swarm": ("experiments.swarm", "SwarmArgs", swarm),
            "swarm_safety": ("experiments.swarm", "SwarmArgs", swarm),
            "field_table": ("experiments.fields", "FieldsArgs", field_table),
            "sample_efficiency": ("experiments.sample_efficiency", "EfficiencyArgs", efficiency),
            "force_maps": ("experiments.force_maps", "ForceMapArgs", maps),
            "benchmark": ("experiments.benchmark", "BenchmarkArgs", bench),
            "lemniscate": ("experiments.tracking", "lemniscate", lem)}


def _write_fakes(runs: Path, names=None) -> dict:
    import importlib

    written = {}
    for name, (module, cls_name, results) in _fakes().items():
        if names is not None and name not in names:
            continue
        mod = importlib.import_module(module)
        cls = mod.args_class(cls_name) if module == "experiments.tracking" else getattr(mod, cls_name)
        args = parse_args(cls, name, ["--out", str(runs / name)])
        pipeline = None if name == "benchmark" else {"pipeline_key": "feedc0ffee12", "pipeline": {}}
        write_results(runs / name, results, args, pipeline)
        written[name] = json.loads((runs / name / "results.json").read_text())
    return written


README = ("# Title\n\nintro text  \n\n## Headline results\n\nhand-typed 0.105 numbers\n\n### sub\n\nmore\n\n"
          "## After\n\ntail\n")
HEADLINE = (HEADLINE_BEGIN, HEADLINE_END, HEADLINE_HEADING)


@pytest.fixture(scope="module")
def transect_run(tmp_path_factory):
    """ONE real quick transect run (baseline and oracle: no models, no collection) into runs/transect."""
    work = tmp_path_factory.mktemp("report")
    proc = subprocess.run([sys.executable, "-m", "experiments.transect", "--quick", "--conditions", "baseline,oracle",
                           "--out", "runs/transect"], cwd=work, capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    return work


def _main(work: Path, *extra: str) -> str:
    return report.main(["--runs", str(work / "runs"), "--results", str(work / "results"),
                        "--docs", str(work / "docs" / "results.md"), "--readme", str(work / "README.md"), *extra])


def _docs(work: Path) -> str:
    return (work / "docs" / "results.md").read_text()


def test_fmt_and_pct():
    assert [fmt(x) for x in (0.09461, 0.2054, 5.7, 107.26, 131912.4, 0.0, None, 3)] == \
        ["0.0946", "0.205", "5.70", "107", "132,000", "0", "-", "3"]
    assert fmt(131912.4, 4) == "131,900" and fmt(1.2514, 4) == "1.251" and pct(0.7834) == "78.3 %" and pct(None) == "-"


def test_report_renders_every_value_and_copies_byte_for_byte(tmp_path, transect_run):
    work = tmp_path
    (work / "runs").mkdir()
    (work / "runs" / "transect").symlink_to(transect_run / "runs" / "transect")
    written = _write_fakes(work / "runs")
    (work / "README.md").write_text(README)
    _main(work)
    for name in (*written, "transect"):  # the committed copy is the experiment's file, byte for byte
        assert (work / "results" / f"{name}.json").read_bytes() == (work / "runs" / name / "results.json").read_bytes()
    text = render(work / "results")
    assert section_of(_docs(work)) == text and _docs(work).startswith(report.RESULTS_PAGE.split(BEGIN)[0] + BEGIN)
    headline = render_headline(work / "results", "docs/results.md")
    assert section_of((work / "README.md").read_text(), HEADLINE_BEGIN, HEADLINE_END) == headline
    assert "[results page](docs/results.md)" in headline and "| condition | lemniscate | transect |" in headline
    lem, tra = written["lemniscate"]["conditions"], json.loads((work / "results" / "transect.json").read_text())
    row = next(line for line in headline.splitlines() if line.startswith("| `oracle`"))
    assert f"| {fmt(lem['oracle']['pos_err_3d_mean'])} ({pct(lem['oracle']['improvement_pos_3d'])}) |" in row
    assert f"| {fmt(tra['conditions']['oracle']['pos_err_3d_mean'])} (" in row
    assert "| `shallow` | " in headline and "| - |" in headline  # the quick transect flew no model
    assert "equivariant 0.105" in headline and "it holds." in headline
    for name in report.EXPERIMENTS:
        assert f"results/{name}.json" in text and "No results yet" not in text
    meta = json.loads((work / "results" / "report.json").read_text())["files"]
    assert set(meta) == set(report.EXPERIMENTS) and meta["benchmark"]["machine"]["cores"] == os.cpu_count()
    assert meta["benchmark"]["machine"]["cpu"] in text and meta["lemniscate"]["written"] in text

    s = written["staged_collection"]
    for st in s["stages"]:
        assert f"| {st['stage']} | {st['separation'][0]:g}-{st['separation'][1]:g} | 5.70 | {st['samples']} |" in text
    assert "| 1 |" in text and "stage0 equivariant | 0.135 |" in text and "stage1 equivariant | 0.205 |" in text
    assert "| equivariant | 0.105 | 13.0 % | 8.04 |" in text and "| deep | 0.133 | 42.9 % | 21.7 |" in text
    # real flights: the models in the order asked for, the lowest error of a row in bold
    assert "| type | train | test | no model | shallow | deep | equivariant | equivariant_general |" in text
    assert "| `L2S` | 23371 | 19360 | 0.933 | 0.644 | 0.611 | **0.595** | 0.599 |" in text
    assert "512 files, 227 flights (0 rejected), 1895894 vehicle records" in text
    # the README's line: the wake types pooled by their test samples (one type here)
    assert ("on the 19360 test samples with a vehicle flying above, trained on other days, the models' RMSE is "
            "`shallow` 0.644, `deep` 0.611, `equivariant` 0.595, `equivariant_general` 0.599 m/s^2, against 0.933 "
            "with no model") in headline
    assert "0.0931 m/s^2" in text and "Failed flights (1): flight 7: ground collision" in text and "95.3 s" in text
    assert "17.1 min of training data, 17.1 min of validation" in text

    e = written["sample_efficiency"]
    for k in MODELS:
        for m, sd in zip(e["models"][k]["rmse_mean"], e["models"][k]["rmse_std"]):
            assert f"{fmt(m)} ± {fmt(sd, 2)}" in text
    assert "16.93 min (full)" in text and "5 trials" in text
    assert ("mean difference -0.0123 m/s^2, 95 % bootstrap interval [-0.0200, -0.0040]; it holds in 90.0 % of the "
            "trials. The claim holds.") in text
    assert "5 min: ours at 4 min, 15 min: ours at 14 min" in text  # nearest points present, said
    assert "| equivariant | 0.240 ± 0.013 | 0.222 | 0.200 ± 0.015 | 0.218 |" in text  # ours beside the paper's
    for paper in ("0.263", "0.255", "0.243", "0.229"):
        assert paper in text

    rows = [line for line in text.splitlines() if line.startswith("| `so2` |") or line.startswith("| `momentum` |")]
    assert rows[0].startswith("| `so2` | 0.0811 | 51.2 % | 51.2 % (+0.012)") and rows[0].endswith("| 52 |")  # so2 first
    assert rows[1].startswith("| `momentum` | 0.0811 | 61.2 % | 61.2 % (+0.012)") and rows[1].endswith("| 51 |")

    assert "airspeed 0.512-3.49 m/s" in text and "sigma_u 1.51 m/s" in text
    # the swarm verdict is computed from the numbers: oracle 0.4, summed_pairwise 0.2 (50 %), the set model 0.1
    assert "summing the pairwise model recovers 50.0 % of the oracle's improvement" in text
    assert "the best condition is `summed_pairwise` with 50.0 %" in text
    assert "| `stack3` | 40.0 % | 20.0 % (+0.025) | 10.0 % (+0.037) |" in text

    for c, v in written["lemniscate"]["conditions"].items():
        row = next(line for line in text.splitlines() if line.startswith(f"| {c} | {fmt(v['pos_err_3d_mean'])} |"))
        for key in ("pos_err_xy_mean", "pos_err_z_mean", "pos_err_3d_peak", "vel_err_3d_mean"):
            assert f"| {fmt(v[key])} |" in row
        n = len(written["lemniscate"]["seeds"])
        assert f"| {crash_cell(v['crash_rate'], n)} |" in row and f"| {pct(v.get('improvement_pos_z'))} |" in row
        if "gap_to_oracle_pos_3d" in v:
            assert f"+{fmt(v['gap_to_oracle_pos_3d'])}" in row
    t = json.loads((work / "results" / "transect.json").read_text())  # the real run's keys render
    for c, v in t["conditions"].items():
        assert f"| {c} | {fmt(v['pos_err_3d_mean'])} | {fmt(v['pos_err_xy_mean'])} |" in text
    assert "36 %" in text and "56 %" in text and "0.181 m" in text and "0.154 m" in text
    assert "A `--quick` smoke run" in text  # the transect run was quick, and the report says so

    for k, v in written["force_maps"]["maps"].items():
        assert f"| {k} | {fmt(v['down_top_rmse_vs_truth'])} | {fmt(v['down_side_rmse_vs_truth'])} |" in text
    for k, v in written["benchmark"].items():
        if isinstance(v, float):
            assert f"| `{k}` | {fmt(v, 4)} |" in text
    # the speed section leads the page, with what users ask first; the aims below, one reached, one not
    assert text.index("## Speed") < min(text.index(f"## {title}") for name, (title, _) in report.EXPERIMENTS.items()
                                        if name != "benchmark")
    b = written["benchmark"]
    summary = text.split("## Speed", 1)[1].split("### The benchmark's full record", 1)[0]
    assert f"times real time | {fmt(b['real_time_factor_serial'])} |" in summary
    assert f"no control at all, world-steps/s | {fmt(b['mujoco_batch_world_steps_per_s'])} | 2.06x one bare" in summary
    # each scene's batched flights against MuJoCo's rollout of it, one row each (no swarm keys here: no row)
    assert ("the pair, 64 worlds in one batch against MuJoCo's own rollout of the same scene (`mujoco.rollout`, no "
            f"control), world-steps/s | {fmt(b['closed_loop_batched_world_steps_per_s'])} | 0.615x of MuJoCo's rollout "
            f"({fmt(b['mujoco_rollout_world_steps_per_s'])} world-steps/s) |") in summary
    assert (f"`formation5` (five vehicles), 64 worlds in one batch against MuJoCo's own rollout of the same scene "
            f"(`mujoco.rollout`, no control), world-steps/s | {fmt(b['formation5_batched_world_steps_per_s'])} | "
            f"0.646x of MuJoCo's rollout ({fmt(b['formation5_mujoco_rollout_world_steps_per_s'])} world-steps/s) |"
            ) in summary
    assert summary.count("x of MuJoCo's rollout") == 2
    assert "| `batched_over_mujoco_rollout` | >= 0.9 | 0.615 | - | no |" in text
    assert ">= " not in summary  # no aims in the summary
    assert "| `serial_over_bare` | >= 0.6 | 0.641 | 0.620 to 0.660 | yes |" in text
    assert "| `batched_over_bare` | >= 1.7 | 1.25 | - | no |" in text
    assert "pipeline key `feedc0ffee12`" in text and "seed 0" in text and "field built-in" in text
    assert f"at {written['benchmark']['provenance']['code']['commit'][:12]}" in text


def test_missing_files_are_named(tmp_path):
    _write_fakes(tmp_path / "runs", names={"benchmark"})
    (tmp_path / "README.md").write_text(README)
    _main(tmp_path)
    text = render(tmp_path / "results")
    for name in report.EXPERIMENTS:
        assert (f"No results yet for `{name}`" in text) == (name != "benchmark")
    nothing = render(tmp_path / "nowhere")
    assert nothing.count("No results yet for") == len(report.EXPERIMENTS)
    assert "No results have been copied yet" in nothing
    assert "No tracking results yet" in render_headline(tmp_path / "nowhere")
    assert "No tracking results yet" in (tmp_path / "README.md").read_text()


def test_rewrite_keeps_the_outside_and_is_idempotent(tmp_path):
    B, E = HEADLINE_BEGIN, HEADLINE_END
    first = rewrite_section(README, "one\n", *HEADLINE)
    head, tail = README.split("\n## Headline results\n")[0], "## After\n\ntail\n"
    assert first == (head + "\n## Headline results\n\n" + B + "\none\n" + E + "\n\n" + tail)
    assert "hand-typed" not in first and rewrite_section(first, "one\n", *HEADLINE) == first
    second = rewrite_section(first, "two\nlines\n", *HEADLINE)
    assert second.replace(f"{B}\ntwo\nlines\n{E}", f"{B}\none\n{E}") == first
    assert section_of(second, B, E) == "two\nlines\n" and section_of(second) is None
    at_end = rewrite_section("# T\n\n## Headline results\n\nold\n", "x\n", *HEADLINE)
    assert at_end == f"# T\n\n## Headline results\n\n{B}\nx\n{E}\n"
    # the results page: the section goes below its level-1 heading, '## ' headings included
    page = rewrite_section("# Results\n\n## Speed\n\nold\n", "## Speed\n\nnew\n")
    assert page == f"# Results\n\n{BEGIN}\n## Speed\n\nnew\n{END}\n" and section_of(page) == "## Speed\n\nnew\n"
    for bad in ("# no heading\n", f"## Headline results\n{E}\n{B}\n",
                "## Headline results\n## Headline results\n"):
        with pytest.raises(ConfigError):
            rewrite_section(bad, "x\n", *HEADLINE)

    _write_fakes(tmp_path / "runs", names={"force_maps"})
    (tmp_path / "README.md").write_text(README)
    _main(tmp_path)
    once = _docs(tmp_path)
    _main(tmp_path, "--runs", "")  # re-render only
    assert _docs(tmp_path) == once
    record_path = tmp_path / "results" / "report.json"  # an old copy date, to see whether a rerun touches it
    record = json.loads(record_path.read_text())
    record["files"]["force_maps"]["copied"] = "2000-01-01 00:00 UTC"
    atomic_write_json(record_path, record)
    _main(tmp_path, "--runs", "")
    once = _docs(tmp_path)
    _main(tmp_path)  # the unchanged file copied again: its record, and so the page, stay as they were
    assert _docs(tmp_path) == once and "2000-01-01 00:00 UTC" in once
    results = tmp_path / "runs" / "force_maps" / "results.json"
    results.write_text(results.read_text().replace('"speed": 0.5', '"speed": 0.25'))
    _main(tmp_path)  # a changed file is copied with a new record
    assert "2000-01-01" not in _docs(tmp_path)


def test_check_fails_on_a_stale_section_and_passes_after_regeneration(tmp_path):
    _write_fakes(tmp_path / "runs", names={"force_maps", "benchmark", "lemniscate"})
    readme, docs = tmp_path / "README.md", tmp_path / "docs" / "results.md"
    readme.write_text(README)
    with pytest.raises(ConfigError, match="--results: .* does not exist"):  # --check copies nothing: no results
        _main(tmp_path, "--check")
    report.copy_results(tmp_path / "runs", tmp_path / "results")
    with pytest.raises(SystemExit) as e:  # no markers yet, no results page: stale
        _main(tmp_path, "--check")
    assert e.value.code == 1 and readme.read_text() == README and not docs.exists()
    _main(tmp_path)
    _main(tmp_path, "--check")
    for page, number in ((docs, fmt(0.0521)), (readme, fmt(0.09461))):  # a hand-typed edit inside the markers
        good = page.read_text()
        stale = good.replace(number, "0.0999")
        assert stale != good
        page.write_text(stale)
        with pytest.raises(SystemExit):
            _main(tmp_path, "--check")
        assert page.read_text() == stale
        _main(tmp_path, "--runs", "")
        _main(tmp_path, "--check")
        assert page.read_text() == good


@pytest.mark.parametrize("case", ["missing", "empty", "garbage", "foreign"])
def test_bad_runs_folder_fails_before_writing(tmp_path, case):
    runs = tmp_path / "runs"
    if case != "missing":
        runs.mkdir()
    if case in ("garbage", "foreign"):
        _write_fakes(runs, names={"benchmark"})  # a good file that must not be copied either
        (runs / "lemniscate").mkdir()
        (runs / "lemniscate" / "results.json").write_text("{not json" if case == "garbage" else '{"minutes": []}')
    (tmp_path / "README.md").write_text(README)
    message = {"missing": "is not a folder", "empty": "holds no", "garbage": "not a readable JSON",
               "foreign": "not a lemniscate results file (missing conditions, seeds)"}[case]
    with pytest.raises(ConfigError, match=re.escape(message)):
        _main(tmp_path)
    assert not (tmp_path / "results").exists() and (tmp_path / "README.md").read_text() == README
    assert not (tmp_path / "docs").exists()


def test_committed_pages_are_generated_from_committed_results():
    """The guard: result numbers are never typed by hand, neither in the docs' results page nor in the
    README's headline table. Regenerate both with `python -m experiments.report --runs ''`."""
    page = (ROOT / "docs" / "results.md").read_text()
    assert page.count(BEGIN) == 1 and page.count(END) == 1 and page.startswith("# Results\n")
    assert section_of(page) == render(ROOT / "results")
    readme = (ROOT / "README.md").read_text()
    assert readme.count(HEADLINE_BEGIN) == 1 and readme.count(HEADLINE_END) == 1
    assert readme.index(f"\n{HEADLINE_HEADING}\n") < readme.index(HEADLINE_BEGIN)
    assert section_of(readme, HEADLINE_BEGIN, HEADLINE_END) == render_headline(ROOT / "results", "docs/results.md")
    report.main(["--runs", "", "--results", str(ROOT / "results"), "--docs", str(ROOT / "docs" / "results.md"),
                 "--readme", str(ROOT / "README.md"), "--check"])


def test_results_older_than_the_golden_records_are_stale(tmp_path):
    """`--check` refuses results whose code predates the last commit that moved a golden number."""
    import subprocess

    def git(*args):
        return subprocess.run(["git", *args], cwd=tmp_path, capture_output=True, text=True, check=True).stdout.strip()

    git("init", "-q")
    git("config", "user.email", "t@t"), git("config", "user.name", "t")
    (tmp_path / "code.py").write_text("1\n")
    git("add", "."), git("commit", "-qm", "code")
    old = git("rev-parse", "HEAD")
    (tmp_path / "tests" / "golden").mkdir(parents=True)
    (tmp_path / "tests" / "golden" / "pipeline.json").write_text("{}\n")
    git("add", "."), git("commit", "-qm", "moves a golden number")
    new = git("rev-parse", "HEAD")
    found = {"lemniscate": {"provenance": {"code": {"commit": old}}}, "transect": {"code": {"commit": new}},
             "benchmark": {}, "swarm": {"provenance": {"code": {"commit": "f" * 40}}}}
    stale = report.stale_results(found, repo=tmp_path)
    assert [s.split(":")[0] for s in stale] == ["lemniscate", "benchmark", "swarm"]
    assert "before" in stale[0] and "no code commit" in stale[1] and "not in this repository" in stale[2]
    assert report.stale_results({"transect": found["transect"]}, repo=tmp_path) == []


def _outdoor_point(improvement, crash=0.0):
    return {"improvement_pos_3d": improvement, "crash_rate": crash}


def test_the_outdoor_verdicts_follow_the_numbers():
    """Memory on the shed truth at 2 m/s and above (the mean over those speeds, memory against its
    memoryless twin) and equivariance (best against best, per training data), read from the results."""
    from experiments.report.sections import equivariance_verdict, memory_verdict

    speeds = [0.5, 2.0, 3.0]
    sweep = {"speeds": speeds, "conditions": {
        "equivariant_memory-outdoor": {"improvement_pos_3d": [0.9, 0.5, 0.3], "crash_rate": [0, 0, 0]},
        "equivariant_general-outdoor": {"improvement_pos_3d": [0.0, 0.2, 0.2], "crash_rate": [0, 0, 0]},
        "deep_memory-outdoor": {"improvement_pos_3d": [0.0, 0.1, 0.1], "crash_rate": [0, 0, 0]},
        "deep-outdoor": {"improvement_pos_3d": [0.9, 0.1, 0.11], "crash_rate": [0, 0, 0]}}}
    r = {"conditions": {"baseline": {}, "oracle": _outdoor_point(0.7), "deep": _outdoor_point(0.1),
                        "equivariant": _outdoor_point(-2.0, 1.0), "deep-outdoor": _outdoor_point(0.05),
                        "equivariant-outdoor": _outdoor_point(0.4)},
         "truths": {"shed": {"sweep": sweep}}}
    memory = memory_verdict(r)
    assert "`equivariant_memory-outdoor` 40.0 % against `equivariant_general-outdoor` 20.0 %: memory helps" in memory
    assert "`deep_memory-outdoor` 10.0 % against `deep-outdoor` 10.5 %: memory makes no clear difference" in memory
    assert "at 2, 3 m/s" in memory  # the slow point is left out
    assert "memory helps (+20.0 points)" in memory and "the wake's memory" not in memory  # (no control truth)
    # a truth without memory is the control: there the history's gain is not the wake's memory
    control = {"speeds": speeds, "conditions": {
        "equivariant_memory-outdoor": {"improvement_pos_3d": [0.0, 0.4, 0.4], "crash_rate": [0, 0, 0]},
        "equivariant_general-outdoor": {"improvement_pos_3d": [0.0, 0.3, 0.25], "crash_rate": [0, 0, 0]}}}
    memory = memory_verdict({**r, "truths": {"shed": {"sweep": sweep}, "momentum": {"sweep": control}}})
    assert ("memory helps (+20.0 points); on the `momentum` truth, which has no memory, the same models differ by "
            "+12.5 points, so the wake's memory accounts for +7.5 points") in memory
    assert "`deep_memory-outdoor` 10.0 % against `deep-outdoor` 10.5 %: memory makes no clear difference (-0.5 " \
           "points)." in memory  # (the control lacks the deep pair: no control for it)
    verdict = equivariance_verdict(r)
    assert "indoor data, the best equivariant model `equivariant` -200.0 % against the best non-equivariant " \
           "`deep` 10.0 %: it does not pay" in verdict
    assert "`equivariant-outdoor` 40.0 % against the best non-equivariant `deep-outdoor` 5.0 %: it pays" in verdict
    assert memory_verdict({"conditions": {}}) is None  # no shed sweep: no statement


def test_the_worst_case_table_takes_each_models_worst_setting():
    """Over the tracking runs, the outdoor sweeps and truths, the field table and the swarm, unguarded and
    guarded apart; the references are not models."""
    from experiments.report.sections import render_worst_cases, worst_cases

    found = {
        "lemniscate": {"conditions": {"baseline": {}, "oracle": _outdoor_point(0.8),
                                      "deep": _outdoor_point(0.6), "deep_guarded": _outdoor_point(0.59)}},
        "outdoor": {"conditions": {"deep": _outdoor_point(-0.1), "deep_guarded": _outdoor_point(0.0)},
                    "sweep": {"speeds": [1.0, 3.0], "conditions": {
                        "deep": {"improvement_pos_3d": [0.1, -2.5], "crash_rate": [0.0, 0.8]},
                        "deep_guarded": {"improvement_pos_3d": [0.1, -0.01], "crash_rate": [0.0, 0.0]}}},
                    "truths": {"shed": {"sweep": {"speeds": [2.0], "conditions": {
                        "deep_guarded": {"improvement_pos_3d": [-0.02], "crash_rate": [0.0]}}}}}},
        "swarm": {"summary": {"linear": {"stack3": {"baseline": {"crash_rate": 0.5},
                                                    "deepsets-pair": _outdoor_point(-0.3),
                                                    "deepsets-pair_guarded": _outdoor_point(0.05, 1 / 3)}}}},
    }
    worst = worst_cases(found)
    assert set(worst) == {"deep", "deepsets-pair"}
    assert worst["deep"]["unguarded"] == (-2.5, "outdoor, 3 m/s", 0.8)
    assert worst["deep"]["guarded"] == (-0.02, "outdoor on shed, 2 m/s", 0.0)
    assert worst["deepsets-pair"]["guarded"] == (0.05, "swarm stack3, linear", 1 / 3)
    assert worst["deepsets-pair"]["guarded_crashes"] == (1 / 3, "swarm stack3, linear", 0.5)  # and the baseline's
    assert "guarded_crashes" not in worst["deep"]
    table = render_worst_cases(found)
    assert "| `deep` | -250.0 % (outdoor, 3 m/s, 80.0 % crashed) | -2.0 % (outdoor on shed, 2 m/s) | none |" in table
    assert "| 33.3 % (swarm stack3, linear; baseline 50.0 %) |" in table
    assert render_worst_cases({"lemniscate": found["lemniscate"] | {"conditions": {"deep": _outdoor_point(0.5)}}}) is None


def test_the_outdoor_section_says_how_much_error_is_the_downwash_and_what_the_stages_flew_with():
    """From the sweep's errors: the baseline against no downwash at all, at each speed; from the outdoor
    collection: how much of the deployed model the guard applied."""
    from experiments.report.sections import _own_error

    sweep = {"speeds": [1.0, 3.0], "conditions": {
        "baseline": {"improvement_pos_3d": [None, None], "crash_rate": [0, 0], "pos_err_3d_mean": [0.3, 0.35]},
        "no_downwash": {"improvement_pos_3d": [None, None], "crash_rate": [0, 0], "pos_err_3d_mean": [0.07, 0.33]}}}
    text = _own_error(sweep)
    assert "0.300 / 0.0700 m at 1 m/s, 0.350 / 0.330 m at 3 m/s" in text and "the oracle included" in text
    assert _own_error({"speeds": [1.0], "conditions": {"baseline": {"improvement_pos_3d": [None]}}}) is None
    assert _own_error({"speeds": [1.0], "conditions": {  # (results written before the errors were kept)
        "baseline": {"pos_err_3d_mean": [0.3]}, "no_downwash": {"pos_err_3d_mean": [None]}}}) is None
    from experiments.report.sections import render_outdoor

    outdoor = _fakes()["outdoor"][2]
    regime = {**outdoor, "conditions": {**outdoor["conditions"], "deep-outdoor": outdoor["conditions"]["deep"]},
              "outdoor_collection": {"minutes": 7.0, "stages": [{"deployed_applied": 0.0}, {"deployed_applied": 0.0123}]}}
    assert ("flown with the indoor equivariant model behind the guard, which applied 0.0 %-1.2 % of its prediction "
            "on average per stage") in render_outdoor(regime, "x")
    regime["outdoor_collection"]["stages"] = [{"name": "outdoor-still"}]  # (results written before the guard flew)
    assert "flown with no model" in render_outdoor(regime, "x")


# What the docs say of the results files, since nothing guards their numbers (checked below).
UNCHECKED = ("The results files are not checked for integrity: they carry no digest, so the report renders any "
             "edit to one that still parses and has its experiment's keys.")


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """runs/ with every fake results file, results/ copied from it, and the README and the results page
    generated from them: a checkout whose pages show results."""
    work = tmp_path_factory.mktemp("generated")
    _write_fakes(work / "runs")
    (work / "README.md").write_text(README)
    _main(work)
    return work


def _copy(generated: Path, tmp_path: Path) -> Path:
    work = tmp_path / "work"
    shutil.copytree(generated, work, symlinks=True)
    return work


def _pages_of(work: Path) -> tuple[bytes, bytes]:
    return (work / "README.md").read_bytes(), (work / "docs" / "results.md").read_bytes()


def _render_only(work: Path, results, *extra: str) -> str:
    return report.main(["--runs", "", "--results", str(results), "--docs", str(work / "docs" / "results.md"),
                        "--readme", str(work / "README.md"), *extra])


def test_a_results_folder_that_is_missing_or_holds_no_results_is_refused(generated, tmp_path):
    work = _copy(generated, tmp_path)
    before = _pages_of(work)
    # the command line: a mistyped folder is one line naming --results, exit 2, and both pages stay as they were
    proc = subprocess.run([sys.executable, "-m", "experiments.report", "--runs", "", "--results", "resultz"],
                          cwd=work, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr.startswith("error: --results: resultz does not exist")
    assert proc.stderr.count("\n") == 1 and proc.stdout == "" and _pages_of(work) == before
    (work / "empty").mkdir()
    (work / "only_record").mkdir()
    (work / "only_record" / "report.json").write_text('{"files": {}}')
    (work / "a_file").write_text("x")
    for results, message in ((work / "empty", "holds none of"), (work / "only_record", "holds none of"),
                             (work / "a_file", "is not a folder")):
        with pytest.raises(ConfigError, match=f"--results: {re.escape(str(results))} {message}"):
            _render_only(work, results)
        with pytest.raises(ConfigError, match="--results"):  # --check renders from the same folder
            _render_only(work, results, "--check")
        assert _pages_of(work) == before
    # asked for explicitly, every section says it has no results
    assert "--allow-empty" in subprocess.run([sys.executable, "-m", "experiments.report", "--help"], cwd=work,
                                             capture_output=True, text=True, timeout=120).stdout
    _render_only(work, work / "empty", "--allow-empty")
    docs = _docs(work)
    assert all(f"No results yet for `{name}`" in docs for name in report.EXPERIMENTS)
    assert "No tracking results yet" in (work / "README.md").read_text()


def test_a_section_that_shows_results_is_not_replaced_by_an_empty_one(generated, tmp_path):
    work = _copy(generated, tmp_path)
    before = _pages_of(work)
    (work / "speed_only").mkdir()  # results the README's headline does not show
    (work / "speed_only" / "benchmark.json").write_bytes((work / "results" / "benchmark.json").read_bytes())
    with pytest.raises(ConfigError, match=re.escape(f"{work / 'README.md'}: ") + ".*replaced by an empty one.*"
                                          "--allow-empty"):
        _render_only(work, work / "speed_only")
    assert _pages_of(work) == before  # the results page, which would have had something, is not written either
    # copying into a new folder the same way: refused before the copy
    runs = tmp_path / "speed_runs"
    _write_fakes(runs, names={"benchmark"})
    with pytest.raises(ConfigError, match="replaced by an empty one"):
        report.main(["--runs", str(runs), "--results", str(tmp_path / "fresh"), "--docs",
                     str(work / "docs" / "results.md"), "--readme", str(work / "README.md")])
    assert not (tmp_path / "fresh").exists() and _pages_of(work) == before
    _render_only(work, work / "speed_only", "--allow-empty")
    assert "No tracking results yet" in (work / "README.md").read_text()
    assert "No results yet for `benchmark`" not in _docs(work)


def test_a_symlinked_page_or_results_file_is_written_through_and_keeps_its_mode(tmp_path):
    _write_fakes(tmp_path / "runs", names={"benchmark", "lemniscate"})
    real = tmp_path / "real"
    real.mkdir()
    (real / "README.md").write_text(README)
    (real / "results.md").write_text(report.RESULTS_PAGE)
    (real / "benchmark.json").write_text("{}\n")  # an old copy, replaced through the link
    for name, mode in (("README.md", 0o640), ("results.md", 0o604), ("benchmark.json", 0o600)):
        os.chmod(real / name, mode)
    (tmp_path / "docs").mkdir()
    (tmp_path / "results").mkdir()
    links = {tmp_path / "README.md": real / "README.md", tmp_path / "docs" / "results.md": real / "results.md",
             tmp_path / "results" / "benchmark.json": real / "benchmark.json"}
    for link, target in links.items():
        link.symlink_to(target)
    _main(tmp_path)
    for link, target in links.items():
        assert link.is_symlink() and link.resolve() == target, link
    assert section_of((real / "README.md").read_text(), HEADLINE_BEGIN, HEADLINE_END) == \
        render_headline(tmp_path / "results", "docs/results.md")
    assert section_of((real / "results.md").read_text()) == render(tmp_path / "results")
    assert (real / "benchmark.json").read_bytes() == (tmp_path / "runs" / "benchmark" / "results.json").read_bytes()
    assert {n: (real / n).stat().st_mode & 0o7777 for n in ("README.md", "results.md", "benchmark.json")} == \
        {"README.md": 0o640, "results.md": 0o604, "benchmark.json": 0o600}
    assert sorted(p.name for p in real.iterdir()) == ["README.md", "benchmark.json", "results.md"]  # no temp files
    # a link to nothing is refused by name: writing would create a file nobody named
    dangling = tmp_path / "docs" / "results.md"
    dangling.unlink()
    dangling.symlink_to(real / "gone.md")
    before = (real / "README.md").read_bytes()
    with pytest.raises(ConfigError, match=re.escape(f"--docs: {dangling} is a link to {real / 'gone.md'}, which "
                                                    "does not exist")):
        _main(tmp_path, "--runs", "")
    assert not (real / "gone.md").exists() and (real / "README.md").read_bytes() == before


@pytest.mark.parametrize("name,data", [
    ("lemniscate", b'{"conditions": {'), ("lemniscate", b"\xff\xfe{}"), ("lemniscate", b'{"seeds": "\xe9"}'),
    ("benchmark", b""), ("lemniscate", b"null"), ("force_maps", b"[1, 2]"), ("swarm", b'{"conditions": []}'),
    ("report", b"[]"), ("report", b'{"files": {"benchmark": 3}}')],
    ids=["bad-json", "not-utf8", "not-utf8-in-a-string", "empty", "null", "a-list", "missing-keys",
         "record-a-list", "record-entry-a-number"])
def test_an_unreadable_results_file_is_a_named_error(generated, tmp_path, name, data):
    work = _copy(generated, tmp_path)
    path = work / "results" / f"{name}.json"
    path.write_bytes(data)
    before = _pages_of(work)
    with pytest.raises(ConfigError) as e:
        _render_only(work, work / "results")
    assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)
    assert _pages_of(work) == before
    if name == "lemniscate" and data == b"null":  # on the command line: one line, exit 2, no traceback
        proc = subprocess.run([sys.executable, "-m", "experiments.report", "--runs", "", "--check"], cwd=work,
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and proc.stderr == f"error: {Path('results') / 'lemniscate.json'}: not a " \
                                                       "lemniscate results file (missing conditions, seeds)\n"


def test_flipped_bytes_in_a_results_file_are_refused_by_name_or_rendered(generated, tmp_path):
    """Results files carry no digest, so a changed byte is either caught (the file no longer parses or
    no longer renders: one line naming the file) or rendered as it is, which the docs say plainly."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    for page in (ROOT / "docs" / "results.md", ROOT / "docs" / "experiments.md"):
        assert UNCHECKED in " ".join(page.read_text().split()), page
    work = _copy(generated, tmp_path)
    files = sorted((work / "results").glob("*.json"))
    originals = {p: p.read_bytes() for p in files}

    @settings(max_examples=40, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
    @given(st.data())
    def flip(data):
        path = data.draw(st.sampled_from(files))
        raw = bytearray(originals[path])
        for _ in range(data.draw(st.integers(1, 3))):
            raw[data.draw(st.integers(0, len(raw) - 1))] ^= data.draw(st.integers(1, 255))
        path.write_bytes(bytes(raw))
        try:
            _render_only(work, work / "results")
        except ConfigError as e:
            assert str(path) in str(e) and "\n" not in str(e), str(e)
        finally:
            path.write_bytes(originals[path])

    flip()
