"""The docs' recipes as a user would write them (docs/extending.md): a controller and a field of one's own,
each with a compiled form, loaded from the page itself so that the benchmark times what the page says.

`docs_blocks(section)` gives a section's python blocks; `load_recipes()` writes the compiled PD controller and
the compiled Gaussian jet into a package `mypkg` (the name the page's imports use) in a temporary folder, as
modules of their own (numba caches by file), and imports them.
"""

from __future__ import annotations

import importlib
import re
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

__all__ = ["DOCS_PAGE", "docs_blocks", "load_recipes"]

DOCS_PAGE = Path(__file__).resolve().parents[2] / "docs" / "extending.md"


def docs_blocks(section: str, page: Path = DOCS_PAGE) -> list[str]:
    """The python code blocks of the page's `## section`, in order (indented ones dedented)."""
    if not page.is_file():
        raise FileNotFoundError(f"docs_blocks: the recipes' page {page} is missing (it ships with the repository, "
                                f"not with the installed package)")
    text = page.read_text()
    if f"## {section}\n" not in text:
        raise ValueError(f"docs_blocks: no section '## {section}' in {page}")
    body = text.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"^( *)```python\n(.*?)^\1```", body, flags=re.S | re.M)
    return [re.sub(rf"(?m)^{indent}", "", code) for indent, code in blocks]


def load_recipes(page: Path = DOCS_PAGE) -> SimpleNamespace:
    """The page's compiled recipes: `CompiledPD` (the controller) and `CompiledGaussianJet` (the field), imported
    from a package written to a temporary folder that stays on sys.path for the process (the classes' numba
    functions are compiled at their first fused flight)."""
    field_blocks, controller_blocks = docs_blocks("A new field", page), docs_blocks("A new controller", page)
    files = {"fields.py": field_blocks[1], "compiled_fields.py": field_blocks[3],
             "compiled_controllers.py": controller_blocks[3]}
    if not (files["fields.py"].startswith("# mypkg/fields.py")
            and files["compiled_fields.py"].startswith("# mypkg/compiled_fields.py")
            and "class CompiledPD" in files["compiled_controllers.py"]):
        raise ValueError(f"load_recipes: the recipes on {page} are not where this loader looks for them "
                         f"(the field's 2nd and 4th blocks, the controller's 4th)")
    root = Path(tempfile.mkdtemp(prefix="downwash_recipes_"))
    (root / "mypkg").mkdir()
    (root / "mypkg" / "__init__.py").write_text("")
    for name, code in files.items():
        (root / "mypkg" / name).write_text(code)
    for name in [m for m in sys.modules if m == "mypkg" or m.startswith("mypkg.")]:
        del sys.modules[name]  # a package of that name imported before is not the recipes'
    sys.path.insert(0, str(root))
    fields = importlib.import_module("mypkg.compiled_fields")
    controllers = importlib.import_module("mypkg.compiled_controllers")
    return SimpleNamespace(CompiledPD=controllers.CompiledPD, CompiledGaussianJet=fields.CompiledGaussianJet,
                           folder=root)
