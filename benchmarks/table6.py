"""Time per pair at full resolution on TOSCA8, the four combinations (paper Table 6; issue 20).

For each pair of TOSCA8 shapes (TOSCA's low-resolution set, every vertex: ~3,400 x 3,400) and each combination
(WKS / LD-SIFT x balanced / partial) with wpot's defaults, it times, in one process:

* ``sig``: the signatures of both shapes (spectrum, WKS or depth images + SIFT), once per shape; cold unless
  ``$WPOT_CACHE_DIR`` holds the spectra (`benchmarks/signatures.py` times them cold);
* ``cost``: the cost matrix (Eq. 29 for WKS, L2 for LD-SIFT);
* ``transport``: wpot's transport as `Comparer` runs it (the default exact solver: the transport LP for
  balanced, the chi^2 QP for partial); with ``--anneal-peer``, partial combinations are also annealed
  (``method="anneal"``, the solver that records D(beta)) in the same run; for partial also ``self``, the
  two self-comparisons of Eq. 27 (computed once per shape in an all-vs-all run, so not part of the per-pair
  time there);
* the peer, ``ot.emd`` (numItermax 1e9, its warning checked) on the same cost with uniform masses: the same
  problem for balanced transport (the gap to it is printed), the time reference for partial.

The paper's Table 6 (TOSCA8 at full resolution, its own code): 1,496 s per pair on its CPU1 (iterative
solver), 6.2 s on a GPU. Results are appended to ``--out`` (JSON lines), so a run resumes where it stopped.

    python benchmarks/table6.py --out /tmp/table6.jsonl [--pairs 2] [--combos wks:balanced ldsift:partial]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

COMBOS = ("wks:balanced", "ldsift:balanced", "wks:partial", "ldsift:partial")
#: the paper's Table 6 per-pair times on TOSCA8, seconds
PAPER = {"CPU1 (iterative)": 1496.0, "GPU": 6.2}
#: pairs of TOSCA8 shapes (its first shapes of two classes each, and a cross-class pair)
PAIRS = (("cat0", "cat1"), ("horse0", "horse2"), ("david0", "michael1"), ("dog0", "centaur0"))


def _data() -> Path:
    here = Path(__file__).resolve().parents[1]
    return Path(os.environ.get("WPOT_DATA", here.parent / "shared" / "data"))


def run_pair(pair, combo: str, folder: Path, device: str, anneal_peer: bool = False) -> dict:
    import numpy as np
    import ot

    import wpot

    sig, transport = combo.split(":")
    meshes = [wpot.load_mesh(folder / f"{n}.mat") for n in pair]
    comparer = wpot.Comparer(signature=sig, transport=transport, device=device, max_vertices=None, cache_dir=False)
    t = time.perf_counter()
    comparer.fit(meshes)
    pts = [comparer.points(m) for m in meshes]
    t_sig = time.perf_counter() - t
    t = time.perf_counter()
    problem = comparer.transport_problem(*pts)
    t_cost = time.perf_counter() - t
    t_self = 0.0
    if transport == "partial":
        t = time.perf_counter()
        for m in meshes:
            comparer.self_energy(m)
        t_self = time.perf_counter() - t
    t = time.perf_counter()
    res = comparer.solver.solve(problem)
    t_ot = time.perf_counter() - t
    C = problem.cost if isinstance(problem.cost, np.ndarray) else problem.cost.numpy()
    n1, n2 = C.shape
    t = time.perf_counter()
    G, log = ot.emd(np.full(n1, 1 / n1), np.full(n2, 1 / n2), C, numItermax=10**9, log=True)
    t_emd = time.perf_counter() - t
    u_emd = float((G * C).sum())
    out = {"pair": "-".join(pair), "combo": combo, "n1": n1, "n2": n2, "sig_s": t_sig, "cost_s": t_cost,
           "transport_s": t_ot, "self_s": t_self, "emd_s": t_emd, "emd_warning": log["warning"] or "",
           "converged": bool(res.converged), "method": comparer.solver.method_for(problem)
           if hasattr(comparer.solver, "method_for") else comparer.solver.name,
           "objective": float(res.objective), "emd_cost": u_emd}
    if transport == "balanced":
        out["gap_to_emd"] = (float(res.cost) - u_emd) / u_emd
    else:
        out["gap_bound_rel"] = res.history[-1].gap_bound / float(res.objective)
    if anneal_peer and transport == "partial":
        t = time.perf_counter()
        ra = wpot.ot.make_solver("anneal").solve(problem)
        out.update(anneal_s=time.perf_counter() - t, anneal_objective=float(ra.objective),
                   anneal_converged=bool(ra.converged))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="JSON-lines file, appended to (resumable)")
    ap.add_argument("--pairs", type=int, default=2, help=f"how many of {PAIRS} (default 2)")
    ap.add_argument("--combos", nargs="+", default=list(COMBOS), choices=COMBOS)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", type=Path, default=_data(), help="the shared data folder (default ../shared/data)")
    ap.add_argument("--anneal-peer", action="store_true",
                    help="also anneal the partial combinations (method='anneal', 2-5 min a pair here), timed in the "
                         "same run")
    a = ap.parse_args()
    folder = a.data / "tosca_lowres"
    if not folder.is_dir():
        print(f"skipped: {folder} not found (set --data or WPOT_DATA)")
        return 0
    done = {}  # (pair, combination) -> its record, from an earlier run into the same --out
    if a.out.is_file():
        for line in a.out.read_text().splitlines():
            r = json.loads(line)
            done[r["pair"], r["combo"]] = r
    print(f"TOSCA8 pairs at full resolution, device {a.device}; paper Table 6: "
          + ", ".join(f"{k} {v:g} s" for k, v in PAPER.items()))
    print(f"{'pair':<18} {'combination':<16} {'N1 x N2':>11} {'sig s':>7} {'cost s':>7} {'OT s':>8} {'self s':>7} "
          f"{'pair s':>8} {'ot.emd s':>9}  note")
    for pair in PAIRS[:a.pairs]:
        for combo in a.combos:
            r = done.get(("-".join(pair), combo))
            if r is None or (a.anneal_peer and combo.endswith("partial") and "anneal_s" not in r):
                r = run_pair(pair, combo, folder, a.device, a.anneal_peer)
                with open(a.out, "a") as fh:
                    fh.write(json.dumps(r) + "\n")
            per_pair = r["cost_s"] + r["transport_s"]
            note = [r["method"], "converged" if r["converged"] else "NOT converged"]
            if "gap_to_emd" in r:
                note.append(f"gap to ot.emd {r['gap_to_emd']:.1e}")
            if "gap_bound_rel" in r:
                note.append(f"certified gap {r['gap_bound_rel']:.1e}")
            if "anneal_s" in r:
                rel = (r["anneal_objective"] - r["objective"]) / r["objective"]
                note.append(f"annealing {r['anneal_s']:.1f} s, objective {rel:+.1e} relative"
                            + ("" if r["anneal_converged"] else ", NOT converged"))
            if r["emd_warning"]:
                note.append(f"ot.emd warning: {r['emd_warning']}")
            print(f"{r['pair']:<18} {combo:<16} {r['n1']:>5}x{r['n2']:<5} {r['sig_s']:>7.1f} {r['cost_s']:>7.1f} "
                  f"{r['transport_s']:>8.1f} {r['self_s']:>7.1f} {per_pair:>8.1f} {r['emd_s']:>9.1f}  {'; '.join(note)}",
                  flush=True)
    print("pair s = cost + OT (signatures are computed once per shape and the self-comparisons once per shape in an "
          "all-vs-all run)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
