"""The API reference documents every public module of the library packages, and names no other.

A module is public when no part of its dotted name starts with "_". The reference is the
``::: module.name`` directives of docs/api/*.md (rendered by mkdocstrings); `experiments`
is command lines, documented in docs/experiments.md, so it is not walked here. Whether the
pages build is tests/test_docs.py's `mkdocs build --strict`.
"""

import importlib
import pkgutil
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
API = ROOT / "docs" / "api"
PACKAGES = ("downwash_core", "downwash_trajectories", "controllers", "sim", "downwash", "downwash_envs")
DIRECTIVE = re.compile(r"^:::[ \t]+(\S+)[ \t]*$", re.MULTILINE)


def _public(name):
    return not any(part.startswith("_") for part in name.split("."))


def _raise(name):
    raise ImportError(f"cannot import {name} to walk it")


def public_modules():
    """Every public module of the packages, subpackages included (walk_packages imports only packages)."""
    found = set()
    for package in PACKAGES:
        found.add(package)
        module = importlib.import_module(package)
        found.update(info.name for info in pkgutil.walk_packages(module.__path__, package + ".", onerror=_raise)
                     if _public(info.name))
    return found


def directives():
    """(page, module) for every ``::: name`` directive of the API pages, in page order."""
    return [(page.name, name) for page in sorted(API.glob("*.md")) for name in DIRECTIVE.findall(page.read_text())]


def test_the_walk_finds_subpackages_and_skips_private_modules():
    modules = public_modules()
    assert {"sim.fields.momentum", "downwash.real_logs.tabular", "downwash_trajectories.primitives"} <= modules
    assert all(_public(name) for name in modules)
    assert len(modules) > 100


def test_every_public_module_is_documented():
    documented = {name for _, name in directives()}
    missing = sorted(public_modules() - documented)
    assert not missing, "public modules missing from docs/api/*.md (add a `::: name` directive): " + ", ".join(missing)


def test_every_directive_names_a_public_module():
    public = public_modules()
    unknown = [f"{page}: {name}" for page, name in directives() if name not in public]
    assert not unknown, "directives naming no public module: " + "; ".join(unknown)


def test_every_module_is_documented_once():
    seen = {}
    for page, name in directives():
        seen.setdefault(name, []).append(page)
    twice = {name: pages for name, pages in seen.items() if len(pages) > 1}
    assert not twice, f"modules documented more than once: {twice}"


def test_every_documented_module_has_a_one_line_summary_on_its_page():
    """Each page's groups open with a table: the module, linked to its section, and what it is for."""
    for page in sorted(API.glob("*.md")):
        text = page.read_text()
        rows = dict(re.findall(r"^\| \[`([\w.]+)`\]\[\1\] \| (.*\S) \|$", text, re.MULTILINE))
        for name in DIRECTIVE.findall(text):
            assert rows.get(name), f"{page.name}: no summary row for {name}"
