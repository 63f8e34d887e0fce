"""The process pool: work run in parallel on local worker processes or a Ray cluster.

Generation (teleop/generate) and parallel export (replay/export/shards.py) run their tasks
here, and the browser session takes `shielded` for saves a Ctrl-C must not cut in half. It
imports only scenes.errors of ours, so it sits on the lowest floor every user can import.

- runner.py: `Runner`, the one parallel runner (this process, local workers forked from
  a fork server that imported their modules once, or Ray tasks; results in submission
  order; stop or drain on Ctrl-C), and `worker_context`, how those workers start.
- worker.py: what a local worker does as it starts (watch the driver, take Ctrl-C
  from it only).
- cluster.py: joining a Ray cluster (`connect_ray`), with one-line errors.
- interrupts.py: `shielded`, for steps a Ctrl-C must not cut in half.
"""

from scenes.workers.cluster import RAY_HINT, ClusterError, check_reachable, connect_ray
from scenes.workers.interrupts import is_cancelled, shielded
from scenes.workers.runner import Runner, WorkerLost, worker_context
from scenes.workers.worker import cancel_token

__all__ = ["RAY_HINT", "ClusterError", "Runner", "WorkerLost", "cancel_token", "check_reachable", "connect_ray",
           "is_cancelled", "shielded", "worker_context"]
