"""The results page's sections: one renderer per experiment's results file, and the machine and provenance lines.

`RENDERERS` maps each experiment's name (`experiments.report.results.EXPERIMENTS`) to
the function that renders its results as markdown; `render_one` adds the
provenance line and turns a file the renderer cannot read into a ConfigError.
"""

from __future__ import annotations

import math
from pathlib import Path

from downwash_core.errors import ConfigError
from experiments.common import FIELD_NAMES as FIELDS  # the registry's names, in its order, without importing it
from experiments.report.formatting import ORDER, ordered, markdown_table, crash_cell, fmt, pct, short
from experiments.report.criteria import settings_points
from experiments.report.baselines import (render_controller_table, render_field_baselines,
                                         render_learning_over_baselines, render_observer_bandwidth,
                                         render_swarm_baselines)
from experiments.report.real_flights import render_real_flights
from experiments.report.safety import render_swarm_safety
from experiments.report.speed import render_benchmark

__all__ = [
    "TRACKED", "PAPER_RMSE", "RENDERERS", "render_machine", "render_provenance", "render_staged", "render_efficiency",
    "render_tracking", "render_outdoor", "render_swarm", "render_force_maps", "render_benchmark", "render_field_table",
    "render_real_flights", "worst_cases", "render_worst_cases", "RENDER_ERRORS", "render_error",
]

TRACKED = ("pos_err_3d_mean", "pos_err_xy_mean", "pos_err_z_mean", "pos_err_3d_peak", "vel_err_3d_mean")
PAPER_RMSE = {5.0: {"shallow": 0.263, "deep": 0.255, "equivariant": 0.222},  # the paper's figure 3 table, m/s^2
              15.0: {"shallow": 0.243, "deep": 0.229, "equivariant": 0.218}}


def render_machine(record: dict) -> str:
    files = record.get("files", {})
    if not files:
        return "No results have been copied yet: run the experiments, then `python -m experiments.report`."

    def line(m: dict) -> str:
        return (f"{m.get('cpu')}, {m.get('cores')} cores, {m.get('os')}, Python {m.get('python')}, "
                f"mujoco {m.get('mujoco')}, torch {m.get('torch')}")

    dates = sorted(f.get("written", "?") for f in files.values())
    when = f"The results were written {dates[0]}" + (f" to {dates[-1]}" if dates[-1] != dates[0] else "") + "."
    machines = {line(f.get("machine", {})) for f in files.values()}
    if len(machines) == 1:
        return f"{when} Machine (recorded when the report copied them from `runs/`): {machines.pop()}."
    return f"{when} Machines (recorded when the report copied each file from `runs/`):\n\n" + "\n".join(
        f"- `{n}`: {line(f.get('machine', {}))}" for n, f in sorted(files.items()))


def render_provenance(name: str, data: dict, record: dict, label: str) -> str:
    """One line: what made the file (code, seed, field, pipeline key) and when."""
    p, a = data.get("provenance", {}), data.get("args", {})
    code = p.get("code") or {}
    parts = [f"code {code.get('version')} at {(code.get('commit') or 'unknown commit')[:12]}"
             + (" with uncommitted changes" if code.get("dirty") else ""),
             f"seed {p.get('seed', a.get('seed'))}", f"field {p.get('field_spec', a.get('field') or 'built-in')}"]
    if p.get("pipeline_key"):
        parts.append(f"pipeline key `{p['pipeline_key']}`")
    entry = record.get("files", {}).get(name)
    if entry:
        parts.append(f"written {entry.get('written')}, copied {entry.get('copied')}")
    quick = " **A `--quick` smoke run: not a measurement.**" if a.get("quick") else ""
    return f"Provenance of `{label}`: " + ", ".join(parts) + "." + quick


def render_staged(r: dict, label: str) -> str:
    rows, failed = [], []
    for s in r["stages"]:
        dep = s.get("deployed_model")
        rows.append([str(s["stage"]), "-".join(short(x) for x in s["separation"]), fmt(s["minutes"]),
                     str(s["samples"]), "none" if dep is None else f"{Path(dep).parent.name} {Path(dep).stem}",
                     fmt(s["deployed_val_rmse"])])
        failed += s.get("failed_flights", [])
    floor = (r.get("noise_floor") or {}).get("rmse_mean")
    models = [[k, fmt(m["val_rmse"]), pct(m["val_rmse"] / floor - 1) if floor and m["val_rmse"] is not None else "-",
               fmt(m.get("train_seconds"))] for k, m in ordered(r["models"])]
    return "\n\n".join([
        f"Stages (`{label}`):",
        markdown_table(["stage", "separation (m)", "training min", "samples", "deployed model",
                "its val RMSE on this stage (m/s^2)"], rows),
        f"Final models (`{label}`), validation RMSE in m/s^2:",
        markdown_table(["model", "val RMSE", "above the noise floor", "train s"], models),
        f"{fmt(r.get('training_minutes'))} min of training data, {fmt(r.get('validation_minutes'))} min of validation "
        f"data. Label-noise floor (labels against the true mean field): {fmt(floor)} m/s^2. "
        + (f"Failed flights ({len(failed)}): " + "; ".join(failed) + "." if failed else "No flight failed.")
        + (f" The collection and its training took {fmt(r['collection_seconds'])} s"
           f" (this run: {fmt(r.get('wall_seconds'))} s)." if r.get("collection_seconds") is not None
           else f" Wall time {fmt(r.get('wall_seconds'))} s.")])


def render_efficiency(r: dict, label: str) -> str:
    minutes = r["minutes"]
    models = r["models"]

    def cell(k: str, i: int) -> str:
        return f"{fmt(models[k]['rmse_mean'][i])} ± {fmt(models[k]['rmse_std'][i], 2)}" if k in models else "-"

    header = ["model"] + [f"{short(m)} min" for m in minutes[:-1]] + [f"{short(minutes[-1])} min (full)"]
    rows = [[k] + [cell(k, i) for i in range(len(minutes))] for k, _ in ordered(models)]
    nearest = {t: min(range(len(minutes)), key=lambda i: abs(minutes[i] - t)) for t in PAPER_RMSE}
    said = ", ".join(f"{short(t)} min: ours at {short(minutes[i])} min" for t, i in nearest.items())
    paper_rows = [[k] + [c for t, i in nearest.items() for c in (cell(k, i), fmt(PAPER_RMSE[t][k]))]
                  for k in PAPER_RMSE[5.0]]
    paper_header = ["model"] + [c for t, i in nearest.items() for c in (f"ours {short(minutes[i])} min",
                                                                          f"paper {short(t)} min")]
    return "\n\n".join([
        f"Validation RMSE (m/s^2), mean ± std over {r.get('trials')} trials (`{label}`):",
        markdown_table(header, rows),
        f"Label-noise floor: {fmt(r['noise_floor'])} m/s^2; validation set {fmt(r.get('validation_minutes'))} min.",
        f"Beside the paper's table (its means; nearest point present, {said}; `{label}`):",
        markdown_table(paper_header, paper_rows)] + ([_claim(r["claim"])] if r.get("claim") else []))


def _claim(c: dict) -> str:
    """The paired test of the paper's claim, and whether it holds (the 95 % interval excludes 0)."""
    holds = c["ci_high"] < 0
    refuted = c["ci_low"] > 0
    verdict = "holds" if holds else ("does not hold" if refuted else "is not established: the interval contains 0")
    return (f"The paper's claim, \"{c['statement']}\", paired over {c['n']} trials (the same data subsets for every "
            f"model): mean difference {c['mean_difference']:+.4f} m/s^2, 95 % bootstrap interval "
            f"[{c['ci_low']:+.4f}, {c['ci_high']:+.4f}]; it holds in {pct(c['fraction_holds'])} of the trials. "
            f"The claim {verdict}.")


def render_tracking(r: dict, label: str) -> str:
    rows = []
    guarded = any("compensation" in e for e in r["conditions"].values())
    for c, e in ordered(r["conditions"]):
        gap = e.get("gap_to_oracle_pos_3d")
        rows.append([c] + [fmt(e[k]) for k in TRACKED] + [pct(e.get(f"improvement_pos_{k}")) for k in ("3d", "z")]
                    + ["-" if gap is None else ("+" if gap >= 0 else "-") + fmt(abs(gap)),
                       crash_cell(e["crash_rate"], len(r["seeds"]))]
                    + ([_shares(e.get("compensation"))] if guarded else []))
    header = ["condition", "pos 3D (m)", "pos xy", "pos z", "peak 3D", "vel 3D (m/s)", "improvement 3D",
              "improvement z", "gap to oracle (m)", "crash rate (Wilson 95 %)"] + (["applied: full / partial / none"] if guarded else [])
    over = render_learning_over_baselines(r["conditions"], len(r["seeds"]))
    return "\n\n".join([f"{len(r['seeds'])} seeds, {short(r['separation'])} m below the leader, "
                        f"{short(r['duration'])} s (`{label}`):", markdown_table(header, rows)] + ([over] if over else []))


def _shares(c: dict | None) -> str:
    """A guarded condition's shares of ticks at full, partial and no compensation."""
    return "-" if c is None else f"{pct(c['full'])} / {pct(c['partial'])} / {pct(c['none'])}"


def render_outdoor(r: dict, label: str) -> str:
    a, wind = r["leader_airspeed"], r.get("wind")
    if wind is None:
        air = "no wind"
    else:
        air = (f"wind: mean ({', '.join(short(x) for x in wind['mean'])}) m/s plus Dryden gusts (W20 {fmt(wind['w20'])} m/s, sigma_u "
               f"{fmt(wind['sigma_u'])} m/s, L_u {fmt(wind['L_u'])} m)")
    c = r["conditions"]
    regime = [k for k in c if k.endswith("-outdoor")]
    made = r.get("outdoor_collection") or {}
    applied = [s["deployed_applied"] for s in made.get("stages", []) if s.get("deployed_applied") is not None]
    flown = ("flown with the indoor equivariant model behind the guard, which applied "
             f"{pct(min(applied))}-{pct(max(applied))} of its prediction on average per stage" if applied
             else "flown with no model")
    trained = ("The models `<kind>` are those of the staged collection (hovering leader, still air)"
               + (f"; `<kind>-outdoor` were trained on those flights plus {fmt(made.get('minutes'))} minutes of "
                  f"outdoor stages ({len(made.get('stages', []))} wind settings from still air to moderate gusts, the "
                  f"leader on lines and circles at 0.5-3 m/s, {flown})." if regime else "."))
    head = (f"The leader flies a {r['leader']} at {short(r['speed'])} m/s (airspeed {fmt(a['min'])}-{fmt(a['max'])} m/s); "
            f"the follower {short(r['separation'])} m beneath it; {air}. {trained}")
    models = [k for k, _ in ordered(c) if k not in ("no_downwash", "baseline", "oracle")]
    best = max(models, key=lambda k: c[k].get("improvement_pos_3d") or -math.inf) if models else None
    crashed = [f"`{k}` ({crash_cell(c[k]['crash_rate'], len(r['seeds']))})" for k in models if c[k].get("crash_rate")]
    verdict = []
    if "oracle" in c and c["oracle"].get("improvement_pos_3d") is not None:
        verdict.append(f"The oracle improves the 3D position error by {pct(c['oracle']['improvement_pos_3d'])} over the "
                       "baseline")
    if best is not None:
        oracle = (c.get("oracle") or {}).get("improvement_pos_3d")
        got = c[best].get("improvement_pos_3d")
        share = "" if not oracle or got is None else f", {pct(got / oracle)} of the oracle's improvement"
        verdict.append(f"the best model, `{best}`, by {pct(got)}{share}")
    if crashed:
        verdict.append("crashes (counted with the crash penalty): " + ", ".join(crashed))
    parts = [head, render_tracking(r, label), "; ".join(verdict) + "."]
    sweep = r.get("sweep")
    if sweep:  # --sweep-speeds: each condition's improvement at each leader speed
        rows = _sweep_rows(sweep["conditions"], len(r["seeds"]))
        parts += ["Improvement of the 3D position error over the baseline against the leader's speed (the same seeds "
                  "and wind at each speed):", markdown_table(["condition"] + [f"{short(v)} m/s" for v in sweep["speeds"]], rows)]
        own = _own_error(sweep)
        if own:
            parts.append(own)
    if r.get("wind_sweep"):  # --sweep-winds: at the run's speed, in each wind
        w = r["wind_sweep"]
        parts += [f"Improvement over the baseline in each wind, the leader at {short(r['speed'])} m/s:",
                  markdown_table(["condition"] + [f"`{spec}`" for spec in w["winds"]], _sweep_rows(w["conditions"], len(r["seeds"])))]
    for truth, t in (r.get("truths") or {}).items():  # --sweep-fields: the whole experiment on each ground truth
        if t.get("sweep"):
            parts += [f"On the `{truth}` truth, improvement over the baseline against the leader's speed:",
                      markdown_table(["condition"] + [f"{short(v)} m/s" for v in t["sweep"]["speeds"]],
                             _sweep_rows(t["sweep"]["conditions"], len(r["seeds"])))]
    verdicts = [v for v in (memory_verdict(r), equivariance_verdict(r)) if v]
    return "\n\n".join(parts + verdicts)


def _own_error(sweep: dict) -> str | None:
    """What the downwash causes at each speed: the baseline's mean 3D error against the same flights with no
    downwash at all (`no_downwash`); what is left without it is the follower's own tracking error, which no
    downwash model, the oracle included, removes."""
    c = sweep["conditions"]
    base, free = ((c.get(k) or {}).get("pos_err_3d_mean") for k in ("baseline", "no_downwash"))
    if not base or not free or any(x is None for x in (*base, *free)):
        return None
    cells = ", ".join(f"{fmt(b)} / {fmt(f)} m at {short(v)} m/s" for v, b, f in zip(sweep["speeds"], base, free))
    return (f"The baseline's mean 3D error against the same flights with no downwash at all (`no_downwash`): {cells}. "
            "Where the two are close, the error is the follower's own tracking error on the fast circle, which no "
            "model of the downwash removes, the oracle included; models trained on outdoor flights learn part of "
            "it, since their labels (f = a - u) hold every acceleration the command does not explain.")


def _sweep_rows(conditions: dict, n: int) -> list[list[str]]:
    return [[f"`{c}`"] + [pct(x) + (f" ({crash_cell(k, n)} crashed)" if k else "") for x, k in
                          zip(e["improvement_pos_3d"], e["crash_rate"])]
            for c, e in ordered(conditions) if c not in ("no_downwash", "baseline")]


# each model with memory and the memoryless model it extends (the same features without the history)
MEMORY_TWINS = {"equivariant_memory": "equivariant_general", "deep_memory": "deep"}
FAST = 2.0  # m/s: the leader speeds at and above which the memory question is asked


def _fast_means(sweep: dict | None, conditions: tuple[str, ...]) -> dict[str, float] | None:
    """Each condition's mean improvement over the baseline at the sweep's speeds of FAST m/s and above
    (None when the sweep lacks one of them or those speeds)."""
    if not sweep:
        return None
    fast = [i for i, v in enumerate(sweep["speeds"]) if v >= FAST]
    got = [sweep["conditions"].get(c) for c in conditions]
    if not fast or any(e is None or any(e["improvement_pos_3d"][i] is None for i in fast) for e in got):
        return None
    return {c: sum(e["improvement_pos_3d"][i] for i in fast) / len(fast) for c, e in zip(conditions, got)}


def _signed(x: float) -> str:
    """A difference of two improvements, in percentage points."""
    return f"{100 * x:+.1f} points"


def memory_verdict(r: dict) -> str | None:
    """Whether memory helps on the shed-wake truth at FAST m/s and above: each model with memory against
    its memoryless twin (both trained on the outdoor stages), mean improvement over those speeds. Where
    the run also swept a truth without memory (``momentum``, else the run's own when it is not the shed
    wake), the same comparison there is the control: a history also tells how the leader moves, which
    helps on any truth, so only the difference between the two gains is the wake's memory."""
    truths = r.get("truths") or {}
    own = (r.get("provenance") or {}).get("field_spec")
    sweep = (truths.get("shed") or {}).get("sweep") or (r.get("sweep") if own == "shed" else None)
    control_name = "momentum" if "momentum" in truths else ("so2" if own != "shed" and r.get("sweep") else None)
    control = (truths.get(control_name) or {}).get("sweep") or (r.get("sweep") if control_name == "so2" else None)
    if not sweep:
        return None
    lines = []
    for memory, twin in MEMORY_TWINS.items():
        pair = (f"{memory}-outdoor", f"{twin}-outdoor")
        shed, other = _fast_means(sweep, pair), _fast_means(control, pair)
        if shed is None:
            continue
        diff = shed[pair[0]] - shed[pair[1]]
        line = (f"`{pair[0]}` {pct(shed[pair[0]])} against `{pair[1]}` {pct(shed[pair[1]])}: memory "
                + ("helps" if diff > 0.02 else "hurts" if diff < -0.02 else "makes no clear difference")
                + f" ({_signed(diff)})")
        if other is not None:
            gain = other[pair[0]] - other[pair[1]]
            line += (f"; on the `{control_name}` truth, which has no memory, the same models differ by {_signed(gain)}, "
                     f"so the wake's memory accounts for {_signed(diff - gain)}")
        lines.append(line)
    if not lines:
        return None
    speeds = ", ".join(short(v) for v in sweep["speeds"] if v >= FAST)
    return (f"**Does memory help on the shed-wake truth at {short(FAST)} m/s and above?** Mean improvement over the "
            f"baseline at {speeds} m/s: " + "; ".join(lines) + ".")


def equivariance_verdict(r: dict) -> str | None:
    """Whether equivariance still pays outdoors: the best equivariant against the best non-equivariant
    model of the same training data, at the run's own setting."""
    c = r["conditions"]
    out = []
    for suffix, data in (("", "indoor data"), ("-outdoor", "indoor and outdoor data")):
        kinds = [k for k in c if k.endswith(suffix) and "-" not in k.removesuffix(suffix) and not k.endswith("_guarded")
                 and k not in ("no_downwash", "baseline", "oracle") and c[k].get("improvement_pos_3d") is not None]
        eq = [k for k in kinds if k.startswith("equivariant")]
        plain = [k for k in kinds if not k.startswith("equivariant")]
        if not eq or not plain:
            continue
        best = lambda ks: max(ks, key=lambda k: c[k]["improvement_pos_3d"])  # noqa: E731
        e, p = best(eq), best(plain)
        pays = c[e]["improvement_pos_3d"] > c[p]["improvement_pos_3d"]
        out.append(f"trained on {data}, the best equivariant model `{e}` {pct(c[e]['improvement_pos_3d'])} against "
                   f"the best non-equivariant `{p}` {pct(c[p]['improvement_pos_3d'])}: it "
                   + ("pays" if pays else "does not pay"))
    return None if not out else "**Does equivariance still pay outdoors?** " + "; ".join(out) + "."


def worst_cases(found: dict[str, dict]) -> dict[str, dict[str, tuple]]:
    """model -> {"unguarded" | "guarded": (worst improvement over the baseline, where, crash rate there),
    "guarded_crashes": (the highest crash rate behind the guard, where, the baseline's there)}
    over every setting of every experiment's results: the tracking runs, the outdoor run with its
    sweeps and truths, the field table's fields and the swarm's presets and laws (a setting without
    crashes behind the guard is not a crash; none: no "guarded_crashes")."""
    points = settings_points(found)
    baseline = {where: e.get("crash_rate") or 0.0 for where, c, e in points if c == "baseline"}
    out: dict[str, dict[str, tuple]] = {}
    for where, c, e in points:
        imp = e.get("improvement_pos_3d")
        if imp is None or c in ("no_downwash", "baseline", "oracle"):
            continue
        model, side = (c.removesuffix("_guarded"), "guarded") if c.endswith("_guarded") else (c, "unguarded")
        have = out.setdefault(model, {}).get(side)
        if have is None or imp < have[0]:
            out[model][side] = (imp, where, e.get("crash_rate") or 0.0)
        crashes = out[model].get("guarded_crashes")
        if side == "guarded" and (e.get("crash_rate") or 0.0) > (0.0 if crashes is None else crashes[0]):
            out[model]["guarded_crashes"] = (e["crash_rate"], where, baseline.get(where))
    return out


def render_worst_cases(found: dict[str, dict]) -> str | None:
    """The worst-case table: each model's worst improvement over the baseline, unguarded and guarded."""
    worst = worst_cases(found)
    if not any("guarded" in w for w in worst.values()):
        return None

    def cell(w: tuple | None) -> str:
        return "-" if w is None else f"{pct(w[0])} ({w[1]}" + (f", {pct(w[2])} crashed" if w[2] else "") + ")"

    def crashes(w: tuple | None) -> str:
        return "none" if w is None else f"{pct(w[0])} ({w[1]}" + ("" if w[2] is None else f"; baseline {pct(w[2])}") + ")"

    rows = [[f"`{m}`", cell(w.get("unguarded")), cell(w.get("guarded")), crashes(w.get("guarded_crashes"))]
            for m, w in ordered(worst)]
    return ("Worst case: each model's worst improvement of the 3D position error over the baseline, over every "
            "setting of every experiment in `results/` (the tracking runs, the outdoor run with its sweeps and ground "
            "truths, the field table, the swarm's presets and laws), unguarded and behind the guard, and the most "
            "flights that crashed behind the guard in any setting, with the baseline's crashes there:\n\n"
            + markdown_table(["model", "worst unguarded", "worst guarded", "most crashes guarded"], rows))


def _share_of_oracle(entry: dict, condition: str) -> float | None:
    """A condition's improvement over the baseline as a share of the oracle's (1: as good as the truth)."""
    oracle, got = entry["oracle"].get("improvement_pos_3d"), entry.get(condition, {}).get("improvement_pos_3d")
    return None if oracle in (None, 0) or got is None else got / oracle


def render_swarm(r: dict, label: str) -> str:
    unlearned = ("integral", "dob")  # (these and the models with the observer: their own table)
    shown = [c for c in r["conditions"][1:] if not c.endswith(("_guarded", "_dob")) and c not in unlearned]
    guarded = [c for c in r["conditions"][1:] if c.endswith("_guarded")]
    parts = [f"{len(r['seeds'])} seeds per preset and law; metrics over every follower of a flight. Each cell: the "
             "improvement of the followers' mean 3D position error over the baseline, and in brackets the gap to "
             "the oracle (m). `summed_pairwise` is the paper's two-vehicle equivariant model summed over neighbours; "
             "`-pair` models were trained on two-vehicle data only, `-mixed` ones on two-vehicle data plus the swarm "
             "stages flown under that law" + (" and its stages of other vehicle kinds, `-kinds` ones on the same data "
                                              "reading each vehicle's kind" if any(c.endswith("-kinds") for c in shown)
                                              else "") + f" (`{label}`):"]
    verdicts = []
    def cell(e: dict) -> str:
        return (pct(e.get("improvement_pos_3d")) + ("" if e.get("gap_to_oracle_pos_3d") is None else
                                                    f" ({e['gap_to_oracle_pos_3d']:+.3f})")
                + (f", {crash_cell(e['crash_rate'], len(r['seeds']))} crashed" if e.get("crash_rate") else ""))

    for law, by_preset in r["summary"].items():
        rows = [[f"`{preset}`"] + [cell(entry[c]) for c in shown] for preset, entry in by_preset.items()]
        parts += [f"**{law} aggregation** ({r['laws'][law]['law'].get('name', law)}):",
                  markdown_table(["preset"] + shown, rows)]
        if guarded:
            rows = [[f"`{preset}`"] + [cell(entry[c]) for c in guarded] for preset, entry in by_preset.items()]
            parts += [f"The same models behind the guard, {law} aggregation:", markdown_table(["preset"] + guarded, rows)]
        shares = {c: [x for e in by_preset.values() if (x := _share_of_oracle(e, c)) is not None] for c in shown[1:]}
        mean = {c: sum(v) / len(v) for c, v in shares.items() if v}
        best = max(mean, key=mean.get) if mean else None
        if "summed_pairwise" in mean:
            verdicts.append(f"under the {law} law, summing the pairwise model recovers {pct(mean['summed_pairwise'])} "
                            f"of the oracle's improvement on average over the presets; the best condition is `{best}` "
                            f"with {pct(mean[best])}")
    if verdicts:
        parts.append("Does summing pairwise models hold up? " + "; ".join(verdicts) + ".")
    over = render_swarm_baselines(r.get("presets") or {})
    return "\n\n".join(parts + ([over] if over else []))


def render_force_maps(r: dict, label: str) -> str:
    keys = ("down_top_rmse_vs_truth", "down_side_rmse_vs_truth", "lateral_rmse_vs_truth_pos",
            "lateral_rmse_vs_truth_neg")
    rows = [[k] + [fmt(m.get(key)) for key in keys] for k, m in ordered(r["maps"])]
    header = ["model", "downward, top view", "downward, side view", "lateral, +v", "lateral, -v"]
    return "\n\n".join([f"RMSE of each model's maps against the truth, m/s^2, follower speed {short(r['speed'])} "
                        f"m/s (`{label}`):", markdown_table(header, rows)])


def render_field_table(r: dict, label: str) -> str:
    table = r["table"]
    shown = [c for c in ORDER if c not in ("no_downwash", "baseline", "integral", "dob") and not c.endswith("_dob")
             and any(c in e["conditions"] for e in table.values())]  # (the observer's and integral's: their own table)
    rows = []
    for name, e in sorted(table.items(), key=lambda kv: (list(FIELDS).index(kv[0]) if kv[0] in FIELDS else len(FIELDS), kv[0])):
        cells = []
        for c in shown:
            m = e["conditions"].get(c, {})
            gap = m.get("gap_to_oracle_pos_3d")
            cells.append(pct(m.get("improvement_pos_3d")) + ("" if gap is None or c == "oracle" else f" ({gap:+.3f})"))
        rows.append([f"`{name}`", fmt(e["conditions"].get("baseline", {}).get("pos_err_3d_mean"))] + cells
                    + [crash_cell(max((m.get("crash_rate") or 0.0) for m in e["conditions"].values()), e["seeds"]),
                       f"{e['wall_seconds']:.0f}"])
    first = next(iter(table.values()))
    return "\n\n".join([
        f"The lemniscate (`python -m experiments.lemniscate --field NAME`, {first['seeds']} seeds, {short(first['duration'])} s) "
        "run from scratch on every registered field by `python -m experiments.fields --run`: the improvement of the "
        "mean 3D position error over the baseline, and in brackets the gap to the oracle (m; + is worse than the "
        f"oracle). The wall time is the whole lemniscate experiment, collection and training included (`{label}`):",
        markdown_table(["field", "baseline 3D error (m)"] + shown + ["worst crash rate (Wilson 95 %)", "wall (s)"], rows)]
        + [t for t in (render_field_baselines(table),) if t])


RENDERERS = {"staged_collection": render_staged, "sample_efficiency": render_efficiency,
             "lemniscate": render_tracking, "transect": render_tracking, "force_maps": render_force_maps, "outdoor": render_outdoor,
             "swarm": render_swarm,
             "field_table": render_field_table, "real_flights": render_real_flights, "benchmark": render_benchmark,
             "observer_bandwidth": render_observer_bandwidth, "swarm_safety": render_swarm_safety,
             "controller_table": render_controller_table}


# What a results file of the right keys but wrong values raises in a renderer (a string where a number
# was, a list where an object was, a zero divisor, an empty list to take the max of).
RENDER_ERRORS = (KeyError, TypeError, IndexError, ValueError, AttributeError, ArithmeticError, StopIteration)


def render_error(where: str, what: str, e: BaseException) -> ConfigError:
    """The one-line ConfigError for a results file (or files) `where` that `what` could not render."""
    return ConfigError(f"{where}: cannot render {what} ({type(e).__name__}: {' '.join(str(e).split())})")


def render_one(name: str, data: dict, record: dict, label: str, where: str | None = None) -> list[str]:
    """The section of one results file and its provenance line; `label` names the file in the text,
    `where` (default `label`) in the error when it cannot be rendered."""
    try:
        return [RENDERERS[name](data, label), render_provenance(name, data, record, label)]
    except RENDER_ERRORS as e:
        raise render_error(where or label, f"this {name} results file", e) from e
