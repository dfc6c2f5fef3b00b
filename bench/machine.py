"""What a bench result says of the machine it ran on. The platform string alone named two hosts alike whose
kernels ran twice as fast on one (AVX-512) as on the other (AVX2), so the CPU and its widest vector unit go in too."""

from __future__ import annotations

import os
import platform
from pathlib import Path

VECTOR_UNITS = ("avx512f", "avx2", "avx", "sse4_2", "asimd")  # widest first; asimd is aarch64's NEON


def describe() -> dict:
    """Platform, CPU count and model, widest vector unit, Python version, and the 1-minute load now."""
    cpu = _cpuinfo()
    flags = set(cpu.get("flags", cpu.get("Features", "")).split())
    model = cpu.get("model name") or platform.processor() or platform.machine()
    if "cpu family" in cpu and "model" in cpu:
        model = f"{model} (family {cpu['cpu family']}, model {cpu['model']})"
    return {"platform": platform.platform(), "cpus": os.cpu_count(), "cpu_model": model,
            "vector_unit": next((unit for unit in VECTOR_UNITS if unit in flags), "unknown"),
            "python": platform.python_version(), "load_1min": round(os.getloadavg()[0], 2)}


def summary(machine: dict) -> str:
    """One line for a table's caption: the CPU, its vector unit and its count, where the result recorded them."""
    cpus = machine.get("cpus") or machine.get("cpu_count")
    cpu = f"{machine['cpu_model']}, {machine.get('vector_unit', 'unknown')}, " if "cpu_model" in machine else ""
    return f"{machine.get('platform', 'not recorded')}, {cpu}{cpus or '?'} CPUs"


def _cpuinfo() -> dict[str, str]:
    """The first processor's fields in /proc/cpuinfo; empty where there is none (not Linux)."""
    path = Path("/proc/cpuinfo")
    if not path.is_file():
        return {}
    fields: dict[str, str] = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            if fields:
                break
            continue
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return fields
