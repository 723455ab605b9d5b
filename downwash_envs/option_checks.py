"""The envs' keyword-option checks, shared by every env's options (`downwash_envs.config`'s and the swarm's).

An unknown option raises TypeError worded as Python's own for an unexpected keyword; a numeric
option refuses strings and bools ("0.6", True), which float() would read as numbers, before its
range check (`downwash_core.validate`) names the option and the allowed range (ConfigError).
`downwash_envs.config` re-exports these.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.validate import number, pair

__all__ = ["unknown_options_error", "check_not_text_or_bool", "number_option", "pair_option"]


def unknown_options_error(who: str, unknown: Sequence[str], allowed: Sequence[str]) -> TypeError:
    """TypeError for unknown keyword options, worded as Python's own (``got an unexpected keyword
    argument 'x'``): wrappers that probe an optional keyword (TorchRL's ``GymEnv`` passes ``frameskip``)
    look for that wording and retry without it."""
    return TypeError(f"{who} got an unexpected keyword argument {unknown[0]!r} (unknown option(s) {list(unknown)}; "
                     f"allowed: {', '.join(allowed)})")


def _text_or_bool(value: Any) -> tuple[bool, Any]:
    """(True, the first string or bool in `value`) or (False, None); `value` a number, or a sequence
    or array of them. float() reads "0.6" as 0.6 and True as 1.0, so these would pass a range check."""
    if isinstance(value, (str, bytes, bool, np.bool_)):
        return True, value
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "bUS":
            return True, value
        if value.dtype.kind != "O":
            return False, None
        value = value.ravel().tolist()
    if isinstance(value, (list, tuple)):
        for v in value:
            found, bad = _text_or_bool(v)
            if found:
                return True, bad
    return False, None


def check_not_text_or_bool(name: str, value: Any, allowed: str) -> None:
    """ConfigError naming `name` and what is `allowed` when `value` is, or holds, a string or a bool."""
    found, bad = _text_or_bool(value)
    if found:
        what = f"a {type(bad).__name__}" if bad is value else f"{bad!r} is a {type(bad).__name__}"
        raise ConfigError(f"{name}: expected a number, got {value!r} ({what}, not a number); allowed {allowed}")


def number_option(name: str, value: Any, unit: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
    """`downwash_core.validate.number`, which also refuses strings and bools."""
    check_not_text_or_bool(name, value, f"{'(' if lo_open else '['}{lo}, {hi}] {unit}")
    return number(name, value, unit, lo, hi, lo_open=lo_open)


def pair_option(name: str, value: Any, unit: str, lo: float, hi: float) -> tuple[float, float]:
    """`downwash_core.validate.pair`, which also refuses strings and bools."""
    check_not_text_or_bool(name, value, f"(low, high) with {lo} <= low <= high <= {hi} {unit}")
    return pair(name, value, unit, lo, hi)
