"""LeRobot's own commands on the simulation: a robot, a teleoperator and an env type (issue 58).

    --robot.type=mujoco_teleop          MujocoTeleop (config_mujoco_teleop.py, mujoco_teleop.py)
    --teleop.type=mujoco_teleop_web     MujocoTeleopWeb (config_mujoco_teleop_web.py, mujoco_teleop_web.py)
    --env.type=mujoco_teleop            MujocoTeleopEnvConfig (env_config.py, lerobot_env.py)

Importing this package registers the three types with LeRobot's draccus registries. It stays light
(LeRobot imports its plugins at every command's start): every LeRobot config module imports torch, so a
type is registered at once where LeRobot's base module is already loaded (inside a LeRobot command it
always is), and otherwise the moment that module finishes loading (an import hook), never by loading it.
MuJoCo, torch and viser are imported only when a robot, teleoperator or env is made.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import logging
import sys
from collections.abc import Callable

# LeRobot's module holding each base class -> our module that subclasses and registers it
REGISTRATIONS: dict[str, str] = {
    "lerobot.robots.config": "teleop.lerobot_plugin.config_mujoco_teleop",
    "lerobot.teleoperators.config": "teleop.lerobot_plugin.config_mujoco_teleop_web",
    "lerobot.envs.configs": "teleop.lerobot_plugin.env_config",
}
ROBOT_TYPE = "mujoco_teleop"
TELEOP_TYPE = "mujoco_teleop_web"
ENV_TYPE = "mujoco_teleop"


class _Then(importlib.abc.Loader):
    """A module's own loader, then `after()` once the module has run (it is in sys.modules by then)."""

    def __init__(self, loader: importlib.abc.Loader, after: Callable[[], None]) -> None:
        self.loader, self.after = loader, after

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module) -> None:
        self.loader.exec_module(module)
        self.after()


class _AfterImport(importlib.abc.MetaPathFinder):
    """Runs our registration right after LeRobot's base module loads, without ever loading it."""

    def __init__(self) -> None:
        self.pending: dict[str, str] = {}

    def find_spec(self, name, path, target=None):
        ours = self.pending.pop(name, None)
        if ours is None:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None:
            return spec
        spec.loader = _Then(spec.loader, lambda: _import(ours))
        return spec


def _import(module: str) -> None:
    """Import one of our registering modules from inside LeRobot's import: a failure is logged, as LeRobot logs a
    plugin that fails, and never breaks LeRobot's own import."""
    try:
        importlib.import_module(module)
    except Exception:
        logging.getLogger(__name__).exception("mujoco_teleop: could not register %s with LeRobot", module)


_HOOK = _AfterImport()


def register() -> None:
    """Register every type whose LeRobot base is loaded; the others when their base loads (idempotent)."""
    for base, ours in REGISTRATIONS.items():
        if base in sys.modules:
            importlib.import_module(ours)
        else:
            _HOOK.pending[base] = ours
    if _HOOK.pending and _HOOK not in sys.meta_path:
        sys.meta_path.insert(0, _HOOK)


register()
