"""The relative mass penalty of partial transport (wpot.comparison.solver_mass_penalty): its formula, closed-form
limits, and that the regime it picks does not depend on the cost's scale or on the number of points."""
from __future__ import annotations

import numpy as np
import pytest

from wpot import ot
from wpot.comparison import (
    DEFAULT_MASS_PENALTY,
    PENALTY_SCALES,
    Comparer,
    Points,
    cost_scale,
    solver_mass_penalty,
)


def _solve(C, kappa, scale="relative"):
    return ot.solve_partial(C, mass_penalty=solver_mass_penalty(C, kappa, penalty_scale=scale), device="cpu")


def _line_problem(n: int, part: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """1-D signatures: A samples [0, part], B samples [0, 1], both with n points; cost |x - y|."""
    b = (np.arange(n) + 0.5) / n
    a = part * b
    return np.abs(a[:, None] - b[None, :]), b < part


# ------------------------------------------------------------------------------------------ formula
def test_factor_formula_and_paper_identity():
    rng = np.random.default_rng(0)
    C = rng.random((12, 27)) * 5.0
    # relative: kappa * mean(C) / sqrt(N1 N2), computed independently here
    assert solver_mass_penalty(C, 0.3) == pytest.approx(0.3 * C.sum() / C.size / np.sqrt(12 * 27), rel=1e-14)
    assert cost_scale(C) == pytest.approx(C.mean(), rel=1e-14)
    # paper: the factor is handed over unchanged, so mass_penalty=1 is alpha = 1/rho^2
    assert solver_mass_penalty(C, 1.0, penalty_scale="paper") == 1.0
    assert solver_mass_penalty(C, 0.7, penalty_scale="paper") == 0.7
    assert set(PENALTY_SCALES) == {"relative", "paper"}


def test_bad_input():
    C = np.ones((3, 4))
    with pytest.raises(ValueError, match="penalty_scale.*'absolute'"):
        solver_mass_penalty(C, 1.0, penalty_scale="absolute")
    with pytest.raises(ValueError, match="mass_penalty.*-1"):
        solver_mass_penalty(C, -1.0)
    with pytest.raises(ValueError, match="positive mean"):
        solver_mass_penalty(np.zeros((3, 4)), 1.0)
    assert solver_mass_penalty(np.zeros((3, 4)), 2.0, penalty_scale="paper") == 2.0
    with pytest.raises(ValueError, match="penalty_scale"):
        Comparer(transport="partial", penalty_scale="Paper")


# ------------------------------------------------------------------------------------ closed forms
@pytest.mark.parametrize("kappa", [1.0, 0.5, 0.1])
def test_block_closed_form(kappa):
    """A fraction f of B costs 0 to every point of A, the rest costs 1: B's fraction receives
    q = min(1, f + f/(2 kappa)) of the mass, A stays uniform (derivation in solver_mass_penalty)."""
    n, f = 40, 0.25
    C = np.ones((n, n))
    C[:, : int(f * n)] = 0.0
    r = _solve(C, kappa)
    assert r.converged
    q = min(1.0, f + f / (2 * kappa))
    assert r.mass2[: int(f * n)].sum() == pytest.approx(q, abs=1e-5)
    np.testing.assert_allclose(r.mass1, 1.0 / n, rtol=1e-5)
    # and the same holds whatever the cost level c (q does not depend on c)
    r7 = _solve(7.0 * C, kappa)
    assert r7.mass2[: int(f * n)].sum() == pytest.approx(q, abs=1e-5)


def test_limits_balanced_and_collapse():
    C, inside = _line_problem(30)
    big = _solve(C, 1e4)  # kappa -> infinity: balanced with the reference (uniform) masses
    np.testing.assert_allclose(big.mass2, 1 / 30, atol=2e-4 / 30 * 30)
    small = _solve(C, 1e-3)  # kappa -> 0: the mass goes to the cheap part of B only
    assert small.mass2[inside].sum() > 0.99


# ---------------------------------------------------------------------------------------- invariances
@pytest.mark.parametrize("lam", [1e-3, 250.0])
def test_relative_penalty_is_invariant_to_cost_scaling(lam):
    rng = np.random.default_rng(1)
    C = rng.random((25, 30))
    r0, r1 = _solve(C, 0.1), _solve(lam * C, 0.1)
    np.testing.assert_allclose(r1.mass1, r0.mass1, atol=1e-9)
    np.testing.assert_allclose(r1.mass2, r0.mass2, atol=1e-9)
    assert r1.objective == pytest.approx(lam * r0.objective, rel=1e-8)
    # the paper's fixed alpha is not: the same factor on scaled costs is another trade-off
    p0, p1 = _solve(C, 1e-3, "paper"), _solve(lam * C, 1e-3, "paper")
    assert np.abs(p1.mass2 - p0.mass2).sum() > 0.05


def test_relative_penalty_is_invariant_to_duplicating_points():
    """Every point of A and of B duplicated d times: the same plan up to the splitting, the same objective."""
    rng = np.random.default_rng(2)
    C = rng.random((15, 15))
    d = 3
    Cd = np.repeat(np.repeat(C, d, axis=0), d, axis=1)
    r, rd = _solve(C, 0.05), _solve(Cd, 0.05)
    np.testing.assert_allclose(rd.mass1.reshape(-1, d).sum(1), r.mass1, atol=1e-5)
    np.testing.assert_allclose(rd.mass2.reshape(-1, d).sum(1), r.mass2, atol=1e-5)
    assert rd.objective == pytest.approx(r.objective, rel=1e-5)
    # with a fixed factor the penalty grows with N and pushes the duplicated problem toward balanced
    a = solver_mass_penalty(C, 0.05)
    p, pd = ot.solve_partial(C, mass_penalty=a, device="cpu"), ot.solve_partial(Cd, mass_penalty=a, device="cpu")
    assert np.abs(pd.mass2.reshape(-1, d).sum(1) - p.mass2).sum() > 0.05


def test_relative_penalty_picks_the_same_regime_at_another_sampling():
    """A samples a third of B's range: the mass B's matching part receives hardly changes from 30 to 90
    points with the relative penalty, but does with a fixed factor."""
    (c30, in30), (c90, in90) = _line_problem(30), _line_problem(90)
    kappa = 0.1
    q30 = _solve(c30, kappa).mass2[in30].sum()
    q90 = _solve(c90, kappa).mass2[in90].sum()
    assert 0.7 < q30 < 0.95  # partial, neither balanced (0.3) nor collapsed (1)
    assert q90 == pytest.approx(q30, abs=0.02)
    a = solver_mass_penalty(c30, kappa)  # the same trade-off at 30 points, as a fixed factor
    f90 = ot.solve_partial(c90, mass_penalty=a, device="cpu").mass2[in90].sum()
    assert abs(f90 - q30) > 0.1


# -------------------------------------------------------------------------------------------- Comparer
def test_comparer_records_and_applies_the_penalty():
    c = Comparer(transport="partial", device="cpu", cache_dir=False)
    assert c.mass_penalty == DEFAULT_MASS_PENALTY and c.penalty_scale == "relative"
    assert c.params()["mass_penalty"] == DEFAULT_MASS_PENALTY and c.params()["penalty_scale"] == "relative"
    p = c.with_options(mass_penalty=1.0, penalty_scale="paper")
    assert p.params()["penalty_scale"] == "paper" and p.params()["mass_penalty"] == 1.0
    assert p.params() != c.params()  # a pipeline run keyed on params() tells them apart
    assert p.source.signature_cache is c.source.signature_cache and p.sampler.samples is c.sampler.samples
    assert "penalty_scale" not in Comparer(transport="balanced", device="cpu", cache_dir=False).params()
    with pytest.raises(ValueError, match="unknown Comparer options"):
        c.with_options(mass_penalt=1.0)

    sa = np.random.default_rng(3).random((20, 4))
    sb = np.random.default_rng(4).random((30, 4))
    for comp, expect in ((c, lambda C: DEFAULT_MASS_PENALTY * C.mean() / np.sqrt(600)), (p, lambda C: 1.0)):
        problem = comp.transport_problem(Points(sa, None, None), Points(sb, None, None))
        C, a = np.asarray(problem.cost), problem.mass_penalty
        assert a == pytest.approx(expect(C), rel=1e-12)
