"""A sweep's summaries presented: markdown tables, the claim in one sentence, and the figure.

The summaries are those of `downwash.sweep_stats.summarize_field` (as `run_sweep`
returns them per field); the figure is drawn on the caller's matplotlib axes (this
module imports no plotting library).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

__all__ = ["minute_labels", "table_rows", "claim_text", "markdown", "plot_field"]


def minute_labels(minutes: Sequence[float]) -> list[str]:
    """Column titles: "5 min", ..., the last "16.9 min (full)"."""
    return [f"{m:.3g} min (full)" if i == len(minutes) - 1 else f"{m:g} min" for i, m in enumerate(minutes)]


def table_rows(summary: Mapping[str, Any], digits: int = 3) -> list[list[str]]:
    """Rows [model, "mean [low, high]", ...] of one field's summary."""
    return [[k] + [f"{mu:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"
                   for mu, lo, hi in zip(m["rmse_mean"], m["rmse_ci_low"], m["rmse_ci_high"])]
            for k, m in summary["models"].items()]


def claim_text(summary: Mapping[str, Any]) -> str:
    """One sentence on the paired claim of a field's summary (or why it was not tested)."""
    c = summary.get("claim")
    if not c:
        return f"Claim not tested: {summary.get('claim_skipped')}."
    return (f"Claim \"{c['statement']}\", paired over {c['n']} seeds: mean difference {c['mean_difference']:+.4f} "
            f"m/s^2, 95 % CI [{c['ci_low']:+.4f}, {c['ci_high']:+.4f}]; it holds for "
            f"{100 * c['fraction_holds']:.0f} % of the seeds.")


def markdown(fields: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown: per field, mean RMSE [95 % CI] per model and minute point, and the claim."""
    parts = []
    for spec, r in fields.items():
        header = ["model"] + minute_labels(r["minutes"])
        lines = [f"### Field `{spec or 'default'}` (collection `{r.get('collection_key')}`)", "",
                 f"Validation RMSE (m/s^2), mean [95 % bootstrap CI] over {len(r['seeds'])} seeds; label-noise "
                 f"floor {r['noise_floor']:.4f} m/s^2; validation set {r.get('validation_minutes', 0):.3g} min.", "",
                 "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(row) + " |" for row in table_rows(r, 4)]
        lines += ["", claim_text(r)]
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"


_COLORS = {"shallow": "tab:orange", "deep": "tab:blue", "equivariant": "tab:green", "equivariant_general": "tab:purple"}


def plot_field(ax: Any, summary: Mapping[str, Any], title: str) -> None:
    """Draw one field's mean RMSE against minutes, its 95 % CI band and the noise floor on ``ax``
    (a matplotlib Axes; this module imports no plotting library)."""
    minutes = summary["minutes"]
    for kind, m in summary["models"].items():
        ax.plot(minutes, m["rmse_mean"], "o-", color=_COLORS.get(kind), label=kind)
        ax.fill_between(minutes, m["rmse_ci_low"], m["rmse_ci_high"], color=_COLORS.get(kind), alpha=0.2)
    ax.axhline(summary["noise_floor"], color="k", ls="--", lw=1, label="label noise floor")
    ax.set_xlabel("training flight time (min)")
    ax.set_ylabel("validation RMSE (m/s^2)")
    ax.set_title(title)
    ax.legend()
