"""Comparison.confidence, .received and .region: closed cases and consistency with the plan."""
from __future__ import annotations

import numpy as np
import pytest

import wpot


def test_a_shape_against_itself_is_matched_whole_and_with_full_confidence():
    m = wpot.example_mesh(300)
    c = wpot.compare(m, m, max_vertices=None, n_eigen=60, n_energies=40)
    np.testing.assert_array_equal(c.correspondence, np.arange(300))
    assert c.confidence.shape == (300,) and c.received.shape == (300,)
    assert c.confidence.min() > 0.99  # every sample goes whole to itself
    np.testing.assert_allclose(c.received, 1.0, rtol=1e-6)  # balanced: every sample receives its mass
    assert c.region().all()


def test_confidence_and_received_follow_the_plan():
    ep = wpot.example_partial(seed=0)
    c = wpot.compare(ep.part, ep.full, transport="partial", max_vertices=150, n_eigen=60, n_energies=40)
    res = c.result
    plan = np.asarray(res.plan)
    na, nb = plan.shape
    # uniform sample masses without pooling: the reference mass is the plan's total over the sample count
    total = plan.sum()
    conf = np.minimum(plan.max(axis=1) / (total / na), 1.0)
    recv = plan.sum(axis=0) / (total / nb)
    np.testing.assert_allclose(c.confidence, c.sample_a.extend(conf), rtol=1e-9)
    np.testing.assert_allclose(c.received, c.sample_b.extend(recv), rtol=1e-9)
    assert 0.0 <= c.confidence.min() and c.confidence.max() <= 1.0
    # partial transport leaves part of the whole unmatched: the region is a proper, non-empty subset
    r = c.region()
    assert r.dtype == bool and r.shape == (ep.full.n_vertices,) and 0 < r.sum() < r.size
    assert c.region(0.0).all() and not c.region(1e9).any()
    assert (c.region(0.9) <= c.region(0.1)).all()  # nested
    with pytest.raises(ValueError, match="threshold"):
        c.region(-1.0)
