"""Running work in parallel: local worker processes or a Ray cluster, for generation and export.

- runner.py: `Runner`, the one parallel runner (this process, spawned workers or Ray
  tasks; results in submission order; stop or drain on Ctrl-C).
- worker.py: what a local worker does as it starts (watch the driver, take Ctrl-C
  from it only).
- cluster.py: joining a Ray cluster (`connect_ray`), with one-line errors.
- interrupts.py: `shielded`, for steps a Ctrl-C must not cut in half.
"""

from replay.parallel.cluster import RAY_HINT, ClusterError, check_reachable, connect_ray
from replay.parallel.interrupts import is_cancelled, shielded
from replay.parallel.runner import Runner, WorkerLost
from replay.parallel.worker import cancel_token

__all__ = ["RAY_HINT", "ClusterError", "Runner", "WorkerLost", "cancel_token", "check_reachable", "connect_ray",
           "is_cancelled", "shielded"]
