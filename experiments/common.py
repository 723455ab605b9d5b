"""What every experiment shares: the command line, the field option, results and tables.

Each experiment declares a frozen dataclass of arguments (typed, defaulted, with a
one-line `help`), parsed once in `main()`; the parsed config and seed are written
beside the results. Any option may also come from a TOML file (`--config FILE.toml`,
keys are the long option names); a flag on the command line overrides the file.

Every numeric option states its range once, in its `arg(..., ge=, gt=, le=, lt=)`, and
every option of names states them in its `check=`; `parse_args` checks each number (finite, within its
range), each name and each output folder (writable) before any work, naming the flag. The file may also
hold tables of library settings ([lqr], [sim], [training], [guard], [safety]) for the experiments that
apply them (`config_tables`); `experiments.config_file` reads it and writes the resolved `config.toml`
beside each results.json, and `experiments.components` turns the tables, `--controller` and `--safety`
(`FlightArgs`) into the library's settings. Tables, logging and progress bars: `experiments.console`.
`--quick` gives the options with an `arg(..., quick=)` that value unless they are given.
`out_lock` holds the --out folder for the run, so two runs on one folder take turns.
`run_main` runs an experiment from the command line: an expected error (`TestbedError`)
prints one line and exits 2 (a bad option) or 1 (a bad file), `--debug` shows its
traceback; a bug keeps its traceback.

Importing this module is cheap (no torch, numba, mujoco or matplotlib), and so is
importing an experiment: they load the heavy stack inside the functions that need it,
so that `--help` and a bad option answer at once. The choices the help lists come from
the static copies in `experiments.options`, which tests/test_cli.py ties to their registries.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterator, NoReturn, Sequence, TypeVar

from downwash_core.errors import ConfigError, TestbedError
from experiments.console import ProgressBar, format_table, setup_logging
from experiments.options import (AGGREGATIONS, CONDITIONS, CONTROLLER_NAMES, DEFAULT_CONDITIONS, DEFAULT_CONTROLLER,
                                 DEFAULT_FIELD, FIELD_CHOICES, FIELD_NAMES, PAIRWISE_KINDS, PAPER_MINUTES, PAPER_MODELS,
                                 PRESETS, SEED_COUNT_MAX, WIND_HELP, WIND_SEVERITIES, comma_items, comma_numbers,
                                 field_check, in_range, load_wind, names_check, one_of, range_words,
                                 registered_field_names, seed_count_check, wind_check)

__all__ = [
    "WIND_HELP", "load_wind", "CommonArgs", "PipelineArgs", "FlightArgs", "Pipeline", "ProgressBar", "arg",
    "parse_args", "load_field", "build_parser", "read_config", "resolve_pipeline", "write_results", "format_table",
    "script", "run_main", "check_writable", "check_options", "allowed_range", "names_check", "comma_items",
    "comma_numbers", "one_of", "field_check",
    "wind_check", "registered_field_names", "seed_count_check", "out_lock", "OneLineParser", "setup_logging",
    "CONDITIONS", "SEED_COUNT_MAX", "DEFAULT_CONDITIONS", "PAIRWISE_KINDS", "option_fields", "one_line",
    "CONTROLLER_NAMES", "FIELD_NAMES", "DEFAULT_FIELD", "PRESETS", "AGGREGATIONS", "WIND_SEVERITIES", "PAPER_MINUTES",
    "PAPER_MODELS",
]

A = TypeVar("A")

SEED_MAX = 2**32 - 1  # seeds go to NumPy's and torch's generators; seed + k stays far inside int64
FLIGHT_SECONDS_MAX = 3600.0  # s, one flight: its log rows are allocated up front, so a huge length is refused
_NO_QUICK = object()  # arg(quick=...) not given: --quick leaves the option alone


def arg(default: Any, help: str, *, ge: float | None = None, gt: float | None = None, le: float | None = None,
        lt: float | None = None, check: Callable[[Any], str | None] | None = None, output: str | None = None,
        quick: Any = _NO_QUICK) -> Any:
    """A dataclass field with a default and a one-line help text.

    A number's range is stated here, once (`ge`/`gt`/`le`/`lt`, and/or `check(value)`, which
    returns what is expected when the value is bad, else None): `parse_args` checks it, and
    that a float is finite, before any work. `output` ("dir" or "file") marks a path the
    experiment writes, checked for writing before any work. `quick`: the value `--quick`
    gives the option when it is not given (on the command line or in --config); one given
    is kept.
    """
    if output not in (None, "dir", "file"):
        raise ValueError(f"output: expected None, 'dir' or 'file', got {output!r}")
    metadata: dict[str, Any] = {"help": help}
    if quick is not _NO_QUICK:
        metadata["quick"] = quick
    bounds = {k: v for k, v in (("ge", ge), ("gt", gt), ("le", le), ("lt", lt)) if v is not None}
    if bounds:
        metadata["bounds"] = bounds
    if check is not None:
        metadata["check"] = check
    if output is not None:
        metadata["output"] = output
    return field(default=default, metadata=metadata)


@dataclass(frozen=True)
class CommonArgs:
    """Options every experiment takes, and the config file's tables (no flags: they come from --config)."""

    # the tables of the config file the experiment applies; any other table is refused, never ignored
    config_tables: ClassVar[tuple[str, ...]] = ()

    out: str = arg("", "output folder (default runs/<experiment>)", output="dir")
    seed: int = arg(0, "base seed; world k of a run uses seed + k", ge=0, le=SEED_MAX)
    quick: bool = arg(False, "tiny budget for smoke tests")
    field: str = arg("", f"the ground-truth field (default {DEFAULT_FIELD}): {FIELD_CHOICES}", check=field_check)
    tables: dict = dataclasses.field(default_factory=dict, hash=False,  # ("field" is the option above)
                                     metadata={"help": "the config file's tables: {table: {key: value}}"})


@dataclass(frozen=True)
class PipelineArgs(CommonArgs):
    """Options of the experiments that use the staged collection and its trained models."""

    collection_dir: str = arg("", "staged collection folder (default: runs/pipeline/<field>-<key>/collection, "
                                  "keyed by the field, config and seed)")
    models_dir: str = arg("", "trained models folder (default: runs/pipeline/<field>-<key>/models); "
                              "collected and trained first when missing")


@dataclass(frozen=True)
class FlightArgs(PipelineArgs):
    """Options of the experiments that fly conditions with the trained models: also the flights' controller."""

    # the flights' controller ([lqr], with --controller lqr), simulator, guard and safety layer settings
    config_tables: ClassVar[tuple[str, ...]] = ("lqr", "sim", "guard", "safety")

    controller: str = arg(DEFAULT_CONTROLLER, f"the flights' outer-loop controller: {', '.join(CONTROLLER_NAMES)} "
                                              "(lqr: the paper's LQR, the [lqr] table's; mellinger, pid: the Crazyflie "
                                              "firmware's, its default gains; indi: incremental dynamic inversion; "
                                              "controllers.registry). The staged collection flies the LQR whatever "
                                              "this says; the condition integral (the LQR's integral action) needs "
                                              "lqr, and with another the default conditions leave it out",
                          check=one_of(CONTROLLER_NAMES))
    safety: bool = arg(False, "fly every condition with the safety layer (sim.safety: a control barrier function filter "
                              "on the commanded accelerations that keeps stacked vehicles apart and off the ground; "
                              "its settings: the config file's [safety] table, which also turns it on)")


@dataclass(frozen=True)
class Pipeline:
    """The resolved collection an experiment uses: its settings, field, provenance and folders."""

    config: Any  # downwash.staged.CollectionConfig
    field: Any
    record: dict
    collection_dir: Path
    models_dir: Path

    def provenance(self) -> dict:
        """For results.json: what the numbers came from."""
        from downwash_core.provenance import fingerprint

        return {"pipeline_key": fingerprint(self.record), "collection_dir": str(self.collection_dir),
                "models_dir": str(self.models_dir), "pipeline": self.record}


def resolve_pipeline(args: PipelineArgs, *, models: Sequence[str] = PAIRWISE_KINDS, **settings: Any) -> Pipeline:
    """The field (checked), the collection settings (seed and --quick from args, plus `settings`)
    and the folders: the ones given, or those keyed by the provenance. When any of `models` (the
    kinds the run needs) is missing, the run collects and trains: both folders are then checked
    for writing (ConfigError naming --collection-dir or --models-dir), before any work."""
    from downwash.staged import CollectionConfig, pipeline_dirs, provenance
    from downwash_core.numerics import request_portable_torch

    request_portable_torch()  # before torch's first operation: training then has the same bits on every CPU
    field = load_field(args.field)
    config = CollectionConfig(seed=args.seed, quick=args.quick, **settings)
    record = provenance(config, field)
    collection_dir, models_dir = pipeline_dirs(record)
    p = Pipeline(config, field, record, Path(args.collection_dir or collection_dir), Path(args.models_dir or models_dir))
    _check_pipeline_writable(p, args, models)
    return p


def _check_pipeline_writable(p: Pipeline, args: PipelineArgs, models: Sequence[str]) -> None:
    """The collection and models folders must take files when the run may write there: when a
    model it needs is missing (`ensure_models` then collects and trains). Folders holding those
    models may be read-only (shared models)."""
    if all((p.models_dir / f"{kind}.pt").is_file() for kind in models):
        return
    check_writable("--collection-dir" + ("" if args.collection_dir else " (default)"), p.collection_dir)
    check_writable("--models-dir" + ("" if args.models_dir else " (default)"), p.models_dir)


def check_writable(option: str, path: str | Path, kind: str = "dir") -> Path:
    """ConfigError naming `option` unless a file can be written in the folder `path` (kind "dir") or
    the file `path` can be made (kind "file": its folder takes files and `path` is no folder).

    Tried for real: the missing folders are made and a temporary file written in the folder,
    then both removed, so the check leaves nothing behind (permissions, a read-only mount, a
    file where a folder is expected, a full quota all show here, before any work).
    """
    target = Path(path)
    if kind == "file":
        if target.is_dir():
            raise ConfigError(f"{option}: {path} is a folder; expected a file path")
        folder = target.parent
    else:
        folder = target
    missing, q = [], folder
    while not q.exists() and not q.is_symlink() and q != q.parent:
        missing.append(q)
        q = q.parent
    if q.exists() and not q.is_dir():
        raise ConfigError(f"{option}: cannot write to {path} ({q} is a file, not a folder)")
    made: list[Path] = []
    try:
        for d in reversed(missing):
            try:
                d.mkdir()
            except FileExistsError:  # made meanwhile by someone else: not ours to remove
                continue
            made.append(d)
        fd, tmp = tempfile.mkstemp(prefix=".write-check-", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise ConfigError(f"{option}: cannot write to {path} ({e.strerror or e})") from None
    finally:
        for d in reversed(made):
            try:
                d.rmdir()
            except OSError:
                pass
    return target


_KINDS = {"int": int, "float": float, "str": str, "bool": bool, "dict": dict}


def option_type(f: dataclasses.Field) -> type:
    """The option's type (int, float, str or bool; dict: the tables), from its annotation (a type or its name)."""
    return _KINDS.get(f.type if isinstance(f.type, str) else f.type.__name__, str)


def option_fields(cls: Any) -> list[dataclasses.Field]:
    """The fields of an options class (or instance) that are command-line options: all but the tables."""
    return [f for f in dataclasses.fields(cls) if option_type(f) is not dict]


def option_name(name: str) -> str:
    return "--" + name.replace("_", "-")


def allowed_range(f: dataclasses.Field) -> str:
    """What a numeric option takes, in words: '>= 1' (an integer: argparse and the TOML reader
    check the type), 'an integer in [5, 301]', 'a finite number in (0, 3600]'."""
    return range_words(option_type(f) is int, f.metadata.get("bounds", {}))


def _out_of_range(f: dataclasses.Field, value: Any) -> str | None:
    """What an option expects when `value` is bad (a number not finite or outside its range, or
    refused by the field's `check`), else None."""
    if option_type(f) in (int, float) and not isinstance(value, bool) and not in_range(value, f.metadata.get("bounds", {})):
        return f"expected {allowed_range(f)}"
    check = f.metadata.get("check")
    return check(value) if check is not None else None


def check_options(args: Any) -> None:
    """ConfigError naming the first option of the dataclass `args` whose value is out of its range or
    refused by its check, or the first bad table: what parse_args checks, for options built in Python
    (`run(args)`)."""
    from experiments.config_file import check_tables

    for f in option_fields(args):
        problem = _out_of_range(f, getattr(args, f.name))
        if problem:
            raise ConfigError(f"{option_name(f.name)}: {problem}, got {getattr(args, f.name)!r}")
    check_tables(getattr(args, "tables", {}), type(args))


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line (the option and what is wrong; --help lists the
    options), exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser(cls: type, name: str, description: str = "") -> argparse.ArgumentParser:
    """The argparse parser of the dataclass `cls`: one long option per field, plus --config and --debug."""
    # allow_abbrev=False: otherwise `--models x` is silently `--models-dir x` where no --models exists
    parser = OneLineParser(prog=f"python -m experiments.{name}", description=description,
                           formatter_class=argparse.RawDescriptionHelpFormatter, allow_abbrev=False)
    for f in option_fields(cls):
        help_text = f.metadata.get("help", "")
        if option_type(f) is bool:  # --no-X undoes an X = true of the config file
            parser.add_argument(option_name(f.name), action=argparse.BooleanOptionalAction, default=f.default,
                                help=help_text)
        else:
            notes = [f"default: {f.default}"] if f.default != "" else []
            if option_type(f) in (int, float) and "bounds" in f.metadata:
                notes.append(allowed_range(f).removeprefix("an integer ").removeprefix("a finite number "))
            if "quick" in f.metadata:
                notes.append(f"--quick: {f.metadata['quick']}")
            parser.add_argument(option_name(f.name), type=option_type(f), default=f.default,
                                help=f"{help_text} ({'; '.join(notes)})" if notes else help_text)
    taken = ", ".join(f"[{t}]" for t in getattr(cls, "config_tables", ()))
    parser.add_argument("--config", metavar="FILE.toml", default=None,
                        help="read options from this TOML file (keys: the long option names, with - or _; a list "
                             "option also takes an array" + (f"; tables: {taken}" if taken else "") + "); flags on "
                             "the command line override it; each run writes its resolved config.toml beside its "
                             "results")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an expected error (a bad option or file) instead of one line")
    return parser


def read_config(path: str | Path, cls: type) -> dict[str, Any]:
    """{field name: value} from the TOML file `path` (its tables, when it has any, under "tables"),
    each key an option of `cls` and each value of its type; ConfigError naming the file, the key and
    the allowed options otherwise (`experiments.config_file.read_file`)."""
    from experiments.config_file import read_file

    values, tables = read_file(path, cls)
    return {**values, **({"tables": tables} if tables else {})}


def one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


_debug = False  # the last parse_args saw --debug: run_main then re-raises expected errors


def parse_args(cls: type[A], name: str, argv: Sequence[str] | None = None, description: str = "") -> A:
    """Parse the command line into the dataclass `cls`, fill the default --out, check every option.

    With `--config FILE.toml`, the file's values replace the defaults and the flags given
    override the file; its tables (those `cls.config_tables` names) go to `tables`. A bad file,
    an unknown key or table, a value of the wrong type, a number that is not finite or outside
    its field's range (from a flag or the file), an empty --out or --config is a usage error
    (exit 2, one line) naming the option, before any work. With --quick, each option with a
    `quick` value that was not given takes it. Then each output path (`--out`, any field with
    `output=`) is checked for writing: ConfigError naming it.
    """
    from experiments.config_file import read_file, unwritable

    global _debug
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(cls, name, description)
    ns = parser.parse_args(argv)
    _debug = ns.debug
    from_file: dict[str, Any] = {}
    tables: dict[str, dict[str, Any]] = {}
    if ns.config is not None:
        if not ns.config.strip():  # else it would silently mean "no file"
            parser.error(f"--config: expected the path of a TOML file, got {ns.config!r}")
        try:
            from_file, tables = read_file(ns.config, cls)
        except ConfigError as e:
            parser.error(str(e))
        parser.set_defaults(**from_file)
        ns = parser.parse_args(argv)
    fields = option_fields(cls)
    values = {f.name: getattr(ns, f.name) for f in fields}
    given = _given_on_command_line(cls, name, argv) | set(from_file)
    if values.get("quick"):
        for f in fields:
            if "quick" in f.metadata and f.name not in given:
                values[f.name] = f.metadata["quick"]
    for f in fields:
        where = f" (from --config {ns.config})" if f.name in from_file and values[f.name] is from_file[f.name] else ""
        problem = _out_of_range(f, values[f.name])
        if problem:
            parser.error(f"{option_name(f.name)}: {problem}, got {values[f.name]!r}{where}")
        if f.name == "out" and f.name in given and not values["out"].strip():  # else it would mean runs/<name>
            parser.error(f"--out: expected a folder path (without --out: runs/{name}), got {values['out']!r}{where}")
    if not values.get("out"):
        values["out"] = str(Path("runs") / name)
    problem = unwritable(values)  # config.toml must hold every value, so that it reruns the run
    if problem:
        parser.error(problem)
    for f in fields:
        if f.metadata.get("output") and values[f.name]:
            check_writable(option_name(f.name), values[f.name], f.metadata["output"])
    return cls(**values, **({"tables": tables} if tables else {}))


def _given_on_command_line(cls: type, name: str, argv: list[str]) -> set[str]:
    """The options of `cls` that `argv` gives (so that --quick keeps them)."""
    unset = object()  # not a string: argparse would convert a string default with the option's type
    probe = build_parser(cls, name)
    probe.set_defaults(**{f.name: unset for f in option_fields(cls)})
    ns = probe.parse_args(argv)
    return {f.name for f in option_fields(cls) if getattr(ns, f.name) is not unset}


def load_field(spec: str) -> Any:
    """The field a `--field` spec names, checked (outputs and provenance) before any work.

    Grammar (`sim.fields.registry`): "" (the default, `so2`), a registered NAME with
    optional parameters NAME:KEY=VALUE,... (`so2`, `so2:strength=8`,
    `momentum:thrust_scale=1.2`), or a MODULE:FACTORY import path whose factory returns
    the field object (`mypkg.fields:make`). `python -m experiments.fields` lists the names.
    """
    from downwash_core.provenance import describe
    from sim.field import check_field
    from sim.fields.registry import DEFAULT_FIELD, parse_field_spec, resolve_field_spec

    label = f"--field {spec or DEFAULT_FIELD}"
    imported = parse_field_spec(spec, label="--field")[0] == "import"
    try:
        obj = resolve_field_spec(spec, label="--field")
        check_field(obj, name=label)
        describe(obj)  # a field that cannot be fingerprinted stops here, before any work
    except ConfigError:
        raise
    except (Exception, SystemExit) as e:
        if not imported:  # a registered field that fails is a bug: keep its traceback
            raise
        # the user's MODULE:FACTORY is not a field factory (it needs arguments, exits, or what it returns
        # fails when called as a field): name the option, as for any bad value
        raise ConfigError(f"{label}: expected MODULE:FACTORY to name a function that takes no arguments and "
                          f"returns a field; it failed with {type(e).__name__}: {one_line(e)}") from e
    return obj


@contextlib.contextmanager
def out_lock(args: Any, name: str) -> Iterator[None]:
    """Hold the lock of the run's --out folder (`args.out`) for the block, so that two runs on one
    folder never mix their files: the second waits for the first (logging once which process holds
    it), then runs, as a second collection on a pipeline folder does (`downwash_core.locks`). A killed
    holder lets go at once. The temporary files a killed run left beside the results go first (the
    folder itself, not its subfolders, which may be other runs' folders under locks of their own).
    The lock file goes on release, and so do the folders the lock had to make if the run left them
    empty (a run refused after parsing leaves nothing behind)."""
    from downwash_core.io import remove_temporaries
    from downwash_core.locks import LOCK_NAME, file_lock

    out = Path(args.out)
    made, q = [], out  # the folders that do not exist yet, deepest first
    while not q.exists() and q != q.parent:
        made.append(q)
        q = q.parent
    try:
        with file_lock(out / LOCK_NAME, label=f"python -m experiments.{name}", target=out, remove=True):
            remove_temporaries(out, recursive=False)
            yield
    finally:
        for d in made:
            try:
                d.rmdir()
            except OSError:  # holds the run's files, or another run's
                break


def write_results(out: str | Path, results: dict, args: Any, provenance: dict | None = None) -> Path:
    """Atomically write results.json into `out`: the parsed arguments (with the tables the experiment
    applies, resolved), the provenance (code version, field, seed base, plus `provenance`) and the
    results. Into the run's own --out, first its resolved config.toml, with which `--config` reruns it."""
    from downwash_core.io import atomic_write_json
    from downwash_core.provenance import code_version
    from experiments.config_file import CONFIG_NAME, resolved_tables, write_config

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tables = resolved_tables(args)
    if getattr(args, "controller", DEFAULT_CONTROLLER) != "lqr":  # flown without the LQR: a rerun refuses [lqr]
        tables.pop("lqr", None)
    if out == Path(args.out):  # not the folders an experiment writes per part (swarm: one per preset)
        write_config(out / CONFIG_NAME, args, tables)
    options = {f.name: getattr(args, f.name) for f in option_fields(args)}
    record = {"code": code_version(), "seed": args.seed, "field_spec": args.field or "built-in", **(provenance or {})}
    payload = {"args": {**options, **({"tables": tables} if tables else {})}, **results,
               "provenance": {**results.get("provenance", {}), **record}}
    path = out / "results.json"
    atomic_write_json(path, payload)
    return path


def run_main(main: Callable[[], Any]) -> None:
    """Run an experiment's `main` on the command line: the one path of `python -m experiments.X`
    and of the console scripts. An expected error (`TestbedError`: a bad option, a bad file)
    prints `error: <message>` to stderr and exits 2 (ConfigError) or 1 (DataError and the
    rest), without a traceback, unless --debug was given; a bug keeps its traceback. Ctrl-C
    (or a SIGTERM that the run turned into one) prints one line and exits 130: what was written
    is kept and a rerun resumes. Returns None, so that a finished run exits 0."""
    global _debug
    _debug = False  # parse_args sets it from this run's --debug
    try:
        main()
    except KeyboardInterrupt:
        if _debug or "--debug" in sys.argv[1:]:
            raise
        print("stopped: interrupted; what was written is kept, and the same command resumes", file=sys.stderr)
        raise SystemExit(130) from None
    except TestbedError as e:
        if _debug or "--debug" in sys.argv[1:]:
            raise
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2 if isinstance(e, ConfigError) else 1) from None


def script(main: Callable[[], Any]) -> Callable[[], None]:
    """The console-script entry point ([project.scripts] in pyproject.toml) of an experiment's `main`:
    `run_main(main)`, which returns None, so that a finished run exits 0 (`main` returns its results to
    Python callers, which a console script would pass to sys.exit as an error)."""

    def entry() -> None:
        run_main(main)

    entry.__doc__ = f"Run {main.__module__} from the command line."
    return entry
