"""Correspondence speed on large meshes: wpot's comparison plus oriented ZoomOut (`wpot.zoomout`), beside plain
ZoomOut (``orient=False``) and pyfmaps (WKS functional map + ZoomOut, `correspondence.FMAPS_SETTINGS`) on the same
pair, at about 10,000 and 60,000 vertices.

The meshes: two FAUST shapes (``faust_5k``, two people in two poses), each midpoint-subdivided (4x the faces) and,
where that overshoots, simplified to the target vertex count by quadric decimation (``fast-simplification``):
independent triangulations of the two shapes at the size asked. It runs what ``wpot compare A B --zoomout`` runs:
`wpot.Comparer` on the meshes themselves, whose WKS of a mesh above `wpot.spectral.SPECTRAL_MAX_VERTICES` vertices is
its simplified copy's (`wpot.simplify`) blended to every vertex, then `wpot.zoomout`, which refines through the same
copies and decides left from right on smaller copies still (`wpot.maps.zoomout.ORIENT_MAX_VERTICES`; the table
gives their sizes, and the time to make them, which a shape pays once: they are cached). For each
size it times

* **cold**: the copies and their Laplace-Beltrami spectra (computed, not read from a cache; run with a fresh
  ``$WPOT_CACHE_DIR``), then the comparison and the refinement (the cold total is the sum of the two columns);
* **warm**: the comparison and the refinement with the spectra cached (the usual case in an all-against-all),
  and the refinement alone, oriented and plain (the least of ``--repeat`` alternated runs of each);
* pyfmaps: its per-shape set-up (spectrum) and its matching, on the meshes themselves, up to ``--peer-max``
  vertices.

It also checks the answer against the FAUST ground truth carried to the new vertices by nearest neighbour: mean
error over sqrt(area) and whether the map is mirrored (median error against the ``.sym.vts`` truth smaller).

Usage: ``python benchmarks/correspondence_speed.py [--sizes 10000 60000] [--pair tr_reg_000 tr_reg_011 [--pair A B ...]]``;
with several pairs it also prints, per size, the mean error, the mirrored count and the slowest times over them.
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks.correspondence import FMAPS_SETTINGS, _data_root  # noqa: E402
from benchmarks.remesh import resized  # noqa: E402


def truth_on(big, small, corres: np.ndarray) -> np.ndarray:
    """The template points' vertices (``corres`` on ``small``) carried to ``big`` by nearest neighbour."""
    from scipy.spatial import cKDTree

    return cKDTree(big.vertices).query(small.vertices[corres])[1]


def errors(b, pred: np.ndarray, dst: np.ndarray, sym: np.ndarray) -> tuple[float, bool]:
    s = np.sqrt(b.area)
    et = np.linalg.norm(b.vertices[pred] - b.vertices[dst], axis=1) / s
    es = np.linalg.norm(b.vertices[pred] - b.vertices[sym], axis=1) / s
    return float(et.mean()), bool(np.median(es) < np.median(et))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=_data_root())
    ap.add_argument("--sizes", type=int, nargs="+", default=[10000, 60000])
    ap.add_argument("--pair", nargs=2, action="append", metavar=("A", "B"),
                    help="a FAUST pair (repeat for several; default tr_reg_000 tr_reg_011)")
    ap.add_argument("--no-peer", action="store_true", help="skip pyfmaps")
    ap.add_argument("--peer-max", type=int, default=20000,
                    help="run pyfmaps only up to this many vertices (default %(default)s; at 60,000 its spectra alone "
                    "take many minutes)")
    ap.add_argument("--repeat", type=int, default=3,
                    help="time the oriented and the plain refinement this many times each, alternated, and keep the "
                    "least of each (default %(default)s)")
    a = ap.parse_args(argv)
    if a.repeat < 1:
        ap.error(f"--repeat must be at least 1, got {a.repeat}")

    import wpot
    from wpot.comparison import Comparer
    from wpot.datasets import tosca_vts
    from wpot.io import load_mesh
    from wpot.maps.zoomout import ORIENT_MAX_VERTICES, ZOOMOUT_MAX_VERTICES, zoomout
    from wpot.mesh import MeshWarning
    from wpot.simplify import simplify
    from wpot.spectral import SPECTRAL_MAX_VERTICES

    vtx = a.data / "faust_5k" / "vtx_5k"
    if not vtx.is_dir():
        ap.error(f"{vtx} not found (set --data)")
    rows = []
    for (x, y), n in itertools.product(a.pair or [("tr_reg_000", "tr_reg_011")], a.sizes):
        small = [load_mesh(vtx / f"{m}.off") for m in (x, y)]
        ma, mb = (resized(m, n) for m in small)
        src = truth_on(ma, small[0], tosca_vts(vtx, x))
        dst = truth_on(mb, small[1], tosca_vts(vtx, y))
        sym = truth_on(mb, small[1], tosca_vts(vtx, y, symmetric=True))
        t0 = time.perf_counter()
        # above SPECTRAL_MAX_VERTICES, the spectra are the simplified copies' (the WKS signatures' and zoomout's)
        sa, sb = simplify(ma, SPECTRAL_MAX_VERTICES), simplify(mb, SPECTRAL_MAX_VERTICES)
        for m in (sa.coarse, sb.coarse):  # cold: these meshes are new to the process (and to a fresh $WPOT_CACHE_DIR)
            if wpot.eigenpairs(m, 500).from_cache:
                print(f"note: the spectrum of a {m.n_vertices}-vertex mesh came from $WPOT_CACHE_DIR: 'cold' is not")
        t_spec = time.perf_counter() - t0
        comparer = Comparer(max_vertices=500)

        def matched() -> np.ndarray:
            # what `wpot compare A B --zoomout` does: WKS through the copies (from the cached spectra), the
            # transport on samples of the meshes themselves
            return comparer.compare(ma, mb).correspondence

        t0 = time.perf_counter()
        res = zoomout(ma, mb, matched())
        t_first = time.perf_counter() - t0
        t0 = time.perf_counter()
        start = matched()
        t_cmp = time.perf_counter() - t0
        t_orient = t_plain = float("inf")
        for _ in range(a.repeat):  # alternated, the least of each: the machine's noise hits both alike
            t0 = time.perf_counter()
            res = zoomout(ma, mb, start)
            t_orient = min(t_orient, time.perf_counter() - t0)
            t0 = time.perf_counter()
            plain = zoomout(ma, mb, start, orient=False)
            t_plain = min(t_plain, time.perf_counter() - t0)
        decided = res.orientation_vertices
        t0 = time.perf_counter()
        if decided is not None:  # the copies left and right are decided on, made afresh (what a shape not in the
            with warnings.catch_warnings():  # cache costs once)
                warnings.simplefilter("ignore", MeshWarning)  # the defects zoomout's own call kept quiet
                for m in (ma, mb):  # from what zoomout refines on: the mesh, or its copy above ZOOMOUT_MAX_VERTICES
                    simplify(simplify(m, ZOOMOUT_MAX_VERTICES).coarse, ORIENT_MAX_VERTICES, cache=False)
        t_copies = time.perf_counter() - t0
        err, mirrored = errors(mb, res.map[src], dst, sym)
        perr, pmirrored = errors(mb, plain.map[src], dst, sym)
        row = {"pair": f"{x} → {y}", "size": n, "n": (ma.n_vertices, mb.n_vertices), "copies": (sa.coarse.n_vertices, sb.coarse.n_vertices), "spectra": t_spec, "first": t_first, "compare": t_cmp,
               "orient": t_orient, "plain": t_plain, "err": err, "mirrored": mirrored, "conf": res.orientation_confidence,
               "plain_err": perr, "plain_mirrored": pmirrored, "decided": decided, "reanchored": res.reanchored,
               "t_copies": t_copies}
        if not a.no_peer and max(row["n"]) <= a.peer_max:
            from pyFM.functional import FunctionalMapping
            from pyFM.mesh import TriMesh

            s = FMAPS_SETTINGS
            t0 = time.perf_counter()
            try:
                tb, ta = (TriMesh(m.vertices, m.faces, area_normalize=True, center=True).process(k=s["k_process"])
                          for m in (mb, ma))
                row["peer_setup"] = time.perf_counter() - t0
                t0 = time.perf_counter()
                model = FunctionalMapping(tb, ta)
                model.preprocess(n_descr=s["n_descr"], descr_type="WKS", subsample_step=s["subsample_step"],
                                 k_process=s["k_process"])
                model.fit(K=s["K"], w_descr=s["w_descr"], w_lap=s["w_lap"], w_dcomm=s["w_dcomm"],
                          w_orient=s["w_orient"])
                p2p = np.asarray(model.get_p2p(model.zoomout_refine(nit=s["zoomout_nit"], step=s["zoomout_step"])))
                row["peer"] = time.perf_counter() - t0
                row["peer_err"], row["peer_mirrored"] = errors(mb, p2p[src], dst, sym)
            except Exception as exc:  # a peer that fails on this size is reported, not a crash of the run
                row["peer_failed"] = f"{type(exc).__name__} after {time.perf_counter() - t0:.0f} s: {exc}"
        rows.append(row)
        print(row, flush=True)
    print("\n| pair | vertices (A, B) | matched through (copies) | left/right decided on (copies, made in) | copies and their spectra, cold (2 shapes) | compare + oriented ZoomOut, first (signatures) | "
          "compare, warm | oriented ZoomOut | plain ZoomOut | oriented / plain | end to end, spectra cached | "
          "error √area (mirrored), confidence | plain: error (mirrored) | pyfmaps set-up | pyfmaps match | "
          "pyfmaps error (mirrored) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        peer = (f"{r['peer_setup']:.1f} s | {r['peer']:.1f} s | {r['peer_err']:.3f} ({'yes' if r['peer_mirrored'] else 'no'})"
                if "peer" in r else f"failed: {r['peer_failed'][:80]} | – | –" if "peer_failed" in r else "– | – | –")
        ca, cb = r["copies"]
        through = "themselves" if r["copies"] == r["n"] else f"{ca:,}, {cb:,}"
        dec = "the same" if r["decided"] is None else f"{r['decided'][0]:,}, {r['decided'][1]:,} ({r['t_copies']:.2f} s)"
        print(f"| {r['pair']} | {r['n'][0]:,}, {r['n'][1]:,} | {through} | {dec} | {r['spectra']:.1f} s | {r['first']:.1f} s | {r['compare']:.1f} s | "
              f"{r['orient']:.1f} s | {r['plain']:.1f} s | {r['orient'] / r['plain']:.2f}x | "
              f"{r['compare'] + r['orient']:.1f} s | {r['err']:.3f} ({'yes' if r['mirrored'] else 'no'}), "
              f"{r['conf']:.2f} | {r['plain_err']:.3f} ({'yes' if r['plain_mirrored'] else 'no'}) | {peer} |")
    for n in a.sizes:
        at = [r for r in rows if r["size"] == n]
        if len(at) > 1:
            cold = [r["spectra"] + r["first"] for r in at]
            print(f"\n{len(at)} pairs at {n:,} vertices: error √area mean {np.mean([r['err'] for r in at]):.3f} (plain "
                  f"{np.mean([r['plain_err'] for r in at]):.3f}), mirrored {sum(r['mirrored'] for r in at)} "
                  f"(plain {sum(r['plain_mirrored'] for r in at)}), cold total median {np.median(cold):.1f} s, max "
                  f"{max(cold):.1f} s, end to end with spectra cached max {max(r['compare'] + r['orient'] for r in at):.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
