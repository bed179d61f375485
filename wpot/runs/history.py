"""D(β): the distance along the annealing (paper §4.1.1), as (n_β, 2) float64 arrays of (β, U_β).

A solver's `wpot.ot.OTResult.energy_history` gives U_β at each β it solved; `history_at` reads such a
history at other β (a pair's own β grid depends on its costs), and `debias_history` applies Eq. 27 at
every β for partial transport.
"""
from __future__ import annotations

import numpy as np
from wpot.ot import debiased

__all__ = ["history_at", "debias_history"]


def history_at(h: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Value of a (β, U) history at each β in ``betas``: the last entry with β' ≤ β (1e-9 relative slack in log β),
    NaN where β is below the first recorded β."""
    h = np.asarray(h, dtype=np.float64).reshape(-1, 2)
    betas = np.asarray(betas, dtype=np.float64)
    if len(h) == 0:
        return np.full(betas.shape, np.nan)
    lb = np.log(h[:, 0])
    pos = np.searchsorted(lb, np.log(betas) + 1e-9, side="right") - 1
    return np.where(pos >= 0, h[np.maximum(pos, 0), 1], np.nan)


def debias_history(h_ab: np.ndarray, h_aa: np.ndarray, h_bb: np.ndarray) -> np.ndarray:
    """SU_β (Eq. 27, `wpot.ot.debiased`) on the β grid of ``h_ab``; each self history is read at the same β
    (its last value after it converged, NaN before its first β)."""

    out = np.array(h_ab, dtype=np.float64, copy=True).reshape(-1, 2)
    if len(out) == 0:
        return out
    out[:, 1] = debiased(out[:, 1], history_at(h_aa, out[:, 0]), history_at(h_bb, out[:, 0]), strict=False)
    return out
