"""Pairs per second of ``wpot all-vs-all`` on one machine, beside POT's ``ot.emd`` on the same pairs (issue 7).

Runs the product path exactly as a user would (``python -m wpot all-vs-all DATA --device D --jobs J``) for a
wall-clock budget, then stops it (the run is resumable, so stopping loses only the pairs in flight) and reads
the run's store: pairs committed, their per-pair seconds, and the steady rate between the first and the last
commit. The set-up before the first pair (spectra, energy grid, signatures, kernel compilation) is timed
apart. The estimate for the whole dataset is set-up + pairs / steady rate.

Peer, in the same run: ``ot.emd`` (exact network simplex) on the cost matrices of the first committed pairs,
rebuilt from the run's cached signatures, in ``J`` processes; its pairs per second and wpot's relative
gap to its optimum on those pairs are printed beside wpot's figures. While wpot runs, ``nvidia-smi`` (where
there is one) is sampled every 5 s for GPU utilisation and memory.

    python benchmarks/throughput.py ../shared/data/tosca_isometric_5k/vtx_5k --device cuda --jobs 12 --seconds 300
    python benchmarks/throughput.py DATA --device cpu --jobs 2 --seconds 600 --peer-pairs 4 --max-vertices 500

Options it does not know go to ``wpot all-vs-all``.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path


def gpu_sample() -> tuple[float, float] | None:
    """(utilisation %, memory used MiB) of GPU 0 from nvidia-smi, or None without one."""
    if shutil.which("nvidia-smi") is None:
        return None
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu,memory.used", "--format=csv,noheader,nounits"],
                             capture_output=True, text=True, timeout=10).stdout.splitlines()[0]
        u, m = (float(x) for x in out.split(","))
        return u, m
    except Exception:
        return None


def run_wpot(data: str, out: Path, device: str, jobs: int, seconds: float, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "wpot", "all-vs-all", data, "--out", str(out), "--device", device, "--jobs", str(jobs),
           "--no-progress", *extra]
    print("running:", " ".join(cmd), flush=True)
    t0 = time.time()
    proc = subprocess.Popen(cmd, start_new_session=True)
    samples = []
    while proc.poll() is None and time.time() - t0 < seconds:
        s = gpu_sample()
        if s is not None:
            samples.append(s)
        time.sleep(5.0)
    stopped = proc.poll() is None
    if stopped:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return dict(t0=t0, wall=time.time() - t0, stopped=stopped, rc=proc.returncode, gpu=samples)


def read_store(out: Path) -> dict:
    """The run's settings and its committed pairs (i, j, energy, seconds, finished_at, converged, n_newton,
    n_linear), oldest first, from its `wpot.runs.store.RunStore`."""
    from wpot.runs.store import RunStore

    with RunStore(out) as store:
        rows = store.con.execute("SELECT i, j, energy, seconds, finished_at, converged, n_newton, n_linear FROM pairs "
                                 "WHERE i <> j ORDER BY finished_at").fetchall()
        return dict(rows=rows, n_shapes=store.n_shapes, params=store.params, energies=store.get("energies"),
                    paths={r[0]: r[2] for r in store.shape_rows()})


def emd_pair(args) -> tuple[float, float]:
    """(seconds, optimal U) of ot.emd on one pair's cost matrix, rebuilt as the run built it."""
    import numpy as np
    import ot

    from wpot.comparison import Comparer
    from wpot.cost import cost_matrix
    from wpot.io import load_mesh

    pa, pb, opts, energies, cache = args
    c = Comparer(**opts, energies=energies, cache_dir=cache, device="cpu")
    xa, xb = c.points(load_mesh(pa)), c.points(load_mesh(pb))
    C = np.asarray(cost_matrix(xa.signatures, xb.signatures, metric=c.stage.metric, device="cpu"))
    t0 = time.perf_counter()
    a = xa.masses if xa.masses is not None else np.full(C.shape[0], 1.0 / C.shape[0])
    b = xb.masses if xb.masses is not None else np.full(C.shape[1], 1.0 / C.shape[1])
    G = ot.emd(a, b, C, numItermax=max(100_000, 50 * C.size))
    return time.perf_counter() - t0, float((G * C).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="folder of meshes (e.g. tosca_isometric_5k/vtx_5k)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--jobs", type=int, default=os.cpu_count())
    ap.add_argument("--seconds", type=float, default=300.0, help="wall-clock budget for wpot (default 300)")
    ap.add_argument("--out", default=None, help="run folder (default: a fresh one under /tmp)")
    ap.add_argument("--peer-pairs", type=int, default=None, help="pairs for the ot.emd peer (default: --jobs; 0: none)")
    ap.add_argument("--peer-seconds", type=float, default=240.0, help="stop waiting for the peer after this")
    args, extra = ap.parse_known_args()  # the rest goes to all-vs-all (e.g. --signature ldsift)
    out = Path(args.out or f"/tmp/wpot-throughput-{os.getpid()}")

    w = run_wpot(args.data, out, args.device, args.jobs, args.seconds, extra)
    st = read_store(out)
    rows = [r for r in st["rows"] if r[4] >= w["t0"]]  # this session's pairs (a resumed run holds earlier ones)
    n_pairs = st["n_shapes"] * (st["n_shapes"] - 1) // 2
    print(f"\nwpot all-vs-all, device {args.device}, {args.jobs} processes, {w['wall']:.0f} s "
          f"({'stopped' if w['stopped'] else 'finished'}, rc {w['rc']})")
    if not rows:
        print("  no pair committed within the budget")
        return
    first, last = rows[0][4], rows[-1][4]
    setup = first - w["t0"]
    secs = [r[3] for r in rows]
    rate = (len(rows) - 1) / (last - first) if len(rows) > 1 and last > first else float("nan")
    print(f"  set-up before the first pair {setup:.0f} s; pairs committed {len(rows)} of {n_pairs}; "
          f"not converged {sum(1 for r in rows if not r[5])}")
    print(f"  per pair (one process): median {statistics.median(secs):.1f} s, min {min(secs):.1f}, max {max(secs):.1f}; "
          f"Newton median {statistics.median(r[6] for r in rows)}, CG median {statistics.median(r[7] for r in rows)}")
    print(f"  steady rate {rate:.3f} pairs/s -> all {n_pairs} pairs in {(setup + n_pairs / rate) / 60:.1f} min (estimate)")
    if w["gpu"]:
        us = [u for u, _ in w["gpu"]]
        ms = [m for _, m in w["gpu"]]
        print(f"  GPU utilisation mean {statistics.mean(us):.0f} % (max {max(us):.0f}); memory used max {max(ms):.0f} MiB")

    # ---- peer: ot.emd on the first committed pairs, same cost matrices
    import concurrent.futures as cf
    import multiprocessing as mp

    params, energies, paths = st["params"], st["energies"], st["paths"]
    cache = os.environ.get("WPOT_CACHE_DIR") or str(out / "cache")  # where the run kept its signatures
    if params.get("transport") != "balanced":
        print("\n(the ot.emd peer is for balanced runs only)")
        return
    keys = ("signature", "transport", "max_vertices", "fps_metric", "pooling", "vertices_per_sample", "n_eigen",
            "n_energies", "scale_invariant", "ldsift_K", "ldsift_resolution", "ldsift_slab", "match_ratio", "solver_options")
    opts = {k: params[k] for k in keys if params.get(k) is not None}
    if params.get("signature") == "ldsift":
        opts.setdefault("ldsift_slab", 1.0)  # runs stored without the key used slab 1.0 (`Comparer.params`)
    n_peer = min(len(st["rows"]), args.jobs if args.peer_pairs is None else args.peer_pairs)
    if n_peer == 0:
        return
    peer_rows = st["rows"][:n_peer]  # the run's first pairs, from this session or an earlier one
    todo = [(paths[r[0]], paths[r[1]], opts, energies, cache) for r in peer_rows]
    t0 = time.time()
    res = []
    with cf.ProcessPoolExecutor(max_workers=args.jobs, mp_context=mp.get_context("spawn")) as ex:
        futs = [ex.submit(emd_pair, t) for t in todo]
        for f in futs:
            try:
                res.append(f.result(timeout=max(1.0, args.peer_seconds - (time.time() - t0))))
            except cf.TimeoutError:
                break
        for f in futs:
            f.cancel()
        for p in getattr(ex, "_processes", {}).values():  # do not wait for a simplex past the budget
            p.kill()
    wall = time.time() - t0
    print(f"\nPOT ot.emd (CPU), {args.jobs} processes, on the first {len(res)} of {n_peer} pairs, {wall:.0f} s")
    if res:
        med = statistics.median(t for t, _ in res)
        ideal = args.jobs / med  # every process busy with simplex solves, no start-up or loading
        print(f"  per pair (one process, the simplex alone): median {med:.1f} s; {args.jobs} processes busy -> "
              f"{ideal:.3f} pairs/s -> all {n_pairs} pairs in {n_pairs / ideal / 60:.1f} min (estimate)")
        gaps = [abs(r[2] - u) / abs(u) for r, (_, u) in zip(peer_rows, res)]
        print(f"  wpot's U against emd's optimum on these pairs: relative gap median {statistics.median(gaps):.1e}, "
              f"max {max(gaps):.1e}")
    else:
        print("  no ot.emd pair finished within --peer-seconds")


if __name__ == "__main__":
    main()
