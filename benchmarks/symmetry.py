"""A shape's own left/right mirror (`wpot.maps.symmetry.reflection_symmetry`), against the data's ground truth.

`keep_orientation` (whole-to-whole maps) and `locate`'s step 4 send a stretch that reverses orientation through a
shape's mirror, so a shape without a detected mirror loses that repair. For every shape of each dataset, the
mirror is detected with ``--oriented-k`` (the default, `ORIENTED_K`: where plain ZoomOut finds no mirror, a second
try whose rounds to that resolution also match the pseudoscalars) and, as the peer, with ``oriented_k=0`` (plain
ZoomOut alone), each without the symmetry
cache and timed, the shape's spectrum computed first. The truth is the data's own: line i of ``<shape>.vts``
and of ``<shape>.sym.vts`` are mirror images. Reported per dataset, for each variant: the shapes whose mirror is
found (orientation score below ``-MIN_SCORE``), the mean and worst error over them (Euclidean, over √area, mean
over the template points), the median time; and, over the shapes both find, how many each does better by more
than 0.003.

Results go to ``--out`` (outside the repository) as they are computed, so a stopped run resumes; the table is
printed at the end (and with ``--report-only``).

Usage::

    WPOT_CACHE_DIR=/work/runs/cache python benchmarks/symmetry.py --out /work/runs/symmetry
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
from benchmarks.ldsift_support import FOLDERS, dataset_folders  # noqa: E402

#: a better / worse verdict between the two variants needs a difference above this (√area)
MARGIN = 0.003


def mirror_error(mesh, sym_map: np.ndarray, points: np.ndarray, mirrors: np.ndarray) -> float:
    """Mean distance over √area(mesh) from the map's image of each template point (``points``, vertex indices)
    to its true mirror (``mirrors``)."""
    return float(np.linalg.norm(mesh.vertices[sym_map[points]] - mesh.vertices[mirrors], axis=1).mean()
                 / np.sqrt(mesh.area))


def variants(a) -> dict[str, int]:
    """Method name -> ``oriented_k``: the setting under test and the peer (plain ZoomOut)."""
    return {f"oriented_k={a.oriented_k}": a.oriented_k, "plain (oriented_k=0)": 0}


def run(a, store: JsonlStore, log) -> None:
    from wpot.datasets import tosca_ground_truth
    from wpot.io import load_mesh
    from wpot.maps.symmetry import reflection_symmetry
    from wpot.maps.zoom import spectral_basis

    for ds, vtx in dataset_folders(a, log):
        for path in sorted(vtx.glob("*.off")):
            name = path.stem
            todo = {m: k for m, k in variants(a).items() if (m, ds, name) not in store.done}
            if not todo:
                continue
            mesh = load_mesh(path)
            spectral_basis(mesh, None)  # the spectrum both variants read, computed (or cached) before the clocks
            points, mirrors = tosca_ground_truth(vtx, name, name, symmetric=True)
            for method, k in todo.items():
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # a mesh's own defects are not what is measured
                    sym = reflection_symmetry(mesh, oriented_k=k, cache=False)
                rec = {"method": method, "dataset": ds, "shape": name, "seconds": time.perf_counter() - t0,
                       "found": sym is not None}
                if sym is not None:
                    rec.update(error=mirror_error(mesh, sym.map, points, mirrors), score=sym.score,
                               residual=sym.residual)
                store.add(rec, None)
                log(f"{ds} {name} {method}: " + (f"error {rec['error']:.4f}, score {rec['score']:.3f}"
                                                 if sym is not None else "no mirror found")
                    + f", {rec['seconds']:.1f} s")


def report(store: JsonlStore, a, log) -> None:
    names = list(variants(a))
    log("\n| dataset | shapes | " + " | ".join(f"{m}: found, mean error (worst), median time" for m in names)
        + f" | both found: mean error {names[0]} / peer, better / worse by {MARGIN} |")
    log("|---|---|" + "---|" * (len(names) + 1))
    for ds in a.dataset:
        recs = {(r["method"], r["shape"]): r for r in store.records if r["dataset"] == ds}
        shapes = sorted({s for _, s in recs})
        if not shapes:
            continue
        cells = []
        for m in names:
            rows = [recs[m, s] for s in shapes if (m, s) in recs]
            err = [r["error"] for r in rows if r["found"]]
            cells.append(f"{len(err)} of {len(rows)}, " + (f"{np.mean(err):.4f} ({max(err):.3f})" if err else "–")
                         + f", {np.median([r['seconds'] for r in rows]):.1f} s")
        both = [(recs[names[0], s]["error"], recs[names[1], s]["error"]) for s in shapes
                if all((m, s) in recs and recs[m, s]["found"] for m in names)]
        b = np.array(both).reshape(-1, 2)
        cells.append(f"{len(b)}: {b[:, 0].mean():.4f} / {b[:, 1].mean():.4f}, "
                     f"{int((b[:, 0] < b[:, 1] - MARGIN).sum())} / {int((b[:, 0] > b[:, 1] + MARGIN).sum())}"
                     if len(b) else "–")
        log(f"| {FOLDERS[ds]} | {len(shapes)} | " + " | ".join(cells) + " |")


def main(argv=None) -> int:
    from wpot.maps.symmetry import ORIENTED_K

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=_data_root())
    ap.add_argument("--out", type=Path, required=True, help="results folder (outside the repository)")
    ap.add_argument("--dataset", nargs="+", default=["faust", "tosca"], choices=list(FOLDERS))
    ap.add_argument("--oriented-k", type=int, default=ORIENTED_K,
                    help="the setting under test (default: ORIENTED_K); the peer is 0, plain ZoomOut")
    ap.add_argument("--report-only", action="store_true")
    a = ap.parse_args(argv)
    if a.oriented_k == 0:
        ap.error("--oriented-k 0 is the peer itself; give the setting to test against it")
    return stored_run(a, ("dataset", "shape"), run, report)


if __name__ == "__main__":
    raise SystemExit(main())
