"""Cheap proxies for LD-SIFT classification on TOSCA (issue 6): no annealing solver needed.

For a list of meshes (default: 4 shapes per class of ``tosca_isometric_5k``), it computes the LD-SIFT
signatures once (through `wpot.Comparer`, so ``$WPOT_CACHE_DIR`` is reused), subsamples every shape
(farthest-point sampling as `Comparer` does, or uniformly at random), and builds two shape-distance
matrices from the same descriptors:

* ``emd``: the exact balanced transport cost between the two sampled descriptor sets with uniform masses
  (POT's network simplex, ``ot.emd2``). It is the beta -> infinity limit of the annealed balanced solver, and
  on the 31-shape subset at ``max_vertices=200`` it reproduces the classification of the `wpot all-vs-all`
  run exactly (50.1 % one-shot, 61.3 % leave-one-out), in seconds instead of 17 minutes;
* ``chamfer``: a transport-free peer, the symmetric mean nearest-neighbour descriptor distance.

and prints the one-shot 1-NN accuracy (10,000 trials, paper Table 1) and the leave-one-out accuracy of
each, per sample size, side by side. With ``--rank`` it also prints the median rank percentile of the true
match (ground truth ``corres/*.vts``) for a few same-class pairs, a pointwise measure of the descriptor.

    OPENBLAS_NUM_THREADS=1 WPOT_CACHE_DIR=... python benchmarks/ldsift_classification.py \\
        [--data ../shared/data] [--per-class 4] [--samples 200 400 800] [--sampling fps|random] \\
        [--metric l2|l1|wks] [--K 3] [--resolution 21] [--slab 1] [--rank]

Needs POT (the ``dev`` extra). Single process; timings are not the point.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import wpot
from wpot.datasets import class_label, tosca_ground_truth

PAIRS = (("cat0", "cat1"), ("michael0", "michael1"), ("horse0", "horse5"), ("dog0", "dog2"), ("centaur0", "centaur1"))


def pick_shapes(folder: Path, per_class: int) -> list[Path]:
    """The first ``per_class`` shapes of every class, in natural order (cat0, cat1, ... cat10)."""
    by_class: dict[str, list[Path]] = {}
    for p in sorted(folder.glob("*.off"), key=lambda p: (class_label(p.stem), int(p.stem[len(class_label(p.stem)):] or 0))):
        by_class.setdefault(class_label(p.stem), []).append(p)
    return [p for c in sorted(by_class) for p in by_class[c][:per_class]]


def cost(a: np.ndarray, b: np.ndarray, metric: str) -> np.ndarray:
    from wpot.cost import cost_matrix

    return np.asarray(cost_matrix(a, b, metric=metric, device="cpu"))


def distance_matrices(points: list[np.ndarray], metric: str) -> dict[str, np.ndarray]:
    """(n, n) exact-EMD and chamfer matrices between the descriptor sets ``points`` (uniform masses)."""
    import ot as pot

    n = len(points)
    out = {"emd": np.zeros((n, n)), "chamfer": np.zeros((n, n))}
    for i in range(n):
        for j in range(i + 1, n):
            a, b = points[i], points[j]
            c = cost(a, b, metric)
            e = pot.emd2(np.full(len(a), 1.0 / len(a)), np.full(len(b), 1.0 / len(b)), c, numItermax=10_000_000)
            out["emd"][i, j] = out["emd"][j, i] = e
            ch = 0.5 * (c.min(1).mean() + c.min(0).mean())
            out["chamfer"][i, j] = out["chamfer"][j, i] = ch
    return out


def rank_percentile(sig_a: np.ndarray, sig_b: np.ndarray, src: np.ndarray, dst: np.ndarray, metric: str, n_points: int = 300) -> float:
    """Median over ``n_points`` ground-truth pairs of the fraction of B's vertices closer than the true match."""
    k = np.random.default_rng(0).choice(len(src), min(n_points, len(src)), replace=False)
    c = cost(sig_a[src[k]], sig_b, metric)
    true = c[np.arange(len(k)), dst[k]]
    return float(np.median((c < true[:, None]).mean(1)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[1] / ".." / "shared" / "data"))
    ap.add_argument("--per-class", type=int, default=4)
    ap.add_argument("--samples", type=int, nargs="+", default=[200, 400])
    ap.add_argument("--sampling", choices=("fps", "random"), default="fps")
    ap.add_argument("--metric", choices=("l2", "l1", "wks"), default="l2")
    ap.add_argument("--K", type=float, default=3.0)
    ap.add_argument("--resolution", type=int, default=21)
    ap.add_argument("--slab", type=float, default=1.0, help="depth slab half-thickness in units of S(v)")
    ap.add_argument("--rank", action="store_true")
    args = ap.parse_args()

    folder = Path(args.data) / "tosca_isometric_5k" / "vtx_5k"
    paths = pick_shapes(folder, args.per_class)
    names = [p.stem for p in paths]
    labels = np.array([class_label(n) for n in names])
    meshes = [wpot.load_mesh(p) for p in paths]
    comparer = wpot.Comparer(signature="ldsift", ldsift_K=args.K, ldsift_resolution=args.resolution,
                             ldsift_slab=args.slab, device="cpu")
    t0 = time.perf_counter()
    sigs = [comparer.signatures(m) for m in meshes]
    print(f"{len(meshes)} shapes, {len(set(labels))} classes; LD-SIFT K={args.K} R={args.resolution} slab={args.slab}: "
          f"{time.perf_counter() - t0:.1f} s")

    if args.rank:
        for a, b in PAIRS:
            if a in names and b in names:
                src, dst = tosca_ground_truth(folder, a, b)
                r = rank_percentile(sigs[names.index(a)], sigs[names.index(b)], src, dst, args.metric)
                print(f"  true-match median rank percentile {a}/{b}: {r:.3f} (chance 0.5)")

    print(f"\n{'samples':>8} {'sampling':>8} | {'EMD one-shot':>12} {'EMD LOO':>8} | {'chamfer one-shot':>16} {'chamfer LOO':>11} | seconds")
    for k in args.samples:
        pts = []
        for i, (m, s) in enumerate(zip(meshes, sigs)):
            if args.sampling == "fps":
                sub = comparer.with_options(max_vertices=k).subsample(m)
                idx = np.arange(m.n_vertices) if sub is None else sub.indices
            else:
                idx = np.sort(np.random.default_rng(i).choice(m.n_vertices, min(k, m.n_vertices), replace=False))
            pts.append(s[idx])
        t = time.perf_counter()
        mats = distance_matrices(pts, args.metric)
        row = []
        for kind in ("emd", "chamfer"):
            one = wpot.one_shot_1nn(mats[kind], labels, n_trials=10_000, seed=0).mean
            loo = wpot.leave_one_out_1nn(mats[kind], labels).accuracy
            row += [100 * one, 100 * loo]
        print(f"{k:>8} {args.sampling:>8} | {row[0]:>12.1f} {row[1]:>8.1f} | {row[2]:>16.1f} {row[3]:>11.1f} | {time.perf_counter() - t:.0f}")


if __name__ == "__main__":
    main()
