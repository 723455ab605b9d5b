"""Cached kernels are stamped with the whole compiled stack's source (`downwash_core.jit`).

numba stamps a cached kernel with its own file only, so a kernel that compiles in a
function of another module (the fused tick calls the autopilot's mixer) would load stale
machine code after that module changed. These tests edit a callee in a copy of the
package and check that the caller's cache is not reused.
"""

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numba

import downwash_core.jit as jit

ROOT = Path(jit.__file__).resolve().parents[1]

CALLER = """
from downwash_core.jit import njit
from downwash_core._probe_callee import value


@njit
def caller():
    return value() + 1
"""


def _callee(result: int) -> str:
    return f"from downwash_core.jit import njit\n\n\n@njit\ndef value():\n    return {result}\n"


def _run(where: Path) -> tuple[int, int]:
    """(caller(), cache hits) in a fresh interpreter on the copy at `where`."""
    code = textwrap.dedent("""
        from downwash_core._probe_caller import caller
        print(caller(), sum(caller.stats.cache_hits.values()))
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=where, capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(where), "NUMBA_CACHE_DIR": ""})
    result, hits = out.stdout.split()
    return int(result), int(hits)


def test_editing_a_callee_recompiles_its_caller(tmp_path):
    shutil.copytree(ROOT / "downwash_core", tmp_path / "downwash_core",
                    ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "downwash_core" / "_probe_caller.py").write_text(CALLER)
    callee = tmp_path / "downwash_core" / "_probe_callee.py"
    callee.write_text(_callee(1))
    assert _run(tmp_path) == (2, 0)  # compiled, and cached
    assert _run(tmp_path) == (2, 1)  # nothing changed: loaded from the cache
    callee.write_text(_callee(41))  # the caller's own file is untouched
    assert _run(tmp_path) == (42, 0)  # numba's own stamp would load the stale 2


def test_the_stamp_covers_every_kernel_package_and_only_ours():
    assert jit.install_locator()  # (idempotent: installed at import)
    from numba.core import caching

    stamped = [c for c in caching.CacheImpl._locator_classes if getattr(c, "downwash_stamp", False)]
    assert len(stamped) == 3
    import sim.passes

    locator = sim.passes.actuate_kernel._cache._impl.locator
    assert getattr(type(locator), "downwash_stamp", False) and locator.get_source_stamp() == jit.source_stamp()
    for package in jit.KERNEL_PACKAGES:
        assert (ROOT / package / "__init__.py").exists(), package
    assert all(c.from_function(numba.njit(lambda: 0).py_func, numba.__file__) is None for c in stamped)
