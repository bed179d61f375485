"""A multilevel V-cycle around the device loop's FSAI preconditioner (`wpot.ot.anneal.resident`).

Why: at high beta the sparse Schur approximation P is nearly the weighted Laplacian of one connected graph
(its off-diagonal row sums nearly its diagonal, the graph many edges deep), so its inverse couples unknowns far
apart, and FSAI's factor (`wpot.ot.anneal.resident.FSAI_ROW` entries a row) is local. On Schur systems taken from
annealing runs, CG with FSAI alone needed several times the iterations it needed with P's exact factors, more so
as N grows, and reordering P first did not help; the V-cycle below comes close to the exact factors (the docs'
Results page).

Hierarchy, built on the host with each full build of the preconditioner from one read of P:

* level 0 is P, smoothed by FSAI;
* level k + 1 aggregates level k's unknowns: pairs of mutually strongest neighbours (strength
  |A_ij| / sqrt(A_ii A_jj)), every other unknown joining its strongest neighbour's pair, or alone; its matrix
  is the Galerkin product A_{k+1} = R_k^T A_k R_k (R_k the 0/1 aggregation matrix), smoothed by weighted
  Jacobi (`JACOBI_WEIGHT`);
* the first level with at most `coarse_size` unknowns is inverted densely, so a P that small is solved
  exactly. A level that shrinks by less than `MIN_SHRINK` ends the hierarchy without a dense level.

Refit (P's new values on its fixed pattern): every fine entry's coarse entry is fixed with the pattern, so the
coarse values, the Jacobi diagonals and the dense inverse are recomputed on the device: kernels only, no read.

Apply, z = M r, the symmetric V-cycle: on level k, pre-smooth x = S_k b, form t = b - A_k x, restrict
R_k^T t, solve the next level the same way (the dense level exactly), prolong and add, then post-smooth
x += S_k (b - A_k x). With the same symmetric smoother before and after, M is symmetric; the Galerkin coarse
correction is an A-orthogonal projection, so it never makes the preconditioned error larger in A's norm. Every
step is a kernel on preallocated arrays, so the cycle runs inside the captured CG loop.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp
import warp as wp
import warp.sparse as wsp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

__all__ = ["COARSE_SIZE", "FSAI_WEIGHT", "JACOBI_WEIGHT", "MAX_DENSE", "MIN_SHRINK", "Multilevel", "aggregate",
           "multilevel_bytes"]

#: the hierarchy's last level is the first with at most this many unknowns, inverted densely
COARSE_SIZE = 64
#: a level that keeps more than this share of the unknowns above it ends the hierarchy (no dense level)
MIN_SHRINK = 0.8
#: damping of the Jacobi smoother on the coarse levels
JACOBI_WEIGHT = 0.7
#: damping of the FSAI smoother on P: the V-cycle is SPD when the damped smoother F satisfies
#: 0 < eig(F P) < 2, and FSAI's eig(F P) came close to 2 on the systems of the module docstring (where 0.85
#: needed no more CG iterations than 1.0; the docs' Results page)
FSAI_WEIGHT = 0.85
#: the dense inverse's largest size (one device thread computes it, O(n^3)); coarse_size may not exceed it
MAX_DENSE = 256
#: the dense level's Cholesky pivots are kept above this share of their diagonal entry (P is SPD; this
#: guards rounding only)
PIVOT_FLOOR = 1e-12


@wp.kernel
def pack_csr(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
             values: wp.array(dtype=wp.float64), n: int, nnz: int, out: wp.array(dtype=wp.float64)):
    """offsets, columns and values in one float64 array (one read); integers below 2^53 are exact."""
    i = wp.tid()
    if i <= n:
        out[i] = wp.float64(offsets[i])
    if i < nnz:
        out[n + 1 + i] = wp.float64(columns[i])
        out[n + 1 + nnz + i] = values[i]


@wp.kernel
def galerkin_values(fine: wp.array(dtype=wp.float64), to_coarse: wp.array(dtype=wp.int32),
                    coarse: wp.array(dtype=wp.float64)):
    """coarse[to_coarse[e]] += fine[e] (``coarse`` zeroed): the values of R^T A R on its fixed pattern."""
    e = wp.tid()
    wp.atomic_add(coarse, to_coarse[e], fine[e])


@wp.kernel
def jacobi_diagonal(values: wp.array(dtype=wp.float64), diag_at: wp.array(dtype=wp.int32), weight: wp.float64,
                    dinv: wp.array(dtype=wp.float64)):
    i = wp.tid()
    dinv[i] = weight / values[diag_at[i]]


@wp.kernel
def residual(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
             values: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64), b: wp.array(dtype=wp.float64),
             t: wp.array(dtype=wp.float64)):
    """t = b - A x, A in CSR (scalar blocks)."""
    i = wp.tid()
    s = b[i]
    for e in range(offsets[i], offsets[i + 1]):
        s -= values[e] * x[columns[e]]
    t[i] = s


@wp.kernel
def jacobi(dinv: wp.array(dtype=wp.float64), r: wp.array(dtype=wp.float64), add: int,
           x: wp.array(dtype=wp.float64)):
    """x = dinv r (``add`` = 0) or x += dinv r."""
    i = wp.tid()
    v = dinv[i] * r[i]
    if add != 0:
        v += x[i]
    x[i] = v


@wp.kernel
def restrict(label: wp.array(dtype=wp.int32), t: wp.array(dtype=wp.float64), rc: wp.array(dtype=wp.float64)):
    """rc = R^T t (``rc`` zeroed)."""
    i = wp.tid()
    wp.atomic_add(rc, label[i], t[i])


@wp.kernel
def prolong(label: wp.array(dtype=wp.int32), xc: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64)):
    """x += R xc."""
    i = wp.tid()
    x[i] = x[i] + xc[label[i]]


@wp.kernel
def dense_inverse(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                  values: wp.array(dtype=wp.float64), m: int, L: wp.array2d(dtype=wp.float64),
                  inv: wp.array2d(dtype=wp.float64)):
    """inv = A^-1 for a small SPD A in CSR, by Cholesky (A = L L^T) and m triangular solve pairs; one thread."""
    for i in range(m):
        for j in range(m):
            L[i, j] = wp.float64(0.0)
    for i in range(m):
        for e in range(offsets[i], offsets[i + 1]):
            L[i, columns[e]] = L[i, columns[e]] + values[e]
    for j in range(m):
        a = L[j, j]
        s = a
        for k in range(j):
            s -= L[j, k] * L[j, k]
        floor = wp.float64(PIVOT_FLOOR) * wp.abs(a)
        if s <= floor:
            s = wp.max(floor, wp.float64(1e-300))
        d = wp.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, m):
            t = L[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    for c in range(m):
        for i in range(m):  # L y = e_c
            t = wp.float64(0.0)
            if i == c:
                t = wp.float64(1.0)
            for k in range(i):
                t -= L[i, k] * inv[k, c]
            inv[i, c] = t / L[i, i]
        for ii in range(m):  # L^T x = y
            i = m - 1 - ii
            t = inv[i, c]
            for k in range(i + 1, m):
                t -= L[k, i] * inv[k, c]
            inv[i, c] = t / L[i, i]


@wp.kernel
def dense_mv(inv: wp.array2d(dtype=wp.float64), r: wp.array(dtype=wp.float64), m: int,
             x: wp.array(dtype=wp.float64)):
    i = wp.tid()
    s = wp.float64(0.0)
    for j in range(m):
        s += inv[i, j] * r[j]
    x[i] = s


def aggregate(A: sp.csr_matrix) -> tuple[np.ndarray, int]:
    """(label of every unknown, number of aggregates): pairs of mutually strongest neighbours (strength
    |A_ij| / sqrt(A_ii A_jj)), every other unknown in its strongest neighbour's pair when that has one, else
    alone. ``A`` symmetric with a positive diagonal."""
    n = A.shape[0]
    C = A.tocoo()
    d = np.abs(A.diagonal())
    off = (C.row != C.col) & (C.data != 0)
    r, c = C.row[off], C.col[off]
    best = np.full(n, -1, dtype=np.int64)
    if r.size:
        s = np.abs(C.data[off]) / np.sqrt(d[r] * d[c])
        order = np.lexsort((-s, r))
        rr, cc = r[order], c[order]
        first = np.r_[True, rr[1:] != rr[:-1]]
        best[rr[first]] = cc[first]
    idx = np.arange(n)
    has = best >= 0
    mutual = has & (best[np.where(has, best, 0)] == idx)
    lead = mutual & (idx < best)
    label = np.full(n, -1, dtype=np.int64)
    m = int(lead.sum())
    label[lead] = np.arange(m)
    label[best[lead]] = label[lead]
    join = (label < 0) & has
    join &= label[np.where(join, best, 0)] >= 0
    label[join] = label[best[join]]
    rest = label < 0
    label[rest] = m + np.arange(int(rest.sum()))
    return label, m + int(rest.sum())


def _galerkin_pattern(offsets: np.ndarray, columns: np.ndarray, label: np.ndarray, m: int):
    """The CSR pattern of R^T A R for A's pattern (``offsets``, ``columns``) and the aggregation ``label``, and
    the coarse entry of every fine entry."""
    rows = np.repeat(np.arange(offsets.shape[0] - 1), np.diff(offsets))
    key = label[rows] * m + label[columns]
    uniq, to_coarse = np.unique(key, return_inverse=True)
    c_rows, c_cols = uniq // m, uniq % m
    return np.searchsorted(c_rows, np.arange(m + 1)), c_cols, to_coarse


def multilevel_bytes(n: int, nnz: int, coarse_size: int = COARSE_SIZE) -> int:
    """Device bytes of a `Multilevel` on an n x n P with ``nnz`` entries, assuming each level halves the one
    above (pairs; the measured levels shrink faster): a label and 3 vectors per unknown, a fine-to-coarse map
    per fine entry and a coarse pattern and values, and the dense level's two arrays."""
    f64, i32 = 8, 4
    levels = (i32 + 4 * f64) * 2 * n + (2 * i32 + f64) * 2 * nnz
    return levels + 2 * f64 * coarse_size ** 2 + f64 * (n + 1 + 2 * nnz)  # + the packed read of P


class _Level:
    """One level's CSR matrix on the device and its vectors: t the residual and, on a coarse level (P's level
    works on the caller's vectors and smooths with FSAI), b the right-hand side, x the solution and the Jacobi
    diagonal; ``label`` maps its unknowns to the next level's (None on the last)."""

    def __init__(self, offsets, columns, values, nnz: int, device, coarse: bool = True) -> None:
        self.n = offsets.shape[0] - 1
        self.nnz = nnz
        self.offsets, self.columns, self.values = offsets, columns, values
        z = lambda: wp.zeros(self.n, dtype=wp.float64, device=device)  # noqa: E731
        self.t = z()
        self.b, self.x, self.dinv = (z(), z(), z()) if coarse else (None, None, None)
        self.diag_at: wp.array | None = None
        self.label: wp.array | None = None
        self.to_coarse: wp.array | None = None  # each entry's place in the next level's values


class Multilevel:
    """The V-cycle preconditioner (see the module docstring) for ``P`` (a Warp BSR matrix, scalar blocks) with
    FSAI ``smoother`` on P itself. ``read`` brings a device array to the host (the caller counts it); the
    constructor reads P once. `refit` after P's values change on the same pattern; `apply` for z = M r."""

    def __init__(self, P: wsp.BsrMatrix, smoother, read: Callable[[wp.array], np.ndarray], *,
                 coarse_size: int = COARSE_SIZE) -> None:
        if not 1 <= coarse_size <= MAX_DENSE:
            raise ValueError(f"coarse_size must be in [1, {MAX_DENSE}], got {coarse_size}")
        d = P.device
        self.device = d
        self.F = smoother
        n = P.nrow
        cap = P.nnz  # an upper bound of the entry count, offsets[n]
        packed = wp.empty(n + 1 + 2 * cap, dtype=wp.float64, device=d)
        wp.launch(pack_csr, dim=max(n + 1, cap), inputs=[P.offsets, P.columns, P.values, n, cap, packed], device=d)
        host = read(packed)
        offsets = host[: n + 1].astype(np.int64)
        nnz = int(offsets[-1])
        columns = host[n + 1: n + 1 + nnz].astype(np.int64)
        values = host[n + 1 + cap: n + 1 + cap + nnz]
        self.levels = [_Level(P.offsets, P.columns, P.values, nnz, d, coarse=False)]
        self.dense: tuple[wp.array, wp.array] | None = None
        A = sp.csr_matrix((values, columns, offsets), shape=(n, n))
        while A.shape[0] > coarse_size:
            label, m = aggregate(A)
            if m > MIN_SHRINK * A.shape[0]:
                break
            c_offsets, c_columns, to_coarse = _galerkin_pattern(A.indptr, A.indices, label, m)
            lv = self.levels[-1]
            lv.label = wp.array(label.astype(np.int32), dtype=wp.int32, device=d)
            lv.to_coarse = wp.array(to_coarse.astype(np.int32), dtype=wp.int32, device=d)
            c_values = np.bincount(to_coarse, weights=A.data, minlength=c_columns.shape[0])
            A = sp.csr_matrix((c_values, c_columns, c_offsets), shape=(m, m))
            c_nnz = c_columns.shape[0]
            nxt = _Level(*(wp.array(a.astype(np.int32), dtype=wp.int32, device=d) for a in (c_offsets, c_columns)),
                         wp.zeros(c_nnz, dtype=wp.float64, device=d), c_nnz, d)
            rows = np.repeat(np.arange(m), np.diff(c_offsets))
            nxt.diag_at = wp.array(np.flatnonzero(rows == c_columns).astype(np.int32), dtype=wp.int32, device=d)
            self.levels.append(nxt)
        last = self.levels[-1]
        if last.n <= coarse_size:
            self.dense = (wp.zeros((last.n, last.n), dtype=wp.float64, device=d),
                          wp.zeros((last.n, last.n), dtype=wp.float64, device=d))
        self.refit()

    @property
    def n_levels(self) -> int:
        """Levels, P's included."""
        return len(self.levels)

    def refit(self) -> None:
        """The coarse values, Jacobi diagonals and dense inverse from P's current values (same pattern)."""
        d = self.device
        for lv, nxt in zip(self.levels, self.levels[1:]):
            nxt.values.zero_()
            wp.launch(galerkin_values, dim=lv.nnz, inputs=[lv.values, lv.to_coarse, nxt.values], device=d)
            wp.launch(jacobi_diagonal, dim=nxt.n, inputs=[nxt.values, nxt.diag_at, wp.float64(JACOBI_WEIGHT)],
                      outputs=[nxt.dinv], device=d)
        if self.dense is not None:
            last = self.levels[-1]
            wp.launch(dense_inverse, dim=1, inputs=[last.offsets, last.columns, last.values, last.n, *self.dense],
                      device=d)

    def apply(self, r: wp.array, z: wp.array) -> None:
        """z = M r (the V-cycle; kernels only)."""
        self._cycle(0, r, z)

    def _smooth(self, k: int, r: wp.array, x: wp.array, add: bool) -> None:
        if k == 0:
            self.F.matvec(r, x, x, FSAI_WEIGHT, 1.0 if add else 0.0)
        else:
            lv = self.levels[k]
            wp.launch(jacobi, dim=lv.n, inputs=[lv.dinv, r, int(add)], outputs=[x], device=self.device)

    def _cycle(self, k: int, b: wp.array, x: wp.array) -> None:
        d, lv = self.device, self.levels[k]
        if k == len(self.levels) - 1 and self.dense is not None:
            wp.launch(dense_mv, dim=lv.n, inputs=[self.dense[1], b, lv.n], outputs=[x], device=d)
            return
        self._smooth(k, b, x, False)
        if k + 1 < len(self.levels):  # the coarse correction (on the last level without a dense one: none)
            nxt = self.levels[k + 1]
            wp.launch(residual, dim=lv.n, inputs=[lv.offsets, lv.columns, lv.values, x, b], outputs=[lv.t],
                      device=d)
            nxt.b.zero_()
            wp.launch(restrict, dim=lv.n, inputs=[lv.label, lv.t], outputs=[nxt.b], device=d)
            self._cycle(k + 1, nxt.b, nxt.x)
            wp.launch(prolong, dim=lv.n, inputs=[lv.label, nxt.x], outputs=[x], device=d)
        wp.launch(residual, dim=lv.n, inputs=[lv.offsets, lv.columns, lv.values, x, b], outputs=[lv.t], device=d)
        self._smooth(k, lv.t, x, True)
