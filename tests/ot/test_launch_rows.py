"""`wpot._warp.launch_rows`: a CPU launch cut into row chunks on host threads gives the same outputs, bit for
bit, as one launch; chunks cover every row once; an error in a chunk reaches the caller."""
from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from wpot._warp import MIN_ENTRIES_PER_THREAD, cpu_threads, launch_rows
from wpot.cost import _cost, cost_matrix
from wpot.ot.exact.balanced import _PRICE, pass_outputs, cost_source
from wpot.ot.problem import prepare_cost


#: rows of 64 entries that make a few threads' worth of work
ROWS = 4 * MIN_ENTRIES_PER_THREAD // 64


def test_chunks_cover_every_row_once():
    seen = []
    launch_rows(lambda lo, hi: seen.append((lo, hi)), ROWS + 7, "cpu", cols=64, threads=3)
    seen.sort()
    assert len(seen) == 3 and seen[0][0] == 0 and seen[-1][1] == ROWS + 7
    assert all(a[1] == b[0] for a, b in zip(seen, seen[1:]))
    few = []
    launch_rows(lambda lo, hi: few.append((lo, hi)), ROWS, "cpu", cols=1, threads=8)
    assert few == [(0, ROWS)]  # too little work to split
    long = []
    launch_rows(lambda lo, hi: long.append((lo, hi)), 5, "cpu", cols=10**6, threads=8)
    assert sorted(long) == [(i, i + 1) for i in range(5)]  # long rows: at most a row a thread
    assert cpu_threads() >= 1


def test_an_error_in_a_chunk_reaches_the_caller():
    def boom(lo, hi):
        if lo > 0:
            raise RuntimeError(f"chunk {lo}")
    with pytest.raises(RuntimeError, match="chunk"):
        launch_rows(boom, ROWS, "cpu", cols=64, threads=2)


def test_split_cost_matrix_equals_one_launch():
    rng = np.random.default_rng(0)
    n = 3 * MIN_ENTRIES_PER_THREAD // 90 + 5
    a = wp.array(rng.random((n, 16)) + 0.01, dtype=wp.float64, device="cpu")
    b = wp.array(rng.random((90, 16)) + 0.01, dtype=wp.float64, device="cpu")
    for code in (0, 1, 2):
        one = wp.empty((n, 90), dtype=wp.float64, device="cpu")
        wp.launch(_cost, dim=one.shape, inputs=[a, b, code, one], device="cpu")
        split = wp.empty((n, 90), dtype=wp.float64, device="cpu")
        launch_rows(lambda lo, hi: wp.launch(_cost, dim=(hi - lo, 90), inputs=[a[lo:hi], b, code, split[lo:hi]],
                                             device="cpu"), n, "cpu", cols=90, threads=3)
        np.testing.assert_array_equal(split.numpy(), one.numpy())
    np.testing.assert_array_equal(cost_matrix(a, b, metric="l1", device="cpu"), one.numpy())  # code 2


def test_split_pricing_pass_equals_one_launch():
    rng = np.random.default_rng(1)
    n1, n2, m = 4 * MIN_ENTRIES_PER_THREAD // 70 + 3, 70, 4
    cost = prepare_cost(rng.random((n1, n2)), "cpu")
    src = cost_source(cost)
    u = wp.array(rng.random(n1) * 0.2, dtype=wp.float64, device="cpu")
    v = wp.array(rng.random(n2) * 0.2, dtype=wp.float64, device="cpu")
    outs = []
    for threads in (1, 3):
        o = pass_outputs(n1, m, "cpu")
        launch_rows(lambda lo, hi: wp.launch(_PRICE[src._cls], dim=hi - lo, device="cpu", inputs=[
            src, lo, n2, u, v, wp.float64(0.05), m, *o]), n1, "cpu", cols=n2, threads=threads)
        outs.append([x.numpy() for x in o])
    for x, y in zip(*outs):
        np.testing.assert_array_equal(x, y)
    assert math.isfinite(outs[0][2].min())
