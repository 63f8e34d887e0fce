"""Names a package exports but imports at their first use (PEP 562), so that importing the package stays quick.

`import teleop` or `from scenes.errors import ...` then costs milliseconds; MuJoCo, mink and the rest load
with the first name that needs them (`teleop --help` and a command that stops at a bad flag never do).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_names(package: str, homes: dict[str, str], namespace: dict[str, Any]) -> tuple[Callable[[str], Any],
                                                                                      Callable[[], list[str]]]:
    """The module-level `__getattr__` and `__dir__` of `package`: each name in `homes` from its module."""

    def __getattr__(name: str) -> Any:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        namespace[name] = value  # the next use is a plain attribute
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(namespace.get("__all__", ())))

    return __getattr__, __dir__
