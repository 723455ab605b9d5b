"""The docs site builds without a warning, and the README and the docs speak to a newcomer.

`mkdocs build --strict` turns every warning (a broken link, a page missing from the nav,
an API block that does not resolve) into a failure. It needs the `docs` extra, which the
`test` extra includes: `pip install -e ".[docs]"`.
"""

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# Words that belong to the project's own bookkeeping, not to a newcomer's page.
INTERNAL = {
    "an issue number": re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE),
    "the issue's": re.compile(r"\bthe issue'?s?\b", re.IGNORECASE),
    "this machine": re.compile(r"\bthis\s+(\S+\s+)?machine\b", re.IGNORECASE),
    "DESIGN.md": re.compile(r"DESIGN\.md"),
    "a DESIGN section": re.compile(r"\bDESIGN\b"),
    "the main job": re.compile(r"\bmain job\b", re.IGNORECASE),
    "golden records": re.compile(r"\bgolden records?\b", re.IGNORECASE),
}
# What a user reads besides the pages: the docstrings the API reference renders, the comments of the
# files they open, the CHANGELOG
CODE_INTERNAL = {k: INTERNAL[k] for k in ("DESIGN.md", "a DESIGN section", "the main job", "golden records")}
PACKAGES = ("downwash_core", "downwash_trajectories", "controllers", "sim", "downwash", "downwash_envs", "experiments",
            "examples")


def _pages():
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_docs_build_strict(tmp_path):
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None:
        pytest.skip("mkdocs and mkdocstrings are not installed: pip install -e \".[docs]\"")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=600,
                          env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    for page in ("index.html", "install/index.html", "results/index.html", "api/sim/index.html",
                 "assets/flight.png"):
        assert (tmp_path / "site" / page).is_file(), page
    assert "sim.simulator.Simulator" in (tmp_path / "site" / "api" / "sim" / "index.html").read_text()


def test_every_docs_page_is_in_the_nav():
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in (ROOT / "docs").rglob("*.md"):
        assert page.relative_to(ROOT / "docs").as_posix() in nav, f"{page} is not in mkdocs.yml's nav"


@pytest.mark.parametrize("page", _pages(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_internal_words(page):
    text = page.read_text()
    found = [f"{what}: {m.group(0)!r} (line {text.count(chr(10), 0, m.start()) + 1})"
             for what, rx in INTERNAL.items() for m in rx.finditer(text)]
    assert not found, f"{page.relative_to(ROOT)}: " + "; ".join(found)


def _code_files():
    return sorted([*(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")), ROOT / "pyproject.toml",
                   ROOT / ".ci" / "constraints.txt", ROOT / "CHANGELOG.md"])


def test_no_internal_words_in_code():
    """The API reference renders the docstrings: they cite no private document (``DESIGN section N``)
    and no bookkeeping word, and neither do the comments or the CHANGELOG."""
    found = []
    for path in _code_files():
        text = path.read_text()
        found += [f"{path.relative_to(ROOT)} line {text.count(chr(10), 0, m.start()) + 1}: {what} {m.group(0)!r}"
                  for what, rx in CODE_INTERNAL.items() for m in rx.finditer(text)]
    assert not found, "\n".join(found)


def test_readme_is_a_newcomers_page():
    """The picture, the two commands, pointers into the docs, licence and citation."""
    text = (ROOT / "README.md").read_text()
    assert "(docs/assets/flight.png)" in text and (ROOT / "docs" / "assets" / "flight.png").is_file()
    first = ("pip install -c .ci/constraints.txt torch --index-url https://download.pytorch.org/whl/cpu "
             "&& pip install -c .ci/constraints.txt -e . && python -m experiments.lemniscate")
    assert first in text  # the CPU build of torch, before anything pulls the CUDA one
    assert "bash .ci/run" in text and 'pip install -c .ci/constraints.txt -e ".[test]" && pytest' in text
    script = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if not line.lstrip().startswith("#")]
    assert script[-1] == 'pip install -c .ci/constraints.txt -e ".[test]" && pytest'
    # the tests run once, after the setup (a command in the header's comment once ran them twice)
    assert sum("pytest" in line for line in script) == 1 and script.index("set -euo pipefail") < len(script) - 1
    for link in re.findall(r"\]\(((?:docs/)?[\w./-]+\.(?:md|png|cff)|LICENSE)\)", text):
        assert (ROOT / link).is_file(), f"README links to {link}, which does not exist"
    assert "LICENSE" in text and "CITATION.cff" in text
    assert len(text.splitlines()) < 120, "the README is a short page: details go into docs/"


def test_python_version_claims_are_what_the_code_needs():
    """requires-python, the README and the install page say one version, and it is the one the code
    needs: the configuration reader imports tomllib (3.11+)."""
    import tomllib

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert meta["requires-python"] == ">=3.11"
    uses_tomllib = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py") if "import tomllib" in p.read_text()]
    assert uses_tomllib  # why 3.11: were it gone, 3.10 could be claimed again (mujoco 4 permitting)
    for page in (ROOT / "README.md", ROOT / "docs" / "install.md"):
        text = page.read_text()
        assert "3.11" in text and "3.10" not in text, page.name


def test_every_package_ships_its_type_hints():
    """PEP 561: a py.typed marker in every library package, and in the wheel's package data."""
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for pkg in PACKAGES[:6]:
        assert (ROOT / pkg / "py.typed").is_file() and "py.typed" in data.get(pkg, []), pkg


def test_package_metadata_matches_the_citation():
    """pyproject's licence (an SPDX expression), authors and version are the CITATION.cff's."""
    import tomllib

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    cff = (ROOT / "CITATION.cff").read_text()
    assert meta["license"] == "MIT" and "license: MIT" in cff and (ROOT / "LICENSE").read_text().startswith("MIT")
    assert f"version: {meta['version']}" in cff
    # the newest release in the CHANGELOG is this version, with the CITATION's date, and is written for users
    newest = re.search(r"^## (\S+) \((\d{4}-\d\d-\d\d)\)$", (ROOT / "CHANGELOG.md").read_text(), re.M)
    assert newest and newest.groups() == (meta["version"], re.search(r"date-released: (\S+)", cff).group(1))
    assert "## Unreleased" not in (ROOT / "CHANGELOG.md").read_text().split(newest.group(0))[0]
    assert "### Upgrading from" in (ROOT / "CHANGELOG.md").read_text().split(newest.group(0))[1].split("\n## ")[0]
    assert all(f"name: {a['name']}" in cff for a in meta["authors"])
    assert "Typing :: Typed" in meta["classifiers"] and meta["keywords"]
