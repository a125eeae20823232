"""What the benchmark peers do before and after importing numpy, so that numpy runs its best.

OpenBLAS picks its kernels from the CPU it detects, and Debian's OpenBLAS 0.3.21 does not know
recent Xeons (the dev VM's reads as "Prescott": SSE3 kernels, about 3x slower than its AVX-512
ones). :func:`pin_openblas_core` names the kernel family from the CPU's flags instead, unless
``OPENBLAS_CORETYPE`` is set already; it must run before numpy is imported, since OpenBLAS reads
the variable when it loads.
"""

from __future__ import annotations

import os
from pathlib import Path


def pin_openblas_core() -> str:
    """Sets ``OPENBLAS_CORETYPE`` from /proc/cpuinfo's flags when unset; returns its value
    (``""`` when left to OpenBLAS)."""
    if os.environ.get("OPENBLAS_CORETYPE"):
        return os.environ["OPENBLAS_CORETYPE"]
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return ""
    flags: set = set()
    for line in info.splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            break
    if {"avx512f", "avx512bw", "avx512vl", "avx512dq"} <= flags:
        core = "SkylakeX"
    elif {"avx2", "fma"} <= flags:
        core = "Haswell"
    else:
        return ""
    os.environ["OPENBLAS_CORETYPE"] = core
    return core


def blas_library() -> str:
    """The BLAS numpy is linked with, as mapped into this process (a path fragment such as
    ``openblas-pthread/libopenblasp-r0.3.21.so``), with the pinned OpenBLAS core if any."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return "unknown"
    core = os.environ.get("OPENBLAS_CORETYPE", "")
    for line in maps.splitlines():
        parts = line.split()
        path = parts[-1] if parts else ""
        name = path.rsplit("/", 1)[-1]
        if any(k in name for k in ("openblas", "mkl_rt", "blis", "libblas", "accelerate")):
            lib = path.split("/x86_64-linux-gnu/")[-1]
            return f"{lib}[{core}]" if core and "openblas" in name else lib
    return "unknown"
