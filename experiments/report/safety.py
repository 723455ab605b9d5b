"""The safety layer's record: the swarm flown with it (`python -m experiments.swarm --safety`) against without.

`safety_comparison(swarm, with_safety)` pairs the two runs' cells (law, preset; the same seeds) and
judges the layer's two promises: no condition crashes in a cell where the baseline flies without a
crash, and where nothing crashes without the layer, it changes no condition's mean 3-D error by
2 % or more. `render_swarm_safety` renders the run's own summary, and `render_safety_comparison`
the comparison, with every miss, when both files are there.
"""

from __future__ import annotations

from typing import Any

from experiments.report.formatting import crash_cell, markdown_table, pct

__all__ = ["CHANGE_LIMIT", "safety_comparison", "render_swarm_safety", "render_safety_comparison"]

CHANGE_LIMIT = 0.02  # the most the layer may change a condition's mean 3-D error where nothing crashes without it


def safety_comparison(swarm: dict, with_safety: dict) -> dict[str, Any]:
    """{"crashes": [(law, preset, condition, rate without, rate with)] where the baseline with the layer flies
    clean and the condition crashes with it; "changes": [(law, preset, condition, relative change)] of every
    condition of the cells where nothing crashes without it; "cells": cells compared}."""
    out: dict[str, Any] = {"crashes": [], "changes": [], "cells": 0}
    for law, by_preset in with_safety["summary"].items():
        for preset, on in by_preset.items():
            off = ((swarm.get("summary") or {}).get(law) or {}).get(preset)
            if off is None:
                continue
            out["cells"] += 1
            if (on.get("baseline") or {}).get("crash_rate") == 0.0:
                out["crashes"] += [(law, preset, c, (off.get(c) or {}).get("crash_rate"), e["crash_rate"])
                                   for c, e in on.items() if e["crash_rate"] > 0]
            if all(e["crash_rate"] == 0.0 for e in off.values()):
                out["changes"] += [(law, preset, c, on[c]["pos_err_3d_mean"] / e["pos_err_3d_mean"] - 1.0)
                                   for c, e in off.items() if c in on]
    return out


def render_swarm_safety(r: dict, label: str) -> str:
    n = len(r["seeds"])
    rows = []
    for law, by_preset in r["summary"].items():
        for preset, entry in by_preset.items():
            worst = max(entry, key=lambda c: entry[c]["crash_rate"])
            rows.append([law, f"`{preset}`", crash_cell(entry["baseline"]["crash_rate"], n),
                         f"`{worst}` {crash_cell(entry[worst]['crash_rate'], n)}" if entry[worst]["crash_rate"] else "none"])
    s = r.get("provenance", {}).get("safety") or {}
    return "\n\n".join([
        f"The swarm experiment flown with the safety layer (`--safety`: each pair's collision ellipsoid inflated "
        f"{s.get('inflation')} times, at most {s.get('max_margin')} m beyond it vertically, height "
        f"{s.get('ground_clearance')} m, k0 {s.get('k0')}, k1 {s.get('k1')}, its "
        f"estimate's bandwidth {s.get('bandwidth')} rad/s), {n} flights per cell (`{label}`):",
        markdown_table(["law", "preset", "baseline crashes", "most crashes"], rows)])


def render_safety_comparison(found: dict[str, dict]) -> str | None:
    """The comparison of the module doc, or None without both runs."""
    if "swarm" not in found or "swarm_safety" not in found:
        return None
    r = safety_comparison(found["swarm"], found["swarm_safety"])
    big = sorted((x for x in r["changes"] if abs(x[3]) >= CHANGE_LIMIT), key=lambda x: -abs(x[3]))
    crashes = "; ".join(f"`{c}` in {preset}, {law}: {pct(off)} without, {pct(on)} with" for law, preset, c, off, on
                        in r["crashes"]) or "none"
    changed = "; ".join(f"`{c}` in {preset}, {law}: {x:+.0%}" for law, preset, c, x in big[:8]) or "none"
    return (f"The safety layer's promises over the {r['cells']} cells of the swarm flown with and without it: "
            f"conditions that crash with it where the baseline flies clean: {crashes}. Changes of the mean 3-D error "
            f"of {pct(CHANGE_LIMIT)} or more where nothing crashes without it: {len(big)} of {len(r['changes'])} "
            f"(largest: {changed}). "
            + ("Both promises hold." if not r["crashes"] and not big else
               "Missed: " + " and ".join(w for w, miss in (("no new crash", r["crashes"]), ("the error kept", big))
                                         if miss) + " (why: design notes, the safety layer)."))
