"""How much of a run's shape distance is pose: Spearman correlation with a pose-only distance (issue 6).

LD-SIFT is extrinsic (a depth image of the mesh around each vertex) and scale invariant (the image covers
K times the local edge length); WKS is intrinsic and, at the meshes' own size, sees size. On TOSCA the
human classes (David, Michael, Victoria) come in similar poses and differ mainly in size, so a signature
that sees pose and not size confuses them. This script measures that on finished `wpot all-vs-all` runs.

The pose-only peer distance is the D2 shape distribution (Osada et al. 2002): the distribution of the
Euclidean distance between two random surface points (area-weighted), divided by sqrt(area), compared by
the L1 distance of the cumulative histograms. It is scale invariant and sees pose (arms spread or not)
but no local geometry.

For every run it prints, over the pairs of shapes in ``--classes`` (default the humans):

* the Spearman rank correlation of the run's D(inf) with the D2 distance, over all those pairs, over the
  same-class pairs, and over the cross-class pairs (the ones 1-NN must tell apart), and with the size
  difference |log(area_a / area_b)| over the cross-class pairs;
* one-shot 1-NN (10,000 trials) and leave-one-out accuracy restricted to those classes,

and the same accuracies of two peer distances: D2 itself (pose only), and |log(area_a / area_b)| (size
only, which no scale-invariant signature can see).

    python benchmarks/pose_sensitivity.py RUN [RUN ...] [--classes david michael victoria] [--pairs 200000]

Needs scipy only. The meshes are read from the paths stored in each run.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

import wpot
from wpot.runs.store import RunStore

BINS = np.linspace(0.0, 1.6, 65)  # distances in units of sqrt(area); TOSCA shapes stay below 1.4


def d2_cdf(mesh: wpot.Mesh, n_pairs: int, seed: int = 0) -> np.ndarray:
    """(64,) cumulative histogram of |p - q| / sqrt(area) for ``n_pairs`` area-uniform point pairs."""
    rng = np.random.default_rng(seed)
    a = mesh.face_areas
    f = mesh.faces[rng.choice(len(a), size=2 * n_pairs, p=a / a.sum())]
    u, v = rng.random((2, 2 * n_pairs, 1))
    flip = (u + v) > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    x = mesh.vertices
    p = x[f[:, 0]] + u * (x[f[:, 1]] - x[f[:, 0]]) + v * (x[f[:, 2]] - x[f[:, 0]])
    d = np.linalg.norm(p[:n_pairs] - p[n_pairs:], axis=1) / np.sqrt(mesh.area)
    h, _ = np.histogram(d, bins=BINS)
    return np.cumsum(h) / n_pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--classes", nargs="+", default=["david", "michael", "victoria"])
    ap.add_argument("--pairs", type=int, default=200_000, help="point pairs per shape for D2")
    args = ap.parse_args()

    cdfs: dict[str, np.ndarray] = {}
    areas: dict[str, float] = {}
    print(f"{'':<34} | {'Spearman with the D2 pose distance':^36} | {'with size':>9} |")
    print(f"{'run':<34} | {'all pairs':>12} {'same-class':>10} {'cross-class':>12} | {'cross':>9} | {'one-shot':>8} {'LOO':>6}")
    for run in args.runs:
        with RunStore(run) as store:
            rows = store.shape_rows()
            d = store.distance_matrix()
            labels = np.array(store.labels(), dtype=object)
        keep = np.flatnonzero(np.isin(labels, args.classes))
        if len(keep) < 3:
            raise SystemExit(f"{run}: fewer than 3 shapes of classes {args.classes}")
        for k in keep:
            name, path = rows[k][1], rows[k][2]
            if name not in cdfs:
                if path is None or not Path(path).exists():
                    raise SystemExit(f"{run}: mesh file of {name!r} not found ({path!r})")
                mesh = wpot.load_mesh(path)
                cdfs[name], areas[name] = d2_cdf(mesh, args.pairs), mesh.area
        names = [rows[k][1] for k in keep]
        lab = labels[keep].astype(str)
        dk = d[np.ix_(keep, keep)]
        if np.isnan(dk).any():
            raise SystemExit(f"{run}: the run is not finished ({int(np.isnan(dk).sum()) // 2} pairs missing)")
        pose = np.array([[np.abs(cdfs[a] - cdfs[b]).sum() for b in names] for a in names])
        iu = np.triu_indices(len(keep), 1)
        same = (lab[:, None] == lab[None, :])[iu]
        log_area = np.log([areas[n] for n in names])
        size = np.abs(log_area[:, None] - log_area[None, :])
        rows_out = [(Path(run).name, dk)]
        if run == args.runs[-1]:
            rows_out += [("peer: D2 pose distance", pose), ("peer: size, |log area ratio|", size)]
        for title, dist in rows_out:
            rho = [spearmanr(dist[iu][m], pose[iu][m])[0] for m in (np.ones_like(same), same, ~same)]
            rho_size = spearmanr(dist[iu][~same], size[iu][~same])[0]
            acc = (wpot.one_shot_1nn(dist, lab, n_trials=10_000, seed=0).mean, wpot.leave_one_out_1nn(dist, lab).accuracy)
            print(f"{title:<34} | {rho[0]:>12.2f} {rho[1]:>10.2f} {rho[2]:>12.2f} | {rho_size:>9.2f} | "
                  f"{100 * acc[0]:>7.1f}% {100 * acc[1]:>5.1f}%")
    print(f"\nclasses: {', '.join(args.classes)} ({len(keep)} shapes); D2 from {args.pairs} area-uniform point pairs per shape")


if __name__ == "__main__":
    main()
