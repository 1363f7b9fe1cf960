"""Small helpers shared by every validator: how a bad value is shown, what counts as a number.

One place decides both, so that a message never prints a multi-megabyte value (an alias-expanded
YAML list, a whole array) and numpy scalars are accepted wherever Python numbers are.
"""

from __future__ import annotations

import math
import reprlib
from typing import Any

import numpy as np

from ctpipe.errors import InputError

__all__ = ["short_repr", "as_real", "as_integer", "as_angles_deg"]

#: Longest repr of a value in an error message; messages are one line.
REPR_LIMIT = 80

_REPR = reprlib.Repr()
_REPR.maxlevel = 3
_REPR.maxlist = _REPR.maxtuple = _REPR.maxset = _REPR.maxfrozenset = _REPR.maxdeque = 8
_REPR.maxdict = 4
_REPR.maxstring = _REPR.maxother = _REPR.maxlong = REPR_LIMIT


def short_repr(value: Any, limit: int = REPR_LIMIT) -> str:
    """``repr(value)`` on one line, cut to at most ``limit`` characters with ``...``.

    reprlib stops walking long or deep containers early, so this is cheap even for a value
    holding millions of items (or itself).
    """
    if isinstance(value, np.generic):
        value = value.item()
    text = " ".join(_REPR.repr(value).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_real(value: Any) -> float | None:
    """``value`` as a Python float if it is a real number (Python or numpy, not bool), else None."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return None
    try:
        return float(value)
    except OverflowError:  # an int beyond float range
        return math.copysign(math.inf, value)


def as_integer(value: Any) -> int | None:
    """``value`` as a Python int if it is an integer (Python or numpy, not bool), else None."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        return None
    return int(value)


def as_angles_deg(value: Any, name: str = "angles_deg") -> np.ndarray:
    """``value`` as a non-empty 1-D float64 array of finite angles, or an ``InputError`` naming ``name``."""
    angles = np.asarray(value)
    if angles.ndim != 1 or angles.size == 0 or not np.issubdtype(angles.dtype, np.number) or np.iscomplexobj(angles):
        raise InputError(f"{name}: must be a non-empty 1-D array of real numbers (degrees), got shape "
                         f"{angles.shape} and dtype {angles.dtype}")
    angles = angles.astype(np.float64)
    if not np.all(np.isfinite(angles)):
        raise InputError(f"{name}: must be finite, got NaN or infinite values")
    return angles
