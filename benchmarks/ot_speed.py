"""Speed and accuracy of wpot.ot against POT, side by side in one run (issue 3).

Problem: C = Euclidean distances between uniform random points in R^8, normalized to max 1; uniform masses, or
with ``--mass-spread s`` log-normal ones (exp(s z), z ~ N(0, 1): max/min ~ 10^3 at s = 1.5, N = 500; unequal
masses as cell-pooled samples give, where an earlier Newton variant stalled).
Solvers: wpot.ot.solve_balanced (Warp; method="exact", the default: the LP by column generation; "anneal" and
"ipm", default CG and optionally the dense direct solve), POT's exact ot.emd (numItermax 1e9, its warning checked), POT's stabilized Sinkhorn (reg 1e-3, tau=1e8) and ot.unbalanced.sinkhorn_unbalanced.
Printed: wall time, relative gap of <C, plan> to ot.emd's optimum, L1 marginal error (relative to the
total mass), wpot's Newton/CG counts, where its time goes, and its host-device transfers per Newton step and
per CG iteration (device-to-host reads are synchronisations on a GPU; the counts are those a GPU run makes,
whatever the device). Timings on a shared machine are noisy.

    python benchmarks/ot_speed.py                 # N = 500, 1000, 3400
    python benchmarks/ot_speed.py --sizes 3400 10000 --methods exact --quick
    python benchmarks/ot_speed.py --tosca 5 --methods exact ipm --quick   # full-resolution TOSCA pairs (WKS)
    python benchmarks/ot_speed.py --sizes 500 1000 --quick
    python benchmarks/ot_speed.py --sizes 500 1000 --quick --mass-spread 1.5
"""
from __future__ import annotations

import argparse
import os
import time
import warnings

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def problem(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    X, Y = rng.random((n, 8)), rng.random((n, 8))
    C = np.sqrt(((X[:, None, :] - Y[None, :, :]) ** 2).sum(-1))
    return C / C.max()


def masses(n: int, spread: float, seed: int = 1):
    """Two (n,) mass vectors summing to 1: uniform (spread 0) or log-normal with log-std ``spread``."""
    if spread == 0:
        a = np.full(n, 1.0 / n)
        return a, a
    rng = np.random.default_rng(seed)
    a, b = np.exp(spread * rng.normal(size=n)), np.exp(spread * rng.normal(size=n))
    return a / a.sum(), b / b.sum()


def row(name, t, gap, merr, extra=""):
    print(f"  {name:<34} {t:9.2f} s   gap {gap:10.2e}   marg.err {merr:9.2e}   {extra}")


def transfers(tm: dict) -> str:
    """The engine's host-device transfers (`wpot.ot.anneal.state.Timers` as a dict, up to the end of the annealing)
    per Newton step and per CG iteration (Schur matvec)."""
    nn, nm = max(tm["n_newton"], 1), max(tm["n_matvec"], 1)
    return (f"host-device transfers: d2h (syncs) {tm['n_d2h']} = {tm['n_d2h'] / nn:.1f} per Newton step, "
            f"{tm['n_d2h'] / nm:.2f} per CG iteration; h2d {tm['n_h2d']} = {tm['n_h2d'] / nn:.1f} per Newton step, "
            f"{tm['n_h2d'] / nm:.2f} per CG iteration ({tm['n_newton']} Newton steps, {tm['n_matvec']} CG iterations); "
            f"preconditioner builds {tm['n_factor']} ({tm['n_factor'] / nn:.2f} per Newton step), device-loop refits "
            f"{tm['n_refit']}; synchronisations with those inside Warp's set-up of the device loop's builds: "
            f"{(tm['n_d2h'] + tm['n_build_sync']) / nn:.2f} per Newton step")


def newton_loops(args) -> list[tuple[str, dict]]:
    """The Newton loops to time, as (label, solver options)."""
    return [(f"{loop} loop" + (f", {pc}" if loop == "device" and len(args.device_preconditioner) > 1 else ""),
             {"newton_loop": loop, **({"device_preconditioner": pc} if loop == "device" else {})})
            for loop in args.newton_loop for pc in (args.device_preconditioner if loop == "device" else [None])]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="*", default=[500, 1000, 3400], help="random problems of these N (none: only --tosca)")
    ap.add_argument("--quick", action="store_true", help="skip the slow peers (Sinkhorns, direct solve)")
    ap.add_argument("--direct", action="store_true", help="also run wpot with linear_solver='direct'")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--methods", nargs="+", default=["exact", "anneal", "ipm"], choices=["exact", "anneal", "ipm"],
                    help="wpot solve_balanced methods to time (default all three)")
    ap.add_argument("--newton-loop", nargs="+", default=["host"], choices=["host", "device"],
                    help="Newton loops to time for anneal and ipm (SolverOptions.newton_loop; default host, the CPU's)")
    ap.add_argument("--device-preconditioner", nargs="+", default=["multilevel"], choices=["multilevel", "fsai"],
                    help="the device loop's preconditioners to time (SolverOptions.device_preconditioner)")
    ap.add_argument("--tosca", type=int, default=0,
                    help="also time this many full-resolution TOSCA pairs (tosca_isometric_5k, 5,000 vertices, "
                    "WKS cost of wpot's defaults) beside ot.emd")
    ap.add_argument("--tosca-samples", type=int, default=None,
                    help="with --tosca: that many farthest-point samples a shape instead of every vertex")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("WPOT_DATA", HERE.parent.parent / "shared" / "data")),
                    help="the shared data folder (default ../shared/data or $WPOT_DATA)")
    ap.add_argument("--mass-spread", type=float, default=0.0,
                    help="log-normal masses with this log-std (default 0: uniform)")
    ap.add_argument("--small", type=int, nargs="*", default=[],
                    help="also time repeated calls at these small N (per-call overhead; e.g. --small 200 250)")
    args = ap.parse_args()

    import ot

    import wpot.ot as wo
    from wpot.ot.anneal import balanced as wbalanced

    for m in ("exact", "anneal", "ipm"):  # compile the kernels outside the timings
        for _, kw in newton_loops(args):
            wo.solve_balanced(problem(60), device=args.device, method=m, **kw)

    # capture the engine's timers (kept on the Engine that the annealing loop drives)
    timers = {}
    orig = wbalanced.anneal

    def anneal(eng, fe, **kw):
        out = orig(eng, fe, **kw)
        timers.clear()
        timers.update(eng.t.as_dict())
        return out

    wbalanced.anneal = anneal

    for n in args.small:
        C = problem(n)
        a = np.full(n, 1.0 / n)
        u0 = ot.emd2(a, a, C, numItermax=10**9)
        t = time.perf_counter()
        for _ in range(3):
            ot.emd(a, a, C, numItermax=10**9)
        t_emd = (time.perf_counter() - t) / 3
        t = time.perf_counter()
        for _ in range(3):
            r = wo.solve_balanced(C, device=args.device)
        tw = (time.perf_counter() - t) / 3
        print(f"N = {n} (mean of 3 calls): wpot default ({r.beta:.3g}) {tw:.3f} s (gap {(r.cost - u0) / u0:.1e}, newton={r.n_newton}"
              f" cg={r.n_linear}), ot.emd {t_emd:.3f} s")

    for n in args.sizes:
        C = problem(n)
        a, b = masses(n, args.mass_spread)
        print(f"\nN = {n}  (C {n}x{n}, float64 {C.nbytes / 2**20:.0f} MiB; masses max/min {a.max() / a.min():.3g},"
              f" {b.max() / b.min():.3g})")
        compare_on(C, a, b, args, timers)

    for name, C in tosca_costs(args.tosca, args.data, args.tosca_samples):
        n1, n2 = C.shape
        print(f"\nTOSCA {name}  (WKS cost {n1}x{n2}{'' if args.tosca_samples is None else ', farthest-point samples'})")
        compare_on(C, np.full(n1, 1.0 / n1), np.full(n2, 1.0 / n2), args, timers)


def tosca_costs(n_pairs: int, data: Path, samples: int | None = None):
    """(name, WKS cost) of ``n_pairs`` TOSCA pairs (consecutive shapes of tosca_isometric_5k, every vertex or
    ``samples`` farthest-point samples, the signature's defaults and one energy grid per pair); skipped with a
    reason if absent."""
    if n_pairs <= 0:
        return
    import wpot
    from wpot.cost import cost_matrix

    folder = data / "tosca_isometric_5k" / "vtx_5k"
    if not folder.is_dir():
        print(f"\n(TOSCA pairs skipped: {folder} not found)")
        return
    files = sorted(folder.glob("*.off"))
    for f1, f2 in list(zip(files[0::2], files[1::2]))[:n_pairs]:
        comparer = wpot.Comparer(device="cpu", max_vertices=samples)
        a, b = wpot.load_mesh(f1), wpot.load_mesh(f2)
        comparer.fit([a, b])
        X, Y = comparer.points(a).signatures, comparer.points(b).signatures
        yield f"{f1.stem}-{f2.stem}", cost_matrix(X, Y, metric="wks")


def compare_on(C, a, b, args, timers):
    """ot.emd and each of wpot's methods on one cost, one line each (time, gap to ot.emd, marginal error)."""
    import ot

    import wpot.ot as wo
    from wpot.ot.exact import solve_exact_problem

    t = time.perf_counter()
    G0, log = ot.emd(a, b, C, numItermax=10**9, log=True)
    t_emd = time.perf_counter() - t
    u0 = float((G0 * C).sum())
    row("POT ot.emd (exact)", t_emd, 0.0, np.abs(G0.sum(1) - a).sum() + np.abs(G0.sum(0) - b).sum(),
        f"warning: {log['warning']}" if log["warning"] else "")

    def report(name, G, t):
        gap = ((G * C).sum() - u0) / u0
        merr = np.abs(G.sum(1) - a).sum() + np.abs(G.sum(0) - b).sum()
        return gap, merr

    for method in args.methods:
        if method == "exact":
            rounds = []
            t = time.perf_counter()
            r = solve_exact_problem(wo.TransportProblem(C, a, b, device=args.device), wo.SolverOptions(),
                                    on_round=rounds.append)
            tw = time.perf_counter() - t
            gap, merr = report("wpot", r.plan, tw)
            row(f"wpot solve_balanced exact ({args.device})", tw, gap, merr,
                f"conv={r.converged} certified gap {r.history[0].gap_bound / r.cost:.1e}  ({tw / t_emd:.2f}x ot.emd)")
            print(f"      {len(rounds)} pricing rounds (passes over all N1 N2 entries: {len(rounds) + 2}, with the first "
                  "support's row and column passes); "
                  f"LP {sum(x.t_lp for x in rounds):.2f} s, passes {sum(x.t_price for x in rounds):.2f} s; "
                  f"support {rounds[-1].support} entries ({rounds[-1].support / len(a):.1f} a row); "
                  f"priced out per round: {' '.join(str(x.violations) for x in rounds)}")
            continue
        for label, kw in newton_loops(args):
            t = time.perf_counter()
            r = wo.solve_balanced(C, a, b, device=args.device, method=method, **kw)
            tw = time.perf_counter() - t
            gap, merr = report("wpot", r.plan, tw)
            tm = {k: v for k, v in timers.items()}
            row(f"wpot solve_balanced {method}, {label} ({args.device})", tw, gap, merr,
                f"conv={r.converged} beta={r.beta:.1e} newton={r.n_newton} cg={r.n_linear}  ({tw / t_emd:.2f}x ot.emd)")
            print("      time split (solver kernels and CG; for ipm the rest is its own passes): "
                  + ", ".join(f"{k} {tm[k]:.2f}s" for k in ("eval", "prep", "precond", "cg", "other"))
                  + f"; {tm['n_eval']} passes of phi over C (+{tm.get('n_free', 0)} for F), {tm['n_matvec']} Schur"
                  f" matvecs, {tm.get('n_factor', 0)} preconditioner builds")
            print("      " + transfers(tm))
        print("      per recorded beta (newton/cg): " + " ".join(f"{h.n_newton}/{h.n_linear}" for h in r.history))
    if args.direct and len(a) <= 2000:
        t = time.perf_counter()
        rd = wo.solve_balanced(C, a, b, device=args.device, linear_solver="direct", method="anneal")
        td = time.perf_counter() - t
        gap, merr = report("direct", rd.plan, td)
        row(f"wpot solve_balanced direct ({args.device})", td, gap, merr, f"newton={rd.n_newton}")
    if args.quick:
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = time.perf_counter()
        Gs = ot.bregman.sinkhorn_stabilized(a, b, C, 1e-3, tau=1e8, numItermax=100000, stopThr=1e-9)
        ts = time.perf_counter() - t
        gap, merr = report("sink", Gs, ts)
        row("POT sinkhorn_stabilized reg=1e-3", ts, gap, merr)
        t = time.perf_counter()
        Gu = ot.unbalanced.sinkhorn_unbalanced(a, b, C, 1e-3, 10.0, method="sinkhorn_stabilized",
                                               numItermax=100000, stopThr=1e-9, tau=1e8)
        tu = time.perf_counter() - t
        gap, merr = report("unb", Gu, tu)
        row("POT sinkhorn_unbalanced reg=1e-3 m=10", tu, gap, merr, "(unbalanced: marginals not enforced)")


if __name__ == "__main__":
    main()
