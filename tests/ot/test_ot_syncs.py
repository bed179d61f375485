"""Host-device transfers of the OT solver: every read of a device array goes through
`Engine.to_host` (counted in ``Timers.n_d2h``) and every write of host data through `Engine.to_device`
(``Timers.n_h2d``), so the counts are the transfers (and, for reads, synchronisations) a GPU run makes.

A spy counts every ``warp.array.numpy`` call (and, on the GPU code path, every ``warp.array.assign`` from
host data) made once the engine exists; the engine's counters, less what its constructor counted, must
equal the spy's.
"""
from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import wpot.ot as wo
from wpot.ot.anneal import newton
from wpot.ot.anneal.state import Timers


class Spy:
    """Counts ``wp.array.numpy`` calls and ``wp.array.assign`` calls from non-Warp data, from the moment an
    `Engine` is constructed until `stop`; keeps the engines. ``gpu_path`` makes each engine take the code
    path of a GPU (uploads by ``assign``, no zero-copy views) on the CPU."""

    def __init__(self, monkeypatch, gpu_path: bool):
        self.engines: list[newton.Engine] = []
        self.at_init = (0, 0)  # the engine's (n_d2h, n_h2d) when its constructor returned
        self.numpy = 0
        self.assign = 0
        self.on = False
        real_init, real_numpy, real_assign = newton.Engine.__init__, wp.array.numpy, wp.array.assign
        spy = self

        def init(eng, *args, **kwargs):
            real_init(eng, *args, **kwargs)
            if gpu_path:
                eng._host = False
                eng.solver._mv_view = None
            spy.engines.append(eng)
            spy.at_init = (eng.t.n_d2h, eng.t.n_h2d)
            spy.on = True

        def numpy(arr, *args, **kwargs):
            if spy.on:
                spy.numpy += 1
            return real_numpy(arr, *args, **kwargs)

        def assign(arr, src):
            if spy.on and not isinstance(src, wp.array):
                spy.assign += 1
            return real_assign(arr, src)

        monkeypatch.setattr(newton.Engine, "__init__", init)
        monkeypatch.setattr(wp.array, "numpy", numpy)
        monkeypatch.setattr(wp.array, "assign", assign)

    def stop(self) -> Timers:
        self.on = False
        assert len(self.engines) == 1
        return self.engines[0].t


def _cost(n1: int, n2: int, seed: int) -> np.ndarray:
    return 0.1 + np.random.default_rng(seed).random((n1, n2))


CASES = {
    "anneal": lambda: wo.solve_balanced(_cost(70, 90, 0), method="anneal", device="cpu"),
    "ipm": lambda: wo.solve_balanced(_cost(80, 80, 1), method="ipm", device="cpu"),
    "partial": lambda: wo.solve_partial(_cost(90, 70, 2), mass_penalty=0.05, device="cpu", method="anneal"),
}


def _run(monkeypatch, case: str, gpu_path: bool):
    with monkeypatch.context() as mp:
        spy = Spy(mp, gpu_path)
        r = CASES[case]()
        t = spy.stop()
    return r, t, spy


@pytest.mark.parametrize("case", sorted(CASES))
def test_every_read_and_write_is_counted(monkeypatch, case):
    r, t, spy = _run(monkeypatch, case, gpu_path=False)
    assert r.converged
    # every read of a device array after the engine exists went through Engine.to_host
    assert t.n_d2h - spy.at_init[0] == spy.numpy > 0
    assert t.n_newton == r.n_newton > 0
    # each CG iteration reads the Schur matvec back and uploads its argument
    assert t.n_matvec >= r.n_linear > 0
    assert t.n_d2h / t.n_newton >= t.n_matvec / t.n_newton
    assert t.n_h2d >= t.n_matvec
    # on the GPU code path (run here on the CPU) the same transfers happen, each one counted: the
    # uploads are `assign`s from host data, and the numerics are those of the zero-copy path
    rg, tg, spy_g = _run(monkeypatch, case, gpu_path=True)
    assert tg.n_d2h - spy_g.at_init[0] == spy_g.numpy
    assert tg.n_h2d - spy_g.at_init[1] == spy_g.assign
    assert (tg.n_d2h, tg.n_h2d) == (t.n_d2h, t.n_h2d)
    assert (tg.n_newton, tg.n_matvec) == (t.n_newton, t.n_matvec)
    assert rg.cost == r.cost
    np.testing.assert_array_equal(rg.mass1, r.mass1)
