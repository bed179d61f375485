"""Class retrieval of parts from a library of whole shapes: issue 23's "a part retrieves its class".

**Parts**: those of a `partial_poses.py` run (``--parts``: its ``--out`` folder, ``parts.jsonl`` and
``parts/<part>.npz``): heads, limbs, plane cuts and holes cut from TOSCA 5k poses.

**Library**: every shape of ``tosca_isometric_5k`` (76 shapes, eight classes) except the part's own source pose,
which holds the part itself. The part's class has other poses there (2 to 19 of them), and so has every other
class: what a user faces who looks a part up in a dataset of whole shapes.

**Distance**: `Comparer.nearest_signature_distance(part, whole)` (the mean, over the part's vertices, of the cost
to the nearest signature of the whole), LD-SIFT with each ``--weights`` w of its thickness column
(``ldsift_thickness``); w = 0, the paper's LD-SIFT, is the peer in the same run. One `Comparer` and its
``with_options`` copies share the signature cache, where LD-SIFT is kept as its descriptor and its thickness
apart, so every weight reuses one descriptor a shape.

**Reported** per weight, over the parts, each part weighing the same: top-1 (the nearest whole is of the
part's class), by kind and by size (parts >= 20 % / < 20 % of the area); the mean rank of the nearest whole of
the part's class (1 = top-1); and each failure with the class it was taken for. `partial_poses.py` reports a
stricter, per-pair score: every same-class pose it drew nearer than one drawn pose of each other class.

Results go to ``--out`` (outside the repository) as they are computed, one line per (weight, part, whole) in
``pairs.jsonl``, so a stopped run resumes; then ``results.md``.

Usage (one busy CPU core: about 20 minutes for 112 parts, 75 wholes and three weights):

    OPENBLAS_NUM_THREADS=1 WPOT_CACHE_DIR=/work/runs/cache python benchmarks/part_retrieval.py \\
        --parts /work/runs/partial_poses --out /work/runs/part_retrieval --weights 0,1,2
    python benchmarks/part_retrieval.py --parts /work/runs/partial_poses --out /work/runs/part_retrieval --report-only
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling modules
from jsonl_store import JsonlStore, results_folder  # noqa: E402
from partial_poses import KINDS, LARGE, _tosca, _vtx, class_members, read_parts  # noqa: E402


def method(w: float, slab: float | None = None) -> str:
    return f"nn-ldsift-w{w:g}" + ("" if slab is None else f"-slab{slab:g}")


def score(recs: list[dict], parts: dict[str, dict], w: float, slab: float | None = None) -> dict:
    """Top-1 and rank of the first whole of the part's class (None when the library has none), per part, for
    weight ``w``; parts not compared with every whole yet are left out."""
    from wpot.datasets import class_label

    by_part: dict[str, list[tuple[float, str]]] = defaultdict(list)
    for r in recs:
        if r["method"] == method(w, slab):
            by_part[r["part"]].append((r["distance"], r["whole"]))
    n_wholes = max((len(v) for v in by_part.values()), default=0)
    rows = {}
    for pt, ds in by_part.items():
        if len(ds) < n_wholes:
            continue  # not finished
        ds.sort()
        cls = parts[pt]["class"]
        labels = [class_label(name) for _, name in ds]
        rank = labels.index(cls) + 1 if cls in labels else None  # None: no other pose of its class
        rows[pt] = {"top1": labels[0] == cls, "rank": rank, "taken_for": ds[0][1],
                    "kind": parts[pt]["kind"], "large": parts[pt]["fraction"] >= LARGE}
    return rows


def report(store: JsonlStore, parts: dict[str, dict], weights: list[float], slab: float | None, out: Path,
           log) -> None:
    lines = [f"LD-SIFT slab: {'the default' if slab is None else f'{slab:g}'}", "",
             "| w | top-1, all parts | parts >= 20 % | < 20 % | " + " | ".join(KINDS) + " | mean rank of the class |",
             "|---|---|---|---|" + "---|" * len(KINDS) + "---|"]
    fails = []
    for w in weights:
        rows = score(store.records, parts, w, slab)
        if not rows:
            continue

        def pct(sel) -> str:
            v = [r["top1"] for r in rows.values() if sel(r)]
            return f"{np.mean(v):.1%} ({len(v)})" if v else "–"

        lines.append(f"| {w:g} | {pct(lambda r: True)} | {pct(lambda r: r['large'])} | "
                     f"{pct(lambda r: not r['large'])} | "
                     + " | ".join(pct(lambda r, k=k: r["kind"] == k) for k in KINDS)
                     + f" | {np.mean([r['rank'] for r in rows.values() if r['rank']]):.2f} |")
        fails.append(f"w = {w:g}: " + (", ".join(f"{pt} ({parts[pt]['fraction']:.0%}) -> {r['taken_for']}"
                                                  for pt, r in sorted(rows.items()) if not r["top1"]) or "none"))
    text = "\n".join(lines + ["", "failures (part, its share of the area, the nearest whole):"] + fails)
    (out / "results.md").write_text(text + "\n")
    log(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", type=Path, required=True, help="a partial_poses.py --out folder (its parts)")
    ap.add_argument("--out", type=Path, required=True, help="results folder, outside the repository")
    ap.add_argument("--tosca", type=Path, default=_tosca(Path("../shared/data/tosca_isometric_5k")),
                    help="tosca_isometric_5k (default: ../shared/data/tosca_isometric_5k)")
    ap.add_argument("--weights", default="0,1,2", help="LD-SIFT thickness weights w, comma-separated (default 0,1,2)")
    ap.add_argument("--ldsift-slab", type=float, default=None,
                    help="LD-SIFT's depth slab (ldsift_slab; default: LD-SIFT's own), a method of its own in --out")
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
    parts = read_parts(a.parts)
    if not parts:
        raise SystemExit(f"--parts {a.parts}: no parts.jsonl there; run partial_poses.py with --out {a.parts} first")
    if not _vtx(a.tosca).is_dir():
        raise SystemExit(f"--tosca {a.tosca}: not found (tosca_isometric_5k, see ../shared/data/README)")
    out, log = results_folder(a.out)
    store = JsonlStore(out, keys=("part", "whole"), folder="unused")
    if not a.report_only:
        run(a, parts, weights, store, log)
    report(store, parts, weights, a.ldsift_slab, out, log)
    return 0


def run(a, parts: dict[str, dict], weights: list[float], store: JsonlStore, log) -> None:
    import wpot
    from wpot.io import load_mesh
    from wpot.mesh import cut

    members = class_members(a.tosca)
    wholes = [n for names in members.values() for n in names]
    slab = {} if a.ldsift_slab is None else {"ldsift_slab": a.ldsift_slab}
    base = wpot.Comparer(signature="ldsift", device=a.device, **slab)
    comparers = {w: base.with_options(ldsift_thickness=w) for w in weights}
    meshes: dict = {}

    def mesh(name: str):
        if name not in meshes:
            meshes[name] = load_mesh(_vtx(a.tosca) / f"{name}.off", warn=False)
        return meshes[name]

    part_meshes = {pt: cut(mesh(p["source"]), np.load(a.parts / "parts" / f"{pt}.npz")["idx"])[0]
                   for pt, p in parts.items()}
    log(f"{len(parts)} parts, {len(wholes)} wholes, weights {weights}; wpot {wpot.__file__}")
    t0 = time.perf_counter()
    for k, name in enumerate(wholes):  # whole by whole: each whole is loaded and its signatures computed once
        for pt, p in parts.items():
            if name == p["source"]:
                continue
            for w, c in comparers.items():
                if (method(w, a.ldsift_slab), pt, name) in store.done:
                    continue
                t = time.perf_counter()
                d = c.nearest_signature_distance(part_meshes[pt], mesh(name))
                store.add({"method": method(w, a.ldsift_slab), "part": pt, "whole": name, "distance": d,
                           "seconds": time.perf_counter() - t}, None)
        log(f"whole {k + 1}/{len(wholes)} {name}: {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    raise SystemExit(main())
