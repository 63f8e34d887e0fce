"""Joining a Ray cluster for work spread over machines (parallel export, generation).

Ray is an optional extra (`pip install 'mujoco-teleop[cluster]'`), imported only
here and only when asked. `ray.init` on an address nothing answers at retries
for minutes, so an address is first tried with a plain TCP connect. Nothing here
detaches: tasks belong to this driver, and Ray cancels them when the driver goes
away (exits, or is killed).
"""

from __future__ import annotations

import os
import socket

from scenes.errors import TeleopError, first_line

RAY_HINT = "Ray is not installed: pip install 'mujoco-teleop[cluster]'"


class ClusterError(TeleopError):
    """No Ray, or no Ray cluster at the address given (one line)."""


def check_reachable(address: str, timeout: float = 3.0) -> None:
    """Raise ClusterError in seconds unless something listens at HOST:PORT (or ray://HOST:PORT)."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise ClusterError(f"Ray address {address!r}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as exc:
        raise ClusterError(f"cannot reach a Ray cluster at {address}: {exc.strerror or exc}") from None


def connect_ray(address: str):
    """The `ray` module, joined to a cluster: "auto" (Ray's meaning: RAY_ADDRESS, else the one
    running on this machine), HOST:PORT or ray://HOST:PORT. A Ray instance this process already
    started (ray.init in a script or test) is used as it is.
    """
    try:
        import ray  # optional extra: only generation and export on a cluster need it
    except ImportError:
        raise ClusterError(RAY_HINT) from None
    if ray.is_initialized():
        return ray
    target = os.environ.get("RAY_ADDRESS", "").strip() if address == "auto" else address
    if target and target not in ("auto", "local"):
        check_reachable(target)
    try:
        ray.init(address=address, logging_level="ERROR", log_to_driver=False, include_dashboard=False)
    except ConnectionError:
        raise ClusterError("no Ray cluster is running on this machine's network "
                           "(start one with `ray start --head`, or give HOST:PORT)") from None
    except Exception as exc:  # noqa: BLE001 - Ray raises RuntimeError, ValueError, TimeoutError...
        raise ClusterError(f"cannot reach a Ray cluster at {address}: {first_line(exc)[:200]}") from None
    return ray
