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
from numpy.typing import ArrayLike
import warp as wp

from wpot._warp import launch_rows, resolve_device

__all__ = ["cost_matrix", "cost_mean", "METRICS"]

# no fused multiply-add: costs identical bit for bit on the CPU and CUDA (and symmetric on both)
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

METRICS = ("wks", "l2", "l1")


#: metric name -> the integer code the Warp funcs below (and the matrix-free OT kernels) take
METRIC_CODES = {"wks": 0, "l2": 1, "l1": 2}


@wp.func
def _wks_term(x: wp.float64, y: wp.float64) -> wp.float64:
    den = x + y
    if den != wp.float64(0.0):
        return wp.abs((x - y) / den)
    return wp.float64(0.0)


# The per-pair sums below run four independent accumulators (combined as (s0 + s1) + (s2 + s3)): the
# single-accumulator loop is bound by the latency of the additions on the CPU backend (the docs' Results
# page), which matters in the matrix-free OT mode where every pass over C recomputes these sums.


@wp.func
def pair_wks(a: wp.array2d(dtype=wp.float64), i: int, b: wp.array2d(dtype=wp.float64), j: int) -> wp.float64:
    """Eq. 29 between rows a[i] and b[j]: sum_d |(a_d - b_d) / (a_d + b_d)|, terms with a_d + b_d = 0 count 0."""
    s0 = wp.float64(0.0)
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    s3 = wp.float64(0.0)
    n = a.shape[1]
    n4 = n - n % 4
    for d in range(0, n4, 4):
        s0 += _wks_term(a[i, d], b[j, d])
        s1 += _wks_term(a[i, d + 1], b[j, d + 1])
        s2 += _wks_term(a[i, d + 2], b[j, d + 2])
        s3 += _wks_term(a[i, d + 3], b[j, d + 3])
    for d in range(n4, n):
        s0 += _wks_term(a[i, d], b[j, d])
    return (s0 + s1) + (s2 + s3)


@wp.func
def pair_l2(a: wp.array2d(dtype=wp.float64), i: int, b: wp.array2d(dtype=wp.float64), j: int) -> wp.float64:
    """Euclidean distance between rows a[i] and b[j]."""
    s0 = wp.float64(0.0)
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    s3 = wp.float64(0.0)
    n = a.shape[1]
    n4 = n - n % 4
    for d in range(0, n4, 4):
        t0 = a[i, d] - b[j, d]
        t1 = a[i, d + 1] - b[j, d + 1]
        t2 = a[i, d + 2] - b[j, d + 2]
        t3 = a[i, d + 3] - b[j, d + 3]
        s0 += t0 * t0
        s1 += t1 * t1
        s2 += t2 * t2
        s3 += t3 * t3
    for d in range(n4, n):
        t = a[i, d] - b[j, d]
        s0 += t * t
    return wp.sqrt((s0 + s1) + (s2 + s3))


@wp.func
def pair_l1(a: wp.array2d(dtype=wp.float64), i: int, b: wp.array2d(dtype=wp.float64), j: int) -> wp.float64:
    """L1 distance between rows a[i] and b[j]."""
    s0 = wp.float64(0.0)
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    s3 = wp.float64(0.0)
    n = a.shape[1]
    n4 = n - n % 4
    for d in range(0, n4, 4):
        s0 += wp.abs(a[i, d] - b[j, d])
        s1 += wp.abs(a[i, d + 1] - b[j, d + 1])
        s2 += wp.abs(a[i, d + 2] - b[j, d + 2])
        s3 += wp.abs(a[i, d + 3] - b[j, d + 3])
    for d in range(n4, n):
        s0 += wp.abs(a[i, d] - b[j, d])
    return (s0 + s1) + (s2 + s3)


@wp.func
def pair_cost(metric: int, a: wp.array2d(dtype=wp.float64), i: int, b: wp.array2d(dtype=wp.float64),
              j: int) -> wp.float64:
    """The cost between rows a[i] and b[j] for a metric code of `METRIC_CODES` (the one per-pair definition,
    shared by `cost_matrix` and the matrix-free OT kernels). All three are symmetric, bit for bit."""
    if metric == 0:
        return pair_wks(a, i, b, j)
    if metric == 1:
        return pair_l2(a, i, b, j)
    return pair_l1(a, i, b, j)


@wp.kernel
def _cost(a: wp.array2d(dtype=wp.float64), b: wp.array2d(dtype=wp.float64), metric: int,
          c: wp.array2d(dtype=wp.float64)):
    i, j = wp.tid()
    c[i, j] = pair_cost(metric, a, i, b, j)


@wp.kernel
def _scan_bad(a: wp.array2d(dtype=wp.float64), check_negative: int, flags: wp.array(dtype=wp.int32)):
    i, j = wp.tid()
    x = a[i, j]
    if not wp.isfinite(x):
        flags[0] = 1
    elif check_negative != 0 and x < wp.float64(0.0):
        flags[1] = 1


def _as_signatures(name: str, s, dev, metric: str) -> wp.array:
    if metric not in METRIC_CODES:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
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


def prepare_signatures(S1, S2, metric: str, dev, names: tuple[str, str] = ("S1", "S2")
                       ) -> tuple[wp.array, wp.array]:
    """Validate a pair of signature arrays for ``metric`` and bring them to device ``dev`` as contiguous
    (N1, D), (N2, D) float64 ``wp.array``s (no copy for a contiguous float64 wp.array already there).

    Raises ValueError (naming the argument by ``names``) for an unknown metric, non-2-D input, mismatched
    D, empty input, NaN/inf values, negative values with ``metric="wks"`` or a wp.array on another device.
    """
    a, b = _prepared(names[0], S1, metric, dev), _prepared(names[1], S2, metric, dev)
    _check_pair(a, b, names)
    return a, b


def _prepared(name: str, s, metric: str, dev) -> wp.array:
    """One side of `prepare_signatures`: checked alone (its width is checked against the other's by `_check_pair`)."""
    a = _as_signatures(name, s, dev, metric)
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"empty signatures: {name} has shape {a.shape}")
    _check_values(name, a, metric, dev)
    return a


def _check_pair(a: wp.array, b: wp.array, names: tuple[str, str]) -> None:
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"{names[0]} and {names[1]} must have the same signature length D, got {a.shape[1]} and "
                         f"{b.shape[1]}")


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
    if out not in ("numpy", "warp"):
        raise ValueError(f"out must be 'numpy' or 'warp', got {out!r}")
    dev = resolve_device(device)
    a, b = prepare_signatures(S1, S2, metric, dev)
    c = wp.empty((a.shape[0], b.shape[0]), dtype=wp.float64, device=dev)
    code = METRIC_CODES[metric]
    launch_rows(lambda lo, hi: wp.launch(_cost, dim=(hi - lo, c.shape[1]), inputs=[a[lo:hi], b, code, c[lo:hi]],
                                         device=dev), c.shape[0], dev,
                cols=c.shape[1])
    if out == "warp":
        return c
    return c.numpy()


@wp.kernel
def _paired(a: wp.array2d(dtype=wp.float64), b: wp.array2d(dtype=wp.float64), ib: wp.array(dtype=wp.int64),
            metric: int, out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = pair_cost(metric, a, i, b, int(ib[i]))


def paired_costs(S1, S2, rows_2: ArrayLike, *, metric: Literal["wks", "l2", "l1"] = "wks",
                 device: str | None = None) -> np.ndarray:
    """(N1,) float64, the cost between ``S1[i]`` and ``S2[rows_2[i]]`` for every i: the entries of
    `cost_matrix` ``(S1, S2)`` that a vertex map picks (e.g. a correspondence's own cost), without the matrix.
    Same validation as `cost_matrix`; ``rows_2`` (N1,) integer indices into S2."""
    dev = resolve_device(device)
    a, b = prepare_signatures(S1, S2, metric, dev)
    r = np.asarray(rows_2)
    if r.shape != (a.shape[0],) or (r.size and not np.issubdtype(r.dtype, np.integer)):
        raise ValueError(f"rows_2 must be ({a.shape[0]},) integer indices, one per row of S1, got shape {r.shape} "
                         f"and dtype {r.dtype}")
    if r.size and (r.min() < 0 or r.max() >= b.shape[0]):
        raise ValueError(f"rows_2 holds indices outside [0, {b.shape[0] - 1}]")
    return _paired_costs(a, b, r, metric, dev)


def _paired_costs(a: wp.array, b: wp.array, rows: np.ndarray, metric: str, dev) -> np.ndarray:
    """`paired_costs` on signatures `prepare_signatures` has already checked and placed on ``dev``."""
    out = wp.empty(a.shape[0], dtype=wp.float64, device=dev)
    wp.launch(_paired, dim=a.shape[0], inputs=[a, b, wp.array(rows.astype(np.int64), dtype=wp.int64, device=dev),
                                               METRIC_CODES[metric], out], device=dev)
    return out.numpy()


def nearest_costs(S1, S2, *, metric: Literal["wks", "l2", "l1"] = "wks", device: str | None = None,
                  block: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """For each row of S1, the row of S2 with the smallest cost and that cost: ((N1,) int64, (N1,) float64),
    the row minima of `cost_matrix` ``(S1, S2)`` computed ``block`` rows at a time (memory O(block · N2)).

    ``metric="l2"`` finds the row through BLAS in float32 (`wpot.cost.nearest_rows`; several times faster than
    the kernel for long signatures such as LD-SIFT's) and then takes its cost from `paired_costs`, so the cost is
    `cost_matrix`'s entry exactly; a row within about 1e-7 of the signatures' squared norms of the nearest may
    be picked instead of it (a near tie); the other metrics through `cost_matrix`. Same validation as
    `cost_matrix`. For one S1 against many S2, `NearestCosts` prepares S1 once."""
    return NearestCosts(S1, metric=metric, device=device, block=block)(S2)


class NearestCosts:
    """`nearest_costs` from fixed signatures ``S1`` to each of many ``S2`` (a part against a library of wholes):
    ``S1`` is validated and brought to the device once, ``self(S2)`` is ``nearest_costs(S1, S2)``."""

    def __init__(self, S1, *, metric: Literal["wks", "l2", "l1"] = "wks", device: str | None = None,
                 block: int = 1024) -> None:
        self.device = resolve_device(device)
        self.metric = metric
        self.block = int(block)
        self._a = _prepared("S1", S1, metric, self.device)
        #: S1 in float32, for the BLAS search of metric "l2"
        self._a32 = np.asarray(self._a.numpy(), dtype=np.float32) if metric == "l2" else None

    def __call__(self, S2) -> tuple[np.ndarray, np.ndarray]:
        dev, a = self.device, self._a
        b = _prepared("S2", S2, self.metric, dev)
        _check_pair(a, b, ("S1", "S2"))
        if self.metric == "l2":
            idx = nearest_rows(self._a32, b.numpy(), dtype=np.float32, block=self.block)[0]
            return idx, _paired_costs(a, b, idx, self.metric, dev)
        x = a.numpy()
        idx = np.empty(len(x), dtype=np.int64)
        best = np.empty(len(x))
        for lo in range(0, len(x), self.block):
            c = cost_matrix(x[lo:lo + self.block], b, metric=self.metric, device=dev)
            j = np.argmin(c, axis=1)
            idx[lo:lo + len(c)] = j
            best[lo:lo + len(c)] = c[np.arange(len(c)), j]
        return idx, best


@wp.kernel
def _cost_row_sums(a: wp.array2d(dtype=wp.float64), b: wp.array2d(dtype=wp.float64), metric: int,
                   out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    s = wp.float64(0.0)
    for j in range(b.shape[0]):
        s += pair_cost(metric, a, i, b, j)
    out[i] = s


def cost_mean(S1, S2, *, metric: Literal["wks", "l2", "l1"] = "wks", device: str | None = None) -> float:
    """The mean of `cost_matrix` ``(S1, S2)`` over all N1 x N2 pairs, without forming the matrix.

    One Warp pass over the pairs, memory O((N1 + N2) D); the matrix-free transport uses it for the cost
    scale of the relative mass penalty (`wpot.comparison.cost_scale`). Inputs and errors as `cost_matrix`.
    """
    dev = resolve_device(device)
    a, b = prepare_signatures(S1, S2, metric, dev)
    rows = wp.empty(a.shape[0], dtype=wp.float64, device=dev)
    code = METRIC_CODES[metric]
    launch_rows(lambda lo, hi: wp.launch(_cost_row_sums, dim=hi - lo, inputs=[a[lo:hi], b, code, rows[lo:hi]],
                                         device=dev), a.shape[0], dev,
                cols=b.shape[0])
    return float(rows.numpy().sum()) / (float(a.shape[0]) * float(b.shape[0]))


#: bytes of one block of `nearest_rows`' distances (rows x M): a block that stays in the processor's cache is
#: searched faster than a larger one (the docs' Results page)
NEAREST_BLOCK_BYTES = 8 << 20


def nearest_rows(queries: np.ndarray, points: np.ndarray, *, dtype: type = np.float32, block: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """For each row of ``queries`` (N, k), the nearest row of ``points`` (M, k) in Euclidean distance.

    Returns ((N,) int64 indices, (N,) squared distances in ``dtype``). Brute force by blocks of ``block`` rows
    (default: as many as fit `NEAREST_BLOCK_BYTES` of distances, at least 16) of BLAS products,
    ``|q|² + |p|² − 2 q·p``; float32 by default (twice as fast; a k-d tree is slow in the 30-100 dimensions
    used here), the distances then good to about 1e-6 of the rows' squared norms. The product is one GEMM of
    ``[q, 1]`` with ``[−2p, |p|²]``, which adds ``|p|²`` on the way (no pass over the block). Blocks of two
    rows or more give the same result; their size changes only the time."""
    if block is None:
        block = max(16, NEAREST_BLOCK_BYTES // (np.dtype(dtype).itemsize * max(len(points), 1)))
    pts = np.ascontiguousarray(points, dtype=dtype)
    pp = np.einsum("ij,ij->i", pts, pts)
    right = np.empty((len(pts), pts.shape[1] + 1), dtype=dtype)
    np.multiply(pts, -2.0, out=right[:, :-1])
    right[:, -1] = pp
    qs = np.ascontiguousarray(queries, dtype=dtype)
    left = np.ones((min(len(qs), int(block)), qs.shape[1] + 1), dtype=dtype)
    out = np.empty(len(qs), dtype=np.int64)
    best = np.empty(len(qs), dtype=dtype)
    for s in range(0, len(qs), int(block)):
        q = qs[s:s + int(block)]
        lq = left[:len(q)]
        lq[:, :-1] = q
        d = lq @ right.T  # |p|^2 - 2 q.p; |q|^2, constant per row, added below
        j = np.argmin(d, axis=1)
        out[s:s + len(q)] = j
        best[s:s + len(q)] = np.maximum(d[np.arange(len(q)), j] + np.einsum("ij,ij->i", q, q), 0)
    return out, best
