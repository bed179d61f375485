"""How far `ClassRanking.probability` (the chance that `Comparer.retrieve`'s first class is right) can be trusted.

Reads two `part_retrieval.py` results folders: a **development** set, on which the calibration is fitted
(logistic regression of "the first class is right" on the ranking's margin, `fit_logistic`), and a **check**
set, on which it is only measured. For each set it prints, beside the fixed rule it replaces ("margin below
`wpot.maps.retrieval.MARGIN_DOUBT` is doubtful"):

* top-1 and the parts with probability >= 0.9: how many, and how many of them are right;
* a reliability table: the parts in ten bins of equal count by probability, each bin's mean probability beside
  its observed accuracy (a calibrated probability lies within a few points of it);
* the logistic fitted afresh to this set, beside the shipped `wpot.maps.retrieval.CALIBRATION` (fitted on the
  development set; the two should agree on the development set only).

and draws the reliability diagram of both sets (``--out``/reliability.png).

Usage:

    python benchmarks/retrieval_calibration.py --dev /work/runs/pr_none --dev-parts /work/runs/pp_none \\
        --check /work/runs/pr_lowres --check-parts /work/runs/pp_lowres --out /work/runs/calibration
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks.part_retrieval import PartMeshes, library_wholes, method, open_store, score  # noqa: E402
from benchmarks.partial_poses import _tosca, read_parts  # noqa: E402


def fit_logistic(x: np.ndarray, y: np.ndarray, *, ridge: float = 1e-3, n_iter: int = 50) -> tuple[float, float]:
    """(intercept, slope) of ``P(y) = 1 / (1 + exp(-(a + b x)))`` by Newton's method on the log-likelihood, with a
    small ridge on the slope (it keeps the fit finite when the set is separable). (NaN, NaN) when every outcome is
    the same (nothing to fit: the intercept would run off to infinity)."""
    if len(y) == 0 or y.min() == y.max():
        return float("nan"), float("nan")
    a = np.array([0.0, 0.0])
    X = np.stack([np.ones_like(x), x], axis=1)
    for _ in range(n_iter):
        p = 1.0 / (1.0 + np.exp(-(X @ a)))
        g = X.T @ (y - p) - ridge * np.array([0.0, a[1]])
        h = (X * (p * (1 - p))[:, None]).T @ X + ridge * np.diag([0.0, 1.0])
        step = np.linalg.solve(h, g)
        a = a + step
        if np.abs(step).max() < 1e-10:
            break
    return float(a[0]), float(a[1])


def rows_of(out: Path, parts_dir: Path, w: float, wholes: dict, edge: str = "library"
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(margins, right, probability) per part of one results folder, at weight ``w``; ``wholes`` the library
    (`library_wholes`), which the parts not stored whole are cut from; ``edge`` LD-SIFT's edge length
    (`part_retrieval.method`)."""
    from wpot.maps.retrieval import RetrievalOptions, probability_of

    store = open_store(out)
    parts = read_parts(parts_dir)
    rows = score(store, parts, w, None, RetrievalOptions(edge=edge), PartMeshes(parts_dir, parts, wholes))
    m = np.array([r["retrieve"]["margin"] for r in rows.values()])
    ok = np.array([r["retrieve"]["top1"] for r in rows.values()], dtype=float)
    return m, ok, np.array([probability_of(x) for x in m])


def reliability(p: np.ndarray, ok: np.ndarray, n_bins: int = 10) -> list[tuple[int, float, float]]:
    """(count, mean probability, accuracy) in ``n_bins`` bins of about equal count, by probability."""
    order = np.argsort(p, kind="stable")
    return [(len(b), float(p[b].mean()), float(ok[b].mean())) for b in np.array_split(order, n_bins) if len(b)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dev", type=Path, required=True, help="part_retrieval.py --out of the development set")
    ap.add_argument("--dev-parts", type=Path, required=True, help="its partial_poses.py --out (the parts)")
    ap.add_argument("--check", type=Path, required=True, help="part_retrieval.py --out of the check set")
    ap.add_argument("--check-parts", type=Path, required=True)
    ap.add_argument("--weight", type=float, default=2.0, help="LD-SIFT thickness weight w (default 2, wpot's)")
    ap.add_argument("--out", type=Path, required=True, help="folder for reliability.png")
    ap.add_argument("--edge", choices=("library", "own"), default="library",
                    help="LD-SIFT's edge length of the stored costs (part_retrieval.py --edge; default %(default)s)")
    ap.add_argument("--tosca", type=Path, default=_tosca(Path("../shared/data/tosca_isometric_5k")),
                    help="tosca_isometric_5k, the parts' sources (default: ../shared/data/tosca_isometric_5k)")
    a = ap.parse_args(argv)
    wholes = library_wholes(a.tosca)

    from wpot.maps.retrieval import CALIBRATION, MARGIN_DOUBT

    print(f"shipped calibration (fitted on the development set): intercept {CALIBRATION[0]:.3f}, slope "
          f"{CALIBRATION[1]:.3f}; method {method(a.weight, None, a.edge)}")
    curves = {}
    for name, out, parts in (("development", a.dev, a.dev_parts), ("check", a.check, a.check_parts)):
        m, ok, p = rows_of(out, parts, a.weight, wholes, a.edge)
        if not len(m):
            print(f"{name}: no scored parts in {out}")
            continue
        fit = fit_logistic(m, ok)
        hi = p >= 0.9
        doubt = m < MARGIN_DOUBT
        print(f"\n{name} ({out}): {len(m)} parts, top-1 {ok.mean():.1%}; logistic fitted here: intercept "
              f"{fit[0]:.3f}, slope {fit[1]:.3f}")
        print(f"  probability >= 0.9: {int(hi.sum())} parts, {int(ok[hi].sum())} right "
              f"({ok[hi].mean() if hi.any() else float('nan'):.2%}); misses with probability >= 0.9: "
              f"{int((hi & (ok == 0)).sum())}")
        print(f"  the fixed rule (margin < {MARGIN_DOUBT}): {int(doubt.sum())} parts doubtful, holding "
              f"{int((doubt & (ok == 0)).sum())} of the {int((ok == 0).sum())} misses; right among the others "
              f"{ok[~doubt].mean() if (~doubt).any() else float('nan'):.1%}")
        print("  | parts | mean probability | right | gap |\n  | --- | --- | --- | --- |")
        bins = reliability(p, ok)
        for n, mp, acc in bins:
            print(f"  | {n} | {mp:.3f} | {acc:.3f} | {100 * (acc - mp):+.1f} points |")
        curves[name] = bins
    if curves:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        a.out.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(figsize=(4.5, 4.5))
        ax.plot([0, 1], [0, 1], color="0.7", lw=1)
        for name, bins in curves.items():
            ax.plot([b[1] for b in bins], [b[2] for b in bins], "o-", label=f"{name} ({sum(b[0] for b in bins)} parts)")
        ax.set_xlabel("ClassRanking.probability (bin mean)")
        ax.set_ylabel("share right (top-1)")
        ax.set_title("retrieve: reliability")
        ax.legend(loc="upper left")
        fig.tight_layout()
        fig.savefig(a.out / "reliability.png", dpi=120)
        print(f"\nfigure: {a.out / 'reliability.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
