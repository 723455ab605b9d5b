"""The guard's criteria, judged over every setting of every results file.

A setting is one cell of an experiment: a tracking run, the outdoor run and each point of its
sweeps and truths, each field of the field table, each preset and law of the swarm
(`settings_points`). In each, for every model flown unguarded and behind the guard
(`<model>` and `<model>_guarded`):

1. crashes: the guarded condition crashes no more often than its unguarded twin;
2. never worse: where the baseline flies without a crash, the guarded condition's improvement
   of the 3-D error over the baseline is at least -2 %;
3. retention: where the baseline flies without a crash, the unguarded gain is above 10 % and
   the model's vehicle kinds are all in its training data (the entry's ``kinds_in_data``), the
   guarded condition keeps at least 90 % of the unguarded gain. An entry that does not say
   whether its kinds were in its data is not judged here, and counted as such.

`guard_criteria(found)` returns each criterion's settings judged and its misses; the report
renders them and a test holds the committed results files to them.
"""

from __future__ import annotations

from typing import Any

from experiments.options import GUARDED
from experiments.report.formatting import markdown_table, pct, short

__all__ = ["WORSE_FLOOR", "RETAIN", "RETAIN_ABOVE", "settings_points", "guard_criteria",
           "render_guard_criteria"]

WORSE_FLOOR = -0.02  # the least improvement over the baseline a guarded condition may have
RETAIN, RETAIN_ABOVE = 0.9, 0.10  # the share of an unguarded gain above RETAIN_ABOVE the guard keeps


def settings_points(found: dict[str, dict]) -> list[tuple[str, str, dict]]:
    """(where, condition, entry) over every setting of every results file; an entry holds at least
    improvement_pos_3d and crash_rate (the sweeps' points are taken apart into such entries)."""
    points: list[tuple[str, str, dict]] = []
    for name in ("lemniscate", "transect"):
        for c, e in (found.get(name) or {}).get("conditions", {}).items():
            points.append((name, c, e))
    outdoor = found.get("outdoor") or {}
    for c, e in outdoor.get("conditions", {}).items():
        points.append(("outdoor", c, e))
    sweeps = [("outdoor", outdoor.get("sweep"), "speeds", " m/s"), ("outdoor", outdoor.get("wind_sweep"), "winds", "")]
    sweeps += [(f"outdoor on {t}", truth.get(k), key, unit) for t, truth in (outdoor.get("truths") or {}).items()
               for k, key, unit in (("sweep", "speeds", " m/s"), ("wind_sweep", "winds", ""))]
    for where, sweep, key, unit in sweeps:
        for c, e in ((sweep or {}).get("conditions") or {}).items():
            for i, at in enumerate(sweep[key]):
                point = {"improvement_pos_3d": e["improvement_pos_3d"][i], "crash_rate": e["crash_rate"][i]}
                if "kinds_in_data" in e:
                    point["kinds_in_data"] = e["kinds_in_data"]
                points.append((f"{where}, {short(at) if key == 'speeds' else at}{unit}", c, point))
    for field, entry in ((found.get("field_table") or {}).get("table") or {}).items():
        for c, e in entry["conditions"].items():
            points.append((f"lemniscate on {field}", c, e))
    for law, by_preset in ((found.get("swarm") or {}).get("summary") or {}).items():
        for preset, entry in by_preset.items():
            for c, e in entry.items():
                points.append((f"swarm {preset}, {law}", c, e))
    return points


def guard_criteria(found: dict[str, dict]) -> dict[str, Any]:
    """{criterion: {"judged": settings judged, "misses": [(where, model, what)]}} for "crashes",
    "never_worse" and "retention", and "retention_unknown": the settings not judged for retention
    because their entry does not say whether the model's kinds were in its data."""
    by_where: dict[str, dict[str, dict]] = {}
    for where, c, e in settings_points(found):
        by_where.setdefault(where, {})[c] = e
    out: dict[str, Any] = {k: {"judged": 0, "misses": []} for k in ("crashes", "never_worse", "retention")}
    out["retention_unknown"] = 0
    for where, cells in by_where.items():
        calm = (cells.get("baseline") or {}).get("crash_rate") == 0.0
        for c, guarded in cells.items():
            if not c.endswith(GUARDED) or c.removesuffix(GUARDED) not in cells:
                continue
            model, plain = c.removesuffix(GUARDED), cells[c.removesuffix(GUARDED)]
            g_crash, u_crash = guarded.get("crash_rate") or 0.0, plain.get("crash_rate") or 0.0
            out["crashes"]["judged"] += 1
            if g_crash > u_crash:
                out["crashes"]["misses"].append((where, model, f"guarded {pct(g_crash)} > unguarded {pct(u_crash)}"))
            g, u = guarded.get("improvement_pos_3d"), plain.get("improvement_pos_3d")
            if not calm or g is None or u is None:
                continue
            out["never_worse"]["judged"] += 1
            if g < WORSE_FLOOR:
                out["never_worse"]["misses"].append((where, model, f"guarded {pct(g)}"))
            if u <= RETAIN_ABOVE:
                continue
            kinds = guarded.get("kinds_in_data", plain.get("kinds_in_data"))
            if kinds is None:
                out["retention_unknown"] += 1
            elif kinds:
                out["retention"]["judged"] += 1
                if g < RETAIN * u:
                    out["retention"]["misses"].append((where, model, f"keeps {pct(g / u)} of {pct(u)}"))
    return out


def render_guard_criteria(found: dict[str, dict]) -> str | None:
    """The criteria with the settings judged and every miss; None without a guarded condition."""
    r = guard_criteria(found)
    if not r["crashes"]["judged"]:
        return None
    words = {"crashes": "a guarded condition crashes no more often than its unguarded twin",
             "never_worse": f"where the baseline flies without a crash, a guarded condition is never worse than "
                            f"{pct(WORSE_FLOOR)} of the baseline's error",
             "retention": f"where the baseline flies without a crash and the model's vehicle kinds are all in its "
                          f"data, the guard keeps >= {pct(RETAIN)} of an unguarded gain above {pct(RETAIN_ABOVE)}"}
    rows = [[words[k], str(r[k]["judged"]), str(len(r[k]["misses"])),
             "; ".join(f"`{m}` in {w}: {what}" for w, m, what in r[k]["misses"]) or "-"] for k in words]
    note = ("" if not r["retention_unknown"] else
            f" {r['retention_unknown']} settings written before results said whether a model's kinds were in its "
            "data are not judged for retention.")
    outdoor = sum(1 for k in ("never_worse", "retention") for w, _, _ in r[k]["misses"] if "outdoor" in w)
    why = ("" if not outdoor else
           f"\n\n{outdoor} of the misses are outdoors. Why the guard keeps little of an indoor model's gain there, "
           "measured flight by flight: [design notes, the guard outdoors](design-notes.md#the-guard-outdoors).")
    return ("The guard's criteria over every setting of every results file (model by model, the guarded "
            f"condition against its unguarded twin).{note}\n\n"
            + markdown_table(["criterion", "settings judged", "missed", "misses"], rows) + why)
