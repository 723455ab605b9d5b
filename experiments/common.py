"""What every experiment shares: the command line, the field option, results and tables.

Each experiment declares a frozen dataclass of arguments (typed, defaulted, with a
one-line `help`), parsed once in `main()`; the parsed config and seed are written
beside the results.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence, TypeVar

from tqdm import tqdm

from downwash_core.errors import ConfigError
from downwash_core.io import atomic_write_json
from downwash_core.provenance import code_version, describe, fingerprint
from downwash.staged import CollectionConfig, pipeline_dirs, provenance
from sim.field import check_field
from sim.fields.registry import DEFAULT_FIELD, resolve_field_spec

__all__ = [
    "WIND_HELP", "load_wind", "CommonArgs", "PipelineArgs", "Pipeline", "ProgressBar", "arg", "parse_args", "load_field", "resolve_pipeline",
    "write_results", "format_table", "setup_logging",
]

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
    field: str = arg("", "the ground-truth field: NAME[:KEY=VALUE,...] of the registry (python -m experiments.fields "
                         "lists them; default so2) or MODULE:FACTORY returning a field object")


@dataclass(frozen=True)
class PipelineArgs(CommonArgs):
    """Options of the experiments that use the staged collection and its trained models."""

    collection_dir: str = arg("", "staged collection folder (default: runs/pipeline/<field>-<key>/collection, "
                                  "keyed by the field, config and seed)")
    models_dir: str = arg("", "trained models folder (default: runs/pipeline/<field>-<key>/models); "
                              "collected and trained first when missing")


@dataclass(frozen=True)
class Pipeline:
    """The resolved collection an experiment uses: its settings, field, provenance and folders."""

    config: CollectionConfig
    field: Any
    record: dict
    collection_dir: Path
    models_dir: Path

    def provenance(self) -> dict:
        """For results.json: what the numbers came from."""
        return {"pipeline_key": fingerprint(self.record), "collection_dir": str(self.collection_dir),
                "models_dir": str(self.models_dir), "pipeline": self.record}


def resolve_pipeline(args: PipelineArgs, **settings: Any) -> Pipeline:
    """The field (checked), the collection settings (seed and --quick from args, plus `settings`)
    and the folders: the ones given, or those keyed by the provenance."""
    field = load_field(args.field)
    config = CollectionConfig(seed=args.seed, quick=args.quick, **settings)
    record = provenance(config, field)
    collection_dir, models_dir = pipeline_dirs(record)
    return Pipeline(config, field, record, Path(args.collection_dir or collection_dir),
                    Path(args.models_dir or models_dir))


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
    """The field a `--field` spec names, checked (outputs and provenance) before any work.

    Grammar (`sim.fields.registry`): "" (the default, `so2`), a registered NAME with
    optional parameters NAME:KEY=VALUE,... (`so2`, `so2:strength=8`,
    `momentum:thrust_scale=1.2`), or a MODULE:FACTORY import path whose factory returns
    the field object (`mypkg.fields:make`). `python -m experiments.fields` lists the names.
    """
    obj = resolve_field_spec(spec, label="--field")
    check_field(obj, name=f"--field {spec or DEFAULT_FIELD}")
    describe(obj)  # a field that cannot be fingerprinted stops here, before any work
    return obj


WIND_HELP = ("ambient wind: off (default), or a MIL-F-8785C severity light|moderate|severe|calm (calm: no gusts) "
             "with an optional mean wind, e.g. light:mean=2,0,0 (m/s, world frame, air moving toward +x)")


def load_wind(spec: str) -> Any:
    """The `DrydenWind` a `--wind` spec names, or None for "" / "off".

    Grammar: SEVERITY[:mean=U,V,W] with SEVERITY one of light, moderate, severe (the
    MIL-F-8785C W20 of 15, 30, 45 kt, which sets the gust intensities) or calm (no gusts,
    the mean wind only); U, V, W in m/s, world frame. ConfigError naming what is allowed.
    """
    from sim.wind import PRESETS_KT, DrydenWind

    text = (spec or "").strip()
    if text in ("", "off"):
        return None
    severity, _, rest = text.partition(":")
    allowed = f"off, calm, {', '.join(PRESETS_KT)}, each with an optional :mean=U,V,W (m/s)"
    if severity not in ("calm", *PRESETS_KT):
        raise ConfigError(f"--wind: unknown {severity!r}; allowed: {allowed}")
    mean = (0.0, 0.0, 0.0)
    if rest:
        key, eq, value = rest.partition("=")
        try:
            mean = tuple(float(x) for x in value.split(","))
        except ValueError:
            mean = ()
        if key.strip() != "mean" or not eq or len(mean) != 3:
            raise ConfigError(f"--wind: bad {rest!r} in {spec!r}; allowed: {allowed}")
    wind = DrydenWind(mean=mean) if severity == "calm" else DrydenWind.preset(severity, mean=mean)
    return None if wind.off else wind


def write_results(out: str | Path, results: dict, args: Any, provenance: dict | None = None) -> Path:
    """Atomically write results.json into `out`: the parsed arguments, the provenance (code
    version, field, seed base, plus `provenance`) and the results."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"code": code_version(), "seed": args.seed, "field_spec": args.field or "built-in", **(provenance or {})}
    payload = {"args": dataclasses.asdict(args), **results, "provenance": {**results.get("provenance", {}), **record}}
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
    """A tqdm progress bar with rate and ETA on stderr, for `progress(done, total)` callbacks;
    quiet when stderr is not a terminal (CI, logs, pipes). `ProgressBar(label)` is also the
    progress factory the library takes (`downwash.staged.collect(..., progress=ProgressBar)`)."""

    def __init__(self, label: str, unit: str = "it"):
        self.label, self.unit = label, unit
        self._bar: tqdm | None = None

    def __call__(self, done: int, total: int) -> None:
        if self._bar is None:
            self._bar = tqdm(total=total, desc=self.label, unit=self.unit, disable=not sys.stderr.isatty(),
                             dynamic_ncols=True, leave=True)
        self._bar.update(done - self._bar.n)
        if done >= total:
            self._bar.close()
