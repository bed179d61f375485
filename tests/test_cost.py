"""Warp cost matrices against NumPy references, on every available device."""
from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from wpot.cost import cost_matrix, nearest_costs, paired_costs


def _ref(a: np.ndarray, b: np.ndarray, metric: str) -> np.ndarray:
    d = a[:, None, :] - b[None, :, :]
    if metric == "wks":
        s = a[:, None, :] + b[None, :, :]
        return np.abs(np.divide(d, s, out=np.zeros_like(d), where=s != 0)).sum(-1)
    if metric == "l2":
        return np.sqrt((d * d).sum(-1))
    return np.abs(d).sum(-1)


@pytest.fixture(scope="module")
def sigs():
    rng = np.random.default_rng(7)
    a = rng.random((37, 23)) ** 3  # nonnegative, spread over decades like WKS values
    b = rng.random((29, 23)) ** 3
    a[0] = 0.0  # a whole zero signature,
    b[1] = 0.0
    a[2, :5] = 0.0  # and zero entries matched against zeros (the a + b = 0 guard)
    b[3, :5] = 0.0
    return a, b


@pytest.mark.parametrize("metric", ["wks", "l2", "l1"])
def test_agrees_with_numpy_reference(sigs, metric, device):
    a, b = sigs
    c = cost_matrix(a, b, metric=metric, device=device)
    assert isinstance(c, np.ndarray) and c.dtype == np.float64 and c.shape == (37, 29)
    np.testing.assert_allclose(c, _ref(a, b, metric), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("metric", ["wks", "l2", "l1"])
def test_paired_costs_are_the_matrix_entries_a_map_picks(sigs, metric, device):
    a, b = sigs
    rows = np.random.default_rng(3).integers(0, len(b), size=len(a))
    rows[2], rows[0] = 3, 1  # the zero guards: zeros against zeros, and a zero row against a zero row
    got = paired_costs(a, b, rows, metric=metric, device=device)
    np.testing.assert_array_equal(got, cost_matrix(a, b, metric=metric, device=device)[np.arange(len(a)), rows])
    with pytest.raises(ValueError, match="rows_2 must be"):
        paired_costs(a, b, rows[:-1], metric=metric, device=device)
    with pytest.raises(ValueError, match="outside"):
        paired_costs(a, b, np.full(len(a), len(b)), metric=metric, device=device)


@pytest.mark.parametrize("metric", ["wks", "l2", "l1"])
def test_nearest_costs_are_the_row_minima(sigs, metric, device):
    a, b = sigs
    c = cost_matrix(a, b, metric=metric, device=device)
    for block in (5, 1024):  # several blocks and one
        idx, best = nearest_costs(a, b, metric=metric, device=device, block=block)
        np.testing.assert_allclose(best, c.min(axis=1), rtol=1e-7, atol=1e-7)
        np.testing.assert_allclose(c[np.arange(len(a)), idx], c.min(axis=1), rtol=1e-7, atol=1e-7)
    with pytest.raises(ValueError, match="same signature length"):
        nearest_costs(a, b[:, :5], metric=metric, device=device)


def test_wks_cost_properties(sigs, device):
    a, _ = sigs
    c = cost_matrix(a, a, metric="wks", device=device)
    np.testing.assert_allclose(np.diag(c), 0.0, atol=0)  # d(x, x) = 0, also for zero entries
    np.testing.assert_allclose(c, c.T, rtol=1e-15)  # symmetric
    assert c.max() <= a.shape[1]  # each term of Eq. 29 is at most 1 for nonnegative inputs
    # scale invariance of Eq. 29: d(λa, λb) = d(a, b)
    np.testing.assert_allclose(cost_matrix(3.7 * a, 3.7 * a, device=device), c, rtol=1e-12, atol=1e-14)
    # a zero signature against a nonzero one costs one per nonzero entry
    assert c[0, 1] == pytest.approx(np.count_nonzero(a[1]))


def test_warp_output_on_device(sigs, device):
    a, b = sigs
    c = cost_matrix(a, b, metric="l2", device=device, out="warp")
    assert isinstance(c, wp.array) and c.dtype == wp.float64 and c.shape == (37, 29)
    assert c.device == wp.get_device(device)
    # warp arrays in: no copy round trip needed, same result
    wa = wp.array(a, dtype=wp.float64, device=device)
    wb = wp.array(b, dtype=wp.float64, device=device)
    np.testing.assert_array_equal(cost_matrix(wa, wb, metric="l2", device=device), c.numpy())


def test_bad_input(sigs, device):
    a, b = sigs
    with pytest.raises(ValueError, match="metric must be one of"):
        cost_matrix(a, b, metric="cosine", device=device)
    with pytest.raises(ValueError, match="same signature length"):
        cost_matrix(a, b[:, :5], device=device)
    with pytest.raises(ValueError, match="2-D"):
        cost_matrix(a[0], b, device=device)
    bad = a.copy()
    bad[4, 2] = np.nan
    with pytest.raises(ValueError, match="S1 contains NaN"):
        cost_matrix(bad, b, metric="l2", device=device)
    bad[4, 2] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        cost_matrix(b, bad, metric="l1", device=device)
    with pytest.raises(ValueError, match="negative entries"):
        cost_matrix(a - 0.5, b, metric="wks", device=device)
    cost_matrix(a - 0.5, b, metric="l2", device=device)  # negative values are fine for l2
    with pytest.raises(ValueError, match="empty"):
        cost_matrix(a[:0], b, device=device)
    with pytest.raises(ValueError, match="out must be"):
        cost_matrix(a, b, device=device, out="torch")
    with pytest.raises(ValueError, match="2-D float64"):
        cost_matrix(wp.array(a.astype(np.float32), dtype=wp.float32, device=device), b, device=device)


def test_wrong_device_is_named():
    wp.init()
    devices = [str(d) for d in wp.get_devices()]
    if len(devices) < 2:
        pytest.skip("needs two Warp devices (cpu and cuda) to place inputs on the wrong one")
    a = wp.zeros((3, 4), dtype=wp.float64, device="cpu")
    with pytest.raises(ValueError, match="expected cuda"):
        cost_matrix(a, np.zeros((2, 4)), device="cuda")


def test_nearest_rows_agrees_with_scipy_and_does_not_depend_on_the_block():
    from scipy.spatial.distance import cdist

    from wpot.cost import nearest_rows

    rng = np.random.default_rng(3)
    q, p = rng.standard_normal((300, 40)), rng.standard_normal((700, 40))
    d = cdist(q, p, "sqeuclidean")
    idx, best = nearest_rows(q, p, dtype=np.float64)
    np.testing.assert_array_equal(idx, d.argmin(axis=1))
    np.testing.assert_allclose(best, d.min(axis=1), rtol=1e-9)
    # float32: the same rows, any block; the distances to float32 rounding (BLAS may take another kernel for a
    # block of 2 rows than for 300, and round the last bit otherwise)
    got = [nearest_rows(q, p, block=b) for b in (None, 2, 7, 64, 1000)]
    for i, b in got[1:]:
        np.testing.assert_array_equal(i, got[0][0])
        np.testing.assert_allclose(b, got[0][1], rtol=1e-6)
    assert np.mean(got[0][0] == idx) > 0.99  # float32 differs from float64 only at near ties
