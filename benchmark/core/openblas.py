"""numpy's OpenBLAS kernels, pinned so that a generated scene is the same on every x86-64 CPU.

The synthetic generator's pixels depend on the last bits of small matrix products (camera and object
transforms, ray-plane tests) that numpy hands to its bundled OpenBLAS. OpenBLAS picks its kernels per
CPU at load time, and kernels round differently: on a CPU with AVX-512 it runs its ``SkylakeX`` kernels,
elsewhere (x86-64 with AVX2) the ``Haswell`` ones, which made the committed scene versions
(``benchmark/synthetic/digests.json``). Where a face lies exactly on a cell boundary of a hard-edged
solid texture, those last bits decide the cell, so some texture pixels flip (by 35 of 255 levels on the
smoke preset). Measured on an AMD EPYC (Zen 4, AVX-512): 7 of the 9 committed digests differed; with
``OPENBLAS_CORETYPE=Haswell`` (or ``Zen``, which runs the same kernels) all 9 reproduced.

So bench4d runs numpy's OpenBLAS on the Haswell kernels wherever the CPU has them:

* :func:`pin_before_numpy` sets ``OPENBLAS_CORETYPE`` for this process and its children when numpy is
  not loaded yet (``import benchmark`` calls it, so the ``bench4d`` command is pinned from its start);
* where numpy was loaded first (a script or a test session that imported torch before bench4d),
  :func:`generation_needs_pinned_process` tells the generator to render in a child process that is.

Elsewhere (another CPU family, numpy on another BLAS) nothing is pinned, and the runner's digest check
says when a scene came out as another version. Only numpy's BLAS is concerned: torch has its own.
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform
import sys
from pathlib import Path
from typing import Optional

CORE_VARIABLE = "OPENBLAS_CORETYPE"
"""The environment variable OpenBLAS reads, once, when it loads."""
PINNED_CORE = "Haswell"
"""The kernels the committed scene versions were generated with (AVX2 + FMA)."""
REFERENCE_CORES = frozenset({"haswell", "zen"})
"""OpenBLAS core names (lower case) that run those kernels: OpenBLAS's Zen target uses Haswell's."""
REQUIRED_CPU_FLAGS = frozenset({"avx2", "fma"})
"""What a CPU needs to run the pinned kernels (forcing them elsewhere would fault)."""
CHILD_FLAG = "BENCH4D_PINNED_CHILD"
"""Set in a child started to generate on pinned kernels: it never starts another."""
_CORENAME_FUNCTIONS = ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename",
                       "openblas_get_corename64_", "openblas_get_corename")
"""Names of OpenBLAS's ``get_corename`` in the builds numpy ships (64-bit-index scipy-openblas first)."""
CPUINFO = Path("/proc/cpuinfo")
"""Where Linux describes the CPU (elsewhere absent: nothing is pinned)."""


def cpuinfo_value(key: str, cpuinfo: Path = CPUINFO) -> Optional[str]:
    """The value of the first ``key : value`` line of ``cpuinfo`` (the first CPU's), None where absent."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return None
    for line in text.splitlines():
        name, _, value = line.partition(":")
        if name.strip() == key:
            return value.strip()
    return None


def cpu_runs_pinned_core(cpuinfo: Path = CPUINFO) -> bool:
    """Whether this is an x86-64 CPU with AVX2 and FMA (read from ``cpuinfo``; False where unreadable)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    return REQUIRED_CPU_FLAGS <= set((cpuinfo_value("flags", cpuinfo) or "").split())


def pin_before_numpy() -> bool:
    """Set ``OPENBLAS_CORETYPE`` to :data:`PINNED_CORE` for this process and its children, if numpy is not
    loaded yet, the variable is unset and the CPU runs those kernels. Returns whether it set it."""
    if "numpy" in sys.modules or CORE_VARIABLE in os.environ or not cpu_runs_pinned_core():
        return False
    os.environ[CORE_VARIABLE] = PINNED_CORE
    return True


@functools.lru_cache(maxsize=1)
def openblas_core() -> Optional[str]:
    """The core (kernel set) numpy's bundled OpenBLAS runs in this process, lower case; None when numpy
    uses another BLAS or the name cannot be read. Read once: OpenBLAS chooses it when it loads, and every
    generated scene and every results file asks."""
    import numpy as np

    libs = Path(np.__file__).resolve().parent.parent / "numpy.libs"
    for path in sorted(libs.glob("*openblas*")) if libs.is_dir() else []:
        try:
            lib = ctypes.CDLL(str(path))  # already loaded by numpy: the same handle
        except OSError:
            continue
        for name in _CORENAME_FUNCTIONS:
            function = getattr(lib, name, None)
            if function is not None:
                function.restype = ctypes.c_char_p
                core = function()
                return core.decode(errors="replace").strip().lower() if core else None
    return None


def generation_needs_pinned_process() -> bool:
    """Whether a scene generated here would come from other kernels than the committed versions' while a
    child process could use theirs."""
    if os.environ.get(CHILD_FLAG) == "1":
        return False
    core = openblas_core()
    return core is not None and core not in REFERENCE_CORES and cpu_runs_pinned_core()


def pinned_environment() -> dict[str, str]:
    """This process's environment with the pinned kernels and the child flag."""
    return {**os.environ, CORE_VARIABLE: PINNED_CORE, CHILD_FLAG: "1"}
