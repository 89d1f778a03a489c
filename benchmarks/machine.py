"""What every benchmark records about the machine it ran on: the CPU model, its SIMD flags,
the numba target, the core count and the load while it ran (ratios are compared within one
run; the machine says how far its absolute times travel)."""

from __future__ import annotations

import os
import platform
import re
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; the platform's processor string elsewhere)."""
    try:
        found = re.search(r"^model name\s*:\s*(.*)$", Path("/proc/cpuinfo").read_text(), re.MULTILINE)
    except OSError:
        found = None
    return found.group(1).strip() if found else (platform.processor() or "unknown")


def machine() -> dict:
    """CPU model, cores, SIMD flags, numba's target CPU, Python, and the 1-minute load now."""
    info = {"cpu": cpu_model(), "cores": os.cpu_count(), "python": platform.python_version(),
            "load_average_1min": os.getloadavg()[0]}
    try:
        flags = re.search(r"^flags\s*:\s*(.*)$", Path("/proc/cpuinfo").read_text(), re.MULTILINE)
        info["simd"] = [f for f in ("avx2", "fma", "avx512f") if flags and f in flags.group(1).split()]
    except OSError:
        pass
    try:
        import llvmlite.binding as ll
        import numba

        info["numba_target_cpu"] = numba.config.CPU_NAME or ll.get_host_cpu_name()
    except ImportError:
        pass
    return info
