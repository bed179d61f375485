"""How far `ClassRanking.probability` (the chance that `Comparer.retrieve`'s first class is right) can be trusted.

Reads `part_retrieval.py` results folders: **development** sets, pooled, on which the calibration is fitted
(logistic regression of "the first class is right" on the ranking's margin, `fit_logistic`), and **check** sets,
on which it is only measured. For each set it prints, beside the fixed rule it replaces ("margin below
`wpot.maps.retrieval.MARGIN_DOUBT` is doubtful"):

* top-1 and the parts with probability >= 0.9: how many, and how many of them are right;
* a reliability table: the parts in ten bins of equal count by probability, each bin's mean probability beside
  its observed accuracy (a calibrated probability lies within a few points of it);
* the logistic fitted afresh to this set and to the pooled development sets, beside the shipped
  `wpot.maps.retrieval.CALIBRATION` (fitted on development sets; the probabilities are the shipped one's).

and draws the reliability diagram of every set (``--out``/reliability.png). Each set is ``RESULTS PARTS [DATA]``:
its `part_retrieval.py` ``--out``, its `partial_poses.py` ``--out``, and the data folder of its library
(default ``--tosca``; e.g. ``faust_5k`` for FAUST's people).

Usage:

    python benchmarks/retrieval_calibration.py --dev /work/runs/pr_dev /work/runs/pp_dev \\
        --dev /work/runs/pr_s1 /work/runs/pp_s1 --check /work/runs/pr_lowres /work/runs/pp_lowres \\
        --check /work/runs/pr_faust /work/runs/pp_faust ../shared/data/faust_5k --weight 0 --out /work/runs/calibration
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks.part_retrieval import PartMeshes, library_wholes, method, open_store, score  # noqa: E402
from benchmarks.partial_poses import _tosca, read_parts  # noqa: E402
from wpot.maps.retrieval import CALIBRATED_THICKNESS, CALIBRATION, MARGIN_DOUBT, fit_logistic  # noqa: E402


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


def _set(values: list[str], default_data: Path) -> tuple[Path, Path, Path]:
    """``RESULTS PARTS [DATA]`` of one set, as paths."""
    if len(values) not in (2, 3):
        raise SystemExit(f"a set is RESULTS PARTS [DATA], got {len(values)} values: {values}")
    data = Path(values[2]) if len(values) == 3 else default_data
    if not data.is_dir():
        raise SystemExit(f"the data folder {data} of the set {values[0]} is not a folder")
    return Path(values[0]), Path(values[1]), data


def report_set(name: str, m: np.ndarray, ok: np.ndarray, probabilities: dict[str, np.ndarray]
               ) -> dict[str, list[tuple[int, float, float]]]:
    """Print one set's top-1 and the fixed rule, then for each calibration (``probabilities``: its name, the
    parts' probabilities) its parts with probability >= 0.9, its log loss and Brier score, and its reliability
    table; return each calibration's table bins."""
    fit = fit_logistic(m, ok)
    doubt = m < MARGIN_DOUBT
    print(f"\n{name}: {len(m)} parts, top-1 {ok.mean():.1%}; logistic fitted here: intercept {fit[0]:.3f}, slope "
          f"{fit[1]:.3f}")
    print(f"  the fixed rule (margin < {MARGIN_DOUBT}): {int(doubt.sum())} parts doubtful, holding "
          f"{int((doubt & (ok == 0)).sum())} of the {int((ok == 0).sum())} misses; right among the others "
          f"{ok[~doubt].mean() if (~doubt).any() else float('nan'):.1%}")
    out = {}
    for cal, p in probabilities.items():
        hi = p >= 0.9
        q = np.clip(p, 1e-12, 1 - 1e-12)
        print(f"  {cal}: probability >= 0.9: {int(hi.sum())} parts, {int(ok[hi].sum())} right "
              f"({ok[hi].mean() if hi.any() else float('nan'):.2%}); log loss "
              f"{-np.mean(ok * np.log(q) + (1 - ok) * np.log(1 - q)):.3f}, Brier {np.mean((p - ok) ** 2):.3f}")
        print("  | parts | mean probability | right | gap |\n  | --- | --- | --- | --- |")
        out[cal] = reliability(p, ok)
        for n, mp, acc in out[cal]:
            print(f"  | {n} | {mp:.3f} | {acc:.3f} | {100 * (acc - mp):+.1f} points |")
    return out


def library_calibration(data: Path, wholes: dict, n_parts: int, out: Path):
    """`Comparer.calibrate_retrieval` on every whole of ``data`` (LD-SIFT at its defaults, the default options),
    read from ``out`` when a run before stored it (JSON); a stopped one resumes from its lookups' record there."""
    import wpot
    from benchmarks.partial_poses import shape_class
    from wpot.maps.retrieval import RetrievalCalibration

    path = out / f"library_calibration_{data.name}_{n_parts}.json"
    if path.exists():
        return RetrievalCalibration.from_json(path.read_text())
    names = sorted(wholes)
    out.mkdir(parents=True, exist_ok=True)
    cal = wpot.Comparer(signature="ldsift", device="cpu").calibrate_retrieval(
        [wholes[n] for n in names], [shape_class(n) for n in names], n_parts=n_parts,
        record=path.with_suffix(".lookups.jsonl"))
    path.write_text(cal.to_json())
    return cal


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dev", nargs="+", action="append", required=True, metavar="PATH",
                    help="a development set, RESULTS PARTS [DATA] (repeat for several; they are pooled)")
    ap.add_argument("--check", nargs="+", action="append", default=[], metavar="PATH",
                    help="a check set, RESULTS PARTS [DATA] (repeat for several)")
    ap.add_argument("--weight", type=float, default=CALIBRATED_THICKNESS,
                    help="LD-SIFT thickness weight w of the stored costs (default %(default)g: wpot.maps.retrieval."
                         "CALIBRATED_THICKNESS, what the shipped calibration was fitted at)")
    ap.add_argument("--out", type=Path, required=True, help="folder for reliability.png")
    ap.add_argument("--edge", choices=("library", "own"), default="library",
                    help="LD-SIFT's edge length of the stored costs (part_retrieval.py --edge; default %(default)s)")
    ap.add_argument("--tosca", type=Path, default=_tosca(Path("../shared/data/tosca_isometric_5k")),
                    help="the data folder of a set that names none (default: ../shared/data/tosca_isometric_5k)")
    ap.add_argument("--library-parts", type=int, default=0,
                    help="also calibrate on each set's library (Comparer.calibrate_retrieval) with this many parts cut "
                         "from its wholes, and report those probabilities beside the shipped ones (default 0: off)")
    a = ap.parse_args(argv)
    if a.library_parts < 0:
        raise SystemExit(f"--library-parts must be >= 0, got {a.library_parts}")
    print(f"shipped calibration: intercept {CALIBRATION[0]:.3f}, slope {CALIBRATION[1]:.3f}; method "
          f"{method(a.weight, None, a.edge)}")
    wholes_of: dict[Path, dict] = {}
    library_of: dict[Path, object] = {}  # each data folder's own calibration, once
    curves, pooled, seen = {}, [], set()
    for role, sets in (("development", a.dev), ("check", a.check)):
        for values in sets:
            out, parts, data = _set(values, a.tosca)
            if data not in wholes_of:
                wholes_of[data] = library_wholes(data)
            m, ok, p = rows_of(out, parts, a.weight, wholes_of[data], a.edge)
            name = f"{role} {out.name}"
            if name in seen:  # two sets in folders of one name: each keeps its curve, told apart by path
                name = f"{role} {out}"
            seen.add(name)
            if not len(m):
                print(f"\n{name}: no scored parts in {out}")
                continue
            probabilities = {"shipped": p}
            if a.library_parts:
                if data not in library_of:
                    library_of[data] = library_calibration(data, wholes_of[data], a.library_parts, a.out)
                cal = library_of[data]
                print(f"\nthe library calibration of {data.name}: {cal.n_right} of {cal.n_parts} parts right, "
                      f"intercept {cal.intercept:.3f}, slope {cal.slope:.3f}")
                probabilities[f"library's own ({data.name})"] = np.array([cal.probability(x) for x in m])
            curves[name] = report_set(name, m, ok, probabilities)
            if role == "development":
                pooled.append((m, ok))
    if pooled:
        fit = fit_logistic(np.concatenate([m for m, _ in pooled]), np.concatenate([ok for _, ok in pooled]))
        print(f"\nthe development sets pooled ({sum(len(m) for m, _ in pooled)} parts): intercept {fit[0]:.3f}, "
              f"slope {fit[1]:.3f}")
    if curves:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        a.out.mkdir(parents=True, exist_ok=True)
        cols = min(3, len(curves))
        rows = -(-len(curves) // cols)
        fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.6 * rows), squeeze=False)
        for ax in axes.ravel()[len(curves):]:
            ax.set_visible(False)
        for ax, (name, by_cal) in zip(axes.ravel(), curves.items()):  # a panel a set, a line a calibration
            ax.plot([0, 1], [0, 1], color="0.7", lw=1)
            for cal_name, bins in by_cal.items():
                ax.plot([b[1] for b in bins], [b[2] for b in bins], "o--" if cal_name != "shipped" else "o-",
                        label=cal_name)
            ax.set_title(f"{name} ({sum(b[0] for b in next(iter(by_cal.values())))} parts)", fontsize=9)
            ax.set_xlabel("ClassRanking.probability (bin mean)", fontsize=8)
            ax.set_ylabel("share right (top-1)", fontsize=8)
            ax.legend(loc="upper left", fontsize=7)
        fig.tight_layout()
        fig.savefig(a.out / "reliability.png", dpi=120)
        print(f"\nfigure: {a.out / 'reliability.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
