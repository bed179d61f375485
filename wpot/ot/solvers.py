"""The OT solvers behind one interface (`TransportSolver`), their registry (`SOLVERS`, `make_solver`) and
the function forms `solve_balanced` / `solve_partial`.

- "anneal": Algorithm 1 from beta0 (balanced or partial, stored or matrix-free cost).
- "ipm": a primal-dual interior-point start up to the first grid beta whose gap bound is <= 1e-3 U, then
  Algorithm 1 (balanced transport with a stored cost only; `wpot.ot.anneal.ipm`).
- "exact": the limit beta = infinity itself by column generation: the transport LP (balanced; `wpot.ot.exact.balanced`)
  or the chi^2 QP (partial; `wpot.ot.exact.partial`), certified over every entry.
- "auto": "exact", balanced or partial.

The annealing solvers record D(beta), the paper's distance along beta (every recorded beta is that beta's saddle
point); "exact" records beta = infinity only, and is much faster than the annealing, for partial transport
the most (`benchmarks/ot_speed.py`, `benchmarks/table6.py`; the docs' Results page).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Mapping, Protocol, runtime_checkable

from wpot._validate import integer_at_least, positive_finite
from wpot.ot import kernels as K
from wpot.ot.anneal.balanced import solve_balanced_problem
from wpot.ot.exact import qp_bytes, solve_exact_batch, solve_exact_problem, support_bytes
from wpot.ot.options import SolverOptions
from wpot.ot.anneal.partial import solve_partial_problem
from wpot.ot.problem import TransportProblem
from wpot.ot.anneal.resident import device_loop_bytes
from wpot.ot.result import BetaStep, OTResult

__all__ = ["SOLVERS", "AnnealSolver", "AutoSolver", "ExactSolver", "InteriorPointSolver", "TransportSolver",
           "make_solver", "solve_balanced", "solve_batch", "solve_partial"]

_F64 = 8
_I32 = 4
#: host bytes per point and per ``topk`` weight of the sparse preconditioner's assembly (the top-k lists'
#: host copies, the pair and column edges, the COO, CSR and CSC forms of the sparse Schur approximation)
_HOST_BYTES_PER_POINT_TOPK = 128
#: host bytes per point of the problem's own vectors and the Newton and CG work vectors (masses, oriented
#: copies, residuals, the Schur data, the CG recurrences: about 40 float64 vectors)
_HOST_BYTES_PER_POINT = 64 * _F64
#: the preconditioner's LU factor (SuperLU, `wpot.ot.anneal.linear`) is the one term whose size depends on the
#: cost's structure: its fill grows with the intrinsic dimension of the points (nonzeros per column, the
#: largest over a solve at topk = 4, from points on a 2-D manifold, as surfaces' signatures are, to points
#: filling 6-D to 100-D: the docs' Results page). The count follows the fastest growth seen, N^1.85 nonzeros,
#: capped by the dense factor's N^2
_FACTOR_EXPONENT = 1.85
#: bytes per nonzero of the LU factor (its values and indices, and SuperLU's growing work space)
_FACTOR_BYTES_PER_NONZERO = 16
#: host bytes per entry of ``OTResult.plan_top`` (the device values and indices, their scaled / int64
#: copies and the CSR arrays)
_PLAN_TOP_BYTES_PER_ENTRY = 40


@runtime_checkable
class TransportSolver(Protocol):
    """A way to solve a `TransportProblem` into an `OTResult` (see `SOLVERS`)."""

    name: ClassVar[str]
    options: SolverOptions

    def solve(self, problem: TransportProblem, *, on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
        """The `OTResult` of ``problem`` (costs in its units; ``converged`` False with a RuntimeWarning when a
        tolerance was not met). ``on_beta`` is called with each solved beta's `BetaStep` as soon as it is
        solved (progress reports); the same steps end up in ``OTResult.history``."""
        ...

    def memory_bytes(self, n1: int, n2: int, *, matrix_free: bool = False, dim: int = 0) -> int:
        """Peak bytes the solver allocates for an ``n1 x n2`` problem (``matrix_free``: a `FeatureCost` of
        ``dim`` features per point)."""
        ...


def _dense_plan(options: SolverOptions, matrix_free: bool) -> bool:
    return (not matrix_free) if options.dense_plan is None else options.dense_plan


def _lanes(options: SolverOptions) -> int:
    """Lanes per row of the evaluation pass: the options', else a GPU's (the larger of the devices')."""
    return max(1, K.MATVEC_LANES if options.matvec_lanes is None else options.matvec_lanes)


def _linear_bytes(n1: int, n2: int, options: SolverOptions, matrix_free: bool, dim: int) -> int:
    """Bytes of the arrays of an annealing solve other than the (N1, N2) ones: `wpot.ot.anneal.newton.Engine`'s
    device vectors (counted one by one), host allowances per point, the preconditioner's LU factor (~N^1.85,
    see `_FACTOR_EXPONENT`) or, with ``newton_loop="device"``, the device loop's arrays
    (`wpot.ot.anneal.resident.device_loop_bytes`), and, matrix-free, the (N, dim) features. ``newton_loop=None``
    (the device's choice) counts both, a bound for either device."""
    n_r, n_c = max(n1, n2), min(n1, n2)
    kk = max(2, min(options.topk, n_c))
    kc = max(1, min(options.topk, n_r))
    lanes = _lanes(options)
    engine = (_F64 * (20 * n_r + 14 * n_c)  # duals, trial duals, snapshot, sums, Newton and CG vectors
              + _I32 * n_r  # pivots
              + (_F64 + _I32) * (n_r * kk + n_c * kc)  # top-k lists of W
              + (6 * _F64 + _I32) * n_r * lanes)  # per-lane partial sums of the evaluation pass
    host = _HOST_BYTES_PER_POINT * (n_r + n_c) + _HOST_BYTES_PER_POINT_TOPK * (n_r + n_c) * options.topk
    if options.linear_solver == "cg" and options.newton_loop != "host":  # the device loop's arrays
        engine += device_loop_bytes(n_r, n_c, kk, kc, options.device_preconditioner != "fsai")
    if options.linear_solver == "cg" and options.newton_loop != "device":  # the host loop's LU factor
        host += _FACTOR_BYTES_PER_NONZERO * int(min(float(n_c) * n_c, float(n_c) ** _FACTOR_EXPONENT))
    plan_top = _PLAN_TOP_BYTES_PER_ENTRY * n1 * min(options.plan_topk, n2)
    features = _F64 * (n1 + n2) * int(dim) if matrix_free else 0
    return engine + host + plan_top + features


def _direct_bytes(n1: int, n2: int) -> int:
    """Host bytes of one dense direct solve of the Schur complement (`wpot.ot.anneal.linear.direct_solve`) on top of
    the stored W: the scaled copy of W and two (n_c, n_c) products, or S with the partial terms (four
    (n_c, n_c) arrays); then S and its Cholesky factor."""
    n_r, n_c = max(n1, n2), min(n1, n2)
    return _F64 * max(n_r * n_c + 2 * n_c * n_c, 4 * n_c * n_c)


def _check_size(n1: int, n2: int, dim: int) -> tuple[int, int, int]:
    return integer_at_least("n1", n1, 1), integer_at_least("n2", n2, 1), integer_at_least("dim", dim, 0)


def _check_problem(problem: Any) -> TransportProblem:
    if not isinstance(problem, TransportProblem):
        raise TypeError(f"solve needs a TransportProblem, got {type(problem).__name__}")
    return problem


@dataclass(frozen=True)
class _Solver:
    options: SolverOptions = field(default_factory=SolverOptions)

    def __post_init__(self):
        if not isinstance(self.options, SolverOptions):
            raise TypeError(f"options must be a SolverOptions, got {type(self.options).__name__}")


@dataclass(frozen=True)
class AnnealSolver(_Solver):
    """Algorithm 1 from beta0: every grid beta is solved (``history`` has them all). Balanced or partial
    transport; stored cost or `FeatureCost`."""

    name: ClassVar[str] = "anneal"

    def solve(self, problem: TransportProblem, *, on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
        """Solve ``problem`` (see `TransportSolver.solve`)."""
        problem = _check_problem(problem)
        if problem.partial:
            return solve_partial_problem(problem, self.options, on_beta=on_beta)
        return solve_balanced_problem(problem, self.options, on_beta=on_beta)

    def memory_bytes(self, n1: int, n2: int, *, matrix_free: bool = False, dim: int = 0) -> int:
        """Peak bytes of a solve of an ``n1 x n2`` problem (``matrix_free``: a `FeatureCost` of ``dim``
        features per point), on the CPU, where the device's and the host's arrays share the memory.

        Stored cost: the device copy of C (counted always; a float64 ``wp.array`` on the device, or on the CPU
        a C-contiguous float64 NumPy array, is used in place, one (N1, N2) array fewer), the Hessian weights W,
        and then the dense plan when it is formed (``dense_plan``): three (N1, N2) float64 arrays; with
        ``linear_solver="direct"``, the dense Schur solve's arrays instead of the plan when larger
        (`_direct_bytes`). Matrix-free: the features
        (N1 + N2) x dim, the plan only with ``dense_plan=True``. Both: the engine's O(N1 + N2) device arrays
        (counted one by one; the per-lane sums with `wpot.ot.kernels.MATVEC_LANES` lanes unless
        ``matvec_lanes`` says otherwise: exact on a GPU, an upper bound on the CPU's one lane), host
        allowances per point (work vectors) and per point and ``topk`` (the preconditioner's assembly), the
        preconditioner's LU factor (grows like N^1.85 for high-dimensional points, the largest fill
        measured; see `_FACTOR_EXPONENT`), and per ``plan_topk`` entry for ``plan_top``.

        The count bounds the peak RSS growth of CPU solves from above (the docs' Results page gives both, the
        growth measured with glibc's mmap threshold fixed; with its default adaptive threshold the allocator may keep up to
        one more freed (N1, N2) array mapped). On a GPU it bounds the device's share; the returned plan's host
        copy comes on top, in host memory.
        """
        n1, n2, dim = _check_size(n1, n2, dim)
        nn = _F64 * n1 * n2
        if matrix_free:
            quad = nn if _dense_plan(self.options, True) else 0
        else:
            plan = nn if _dense_plan(self.options, False) else 0
            direct = _direct_bytes(n1, n2) if self.options.linear_solver == "direct" else 0
            quad = 2 * nn + max(plan, direct)
        return quad + _linear_bytes(n1, n2, self.options, matrix_free, dim)


@dataclass(frozen=True)
class InteriorPointSolver(_Solver):
    """A primal-dual interior-point method (Mehrotra) follows the central path (for N >= ~50 the saddle point
    at beta is the LP central point with G s = 1/beta) from the product plan to the first grid beta whose
    gap bound N1 N2 / beta is <= 1e-3 U; Algorithm 1 goes on from there (``history`` starts at that beta;
    ``n_newton`` / ``n_linear`` include the interior-point iterations). The same result at convergence, and
    faster (`benchmarks/ot_speed.py`; the docs' Results page). Balanced transport with a stored cost only: it keeps
    the primal plan and the reduced costs, two more (N1, N2) arrays (`wpot.ot.anneal.ipm`)."""

    name: ClassVar[str] = "ipm"

    def solve(self, problem: TransportProblem, *, on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
        """Solve ``problem`` (see `TransportSolver.solve`); ValueError for partial or matrix-free problems."""
        problem = _check_problem(problem)
        if problem.partial:
            raise ValueError("method='ipm' solves balanced transport only (mass_penalty=None); use "
                             "method='exact' or 'anneal' for partial transport")
        return solve_balanced_problem(problem, self.options, interior_point=True, on_beta=on_beta)

    def memory_bytes(self, n1: int, n2: int, *, matrix_free: bool = False, dim: int = 0) -> int:
        """Peak bytes of a solve (see `AnnealSolver.memory_bytes`): during the interior-point start, C, W,
        the primal plan G and the reduced costs S (four (N1, N2) float64 arrays; the product plan that
        initializes G is built on the host before S exists), and the dense solve's arrays on top with
        ``linear_solver="direct"``; the annealing after it needs no more. ``matrix_free`` raises ValueError, as
        `solve` does."""
        n1, n2, dim = _check_size(n1, n2, dim)
        if matrix_free:
            raise ValueError("method='ipm' needs the stored cost matrix; it has no matrix-free mode")
        nn = _F64 * n1 * n2
        direct = _direct_bytes(n1, n2) if self.options.linear_solver == "direct" else 0
        n_r, n_c = max(n1, n2), min(n1, n2)
        ipm_vectors = _F64 * (14 * n_r + 4 * n_c)
        return 4 * nn + direct + ipm_vectors + _linear_bytes(n1, n2, self.options, False, dim)




@dataclass(frozen=True)
class ExactSolver(_Solver):
    """The limit beta = infinity itself by column generation: the transport LP (balanced, POT's network
    simplex; `wpot.ot.exact.balanced`) or the chi^2 QP (partial, Clarabel's interior point; `wpot.ot.exact.partial`)
    on a sparse support that Warp pricing passes over all N1 N2 entries grow until none has a negative
    reduced cost; the last pass certifies the optimum. Stored cost or `FeatureCost`.
    ``history`` has the one beta = inf step (no D(beta) along the annealing); of the options it reads
    ``tol``, ``atol`` (the certified gap), ``max_iter`` (pricing rounds; a few in practice), ``dense_plan``,
    ``plan_topk`` and ``verbose``."""

    name: ClassVar[str] = "exact"

    def solve(self, problem: TransportProblem, *, on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
        """Solve ``problem``, balanced or partial (see `TransportSolver.solve`)."""
        problem = _check_problem(problem)
        kind = "solve_partial" if problem.partial else "solve_balanced"
        return solve_exact_problem(problem, self.options, kind=kind, on_beta=on_beta)

    def memory_bytes(self, n1: int, n2: int, *, matrix_free: bool = False, dim: int = 0) -> int:
        """Peak bytes of a solve: the device copy of C (stored mode; counted always, although the CPU reads a
        C-contiguous float64 array in place) or the features, the dense plan when it
        is formed, the pricing pass's per-row lists and the sparse support with the network simplex's graph
        of it (`wpot.ot.exact.balanced.support_bytes`), or for a partial problem the interior-point method's (the
        larger, counted always)."""

        n1, n2, dim = _check_size(n1, n2, dim)
        nn = _F64 * n1 * n2
        plan = nn if _dense_plan(self.options, matrix_free) else 0
        stored = 0 if matrix_free else nn
        features = _F64 * (n1 + n2) * dim if matrix_free else 0
        return stored + plan + features + max(support_bytes(n1, n2), qp_bytes(n1, n2))


@dataclass(frozen=True)
class AutoSolver(_Solver):
    """The exact solver (`ExactSolver`), balanced or partial. D(beta) along the annealing needs
    ``method="anneal"`` (or ``"ipm"``, balanced)."""

    name: ClassVar[str] = "auto"

    def method_for(self, problem: TransportProblem) -> str:
        """The registry name of the solver ``problem`` gets ("exact")."""
        _check_problem(problem)
        return "exact"

    def solve(self, problem: TransportProblem, *, on_beta: Callable[[BetaStep], None] | None = None) -> OTResult:
        """Solve ``problem`` with the solver `method_for` picks."""
        return SOLVERS[self.method_for(problem)](self.options).solve(problem, on_beta=on_beta)

    def memory_bytes(self, n1: int, n2: int, *, matrix_free: bool = False, dim: int = 0) -> int:
        """Peak bytes of a solve of this size, balanced or partial (`ExactSolver.memory_bytes`)."""
        return ExactSolver(self.options).memory_bytes(n1, n2, matrix_free=matrix_free, dim=dim)


#: the solvers by name (`make_solver`'s ``method``)
SOLVERS: Mapping[str, type] = {"anneal": AnnealSolver, "ipm": InteriorPointSolver, "auto": AutoSolver,
                               "exact": ExactSolver}


def _options(options: SolverOptions | None, option_keywords: Mapping[str, Any], caller: str) -> SolverOptions:
    """``options`` (default `SolverOptions()`) with ``option_keywords`` applied; TypeError naming an unknown
    keyword the way Python names an unexpected keyword argument."""
    if options is None:
        options = SolverOptions()
    elif not isinstance(options, SolverOptions):
        raise TypeError(f"{caller}() options must be a SolverOptions or None, got {type(options).__name__}")
    unknown = sorted(set(option_keywords) - set(SolverOptions.names()))
    if unknown:
        raise TypeError(f"{caller}() got an unexpected keyword argument {unknown[0]!r} (the solver options are "
                        f"{', '.join(SolverOptions.names())})")
    return options.replace(**option_keywords) if option_keywords else options


def make_solver(method: str = "anneal", options: SolverOptions | None = None, **option_keywords: Any
                ) -> TransportSolver:
    """The solver registered as ``method`` (`SOLVERS`: "anneal", "ipm", "auto") with ``options`` (default
    `SolverOptions()`) updated by ``option_keywords`` (the fields of `SolverOptions`)."""
    if not isinstance(method, str) or method not in SOLVERS:
        raise ValueError(f"method must be one of {tuple(SOLVERS)}, got {method!r}")
    return SOLVERS[method](_options(options, option_keywords, "make_solver"))


def solve_balanced(C, a=None, b=None, *, method: str = "auto", device: str | None = None,
                   options: SolverOptions | None = None, **option_keywords: Any) -> OTResult:
    """Balanced optimal transport min_G sum C G, G >= 0, G 1 = a, G^T 1 = b (Eq. 6-7): by default the exact
    optimum (the annealing's limit beta -> infinity, by column generation; `wpot.ot.exact.balanced`), or by annealing
    (Algorithm 1; `wpot.ot.anneal.balanced`), which also gives U(beta) along the way.

    Parameters
    ----------
    C : (N1, N2) float64 numpy array or 2-D float64 ``wp.array`` (used without a copy when on ``device``);
        finite, >= 0; or a `FeatureCost` (signatures and a metric: the matrix-free mode, C recomputed inside
        the kernels, memory O((N1 + N2) D); same results). Results are in C's units.
    a, b : (N1,), (N2,) positive masses with equal sums (default uniform, 1/N). The plan is computed for
        masses normalized to sum 1 and multiplied back by the total.
    method : a solver of `SOLVERS`: "auto" (default; "exact" for balanced transport), "exact" (the transport
        LP, certified over every entry; ``history`` holds beta = inf only), "anneal" (Algorithm 1 from beta0,
        every grid beta solved and recorded) or "ipm" (an interior-point start, then Algorithm 1; stored cost
        only; `InteriorPointSolver`).
    device : Warp device (None: Warp's default).
    options, **option_keywords : a `SolverOptions` (default: the defaults) and keyword overrides of its
        fields (``tol=1e-8``, ``linear_solver="direct"``, ...), documented there. An unknown keyword is a
        TypeError.

    Returns
    -------
    OTResult (``x`` = 0, ``objective`` = ``cost``). ``converged`` is False, with a RuntimeWarning, when
    a tolerance was not met (the annealing's, a Newton solve's, or the exact solve's certified gap).
    """
    solver = make_solver(method, _options(options, option_keywords, "solve_balanced"))
    return solver.solve(TransportProblem(C, a, b, device=device))


def solve_partial(C, rho1=None, rho2=None, *, mass_penalty: float = 1.0, method: str = "auto",
                  device: str | None = None, options: SolverOptions | None = None, **option_keywords: Any) -> OTResult:
    """Partial OT with a Pearson chi^2 mass penalty (Eq. 17-18): by default its exact optimum (the
    annealing's limit beta -> infinity, a convex QP, by column generation; `wpot.ot.exact.partial`), or by
    annealing (Algorithm 1; `wpot.ot.anneal.partial`), which also gives U(beta) and F(beta) along the way:

        min_{G >= 0, m1, m2}  sum C G + sum_k alpha1(k) m1(k)^2 + sum_l alpha2(l) m2(l)^2
        s.t. G 1 = m1, G^T 1 = m2, sum G = 1,       alpha_i = mass_penalty / rho_i^2.

    ``mass_penalty = 1`` is exactly the paper's formulation. Note: as mass_penalty grows the masses tend to
    rho^2 / sum rho^2 (the minimizer of the penalty under sum m = 1), not to rho: a huge mass_penalty
    recovers the balanced problem with those masses (the same as rho when rho is uniform).

    Parameters are those of `solve_balanced` (``C`` may be a `FeatureCost`; ``options`` and the keyword
    overrides of `SolverOptions`), with rho1 (N1,), rho2 (N2,) positive reference measures (default
    uniform; normalized to sum 1) instead of a, b. ``method``: "auto" (default) or "exact" (the QP, certified
    over every entry; ``history`` holds beta = inf only; much faster than the annealing, see the docs' Results
    page) or "anneal" (every grid beta solved and recorded; "ipm" is a ValueError, as for the solver).

    Returns OTResult with ``mass1``, ``mass2`` the plan's marginals (sum 1 together), ``cost`` the
    transport part sum C G, ``objective`` Eq. 17 (cost + penalty), ``free_energy`` Eq. 23 (= ``objective``
    at beta = inf), ``lam``, ``mu``, ``x`` the duals (Eq. 26's sign).
    """
    mass_penalty = positive_finite("mass_penalty", mass_penalty)
    solver = make_solver(method, _options(options, option_keywords, "solve_partial"))
    return solver.solve(TransportProblem(C, rho1, rho2, mass_penalty=mass_penalty, device=device))


def solve_batch(problems, *, options: SolverOptions | None = None, **option_keywords: Any) -> list[OTResult]:
    """Many problems (`TransportProblem`s, balanced or partial, with stored costs of any sizes, on one device)
    solved exactly (``method="exact"``) together: each round's pricing passes of every problem still running
    share one kernel launch, so that a GPU stays busy with small problems (the restricted LPs and QPs are
    solved on the host). Each result equals that of ``make_solver("exact").solve`` on the problem alone, bit
    for bit.

    ``options`` and ``**option_keywords`` as in `solve_balanced`; a `FeatureCost` is a ValueError."""
    problems = [_check_problem(p) for p in problems]
    return solve_exact_batch(problems, _options(options, option_keywords, "solve_batch"))
