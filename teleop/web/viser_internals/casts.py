"""viser's property cast, quicker for float arrays (a process-wide patch: `install_quick_array_casts`, applied by
teleop.web.viser_internals.install).

Every property a handle is given goes through `AssignablePropsBase._cast_value_recursive`,
which compares the property's type hint with `npt.NDArray[np.float16]`, `[np.float32]` and
`[np.float64]` built anew at each call (typing's substitution machinery: ~20-35 us a property,
a third of a scene update's cost). Patched, a float-array hint is looked up in a table built
once (`FLOAT_ARRAY_HINTS`) and cast as viser does (`np.asarray(value).astype(dtype)`); any
other hint goes to viser's own function unchanged.
"""

from __future__ import annotations

import threading

import numpy as np
import numpy.typing as npt
from viser._assignable_props_api import AssignablePropsBase

FLOAT_ARRAY_HINTS = {npt.NDArray[t]: t for t in (np.float16, np.float32, np.float64)}  # viser's float-array hints
_CAST_LOCK = threading.Lock()


def install_quick_array_casts() -> None:
    """Make viser's property cast look float-array hints up in FLOAT_ARRAY_HINTS (once per process; see above)."""
    with _CAST_LOCK:
        original = AssignablePropsBase._cast_value_recursive  # noqa: SLF001
        if getattr(original, "quick", False):
            return

        def cast(self, hint, value, prop_name):
            try:
                dtype = FLOAT_ARRAY_HINTS.get(hint)
            except TypeError:  # an unhashable hint: viser's own comparisons
                dtype = None
            if dtype is not None:
                return np.asarray(value).astype(dtype)
            return original(self, hint, value, prop_name)

        cast.quick = True  # type: ignore[attr-defined]
        cast.original = original  # type: ignore[attr-defined]
        AssignablePropsBase._cast_value_recursive = cast  # noqa: SLF001


def quick_array_casts_installed() -> bool:
    """Whether install_quick_array_casts's cast is in place."""
    return bool(getattr(AssignablePropsBase._cast_value_recursive, "quick", False))  # noqa: SLF001
