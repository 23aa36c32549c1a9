"""Shared by the `scripts/bench_*.py` benchmarks: the line that says where and when a timing was taken.

    from _bench import machine_line   # scripts/ is on sys.path when a script in it runs
    print(machine_line())

prints e.g. `machine: Intel(R) Xeon(R) Processor @ 2.80GHz, 2 cores (2 usable), load 1.02 0.85 0.60
(1/5/15 min), torch 2.13.0+cpu, Python 3.11.7, Linux, 2026-11-28 04:20 UTC` (each script prints the
threads it gives torch). Timings on a
shared machine move with its load, so every benchmark prints this line with its ratios (each against
a baseline measured in the same run), and the README quotes both.
"""

from __future__ import annotations

import datetime
import os
import platform
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux), else what `platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.split(":")[0].strip() in ("model name", "Hardware", "cpu model"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def machine_line() -> str:
    """One line: CPU model, cores (and those this process may use), load averages, torch's version,
    Python, OS, date and time (UTC)."""
    cores = os.cpu_count() or 0
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores
    load = " ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    try:
        import torch

        lib = f"torch {torch.__version__}"
    except ImportError:
        lib = "no torch"
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (
        f"machine: {cpu_model()}, {cores} cores ({usable} usable), load {load} (1/5/15 min), {lib}, "
        f"Python {platform.python_version()}, {platform.system()}, {now}"
    )


if __name__ == "__main__":
    print(machine_line())
