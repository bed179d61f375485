"""Argument checks shared by every stage, so each rule and its message live in one place.

Each check returns the value converted (``float``, ``int``) and raises `ValueError` naming the argument
and the value received. ``name`` is the caller's name for the argument (a keyword, or a CLI flag).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Iterable

if TYPE_CHECKING:
    import numpy as np

__all__ = ["positive_finite", "nonnegative_finite", "number_at_least", "integer_at_least", "one_of",
           "one_of_or_positive", "boolean", "vertex_map"]


def _number(value: Any) -> float | None:
    if isinstance(value, (bool, str, bytes)):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def finite(name: str, value: Any) -> float:
    """``value`` as a finite float (a bool or a string is refused)."""
    v = _number(value)
    if v is None or not math.isfinite(v):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return v


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


def one_of_or_positive(name: str, value: Any, choices: Iterable[str]) -> str | float:
    """``value`` itself when it is one of the strings ``choices``, else as a float > 0 and finite."""
    choices = tuple(choices)
    if isinstance(value, str) and value in choices:
        return value
    v = None if isinstance(value, str) else _number(value)
    if v is None or not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be one of {choices} or a positive number, got {value!r}")
    return v


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


def vertex_map(name: str, value: Any, n_a: int, n_b: int) -> "np.ndarray":
    """``value`` as an (n_a,) int64 map from the vertices of a mesh A to those of a mesh B: integers (or floats
    with integer values) in [0, n_b)."""
    import numpy as np

    t = np.asarray(value)
    if t.shape != (n_a,):
        raise ValueError(f"{name} must have shape (N_A,) = ({n_a},), one vertex of B per vertex of A; "
                         f"got shape {t.shape}")
    if t.size and not np.issubdtype(t.dtype, np.integer):
        if not (np.issubdtype(t.dtype, np.floating) and np.all(np.isfinite(t)) and np.all(t == np.round(t))):
            raise ValueError(f"{name} must hold vertex indices (integers), got dtype {t.dtype}")
    t = t.astype(np.int64)
    bad = np.nonzero((t < 0) | (t >= n_b))[0]
    if bad.size:
        raise ValueError(f"{name} holds {bad.size} indices outside B's vertices [0, {n_b}), e.g. "
                         f"{name}[{bad[0]}] = {t[bad[0]]}")
    return t
