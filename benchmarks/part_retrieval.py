"""Class retrieval of parts from a library of whole shapes: issue 23's "a part retrieves its class".

**Parts**: those of a `partial_poses.py` run (``--parts``: its ``--out`` folder, ``parts.jsonl`` and
``parts/<part>.npz``): heads, limbs, plane cuts and holes cut from TOSCA 5k poses.

**Library**: every shape of ``tosca_isometric_5k`` (76 shapes, eight classes) except the part's own source pose,
which holds the part itself (with ``--tosca`` naming ``faust_5k``: its 100 shapes, a shape's class its person).
The part's class has other poses there (2 to 19 of them), and so has every other class: what a user faces who
looks a part up in a dataset of whole shapes.

**Costs**: for each part and each whole of its library, the cost from each vertex of the part to the nearest
signature of the whole (`Comparer.nearest_costs`), LD-SIFT at one edge length for the part and the library, the
library's, as `Comparer.retrieve` does (``--edge library``, the default; ``--edge own``: each mesh's own, the
paper's), with each ``--weights`` w of its thickness column
(``ldsift_thickness``); w = 0, the paper's LD-SIFT, is the peer in the same run. One `Comparer` and its
``with_options`` copies share the signature cache, where LD-SIFT is kept as its descriptor and its thickness
apart, so every weight reuses one descriptor a shape.

**Two scorings of the same costs**, per weight:
- *nearest whole*: the class of the whole with the least mean cost (`Comparer.nearest_signature_distance`);
- *retrieve*: the first class of `Comparer.retrieve` (`wpot.maps.retrieval.rank_classes`: each vertex's costs
  standardised over the library, a class scored by the union of its ``--k-nearest`` nearest members).

**Reported** per weight and scoring, over the parts, each part weighing the same: top-1 (the part's class comes
first), by kind and by size (parts >= 20 % / < 20 % of the area); the mean rank of the part's class (1 = top-1);
and each failure with the class it was taken for. `partial_poses.py` reports a stricter, per-pair score: every
same-class pose it drew nearer than one drawn pose of each other class.

Results go to ``--out`` (outside the repository) as they are computed, one line per (weight, part) in
``pairs.jsonl`` and the part's (N, M) costs in ``costs/<method>/<part>__library.npz`` (float32, with the
wholes' names), so a stopped run resumes and ``--report-only`` rescores at another ``--k-nearest``; then
``results.md``.

Usage (two CPU cores: about 10 minutes a weight for 112 parts and 75 wholes):

    WPOT_CACHE_DIR=/work/runs/cache python benchmarks/part_retrieval.py \\
        --parts /work/runs/partial_poses --out /work/runs/part_retrieval --weights 0,1,2
    python benchmarks/part_retrieval.py --parts /work/runs/partial_poses --out /work/runs/part_retrieval --report-only
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks.jsonl_store import JsonlStore, results_folder  # noqa: E402
from benchmarks.partial_poses import KINDS, LARGE, _tosca, _vtx, class_members, read_parts, shape_class  # noqa: E402


def method(w: float, slab: float | None = None, edge: str = "own", orientation: str = "frame") -> str:
    """The stored costs' name: LD-SIFT's thickness weight, its slab, its edge length (``"library"``: the
    library's for every mesh, as `Comparer.retrieve` does by default; ``"own"``: each mesh's, the paper's) and its
    orientation (``"frame"``, the paper's, is not named)."""
    return (f"nn-ldsift-w{w:g}" + ("" if slab is None else f"-slab{slab:g}") + ("-libedge" if edge == "library" else "")
            + ("" if orientation == "frame" else f"-{orientation}"))


LIBRARY = "library"  # the second key of a record: the part's library (every whole but its source)
SCORINGS = ("nearest whole", "retrieve")


def open_store(out: Path) -> JsonlStore:
    """The results of a run in folder ``out``: one record per (method, part, library), the costs in ``costs/``."""
    return JsonlStore(out, keys=("part", "library"), folder="costs")


class PartMeshes:
    """The parts of a `partial_poses.py` run as meshes, by name: a re-meshed part (``--remesh``) is stored whole,
    the others are cut from their source pose (one of ``wholes``) again."""

    def __init__(self, parts_dir: Path, parts: dict[str, dict], wholes: dict) -> None:
        self.parts_dir, self.parts, self.wholes = parts_dir, parts, wholes

    def __call__(self, name: str):
        import wpot
        from wpot.mesh import cut

        with np.load(self.parts_dir / "parts" / f"{name}.npz", allow_pickle=False) as stored:
            if "vertices" in stored:
                return wpot.Mesh(stored["vertices"], stored["faces"], warn=False)
            return cut(self.wholes[self.parts[name]["source"]], stored["idx"])[0]


def library_wholes(tosca: Path) -> dict:
    """Every shape of ``tosca`` (tosca_isometric_5k), by name."""
    from wpot.io import load_mesh

    return {n: load_mesh(_vtx(tosca) / f"{n}.off", warn=False) for names in class_members(tosca).values()
            for n in names}


def score_part(costs: np.ndarray, wholes: list[str], cls: str, options, sample=None) -> dict[str, dict]:
    """Both scorings of one part from its (N, M) ``costs`` to ``wholes``, on the rows `Comparer.retrieve` uses:
    those of ``sample`` (the part's `wpot.maps.retrieval.retrieval_sample`, weighted by its cells), or every row
    when it is None. Per scoring: top-1, the rank of class ``cls`` (None when the library has none of it) and
    what the part was taken for (the first whole or class)."""
    from wpot.maps.retrieval import rank_classes

    labels = [shape_class(n) for n in wholes]
    if sample is not None:
        costs, weights = costs[sample.indices], sample.counts
    else:
        weights = None
    r = rank_classes(costs, labels, weights=weights, options=options)
    order = np.argsort(r.whole_costs, kind="stable")
    ranked = [labels[j] for j in order]
    return {"nearest whole": {"top1": ranked[0] == cls, "rank": ranked.index(cls) + 1 if cls in ranked else None,
                              "taken_for": wholes[order[0]]},
            "retrieve": {"top1": r.label == cls, "rank": r.rank(cls) if cls in r.classes else None,
                         "taken_for": f"{r.label} ({wholes[r.members[0][0]]})", "margin": r.margin}}


def score(store: JsonlStore, parts: dict[str, dict], w: float, slab: float | None, options,
          meshes: PartMeshes | None = None, orientation: str = "frame") -> dict:
    """Per part with stored costs for weight ``w``: its kind, its size, and `score_part` on the rows of its
    `wpot.maps.retrieval.retrieval_sample` (``meshes`` gives the part's mesh; None: every row, as for parts of
    at most ``options.max_points`` vertices)."""
    from wpot.maps.retrieval import retrieval_sample

    rows = {}
    for rec in store.records:
        if rec["method"] != method(w, slab, options.edge, orientation) or rec["part"] not in parts:
            continue
        p = parts[rec["part"]]
        with np.load(store.npz_path(rec["method"], rec["part"], LIBRARY), allow_pickle=False) as z:
            costs, wholes = z["costs"].astype(np.float64), [str(x) for x in z["wholes"]]
        rows[rec["part"]] = {"kind": p["kind"], "large": p["fraction"] >= LARGE,
                             **score_part(costs, wholes, p["class"], options,
                                          None if meshes is None else retrieval_sample(meshes(rec["part"]), options))}
    return rows


def margin_line(w: float, rows: dict, share: float = 0.1) -> str:
    """How well `ClassRanking.margin` flags retrieve's misses: how many of them lie in the ``share`` of the parts
    with the smallest margins, and top-1 over the other parts."""
    m = np.array([r["retrieve"]["margin"] for r in rows.values()])
    ok = np.array([r["retrieve"]["top1"] for r in rows.values()])
    low = np.argsort(m, kind="stable")[:int(round(share * len(m)))]
    rest = np.setdiff1d(np.arange(len(m)), low)
    worst = f"{m[~ok].max():.3g}" if (~ok).any() else "–"
    return (f"\nw = {w:g}, retrieve's margin (second class's score less the first's): the {share:.0%} of parts with "
            f"the smallest margins ({len(low)}) hold {int((~ok[low]).sum())} of the {int((~ok).sum())} misses; top-1 "
            f"over the other parts {ok[rest].mean():.1%}; the misses' largest margin {worst}\n")


def report(store: JsonlStore, parts: dict[str, dict], weights: list[float], slab: float | None, options,
           meshes: PartMeshes | None, out: Path, log, orientation: str = "frame") -> None:
    lines = [f"LD-SIFT slab: {'the default' if slab is None else f'{slab:g}'}, edge length: {options.edge}, "
             f"orientation: {orientation}; retrieve: "
             f"k_nearest {options.k_nearest}, standardize {options.standardize}, max_points {options.max_points}", "",
             "| w | scoring | top-1, all parts | parts >= 20 % | < 20 % | " + " | ".join(KINDS)
             + " | mean rank of the class |", "|---|---|---|---|---|" + "---|" * len(KINDS) + "---|"]
    fails = []
    for w in weights:
        rows = score(store, parts, w, slab, options, meshes, orientation)
        if not rows:
            continue
        for sc in SCORINGS:
            def pct(sel) -> str:
                v = [r[sc]["top1"] for r in rows.values() if sel(r)]
                return f"{np.mean(v):.1%} ({len(v)})" if v else "–"

            ranks = [r[sc]["rank"] for r in rows.values() if r[sc]["rank"]]
            lines.append(f"| {w:g} | {sc} | {pct(lambda r: True)} | {pct(lambda r: r['large'])} | "
                         f"{pct(lambda r: not r['large'])} | "
                         + " | ".join(pct(lambda r, k=k: r["kind"] == k) for k in KINDS)
                         + f" | {np.mean(ranks):.2f} |")
            fails.append(f"w = {w:g}, {sc}: " + (", ".join(
                f"{pt} ({parts[pt]['fraction']:.0%}) -> {r[sc]['taken_for']}"
                for pt, r in sorted(rows.items()) if not r[sc]["top1"]) or "none"))
        lines.append(margin_line(w, rows))
    text = "\n".join(lines + ["", "failures (part, its share of the area, what it was taken for):"] + fails)
    (out / "results.md").write_text(text + "\n")
    log(text)


def main(argv=None) -> int:
    from wpot.maps.retrieval import EDGES, RetrievalOptions
    from wpot.signatures._ldsift import ORIENTATIONS

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", type=Path, required=True, help="a partial_poses.py --out folder (its parts)")
    ap.add_argument("--out", type=Path, required=True, help="results folder, outside the repository")
    ap.add_argument("--tosca", type=Path, default=_tosca(Path("../shared/data/tosca_isometric_5k")),
                    help="tosca_isometric_5k (default: ../shared/data/tosca_isometric_5k)")
    ap.add_argument("--weights", default="0,1,2", help="LD-SIFT thickness weights w, comma-separated (default 0,1,2)")
    ap.add_argument("--ldsift-slab", type=float, default=None,
                    help="LD-SIFT's depth slab (ldsift_slab; default: LD-SIFT's own), a method of its own in --out")
    ap.add_argument("--ldsift-orientation", choices=ORIENTATIONS, default="frame",
                    help="LD-SIFT's orientation (ldsift_orientation; the paper's 'frame' by default), a method of its "
                         "own in --out")
    ap.add_argument("--k-nearest", type=int, default=RetrievalOptions.k_nearest,
                    help="retrieve's k_nearest: a class is the union of this many of its members (default %(default)s)")
    ap.add_argument("--edge", choices=EDGES, default=RetrievalOptions.edge,
                    help="LD-SIFT's edge length: the library's for every mesh (library, retrieve's default) or each "
                    "mesh's own (own, the paper's); default %(default)s")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--report-only", action="store_true")
    a = ap.parse_args(argv)
    try:
        weights = [float(x) for x in a.weights.split(",")]
    except ValueError:
        raise SystemExit(f"--weights must be numbers separated by commas, got {a.weights!r}")
    if not all(np.isfinite(w) and w >= 0 for w in weights):
        raise SystemExit(f"--weights must be finite and >= 0, got {a.weights!r}")
    if a.ldsift_slab is not None and not (np.isfinite(a.ldsift_slab) and a.ldsift_slab > 0):
        raise SystemExit(f"--ldsift-slab must be a positive number, got {a.ldsift_slab}")
    if a.k_nearest < 1:
        raise SystemExit(f"--k-nearest must be at least 1, got {a.k_nearest}")
    parts = read_parts(a.parts)
    if not parts:
        raise SystemExit(f"--parts {a.parts}: no parts.jsonl there; run partial_poses.py with --out {a.parts} first")
    if not _vtx(a.tosca).is_dir():
        raise SystemExit(f"--tosca {a.tosca}: not found (tosca_isometric_5k, see ../shared/data/README)")
    out, log = results_folder(a.out)
    store = open_store(out)
    wholes = library_wholes(a.tosca)
    meshes = PartMeshes(a.parts, parts, wholes)
    options = RetrievalOptions(k_nearest=a.k_nearest, edge=a.edge)
    if not a.report_only:
        run(a, parts, weights, store, wholes, meshes, log)
    report(store, parts, weights, a.ldsift_slab, options, meshes, out, log, a.ldsift_orientation)
    return 0


def run(a, parts: dict[str, dict], weights: list[float], store: JsonlStore, wholes: dict, meshes: PartMeshes,
        log) -> None:
    import wpot
    from wpot.comparison import at_common_edge

    slab = {} if a.ldsift_slab is None else {"ldsift_slab": a.ldsift_slab}
    base = wpot.Comparer(signature="ldsift", device=a.device, ldsift_orientation=a.ldsift_orientation, **slab)
    comparers = {w: base.with_options(ldsift_thickness=w) for w in weights}
    log(f"{len(parts)} parts, {len(wholes)} wholes, weights {weights}; wpot {wpot.__file__}")
    t0 = time.perf_counter()
    for k, (pt, p) in enumerate(parts.items()):
        name = {w: method(w, a.ldsift_slab, a.edge, a.ldsift_orientation) for w in comparers}
        todo = {w: c for w, c in comparers.items() if (name[w], pt, LIBRARY) not in store.done}
        if not todo:
            continue
        part = meshes(pt)
        library = [n for n in wholes if n != p["source"]]
        for w, c in todo.items():
            t = time.perf_counter()
            if a.edge == "library":  # as Comparer.retrieve: one edge length, the library's, for part and wholes
                c = at_common_edge(c, [wholes[n] for n in library])
            costs = c.nearest_costs(part, [wholes[n] for n in library])
            store.add({"method": name[w], "part": pt, "library": LIBRARY, "n_wholes": len(library),
                       "seconds": time.perf_counter() - t},
                      {"costs": costs.astype(np.float32), "wholes": np.array(library)})
        log(f"part {k + 1}/{len(parts)} {pt}: {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    raise SystemExit(main())
