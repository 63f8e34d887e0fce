"""A task file's `success = "python:module:function"`: the function, from a module beside the file or installed.

A module beside the task file is loaded from its path (and goes into the task's bundle,
so replay needs nothing else); otherwise the module is imported by name.
"""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable
from pathlib import Path

from scenes.errors import first_line
from scenes.tasks.file_values import TaskFileError


def load_python_judge(success: str, task_path: Path, task_name: str, files: dict[str, Path], where: str) -> Callable:
    """The judge function `success` names; a module file beside the task is added to `files` (relative -> path)."""
    parts = success.split(":")
    if len(parts) != 3 or not all(parts[1:]):
        raise TaskFileError(f"{where}: success: expected \"python:module:function\", got {success!r}")
    module_name, func = parts[1], parts[2]
    beside = task_path.parent / f"{module_name.replace('.', '/')}.py"
    try:
        if beside.is_file():
            files[beside.relative_to(task_path.parent).as_posix()] = beside
            spec = importlib.util.spec_from_file_location(f"teleop_task_{task_name}_{module_name}", beside)
            module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
            spec.loader.exec_module(module)  # type: ignore[union-attr]
        else:
            module = importlib.import_module(module_name)
    except Exception as exc:
        raise TaskFileError(f"{where}: success: module {module_name!r} does not import: {first_line(exc)}") from None
    fn = getattr(module, func, None)
    if not callable(fn):
        raise TaskFileError(f"{where}: success: module {module_name!r} has no function {func!r}")
    return fn
