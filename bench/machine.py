"""What a bench result says of the machine it ran on. The platform string alone named two hosts alike whose
kernels ran twice as fast on one (AVX-512) as on the other (AVX2), so the CPU and its widest vector unit go in too."""

from __future__ import annotations

import os
import platform
from pathlib import Path

VECTOR_UNITS = ("avx512f", "avx2", "avx", "sse4.2", "neon")  # widest first, as LLVM names them


def describe() -> dict:
    """Platform, CPU count, the CPU's name and LLVM's (the target numba compiles the kernels for), the widest
    vector unit LLVM may use there, and the Python version. What the machine is, not its load at the moment."""
    import llvmlite.binding as llvm

    features = llvm.get_host_cpu_features()
    return {"platform": platform.platform(), "cpus": os.cpu_count(), "cpu_model": _model_name(),
            "llvm_cpu": llvm.get_host_cpu_name(),
            "vector_unit": next((unit for unit in VECTOR_UNITS if features.get(unit, False)), "unknown"),
            "python": platform.python_version()}


def summary(machine: dict) -> str:
    """One line for a table's caption: the CPU, its vector unit and its count, where the result recorded them."""
    cpus = machine.get("cpus") or machine.get("cpu_count")
    parts = [machine.get("platform", "not recorded")]
    if "cpu_model" in machine:
        llvm_cpu = f" ({machine['llvm_cpu']})" if "llvm_cpu" in machine else ""
        parts += [f"{machine['cpu_model']}{llvm_cpu}", machine.get("vector_unit", "unknown")]
    return ", ".join([*parts, f"{cpus or '?'} CPUs"])


def _model_name() -> str:
    """The CPU's marketing name from /proc/cpuinfo (Python's platform.processor() is empty on Linux)."""
    path = Path("/proc/cpuinfo")
    lines = path.read_text().splitlines() if path.is_file() else []
    name = next((line.partition(":")[2].strip() for line in lines if line.startswith("model name")), "")
    return name or platform.processor() or platform.machine()
