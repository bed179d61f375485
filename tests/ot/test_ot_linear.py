"""The sparse Schur preconditioner and PCG of `wpot.ot.anneal.linear`."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from wpot.ot.anneal import linear


def _laplacian(n: int, edges: list[tuple[int, int, float]]) -> np.ndarray:
    L = np.zeros((n, n))
    for i, j, w in edges:
        L[i, i] += w
        L[j, j] += w
        L[i, j] -= w
        L[j, i] -= w
    return L


def test_preconditioner_survives_a_sparse_schur_approximation_with_a_zero_row():
    # S: a connected graph Laplacian (balanced: singular along the constants, gauge dy[-1] = 0). Column 0
    # couples to the rest only weakly, and the sparse approximation P keeps none of its couplings: P's row 0
    # is zero and SuperLU says "Factor is exactly singular" (as on a cell-pooled TOSCA pair, where at high
    # beta a column's rows all pivot on it and its exact Schur diagonal is 0).
    rng = np.random.default_rng(0)
    n = 12
    strong = [(i, j, rng.uniform(1, 2)) for i in range(1, n) for j in range(i + 1, n)]
    weak = [(0, 3, 1e-3), (0, 7, 2e-3)]
    S = _laplacian(n, strong + weak)
    P = sp.csc_matrix(_laplacian(n, strong))
    M = linear.SchurPreconditioner(P, np.zeros(n), True)
    assert M.shifted
    rhs = rng.normal(size=n)
    rhs -= rhs.mean()  # consistent: in the range of S
    z = M(rhs)
    assert np.all(np.isfinite(z)) and z[-1] == 0.0
    x, info = linear.pcg(lambda v: S @ v, rhs, M, rtol=1e-10, max_iter=200, gauge=True)
    assert info.converged
    exact = np.zeros(n)
    exact[:-1] = np.linalg.solve(S[:-1, :-1], rhs[:-1])
    np.testing.assert_allclose(x, exact, rtol=1e-7, atol=1e-8 * np.abs(exact).max())
    # a connected P is factorized as it is
    assert not linear.SchurPreconditioner(sp.csc_matrix(S), np.zeros(n), True).shifted
