"""The report's rendering helpers: numbers, percentages, the order of conditions, markdown tables."""

from __future__ import annotations

import math
from typing import Any

from experiments.common import CONDITIONS

__all__ = ["ORDER", "fmt", "short", "pct", "crash_cell", "ordered", "markdown_table"]

ORDER = CONDITIONS  # conditions and models in one order: the references, then PAIRWISE_KINDS (the paper's order)


def fmt(x: Any, sig: int = 3) -> str:
    """A number with `sig` significant digits (thousands grouped, no exponent above 1e-4); None as '-'."""
    if x is None:
        return "-"
    if isinstance(x, (bool, int)):
        return str(x)
    x = float(x)
    if not math.isfinite(x) or x == 0:
        return "0" if x == 0 else str(x)
    mag = math.floor(math.log10(abs(x)))
    if mag < -4:
        return f"{x:.{sig - 1}e}"
    if mag >= sig - 1:
        return f"{round(x, sig - 1 - mag):,.0f}"
    return f"{x:.{sig - 1 - mag}f}"


def short(x: float) -> str:
    """Minutes, metres and seconds of a setting: two decimals at most (5, 7.5, 16.93)."""
    return f"{round(float(x), 2):g}"


def pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f} %"


def crash_cell(rate: float | None, n: int) -> str:
    """A crash rate over n flights with its Wilson 95 % interval: "0.0 % (0-27.8 %)"."""
    from sim.metrics import wilson_interval

    if rate is None:
        return "-"
    lo, hi = wilson_interval(int(round(rate * n)), n)
    return f"{pct(rate)} ({100 * lo:.1f}-{pct(hi)})"


def ordered(d: dict) -> list[tuple[str, Any]]:
    """The items of `d` in ORDER, unknown names after, alphabetically (the files hold sorted keys)."""
    return sorted(d.items(), key=lambda kv: (ORDER.index(kv[0]) if kv[0] in ORDER else len(ORDER), kv[0]))


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])
