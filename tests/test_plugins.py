"""Plugins through the entry-point group `downwash_testbed.plugins` (downwash_core/registry.py).

The loader's rules, in this process with a loader of its own (entry points made here): plugins load
once, on the first lookup; each registry takes its registrations on its own first lookup, after its
built-in entries, through its own register function; a plugin that fails warns naming it and
registers nothing; a registration that fails warns naming the plugin. Then an installed plugin, a
package and its `*.dist-info` on PYTHONPATH of a fresh interpreter: its field and vehicle kind are in
the registries and the listing command, and a flight under its field with its vehicle flies.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import warnings
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from downwash_core.errors import ConfigError
from downwash_core.registry import PLUGIN_GROUP, PluginLoader, PluginWarning, Registry

ROOT = Path(__file__).resolve().parents[1]


def _module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, code: str) -> None:
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(code))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, name, raising=False)


def _loader(*specs: str) -> PluginLoader:
    """A loader of its own over the entry points NAME=MODULE:FUNCTION."""
    eps = [EntryPoint(s.split("=")[0], s.split("=")[1], PLUGIN_GROUP) for s in specs]
    return PluginLoader(find=lambda: eps)


def _widgets(loader: PluginLoader, group: str = "fields") -> Registry:
    reg = Registry("widget", group=group, plugins=loader)
    reg.register("plain", lambda size=1: ("plain", size), "a built-in widget")
    return reg


PLUGIN = """
    calls = []

    def register(registries):
        calls.append(registries.plugin)
        registries.fields.register("extra", lambda size=2: ("extra", size), "a plugin's widget")
        registries.vehicles.register("kind_a", lambda: "a", "a plugin's thing of another registry")
"""


# ----------------------------------------------------------------------------- the loader's rules
def test_plugins_load_once_on_the_first_lookup_after_the_built_in_entries(tmp_path, monkeypatch):
    _module(tmp_path, monkeypatch, "plug_once", PLUGIN)
    loader = _loader("one=plug_once:register")
    reg = _widgets(loader)
    import plug_once

    assert plug_once.calls == [] and loader.plugins == []  # registering runs nothing
    assert list(reg) == ["plain", "extra"] and reg["extra"].plugin == "one" and reg["plain"].plugin is None
    assert reg.resolve("extra:size=5") == ("extra", 5)
    assert "extra" in reg and len(reg) == 2 and plug_once.calls == ["one"]  # once
    assert loader.plugins == [{"name": "one", "value": "plug_once:register", "status": "loaded", "registrations": 2}]
    later = Registry("thing", group="vehicles", plugins=loader)  # a registry made after the plugins ran
    assert list(later) == ["kind_a"] and later["kind_a"].plugin == "one" and plug_once.calls == ["one"]
    assert list(Registry("widget", plugins=loader)) == []  # a registry of no group takes nothing


def test_registrations_go_through_the_registry_s_own_register_function(tmp_path, monkeypatch):
    _module(tmp_path, monkeypatch, "plug_adder", """
        def register(registries):
            registries.fields.register("made", 7)
    """)
    reg = _widgets(_loader("p=plug_adder:register"))

    @reg.adder
    def register_widget(name, size):  # the owner's signature, not Registry.register's
        return reg.register(name, lambda: ("made", size), f"a widget of size {size}")

    assert reg.make("made") == ("made", 7) and reg["made"].description == "a widget of size 7"


@pytest.mark.parametrize("code, words", [
    ("raise ImportError('no such thing')", "ImportError: no such thing"),
    ("def register(registries):\n    registries.fields.register('half', lambda: 1, 'queued, then the bug')\n"
     "    raise RuntimeError('a bug')", "RuntimeError: a bug"),
    ("register = 42", "TypeError: plug_bad_{i}:register is a int, not a function of the registries"),
    ("import sys\ndef register(registries):\n    sys.exit(3)", "SystemExit: 3"),
])
def test_a_plugin_that_fails_warns_naming_it_and_registers_nothing(tmp_path, monkeypatch, code, words):
    i = abs(hash(code)) % 10**6
    _module(tmp_path, monkeypatch, f"plug_bad_{i}", code)
    _module(tmp_path, monkeypatch, "plug_good", PLUGIN)
    loader = _loader(f"bad=plug_bad_{i}:register", "good=plug_good:register")
    reg = _widgets(loader)
    with pytest.warns(PluginWarning) as record:
        names = list(reg)
    message = str(record[0].message)
    assert message.startswith(f"plugin 'bad' (plug_bad_{i}:register): failed: ") and words.format(i=i) in message
    assert message.endswith("; skipped") and len(record) == 1
    assert names == ["plain", "extra"]  # the other plugin's registration stands
    assert [(p["name"], p["status"].split(":")[0], p["registrations"]) for p in loader.plugins] == [
        ("bad", "failed", 0), ("good", "loaded", 2)]


def test_a_registration_that_fails_warns_naming_the_plugin_and_the_rest_stand(tmp_path, monkeypatch):
    _module(tmp_path, monkeypatch, "plug_dup", """
        def register(registries):
            registries.fields.register("plain", lambda: 0, "a taken name")
            registries.fields.register("Bad Name", lambda: 0, "a bad name")
            registries.fields.register("fresh", lambda: 0, "fine")
    """)
    reg = _widgets(_loader("dup=plug_dup:register"))
    with pytest.warns(PluginWarning) as record:
        assert list(reg) == ["plain", "fresh"]
    assert [str(w.message) for w in record] == [
        "plugin 'dup': could not register widget 'plain', skipped: widget name 'plain' is already registered",
        "plugin 'dup': could not register widget 'Bad Name', skipped: widget name 'Bad Name': use lowercase "
        "letters, digits, '-' and '_' (no '.' or ':')"]
    with pytest.raises(ConfigError, match=r"widget name 'fresh' is already registered \(by plugin 'dup'\)"):
        reg.register("fresh", lambda: 0)


def test_a_plugin_may_look_up_a_registry_while_it_registers(tmp_path, monkeypatch):
    _module(tmp_path, monkeypatch, "plug_nested", """
        REGISTRY = None

        def register(registries):
            base = REGISTRY["plain"]  # a lookup inside the loading: no second load, no deadlock
            registries.fields.register("derived", lambda: base.make(size=3), "built on plain")
    """)
    import plug_nested

    reg = _widgets(_loader("nested=plug_nested:register"))
    plug_nested.REGISTRY = reg
    assert reg.make("derived") == ("plain", 3)


def test_an_unreadable_entry_point_list_is_a_warning_not_a_crash():
    def broken():
        raise OSError("metadata unreadable")

    reg = _widgets(PluginLoader(find=broken))
    with pytest.warns(PluginWarning, match="cannot list them: metadata unreadable"):
        assert list(reg) == ["plain"]


# ----------------------------------------------------------------------------- an installed plugin
DEMO = '''
import dataclasses


def gust(strength: float = 4.0, swirl: float = 0.1):
    """so2 at 4 m/s^2 with a swirl."""
    from sim.field import DownwashField

    return DownwashField(strength=strength, swirl=swirl)


def soft_lqr(vehicle_kind=None):
    """The LQR with a softer position weight."""
    from controllers.lqr import FeedbackLinearisedLQR, LQRConfig

    return FeedbackLinearisedLQR(LQRConfig(q=(0.5, 0.5, 4.0, 0.01, 0.01, 0.1, 1.0)))


def wide_stack():
    """stack3's vehicles 0.8 m apart."""
    from sim.presets import make_preset

    return make_preset("stack", n=3, spacing=0.8)


def register(registries):
    from downwash_core.vehicles import PAPER_QUAD

    registries.controllers.register("demo_lqr", soft_lqr, "a plugin's controller: the LQR, softer")
    registries.presets.register("demo_stack", wide_stack, "a plugin's preset: three quads 0.8 m apart")

    registries.fields.register("demo-gust", gust, "a plugin's field: so2 at 4 m/s^2 with a swirl",
                               "SO(2) about the leader axis (chiral)", {"strength": float, "swirl": float})
    registries.vehicles.register(dataclasses.replace(
        PAPER_QUAD, name="demo_quad", mass=0.75, description="a plugin's vehicle: the paper quad at 0.75 kg",
        source="the demo plugin: the paper quad at 0.75 kg"))


def register_taken(registries):
    registries.fields.register("so2", gust, "a field whose name is taken", "none")
'''


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """A folder holding the plugin as pip installs one: the package and its dist-info."""
    site = tmp_path_factory.mktemp("site")
    (site / "downwash_plugin_demo").mkdir()
    (site / "downwash_plugin_demo" / "__init__.py").write_text(DEMO)
    info = site / "downwash_plugin_demo-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: downwash-plugin-demo\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{PLUGIN_GROUP}]\ndemo = downwash_plugin_demo:register\n"
                                           "taken = downwash_plugin_demo:register_taken\n"
                                           "missing = downwash_plugin_missing:register\n")
    return site


def _python(site: Path, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


FLY = """
import json
import numpy as np
from downwash_core.registry import PLUGINS
from downwash_core.status import Status
from downwash_core.vehicles import VEHICLES, get_vehicle
from experiments.common import load_field
from sim.fields import FIELDS
from sim.flight import fly
from sim.scene import build_scene
from downwash_trajectories import Hover, stack

field = load_field("demo-gust:strength=3")  # the experiments' --field path, checked as theirs are
leader = np.array([0.0, 0.0, 2.5])
ref = stack([Hover(leader, n_worlds=1), Hover(leader - [0.05, 0.0, 0.7], n_worlds=1)])
log = fly(build_scene(kinds=("paper_quad", "demo_quad")), ref, [0], 1.5, field=field)[0]
print(json.dumps({"fields": list(FIELDS), "vehicles": list(VEHICLES), "plugin": FIELDS["demo-gust"].plugin,
                  "strength": field.strength, "swirl": field.swirl, "mass": get_vehicle("demo_quad").mass,
                  "ok": bool(log.meta["status"] == Status.OK), "push": float(np.abs(log["field_mean"]).max()),
                  "finite": bool(np.isfinite(log["pos"]).all()), "plugins": PLUGINS.plugins}))
"""


def test_an_installed_plugin_s_field_and_vehicle_are_registered_and_fly(site):
    proc = _python(site, "-c", FLY)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["fields"][-1] == "demo-gust" and out["plugin"] == "demo" and out["fields"].count("so2") == 1
    assert out["vehicles"][-1] == "demo_quad" and out["mass"] == 0.75
    assert (out["strength"], out["swirl"]) == (3.0, 0.1)
    assert out["ok"] and out["finite"] and out["push"] > 0.1  # the follower flew in the plugin field's wake
    assert {p["name"]: p["status"].split(":")[0] for p in out["plugins"]} == {
        "demo": "loaded", "taken": "loaded", "missing": "failed"}
    # the broken ones are one warning each, naming them; the command ran on
    assert "PluginWarning: plugin 'missing' (downwash_plugin_missing:register): failed: ModuleNotFoundError" \
        in proc.stderr
    assert "plugin 'taken': could not register field 'so2', skipped: field name 'so2' is already registered" \
        in proc.stderr


def test_the_listing_command_lists_every_kind_with_the_plugin_s_entries(site, tmp_path):
    proc = _python(site, "-m", "experiments.registry", "--out", str(tmp_path / "all"))
    results = json.loads((tmp_path / "all" / "results.json").read_text())
    assert set(results["registry"]) == {"fields", "models", "vehicles", "presets", "sensors", "controllers",
                                        "aggregations"}
    assert all(results["registry"][kind] for kind in results["registry"])
    fields = {e["name"]: e for e in results["registry"]["fields"]}
    assert fields["demo-gust"]["plugin"] == "demo" and fields["so2"]["plugin"] is None
    assert fields["demo-gust"]["params"] == {"strength": {"type": "float", "default": 4.0},
                                             "swirl": {"type": "float", "default": 0.1}}
    assert fields["demo-gust"]["symmetry"] == "SO(2) about the leader axis (chiral)"
    vehicles = {e["name"]: e for e in results["registry"]["vehicles"]}
    assert vehicles["demo_quad"]["plugin"] == "demo" and "0.75 kg" in vehicles["demo_quad"]["description"]
    presets = {e["name"]: e for e in results["registry"]["presets"]}
    assert presets["stack"]["params"] == {"n": {"type": "int", "default": 3},
                                          "spacing": {"type": "float", "default": 0.6}}
    assert {p["name"] for p in results["plugins"]} == {"demo", "taken", "missing"}
    assert "demo-gust" in proc.stdout and "[plugin demo]" in proc.stdout and "demo_quad" in proc.stdout

    _python(site, "-m", "experiments.registry", "--kind", "fields", "--out", str(tmp_path / "fields"))
    one = json.loads((tmp_path / "fields" / "results.json").read_text())
    assert list(one["registry"]) == ["fields"] and one["registry"]["fields"][-1]["name"] == "demo-gust"


def test_the_command_lines_take_a_plugin_s_controller_field_and_preset(site, tmp_path):
    """Names a plugin registered pass the checks that run while the command line is parsed, and fly."""
    _python(site, "-m", "experiments.lemniscate", "--quick", "--controller", "demo_lqr", "--field", "demo-gust",
            "--conditions", "baseline", "--out", str(tmp_path / "lem"))
    results = json.loads((tmp_path / "lem" / "results.json").read_text())
    assert results["provenance"]["controller"]["q"][0] == 0.5  # the plugin's controller flew
    assert results["args"]["field"] == "demo-gust"
    code = ("from experiments.common import parse_args; from experiments.swarm import SwarmArgs; "
            "a = parse_args(SwarmArgs, 'swarm', ['--presets', 'demo_stack,stack3', '--quick']); print(a.presets)")
    assert _python(site, "-c", code).stdout.strip().splitlines()[-1] == "demo_stack,stack3"
    bad = subprocess.run([sys.executable, "-m", "experiments.lemniscate", "--controller", "nope"], cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])},
                         capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "demo_lqr" in bad.stderr  # a bad name's message lists the plugin's too


def test_the_listing_refuses_an_unknown_kind_and_a_field(tmp_path):
    from experiments.registry import main

    with pytest.raises(SystemExit) as e:
        main(["--kind", "fields,nope", "--out", str(tmp_path / "a")])
    assert e.value.code == 2 and not (tmp_path / "a").exists()
    with warnings.catch_warnings(), pytest.raises(ConfigError, match="--field: the registry listing flies nothing"):
        main(["--field", "so2", "--out", str(tmp_path / "b")])
