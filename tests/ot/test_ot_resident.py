"""The device-resident Newton loop (`wpot.ot.anneal.resident`, ``newton_loop="device"``): the same saddle points as
the host loop, its pieces against independent references (the sparse Schur approximation against the host
assembly, the CG direction against a dense solve), and its host reads (at most 2 per Newton step, none
per CG iteration)."""
from __future__ import annotations

import numpy as np
import ot
import pytest
import scipy.sparse as sp
import warp as wp

import wpot.ot as wo
from wpot.ot.anneal import linear, newton, resident
from wpot.ot.anneal.host import HostSolver
from wpot.ot.anneal.newton import Engine
from wpot.ot.anneal.state import Point
from wpot.ot.problem import orient, prepare_cost


def _cost(n1, n2, seed=0, d=6):
    rng = np.random.default_rng(seed)
    X, Y = rng.random((n1, d)), rng.random((n2, d))
    return np.linalg.norm(X[:, None] - Y[None], axis=-1)


def _masses(n, seed):
    m = np.random.default_rng(seed).random(n) + 0.3
    return m / m.sum()


# --------------------------------------------------------------------------- whole solves
@pytest.mark.parametrize("pc", ["multilevel", "fsai"])
@pytest.mark.parametrize("method", ["anneal", "ipm"])
def test_balanced_device_loop_reaches_the_host_loops_saddle_points(device, method, pc):
    C = _cost(70, 85, seed=1)  # 70 columns: P has a coarse level below it (wpot.ot.anneal.multilevel.COARSE_SIZE)
    a, b = _masses(70, 2), _masses(85, 3)
    host = wo.solve_balanced(C, a, b, method=method, device="cpu", newton_loop="host")
    dev = wo.solve_balanced(C, a, b, method=method, device=device, newton_loop="device", device_preconditioner=pc)
    assert host.converged and dev.converged
    G0 = ot.emd(a, b, C, numItermax=10**8)
    u0 = float((G0 * C).sum())
    assert abs(dev.cost - u0) <= 1e-6 * u0
    assert abs(dev.cost - host.cost) <= 1e-9 * host.cost
    np.testing.assert_allclose(dev.plan.sum(1), a, atol=1e-11)
    np.testing.assert_allclose(dev.plan.sum(0), b, atol=1e-11)
    # D(beta): the same betas, each solved to the Newton tolerance, the same U, F there
    hb = {round(np.log10(s.beta), 6): s for s in host.history}
    common = [s for s in dev.history if round(np.log10(s.beta), 6) in hb]
    assert len(common) >= len(host.history) - 2 and len(common) >= 5
    for s in common:
        h = hb[round(np.log10(s.beta), 6)]
        assert s.residual <= 1e-11 and h.residual <= 1e-11  # the saddle point at that beta
        assert abs(s.cost - h.cost) <= 1e-8 * abs(h.cost) + 1e-14
        assert abs(s.free_energy - h.free_energy) <= 1e-8 * abs(h.free_energy) + 1e-12


def test_partial_device_loop_agrees_with_the_host_loop_and_the_qp(device):
    from helpers import partial_qp

    C = _cost(70, 85, seed=4)  # 70 columns: the multilevel V-cycle has a coarse level
    C /= C.max()
    r1, r2 = _masses(70, 5), _masses(85, 6)
    host = wo.solve_partial(C, r1, r2, mass_penalty=0.05, method="anneal", device="cpu", newton_loop="host")
    dev = wo.solve_partial(C, r1, r2, mass_penalty=0.05, method="anneal", device=device, newton_loop="device")
    assert host.converged and dev.converged
    assert abs(dev.objective - host.objective) <= 1e-9 * abs(host.objective)
    assert abs(dev.free_energy - host.free_energy) <= 1e-9 * abs(host.free_energy)
    np.testing.assert_allclose(dev.mass1, host.mass1, rtol=1e-6, atol=1e-12)
    val, m1, m2 = partial_qp(C, r1, r2, 0.05)
    assert abs(dev.objective - val) <= 1e-6 * val
    np.testing.assert_allclose(dev.mass1, m1, atol=1e-6)
    np.testing.assert_allclose(dev.mass2, m2, atol=1e-6)


def test_matrix_free_device_loop_equals_the_stored_one():
    rng = np.random.default_rng(7)
    X, Y = rng.random((60, 5)), rng.random((75, 5))
    C = np.linalg.norm(X[:, None] - Y[None], axis=-1)
    stored = wo.solve_balanced(C, method="anneal", device="cpu", newton_loop="device")
    lazy = wo.solve_balanced(wo.FeatureCost(X, Y, metric="l2"), method="anneal", device="cpu",
                             newton_loop="device")
    assert stored.converged and lazy.converged
    assert abs(lazy.cost - stored.cost) <= 1e-10 * stored.cost
    np.testing.assert_array_equal(lazy.argmax, stored.argmax)


# --------------------------------------------------------------------------- the pieces
def _engine_at(C, partial: bool, beta: float, loop: str, **opts) -> tuple[Engine, Point]:
    """An engine for C, evaluated at ``beta`` and fixed random duals (the same for every loop)."""
    n1, n2 = C.shape
    cost = prepare_cost(C, "cpu")
    if partial:
        b1, a2 = np.full(n1, 2.0 / n1), np.full(n2, 3.0 / n2)
        prob = orient(cost, np.zeros(n1), np.zeros(n2), b1, a2, True, "cpu")
    else:
        prob = orient(cost, np.full(n1, 1 / n1), np.full(n2, 1 / n2), np.zeros(n1), np.zeros(n2), False, "cpu")
    o = wo.SolverOptions(newton_loop=loop, **opts).normalized(n1, n2, cost.scale)
    eng = Engine(prob, o)
    rng = np.random.default_rng(3)
    eng.init_point(0.01 * rng.random(prob.n_r), np.full(prob.n_c, n1 * n2 / o.beta0) + 0.01 * rng.random(prob.n_c))
    return eng, eng.evaluate(eng.lam, eng.y, beta)


@pytest.mark.parametrize("partial", [False, True])
def test_device_assembly_of_the_sparse_schur_approximation_equals_the_host_one(partial):
    C = _cost(50, 40, seed=8)
    eng, pt = _engine_at(C, partial, beta=3e5, loop="device")
    eng.direction(pt)  # builds the preconditioner (fresh): top-k lists, diag(S_W), e1 at this point
    dev = eng.solver.dev
    n = eng.p.n_c
    data = linear.SchurData(eng.diag_s.numpy().copy(), eng.e1.numpy().copy(), eng.piv.numpy().copy(), eng.p.a_c,
                            not partial)
    ref = linear.assemble_sparse_schur(data, eng.top_val.numpy(), eng.top_idx.numpy(), eng.ctop_val.numpy(),
                                       eng.ctop_idx.numpy()).toarray()
    P = dev.P
    got = sp.csr_matrix((P.values.numpy()[: P.nnz], P.columns.numpy()[: P.nnz], P.offsets.numpy()), shape=(n, n))
    got = got.toarray()
    assert np.count_nonzero(ref - np.diag(np.diag(ref))) > n  # the approximation has couplings to compare
    if not partial:  # the gauge column: dropped, an identity row instead
        ref[-1, :] = ref[:, -1] = 0.0
        ref[-1, -1] = 1.0
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("partial", [False, True])
def test_device_cg_direction_solves_the_newton_system(partial):
    # the direction of the device loop (FSAI-preconditioned CG, to a tight tolerance) against a dense direct
    # solve of the same Schur system (the host loop's linear_solver="direct") at the same point
    C = _cost(45, 35, seed=9)
    eng_d, pt_d = _engine_at(C, partial, beta=1e6, loop="device", cg_rtol=1e-12)
    eng_h, pt_h = _engine_at(C, partial, beta=1e6, loop="host", linear_solver="direct")
    n_lin, ok = eng_d.direction(Point(None, None, 0.0, 0.0))
    assert ok and n_lin > 1
    eng_h.direction(pt_h)
    for a_d, a_h in ((eng_d.dy_a, eng_h.dy_a), (eng_d.d_a, eng_h.d_a), (eng_d.d_b, eng_h.d_b)):
        x, y = a_d.numpy(), a_h.numpy()
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-7 * np.abs(y).max())


def test_device_loop_options_are_validated():
    with pytest.raises(ValueError, match="newton_loop must be one of"):
        wo.SolverOptions(newton_loop="gpu")
    with pytest.raises(ValueError, match="newton_loop='device' needs linear_solver='cg'"):
        wo.SolverOptions(newton_loop="device", linear_solver="direct")
    with pytest.raises(ValueError, match="device_preconditioner must be one of"):
        wo.SolverOptions(device_preconditioner="ilu")
    for kw in ({"newton_loop": "host"}, {"linear_solver": "direct"}):  # the host loop's is SuperLU
        with pytest.raises(ValueError, match="device_preconditioner is the device loop's"):
            wo.SolverOptions(device_preconditioner="fsai", **kw)
    assert wo.SolverOptions(device_preconditioner="fsai").device_preconditioner == "fsai"  # newton_loop=None


def test_default_loop_is_the_host_one_on_the_cpu():
    C = _cost(20, 20)
    eng, _ = _engine_at(C, False, beta=1e4, loop=None)
    assert isinstance(eng.solver, HostSolver)


# --------------------------------------------------------------------------- host reads
class ReadSpy:
    """Counts ``wp.array.numpy`` calls once an `Engine` exists, apart from those inside Warp's preconditioner
    set-up in a full build (`resident.DeviceLoop.build_preconditioner`: FSAI), counted on their own; the
    engine's own reads (`Engine.to_host`, the multilevel hierarchy's read of P in a build included) count in
    ``numpy``."""

    def __init__(self, monkeypatch, gpu_path: bool = False):
        self.engines, self.on, self.in_build, self.in_engine = [], False, False, False
        self.numpy = self.build_reads = 0
        self.at_init = 0
        real_init, real_numpy = newton.Engine.__init__, wp.array.numpy
        real_build = resident.DeviceLoop.build_preconditioner
        real_to_host = newton.Engine.to_host
        spy = self

        def init(eng, *args, **kwargs):
            real_init(eng, *args, **kwargs)
            if gpu_path:  # uploads by assign, as on a GPU
                eng._host = False
            spy.engines.append(eng)
            spy.at_init = eng.t.n_d2h
            spy.on = True

        def numpy(arr, *args, **kwargs):
            if spy.on:
                if spy.in_build and not spy.in_engine:
                    spy.build_reads += 1
                else:
                    spy.numpy += 1
            return real_numpy(arr, *args, **kwargs)

        def build(dev):
            spy.in_build = True
            try:
                real_build(dev)
            finally:
                spy.in_build = False

        def to_host(eng, arr):
            spy.in_engine = True
            try:
                return real_to_host(eng, arr)
            finally:
                spy.in_engine = False

        monkeypatch.setattr(newton.Engine, "__init__", init)
        monkeypatch.setattr(newton.Engine, "to_host", to_host)
        monkeypatch.setattr(wp.array, "numpy", numpy)
        monkeypatch.setattr(resident.DeviceLoop, "build_preconditioner", build)


CASES = {
    "anneal": lambda: wo.solve_balanced(_cost(80, 100, 0), method="anneal", device="cpu", newton_loop="device"),
    "ipm": lambda: wo.solve_balanced(_cost(90, 80, 1), method="ipm", device="cpu", newton_loop="device"),
    "partial": lambda: wo.solve_partial(_cost(90, 70, 2), mass_penalty=0.05, device="cpu", method="anneal",
                                        newton_loop="device"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_device_loop_reads_at_most_twice_per_newton_step(monkeypatch, case):
    with monkeypatch.context() as mp:
        spy = ReadSpy(mp)
        r = CASES[case]()
        spy.on = False
    assert r.converged
    (eng,) = spy.engines
    t = eng.t
    # every read of the loop goes through Engine.to_host ...
    assert t.n_d2h - spy.at_init == spy.numpy
    # ... and there are at most 2 a Newton step (one per trial point, plus a few per beta; one per
    # interior-point iteration), none per CG iteration: CG ran many more iterations than there were reads
    assert t.n_newton == r.n_newton > 10 and r.n_linear == t.n_matvec
    assert t.n_d2h <= 2 * t.n_newton
    assert t.n_matvec >= 3 * t.n_newton
    # nothing is uploaded per step (at set-up only: the masses, the starting duals, the interior point's plan)
    assert t.n_h2d <= 10
    # a full preconditioner build reads a few scalars inside Warp (FSAI set-up; reported by
    # benchmarks/ot_speed.py); the refits, most of the rebuilds, read nothing (their reads would be in
    # spy.numpy, which equals the engine's own count above)
    assert t.n_factor > 0 and spy.build_reads <= (resident.BUILD_SYNCS - 1) * t.n_factor  # + a stream sync on CUDA
    assert t.n_refit > t.n_factor and t.n_build_sync == resident.BUILD_SYNCS * t.n_factor


def test_a_refit_at_the_same_point_reproduces_the_full_build():
    # the refit (new values on the last pattern, FSAI refitted on its supports; no host read) at the very
    # point of the full build must give the same preconditioner
    C = _cost(60, 45, seed=11)
    eng, pt = _engine_at(C, False, beta=3e5, loop="device")
    eng.direction(pt)
    dev = eng.solver.dev
    r = np.random.default_rng(0).normal(size=eng.p.n_c)
    r[-1] = 0.0
    eng.to_device(dev.r, r)
    dev.apply_preconditioner()
    z_build = dev.z.numpy().copy()
    G_build = dev.M.G.values.numpy().copy()
    dev.refit_preconditioner()
    dev.apply_preconditioner()
    np.testing.assert_allclose(dev.M.G.values.numpy(), G_build, rtol=1e-12, atol=0)
    np.testing.assert_allclose(dev.z.numpy(), z_build, rtol=1e-10, atol=1e-12 * np.abs(z_build).max())
    assert np.abs(z_build).max() > 0 and not np.allclose(z_build, r)


@pytest.mark.parametrize("partial", [False, True])
def test_the_captured_cg_loop_equals_the_plain_one(partial):
    # on a GPU with conditional graph nodes the CG loop is captured once per solve (wp.ScopedCapture around
    # wp.capture_while) and replayed; Warp captures on the CPU too, so the captured structure is run here and
    # must give the plain loop's direction, bit for bit (90 columns: the multilevel V-cycle, below P, is captured)
    C = _cost(110, 90, seed=12)
    out = []
    for captured in (False, True):
        eng, pt = _engine_at(C, partial, beta=3e5, loop="device", cg_rtol=1e-10)
        eng.solver.dev.captured = captured
        n_lin, ok = eng.direction(Point(None, None, 0.0, 0.0))
        assert ok and n_lin >= 3
        out.append((n_lin, eng.dy_a.numpy().copy(), eng.d_b.numpy().copy()))
    assert out[0][0] == out[1][0]
    np.testing.assert_array_equal(out[0][1], out[1][1])
    np.testing.assert_array_equal(out[0][2], out[1][2])


def test_the_captured_cg_graph_is_reused_and_still_exact():
    # a whole Newton solve (many directions: refits reuse the captured graph, a full build captures anew)
    # with the captured loop equals the plain loop's, bit for bit (80 columns: a V-cycle with a coarse level)
    C = _cost(100, 80, seed=13)
    out = []
    for captured in (False, True):
        eng, pt = _engine_at(C, False, beta=3e5, loop="device")
        eng.solver.dev.captured = captured
        pt, nn, nl, ok = eng.newton(3e5, pt)
        assert ok and nn > 3
        out.append((nn, nl, eng.t.n_refit, eng.lam[0].numpy().copy(), eng.y[0].numpy().copy()))
        if captured:  # one capture per full build, none per refit
            assert eng.solver.dev.n_captures == eng.t.n_factor < eng.solver.dev.n_solves
    assert out[0][:3] == out[1][:3] and out[1][2] > 0
    np.testing.assert_array_equal(out[0][3], out[1][3])
    np.testing.assert_array_equal(out[0][4], out[1][4])


def test_device_loop_with_the_gpus_strided_kernels():
    # on a GPU the passes over W run as strided lanes (matvec_lanes = kernels.MATVEC_LANES); the device loop
    # on them, forced here on the CPU, reaches the same optimum as with the row kernels
    C = _cost(70, 60, seed=14)
    rows = wo.solve_balanced(C, method="ipm", device="cpu", newton_loop="device", matvec_lanes=0)
    lanes = wo.solve_balanced(C, method="ipm", device="cpu", newton_loop="device", matvec_lanes=8)
    part = wo.solve_partial(C, mass_penalty=0.05, method="anneal", device="cpu", newton_loop="device", matvec_lanes=8)
    part0 = wo.solve_partial(C, mass_penalty=0.05, method="anneal", device="cpu", newton_loop="host")
    assert rows.converged and lanes.converged and part.converged
    assert abs(lanes.cost - rows.cost) <= 1e-10 * rows.cost
    assert abs(part.objective - part0.objective) <= 1e-9 * part0.objective


def test_device_loop_counts_are_those_of_the_gpu_code_path(monkeypatch):
    # the engine's GPU code path (uploads by assign, no zero-copy views), run on the CPU: the same reads,
    # writes and result as the CPU path
    runs = []
    for gpu_path in (False, True):
        with monkeypatch.context() as mp:
            spy = ReadSpy(mp, gpu_path)
            r = CASES["anneal"]()
            spy.on = False
        t = spy.engines[0].t
        runs.append((r.cost, t.n_d2h, t.n_h2d, t.n_newton, t.n_matvec, t.n_factor, t.n_refit))
    assert runs[0] == runs[1]
