"""LD-SIFT's candidate matches across mesh densities and support sizes (issue 41, items 4 and 5).

`wpot.maps.locate` starts from candidates: for each anchor of the part, the ``--candidates`` vertices of the whole
with the nearest LD-SIFT signatures. This measures how often the right vertex is among them when the two meshes
were triangulated apart and at other densities, for each scale factor K (the image of a vertex covers 2 K D,
D one edge length for both meshes: the target's, as ``LocateOptions(edge="whole")`` sets it; the paper's K is 3,
the peer in every table), and for each of LD-SIFT's ``--orientation`` (the paper's ``frame``, the peer, and SIFT's
own ``gradient``).

For each pair (S, T) of poses of one class: S is re-meshed at F times its vertices (`benchmarks.remesh.resized`:
every vertex moves, no edge is S's; at 1× another triangulation at the same density), ``--samples``
farthest-point samples of the re-meshing are the queries, each one's truth is the template point nearest it on
S carried to T by the ``.vts`` ground truth (``.sym.vts``: its left/right mirror). Reported per dataset, K and F,
averaged over the pairs:

* recall@n: the share of queries with a candidate within ``--radius`` √area(T) of the truth (Euclidean);
* either@n: the same against the truth or its mirror (a mirror match is still a match the consistency step and
  the orientation step can use);
* recall@1: the nearest signature itself within the radius.

Whole shapes are compared, not parts, so that the density and the support are measured apart from the part's
boundary; `partial_poses.py --ldsift-K` measures the located maps themselves.

Results go to ``--out`` (outside the repository) as they are computed, so a stopped run resumes; the table is
printed at the end (and with ``--report-only``).

Usage::

    WPOT_CACHE_DIR=/work/runs/cache python benchmarks/ldsift_support.py --out /work/runs/ldsift_support
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks.correspondence import _data_root  # noqa: E402
from benchmarks.jsonl_store import JsonlStore, stored_run  # noqa: E402

#: one pair of poses per class, the first pose against another (`tosca_isometric_5k`; FAUST: one person each)
PAIRS = {
    "tosca": ["cat0:cat2", "centaur0:centaur2", "david0:david1", "dog0:dog1", "horse0:horse5", "michael0:michael1",
              "victoria0:victoria1", "wolf0:wolf1"],
    "faust": ["tr_reg_000:tr_reg_005", "tr_reg_012:tr_reg_017", "tr_reg_024:tr_reg_029", "tr_reg_036:tr_reg_031",
              "tr_reg_048:tr_reg_043", "tr_reg_060:tr_reg_065", "tr_reg_072:tr_reg_077", "tr_reg_084:tr_reg_089"],
}
FOLDERS = {"tosca": "tosca_isometric_5k", "faust": "faust_5k"}


def dataset_folders(a, log):
    """(name, its ``vtx_5k`` folder) for each of ``a.dataset`` under ``a.data``; a missing one is logged and skipped."""
    for ds in a.dataset:
        vtx = a.data / FOLDERS[ds] / "vtx_5k"
        if vtx.is_dir():
            yield ds, vtx
        else:
            log(f"{ds}: {vtx} is missing, skipped")


def hits(images: np.ndarray, truth: np.ndarray, radius: float) -> np.ndarray:
    """(Q, n) bool: each candidate position (Q, n, 3) within ``radius`` of its query's truth (Q, 3)."""
    return np.linalg.norm(images - truth[:, None], axis=2) < radius


def queries_on(source, remeshed, src: np.ndarray, dst: np.ndarray, sym: np.ndarray, target, samples: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``samples`` farthest-point samples of the re-meshed source (the queries), and the positions on the target of
    each one's truth and of its mirror: the template point nearest it on the source, carried by ``dst`` / ``sym``."""
    from scipy.spatial import cKDTree

    from wpot.sampling import farthest_point_sampling

    queries = farthest_point_sampling(remeshed, min(samples, remeshed.n_vertices)).indices
    nearest = cKDTree(source.vertices[src]).query(remeshed.vertices[queries])[1]
    return queries, target.vertices[dst[nearest]], target.vertices[sym[nearest]]


def ldsift(K: float, target, orientation: str = "frame"):
    """The LD-SIFT comparer at scale factor ``K`` and the target's edge length (what ``LocateOptions(edge="whole")``
    gives both meshes), with the slab `partial_poses.py` uses, and descriptors turned by ``orientation``."""
    from wpot.comparison import Comparer
    from wpot.signatures._frames import common_edge

    return Comparer(signature="ldsift", ldsift_K=K, ldsift_edge=common_edge([target]), ldsift_slab=1.0,
                    ldsift_orientation=orientation)


def method(K: float, orientation: str) -> str:
    """A variant's tag: ``K3`` for the paper's orientation (the tag of runs stored before it was a choice)."""
    return f"K{K:g}" + ("" if orientation == "frame" else f"-{orientation}")


def signatures(comparer, mesh) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a re-meshing's own defects are not what is measured
        return np.asarray(comparer.signatures(mesh))


def recall(s_r: np.ndarray, s_t: np.ndarray, queries: np.ndarray, truth: np.ndarray, mirror: np.ndarray, target,
           a) -> dict:
    """The recall figures of the queries (rows of the re-meshing's signatures ``s_r``) against the target's
    signatures ``s_t``, with each query's truth and mirror positions (Q, 3) on the target."""
    from wpot.maps.locate import candidate_matches

    cand = target.vertices[candidate_matches(s_r, s_t, queries, a.candidates, "l2", a.device)]
    radius = a.radius * np.sqrt(target.area)
    right, other = hits(cand, truth, radius), hits(cand, mirror, radius)
    return {"recall": float(right.any(1).mean()), "either": float((right | other).any(1).mean()),
            "recall1": float(right[:, 0].mean())}


def run(a, store: JsonlStore, log) -> None:
    from benchmarks.remesh import resized
    from wpot.datasets import tosca_ground_truth
    from wpot.io import load_mesh

    for ds, vtx in dataset_folders(a, log):
        for pair in PAIRS[ds]:
            s, t = pair.split(":")
            todo = [(F, K, o) for F in a.densities for K in a.K for o in a.orientation
                    if (method(K, o), f"{ds}:{pair}", f"F{F:g}") not in store.done]
            if not todo:
                continue
            source, target = load_mesh(vtx / f"{s}.off"), load_mesh(vtx / f"{t}.off")
            src, dst = tosca_ground_truth(vtx, s, t)
            _, sym = tosca_ground_truth(vtx, s, t, symmetric=True)
            # each re-meshing and its queries once, then each (K, orientation)'s target signatures once
            remeshed = {F: resized(source, int(round(F * source.n_vertices))) for F in sorted({job[0] for job in todo})}
            queries = {F: queries_on(source, r, src, dst, sym, target, a.samples) for F, r in remeshed.items()}
            for K, o in sorted({job[1:] for job in todo}):
                comparer = ldsift(K, target, o)
                s_t = signatures(comparer, target)
                for F in [F for F, L, p in todo if (L, p) == (K, o)]:
                    t0 = time.perf_counter()
                    s_r = signatures(comparer, remeshed[F])
                    rec = {**recall(s_r, s_t, *queries[F], target, a), "n_vertices": int(remeshed[F].n_vertices),
                           "signature_seconds": time.perf_counter() - t0}
                    store.add({"method": method(K, o), "pair": f"{ds}:{pair}", "density": f"F{F:g}", "dataset": ds,
                               "K": K, "orientation": o, "F": F, **rec}, None)
                    log(f"{ds} {pair} F={F:g} K={K:g} {o}: recall@{a.candidates} {rec['recall']:.3f}, "
                        f"either {rec['either']:.3f}, recall@1 {rec['recall1']:.3f}")


def report(store: JsonlStore, a, log) -> None:
    for ds in a.dataset:
        recs = [r for r in store.records if r["dataset"] == ds]
        if not recs:
            continue
        variants = sorted({(r["K"], r.get("orientation", "frame")) for r in recs})
        Fs = sorted({r["F"] for r in recs})
        log(f"\n## {ds}: recall@{a.candidates} (either side) / recall@1, mean over the pairs; K = 3 and the frame's "
            "orientation are the paper's\n")
        log("| K | orientation | " + " | ".join(f"re-meshed at {F:g}×" for F in Fs) + " | largest gap to 1× |")
        log("|---|---|" + "---|" * (len(Fs) + 1))
        for K, o in variants:
            cells, rec_at = [], {}
            for F in Fs:
                rows = [r for r in recs if (r["K"], r.get("orientation", "frame"), r["F"]) == (K, o, F)]
                if not rows:
                    cells.append("–")
                    continue
                m = {k: float(np.mean([r[k] for r in rows])) for k in ("recall", "either", "recall1")}
                rec_at[F] = m["recall"]
                cells.append(f"{m['recall']:.3f} ({m['either']:.3f}) / {m['recall1']:.3f}, {len(rows)} pairs")
            gap = (max(abs(v - rec_at[1.0]) for v in rec_at.values()) if 1.0 in rec_at else float("nan"))
            log(f"| {K:g} | {o} | " + " | ".join(cells) + f" | {gap:.3f} |")


def main(argv=None) -> int:
    from wpot.signatures._ldsift import ORIENTATIONS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=_data_root())
    ap.add_argument("--out", type=Path, required=True, help="results folder (outside the repository)")
    ap.add_argument("--dataset", nargs="+", default=["tosca", "faust"], choices=list(PAIRS))
    ap.add_argument("--K", type=float, nargs="+", default=[3.0, 4.5, 6.0], help="LD-SIFT scale factors")
    ap.add_argument("--orientation", nargs="+", default=list(ORIENTATIONS), choices=ORIENTATIONS,
                    help="LD-SIFT's orientations (`LDSIFTOptions.orientation`; 'frame' is the paper's, the peer)")
    ap.add_argument("--densities", type=float, nargs="+", default=[1.0, 2.0, 0.5],
                    help="vertex ratios of the re-meshing")
    ap.add_argument("--samples", type=int, default=200, help="queries per pair")
    ap.add_argument("--candidates", type=int, default=10, help="candidates per query (locate's n_candidates)")
    ap.add_argument("--radius", type=float, default=0.05, help="a hit: within this of the truth, over √area(T)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--report-only", action="store_true")
    a = ap.parse_args(argv)
    if 1.0 not in a.densities:
        ap.error("--densities must include 1 (the control: another triangulation at the same density)")
    return stored_run(a, ("pair", "density"), run, report)


if __name__ == "__main__":
    raise SystemExit(main())
