"""The thickness of a part against its whole's (issue 41, item 3: LD-SIFT's thickness column on cut parts).

A part cut from a whole keeps the whole's geometry away from the cut, so its local thickness
(`wpot.signatures._thickness`) there should be the whole's, at the same vertices. Parts: Euclidean balls of 15, 30
and 50 % of the vertices around random vertices (the largest piece kept), ``--per-size`` of each size a shape.
Shapes: ``--shapes`` spread over each dataset's names (``tosca_isometric_5k``, ``faust_5k``). Compared at the
part's vertices ``--rings`` or more edges from its cut, reported per dataset and size:

* within 5 %: the share of those vertices whose thickness is within 5 % of the whole's; mean |log ratio|; the
  median log ratio (negative: the part reads thinner);
* the same over the vertices that have a value of their own (`thickness_field`'s ``own``: the part measures
  them, no ray that leaves through the cut could move them), and the share of them: the rest are filled in
  from their neighbours, within the bounds their rays give;
* peer, the same run: the part read as the solid its caps close (its rays that leave through the cut read at
  the cap: ``ThicknessField.low``), what a shape diameter function gives a part closed over its holes.

Results go to ``--out`` (outside the repository) as they are computed, so a stopped run resumes; the table is
printed at the end (and with ``--report-only``).

Usage::

    python benchmarks/thickness_parts.py --out /work/runs/thickness_parts
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks.correspondence import _data_root  # noqa: E402
from benchmarks.jsonl_store import JsonlStore, stored_run  # noqa: E402
from benchmarks.ldsift_support import FOLDERS, dataset_folders  # noqa: E402
#: part sizes, shares of the whole's vertices
SIZES = (0.15, 0.30, 0.50)
#: within this relative difference, a vertex's thickness counts as its whole's (issue 41: "to 5 %")
WITHIN = 0.05


def ball_part(mesh, rng: np.random.Generator, share: float):
    """A Euclidean ball of ``share`` of the vertices around a random vertex, the largest piece kept
    (`partial_poses.cut_one_piece`): (part, index map into ``mesh``)."""
    from benchmarks.partial_poses import cut_one_piece

    centre = mesh.vertices[rng.integers(mesh.n_vertices)]
    near = np.argsort(np.linalg.norm(mesh.vertices - centre, axis=1))[: int(round(share * mesh.n_vertices))]
    return cut_one_piece(mesh, near)


def agreement(part: np.ndarray, whole: np.ndarray) -> dict:
    """Share within `WITHIN`, mean |log ratio| and median log ratio of ``part`` against ``whole`` (same shape),
    over the vertices where ``part`` has a value (the capped peer has none where no ray crosses the solid)."""
    ok = np.isfinite(part) & (part > 0)
    part, whole = part[ok], whole[ok]
    if part.size == 0:
        return {"n": 0, "within": float("nan"), "mean_abs_log": float("nan"), "median_log": float("nan")}
    r = np.log(part / whole)
    return {"n": int(part.size), "within": float(np.mean(np.abs(part / whole - 1) <= WITHIN)),
            "mean_abs_log": float(np.mean(np.abs(r))), "median_log": float(np.median(r))}


def run(a, store: JsonlStore, log) -> None:
    from wpot.io import load_mesh
    from wpot.mesh import boundary_rings
    from wpot.signatures._thickness import thickness_field

    for ds, vtx in dataset_folders(a, log):
        names = sorted(p.stem for p in vtx.glob("*.off"))
        names = [names[i] for i in np.unique(np.linspace(0, len(names) - 1, a.shapes).round().astype(int))]
        for name in names:
            todo = [(s, k) for s in SIZES for k in range(a.per_size)
                    if ("ball", f"{ds}:{name}", f"{s:g}:{k}") not in store.done]
            if not todo:
                continue
            whole = load_mesh(vtx / f"{name}.off")
            t_whole = thickness_field(whole, device=a.device).values
            for share, k in todo:
                part, idx = ball_part(whole, np.random.default_rng([a.seed, k, int(share * 100), *map(ord, name)]),
                                      share)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the part's own warning (few vertices measured) is expected
                    f = thickness_field(part, device=a.device)
                far = boundary_rings(part) >= a.rings
                w = t_whole[idx]
                rec = {"method": "ball", "shape": f"{ds}:{name}", "part": f"{share:g}:{k}", "dataset": ds,
                       "share": share, "n_vertices": int(part.n_vertices), "far": int(far.sum()),
                       "own": int((far & f.own).sum()),
                       "all": agreement(f.values[far], w[far]),
                       "own_only": agreement(f.values[far & f.own], w[far & f.own]),
                       "filled": agreement(f.values[far & ~f.own], w[far & ~f.own]),
                       "capped": agreement(f.low[far], w[far])}
                store.add(rec, None)
                log(f"{ds} {name} {share:.0%} #{k}: {part.n_vertices} vertices, {far.sum()} far from the cut, "
                    f"{rec['own']} of them measured; within 5 %: {rec['all']['within']:.2f} (measured "
                    f"{rec['own_only']['within']:.2f}; capped {rec['capped']['within']:.2f})")


def _pooled(rows: list[dict], key: str) -> str:
    """Vertex-weighted pool of the rows' ``key`` agreements: 'within, mean |log|, median log (of the rows)'."""
    rows = [r[key] for r in rows if r[key]["n"] > 0]
    if not rows:
        return "–"
    n = np.array([r["n"] for r in rows], float)
    within = float(np.sum(n * [r["within"] for r in rows]) / n.sum())
    mal = float(np.sum(n * [r["mean_abs_log"] for r in rows]) / n.sum())
    return f"{within:.1%}, {mal:.3f}, {np.median([r['median_log'] for r in rows]):+.3f}"


def report(store: JsonlStore, a, log) -> None:
    log(f"\nVertices {a.rings} or more edges from the cut; each cell: within 5 % of the whole's, mean |log ratio|, "
        "median log ratio (the parts' medians)\n")
    log("| dataset | part size | parts | measured (own value) | all: as built | measured vertices | filled-in "
        "vertices | peer: capped part |")
    log("|---|---|---|---|---|---|---|---|")
    for ds in a.dataset:
        for share in SIZES:
            rows = [r for r in store.records if r["dataset"] == ds and r["share"] == share]
            if not rows:
                continue
            own = sum(r["own"] for r in rows) / max(1, sum(r["far"] for r in rows))
            log(f"| {ds} | {share:.0%} | {len(rows)} | {own:.1%} | {_pooled(rows, 'all')} | "
                f"{_pooled(rows, 'own_only')} | {_pooled(rows, 'filled')} | {_pooled(rows, 'capped')} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=_data_root())
    ap.add_argument("--out", type=Path, required=True, help="results folder (outside the repository)")
    ap.add_argument("--dataset", nargs="+", default=["tosca", "faust"], choices=list(FOLDERS))
    ap.add_argument("--shapes", type=int, default=10, help="shapes per dataset, spread over its names")
    ap.add_argument("--per-size", type=int, default=2, help="parts of each size a shape")
    ap.add_argument("--rings", type=int, default=5, help="compare vertices at least this many edges from the cut")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--report-only", action="store_true")
    a = ap.parse_args(argv)
    if a.shapes < 1 or a.per_size < 1 or a.rings < 0:
        ap.error("--shapes and --per-size must be at least 1, --rings at least 0")
    return stored_run(a, ("shape", "part"), run, report)


if __name__ == "__main__":
    sys.exit(main())
