"""Config files: what `--config FILE.toml` may hold, and the resolved `config.toml` each run writes.

A file holds the options, by their long names (with - or _); an option that takes several
values in one string (its help says "comma list", or ';'-separated) also takes a TOML array,
whose items are joined with that separator. Beside them, tables of the settings a researcher
tunes, each mapping onto the library's own settings:

    [lqr]       controllers.lqr.LQRConfig: the outer loop of the experiment's flights
    [sim]       sim.simulator.SimConfig, its plain numbers: the failure checks and the noise block
    [training]  downwash.train.TrainConfig: the training the experiment runs (the seed is --seed)
    [guard]     downwash.guard.GuardedPredictor's settings (GUARD_DEFAULTS): its guarded conditions
    [safety]    sim.safety.SafetyConfig: the safety layer, which the table (or --safety) turns on

An experiment applies the tables its options class names (`config_tables`); any other table,
an unknown key, a value of the wrong type or out of range stops the run before any work. The
keys and ranges here are static copies, so that a bad file answers without the heavy imports;
tests/test_config_files.py ties them to the classes. The tables' values reach the library
through the builders of `experiments.common` (`lqr_config`, `sim_config`, `training_config`,
`guard_config`), the one place each experiment makes those settings.

Every run writes `config.toml` beside its results.json in --out (atomically): every option's
final value (defaults and what --quick gave included) and every table the experiment applies,
resolved. `--config OUT/config.toml` runs the same run again; a flag given beside it wins.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from downwash_core.errors import ConfigError
from experiments.common import option_type, one_line, option_name, option_fields
from experiments.options import in_range, range_words

__all__ = ["TABLES", "RESERVED", "CONFIG_NAME", "CONFIG_BYTES_MAX", "Key", "list_separator", "read_file", "check_table",
           "check_tables", "refuse_table", "resolved_tables", "dumps", "unwritable", "write_config"]

CONFIG_NAME = "config.toml"  # the resolved config, beside results.json
CONFIG_BYTES_MAX = 1 << 20  # an options file is a few lines; reading a huge or endless one is refused


@dataclass(frozen=True)
class Key:
    """One key of a table: its type (float, int, bool; tuple: an array of `length` numbers), what it
    means, and its range (of the number, or of each number of the array)."""

    kind: type
    help: str
    bounds: dict[str, float] = field(default_factory=dict)
    length: int = 0
    infinite: bool = False  # +inf is allowed (no limit)


@dataclass(frozen=True)
class Table:
    """A table of the config file: the settings class it maps onto and its keys; `left_out`: the
    fields of that class a file cannot set, with why."""

    source: str
    keys: dict[str, Key]
    left_out: dict[str, str] = field(default_factory=dict)


_POSITIVE = {"gt": 0.0}
TABLES = {
    "lqr": Table("controllers.lqr.LQRConfig", {
        "q": Key(tuple, "diagonal of Q, the weights of x, y, z (m), vx, vy, vz (m/s), yaw (rad)", {"ge": 0.0}, 7),
        "r": Key(tuple, "diagonal of R, the weights of ax, ay, az (m/s^2), yaw rate (rad/s)", _POSITIVE, 4),
        "max_tilt_deg": Key(float, "tilt limit of the feedback linearisation, deg", {"gt": 0.0, "lt": 90.0}),
        "min_thrust_g": Key(float, "floor of the commanded vertical specific force, g", {"ge": 0.0, "lt": 1.0}),
    }),
    "sim": Table("sim.simulator.SimConfig", {
        "ground_clearance": Key(float, "a vehicle centre below this height has hit the ground, m", {"ge": 0.0}),
        "collision_radius_xy": Key(float, "paper quads closer than this laterally ... (m)", {"ge": 0.0}),
        "collision_radius_z": Key(float, "... and vertically (ellipsoid) have collided, m", {"ge": 0.0}),
        "max_distance": Key(float, "beyond this from the origin the flight has diverged, m", _POSITIVE),
        # each world holds a block of noise (block x vehicles x 9 floats): bounded so that memory stays small
        "noise_block": Key(int, "autopilot ticks of noise drawn per generator call", {"ge": 1, "le": 4096}),
    }, {"rates": "not a plain number", "quad": "not a plain number (the vehicle kinds: sim.vehicle_params)",
        "mocap": "not a plain number (the sensor)"}),
    "training": Table("downwash.train.TrainConfig", {
        "lr": Key(float, "peak Adam learning rate (default: the model kind's)", _POSITIVE),
        "lr_final": Key(float, "final learning rate as a fraction of lr", {"gt": 0.0, "le": 1.0}),
        "batch_size": Key(int, "samples per mini-batch", {"ge": 1}),
        "max_epochs": Key(int, "passes over the training part", {"ge": 1}),
        "min_steps": Key(int, "at least this many mini-batch steps", {"ge": 0}),
        "patience": Key(int, "epochs without a new best validation loss before stopping", {"ge": 1}),
        "min_delta": Key(float, "relative improvement of the validation loss that counts", {"ge": 0.0, "lt": 1.0}),
        "val_fraction": Key(float, "share of training flights held out for early stopping", {"gt": 0.0, "lt": 1.0}),
        "weight_decay": Key(float, "Adam L2 penalty", {"ge": 0.0}),
        "num_threads": Key(int, "torch intra-op threads while training", {"ge": 1}),
        "portable": Key(bool, "train with kernels that give the same bits on every x86-64 CPU"),
    }, {"seed": "the seed is the option seed (--seed)"}),
    "guard": Table("downwash.guard.GuardedPredictor", {
        "recovery": Key(float, "how fast the applied fraction may rise, 1/s", _POSITIVE),
        "bound": Key(float, "the hard bound of a guarded prediction, m/s^2", _POSITIVE),
        "monitor": Key(float, "time constant of the monitor's sums, s", _POSITIVE),
        "prior": Key(float, "the monitor's prior evidence that the model is right, (m/s^2)^2", _POSITIVE),
        "skeptic": Key(float, "evidence a model outside its support must first outweigh, (m/s^2)^2 (inf: the "
                              "support alone decides)", _POSITIVE, infinite=True),
        "fast_monitor": Key(float, "memory of the fast sums, s", _POSITIVE),
        "fast_prior": Key(float, "prior of the fast sums, (m/s^2)^2", _POSITIVE),
    }, {"predictor_hz": "the predictor's rate is the simulator's"}),
    "safety": Table("sim.safety.SafetyConfig", {
        "inflation": Key(float, "the factor on each pair's collision ellipsoid its barrier keeps out of",
                         {"ge": 1.0, "le": 100.0}),
        "max_margin": Key(float, "the most the barrier's surface lies beyond a pair's ellipsoid, vertically, m",
                          {"gt": 0.0, "le": 100.0}),
        "ground_clearance": Key(float, "the least height of a vehicle's centre, m", {"ge": 0.0, "le": 100.0}),
        "k0": Key(float, "the barrier's gain on h, 1/s^2", {"gt": 0.0, "le": 1e4}),
        "k1": Key(float, "the barrier's gain on h', 1/s (at least 2 sqrt(k0))", {"gt": 0.0, "le": 1e3}),
        "bandwidth": Key(float, "of the filter's own disturbance estimate, rad/s", {"gt": 0.0, "le": 1e3}),
        "thrust_fraction": Key(float, "of a vehicle's full thrust the filter may command", {"gt": 0.0, "le": 1.0}),
    }),
}
# tables a file may name that map onto nothing yet: refused with why
RESERVED: dict[str, str] = {}


def list_separator(f: dataclasses.Field) -> str | None:
    """The separator of an option that takes several values in one string, as its help states it
    (a comma list, or ';'-separated), else None: such an option also takes a TOML array."""
    help_text = f.metadata.get("help", "")
    if option_type(f) is not str:
        return None
    if "';'" in help_text:
        return ";"
    return "," if "comma list" in help_text else None


# ----------------------------------------------------------------------------- reading


def read_file(path: str | Path, cls: type) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """({field name: value}, {table: {key: value}}) from the TOML file `path`: each key an option of
    `cls` or a table it applies, each value of its type (a table's also within its range);
    ConfigError naming the file, the key and what is allowed otherwise."""
    raw = _load(path)
    fields = {f.name: f for f in option_fields(cls)}
    values: dict[str, Any] = {}
    tables: dict[str, dict[str, Any]] = {}
    for key, value in raw.items():
        name = key.replace("-", "_")
        if name in values or name in tables:
            raise ConfigError(f"--config {path}: key {key!r} given twice (with - and with _)")
        try:
            if name in fields and not (name in TABLES and isinstance(value, dict)):  # [safety] is the table
                values[name] = _option_value(key, value, fields[name])
            elif name in TABLES or name in RESERVED:
                tables[name] = _table_of(key, value, cls)
            else:
                taken = ", ".join(f"[{t}]" for t in getattr(cls, "config_tables", ()))
                raise ConfigError(f"unknown key {key!r}; allowed: {', '.join(n.replace('_', '-') for n in fields)}"
                                  + (f"; tables: {taken}" if taken else ""))
        except ConfigError as e:
            raise ConfigError(f"--config {path}: {e}") from None
    return values, tables


def _load(path: str | Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:
            data = fh.read(CONFIG_BYTES_MAX + 1)
    except FileNotFoundError:
        raise ConfigError(f"--config {path}: no such file") from None
    except OSError as e:
        raise ConfigError(f"--config {path}: cannot read it ({e.strerror or e})") from None
    if len(data) > CONFIG_BYTES_MAX:
        raise ConfigError(f"--config {path}: larger than {CONFIG_BYTES_MAX >> 20} MiB; expected a short TOML file")
    try:
        return tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise ConfigError(f"--config {path}: not a UTF-8 text file ({e.reason} at byte {e.start})") from None
    except (ValueError, RecursionError) as e:  # TOMLDecodeError; an integer of thousands of digits; deep nesting
        raise ConfigError(f"--config {path}: not valid TOML ({one_line(e)})") from None


_EXPECTED = {bool: "a boolean (true or false)", int: "an integer", float: "a number", str: "a string"}


def _option_value(key: str, value: Any, f: dataclasses.Field) -> Any:
    """An option's value from the file, of its type (an array joined for a list option)."""
    kind, sep = option_type(f), list_separator(f)
    expected = _EXPECTED[kind]
    if sep is not None:
        expected = f"a string or an array of strings and numbers (joined with {sep!r})"
        if isinstance(value, list) and all(_is_number(x) or isinstance(x, str) for x in value):
            value = sep.join(x if isinstance(x, str) else repr(x) for x in value)
    if not _of_kind(value, kind):
        raise ConfigError(f"{key} = {value!r}: expected {expected}, got a TOML {_toml_type(value)} "
                          f"({option_name(f.name)}: {f.metadata.get('help', '')})")
    try:
        return float(value) if kind is float else value
    except OverflowError:  # an integer beyond any float
        raise ConfigError(f"{key}: expected a finite number, got an integer of {len(str(abs(value)))} digits") from None


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _of_kind(value: Any, kind: type) -> bool:
    if kind is bool:
        return isinstance(value, bool)
    if kind is float:
        return _is_number(value)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, str)


def _toml_type(value: Any) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
            dict: "table"}.get(type(value), type(value).__name__)


def _table_of(key: str, value: Any, cls: type) -> dict[str, Any]:
    """A table of the file, checked: one `cls` applies, its keys and values."""
    name = key.replace("-", "_")
    if name in RESERVED:
        raise ConfigError(f"[{key}]: {RESERVED[name]}")
    if not isinstance(value, dict):
        raise ConfigError(f"{key} = {value!r}: expected a table [{name}] of {TABLES[name].source} settings, got a "
                          f"TOML {_toml_type(value)}")
    if name not in getattr(cls, "config_tables", ()):
        raise ConfigError(refuse_table(name, cls))
    return check_table(name, value)


def refuse_table(name: str, cls: type) -> str:
    """Why a table is refused for the experiment of options class `cls`: it does not apply it."""
    taken = ", ".join(f"[{t}]" for t in getattr(cls, "config_tables", ())) or "none"
    return (f"[{name}]: this experiment does not apply {TABLES[name].source} settings, so the table is refused "
            f"rather than ignored; the tables it applies: {taken}")


def check_table(name: str, values: dict[str, Any]) -> dict[str, Any]:
    """{key: value} of the table `name`, checked (each key known, each value of its type and within its
    range; an integer for a number is that float, an array a tuple); ConfigError naming the table, the
    key and what is allowed."""
    if name in RESERVED:
        raise ConfigError(f"[{name}]: {RESERVED[name]}")
    table = TABLES[name]
    out: dict[str, Any] = {}
    for key, value in values.items():
        k = key.replace("-", "_")
        if k not in table.keys:
            why = f" ({table.left_out[k]})" if k in table.left_out else ""
            raise ConfigError(f"[{name}] unknown key {key!r}{why}; allowed: {', '.join(table.keys)}")
        if k in out:
            raise ConfigError(f"[{name}] key {key!r} given twice (with - and with _)")
        out[k] = _table_value(name, key, value, table.keys[k])
    return out


def _table_value(name: str, key: str, value: Any, spec: Key) -> Any:
    source = f"{TABLES[name].source}.{key.replace('-', '_')}: {spec.help}"
    items = value if spec.kind is tuple else [value]
    if spec.kind is tuple:
        ok = isinstance(value, (list, tuple)) and len(value) == spec.length and all(map(_is_number, value))
        expected = f"an array of {spec.length} numbers"
    else:
        ok = _of_kind(value, spec.kind)
        expected = _EXPECTED[spec.kind]
    if not ok:
        got = f"{len(value)} items" if isinstance(value, list) and spec.kind is tuple else f"a TOML {_toml_type(value)}"
        raise ConfigError(f"[{name}] {key} = {value!r}: expected {expected}, got {got} ({source})")
    if spec.kind in (tuple, float, int):
        integer = spec.kind is int
        for x in items:
            try:
                number = x if integer else float(x)
            except OverflowError:  # an integer beyond any float
                number = math.inf
            if not (in_range(number, spec.bounds) or spec.infinite and number == math.inf):
                what = range_words(integer, spec.bounds) + (" (or inf)" if spec.infinite else "")
                each = "each " if spec.kind is tuple else ""
                raise ConfigError(f"[{name}] {key} = {value!r}: expected {each}{what}")
        if spec.kind is tuple:
            return tuple(float(x) for x in value)
        return value if integer else float(value)
    return value


def check_tables(tables: dict[str, Any], cls: type) -> dict[str, dict[str, Any]]:
    """The tables of options built in Python, checked as a file's are (each one `cls` applies)."""
    if not isinstance(tables, dict):
        raise ConfigError(f"tables: expected {{table: {{key: value}}}}, got {tables!r}")
    out = {}
    for name, values in tables.items():
        if name not in TABLES and name not in RESERVED:
            raise ConfigError(f"tables: unknown table {name!r}; allowed: {', '.join(TABLES)}")
        out[name] = _table_of(name, values, cls)
    return out


# ----------------------------------------------------------------------------- writing


def resolved_tables(args: Any) -> dict[str, dict[str, Any]]:
    """Every table the experiment of `args` applies, with every key's value in force (the defaults
    and --quick's included): what its run used. A key whose default is "unset" (None: the training's
    lr and num_threads) is left out, which means the same."""
    from experiments import components

    out = {}
    for name in getattr(type(args), "config_tables", ()):
        if name == "safety":  # (written only where the layer flies: --safety or a [safety] table)
            safety = components.safety_config(args)
            if safety is None:
                continue
            settings = dataclasses.asdict(safety)
        elif name == "lqr":
            settings = dataclasses.asdict(components.lqr_config(args))
        elif name == "sim":
            settings = dataclasses.asdict(components.sim_config(args))
        elif name == "training":
            settings = dataclasses.asdict(components.training_config(args))
        else:
            settings = components.guard_config(args)
        keys = TABLES[name].keys
        out[name] = {k: _plain(v) for k, v in settings.items() if k in keys and v is not None}
    return out


def _plain(value: Any) -> Any:
    """A setting as TOML writes it: arrays as lists, NumPy numbers as Python's."""
    if isinstance(value, (list, tuple)):
        return [_plain(x) for x in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        return value.item()
    return value


def dumps(values: dict[str, Any], tables: dict[str, dict[str, Any]] | None = None, header: str = "") -> str:
    """TOML text of `values` (str, int, float, bool and lists of them) and `tables` ({name: values}),
    read back by tomllib to the same values; ValueError naming the key of a value TOML cannot hold."""
    lines = [f"# {line}" for line in header.splitlines()]
    lines += [f"{_key(k)} = {_value(k, v)}" for k, v in values.items()]
    for name, table in (tables or {}).items():
        lines += ["", f"[{_key(name)}]"] + [f"{_key(k)} = {_value(k, v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def _key(k: str) -> str:
    bare = k and all(c.isascii() and (c.isalnum() or c in "-_") for c in k)
    return k if bare else _string(k, k)


def _value(key: str, v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else "inf" if v > 0 else "-inf")
    if isinstance(v, str):
        return _string(key, v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(key, x) for x in v) + "]"
    raise ValueError(f"{option_name(key)}: config.toml cannot hold a {type(v).__name__} ({v!r})")


_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _string(key: str, s: str) -> str:
    """A TOML basic string (every control character escaped)."""
    out = []
    for c in s:
        if c in _ESCAPES:
            out.append(_ESCAPES[c])
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04x}")
        elif 0xD800 <= ord(c) <= 0xDFFF:  # a byte that was no UTF-8 (a path from the command line): no TOML string
            raise ValueError(f"{option_name(key)}: {s!r} holds bytes that are no UTF-8 text; config.toml (UTF-8 TOML) "
                             "cannot hold it")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def unwritable(values: dict[str, Any]) -> str | None:
    """What keeps config.toml from holding the options `values`, else None (checked while parsing,
    so that a run that cannot write its config stops before any work)."""
    try:
        dumps(values)
    except ValueError as e:
        return str(e)
    return None


HEADER = ("The resolved config of the run whose results.json lies beside it: every option's value and the\n"
          "tables the experiment applies. Run it again with --config <this file> (a flag given beside it wins).")


def write_config(path: str | Path, args: Any, tables: dict[str, dict[str, Any]]) -> Path:
    """Atomically write the resolved config of the run `args` (its options, and `tables`) to `path`."""
    from downwash_core.io import atomic_write_bytes

    # (an option and a table of one name, --safety and [safety]: the table alone says both, as TOML has one key)
    values = {f.name: getattr(args, f.name) for f in option_fields(args) if f.name not in tables}
    atomic_write_bytes(path, dumps(values, tables, HEADER).encode())
    return Path(path)
