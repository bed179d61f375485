"""Argument checks shared by every stage, so each rule and its message live in one place.

Each check returns the value converted (``float``, ``int``) and raises `ValueError` naming the argument
and the value received. ``name`` is the caller's name for the argument (a keyword, or a CLI flag).
"""
from __future__ import annotations

import math
from typing import Any, Iterable

__all__ = ["positive_finite", "nonnegative_finite", "number_at_least", "integer_at_least", "one_of", "boolean"]


def _number(value: Any) -> float | None:
    if isinstance(value, (bool, str, bytes)):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def positive_finite(name: str, value: Any) -> float:
    """``value`` as a float > 0 and finite (a bool or a string is refused)."""
    v = _number(value)
    if v is None or not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def nonnegative_finite(name: str, value: Any) -> float:
    """``value`` as a float >= 0 and finite."""
    v = _number(value)
    if v is None or not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def number_at_least(name: str, value: Any, minimum: float) -> float:
    """``value`` as a finite float >= ``minimum``."""
    v = _number(value)
    if v is None or not (math.isfinite(v) and v >= minimum):
        raise ValueError(f"{name} must be a number >= {minimum:g}, got {value!r}")
    return v


def integer_at_least(name: str, value: Any, minimum: int) -> int:
    """``value`` as an int >= ``minimum``; integral floats (3.0) are accepted, bools are not."""
    v = _number(value)
    if v is None or not math.isfinite(v) or v != int(v) or int(v) < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(v)


def one_of(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """``value`` itself when it is one of ``choices``."""
    choices = tuple(choices)
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")
    return value


def boolean(name: str, value: Any) -> bool:
    """``value`` as a bool; only True/False (and NumPy bools) are accepted, not "yes" or 1."""
    import numpy as np

    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)
