"""Where a warning of tcd points: the user's line, not tcd's."""
from __future__ import annotations

import os
import sys

_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def _in_tcd(frame) -> bool:
    """A frame of tcd's own code: a file of the package, or the `__init__` that `dataclasses`
    generates for one of its classes (its file is "<string>")."""
    name = frame.f_code.co_filename
    if os.path.abspath(name).startswith(_PACKAGE):
        return True
    owner = frame.f_locals.get("self") if frame.f_code.co_name == "__init__" else None
    return name == "<string>" and type(owner).__module__.startswith("tcd.")


def user_stacklevel() -> int:
    """The `stacklevel` that makes a warning raised by the caller point at the first frame
    outside the tcd package (the user's line), however deep inside tcd the warning is raised."""
    level, frame = 1, sys._getframe(1)
    while frame is not None and _in_tcd(frame):
        frame, level = frame.f_back, level + 1
    return level
