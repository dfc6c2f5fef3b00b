"""bench/machine.py: a bench result names the CPU and its widest vector unit, not the platform string alone,
which read the same on an AVX-512 host and on an AVX2 host with half its kernel speed."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.no_kernels

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from machine import VECTOR_UNITS, describe, summary  # noqa: E402

sys.path.pop(0)

KERNEL_FLAG = {"sse4.2": "sse4_2", "neon": "asimd"}  # /proc/cpuinfo's name where it is not LLVM's


@pytest.mark.skipif(not Path("/proc/cpuinfo").is_file(), reason="checks LLVM's reading against /proc/cpuinfo")
def test_a_result_records_the_cpu_and_the_widest_vector_unit_the_kernel_reports():
    machine = describe()
    flags = set(next(line for line in Path("/proc/cpuinfo").read_text().splitlines()
                     if line.startswith(("flags", "Features"))).split(":", 1)[1].split())
    assert machine["cpu_model"] and machine["llvm_cpu"] and machine["cpus"] >= 1
    assert KERNEL_FLAG.get(machine["vector_unit"], machine["vector_unit"]) in flags
    wider = VECTOR_UNITS[:VECTOR_UNITS.index(machine["vector_unit"])]
    assert not flags & {KERNEL_FLAG.get(unit, unit) for unit in wider}


def test_the_caption_names_the_cpu_and_keeps_older_results_readable():
    machine = {"platform": "Linux-6.18", "cpus": 2, "cpu_model": "AMD EPYC", "llvm_cpu": "znver3",
               "vector_unit": "avx2"}
    assert summary(machine) == "Linux-6.18, AMD EPYC (znver3), avx2, 2 CPUs"
    assert summary({"platform": "Linux-6.18", "cpus": 2, "cpu_model": "AMD EPYC (family 25, model 1)",
                    "vector_unit": "avx2"}) == "Linux-6.18, AMD EPYC (family 25, model 1), avx2, 2 CPUs"
    assert summary({"platform": "Linux-6.18", "cpu_count": 2}) == "Linux-6.18, 2 CPUs"
    assert summary({}) == "not recorded, ? CPUs"
