"""Argument checks shared by the configuration objects: one ValueError naming every bad field."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["integer", "real", "raise_invalid"]


def integer(value, low: int, none: bool = False) -> bool:
    """Whether ``value`` is an integer (not a bool) of at least ``low``.

    * ``value``: the value to check.
    * ``low``: the smallest value allowed.
    * ``none``: whether None is allowed.
    """
    if value is None:
        return none
    return not isinstance(value, bool) and isinstance(value, (int, np.integer)) and value >= low


def real(value, low=None, high=None, low_open: bool = False, none: bool = False, inf: bool = False) -> bool:
    """Whether ``value`` is a real number (not a bool, not NaN) in the given range.

    * ``value``: the value to check.
    * ``low``, ``high``: the bounds (None: unbounded); ``high`` is closed.
    * ``low_open``: whether ``low`` itself is excluded.
    * ``none``: whether None is allowed.
    * ``inf``: whether infinity is allowed.
    """
    if value is None:
        return none
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return False
    value = float(value)
    if math.isnan(value) or (math.isinf(value) and not inf):
        return False
    if low is not None and (value <= low if low_open else value < low):
        return False
    return high is None or value <= high


def raise_invalid(owner, checks: dict) -> None:
    """Raise one ValueError naming every field of ``owner`` whose check failed, its value and what is expected.

    * ``owner``: the object checked (its class name and its attributes are read).
    * ``checks``: field name -> (passed, what is expected).
    """
    bad = [k for k, (ok, _) in checks.items() if not ok]
    if bad:
        raise ValueError(
            f"invalid {type(owner).__name__} field(s) {bad}: "
            + "; ".join(f"{k}={getattr(owner, k)!r} (expected {checks[k][1]})" for k in bad)
        )
