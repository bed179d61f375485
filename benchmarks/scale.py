"""How time and memory grow with N: wpot's stored-C solver, its matrix-free mode and POT's ot.emd (issue 7).

Problem: N random signatures per side in R^d (uniform in [0, 1]^d, seeds fixed), C(k, l) = L2 distance between
signatures, uniform masses, balanced transport. Each (method, N) runs in a fresh subprocess, so the peak resident
memory (ru_maxrss) is that run's alone; a run that exceeds ``--timeout`` is killed and larger N are skipped for that
method. The three methods solve the same problem, so the table also gives each wpot run's relative gap to emd.

    python benchmarks/scale.py                               # N = 500 ... 5000 on "cpu"
    python benchmarks/scale.py --sizes 1000 2000 --methods stored emd
    python benchmarks/scale.py --device cuda --sizes 3400 10000 50000 --methods matrix-free stored
    python benchmarks/scale.py --sizes 5000 10000 20000 50000 --methods exact-matrix-free exact emd
    python benchmarks/scale.py --sizes 3400 10000 --methods partial-exact partial-anneal emd

Methods: ``exact`` (solve_balanced's default on the dense C: the transport LP by column generation, exact and
certified), ``exact-matrix-free`` (the same on a FeatureCost: the pricing passes recompute C in the kernels, no
N x N array), ``stored`` (solve_balanced(method="anneal") on the dense C: O(N^2) memory for C and the Hessian weights), ``stored-ipm``
(the same with method="ipm": two more N x N arrays, the primal plan and the reduced costs), ``matrix-free``
(solve_balanced(wpot.ot.FeatureCost(X, Y, "l2"), method="anneal"): C recomputed inside the kernels, O(N d) memory; skipped with a note
when this wpot has no FeatureCost) and ``emd`` (POT's exact network simplex on the dense C, numItermax raised so that
it reaches optimality). Partial transport (the chi^2 problem, Eq. 17, with the comparison's default mass penalty
`wpot.comparison.solver_mass_penalty` at kappa = 0.01): ``partial-exact`` (solve_partial's default, the QP by column
generation, certified), ``partial-exact-matrix-free`` (the same on a FeatureCost) and ``partial-anneal``
(method="anneal"); their U column is the objective (Eq. 17), ot.emd the time reference on the same cost (a
different problem: no gap). Timings on a shared machine are noisy; memory is exact.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time

METHODS = ("exact", "exact-matrix-free", "stored", "stored-ipm", "matrix-free", "emd", "partial-exact",
           "partial-exact-matrix-free", "partial-anneal")
#: (N x N float64 arrays, O(N d)) each method holds at its peak: refused up front, with the figure, when they do
#: not fit in the memory available (a run that the OS kills for memory could take other jobs with it)
DENSE_ARRAYS = {"exact": 2, "stored": 3, "stored-ipm": 4, "emd": 2, "exact-matrix-free": 0, "matrix-free": 0,
                "partial-exact": 2, "partial-exact-matrix-free": 0, "partial-anneal": 3}


def features(n: int, d: int, seed: int):
    import numpy as np

    rng = np.random.default_rng(seed)
    return rng.random((n, d)), rng.random((n, d))


def child(method: str, n: int, d: int, device: str) -> dict:
    """One run in this process; returns the figures as a dict (printed as JSON by ``--child``)."""
    import resource

    import numpy as np

    X, Y = features(n, d, seed=n)
    out: dict = {"method": method, "n": n}
    if method == "emd":
        import ot

        t0 = time.perf_counter()
        C = ot.dist(X, Y, metric="euclidean")
        G = ot.emd(np.full(n, 1.0 / n), np.full(n, 1.0 / n), C, numItermax=max(100_000, 50 * n * n))
        out["time"] = time.perf_counter() - t0
        out["cost"] = float((G * C).sum())
        out["converged"] = True
    else:
        import wpot.ot as wo

        if method.endswith("matrix-free"):
            if not hasattr(wo, "FeatureCost"):
                return {"method": method, "n": n, "skipped": "this wpot has no matrix-free mode (wpot.ot.FeatureCost)"}
            cost = wo.FeatureCost(X, Y, metric="l2", device=device)
        else:
            from wpot.cost import cost_matrix

            cost = None
        for m in ("anneal", "ipm", "exact"):  # compile outside the timing
            wo.solve_balanced(np.random.default_rng(0).random((60, 60)), device=device, method=m)
            if m != "ipm":
                wo.solve_balanced(wo.FeatureCost(X[:60], Y[:60], metric="l2", device=device), device=device, method=m)
        t0 = time.perf_counter()
        if cost is None:
            cost = cost_matrix(X, Y, metric="l2", device=device, out="warp")
        if method.startswith("partial"):
            # the comparison's relative penalty (`wpot.comparison.solver_mass_penalty`: kappa mean(C) / N, kappa
            # = 0.01), the mean over 200 rows of C, computed outside the timing
            rows = range(0, n, max(1, n // 200))
            mp = 0.01 * float(np.mean([np.linalg.norm(X[i] - Y, axis=1).mean() for i in rows])) / n
            t0 = time.perf_counter()
            r = wo.solve_partial(cost, device=device, mass_penalty=mp, dense_plan=False,
                                 method="anneal" if method == "partial-anneal" else "exact")
            out["mass_penalty"] = mp
        else:
            solver = {"stored-ipm": "ipm", "exact": "exact", "exact-matrix-free": "exact"}.get(method, "anneal")
            r = wo.solve_balanced(cost, device=device, method=solver, dense_plan=False)
        out["time"] = time.perf_counter() - t0
        out["cost"] = float(r.objective)
        out["converged"] = bool(r.converged)
        out["n_newton"] = int(r.n_newton)
        out["n_linear"] = int(r.n_linear)
        out["gap_bound_rel"] = float(r.history[-1].gap_bound / r.cost)
    if device.startswith("cuda") and method != "emd":
        import warp as wp

        out["gpu_peak_mb"] = float(wp.get_mempool_used_mem_high(device)) / 2**20 if hasattr(
            wp, "get_mempool_used_mem_high") else math.nan
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def blas_threads() -> str:
    """BLAS threads of the runs: $OPENBLAS_NUM_THREADS, or every core (the matrix-free exact solve's passes on
    the CPU use BLAS for the inner products, `wpot.ot.gram`; the annealing and ot.emd run on one core)."""
    return os.environ.get("OPENBLAS_NUM_THREADS", str(os.cpu_count() or 1))


def run_one(method: str, n: int, d: int, device: str, timeout: float) -> dict:
    need = DENSE_ARRAYS[method] * 8.0 * n * n
    if need:
        from wpot._warp import available_memory

        avail = available_memory("cpu")
        if need > avail:
            return {"method": method, "n": n, "failed": f"needs {DENSE_ARRAYS[method]} N x N float64 arrays, "
                    f"{need / 2**30:.1f} GiB, more than the {avail / 2**30:.1f} GiB available: not run"}
    cmd = [sys.executable, os.path.abspath(__file__), "--child", method, str(n), str(d), device]
    env = dict(os.environ, OPENBLAS_NUM_THREADS=blas_threads())
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {"method": method, "n": n, "failed": f"killed after {timeout:.0f} s"}
    if p.returncode != 0:
        tail = (p.stderr or p.stdout).strip().splitlines()[-1:] or ["?"]
        why = "out of memory (killed)" if p.returncode in (-9, 137) else f"exit {p.returncode}: {tail[0][:120]}"
        return {"method": method, "n": n, "failed": why, "wall": time.perf_counter() - t0}
    for line in reversed(p.stdout.strip().splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    return {"method": method, "n": n, "failed": "no result printed"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[500, 1000, 2000, 3400, 5000])
    ap.add_argument("--dim", type=int, default=100, help="signature dimension d (default 100, as WKS)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run before it is killed")
    ap.add_argument("--json", default=None, help="also write all rows to this JSON file")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        method, n, d, device = a.child
        print(json.dumps(child(method, int(n), int(d), device)), flush=True)
        return

    print(f"OT, N x N, L2 costs of random signatures in R^{a.dim}, device {a.device}, "
          f"OPENBLAS_NUM_THREADS={blas_threads()}")
    print(f"{'N':>7} {'method':<26} {'time s':>9} {'peak RSS MB':>12} {'dense C MB':>11} {'U':>14} "
          f"{'gap vs emd':>11}  note")
    rows = []
    dead: set[str] = set()
    for n in a.sizes:
        res = {}
        for m in a.methods:
            if m in dead:
                res[m] = {"method": m, "n": n, "failed": "skipped (failed at a smaller N)"}
            else:
                res[m] = run_one(m, n, a.dim, a.device, a.timeout)
                if "failed" in res[m]:
                    dead.add(m)
        u_emd = res.get("emd", {}).get("cost")
        for m in a.methods:
            r = res[m]
            rows.append(r)
            dense_mb = 8.0 * n * n / 2**20
            if "time" in r:
                gap = ("" if u_emd is None or m == "emd" or m.startswith("partial")
                       else f"{(r['cost'] - u_emd) / u_emd:.1e}")
                note = []
                if r.get("n_newton"):
                    note.append(f"newton {r['n_newton']} cg {r['n_linear']}")
                if "gap_bound_rel" in r:
                    note.append(f"certified gap {r['gap_bound_rel']:.1e}")
                if r.get("converged") is False:
                    note.append("NOT converged")
                if "gpu_peak_mb" in r:
                    note.append(f"GPU peak {r['gpu_peak_mb']:.0f} MB")
                print(f"{n:>7} {m:<26} {r['time']:>9.2f} {r['peak_rss_mb']:>12.0f} {dense_mb:>11.0f} "
                      f"{r['cost']:>14.8g} {gap:>11}  {'; '.join(note)}", flush=True)
            else:
                print(f"{n:>7} {m:<26} {'-':>9} {'-':>12} {dense_mb:>11.0f} {'-':>14} {'':>11}  "
                      f"{r.get('failed') or r.get('skipped')}", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
