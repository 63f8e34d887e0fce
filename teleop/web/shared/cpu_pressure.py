"""How crowded the machine's CPUs are, from Linux's pressure stall information, so that optional work can yield.

`/proc/pressure/cpu`'s "some avg10" is the share of the last ~10 s in which at least one runnable task waited for
a CPU, in percent. On the project's 2-core machine, with watched campaign sessions (bench/campaign.py), it was
14 % with 8 sessions, 33 % with 12, 86 % with 16 (every loop still on time) and 95-100 % with 20 and 24 (loops
late). Where the file is missing (not Linux, a kernel without PSI) there is no figure, and nothing yields.
"""

from __future__ import annotations

from pathlib import Path

PSI_CPU = Path("/proc/pressure/cpu")


def cpu_pressure(path: Path = PSI_CPU) -> float | None:
    """Percent of the last ~10 s in which some runnable task waited for a CPU; None where the kernel does not say."""
    try:
        with open(path) as f:
            line = f.readline()  # "some avg10=35.60 avg60=78.64 avg300=51.91 total=12185736565"
        return float(line.split("avg10=", 1)[1].split(None, 1)[0])
    except (OSError, IndexError, ValueError):
        return None
