"""One registry type for the named components, one grammar for their specs, and plugins.

A `Registry` maps names to entries (`Entry`: a factory, a one-line description, typed parameters
and their defaults): the fields, model kinds, vehicle kinds, presets, sensors and controllers are
each one. It reads as a read-only mapping; `R[name]` is the entry, or in a registry of objects
(vehicle kinds, model classes) the object. The one spec grammar (`Registry.parse`; `format_spec`)::

    NAME                          the entry with its defaults
    NAME:KEY=VALUE[,KEY=VALUE]    typed by the entry: int, float (finite), bool (true/1/yes/on or
                                  false/0/no/off), str (no ','), or a tuple of one of these whose
                                  items go on after commas (mean=2,0,0; hidden=64,64)

A bad name, key or value is one ConfigError naming the spec, what is wrong and what is allowed.

Plugins: each entry point of the group `downwash_testbed.plugins` names a function
`register(registries)`, whose `registries.fields` (`.models`, `.vehicles`, `.presets`, `.sensors`,
`.controllers`) `.register(...)` takes the arguments of that registry's own register function
(`register_field`, `downwash.registry.register`, `register_vehicle`, `register_preset`,
`register_sensor`; else `Registry.register`). They load once, on the first lookup or listing of a
registry that takes plugins; each registry applies its share on its own first lookup, after its
built-in entries. A plugin that fails to load, or a registration that fails, is a `PluginWarning`
naming the plugin, and is skipped: every command still runs.
"""

from __future__ import annotations

import collections.abc
import contextlib
import dataclasses
import inspect
import math
import re
import threading
import types
import typing
import warnings
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from types import MappingProxyType
from typing import Any, Callable, Iterable, Iterator, Mapping

from downwash_core.errors import ConfigError

__all__ = ["Registry", "Entry", "UnknownNameError", "PluginWarning", "PluginLoader", "PluginRegistries", "PLUGINS",
           "PLUGIN_GROUP", "PLUGIN_KINDS", "NAME_PATTERN", "convert_value", "format_spec", "type_name", "param_type",
           "infer_params"]

PLUGIN_GROUP = "downwash_testbed.plugins"
PLUGIN_KINDS = ("fields", "models", "vehicles", "presets", "sensors", "controllers")  # a plugin's registries
NAME_PATTERN = r"[a-z][a-z0-9_-]*"  # no '.' or ':', so never a module path nor a spec's separator
TRUE, FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")
SCALARS = (bool, int, float, str)
_PLURAL = {bool: "bools", int: "integers", float: "numbers", str: "strings"}
_NO_DEFAULT = object()
_ENTRY_FIELDS = ("name", "factory", "description", "params", "defaults", "preset", "kind", "obj", "plugin")


class UnknownNameError(ConfigError, KeyError):
    """An unknown name: a ConfigError that `except KeyError` (a mapping's lookup) also catches."""

    __str__ = ConfigError.__str__  # the message as it is (KeyError's would quote it)


class PluginWarning(UserWarning):
    """A plugin failed to load, or one of its registrations failed: it is skipped."""


# ----------------------------------------------------------------------------- types and values
def _tuple_items(kind: Any) -> tuple[type, int | None] | None:
    """(item type, length or None for any) of a tuple type, None for a scalar type."""
    if typing.get_origin(kind) is not tuple:
        return None
    args = typing.get_args(kind)
    return (args[0], None) if len(args) == 2 and args[1] is Ellipsis else (args[0], len(args))


def type_name(kind: Any) -> str:
    """'float', 'tuple[int, ...]': a parameter type in a listing."""
    items = _tuple_items(kind)
    return kind.__name__ if items is None else f"tuple[{items[0].__name__}, ...]" if items[1] is None else \
        f"tuple[{', '.join([items[0].__name__] * items[1])}]"


def _check_type(kind: Any) -> bool:
    items = _tuple_items(kind)
    return kind in SCALARS if items is None else \
        items[0] in SCALARS and all(a is items[0] for a in typing.get_args(kind) if a is not Ellipsis)


def param_type(annotation: Any, default: Any = _NO_DEFAULT) -> Any:
    """The grammar's type for an annotation (`X | None` as X, a sequence of X as tuple[X, ...]) or,
    without one, for the default's type; None where the grammar has none."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):  # X | None, X | np.ndarray: X where one arm is the grammar's
        arms = {param_type(a) for a in args if a is not type(None)} - {None}
        return arms.pop() if len(arms) == 1 else None
    if annotation in SCALARS or (origin is tuple and args and args[-1] is not Ellipsis):  # a fixed length
        return annotation if _check_type(annotation) else None
    if origin in (tuple, list, collections.abc.Sequence) and args and args[0] in SCALARS:
        return tuple[args[0], ...]
    if not (isinstance(annotation, str) or annotation in (inspect.Parameter.empty, None, Any)):
        return None  # a type of its own
    if type(default) in SCALARS:
        return type(default)
    same = isinstance(default, (tuple, list)) and default and {type(x) for x in default} == {type(default[0])}
    return tuple[type(default[0]), ...] if same and type(default[0]) in SCALARS else None


def infer_params(factory: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """({name: type}, {name: default}): what a spec can set of a dataclass's init fields or a function's
    (a class's constructor's) keyword parameters, typed by `param_type`, and the defaults of them all."""
    try:
        hints = typing.get_type_hints(factory.__init__ if isinstance(factory, type) and not
                                      dataclasses.is_dataclass(factory) else factory)
    except Exception:  # an annotation that does not resolve here: the defaults tell
        hints = {}
    if isinstance(factory, type) and dataclasses.is_dataclass(factory):
        found = [(f.name, f.type, f.default if f.default is not dataclasses.MISSING else f.default_factory()
                  if f.default_factory is not dataclasses.MISSING else _NO_DEFAULT)
                 for f in dataclasses.fields(factory) if f.init]
    else:
        try:
            parameters = inspect.signature(factory).parameters.values()
        except (TypeError, ValueError):  # a builtin without a signature
            parameters = []
        found = [(p.name, p.annotation, _NO_DEFAULT if p.default is p.empty else p.default)
                 for p in parameters if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    params, defaults = {}, {}
    for name, annotation, default in found:
        kind = param_type(hints.get(name, annotation), default)
        if kind is not None and not name.startswith("_"):
            params[name] = kind
        if default is not _NO_DEFAULT:
            defaults[name] = default
    return params, defaults


def _scalar(text: str, kind: type) -> Any:
    """`text` as a `kind`; ValueError saying what was expected."""
    if kind is str:
        return text
    if kind is bool:
        if text.lower() not in TRUE + FALSE:
            raise ValueError(f"expected a bool ({'/'.join(TRUE)} or {'/'.join(FALSE)})")
        return text.lower() in TRUE
    try:
        number = int(text) if kind is int else float(text)
    except ValueError:
        raise ValueError("expected an integer" if kind is int else "expected a number") from None
    if not math.isfinite(number):
        raise ValueError("must be finite")
    return number


def convert_value(text: str, kind: Any) -> Any:
    """A spec's value text as a value of the parameter type `kind`; ConfigError saying what is expected."""
    items = _tuple_items(kind)
    try:
        if items is None:
            return _scalar(text.strip(), kind)
        values = []
        for part in [p.strip() for p in text.split(",")] if text.strip() else []:
            try:
                values.append(_scalar(part, items[0]))
            except ValueError as e:
                raise ValueError(f"expected a comma list of {_PLURAL[items[0]]}; {part!r}: {e}") from None
        if items[1] is not None and len(values) != items[1]:
            raise ValueError(f"expected {items[1]} {_PLURAL[items[0]]}, comma-separated, got {len(values)}")
        return tuple(values)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _format_value(key: str, value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return ",".join(_format_value(key, v) for v in value)
    text = ("true" if value else "false") if isinstance(value, bool) else repr(value) if isinstance(value, float) \
        else str(value) if isinstance(value, int) else value if isinstance(value, str) else None
    if text is None or text != text.strip() or "," in text or "=" in text or text in ("nan", "inf", "-inf"):
        raise ConfigError(f"format_spec: {key}={value!r}: a spec value is a bool, a finite number, a string "
                          "without ',', '=' or surrounding spaces, or a tuple of these")
    return text


def format_spec(name: str, params: Mapping[str, Any] | None = None) -> str:
    """'stack:n=6,spacing=0.5' from ('stack', {'n': 6, 'spacing': 0.5}): what `Registry.parse` reads back."""
    items = [f"{key}={_format_value(key, value)}" for key, value in (params or {}).items()]
    return f"{name}:{','.join(items)}" if items else name


# ----------------------------------------------------------------------------- entries
@dataclass(frozen=True)
class Entry:
    """One registered component: name; factory(**params) -> the component; description (one line);
    params {parameter: type} a spec may set; defaults: the factory's own values, where known; preset:
    values fixed unless a spec overrides them; kind: the registry's noun; obj: the object, in a
    registry of objects; plugin: the plugin that registered it, if one did."""

    name: str
    factory: Callable[..., Any]
    description: str
    params: Mapping[str, Any]
    defaults: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    preset: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    kind: str = "entry"
    obj: Any = field(default=None, repr=False)
    plugin: str | None = None

    def allowed(self) -> str:
        return ", ".join(self.params) or "no parameters"

    def make(self, **params: Any) -> Any:
        """The component with `params` (already typed) over the preset; ConfigError for unknown ones."""
        unknown = sorted(set(params) - set(self.params))
        if unknown:
            raise ConfigError(f"{self.kind} {self.name!r} has no parameter(s) {unknown}; allowed: {self.allowed()}")
        return self.factory(**{**self.preset, **params})

    def parse_params(self, text: str, spec: str | None = None, label: str | None = None) -> dict[str, Any]:
        """{key: typed value} of the KEY=VALUE,... part of a spec (`spec`, for messages); ConfigError."""
        label, spec = label or self.kind, self.name + (f":{text}" if text else "") if spec is None else spec
        where = f"{label}: {spec!r}: {self.kind} {self.name!r}"
        raw: dict[str, str] = {}
        last: str | None = None
        for item in filter(None, (x.strip() for x in text.split(","))):
            key, eq, value = item.partition("=")
            if not eq:
                if last is not None and _tuple_items(self.params[last]) is not None:  # the tuple goes on
                    raw[last] = f"{raw[last]},{item}"
                    continue
                raise ConfigError(f"{where}: parameters are KEY=VALUE, got {item!r}; allowed: {self.allowed()}")
            key = key.strip()
            if key not in self.params:
                raise ConfigError(f"{where} has no parameter {key!r}; allowed: {self.allowed()}")
            if key in raw:
                raise ConfigError(f"{label}: {spec!r}: parameter {key!r} given twice")
            raw[key], last = value.strip(), key
        out = {}
        for key, value in raw.items():
            try:
                out[key] = convert_value(value, self.params[key])
            except ConfigError as e:
                raise ConfigError(f"{where} parameter {key}={value!r}: {e}") from None
        return out

    def describe(self) -> dict[str, Any]:
        """For a listing (JSON): each parameter's type and default, and a subclass's fields (a field's symmetry)."""
        params = {k: {"type": type_name(t), "default": self.preset.get(k, self.defaults.get(k))}
                  for k, t in self.params.items()}
        extra = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in _ENTRY_FIELDS}
        return {"name": self.name, "description": self.description, **extra, "params": params,
                **({"preset": dict(self.preset)} if self.preset else {}), "plugin": self.plugin}


# ----------------------------------------------------------------------------- plugins
class PluginRegistries(types.SimpleNamespace):
    """What a plugin's function receives: `.plugin` (its entry point's name) and, as `.fields`, `.models`,
    `.vehicles`, `.presets`, `.sensors` and `.controllers`, a handle whose `register(...)` queues a
    registration (the arguments of that registry's own register function), applied if the function returns."""

    def __init__(self, plugin: str, queue: list):
        def handle(kind: str) -> types.SimpleNamespace:
            return types.SimpleNamespace(register=lambda *args, **kwargs: queue.append((kind, args, kwargs)))

        super().__init__(plugin=plugin, **{kind: handle(kind) for kind in PLUGIN_KINDS})


class PluginLoader:
    """Runs the plugins of an entry-point group once (`load`) and holds their registrations until each
    registry takes its own (`take`). find(): the entry points (default: the installed ones).
    plugins: what each did ({name, value, status, registrations}); current: the plugin acting now."""

    def __init__(self, group: str = PLUGIN_GROUP, find: Callable[[], Iterable[Any]] | None = None):
        self.group, self.plugins, self.current = group, [], None
        self._find = find if find is not None else (lambda: entry_points(group=group))
        self._lock = threading.RLock()
        self._state = "new"  # new -> loading -> done
        self._pending: dict[str, list[tuple[str, tuple, dict]]] = {}

    def settled(self, kind: str) -> bool:
        """Whether the plugins have run and left nothing for the registry `kind`."""
        return self._state == "done" and not self._pending.get(kind)

    def load(self) -> None:
        """Run every plugin's function once (a later or nested call returns at once)."""
        with self._lock:
            if self._state != "new":
                return
            self._state = "loading"
            try:
                found = sorted(self._find(), key=lambda ep: ep.name)
            except Exception as e:  # unreadable metadata: no plugins, said once
                warnings.warn(PluginWarning(f"plugins of {self.group!r}: cannot list them: {e}"), stacklevel=3)
                found = []
            try:
                for ep in found:
                    self._load_one(ep)
            finally:
                self._state = "done"

    def _load_one(self, ep: Any) -> None:
        queue: list = []
        value = getattr(ep, "value", "?")
        try:
            with self.acting_for(ep.name):
                function = ep.load()
                if not callable(function):
                    raise TypeError(f"{value} is a {type(function).__name__}, not a function of the registries")
                function(PluginRegistries(ep.name, queue))
        except (Exception, SystemExit) as e:  # a broken plugin must not stop every command
            status = f"failed: {type(e).__name__}: {e}"
            warnings.warn(PluginWarning(f"plugin {ep.name!r} ({value}): {status}; skipped"), stacklevel=4)
            queue = []
        else:
            status = "loaded"
            for kind, args, kwargs in queue:
                self._pending.setdefault(kind, []).append((ep.name, args, kwargs))
        self.plugins.append({"name": ep.name, "value": value, "status": status, "registrations": len(queue)})

    def take(self, kind: str) -> list[tuple[str, tuple, dict]]:
        """The registrations queued for the registry `kind`, in plugin order (each handed out once)."""
        with self._lock:
            return self._pending.pop(kind, [])

    @contextlib.contextmanager
    def acting_for(self, plugin: str) -> Iterator[None]:
        previous, self.current = self.current, plugin
        try:
            yield
        finally:
            self.current = previous


PLUGINS = PluginLoader()  # the installed plugins (entry-point group `downwash_testbed.plugins`)


# ----------------------------------------------------------------------------- the registry
class Registry(Mapping[str, Any]):
    """Named components of one kind (see the module docstring). kind: the noun of messages ("field");
    label: the prefix of lookup errors (default kind); group: the `PLUGIN_KINDS` name whose plugin
    registrations it takes (None: none, and no plugin loading); objects: `R[name]` is the entry's
    object; default: the name an empty spec means; hint: added to unknown-name errors; name_pattern,
    name_rule: the names allowed, in words; reserved: {name: what it is}; entry_type: an `Entry` subclass."""

    def __init__(self, kind: str, *, label: str | None = None, group: str | None = None, objects: bool = False,
                 default: str | None = None, hint: str = "", name_pattern: str = NAME_PATTERN,
                 name_rule: str = "lowercase letters, digits, '-' and '_' (no '.' or ':')",
                 reserved: Mapping[str, str] | None = None, entry_type: type[Entry] = Entry, description: str = "",
                 plugins: PluginLoader | None = None):
        if group is not None and group not in PLUGIN_KINDS:
            raise ConfigError(f"Registry group: expected one of {', '.join(PLUGIN_KINDS)} or None, got {group!r}")
        self.kind, self.label, self.group, self.objects = kind, label or kind, group, objects
        self.default, self.hint, self.name_rule, self.description = default, hint, name_rule, description
        self._pattern, self._reserved, self._entry_type = re.compile(name_pattern), dict(reserved or {}), entry_type
        self._plugins = plugins if plugins is not None else PLUGINS
        self._entries: dict[str, Entry] = {}
        self._adder: Callable[..., Any] | None = None

    def register(self, name: str, factory: Callable[..., Any] | None = None, description: str = "", *,
                 params: Mapping[str, Any] | None = None, defaults: Mapping[str, Any] | None = None,
                 preset: Mapping[str, Any] | None = None, obj: Any = None, **extra: Any) -> Entry:
        """Add an entry; ConfigError for a bad or taken name, a factory not callable, a description of more
        than a line, a parameter type outside the grammar, a preset of no parameter. params, defaults: the
        factory's unless given (`infer_params`); obj: a registry of objects' object (default: the factory;
        without a factory, one that returns obj); extra: the entry type's fields (a field's symmetry)."""
        if not isinstance(name, str) or not self._pattern.fullmatch(name):
            raise ConfigError(f"{self.kind} name {name!r}: use {self.name_rule}")
        if name in self._reserved:
            raise ConfigError(f"{self.kind} name {name!r} is {self._reserved[name]}")
        if name in self._entries:
            by = self._entries[name].plugin
            raise ConfigError(f"{self.kind} name {name!r} is already registered" + f" (by plugin {by!r})" * bool(by))
        obj = factory if self.objects and obj is None else obj
        factory = (lambda: obj) if factory is None and obj is not None else factory  # returns the object
        if not callable(factory):
            raise ConfigError(f"{self.kind} {name!r}: factory must be callable, got {type(factory).__name__}")
        if not isinstance(description, str) or "\n" in description.strip():
            raise ConfigError(f"{self.kind} {name!r}: description: expected one line, got {description!r}")
        found, found_defaults = infer_params(factory) if params is None or defaults is None else ({}, {})
        params = dict(found if params is None else params)
        for key, kind in params.items():
            if not (isinstance(key, str) and key.isidentifier()) or not _check_type(kind):
                raise ConfigError(f"{self.kind} {name!r}: parameter {key!r}: {kind!r} is not a type of the grammar "
                                  "(int, float, bool, str, or tuple[X, ...] of one of these)")
        defaults = {k: v for k, v in found_defaults.items() if k in params} if defaults is None else dict(defaults)
        preset = dict(preset or {})
        if set(preset) - set(params):
            raise ConfigError(f"{self.kind} {name!r}: preset {sorted(set(preset) - set(params))} of no parameter; "
                              f"allowed: {', '.join(params) or 'no parameters'}")
        entry = self._entry_type(name=name, factory=factory, description=description.strip(),
                                 params=MappingProxyType(params), defaults=MappingProxyType(defaults),
                                 preset=MappingProxyType(preset), kind=self.kind, obj=obj,
                                 plugin=self._plugins.current if self.group else None, **extra)
        self._entries[name] = entry
        return entry

    def adder(self, function: Callable[..., Any]) -> Callable[..., Any]:
        """Decorator: `function`, the owner's register function, is what plugins' registrations call."""
        self._adder = function
        return function

    def add(self, *args: Any, **kwargs: Any) -> Any:
        """Register through the owner's register function (`adder`), else `register`."""
        return (self._adder or self.register)(*args, **kwargs)

    def pop(self, name: str, *default: Any) -> Any:
        """Remove an entry (a test's): the entry, else `default`, else the unknown-name error."""
        if name in self._entries or default:
            return self._entries.pop(name, *default)
        raise self.unknown(name)

    def peek(self, name: str) -> Entry | None:
        """The entry `name` or None, without loading plugins (for register functions)."""
        return self._entries.get(name) if isinstance(name, str) else None

    def _ready(self) -> None:
        """Load the plugins (once) and apply the registrations they queued for this registry."""
        loader = self._plugins
        if self.group is None or loader.settled(self.group):
            return
        loader.load()
        for plugin, args, kwargs in loader.take(self.group):
            try:
                with loader.acting_for(plugin):
                    self.add(*args, **kwargs)
            except Exception as e:  # one bad registration must not stop every command
                first = args[0] if args else kwargs.get("name", "")
                what = first if isinstance(first, str) else getattr(first, "name", None) or \
                    getattr(first, "kind", None) or type(first).__name__
                warnings.warn(PluginWarning(f"plugin {plugin!r}: could not register {self.kind} {what!r}, "
                                            f"skipped: {e}"), stacklevel=3)

    def unknown(self, name: Any, label: str | None = None, spec: str | None = None) -> UnknownNameError:
        """The error for an unknown name, naming the allowed ones (and the spec it came from)."""
        where = f" in {spec!r}" if spec is not None and spec != name else ""
        allowed = ", ".join(self._entries) or "none registered"
        return UnknownNameError(f"{label or self.label}: unknown {name!r}{where}; allowed: {allowed}"
                                + f"; {self.hint}" * bool(self.hint))

    def entry(self, name: str, label: str | None = None) -> Entry:
        """The entry `name`; ConfigError (and KeyError) naming the allowed names."""
        self._ready()
        entry = self._entries.get(name) if isinstance(name, str) else None
        if entry is None:
            raise self.unknown(name, label)
        return entry

    def __getitem__(self, name: str) -> Any:
        entry = self.entry(name)
        return entry.obj if self.objects else entry

    def get(self, name: str, default: Any = None) -> Any:
        return self[name] if name in self else default

    def __contains__(self, name: object) -> bool:
        self._ready()
        return isinstance(name, str) and name in self._entries

    def __iter__(self) -> Iterator[str]:
        self._ready()
        return iter(tuple(self._entries))

    def __len__(self) -> int:
        self._ready()
        return len(self._entries)

    def names(self) -> tuple[str, ...]:
        return tuple(self)

    def entries(self) -> tuple[Entry, ...]:
        self._ready()
        return tuple(self._entries.values())

    def make(self, name: str, /, **params: Any) -> Any:
        """The component `name` built with typed `params` over its preset; ConfigError naming what is allowed."""
        return self.entry(name).make(**params)

    def parse(self, spec: str, label: str | None = None) -> tuple[str, dict[str, Any]]:
        """(name, {typed params}) of a spec NAME[:KEY=VALUE,...] ("" is the default, if any); ConfigError."""
        label = label or self.label
        if not isinstance(spec, str):
            article = "an" if self.kind[:1] in "aeiou" else "a"
            raise ConfigError(f"{label}: expected {article} {self.kind} spec NAME[:KEY=VALUE,...], got "
                              f"{type(spec).__name__}")
        text = spec.strip() or (self.default or "")
        head, _, tail = text.partition(":")
        if head not in self:
            raise self.unknown(head, label, text)
        return head, self._entries[head].parse_params(tail, text, label)

    def resolve(self, spec: str, label: str | None = None) -> Any:
        """The component a spec names, built; ConfigError naming the spec (a factory's own included)."""
        name, params = self.parse(spec, label)
        try:
            return self._entries[name].make(**params)
        except ConfigError as e:  # a value the factory refuses: say which spec
            raise ConfigError(f"{label or self.label}: {spec.strip() or self.default!r}: {e}") from e

    def listing(self) -> list[dict[str, Any]]:
        """Every entry's `Entry.describe()`, in registration order (plugins' last)."""
        return [e.describe() for e in self.entries()]
