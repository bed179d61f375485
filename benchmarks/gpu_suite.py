"""Every GPU figure wpot reports, in one call (a lent GPU machine has ~15 minutes in all): agreement of the
device with the CPU, then the solver's timings beside their peers, all in the same run.

    python benchmarks/gpu_suite.py --device cuda [--out DIR]      # on a GPU machine (a few minutes on an H200)
    python benchmarks/gpu_suite.py --device cpu --small           # the same suite at small sizes (a few minutes here)

On a GPU machine warp-lang is not installed and its wheel travels in three calls (../shared/tools/warp-for-gpu.sh
says how); POT, when installed there, is the exact peer (`ot.emd` with numItermax=1e9, its log's warning checked).
Nothing here reads ../shared (it does not travel to that machine): the meshes are generated (`wpot.examples`).

Sections, each printed as a table and saved to ``DIR/gpu_suite.json`` when ``--out`` is given:

1. environment: Warp's version and devices;
2. agreement: the same problems solved on ``--device`` and on "cpu" (the exact LP, stored and matrix-free,
   balanced annealing, the interior-point start, partial transport exact and annealed, the matrix-free
   annealing): relative
   difference of U and the largest marginal difference (the kernels use no fused multiply-add, so the two
   devices agree to rounding);
3. a TOSCA-sized pair (two generated shapes of 5,000 vertices, or 800 with ``--small``; WKS cost): wpot's default
   solver (the exact LP) and the interior-point annealing beside ``ot.emd`` and MDOT-TNT (when installed:
   ``pip install mdot-tnt`` with PyTorch; `_mdot`) on the same cost, with the gaps; and partial transport on
   the same cost (the comparison's default mass penalty), exact (the default);
4. large matrix-free problems (random L2 costs in R^100, N = 20,000 and 50,000 on a GPU, 300 with ``--small``):
   the exact LP to the end, with its certified gap (the dual bound over all N^2 entries), and the annealing
   for its first 12 (4) betas;
5. host-device transfers of each run above on ``--device``: for the annealing per Newton step and per CG
   iteration, as the engine counts them (`wpot.ot.anneal.state.Timers`: the same counts on every device, up to the
   end of the annealing), in the device-resident Newton loop (`wpot.ot.anneal.resident`, the default on a GPU) and
   the host loop; for the exact LP per pricing round (`wpot.ot.exact.balanced.Round`). Device-to-host reads are the
   synchronisations on a GPU;
6. a batch of pairs (500 pairs of 300 points; 20 of 100 with ``--small``): `wpot.ot.solve_batch`, whose
   pricing passes share one launch a round, in pairs per second beside the same pairs solved one by one and
   beside ``ot.emd`` and MDOT-TNT's batched solver, and whether every result equals the one-pair solve;
7. what could not be run here (a peer not installed), printed as not available.
"""
from __future__ import annotations

import argparse
import json
import time
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np


def _emd(a, b, C):
    """POT's exact network simplex (None when POT is not installed), with its early stop ruled out."""
    try:
        import ot
    except ImportError:
        return None
    t = time.perf_counter()
    G, log = ot.emd(a, b, C, numItermax=int(1e9), log=True)
    if log.get("warning"):
        raise RuntimeError(f"ot.emd stopped early: {log['warning']}")
    return float((G * C).sum()), time.perf_counter() - t


#: MDOT-TNT's final inverse temperature on costs scaled to [0, 1]: its authors' largest stable value (float64)
MDOT_GAMMA = 2.0 ** 18


def _mdot(costs: list[np.ndarray], device: str, gamma: float = MDOT_GAMMA):
    """MDOT-TNT (Kemertas et al., ICLR 2025: annealed entropic OT by truncated Newton, PyTorch), the closest
    published method, on the same costs with uniform marginals: None when it is not installed (``pip install
    mdot-tnt`` and PyTorch; a benchmark peer only, under a non-commercial licence). Each cost is scaled to
    [0, 1] as its authors recommend and its transport cost (the Altschuler-rounded, feasible plan's) scaled
    back. One cost: `solve_OT`; several of one shape: `solve_OT_batched` in one call. Returns (costs, seconds),
    the time including the transfer of the costs to ``device``."""
    try:
        import torch
        from mdot_tnt import solve_OT, solve_OT_batched
    except ImportError:
        return None
    dev = "cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu"
    scale = np.array([float(np.max(C)) for C in costs])
    n, m = costs[0].shape
    solve_OT(torch.full((8,), 1 / 8, dtype=torch.float64, device=dev), torch.full((8,), 1 / 8, dtype=torch.float64,
             device=dev), torch.rand(8, 8, dtype=torch.float64, device=dev), gamma_f=64.0)  # warm-up
    t = time.perf_counter()
    r = torch.full((n,), 1.0 / n, dtype=torch.float64, device=dev)
    c = torch.full((m,), 1.0 / m, dtype=torch.float64, device=dev)
    if len(costs) == 1:
        out = [float(solve_OT(r, c, torch.as_tensor(costs[0] / scale[0], device=dev), gamma_f=gamma))]
    else:
        Cb = torch.as_tensor(np.stack([C / k for C, k in zip(costs, scale)]), device=dev)
        b = len(costs)
        out = solve_OT_batched(r.expand(b, n).contiguous(), c.expand(b, m).contiguous(), Cb, gamma_f=gamma)
        out = [float(x) for x in out.cpu()]
    secs = time.perf_counter() - t
    return np.asarray(out) * scale, secs


def _random_problem(n: int, dim: int, seed: int):
    rng = np.random.default_rng(seed)
    x, y = rng.random((n, dim)), rng.random((n, dim))
    return x, y


@contextmanager
def engine_timers():
    """Collects each solve's engine timers (`wpot.ot.anneal.state.Timers.as_dict`, taken when its annealing
    returns, as benchmarks/ot_speed.py takes them) into the yielded list."""
    from wpot.ot.anneal import balanced, partial

    got: list[dict] = []
    originals = (balanced.anneal, partial.anneal)

    def wrap(orig):
        def anneal(eng, fe, **kw):
            out = orig(eng, fe, **kw)
            got.append(eng.t.as_dict())
            return out
        return anneal

    balanced.anneal, partial.anneal = wrap(originals[0]), wrap(originals[1])
    try:
        yield got
    finally:
        balanced.anneal, partial.anneal = originals


def transfers(tm: dict | None) -> dict:
    """Host-device transfers of one annealing solve (its engine timers) in all and per Newton step and CG
    iteration (zeros when the solve had no annealing)."""
    if tm is None:
        tm = {"n_newton": 0, "n_matvec": 0, "n_d2h": 0, "n_h2d": 0, "n_factor": 0, "n_build_sync": 0}
    nn, nm = max(tm["n_newton"], 1), max(tm["n_matvec"], 1)
    return {"n_newton": tm["n_newton"], "n_cg": tm["n_matvec"], "n_d2h": tm["n_d2h"], "n_h2d": tm["n_h2d"],
            "n_factor": tm["n_factor"], "factor_per_newton": tm["n_factor"] / nn,
            "syncs_per_newton_with_builds": (tm["n_d2h"] + tm["n_build_sync"]) / nn,
            "d2h_per_newton": tm["n_d2h"] / nn, "h2d_per_newton": tm["n_h2d"] / nn,
            "d2h_per_cg": tm["n_d2h"] / nm, "h2d_per_cg": tm["n_h2d"] / nm}


def exact_solve(C, device: str, mass_penalty: float | None = None) -> tuple:
    """wpot's exact solver on ``C`` (a matrix or a FeatureCost; partial with ``mass_penalty``): (result, seconds,
    its pricing rounds)."""
    import wpot.ot as wo
    from wpot.ot.exact import solve_exact_problem

    rounds: list = []
    t = time.perf_counter()
    r = solve_exact_problem(wo.TransportProblem(C, device=device, mass_penalty=mass_penalty), wo.SolverOptions(),
                            on_round=rounds.append)
    return r, time.perf_counter() - t, rounds


def round_transfers(rounds: list) -> dict:
    """Host-device transfers of an exact solve, in all and per pricing round."""
    n = max(len(rounds), 1)
    d2h, h2d = sum(x.n_d2h for x in rounds), sum(x.n_h2d for x in rounds)
    return {"n_rounds": len(rounds), "n_d2h": d2h, "n_h2d": h2d, "d2h_per_round": d2h / n, "h2d_per_round": h2d / n}


def environment(device: str) -> dict:
    import warp as wp

    from wpot._warp import resolve_device

    dev = resolve_device(device)
    out = {"warp": wp.__version__, "device": str(dev), "cuda_devices": wp.get_cuda_device_count()}
    if dev.is_cuda:
        out["gpu"] = dev.name
    return out


def agreement(device: str, n: int) -> list[dict]:
    """The same problems on ``device`` and on "cpu"."""
    import wpot.ot as wo
    from wpot.cost import cost_matrix

    x, y = _random_problem(n, 8, 1)
    C = cost_matrix(x, y, metric="l2", device="cpu")
    cases = {
        "balanced, exact": lambda d: wo.solve_balanced(C, device=d, method="exact"),
        "balanced, exact matrix-free": lambda d: wo.solve_balanced(wo.FeatureCost(x, y, "l2", device=d), device=d,
                                                                  method="exact"),
        "balanced, anneal, device loop": lambda d: wo.solve_balanced(C, device=d, method="anneal",
                                                                     newton_loop="device"),
        "balanced, anneal, host loop": lambda d: wo.solve_balanced(C, device=d, method="anneal", newton_loop="host"),
        "balanced, ipm, device loop": lambda d: wo.solve_balanced(C, device=d, method="ipm", newton_loop="device"),
        "partial (mass_penalty 0.05), exact": lambda d: wo.solve_partial(C, mass_penalty=0.05, device=d),
        "partial (mass_penalty 0.05), anneal, device loop": lambda d: wo.solve_partial(
            C, mass_penalty=0.05, device=d, method="anneal", newton_loop="device"),
        "balanced, matrix-free, device loop": lambda d: wo.solve_balanced(
            wo.FeatureCost(x, y, "l2", device=d), device=d, method="anneal", newton_loop="device"),
    }
    rows = []
    for name, solve in cases.items():
        t = time.perf_counter()
        with engine_timers() as tms:
            r = solve(device)
        secs = time.perf_counter() - t
        ref = solve("cpu") if device != "cpu" else r
        rows.append({
            "problem": f"{name}, N = {n}",
            "converged": bool(r.converged and ref.converged),
            "rel_diff_U": abs(r.cost - ref.cost) / abs(ref.cost),
            "max_marginal_diff": float(max(np.abs(r.mass1 - ref.mass1).max(), np.abs(r.mass2 - ref.mass2).max())),
            "seconds": secs,
            "transfers": transfers(tms[-1] if tms else None),
        })
    return rows


def tosca_sized_pair(device: str, n: int) -> dict:
    """Two generated shapes of ``n`` vertices, WKS (as all-vs-all computes it), wpot's default solver."""
    import wpot
    from wpot.cost import cost_matrix

    pair = wpot.examples.example_pair(n, seed=0, n_target=n)
    comparer = wpot.Comparer(signature="wks", device=device, cache_dir=False)
    comparer.fit([pair.source, pair.target])
    pa, pb = comparer.points(pair.source), comparer.points(pair.target)
    C = cost_matrix(pa.signatures, pb.signatures, metric="wks", device="cpu")
    for method in ("exact", "ipm"):  # compile the kernels outside the timing
        wpot.ot.solve_balanced(C[:60, :60], device=device, method=method)
    r, secs, rounds = exact_solve(C, device)
    row = {"problem": f"WKS pair, {n} x {n} vertices (exact, the default)", "seconds": secs, "U": r.cost,
           "converged": bool(r.converged), "gap_bound_rel": r.history[0].gap_bound / r.cost,
           "round_transfers": round_transfers(rounds)}
    # the device loop with its default preconditioner (the multilevel V-cycle) and with FSAI alone: fewer CG
    # iterations against fewer kernel launches per iteration, which only a GPU can weigh; and the host loop
    for key, kw in (("", {"newton_loop": "device"}),
                    ("fsai_", {"newton_loop": "device", "device_preconditioner": "fsai"}),
                    ("host_", {"newton_loop": "host"})):
        t = time.perf_counter()
        with engine_timers() as tms:
            ri = wpot.ot.solve_balanced(C, device=device, method="ipm", **kw)
        row.update({f"{key}ipm_seconds": time.perf_counter() - t, f"{key}ipm_U": ri.cost,
                    f"{key}n_newton": ri.n_newton, f"{key}transfers": transfers(tms[-1])})
    a = np.full(n, 1.0 / n)
    emd = _emd(a, a, C)
    if emd is not None:
        row.update(emd_U=emd[0], emd_seconds=emd[1], gap=(r.cost - emd[0]) / emd[0], ipm_gap=(ri.cost - emd[0]) / emd[0])
    md = _mdot([np.asarray(C)], device)
    if md is not None:
        row.update(mdot_U=float(md[0][0]), mdot_seconds=md[1], mdot_gap=(float(md[0][0]) - r.cost) / r.cost)
    from wpot.comparison import solver_mass_penalty
    from wpot.config import DEFAULT_MASS_PENALTY

    rp, secs, rounds = exact_solve(C, device, solver_mass_penalty(C, DEFAULT_MASS_PENALTY))
    row.update(partial_seconds=secs, partial_converged=bool(rp.converged), partial_rounds=len(rounds),
               partial_gap_bound_rel=rp.history[0].gap_bound / rp.objective)
    return row


def large_exact(device: str, n: int) -> dict:
    """Random L2 costs in R^100, cost recomputed in the kernels (no N x N array), the exact LP to the end."""
    import wpot.ot as wo

    x, y = _random_problem(n, 100, 2)
    r, secs, rounds = exact_solve(wo.FeatureCost(x, y, "l2", device=device), device)
    return {"problem": f"exact LP, matrix-free L2 in R^100, N = {n}", "seconds": secs, "converged": bool(r.converged),
            "gap_bound_rel": r.history[0].gap_bound / r.cost, "rounds": len(rounds),
            "t_lp": sum(x.t_lp for x in rounds), "t_pass": sum(x.t_price for x in rounds),
            "support": rounds[-1].support, "round_transfers": round_transfers(rounds)}


def large_matrix_free(device: str, n: int, max_iter: int) -> dict:
    """Random L2 costs in R^100, cost recomputed in the kernels (no N x N array)."""
    import wpot.ot as wo

    x, y = _random_problem(n, 100, 2)
    t = time.perf_counter()
    # capped at max_iter betas: "not converged" is expected and reported below
    with warnings.catch_warnings(), engine_timers() as tms:
        warnings.simplefilter("ignore", RuntimeWarning)
        r = wo.solve_balanced(wo.FeatureCost(x, y, "l2", device=device), device=device, max_iter=max_iter, method="anneal")
    secs = time.perf_counter() - t
    last = r.history[-1]
    return {"problem": f"matrix-free L2 in R^100, N = {n}", "seconds": secs, "converged": bool(r.converged),
            "betas": len(r.history), "gap_bound_rel": last.gap_bound / abs(r.cost), "n_newton": r.n_newton,
            "transfers": transfers(tms[-1])}


def batch_of_pairs(device: str, n_pairs: int, n: int) -> dict:
    """``n_pairs`` random L2 problems of ``n`` points in R^8 (stored costs), solved as one batch and one by one."""
    import wpot.ot as wo
    from wpot.cost import cost_matrix

    problems = []
    for i in range(n_pairs):
        x, y = _random_problem(n, 8, 100 + i)
        problems.append(wo.TransportProblem(cost_matrix(x, y, metric="l2", device=device, out="warp"), device=device))
    wo.solve_batch(problems[:2])  # compile outside the timing
    t = time.perf_counter()
    batch = wo.solve_batch(problems, dense_plan=False)
    t_batch = time.perf_counter() - t
    t = time.perf_counter()
    single = [wo.solve_balanced(p.cost, device=device, dense_plan=False) for p in problems]
    t_single = time.perf_counter() - t
    row = {"problem": f"batch of {n_pairs} pairs of {n} points", "pairs_per_s": n_pairs / t_batch,
           "single_pairs_per_s": n_pairs / t_single,
           "identical": all(b.cost == s.cost and np.array_equal(b.lam, s.lam) for b, s in zip(batch, single))}
    import ot  # a dependency of wpot (its exact solver's LP)

    a = np.full(n, 1.0 / n)
    costs = [p.cost.numpy() for p in problems]
    t = time.perf_counter()
    for C in costs:
        ot.emd(a, a, C, numItermax=int(1e9))
    row["emd_pairs_per_s"] = n_pairs / (time.perf_counter() - t)
    md = _mdot(costs, device)
    if md is not None:
        exact = np.array([b.cost for b in batch])
        gap = (md[0] - exact) / exact  # its batched solver returns NaN for some problems at large gamma
        ok = np.isfinite(gap)
        row.update(mdot_pairs_per_s=n_pairs / md[1], mdot_failed=int((~ok).sum()),
                   mdot_max_gap=float(gap[ok].max()) if ok.any() else float("nan"))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda", help='Warp device (default "cuda")')
    ap.add_argument("--small", action="store_true", help="small sizes, for the CPU (a few minutes)")
    ap.add_argument("--out", default=None, help="folder for gpu_suite.json, rewritten after each section (a run "
                    "stopped at its time limit keeps what it finished)")
    ap.add_argument("--n-agree", type=int, default=None, help="size of the agreement problems (default 1000; 200 "
                    "with --small)")
    ap.add_argument("--n-exact", type=int, nargs="*", default=None, help="sizes of the large exact LPs (default "
                    "20000 50000; 300 with --small)")
    a = ap.parse_args()
    n_agree, n_pair, n_large, max_iter = (200, 800, 300, 4) if a.small else (1000, 5000, 20000, 12)
    n_exact = (300,) if a.small else (20000, 50000)
    n_agree = a.n_agree or n_agree
    n_exact = n_exact if a.n_exact is None else tuple(a.n_exact)
    n_batch, n_batch_points = (20, 100) if a.small else (500, 300)
    report: dict = {"environment": environment(a.device)}
    print("environment:", report["environment"])

    def save() -> None:
        if a.out:
            out = Path(a.out)
            out.mkdir(parents=True, exist_ok=True)
            (out / "gpu_suite.json").write_text(json.dumps(report, indent=2, default=float))

    report["agreement"] = agreement(a.device, n_agree)
    print(f"\n{'agreement with the CPU':<44} {'conv':>5} {'rel diff U':>11} {'max marg diff':>14} {'s':>8}")
    for r in report["agreement"]:
        print(f"{r['problem']:<44} {str(r['converged']):>5} {r['rel_diff_U']:>11.2e} {r['max_marginal_diff']:>14.2e} "
              f"{r['seconds']:>8.2f}")

    save()
    r = report["pair"] = tosca_sized_pair(a.device, n_pair)
    peer = (f"ot.emd {r['emd_seconds']:.2f} s; gaps {r['gap']:.1e} (exact), {r['ipm_gap']:.1e} (ipm)"
            if "emd_seconds" in r else "ot.emd: POT not installed here")
    print(f"\n{r['problem']}: {r['seconds']:.2f} s, converged {r['converged']}, certified gap "
          f"{r['gap_bound_rel']:.1e}; ipm {r['ipm_seconds']:.2f} s ({r['n_newton']} Newton steps, "
          f"{r['transfers']['n_cg']} CG iterations, device loop), {r['fsai_ipm_seconds']:.2f} s ({r['fsai_n_newton']}, "
          f"{r['fsai_transfers']['n_cg']}, device loop with FSAI alone), {r['host_ipm_seconds']:.2f} s "
          f"({r['host_n_newton']}, {r['host_transfers']['n_cg']}, host loop); {peer}")
    if "mdot_seconds" in r:
        print(f"  MDOT-TNT (gamma {MDOT_GAMMA:g} on costs scaled to [0, 1]) on the same cost: "
              f"{r['mdot_seconds']:.2f} s, its plan {r['mdot_gap']:.1e} above the exact optimum")
    print(f"  partial transport on the same cost (exact, the default): {r['partial_seconds']:.2f} s, "
          f"{r['partial_rounds']} rounds, converged {r['partial_converged']}, certified gap "
          f"{r['partial_gap_bound_rel']:.1e} of the objective")

    save()
    r = report["batch"] = batch_of_pairs(a.device, n_batch, n_batch_points)
    print(f"\n{r['problem']}: {r['pairs_per_s']:.1f} pairs/s (one by one {r['single_pairs_per_s']:.1f}; ot.emd "
          f"{r['emd_pairs_per_s']:.1f} pairs/s); "
          f"every result equal to its one-pair solve: {r['identical']}")
    if "mdot_pairs_per_s" in r:
        print(f"  MDOT-TNT, the same pairs in one batched call: {r['mdot_pairs_per_s']:.1f} pairs/s, its plans up to "
              f"{r['mdot_max_gap']:.1e} above the exact optima, {r['mdot_failed']} of {n_batch} results NaN")

    save()
    report["large_exact"] = [large_exact(a.device, n) for n in n_exact]
    for r in report["large_exact"]:
        print(f"{r['problem']}: {r['seconds']:.1f} s ({r['rounds']} rounds: LP {r['t_lp']:.1f} s, passes "
              f"{r['t_pass']:.1f} s; support {r['support']}), certified gap {r['gap_bound_rel']:.1e} of U, "
              f"converged {r['converged']}")
    save()
    r = report["large"] = large_matrix_free(a.device, n_large, max_iter)
    print(f"{r['problem']}: {r['seconds']:.1f} s for {r['betas']} betas (max_iter {max_iter}), gap bound "
          f"{r['gap_bound_rel']:.1e} of U, converged {r['converged']}")

    print(f"\n{'host-device transfers on ' + a.device + ' (d2h: syncs)':<52} {'newton':>6} {'cg':>6} "
          f"{'d2h/newton':>10} {'h2d/newton':>10} {'d2h/cg':>7} {'h2d/cg':>7} {'builds/newton':>13} "
          f"{'syncs/newton':>12}")
    pair = [dict(report["pair"], problem=report["pair"]["problem"] + ", ipm" + label, transfers=report["pair"][key])
            for label, key in (("", "transfers"), (" FSAI alone", "fsai_transfers"), (" host loop", "host_transfers"))]
    for r in [*report["agreement"], *pair, report["large"]]:
        tr = r["transfers"]
        print(f"{r['problem']:<52} {tr['n_newton']:>6} {tr['n_cg']:>6} {tr['d2h_per_newton']:>10.1f} "
              f"{tr['h2d_per_newton']:>10.1f} {tr['d2h_per_cg']:>7.2f} {tr['h2d_per_cg']:>7.2f} "
              f"{tr['factor_per_newton']:>13.2f} {tr['syncs_per_newton_with_builds']:>12.2f}")
    print("  (syncs/newton: d2h plus, for the device loop's full preconditioner builds, the synchronisations inside "
          "FSAI's set-up, wpot.ot.anneal.resident.BUILD_SYNCS each; its refits have none)")
    print(f"\n{'exact LP on ' + a.device + ' (d2h: syncs)':<44} {'rounds':>6} {'d2h/round':>10} {'h2d/round':>10}")
    for r in [report["pair"], *report["large_exact"]]:
        tr = r["round_transfers"]
        print(f"{r['problem']:<44} {tr['n_rounds']:>6} {tr['d2h_per_round']:>10.1f} {tr['h2d_per_round']:>10.1f}")

    save()
    report["not_available"] = {}
    if "mdot_seconds" not in report["pair"]:
        report["not_available"]["MDOT-TNT peer"] = "not run (pip install mdot-tnt, with PyTorch)"
    for k, v in report["not_available"].items():
        print(f"{k}: {v}")
    save()
    if a.out:
        print(f"saved {Path(a.out) / 'gpu_suite.json'}")


if __name__ == "__main__":
    main()
