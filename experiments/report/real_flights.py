"""The results page's section on real flights (the Neural-Swarm data set): what was read, the models
per interaction type beside the data set's own errors, the fitted wakes, sim and real side by side,
pairs to triples and the learning curves."""

from __future__ import annotations

from experiments.report.formatting import markdown_table, fmt

__all__ = ["render_real_flights", "real_model_names"]


def real_model_names(r: dict) -> list[str]:
    """The models of a real-flights file in the order asked for: the pair models, then the sets'."""
    a = r["args"]
    sets = [f"{k}_kinds" for k in a.get("set_models", "").split(",") if k]
    return [k for k in [*a["models"].split(","), *sets] if k in r["models"]]


def _bold_min(errs: list) -> list[str]:
    best = min(range(len(errs)), key=lambda i: errs[i])
    return [f"**{fmt(e)}**" if i == best and len(set(errs)) > 1 else fmt(e) for i, e in enumerate(errs)]


def _render_fitted(fitted: dict) -> list[str]:
    """The registered wakes fitted to the training flights: constants with their intervals beside the
    published ones, the test error of each, and the wake's mean vertical push by separation."""
    rows = []
    for name, f in fitted.items():
        fit, test = f["fit"], f["test"]
        ci = fit.get("intervals") or {}
        consts = "; ".join(f"{p} {fmt(v)}" + (f" [{fmt(ci[p][0])}, {fmt(ci[p][1])}]" if p in ci else "")
                           + f" ({fmt(test['default']['field'].get(p))})" for p, v in fit["params"].items())
        rows.append([f"`{name}`", consts, fmt(test["default"]["rmse"]), fmt(test["fitted"]["rmse"]),
                     fmt(test["fitted"]["rmse_zero"])])
    first = next(iter(fitted.values()))["test"]["fitted"]
    profile = [[f"{fmt(b['lo'])}-{fmt(b['hi'])}", str(b["n"]), fmt(b["z_measured"])]
               + [fmt(f["test"]["fitted"]["vertical"][i]["z_predicted"]) for f in fitted.values()]
               for i, b in enumerate(first["vertical"]) if b["n"]]
    boots = {f["fit"]["bootstrap"]["n_boot"] for f in fitted.values() if f["fit"].get("bootstrap")}
    return [
        "The registered wakes fitted to the training flights' labels (least squares of two constants each, every "
        "pair scaled for its vehicles' kinds; samples with one vehicle above or none; 95 % intervals from "
        f"{'/'.join(str(b) for b in sorted(boots)) or 'no'} bootstrap refits over whole flights; the default, "
        "published constant in parentheses), and each field's RMSE on the test flights' samples with its default "
        "and its fitted constants (m/s^2, three axes). Each fit is written with its data's digest; "
        "`--field fitted:PATH` flies it:",
        markdown_table(["field", "fitted constants [95 % CI] (default)", "default", "fitted", "no field"], rows),
        f"The wake's mean vertical push on the test samples within {fmt(first['lateral_max'])} m laterally of the "
        "vehicle above, by its height above them (m; m/s^2), measured and as each fitted field predicts it:",
        markdown_table(["height", "samples", "measured", *(f"`{n}`" for n in fitted)], profile)]


def _cm(x) -> str:
    return "-" if x is None else fmt(100.0 * x)


def _field_gains(key: str) -> list[str]:
    field, _, gains = key.partition("|")
    return [f"`{field}`", gains]


def _render_replays(rp: dict) -> list[str]:
    """The test flights' setpoints flown in the simulator: tracking beside the real flights', and the
    model trained on real flights in the loop."""
    first = next(iter(rp["tracking"].values()))
    worlds = rp["flights"] * len(first["seeds"])
    rows = []
    for key, t in rp["tracking"].items():
        under, alone = t["pooled"]["under"], t["pooled"]["alone"]
        rows.append([*_field_gains(key), f"{len(t['ended_early'])} of {worlds}", _cm(under["real"]["pos"]["rms"]),
                     _cm(under["sim"]["pos"]["rms"]), _cm(under["real"]["z"]["mean"]), _cm(under["sim"]["z"]["mean"]),
                     _cm(alone["real"]["pos"]["rms"]), _cm(alone["sim"]["pos"]["rms"])])
    parts = [f"Sim and real side by side: the setpoints of the {rp['flights']} test flights of `{rp['tasks']}` flown in "
             "the simulator (each vehicle its registered kind, from its logged start) against each field, with the "
             "default constants or the fit above (`fitted-...`); position error RMS and mean vertical error (cm) of "
             "the vehicles with another above them and of those alone, real and simulated, over the rows flown. "
             f"What differs: {first['differences']}",
             "The gains are the LQR's default weights, or weights whose gain is the Crazyflie firmware's default "
             "position PD (`crazyflie`: as stiff as the real vehicles flew; the default LQR is about 12 times softer "
             "in height).",
             markdown_table(["field", "gains", "worlds ended early", "under: real", "sim", "z mean: real", "sim", "alone: real",
                     "sim"], rows)]
    loop = rp.get("in_loop") or {}
    if loop:
        lrows = []
        for key, v in loop.items():
            pen, flown, kept = v["under_rms_penalised"], v["under_rms"], v["oracle_gain_kept"]
            ended = {c: sum(1 for e in v["ended_early"] if e.get("condition") == c) for c in v["conditions"]}
            lrows.append([*_field_gains(key), *(f"{_cm(pen[c])} ({_cm(flown[c])})" for c in v["conditions"]),
                          " / ".join(str(ended[c]) for c in v["conditions"]),
                          fmt(kept["penalised"]) if not ended["oracle"] else "- (the oracle crashed)"])
        conds = next(iter(loop.values()))["conditions"]
        parts += ["The model trained on the real training flights (`equivariant-real`, its checkpoint in "
                  "`<out>/models/equivariant.pt`) flown in the loop on the same setpoints, beside no model and the "
                  "field's own prediction (`oracle`): position error RMS (cm) of the vehicles with another above, the "
                  "ticks a crashed world did not fly counted at the crash penalty (in parentheses: over the rows "
                  "flown), the worlds that ended early, and the share of the oracle's gain the model keeps:",
                  markdown_table(["field", "gains", *conds, "ended early", "oracle gain kept"], lrows)]
    return parts


def render_real_flights(r: dict, label: str) -> str:
    """Real flights: what was read, per interaction type each model's test error beside none and the
    data set's own, the pairs-to-triples question and the learning curves."""
    a = r["args"]
    kinds = real_model_names(r)
    rejected = r["rejected"]
    free = r["free_air_label"]
    rows = [[f"`{name}`", str(t["n_train"]), str(t["n_test"])]
            + _bold_min([t["rmse"]["none"], *(t["rmse"][k] for k in kinds)]) for name, t in r["per_type"].items()]
    parts = [
        "The paper's models trained and judged on real flights: the Neural-Swarm data set's onboard logs (Shi et al., "
        "github.com/aerorobotics/neural-swarm; Crazyflie 2.x vehicles of a small and a large frame), read by "
        f"`python -m experiments.real_flights` ([how](real-flights.md)): {r['files']} files, "
        f"{sum(r['flights'].values())} flights ({len(rejected)} rejected), {r['records']} vehicle records at 100 Hz, "
        f"read and converted in {r['read_seconds']:.1f} s. Trained on `{a['train']}` ({r['samples']['train']} samples, "
        f"one in {r['samples']['stride']} of the labels), tested on `{a['test']}` ({r['samples']['test']}). The labels of vehicles "
        f"with none above, away from the ground, scatter by {', '.join(fmt(x) for x in free['scatter'])} m/s^2 (x, y, "
        f"z) about a mean of {', '.join(fmt(x) for x in free['mean'])}: the floor any model can reach.",
        "Test RMSE per interaction type (m/s^2, over the three axes; `S2L`: a small vehicle above a large one, `SL2S`: a "
        "small and a large above a small one, `Ge2S`: near the ground with none above, `none2S`: free air). Pair models "
        "read the nearest other vehicle only; the models of sets (`..._kinds`) read both others and every vehicle's "
        f"kind; the lowest error of each row is in bold (`{label}`):",
        markdown_table(["type", "train", "test", "no model", *kinds], rows)]
    published = r.get("published")
    if published:
        prow = [[f"`{name}`", fmt(t["z_rmse"]["none"]), *(fmt(t["z_rmse"][k]) for k in kinds),
                 fmt(t["published"]["z_rmse"]), fmt(t["published"]["mse_gf2"])]
                for name, t in r["per_type"].items() if "published" in t]
        parts += [f"The vertical component beside the data set's own per-type errors ({published['units']}). Theirs are "
                  "errors on their training samples, after training one network per vehicle frame on the flights of "
                  "all days; ours are on a held-out day, so theirs are the lower bound of a like-for-like comparison:",
                  markdown_table(["type", "no model", *kinds, "Neural-Swarm", "Neural-Swarm (gf^2)"], prow)]
    triples = r.get("pairs_to_triples") or {}
    if "models" in triples:
        trow = [[f"`{k}`", fmt(v["nearest"]), fmt(v["summed"])] for k, v in triples["models"].items()]
        parts += [f"Pairs to triples: the per-neighbour models trained on the two-vehicle training flights only "
                  f"({triples['n_train']} samples), judged on the {triples['n_test']} test samples with two vehicles "
                  f"above (no model: {fmt(triples['none'])} m/s^2), reading the nearest vehicle above, and summed over "
                  "both (the paper's naive multi-vehicle law):", markdown_table(["model", "nearest", "summed"], trow)]
    fitted = r.get("fitted_fields") or {}
    if fitted:
        parts += _render_fitted(fitted)
    replays = r.get("replays") or {}
    if replays.get("tracking"):
        parts += _render_replays(replays)
    curves = r.get("learning_curves") or {}
    if "curves" in curves:
        names = list(curves["curves"])
        fractions = [p["fraction"] for p in curves["curves"][names[0]]]
        crow = [[fmt(f), str(curves["curves"][names[0]][i]["flights"])]
                + _bold_min([curves["curves"][k][i]["mean"] for k in names]) for i, f in enumerate(fractions)]
        parts += [f"Learning curves: the test RMSE on the {curves['n_test']} samples with a vehicle above (no model "
                  f"{fmt(curves['none'])} m/s^2), each model trained on a share of the training flights of two or three "
                  f"vehicles, the mean over {a['curve_seeds']} draws of flights:",
                  markdown_table(["share", "flights", *names], crow)]
        claim = curves.get("claim")
        if claim:
            verdict = ("holds" if claim["ci_high"] < 0 else "does not hold" if claim["ci_low"] > 0 else
                       "is not established (the 95 % interval contains 0)")
            parts.append(f"The paper's question on real flights: `equivariant` on {fmt(claim['fraction'])} of the flights "
                         f"against the better of {', '.join(f'`{b}`' for b in claim['baselines'])} on all of them, "
                         f"paired by draw: mean difference {fmt(claim['mean_difference'])} m/s^2, 95 % CI "
                         f"[{fmt(claim['ci_low'])}, {fmt(claim['ci_high'])}] over {claim['n']} draws: the claim {verdict}.")
    return "\n\n".join(parts)
