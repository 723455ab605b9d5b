"""What every experiment shares: the command line, the field option, results and tables.

Each experiment declares a frozen dataclass of arguments (typed, defaulted, with a
one-line `help`), parsed once in `main()`; the parsed config and seed are written
beside the results.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence, TypeVar

from core.errors import ConfigError
from core.io import atomic_write_json
from sim.field import DownwashField

__all__ = ["CommonArgs", "ProgressBar", "arg", "parse_args", "load_field", "write_results", "format_table", "setup_logging"]

A = TypeVar("A")


def arg(default: Any, help: str) -> Any:
    """A dataclass field with a default and a one-line help text."""
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class CommonArgs:
    """Options every experiment takes (DESIGN section 10)."""

    out: str = arg("", "output folder (default runs/<experiment>)")
    seed: int = arg(0, "base seed; world k of a run uses seed + k")
    quick: bool = arg(False, "tiny budget for smoke tests")
    field: str = arg("", "MODULE:FACTORY returning a field object with DownwashField's call signature (default: built-in)")


def parse_args(cls: type[A], name: str, argv: Sequence[str] | None = None, description: str = "") -> A:
    """Build an argparse parser from the dataclass `cls`, parse, and fill the default --out."""
    parser = argparse.ArgumentParser(prog=f"python -m experiments.{name}", description=description)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        help_text = f.metadata.get("help", "")
        if f.type in (bool, "bool"):
            parser.add_argument(flag, action="store_true", help=help_text)
        else:
            conv = {"int": int, "float": float, "str": str}.get(f.type if isinstance(f.type, str) else f.type.__name__, str)
            parser.add_argument(flag, type=conv, default=f.default, help=f"{help_text} (default: {f.default})")
    ns = parser.parse_args(argv)
    values = {f.name: getattr(ns, f.name) for f in dataclasses.fields(cls)}
    if not values.get("out"):
        values["out"] = str(Path("runs") / name)
    return cls(**values)


def load_field(spec: str) -> Any:
    """The built-in field, or the object a `MODULE:FACTORY` import path returns."""
    if not spec:
        return DownwashField()
    if spec.count(":") != 1:
        raise ConfigError(f"--field: expected MODULE:FACTORY (e.g. mypkg.fields:make_field), got {spec!r}")
    module_name, factory_name = spec.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        raise ConfigError(f"--field: cannot import module {module_name!r}: {e}") from e
    factory = getattr(module, factory_name, None)
    if not callable(factory):
        raise ConfigError(f"--field: {module_name!r} has no callable {factory_name!r}")
    obj = factory()
    if not callable(obj):
        raise ConfigError(f"--field: {spec} returned {type(obj).__name__}, which is not callable as field(p_a, v_a, R_a, p_b, v_b)")
    return obj


def write_results(out: str | Path, results: dict, args: Any) -> Path:
    """Atomically write results.json (with the parsed arguments) into `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    payload = {"args": dataclasses.asdict(args), **results}
    path = out / "results.json"
    atomic_write_json(path, payload)
    return path


def format_table(rows: Sequence[Sequence[Any]], header: Sequence[str]) -> str:
    """A plain fixed-width table; floats with 4 significant digits."""

    def fmt(x: Any) -> str:
        if isinstance(x, float):
            return f"{x:.4g}"
        return str(x)

    cells = [[fmt(x) for x in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in cells]
    return "\n".join(lines)


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )


class ProgressBar:
    """A one-line progress bar on a terminal (stderr); silent when stderr is not a TTY."""

    def __init__(self, label: str, width: int = 30):
        self.label, self.width = label, width
        self.enabled = sys.stderr.isatty()
        self._last = -1

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        filled = int(self.width * done / max(total, 1))
        if filled == self._last and done != total:
            return
        self._last = filled
        bar = "#" * filled + "-" * (self.width - filled)
        end = "\n" if done >= total else ""
        sys.stderr.write(f"\r{self.label} [{bar}] {done}/{total}{end}")
        sys.stderr.flush()
