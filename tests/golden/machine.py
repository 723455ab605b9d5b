"""What a golden record was made on, and the BLAS kernels this CPU can run.

Beside each golden file the record keeps the CPU, its BLAS kernel and the versions
of the packages whose bits it depends on, so that a mismatch on another machine
says what differs.
"""

from __future__ import annotations

import platform
import sys
from importlib import metadata

PACKAGES = ("numpy", "scipy", "numba", "llvmlite", "mujoco", "torch", "control", "gymnasium")

# OpenBLAS kernels by the CPU flags they need (OPENBLAS_CORETYPE values); a kernel whose
# flags the CPU lacks would die of an illegal instruction, so it is not offered.
BLAS_KERNELS = {
    "Prescott": ("pni",),  # SSE3 ("pni" in /proc/cpuinfo)
    "Nehalem": ("sse4_2",),
    "Sandybridge": ("avx",),
    "Haswell": ("avx2", "fma"),
    "Zen": ("avx2", "fma"),
    "SkylakeX": ("avx512f", "avx512bw", "avx512vl", "avx512dq"),
}


def cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def runnable_blas_kernels() -> list[str]:
    """The OPENBLAS_CORETYPE values this CPU can run (empty off Linux x86-64)."""
    if platform.system() != "Linux" or platform.machine() not in ("x86_64", "AMD64"):
        return []
    flags = cpu_flags()
    return [name for name, need in BLAS_KERNELS.items() if all(f in flags for f in need)]


def runs_portable_torch() -> bool:
    """Whether this CPU runs torch's portable training kernels (`downwash_core.numerics.PORTABLE_TORCH`:
    AVX2 with FMA), and so trains the recorded bits."""
    return platform.machine() in ("x86_64", "AMD64") and {"avx2", "fma"} <= cpu_flags()


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    """The CPU, its widest vector extension, the BLAS kernels in use and the package versions."""
    try:
        from threadpoolctl import threadpool_info

        blas = sorted({f"{i['internal_api']} {i.get('architecture')}" for i in threadpool_info()
                       if i["user_api"] == "blas"})
    except ImportError:  # pragma: no cover - the test extra installs it
        blas = []
    flags = cpu_flags()
    widest = next((x for x in ("avx512f", "avx2", "avx", "sse4_2") if x in flags), "")
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {"cpu": _cpu_model(), "vector_extension": widest, "blas": blas,
            "python": sys.version.split()[0], "os": f"{platform.system()} {platform.machine()}",
            "versions": versions}
