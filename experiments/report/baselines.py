"""What learning adds over the generic tools: the disturbance observer and integral action.

`render_learning_over_baselines(conditions, n)` answers, for a results file whose conditions include
`baseline`, `dob` and `integral` flown on the same seeds, per learned model m with its observer twin
`m_dob`: how much of m's gain over the baseline do `dob` and `integral` already give, and does the
model with the observer on its residual beat both m and `dob`? Every comparison is paired by seed (a
seed is the same flight under every condition), with a 95 % t interval of the mean difference of the
follower's mean 3-D error. `render_observer_bandwidth` shows how the observer's bandwidth was chosen.
"""

from __future__ import annotations

import math
from typing import Any

from experiments.common import CONTROLLER_NAMES
from experiments.options import UNLEARNED
from experiments.report.formatting import crash_cell, fmt, markdown_table, ordered, pct, short

__all__ = ["paired_interval", "render_learning_over_baselines", "render_field_baselines",
           "render_swarm_baselines", "render_observer_bandwidth", "render_controller_table"]

_ERROR = "pos_err_3d_mean"
# two-sided 97.5 % quantiles of Student's t by degrees of freedom (scipy.stats.t.ppf(0.975, df)), so the
# report needs no scipy; beyond the table the normal quantile
_T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262, 10: 2.228,
         11: 2.201, 12: 2.179, 13: 2.160, 14: 2.145, 15: 2.131, 19: 2.093, 24: 2.064, 29: 2.045}


def paired_interval(a: list[float], b: list[float]) -> tuple[float, float, float]:
    """(mean, low, high) of the per-seed differences a - b with its 95 % t interval (one seed: no width)."""
    d = [x - y for x, y in zip(a, b, strict=True)]
    n = len(d)
    mean = sum(d) / n
    if n < 2:
        return mean, mean, mean
    sd = math.sqrt(sum((x - mean) ** 2 for x in d) / (n - 1))
    t = _T975.get(n - 1) or next((v for k, v in sorted(_T975.items()) if k >= n - 1), 1.96)
    half = t * sd / math.sqrt(n)
    return mean, mean - half, mean + half


def _cm(interval: tuple[float, float, float]) -> str:
    mean, lo, hi = (100 * x for x in interval)
    return f"{mean:+.2f} ({lo:+.2f} to {hi:+.2f})"


def _answer(vs_model: tuple, vs_dob: tuple, dob_vs_model: tuple) -> str:
    """The verdict of one row from the three paired intervals (negative: the first has the smaller error):
    the model with the observer against both, then the observer alone against the model."""
    if vs_model[2] < 0 and vs_dob[2] < 0:
        first = "model + observer beats both"
    elif vs_model[1] > 0 or vs_dob[1] > 0:
        first = "model + observer is worse than " + ("the model" if vs_model[1] > 0 else "the observer alone")
    else:
        first = "model + observer not significantly better than both"
    if dob_vs_model[2] < 0:
        return first + "; the observer alone beats the model"
    if dob_vs_model[1] > 0:
        return first + "; the model beats the observer alone"
    return first + "; the model and the observer alone on par"


def render_learning_over_baselines(conditions: dict[str, Any], n_seeds: int) -> str | None:
    """The table of the module doc, or None when the file lacks `baseline`, `dob` or `integral`."""
    c = conditions
    if not all(k in c for k in ("baseline", *UNLEARNED)):
        return None
    err = {k: e["per_seed"][_ERROR] for k, e in c.items()}
    gain = {k: c[k].get("improvement_pos_3d") for k in c}
    rows = []
    for model, _ in ordered(c):
        twin = model + "_dob"
        if twin not in c:
            continue
        share = {k: None if not gain[model] or gain[k] is None else gain[k] / gain[model] for k in UNLEARNED}
        vs_model, vs_dob = paired_interval(err[twin], err[model]), paired_interval(err[twin], err["dob"])
        rows.append([f"`{model}`", pct(gain[model]), f"{pct(gain['dob'])} ({pct(share['dob'])})",
                     f"{pct(gain['integral'])} ({pct(share['integral'])})", pct(gain[twin]), _cm(vs_model), _cm(vs_dob),
                     _answer(vs_model, vs_dob, paired_interval(err["dob"], err[model]))])
    if not rows:
        return None
    header = ["model", "its gain over the baseline", "`dob`'s gain (share of the model's)",
              "`integral`'s gain (share)", "model + `dob` gain", "model + `dob` minus model, cm (95 % CI)",
              "model + `dob` minus `dob`, cm (95 % CI)", "answer"]
    return "\n\n".join([
        "What does learning add over the tools a control engineer tries first? Gains are the improvement of the "
        "follower's mean 3-D error over the baseline (the LQR alone); `dob` is the LQR compensating with the "
        "disturbance observer, `integral` the LQR with integral action, `<model>_dob` the model as feed-forward "
        f"with the observer on what it misses. Differences are paired by seed over {n_seeds} seeds, negative where "
        "the model with the observer has the smaller error:", markdown_table(header, rows)])


def render_field_baselines(table: dict[str, dict]) -> str | None:
    """Per field of the field table and model: its gain, `dob`'s and `integral`'s, the model with the observer's,
    and the answer of `render_learning_over_baselines`; None without those conditions in the table."""
    rows = []
    for field, entry in table.items():
        c = entry["conditions"]
        if not all(k in c and "per_seed" in c[k] for k in ("baseline", *UNLEARNED)):
            continue
        err = {k: e["per_seed"][_ERROR] for k, e in c.items() if "per_seed" in e}
        for model, _ in ordered(c):
            twin = model + "_dob"
            if twin not in err or model not in err:
                continue
            vs_model, vs_dob = paired_interval(err[twin], err[model]), paired_interval(err[twin], err["dob"])
            rows.append([f"`{field}`", f"`{model}`"] + [pct(c[k].get("improvement_pos_3d")) for k in
                                                       (model, "dob", "integral", twin)]
                        + [_answer(vs_model, vs_dob, paired_interval(err["dob"], err[model]))])
    if not rows:
        return None
    return "\n\n".join([
        "What does learning add over the observer and integral action on each field (gains over the baseline, "
        "answers from paired 95 % intervals over the seeds, as for the tracking experiments):",
        markdown_table(["field", "model", "its gain", "`dob`", "`integral`", "model + `dob`", "answer"], rows)])


def render_swarm_baselines(presets: dict[str, dict]) -> str | None:
    """Per law and preset of the swarm (its results' ``presets``): the best learned model there, its gain, `dob`'s,
    `integral`'s and the best model with the observer's, and the answer for that model; None without them."""
    rows = []
    for preset, by_law in presets.items():
        for law, entry in by_law.items():
            c = entry["conditions"]
            if not all(k in c for k in ("baseline", *UNLEARNED)):
                continue
            err = {k: e["per_seed"][_ERROR] for k, e in c.items()}
            models = [m for m in c if m + "_dob" in c]
            if not models:
                continue
            best = max(models, key=lambda m: c[m].get("improvement_pos_3d") or -math.inf)
            twin = best + "_dob"
            vs_model, vs_dob = paired_interval(err[twin], err[best]), paired_interval(err[twin], err["dob"])
            rows.append([law, f"`{preset}`", f"`{best}`"] + [pct(c[k].get("improvement_pos_3d")) for k in
                                                          (best, "dob", "integral", twin)]
                        + [_answer(vs_model, vs_dob, paired_interval(err["dob"], err[best]))])
    if not rows:
        return None
    return "\n\n".join([
        "What does learning add over the observer and integral action in the swarm? Per law and preset, the best "
        "learned model there against `dob` and `integral` (gains over the baseline, answers from paired 95 % "
        "intervals over the seeds):",
        markdown_table(["law", "preset", "best model", "its gain", "`dob`", "`integral`", "model + `dob`", "answer"],
                       rows)])


def render_observer_bandwidth(r: dict, label: str) -> str:
    controllers = {c: r["controllers"][c] for c in sorted(r["controllers"], key=lambda k: (
        CONTROLLER_NAMES.index(k) if k in CONTROLLER_NAMES else len(CONTROLLER_NAMES), k))}  # the registry's order
    chosen = ", ".join(f"{c} **{short(e['chosen'])} rad/s**" for c, e in controllers.items())
    parts = [f"The disturbance observer's one setting, its bandwidth, chosen once on the staged collection's training "
             f"flights ({r['flights_per_stage']} per stage, {short(r['seconds'])} s each, the follower flying the "
             f"stages' patterns with the observer alone) under each controller, never on a test flight. Criterion: "
             f"{r['criterion']}; rule: {r['rule']}. Chosen: {chosen}; every `dob` and `<model>_dob` condition flies "
             f"its controller's (`sim.observer.bandwidth_for`; `{label}`):"]
    for c, e in controllers.items():
        rows = [[short(x["bandwidth"]), fmt(100 * x[_ERROR]),
                 "{:+.2f} to {:+.2f}".format(*(100 * v for v in x["minus_best_ci95"])), fmt(x["estimation_rms"]),
                 str(x["crashes"])] for x in e["candidates"]]
        parts += [f"Under `{c}` (best {short(e['best'])} rad/s, chosen {short(e['chosen'])} rad/s):",
                  markdown_table(["bandwidth (rad/s)", "3-D error (cm)", "minus the best, cm (95 % CI)",
                                  "estimation RMS (m/s^2)", "crashes"], rows)]
    return "\n\n".join(parts)


def render_controller_table(r: dict, label: str) -> str:
    """`python -m experiments.controller_table`: per track, each condition's error under each controller."""
    table = r["table"]
    controllers = sorted(table, key=lambda k: (CONTROLLER_NAMES.index(k) if k in CONTROLLER_NAMES else len(CONTROLLER_NAMES), k))
    parts = [f"The tracking experiments under each controller labs fly (`--controller`), the models trained under "
             f"the LQR; the follower's mean 3-D error in m, in brackets the improvement over that controller's own "
             f"baseline (`{label}`):"]
    for track in r["tracks"]:
        conditions = [c for c, _ in ordered({c: None for k in controllers for c in table[k][track]["conditions"]})]
        rows = []
        for c in conditions:
            cells = []
            for k in controllers:
                e = table[k][track]["conditions"].get(c)
                if e is None:
                    cells.append("-")
                    continue
                n = table[k][track]["seeds"]
                cells.append(fmt(e["pos_err_3d_mean"]) + ("" if e.get("improvement_pos_3d") is None else
                                                           f" ({pct(e['improvement_pos_3d'])})")
                             + (f", {crash_cell(e['crash_rate'], n)} crashed" if e.get("crash_rate") else ""))
            rows.append([f"`{c}`"] + cells)
        first = table[controllers[0]][track]
        parts += [f"**{track}** ({first['seeds']} seeds, {short(first['duration'])} s):",
                  markdown_table(["condition"] + [f"`{k}`" for k in controllers], rows)]
    return "\n\n".join(parts)
