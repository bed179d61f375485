"""Registration of a comparison's matched pairs: the plain weighted least-squares fit (`fit_similarity`, the
peer) against the registration the `Comparer` stores (scale: the size ratio of the two shapes,
`area_scale`; rotation and translation: `fit_similarity_robust`), on the same pairs in the same run.

* **demo**: the shapes of ``wpot demo`` (one surface triangulated twice, B rigidly moved; 400 vertices, WKS
  with 100 eigenpairs and 100 energies, balanced transport). The true motion is known: scale 1, and the
  rotation error is the angle of ``R_fit R_trueᵀ``, the translation error relative to the bounding-box diagonal.
* **TOSCA**: same-class pairs of ``tosca_isometric_5k/test_pairs.txt`` (two poses of one body, of one size), the
  first ``--pairs`` of them taking one pair per class in turn, WKS balanced with ``--max-vertices`` samples.
  No rigid truth exists between two poses; the scale should be 1 (same size), and the rotation is reported
  against the robust fit to the ground-truth correspondence (``corres/*.vts``, 5,000 template points).

Prints one table (markdown) with, for each pair: matched pairs, then scale and rotation error of the plain and
of the robust fit side by side, the robust fit's inlier fraction and its time. Skips TOSCA with a reason when
the data is absent.

Usage (about 20 s per TOSCA pair on 2 busy cores; WPOT_CACHE_DIR speeds up a second run)::

    OPENBLAS_NUM_THREADS=1 python benchmarks/registration.py --pairs 10 --max-vertices 400
"""
from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: the shared data folder: $WPOT_DATA, else ../shared/data beside the repository
TOSCA = Path(os.environ.get("WPOT_DATA", ROOT.parent / "shared" / "data")) / "tosca_isometric_5k"


def angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def fits(c, mesh_a, mesh_b):
    """The plain least-squares fit of the comparison's matched pairs, and the registration the Comparer stored
    (the size ratio of the two shapes as scale, rotation and translation by the robust fit), refitted here
    to time it."""
    from wpot.maps.registration import fit_similarity, fit_similarity_robust

    p, q, w = mesh_a.vertices[c.matched[:, 0]], mesh_b.vertices[c.matched[:, 1]], c.matched_weight
    plain = fit_similarity(p, q, w)
    t0 = time.perf_counter()
    stored = c.registration
    again = fit_similarity_robust(p, q, w, scale=stored.scale if stored.scale_from == "given" else None)
    assert again.scale == stored.scale and np.array_equal(again.rotation, stored.rotation)
    return plain, stored, time.perf_counter() - t0


def row(name, n, plain, robust, seconds, truth_rot=None, note=""):
    def err(r):
        rot = f"{angle_deg(r.rotation @ truth_rot.T):.2f}" if truth_rot is not None else "-"
        return f"{r.scale:.3f} | {rot}"
    return (f"| {name} | {n} | {err(plain)} | {err(robust)} | {100 * robust.inlier_fraction:.0f} % | "
            f"{1000 * seconds:.0f} ms |{note}")


def demo_rows():
    from wpot.cli import DEMO
    from wpot.comparison import Comparer
    from wpot.examples import example_pair

    pair = example_pair(DEMO["n"], seed=0, n_target=DEMO["n"])
    c = Comparer(n_eigen=DEMO["n_eigen"], n_energies=DEMO["n_energies"]).compare(pair.source, pair.target)
    plain, robust, dt = fits(c, pair.source, pair.target)
    yield row("demo (truth: scale 1, known rotation)", len(c.matched), plain, robust, dt, np.asarray(pair.rotation))
    diag = pair.source.bounding_box_diagonal
    for label, r in (("plain", plain), ("robust", robust)):
        print(f"  demo {label}: translation error {100 * np.linalg.norm(r.translation - pair.translation) / diag:.2f} % "
              f"of the diagonal; rms {r.with_target(pair.target).rms_text()}", file=sys.stderr)


def tosca_pairs(limit: int) -> list[tuple[str, str]]:
    pairs = [tuple(line.split()) for line in (TOSCA / "test_pairs.txt").read_text().splitlines() if line.strip()]
    pairs = [(x, y) for x, y in pairs if x.rstrip("0123456789") == y.rstrip("0123456789")]
    by_class: dict[str, list] = {}
    for x, y in pairs:
        by_class.setdefault(x.rstrip("0123456789"), []).append((x, y))
    out, i = [], 0
    while len(out) < limit and any(i < len(v) for v in by_class.values()):
        out += [v[i] for v in by_class.values() if i < len(v)]
        i += 1
    return out[:limit]


def tosca_rows(limit: int, max_vertices: int):
    from wpot.comparison import Comparer
    from wpot.io import load_mesh
    from wpot.maps.registration import fit_similarity_robust

    vtx = TOSCA / "vtx_5k"
    comparer = Comparer(max_vertices=max_vertices)
    for x, y in tosca_pairs(limit):
        a, b = load_mesh(vtx / f"{x}.off"), load_mesh(vtx / f"{y}.off")
        ta = np.loadtxt(vtx / "corres" / f"{x}.vts", dtype=np.int64) - 1
        tb = np.loadtxt(vtx / "corres" / f"{y}.vts", dtype=np.int64) - 1
        truth = fit_similarity_robust(a.vertices[ta], b.vertices[tb])
        c = comparer.compare(a, b)
        plain, robust, dt = fits(c, a, b)
        yield row(f"TOSCA {x}/{y}", len(c.matched), plain, robust, dt, truth.rotation,
                  note=f" truth fit: scale {truth.scale:.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=10, help="TOSCA same-class pairs (default 10; 0 skips TOSCA)")
    ap.add_argument("--max-vertices", type=int, default=400, help="farthest-point samples per TOSCA mesh (default 400)")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    print("| pair | matched pairs | plain scale | plain rotation error (deg) | robust scale | robust rotation "
          "error (deg) | robust inliers | robust fit time |")
    print("|---|---|---|---|---|---|---|---|")
    for line in demo_rows():
        print(line, flush=True)
    if a.pairs <= 0:
        return 0
    if not (TOSCA / "test_pairs.txt").is_file():
        print(f"TOSCA skipped: {TOSCA} is absent", file=sys.stderr)
        return 0
    for line in tosca_rows(a.pairs, a.max_vertices):
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
