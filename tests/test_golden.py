"""The pipeline's numbers against the golden record, on this CPU and on emulated others.

`tests/golden/record.py` wrote `tests/golden/pipeline.json` from a quick staged
collection and a short lemniscate with all six conditions (see its docstring for
when to re-record, and for which numbers hold bit for bit on every CPU and which
within a stated tolerance). A refactor that moves any number beyond that fails here.
"""

import importlib.util
import json
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location("golden_record", Path(__file__).parent / "golden" / "record.py")
record = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(record)

# Another CPU with AVX2, emulated: the first OpenBLAS kernel this CPU can run (an SSE one,
# unlike what OpenBLAS picks on any current CPU), MKL without its AVX-512 paths, and NumPy
# without its AVX-512 loops (a feature this CPU lacks is ignored).
_KERNELS = record.machine.runnable_blas_kernels()
OTHER_CPU = {"OPENBLAS_CORETYPE": _KERNELS[0] if _KERNELS else "", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
             "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"}
PORTABLE = record.machine.runs_portable_torch()


def _check(workdir: Path, env: dict | None = None) -> None:
    record.run_pipeline(workdir, env)
    problems, same_torch = record.compare(record.summarize(workdir), json.loads(record.GOLDEN.read_text()))
    assert not problems, "\n".join(problems)
    if PORTABLE:  # the portable training kernels: the recorded bits, whatever CPU made the record
        assert same_torch, "a checkpoint differs from its recorded digest, though this CPU runs the portable kernels"


def test_pipeline_matches_golden_record(tmp_path):
    """Bit for bit on a CPU with AVX2 (the portable training kernels); else within tolerance."""
    _check(tmp_path)


@pytest.mark.skipif(not (_KERNELS and PORTABLE), reason="needs Linux on x86-64 with AVX2 (OPENBLAS_CORETYPE, "
                                                        "the portable kernels)")
def test_pipeline_matches_golden_record_with_another_cpus_kernels(tmp_path):
    """Bit for bit under another CPU's BLAS, MKL and NumPy kernels: nothing trained or flown depends on them."""
    _check(tmp_path, OTHER_CPU)


def test_the_record_says_what_it_was_made_on():
    made_on = json.loads(record.GOLDEN.read_text())["machine"]
    assert made_on["cpu"] and made_on["blas"] and made_on["versions"]["torch"] and made_on["versions"]["numpy"]


def test_comparison_catches_a_moved_number():
    """The tolerant tier still fails a change of meaning; the exact tier fails any bit."""
    want = json.loads(record.GOLDEN.read_text())
    got = json.loads(record.GOLDEN.read_text())
    assert record.compare(got, want) == ([], True)
    log = next(n for n in got["staged"]["logs"] if n.startswith(record.EXACT_LOGS))
    got["staged"]["logs"][log]["digest"] = "0" * 64
    assert any(log in p for p in record.compare(got, want)[0])
    got = json.loads(record.GOLDEN.read_text())
    ckpt = next(iter(got["staged"]["checkpoints"]))
    got["staged"]["checkpoints"][ckpt]["digest"] = "0" * 64  # another CPU's torch
    cond = next(c for c in got["lemniscate"] if "pos_err_3d_mean" in got["lemniscate"][c])
    got["lemniscate"][cond]["pos_err_3d_mean"][0] *= 1.0001  # within the tolerant tier
    problems, same_torch = record.compare(got, want)
    assert not same_torch and problems == []
    got["lemniscate"][cond]["pos_err_3d_mean"][0] *= 1.1  # a 10 % change is not round-off
    assert any("lemniscate" in p for p in record.compare(got, want)[0])
