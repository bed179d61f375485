"""Signature cost matrices as Warp kernels (float64), on "cpu" or "cuda".

Metrics, for signatures a = S1[i] and b = S2[j] of length D:

* ``"wks"``: paper Eq. 29, ``C_ij = Σ_d |(a_d − b_d) / (a_d + b_d)|``. Signatures must be nonnegative
  (WKS are); a term with ``a_d + b_d = 0`` (then ``a_d = b_d = 0``) counts 0.
* ``"l2"``: Euclidean distance ``sqrt(Σ_d (a_d − b_d)²)`` (paper §3.1, LD-SIFT).
* ``"l1"``: ``Σ_d |a_d − b_d|``.

The result is an (N1, N2) float64 array: NumPy by default (``out="numpy"``), or a ``wp.array`` of
dtype float64 on the chosen device (``out="warp"``), which the OT solver takes without a copy.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
import warp as wp

from wpot._warp import resolve_device

__all__ = ["cost_matrix", "METRICS"]

wp.set_module_options({"enable_backward": False})

METRICS = ("wks", "l2", "l1")


@wp.kernel
def _cost_wks(a: wp.array2d(dtype=wp.float64), b: wp.array2d(dtype=wp.float64), c: wp.array2d(dtype=wp.float64)):
    i, j = wp.tid()
    s = wp.float64(0.0)
    for d in range(a.shape[1]):
        x = a[i, d]
        y = b[j, d]
        den = x + y
        if den != wp.float64(0.0):
            s += wp.abs((x - y) / den)
    c[i, j] = s


@wp.kernel
def _cost_l2(a: wp.array2d(dtype=wp.float64), b: wp.array2d(dtype=wp.float64), c: wp.array2d(dtype=wp.float64)):
    i, j = wp.tid()
    s = wp.float64(0.0)
    for d in range(a.shape[1]):
        t = a[i, d] - b[j, d]
        s += t * t
    c[i, j] = wp.sqrt(s)


@wp.kernel
def _cost_l1(a: wp.array2d(dtype=wp.float64), b: wp.array2d(dtype=wp.float64), c: wp.array2d(dtype=wp.float64)):
    i, j = wp.tid()
    s = wp.float64(0.0)
    for d in range(a.shape[1]):
        s += wp.abs(a[i, d] - b[j, d])
    c[i, j] = s


@wp.kernel
def _scan_bad(a: wp.array2d(dtype=wp.float64), check_negative: int, flags: wp.array(dtype=wp.int32)):
    i, j = wp.tid()
    x = a[i, j]
    if not wp.isfinite(x):
        flags[0] = 1
    elif check_negative != 0 and x < wp.float64(0.0):
        flags[1] = 1


_KERNELS = {"wks": _cost_wks, "l2": _cost_l2, "l1": _cost_l1}


def _as_signatures(name: str, s, dev) -> wp.array:
    if isinstance(s, wp.array):
        if s.dtype != wp.float64 or s.ndim != 2:
            raise ValueError(f"{name} must be a 2-D float64 array, got a wp.array of dtype {s.dtype.__name__} with ndim {s.ndim}")
        if s.device != dev:
            raise ValueError(f"{name} is on device {s.device}; expected {dev} (the device argument)")
        if not s.is_contiguous:
            s = wp.clone(s)
        return s
    a = np.asarray(s)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (N, D) array of signatures, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.iscomplexobj(a):
        raise ValueError(f"{name} must be a real numeric array, got dtype {a.dtype}")
    return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.float64, device=dev)


def _check_values(name: str, s: wp.array, metric: str, dev) -> None:
    flags = wp.zeros(2, dtype=wp.int32, device=dev)
    wp.launch(_scan_bad, dim=s.shape, inputs=[s, int(metric == "wks"), flags], device=dev)
    bad_nan, bad_neg = flags.numpy()
    if bad_nan:
        raise ValueError(f"{name} contains NaN or inf values")
    if bad_neg:
        raise ValueError(f"{name} has negative entries; metric='wks' (Eq. 29) needs nonnegative signatures such as WKS")


def cost_matrix(
    S1,
    S2,
    *,
    metric: Literal["wks", "l2", "l1"] = "wks",
    device: str | None = None,
    out: Literal["numpy", "warp"] = "numpy",
):
    """Pairwise cost between two sets of per-vertex signatures (paper Eq. 29 for WKS, L2 for LD-SIFT).

    Parameters
    ----------
    S1 : (N1, D) signatures of shape 1: NumPy array-like or a float64 ``wp.array`` on ``device``.
    S2 : (N2, D) signatures of shape 2 (same D, same energy grid for WKS).
    metric : ``"wks"`` (Eq. 29, ``Σ_d |(a−b)/(a+b)|``, terms with a+b = 0 count 0; inputs must be
        nonnegative), ``"l2"`` (Euclidean distance) or ``"l1"``.
    device : Warp device (``"cpu"``, ``"cuda"``, ``"cuda:0"``...); None means Warp's default device.
    out : ``"numpy"`` for a NumPy array, ``"warp"`` for a ``wp.array`` on ``device``.

    Returns
    -------
    C : (N1, N2) float64, ``C[i, j]`` the cost between ``S1[i]`` and ``S2[j]``.

    Raises
    ------
    ValueError : unknown metric/out, non-2-D input, mismatched D, empty input, NaN/inf values,
        negative values with ``metric="wks"``, or a ``wp.array`` on another device.
    """
    if metric not in _KERNELS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    if out not in ("numpy", "warp"):
        raise ValueError(f"out must be 'numpy' or 'warp', got {out!r}")
    dev = resolve_device(device)
    a = _as_signatures("S1", S1, dev)
    b = _as_signatures("S2", S2, dev)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"S1 and S2 must have the same signature length D, got {a.shape[1]} and {b.shape[1]}")
    if a.shape[0] == 0 or b.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"empty signatures: S1 has shape {a.shape}, S2 has shape {b.shape}")
    _check_values("S1", a, metric, dev)
    _check_values("S2", b, metric, dev)
    c = wp.empty((a.shape[0], b.shape[0]), dtype=wp.float64, device=dev)
    wp.launch(_KERNELS[metric], dim=c.shape, inputs=[a, b, c], device=dev)
    if out == "warp":
        return c
    return c.numpy()
