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
}


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


def test_readme_is_a_newcomers_page():
    """The picture, the two commands, pointers into the docs, licence and citation."""
    text = (ROOT / "README.md").read_text()
    assert "(docs/assets/flight.png)" in text and (ROOT / "docs" / "assets" / "flight.png").is_file()
    assert "pip install -e . && python -m experiments.lemniscate" in text
    assert "bash .ci/run" in text and 'pip install -c .ci/constraints.txt -e ".[test]" && pytest' in text
    for link in re.findall(r"\]\(((?:docs/)?[\w./-]+\.(?:md|png|cff)|LICENSE)\)", text):
        assert (ROOT / link).is_file(), f"README links to {link}, which does not exist"
    assert "LICENSE" in text and "CITATION.cff" in text
    assert len(text.splitlines()) < 120, "the README is a short page: details go into docs/"
