"""The device loop's multilevel preconditioner (`wpot.ot.anneal.multilevel`): its aggregation, its Galerkin levels
(built and refitted on the device) against scipy, its dense level against numpy, and the V-cycle's symmetry,
definiteness and effect on CG against FSAI alone."""
import numpy as np
import pytest
import scipy.sparse as sp
import warp as wp
import warp.sparse as wsp
from warp.optim.linear import FSAI

from wpot.ot.anneal import multilevel as ml
from wpot.ot.anneal.linear import pcg
from wpot.ot.anneal.resident import FSAI_ROW


def _bsr(A: sp.csr_matrix) -> wsp.BsrMatrix:
    C = A.tocoo()
    B = wsp.bsr_zeros(A.shape[0], A.shape[1], wp.float64, device="cpu")
    wsp.bsr_set_from_triplets(B, *(wp.array(a, device="cpu") for a in (C.row.astype(np.int32),
                                                                        C.col.astype(np.int32), C.data)))
    return B


def _fsai(B: wsp.BsrMatrix) -> FSAI:
    F = FSAI(B, max_row_size=FSAI_ROW, reuse_pattern=True, regularize_refit=True, validate_topology=False,
             defer_pattern=True)
    F.update(B)
    return F


def _tree_laplacian(n: int, seed: int, shift: float = 1e-4) -> sp.csr_matrix:
    """A weighted random tree's Laplacian plus a few random extra edges and a small diagonal: the near-singular,
    far-coupled kind of matrix P is at high beta."""
    rng = np.random.default_rng(seed)
    parent = np.array([rng.integers(max(0, k - 30), k) for k in range(1, n)])  # deep: each node near its parent
    rows = np.r_[np.arange(1, n), rng.integers(0, n, n // 10)]
    cols = np.r_[parent, rng.integers(0, n, n // 10)]
    keep = rows != cols
    W = sp.coo_matrix((rng.uniform(0.1, 1.0, keep.sum()), (rows[keep], cols[keep])), shape=(n, n)).tocsr()
    W = W + W.T
    return (sp.diags(np.asarray(W.sum(1)).ravel() * (1 + shift)) - W).tocsr()


def _apply(M: ml.Multilevel, r: np.ndarray) -> np.ndarray:
    rr = wp.array(r, dtype=wp.float64, device="cpu")
    z = wp.zeros(r.shape[0], dtype=wp.float64, device="cpu")
    M.apply(rr, z)
    return z.numpy().copy()


def test_aggregation_pairs_mutually_strongest_neighbours():
    # a path 0-1-2-3-4 with strengths 3, 1, 3, 0.5 and a hub 5 tied to 0 only weakly
    n = 6
    e = [(0, 1, 3.0), (1, 2, 1.0), (2, 3, 3.0), (3, 4, 0.5), (0, 5, 0.1)]
    W = sp.coo_matrix(([w for *_, w in e], ([i for i, *_ in e], [j for _, j, _ in e])), shape=(n, n)).tocsr()
    W = W + W.T
    A = (sp.diags(np.asarray(W.sum(1)).ravel() + 1.0) - W).tocsr()
    label, m = ml.aggregate(A)
    assert m == 2
    assert label[0] == label[1] != label[2] == label[3]  # the two strong pairs
    assert label[4] == label[3] and label[5] == label[0]  # the others join their strongest neighbour's pair
    # no off-diagonal entries: every unknown alone
    label, m = ml.aggregate(sp.identity(4, format="csr"))
    assert m == 4 and sorted(label) == [0, 1, 2, 3]


def test_levels_are_galerkin_products_after_build_and_refit():
    A = _tree_laplacian(400, seed=1)
    B = _bsr(A)
    M = ml.Multilevel(B, _fsai(B), lambda a: a.numpy())
    assert M.n_levels >= 3 and M.dense is not None and M.levels[-1].n <= ml.COARSE_SIZE

    def check(A):
        cur = A
        for lv, nxt in zip(M.levels, M.levels[1:]):
            label = lv.label.numpy()
            R = sp.csr_matrix((np.ones(lv.n), (np.arange(lv.n), label)), shape=(lv.n, nxt.n))
            cur = (R.T @ cur @ R).tocsr()
            got = sp.csr_matrix((nxt.values.numpy(), nxt.columns.numpy(), nxt.offsets.numpy()), shape=cur.shape)
            np.testing.assert_allclose(got.toarray(), cur.toarray(), rtol=1e-12, atol=1e-14 * abs(cur).max())
            np.testing.assert_allclose(nxt.dinv.numpy(), ml.JACOBI_WEIGHT / cur.diagonal(), rtol=1e-12)
        np.testing.assert_allclose(M.dense[1].numpy(), np.linalg.inv(cur.toarray()), rtol=1e-8,
                                   atol=1e-10 * abs(np.linalg.inv(cur.toarray())).max())

    check(A)
    # new values on the same pattern: refit on the device, no new aggregation
    A2 = A.copy()
    A2.data = A2.data * np.random.default_rng(2).uniform(0.5, 2.0, A2.nnz)
    A2 = ((A2 + A2.T) / 2).tocsr()
    A2 = A2 + sp.diags(abs(A2).sum(1).A.ravel())  # diagonally dominant again (same pattern: the diagonal exists)
    A2.sort_indices()
    B.values.assign(sp.csr_matrix(A2).data)  # B's pattern is A's, in the same sorted CSR order
    M.refit()
    check(A2)


def test_a_small_p_is_solved_exactly():
    A = _tree_laplacian(50, seed=3)
    B = _bsr(A)
    M = ml.Multilevel(B, _fsai(B), lambda a: a.numpy())
    assert M.n_levels == 1 and M.dense is not None
    r = np.random.default_rng(4).standard_normal(50)
    np.testing.assert_allclose(_apply(M, r), np.linalg.solve(A.toarray(), r), rtol=1e-9)


def test_the_v_cycle_is_symmetric_positive_definite_and_beats_fsai_on_far_couplings():
    n = 1500
    A = _tree_laplacian(n, seed=5)
    B = _bsr(A)
    F = _fsai(B)
    M = ml.Multilevel(B, F, lambda a: a.numpy())
    assert M.n_levels >= 4
    rng = np.random.default_rng(6)
    U = rng.standard_normal((n, 4))
    MU = np.column_stack([_apply(M, u) for u in U.T])
    G = U.T @ MU  # the Gram matrix of M on 4 random vectors: symmetric, positive definite
    np.testing.assert_allclose(G, G.T, rtol=1e-10)
    assert np.all(np.linalg.eigvalsh((G + G.T) / 2) > 0)
    b = rng.standard_normal(n)

    def fsai(r):
        rr = wp.array(r, dtype=wp.float64, device="cpu")
        z = wp.zeros(n, dtype=wp.float64, device="cpu")
        F.matvec(rr, z, z, 1.0, 0.0)
        return z.numpy().copy()

    _, it_f = pcg(lambda v: A @ v, b, fsai, rtol=1e-8, max_iter=5000)
    x, it_m = pcg(lambda v: A @ v, b, lambda r: _apply(M, r), rtol=1e-8, max_iter=5000)
    assert it_m.converged and it_f.converged
    np.testing.assert_allclose(A @ x, b, atol=1e-7 * np.linalg.norm(b))
    assert it_m.iterations * 2 < it_f.iterations  # a deep tree: FSAI's local factor needs 3x as many here


def test_coarse_size_is_validated():
    B = _bsr(_tree_laplacian(20, seed=7))
    with pytest.raises(ValueError, match="coarse_size"):
        ml.Multilevel(B, _fsai(B), lambda a: a.numpy(), coarse_size=ml.MAX_DENSE + 1)


def test_a_p_that_does_not_coarsen_gets_two_smoothing_steps():
    # no off-diagonal entries: no aggregate forms, so the hierarchy is P alone, above coarse_size, without a
    # dense level; the cycle is pre- and post-smoothing with the damped FSAI (exact for a diagonal):
    # M = 2 w F - w^2 F P F = (2 w - w^2) P^-1
    d = np.random.default_rng(8).uniform(1.0, 3.0, 100)
    B = _bsr(sp.diags(d).tocsr())
    M = ml.Multilevel(B, _fsai(B), lambda a: a.numpy())
    assert M.n_levels == 1 and M.dense is None
    r = np.random.default_rng(9).standard_normal(100)
    w = ml.FSAI_WEIGHT
    np.testing.assert_allclose(_apply(M, r), (2 * w - w * w) * r / d, rtol=1e-12)
