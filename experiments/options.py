"""What each option accepts: the names it takes and the checks `experiments.common.parse_args` runs.

The names are copied from their registries so that `--help` and a bad name need none of
the heavy imports behind them (tests/test_cli.py checks each copy against its source);
each `check` returns what is expected when a value is bad, else None, and runs while the
command line is parsed, before any work.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import math
import sys
from typing import Any, Callable, Sequence

from downwash_core.errors import ConfigError

__all__ = [
    "PAIRWISE_KINDS", "CONDITIONS", "DEFAULT_CONDITIONS", "FIELD_NAMES", "DEFAULT_FIELD", "PRESETS", "AGGREGATIONS",
    "WIND_SEVERITIES", "PAPER_MINUTES", "PAPER_MODELS", "CONTROLLER_NAMES", "DEFAULT_CONTROLLER", "FIELD_CHOICES",
    "SEED_COUNT_MAX", "WIND_HELP", "RegisteredNames", "PLUGIN_GROUP", "GUARDED", "UNLEARNED",
    "seed_count_check", "one_of", "names_check", "registered_field_names", "field_check", "wind_check", "load_wind",
    "in_range", "range_words", "comma_items", "comma_numbers",
]


PLUGIN_GROUP = "downwash_testbed.plugins"  # downwash_core.registry.PLUGIN_GROUP
GUARDED = "_guarded"  # downwash.conditions.GUARDED: the suffix of a guarded learned condition
UNLEARNED = ("integral", "dob")  # downwash.conditions.UNLEARNED: the non-learned compensations


@functools.lru_cache(maxsize=1)
def plugins_installed() -> bool:
    """Whether any package registers components through the entry-point group (`downwash_core.registry`)."""
    from importlib.metadata import entry_points

    return bool(entry_points(group=PLUGIN_GROUP))


class RegisteredNames(Sequence[str]):
    """A registry's names for the option checks: the static copy (the built-in names, no import), and
    the registry itself, with every installed plugin's names, once a name outside the copy is asked for
    (`in`): a plugin's component passes the check where the built-in ones do, and a bad name's message
    lists every registered one."""

    def __init__(self, static: tuple[str, ...], module: str, attr: str):
        self.static, self.module, self.attr = static, module, attr
        self._live: tuple[str, ...] | None = None

    def _names(self) -> tuple[str, ...]:
        return self._live if self._live is not None else self.static

    def __contains__(self, name: object) -> bool:
        if name in self.static:
            return True
        if self._live is None:
            if not plugins_installed():  # nothing can have been added: refused without importing the stack
                return False
            self._live = tuple(getattr(importlib.import_module(self.module), self.attr))  # its plugins loaded
        return name in self._live

    def __getitem__(self, index: Any) -> Any:
        return self._names()[index]

    def __len__(self) -> int:
        return len(self._names())

    def __eq__(self, other: object) -> bool:
        return tuple(self) == (tuple(other) if isinstance(other, (tuple, list, RegisteredNames)) else other)

    def __hash__(self) -> int:
        return hash(tuple(self))


# The names the options take, copied from their registries so that `--help` needs none of
# the heavy imports behind them (tests/test_cli.py checks each against its source).
PAIRWISE_KINDS = ("shallow", "deep", "equivariant", "equivariant_general", "equivariant_memory",
                  "deep_memory")  # downwash.models.PAIRWISE_KINDS
CONDITIONS = ("no_downwash", "baseline", "oracle", "integral", "dob", *PAIRWISE_KINDS,
              *(k + "_guarded" for k in PAIRWISE_KINDS), *(k + "_dob" for k in PAIRWISE_KINDS))  # downwash.conditions.CONDITIONS
DEFAULT_CONDITIONS = ("no_downwash", "baseline", "oracle", *PAIRWISE_KINDS[:4], *(k + "_guarded" for k in PAIRWISE_KINDS[:4]),
                      "integral", "dob", *(k + "_dob" for k in PAIRWISE_KINDS[:4]))  # downwash.conditions.DEFAULT_CONDITIONS
FIELD_NAMES = ("so2", "so2-c4", "so2-swirl", "so2-skew", "momentum", "shed", "jet", "pybullet")  # sim.fields.registry.FIELDS
DEFAULT_FIELD = "so2"  # sim.fields.registry.DEFAULT_FIELD
PRESETS = RegisteredNames(("pair", "stack3", "stack4", "stack", "swap", "formation5", "heavy_over_light",
                           "crazyflie_stack", "mixed_formation"), "sim.presets", "PRESETS")  # sim.presets.PRESETS
AGGREGATIONS = ("linear", "velocity", "shielding")  # sim.aggregation.AGGREGATIONS
WIND_SEVERITIES = ("light", "moderate", "severe")  # sim.wind.PRESETS_KT
PAPER_MINUTES = (1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0)  # downwash.sweep_cells.PAPER_MINUTES
PAPER_MODELS = ("shallow", "deep", "equivariant")  # downwash.sweep_cells.PAPER_MODELS
CONTROLLER_NAMES = RegisteredNames(("lqr", "mellinger", "pid", "indi"), "controllers.registry",
                                   "CONTROLLERS")  # controllers.registry.CONTROLLER_NAMES
DEFAULT_CONTROLLER = "lqr"  # controllers.registry.DEFAULT_CONTROLLER

FIELD_CHOICES = (f"NAME[:KEY=VALUE,...] with NAME one of {', '.join(FIELD_NAMES)} (python -m experiments.fields "
                 f"lists their parameters), or MODULE:FACTORY returning a field object")
# flights per condition (or trials per point): they fly as one batch of worlds, so a count beyond any sensible
# study is refused while parsing, not by the memory check after the collection and training
SEED_COUNT_MAX = 1000


def _num(x: float) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def in_range(value: float, b: dict[str, float]) -> bool:
    """Whether a number is finite and within the bounds `b` (ge/gt/le/lt)."""
    finite = isinstance(value, int) or math.isfinite(value)  # isfinite cannot take an int beyond a float
    return (finite and ("ge" not in b or value >= b["ge"]) and ("gt" not in b or value > b["gt"])
            and ("le" not in b or value <= b["le"]) and ("lt" not in b or value < b["lt"]))


def range_words(integer: bool, b: dict[str, float]) -> str:
    """What a number with the bounds `b` (ge/gt/le/lt) takes, in words: '>= 1' (an integer: the parsers
    check the type), 'an integer in [5, 301]', 'a finite number in (0, 3600]'."""
    lo = ("[", b["ge"]) if "ge" in b else ("(", b["gt"]) if "gt" in b else None
    hi = ("]", b["le"]) if "le" in b else (")", b["lt"]) if "lt" in b else None
    if lo and hi:
        return f"{'an integer' if integer else 'a finite number'} in {lo[0]}{_num(lo[1])}, {_num(hi[1])}{hi[0]}"
    side = (f"{'>=' if lo[0] == '[' else '>'} {_num(lo[1])}" if lo else
            f"{'<=' if hi[0] == ']' else '<'} {_num(hi[1])}" if hi else "")
    if integer:
        return side or "an integer"
    return f"a finite number {side}".rstrip()


def seed_count_check(n: int) -> str | None:
    """A `check` for a count of seeds (flights per condition, trials per point): at most SEED_COUNT_MAX."""
    return None if n <= SEED_COUNT_MAX else f"expected at most {SEED_COUNT_MAX}"


def one_of(allowed: Sequence[str]) -> Callable[[str], str | None]:
    """A `check` for one name from `allowed`."""

    def check(text: str) -> str | None:
        return None if text in allowed else f"unknown {text!r}; allowed: {', '.join(allowed)}"

    return check


def registered_field_names(name: str | None = None) -> tuple[str, ...]:
    """The registered field names: the registry's own once it is loaded (a user's `register_field`
    shows there), or when `name` is not a built-in one (the registry loads the installed plugins,
    which may have registered it); else the static copy."""
    registry = sys.modules.get("sim.fields.registry")
    if registry is None and name is not None and name not in FIELD_NAMES and plugins_installed():
        registry = importlib.import_module("sim.fields.registry")
    return tuple(registry.FIELDS) if registry is not None else FIELD_NAMES


def field_check(spec: str) -> str | None:
    """A `check` for a `--field` spec: the grammar of `sim.fields.registry.parse_field_spec` and its
    names, without loading the registry (numba); for MODULE:FACTORY, that the module imports and the
    factory is a callable that takes no arguments. Parameters and what the factory returns are
    checked when the field is loaded (`load_field`), still before any work."""
    text = spec.strip()
    if not text:
        return None
    head, colon, tail = text.partition(":")
    names = registered_field_names(head if "." not in head else None)  # (a dotted head: a module path)
    if head in names:
        return None
    registered = ", ".join(names)
    if not colon:
        return (f"unknown field {text!r}; registered: {registered}; or a MODULE:FACTORY import path "
                "(e.g. mypkg.fields:make_field)")
    if "=" in tail:
        return (f"unknown field {head!r} in {text!r}; registered: {registered} (a MODULE:FACTORY import path takes "
                "no KEY=VALUE parameters)")
    if ":" in tail or not head or not tail:
        return f"expected a registered field ({registered}) or MODULE:FACTORY (e.g. mypkg.fields:make_field)"
    return _factory_problem(head, tail)


def _factory_problem(module: str, name: str) -> str | None:
    """What is wrong with MODULE:FACTORY as a field factory that can be seen without calling it, else None."""
    try:
        factory = getattr(importlib.import_module(module), name)
    except ImportError as e:
        return f"cannot import {module!r} ({e})"
    except AttributeError:
        return f"module {module!r} has no {name!r}"
    if not callable(factory):
        return f"{module}:{name} is a {type(factory).__name__}, not a function that returns a field"
    try:
        inspect.signature(factory).bind()
    except TypeError as e:  # it needs arguments the experiment cannot give
        return f"{module}:{name} must take no arguments and return a field ({e})"
    except ValueError:  # a builtin without a signature: its call tells
        pass
    return None


def comma_items(text: str) -> list[str]:
    """The items of an option's comma list, stripped, empty ones dropped: 'a, b,' -> ['a', 'b']."""
    return [x.strip() for x in text.split(",") if x.strip()]


def comma_numbers(text: str) -> list[float]:
    """The numbers of an option's comma list (`comma_items`); ValueError for an item that is not one."""
    return [float(x) for x in comma_items(text)]


def names_check(allowed: Sequence[str], empty: bool = False) -> Callable[[str], str | None]:
    """A `check` for a comma list of names from `allowed` (at least one unless `empty`, each once), so
    that a bad name is refused with the others, before any import of the registry it comes from."""

    def check(text: str) -> str | None:
        names = comma_items(text)
        unknown = [n for n in names if n not in allowed]
        if (not names and not empty) or unknown or len(set(names)) != len(names):
            why = f"unknown {unknown}" if unknown else "duplicate names" if names else "no name"
            return f"{why}; allowed: a comma list of {', '.join(allowed)}, each at most once"
        return None

    return check


WIND_HELP = (f"ambient wind: off (default), or a MIL-F-8785C severity {'|'.join(WIND_SEVERITIES)}|calm (calm: no gusts) "
             "with an optional mean wind, e.g. light:mean=2,0,0 (m/s, world frame, air moving toward +x)")


def _parse_wind(spec: str) -> tuple[str, tuple[float, ...]] | None:
    """(severity, mean) of a `--wind` spec, None for "" / "off"; ConfigError naming what is allowed.
    Plain text work (the severities are the static copy), so that parse_args can check it."""
    text = (spec or "").strip()
    if text in ("", "off"):
        return None
    severity, _, rest = text.partition(":")
    allowed = f"off, calm, {', '.join(WIND_SEVERITIES)}, each with an optional :mean=U,V,W (m/s, finite)"
    if severity not in ("calm", *WIND_SEVERITIES):
        raise ConfigError(f"--wind: unknown {severity!r}; allowed: {allowed}")
    mean: tuple[float, ...] = (0.0, 0.0, 0.0)
    if rest:
        key, eq, value = rest.partition("=")
        try:
            mean = tuple(float(x) for x in value.split(","))
        except ValueError:
            mean = ()
        if key.strip() != "mean" or not eq or len(mean) != 3 or not all(map(math.isfinite, mean)):
            raise ConfigError(f"--wind: bad {rest!r} in {spec!r}; allowed: {allowed}")
    return severity, mean


def wind_check(spec: str) -> str | None:
    """A `check` for a `--wind` spec (what `load_wind` accepts)."""
    try:
        _parse_wind(spec)
    except ConfigError as e:
        return str(e).removeprefix("--wind: ")
    return None


def load_wind(spec: str) -> Any:
    """The `DrydenWind` a `--wind` spec names, or None for "" / "off".

    Grammar: SEVERITY[:mean=U,V,W] with SEVERITY one of light, moderate, severe (the
    MIL-F-8785C W20 of 15, 30, 45 kt, which sets the gust intensities) or calm (no gusts,
    the mean wind only); U, V, W in m/s, world frame. ConfigError naming what is allowed.
    """
    parsed = _parse_wind(spec)
    if parsed is None:
        return None
    from sim.wind import DrydenWind

    severity, mean = parsed
    wind = DrydenWind(mean=mean) if severity == "calm" else DrydenWind.preset(severity, mean=mean)
    return None if wind.off else wind
