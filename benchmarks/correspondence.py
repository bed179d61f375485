"""Correspondence on the TOSCA test pairs: wpot's transport plan against functional maps (paper §4.1.3,
Table 5, Fig. 6).

For every pair (X, Y) of ``tosca_isometric_5k/test_pairs.txt`` (284 pairs) it computes, for each vertex of X,
a vertex of Y with

* **wpot**: `wpot.comparison.Comparer` (WKS, balanced transport by default; ``--signature ldsift``,
  ``--transport partial``). Both meshes are subsampled to ``--max-vertices`` points by farthest-point
  sampling; signatures are computed on the full meshes, and the correspondence of every vertex of X is that
  of its nearest sample (`Comparer.compare`). One WKS energy grid is fitted to all 76 shapes (§3.2).
* **wpot-zoomout** (``--methods wpot-zoomout``): the same map refined by `wpot.zoomout` (spectral upsampling,
  k = 10 to 200 in steps of 5, the full meshes' Laplace-Beltrami eigenpairs that WKS computed), with its
  defaults: ``orient=True`` (three candidates, the given map and the maps of two orientation-aware functional
  maps fitted from WKS, refined to k = 60 and ranked by the functional-map energy, the chosen one mended through
  the shape's symmetry where it is mirrored on a part, and the regions its seams cut off mapped again from the
  rest; `wpot.maps.zoomout`) and
  ``samples=2000`` (rounds before the last on farthest-point samples). Its time per pair is the transport and
  the refinement (``info.zoomout_seconds`` the refinement alone).
* **fmaps** (the peer a user would pick instead): pyfmaps (pyFM) 1.3.1 on the full meshes, with the settings
  of its README quickstart: area-normalized, centred meshes, 200 Laplace-Beltrami eigenpairs, 100 WKS
  descriptors (every second one kept), a 30 x 30 functional map fitted with w_descr = 1, w_lap = 0.1,
  w_dcomm = 1, w_orient = 1 (the orientation term keeps left from right), then ZoomOut for 16 iterations of
  step 5 (to 110 x 110), and the point-to-point map read off it.

Both are evaluated against the ground truth (``corres/<name>.vts``, 5,000 template points) with
`wpot.evaluate`: geodesic errors on Y by the heat method (potpourri3d), normalized

* by sqrt(area(Y)) (the paper's ε, curve and AUC over [0, 0.25]), and
* as in the official SHREC'19 code: by the largest geodesic distance between a true and a predicted point of
  the pair (curve and AUC over [0, 0.5]);

the AUC is the mean of the cumulative curve over that range, averaged over pairs (each pair weighs the
same). Also reported: the flip-aware AUC (each point scored against the truth or its mirror, ``.sym.vts``,
whichever is nearer), the fraction of points that are symmetric flips and of pairs that are mostly flipped
(`wpot.evaluate.symmetric_flip`), mean / median error, and the time per pair. Per-shape set-up (spectra and
signatures for wpot, which are cached on disk under ``$WPOT_CACHE_DIR``; the spectrum for fmaps) is timed
separately and left out of the time per pair.

Needs the ``bench`` extra for the peer (``pip install -e ".[bench]"``: pyfmaps 1.3.1 and its dependencies).

Results go to ``--out`` (outside the repository) as they are computed, so an interrupted run resumes:
``pairs.jsonl`` (one line per method and pair), ``maps/<method>/<X>__<Y>.npz`` (the predicted vertex and raw
geodesic error of every template point), ``shapes.jsonl`` (set-up times), then ``results.md`` and
``correspondence.png`` (the mean cumulative curves, both normalizations).

Usage (2 busy CPU cores; about 10-15 s per pair for both methods at --max-vertices 500):

    OPENBLAS_NUM_THREADS=1 WPOT_CACHE_DIR=/work/runs/cache \\
        python benchmarks/correspondence.py --out /work/runs/corr --max-vertices 500
    python benchmarks/correspondence.py --out /work/runs/corr --max-vertices 1000 --limit 40 --methods wpot
    python benchmarks/correspondence.py --out /work/runs/corr --report-only            # the --methods at these settings
    python benchmarks/correspondence.py --out /work/runs/corr --report-only --report-all  # every stored method

The run log names the ``wpot`` code it imported (`code_version`). In a working tree others are editing, run
it against a frozen copy (``git archive <commit> | tar -x -C /tmp/snap`` and ``PYTHONPATH=/tmp/snap``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from collections import Counter, OrderedDict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root, when run as a script
from benchmarks.jsonl_store import JsonlStore, results_folder  # noqa: E402

#: pyfmaps settings (its README quickstart), recorded with every result
FMAPS_SETTINGS = {
    "k_process": 200, "n_descr": 100, "subsample_step": 2, "K": 30, "w_descr": 1.0, "w_lap": 0.1,
    "w_dcomm": 1.0, "w_orient": 1.0, "zoomout_nit": 16, "zoomout_step": 5,
}
FMAPS_TAG = "fmaps-wks-zoomout"
#: the store's tag of wpot + ZoomOut is wpot's tag and this (orient=True: three candidates ranked by the
#: functional-map energy at k = 60, two that agree outvoting a third, the chosen one mended where mirrored on a
#: part, the regions its seams cut off mapped again from the rest, refined on to k = 200; sampled rounds, the
#: candidates compared on 1,000 samples)
ZOOMOUT_SUFFIX = "+zoomout-choose60-mend-sampled-vote-c1000-seams-edges"
#: the same without orienting (``orient=False``): plain ZoomOut of wpot's map, for the cost of orienting
PLAIN_SUFFIX = "+zoomout-plain"
#: the datasets the benchmark knows: folder under ``--data``
DATASETS = {"tosca": "tosca_isometric_5k", "faust": "faust_5k"}
NORMS = ("sqrt_area", "shrec19")


def _data_root() -> Path:
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def wpot_tag(signature: str, transport: str, max_vertices: int | None, scale_invariant: bool = False,
             pooling: str = "none") -> str:
    """The store's name for a wpot setting; ``-areanorm`` marks WKS on area-normalized meshes, ``-cell`` cell
    pooling."""
    tag = f"wpot-{signature}-{transport}-{max_vertices if max_vertices else 'full'}"
    tag += "-areanorm" if scale_invariant and signature == "wks" else ""
    return tag + ("-cell" if pooling == "cell" and max_vertices else "")


def select_pairs(pairs: list[tuple[str, str]], limit: int | None) -> list[tuple[str, str]]:
    """``limit`` pairs evenly spaced over the list (so every class is represented), then grouped by target
    so that each target's geodesic distances are computed once. The targets of the classes are interleaved
    (every class advances at the same rate), so a run stopped part-way has covered every class."""
    from wpot.datasets import class_label

    if limit is not None and limit < len(pairs):
        idx = np.unique(np.linspace(0, len(pairs) - 1, limit).round().astype(int))
        pairs = [pairs[i] for i in idx]
    by_class: dict[str, list[str]] = {}
    for t in sorted({y for _, y in pairs}):
        by_class.setdefault(class_label(t), []).append(t)
    rank = {t: ((k + 0.5) / len(ts), c) for c, ts in by_class.items() for k, t in enumerate(ts)}
    return sorted(pairs, key=lambda p: (rank[p[1]], p[1], p[0]))


# ----------------------------------------------------------------------------- the two matchers
class WpotMatcher:
    """wpot's correspondence (argmax of each plan row, §4.1.3) through one caching `Comparer`."""

    def __init__(self, meshes: dict, *, signature: str, transport: str, max_vertices: int | None, n_eigen: int,
                 n_energies: int, scale_invariant: bool, device: str, log, pooling: str = "none") -> None:
        from wpot.comparison import Comparer

        self.tag = wpot_tag(signature, transport, max_vertices, scale_invariant, pooling)
        self.meshes = meshes
        self.comparer = Comparer(signature=signature, transport=transport, max_vertices=max_vertices,
                                 n_eigen=n_eigen, n_energies=n_energies, scale_invariant=scale_invariant,
                                 device=device, pooling=pooling)
        self.setup_seconds: dict[str, float] = {}
        #: ((x, y), match(x, y)) of the last pair matched, for `match_cached`
        self.last: tuple[tuple[str, str], tuple[np.ndarray, float, dict]] | None = None
        if signature == "wks":
            t0 = time.perf_counter()
            self.comparer.fit_energies([meshes[n] for n in sorted(meshes)])
            log(f"{self.tag}: WKS energy grid fitted to {len(meshes)} shapes in {time.perf_counter() - t0:.0f} s")

    def settings(self) -> dict:
        return self.comparer.params()

    def _prepare(self, name: str) -> None:
        if name not in self.setup_seconds:
            t0 = time.perf_counter()
            self.comparer.signatures(self.meshes[name])
            self.comparer.subsample(self.meshes[name])
            self.setup_seconds[name] = time.perf_counter() - t0

    def match(self, x: str, y: str) -> tuple[np.ndarray, float, dict]:
        self._prepare(x)
        self._prepare(y)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0 = time.perf_counter()
            comp = self.comparer.compare(self.meshes[x], self.meshes[y])
            dt = time.perf_counter() - t0
        info = {"converged": bool(comp.result.converged), "distance": float(comp.distance),
                "n_warnings": len(caught)}
        self.last = ((x, y), (np.asarray(comp.correspondence, dtype=np.int64), dt, info))
        return self.last[1]

    def match_cached(self, x: str, y: str) -> tuple[np.ndarray, float, dict]:
        """`match`, or its result when the last pair matched was (x, y)."""
        return self.last[1] if self.last is not None and self.last[0] == (x, y) else self.match(x, y)


class ZoomOutMatcher:
    """wpot's correspondence refined by `wpot.zoomout` (defaults: k = 10, 15, ..., 200), on the full meshes; its
    time per pair is wpot's plus the refinement's."""

    def __init__(self, base: WpotMatcher, *, orient: bool = True) -> None:
        from wpot.maps.zoomout import ZOOMOUT_K_END, ZOOMOUT_SAMPLES

        self.base = base
        self.tag = base.tag + (ZOOMOUT_SUFFIX if orient else PLAIN_SUFFIX)
        self.setup_seconds: dict[str, float] = {}
        self.options = {"k_start": 10, "k_end": ZOOMOUT_K_END, "step": 5, "orient": orient,
                        "samples": ZOOMOUT_SAMPLES}


    def settings(self) -> dict:
        return {**self.base.settings(), "zoomout": self.options}

    def match(self, x: str, y: str) -> tuple[np.ndarray, float, dict]:
        from wpot.maps.zoomout import zoomout

        pred, dt, info = self.base.match_cached(x, y)
        t0 = time.perf_counter()
        res = zoomout(self.base.meshes[x], self.base.meshes[y], pred, **self.options)
        dz = time.perf_counter() - t0
        return res.map, dt + dz, {**info, "zoomout_seconds": dz, "orientation_confidence": res.orientation_confidence,
                                  "candidate": res.candidate, "energies": res.energies, "mended": res.mended,
                                  "reanchored": res.reanchored}


class FmapsMatcher:
    """pyfmaps: WKS functional map plus ZoomOut (`FMAPS_SETTINGS`), on the full meshes."""

    tag = FMAPS_TAG

    def __init__(self, meshes: dict, *, max_cached: int = 80) -> None:
        self.meshes = meshes
        self._processed: OrderedDict = OrderedDict()
        self.max_cached = max_cached
        self.setup_seconds: dict[str, float] = {}

    def settings(self) -> dict:
        import importlib.metadata

        return {"pyfmaps": importlib.metadata.version("pyfmaps"), **FMAPS_SETTINGS}

    def _trimesh(self, name: str):
        from pyFM.mesh import TriMesh

        tm = self._processed.get(name)
        if tm is None:
            m = self.meshes[name]
            t0 = time.perf_counter()
            tm = TriMesh(m.vertices, m.faces, area_normalize=True, center=True).process(k=FMAPS_SETTINGS["k_process"])
            self.setup_seconds.setdefault(name, time.perf_counter() - t0)
            self._processed[name] = tm
            while len(self._processed) > self.max_cached:
                self._processed.popitem(last=False)
        self._processed.move_to_end(name)
        return tm

    def match(self, x: str, y: str) -> tuple[np.ndarray, float, dict]:
        from pyFM.functional import FunctionalMapping

        s = FMAPS_SETTINGS
        ty, tx = self._trimesh(y), self._trimesh(x)
        t0 = time.perf_counter()
        # pyFM's p2p_21 maps mesh2 -> mesh1: mesh1 = Y, mesh2 = X gives a vertex of Y for every vertex of X
        model = FunctionalMapping(ty, tx)
        model.preprocess(n_descr=s["n_descr"], descr_type="WKS", subsample_step=s["subsample_step"],
                         k_process=s["k_process"])
        model.fit(K=s["K"], w_descr=s["w_descr"], w_lap=s["w_lap"], w_dcomm=s["w_dcomm"], w_orient=s["w_orient"])
        fm = model.zoomout_refine(nit=s["zoomout_nit"], step=s["zoomout_step"])
        p2p = model.get_p2p(fm)
        dt = time.perf_counter() - t0
        return np.asarray(p2p, dtype=np.int64), dt, {}


# ----------------------------------------------------------------------------- evaluation and storage
def evaluate_pair(geo, pred_all: np.ndarray, src: np.ndarray, dst: np.ndarray, sym: np.ndarray) -> tuple[dict, dict]:
    """Scores of one map (``pred_all``: (N_X,) vertex of Y per vertex of X) at the template points."""
    from wpot.evaluate import correspondence_error, symmetric_flip

    pred = pred_all[src]
    rec: dict = {}
    raw = None
    for norm in NORMS:
        e = correspondence_error(geo, pred, dst, normalization=norm, symmetric_truth=sym)
        raw = e.raw
        rec[norm] = {"scale": e.scale, "max_threshold": e.max_threshold, "auc": e.auc,
                     "flip_aware_auc": e.flip_aware_auc, "mean": e.mean_error, "median": float(np.median(e.errors))}
        rec["n_cross_component"] = e.n_cross_component
    f = symmetric_flip(geo, pred, dst, sym)
    rec["flip"] = {"fraction": f.fraction, "map_flipped": f.map_flipped, "n_lateral": f.n_lateral}
    return rec, {"predicted": pred.astype(np.int32), "raw": raw.astype(np.float32)}


class Store(JsonlStore):
    """Append-only results: ``pairs.jsonl`` plus one npz per (method, pair) (`jsonl_store.JsonlStore`)."""

    def __init__(self, out: Path) -> None:
        super().__init__(out, keys=("source", "target"), folder="maps")


# ----------------------------------------------------------------------------- report
def _curves(store: Store, recs: list[dict], norm: str, tmax: float, n: int = 501):
    from wpot.evaluate import cumulative_curve, curve_auc

    thr = np.linspace(0.0, tmax, n)
    curves, aucs = [], []
    for r in recs:
        raw = np.load(store.npz_path(r["method"], r["source"], r["target"]), allow_pickle=False)["raw"].astype(np.float64)
        e = raw / r[norm]["scale"]
        curves.append(cumulative_curve(e, thr))
        aucs.append(curve_auc(e, tmax))
    return thr, np.mean(curves, axis=0), np.array(aucs)


def report(store: Store, out: Path, tmax: dict, log, keep: set | None = None, tags: set | None = None,
           dataset: str = "tosca") -> None:
    """Table and figure over the pairs every method has finished (within ``keep`` when given), for the
    method tags in ``tags`` (all stored methods when None)."""
    by_method: dict[str, dict] = {}
    for r in store.records:
        if keep is not None and (r["source"], r["target"]) not in keep:
            continue
        if tags is not None and r["method"] not in tags:
            continue
        by_method.setdefault(r["method"], {})[(r["source"], r["target"])] = r
    if not by_method:
        log("no results yet")
        return
    methods = sorted(by_method, key=lambda m: (m != FMAPS_TAG, m))
    common = set.intersection(*(set(v) for v in by_method.values()))
    lines = [f"# Correspondence on {DATASETS[dataset]} test pairs ({len(common)} pairs common to all methods)\n",
             f"AUC = mean over pairs of the mean cumulative curve over [0, {tmax['sqrt_area']}] of d/sqrt(area(Y)) "
             f"(paper) and over [0, {tmax['shrec19']}] of d/max geodesic (SHREC'19 code). Geodesics: heat method. "
             "Errors at the 5,000 template points of each pair. Time: seconds per pair, per-shape set-up excluded "
             "(median, and mean); the machine was shared, so times are noisy.\n",
             "| method | pairs | AUC √area [0,%g] | flip-aware | AUC SHREC'19 [0,%g] | flip-aware | mean err √area | "
             "median err √area | mean err SHREC'19 | flipped points | flipped pairs | s/pair median (mean) | "
             "not converged |" % (tmax["sqrt_area"], tmax["shrec19"]),
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    summary = {}
    curves = {norm: {} for norm in NORMS}
    for m in methods:
        recs = [by_method[m][k] for k in sorted(common)]
        if not recs:
            continue
        row = {"n": len(recs)}
        for norm in NORMS:
            thr, curve, aucs = _curves(store, recs, norm, tmax[norm])
            row[f"auc_{norm}"] = float(aucs.mean())
            row[f"auc_{norm}_std"] = float(aucs.std())
            if tmax[norm] == recs[0][norm]["max_threshold"]:
                row[f"flip_auc_{norm}"] = float(np.mean([r[norm]["flip_aware_auc"] for r in recs]))
            else:
                row[f"flip_auc_{norm}"] = float("nan")  # stored flip-aware AUCs are at the default range
            row[f"mean_{norm}"] = float(np.mean([r[norm]["mean"] for r in recs]))
            row[f"median_{norm}"] = float(np.median([r[norm]["median"] for r in recs]))
            curves[norm][m] = (thr, curve, row[f"auc_{norm}"])
        row["flip_points"] = float(np.nanmean([r["flip"]["fraction"] for r in recs]))
        row["flip_pairs"] = float(np.mean([r["flip"]["map_flipped"] for r in recs]))
        t = np.array([r["seconds"] for r in recs])
        row["sec_median"], row["sec_mean"] = float(np.median(t)), float(t.mean())
        row["not_converged"] = int(sum(not r.get("info", {}).get("converged", True) for r in recs))
        summary[m] = row
        lines.append(
            f"| {m} | {row['n']} | {row['auc_sqrt_area']:.3f} ± {row['auc_sqrt_area_std']:.3f} | "
            f"{row['flip_auc_sqrt_area']:.3f} | {row['auc_shrec19']:.3f} ± {row['auc_shrec19_std']:.3f} | "
            f"{row['flip_auc_shrec19']:.3f} | {row['mean_sqrt_area']:.4f} | {row['median_sqrt_area']:.4f} | "
            f"{row['mean_shrec19']:.4f} | {row['flip_points']:.1%} | {row['flip_pairs']:.1%} | "
            f"{row['sec_median']:.1f} ({row['sec_mean']:.1f}) | {row['not_converged']} |")
    lines.append("\n± is the spread (std) of the per-pair AUC over pairs, not the error of the mean.\n")
    lines += orientation_section(by_method, common, out, DATASETS[dataset])
    # per class (sqrt_area AUC)
    class_label = group_of(dataset)
    classes = sorted({class_label(y) for _, y in common})
    lines.append("\n## AUC √area [0,%g] per class\n" % tmax["sqrt_area"])
    lines.append("| class | pairs | " + " | ".join(methods) + " |")
    lines.append("|---|---|" + "---|" * len(methods))
    for c in classes:
        keys = sorted(k for k in common if class_label(k[1]) == c)
        cells = []
        for m in methods:
            _, _, aucs = _curves(store, [by_method[m][k] for k in keys], "sqrt_area", tmax["sqrt_area"])
            cells.append(f"{aucs.mean():.3f}")
        lines.append(f"| {c} | {len(keys)} | " + " | ".join(cells) + " |")
    setup: dict[str, list] = {}
    spath = out / "shapes.jsonl"
    if spath.is_file():
        first: dict[tuple[str, str], float] = {}  # a resumed run times a shape again; keep the first
        for line in spath.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                first.setdefault((r["method"], r["shape"]), r["seconds"])
        for (m, _), sec in first.items():
            setup.setdefault(m, []).append(sec)
    if setup:
        lines.append("\n## Per-shape set-up (not in the time per pair; wpot reads signatures from $WPOT_CACHE_DIR "
                     "when they are there)\n")
        lines.append("| method | shapes | mean s | median s |\n|---|---|---|---|")
        for m, v in sorted(setup.items()):
            lines.append(f"| {m} | {len(v)} | {np.mean(v):.1f} | {np.median(v):.1f} |")
    lines.append(
        "\nFor context, the paper's Table 5 gives AUCs on SHREC'19 only (not TOSCA), all four test sets together: "
        "WKS balanced 0.54, WKS partial 0.06, LD-SIFT balanced 0.25, LD-SIFT partial 0.05, with full meshes of "
        "about 10,000 vertices (normalization ε = d/√area; threshold range not stated).\n")
    md = "\n".join(lines) + "\n"
    (out / "results.md").write_text(md)
    (out / "summary.json").write_text(json.dumps({"pairs": len(common), "tmax": tmax, "methods": summary}, indent=1))
    log(md)
    figure(curves, out / "correspondence.png", len(common), DATASETS[dataset])
    log(f"figure: {out / 'correspondence.png'}")


def group_of(dataset: str):
    """A shape's group in the per-class table: TOSCA's class, FAUST's person (number div 10)."""
    from wpot.datasets import class_label

    if dataset == "faust":
        return lambda name: f"person {int(name.rsplit('_', 1)[-1]) // 10}"
    return class_label


def orientation_section(by_method: dict, common: set, out: Path, dataset: str) -> list[str]:
    """The left/right decision of `wpot.zoomout` (its stored energies and orientation confidence) against the
    ground truth: how often a pair is mirrored overall and above the confidence threshold, the decision signal's
    two distributions (energy of the maps on the true side, of those on the mirror side; one of each per pair: the
    chosen map and its mirror image) drawn to ``orientation.png``, and the time against plain ZoomOut."""
    from wpot.maps.zoomout import ORIENTATION_DOUBT

    lines = []
    for m in sorted(by_method):
        if not m.endswith(ZOOMOUT_SUFFIX):
            continue
        recs = [by_method[m][k] for k in sorted(common)]
        recs = [r for r in recs if "energies" in r.get("info", {})]
        if not recs:
            continue
        conf = np.array([np.nan if r["info"]["orientation_confidence"] is None else r["info"]["orientation_confidence"]
                         for r in recs], dtype=float)
        flipped = np.array([bool(r["flip"]["map_flipped"]) for r in recs])
        true_e, mirror_e = [], []
        for r, f in zip(recs, flipped):
            e = r["info"]["energies"]
            chosen, mirror = e[r["info"]["candidate"]], e[r["info"]["candidate"] + "_mirror"]
            (mirror_e if f else true_e).append(chosen)
            (true_e if f else mirror_e).append(mirror)
        trusted = conf >= ORIENTATION_DOUBT
        top90 = conf >= np.nanquantile(conf, 0.1)
        lines += [f"\n## Left and right: {m}\n",
                  "| pairs | mirrored | confidence < %g | mirrored among the rest | mirrored among the top 90 %% of "
                  "confidence | candidates chosen |" % ORIENTATION_DOUBT, "|---|---|---|---|---|---|",
                  f"| {len(recs)} | {flipped.sum()} ({flipped.mean():.1%}) | {(~trusted).sum()} | "
                  f"{flipped[trusted].sum()} of {trusted.sum()} | {flipped[top90].sum()} of {top90.sum()} | "
                  + ", ".join(f"{n} {c}" for n, c in sorted(Counter(r["info"]["candidate"] for r in recs).items()))
                  + "".join(f"; {key} {sum(bool(r['info'][key]) for r in recs)}" for key in ("mended", "reanchored")
                            if all(key in r["info"] for r in recs)) + " |"]
        plain = by_method.get(m[:-len(ZOOMOUT_SUFFIX)] + PLAIN_SUFFIX, {})
        timed = [r for r in recs if (r["source"], r["target"]) in plain]
        ratio = [r["info"]["zoomout_seconds"] / plain[(r["source"], r["target"])]["info"]["zoomout_seconds"]
                 for r in timed]
        repaired = [x for x, r in zip(ratio, timed) if r["info"].get("reanchored")]
        if ratio:
            lines.append(f"\nTime of the oriented refinement over plain ZoomOut (orient=False) on the same pair (each "
                         "as stored: measured in the same run only when both were; the oriented time of a shape's "
                         "first pair in a process holds its one-off set-up, its left/right symmetry and functional-map "
                         "terms, unless $WPOT_CACHE_DIR had them; benchmarks/correspondence_speed.py times both side by "
                         "side): "
                         f"median {np.median(ratio):.2f}x, 90th percentile {np.quantile(ratio, 0.9):.2f}x, "
                         f"largest {max(ratio):.2f}x ({len(ratio)} pairs)"
                         + (f"; on the {len(repaired)} re-anchored pairs {min(repaired):.2f}x to {max(repaired):.2f}x "
                            f"(median {np.median(repaired):.2f}x)" if repaired else "") + ".\n")
        lines.append(f"Decision signal: `orientation.png` ({len(true_e)} true-side and {len(mirror_e)} mirror-side "
                     f"energies; largest true-side {max(true_e):.2f}, smallest mirror-side {min(mirror_e):.2f}).\n")
        orientation_figure(np.array(true_e), np.array(mirror_e), out / "orientation.png", dataset, len(recs))
    return lines


def orientation_figure(true_e: np.ndarray, mirror_e: np.ndarray, path: Path, dataset: str, n_pairs: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    bins = np.geomspace(max(min(true_e.min(), mirror_e.min()), 1e-3), max(true_e.max(), mirror_e.max()), 40)
    ax.hist(true_e, bins=bins, alpha=0.6, label="maps on the true side")
    ax.hist(mirror_e, bins=bins, alpha=0.6, label="maps on the mirror side")
    ax.set_xscale("log")
    ax.set_xlabel("functional-map energy at k = 30 (descriptors, commutativity, orientation)")
    ax.set_ylabel("maps")
    ax.set_title(f"{dataset}: the left/right decision signal ({n_pairs} pairs)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def figure(curves: dict, path: Path, n_pairs: int, dataset: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from wpot.plot import plot_cumulative_errors

    fig, axes = plt.subplots(1, 2, figsize=(11.5, 4.3))
    labels = {"sqrt_area": "geodesic error / √area(Y)  (paper)", "shrec19": "geodesic error / max geodesic  (SHREC'19 code)"}
    for ax, norm in zip(axes, NORMS):
        cs = {f"{m} (AUC {a:.3f})": (t, c) for m, (t, c, a) in curves[norm].items()}
        plot_cumulative_errors(cs, ax=ax, xlabel=labels[norm], title=f"{dataset} test pairs ({n_pairs})")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def code_version() -> str:
    """Where the imported ``wpot`` lives and, when it is a git checkout, its commit and whether the tracked
    files differ from it (timings and convergence depend on the solver code actually imported)."""
    import subprocess

    import wpot

    root = Path(wpot.__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "wpot"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        head, dirty = "", ""
    if not head:
        return f"{root} (not a git checkout)"
    return f"{root} at {head}" + (" with uncommitted changes to wpot/" if dirty else "")


# ----------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=_data_root(),
                    help="the folder holding the datasets (default: ../shared/data beside the repository)")
    ap.add_argument("--dataset", nargs="+", default=["tosca"], choices=sorted(DATASETS),
                    help="tosca: tosca_isometric_5k's 284 test pairs; faust: faust_5k's 300 (one table each)")
    ap.add_argument("--out", type=Path, required=True,
                    help="results folder (outside the repository); one subfolder per dataset")
    ap.add_argument("--methods", nargs="+", default=["wpot", "fmaps"], choices=["wpot", "wpot-zoomout", "wpot-zoomout-plain", "fmaps"],
                    help="wpot-zoomout: wpot's map refined by wpot.zoomout; wpot-zoomout-plain: the same with "
                    "orient=False (default: wpot fmaps)")
    ap.add_argument("--limit", type=int, default=None,
                    help="only K pairs, evenly spaced over test_pairs.txt (the report then covers those K only)")
    ap.add_argument("--shard", default=None, metavar="I/N",
                    help="only every N-th pair from the I-th (0-based), so that N processes share a run's pairs "
                    "(each appends whole lines to the same results)")
    ap.add_argument("--max-vertices", type=int, default=500, help="wpot's farthest-point sample size (0: none)")
    ap.add_argument("--signature", default="wks", choices=["wks", "ldsift"])
    ap.add_argument("--transport", default="balanced", choices=["balanced", "partial"])
    ap.add_argument("--pooling", default="none", choices=["none", "cell"],
                    help="wpot: each sample keeps its own signature (none) or its cell's mean and size (cell)")
    ap.add_argument("--n-eigen", type=int, default=500, help="WKS eigenpairs (paper: 500)")
    ap.add_argument("--n-energies", type=int, default=200, help="WKS energies (paper: 200)")
    ap.add_argument("--scale-invariant", action="store_true",
                    help="WKS on area-normalized meshes (wpot's default is the meshes' own size, as in the paper)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sqrt-area-max", type=float, default=None, help="AUC range for d/sqrt(area) (default 0.25)")
    ap.add_argument("--shrec-max", type=float, default=None, help="AUC range for the SHREC'19 normalization (default 0.5)")
    ap.add_argument("--report-only", action="store_true", help="only rebuild the table and figure from --out")
    ap.add_argument("--report-all", action="store_true",
                    help="report every method stored in --out (default: the --methods at these settings only)")
    a = ap.parse_args(argv)

    from wpot.evaluate import DEFAULT_MAX_THRESHOLD

    if a.shard:
        i, _, n = a.shard.partition("/")
        if not (i.isdigit() and n.isdigit() and int(i) < int(n)):
            ap.error(f"--shard must be I/N with 0 <= I < N, got {a.shard!r}")
    tmax = {"sqrt_area": a.sqrt_area_max or DEFAULT_MAX_THRESHOLD["sqrt_area"],
            "shrec19": a.shrec_max or DEFAULT_MAX_THRESHOLD["shrec19"]}
    for name in a.dataset:
        a.tosca = a.data / DATASETS[name]
        if not (a.tosca / "test_pairs.txt").is_file():
            ap.error(f"--dataset {name}: {a.tosca} has no test_pairs.txt (set --data)")
        out, log = results_folder(a.out / name)
        store = Store(out)
        if not a.report_only:
            run(a, out, store, log)
        keep = None
        if a.limit is not None:  # report the selected pairs only
            from wpot.datasets import read_test_pairs

            keep = set(select_pairs(read_test_pairs(a.tosca / "test_pairs.txt"), a.limit))
        tags = None if a.report_all else {method_tags(a)[m] for m in a.methods}
        report(store, out, tmax, log, keep, tags, dataset=name)
    return 0


def method_tags(a) -> dict[str, str]:
    """The store's method tag for each ``--methods`` name at these settings."""
    w = wpot_tag(a.signature, a.transport, a.max_vertices or None, a.scale_invariant, a.pooling)
    return {"wpot": w, "wpot-zoomout": w + ZOOMOUT_SUFFIX, "wpot-zoomout-plain": w + PLAIN_SUFFIX, "fmaps": FMAPS_TAG}


def run(a, out: Path, store: Store, log) -> None:
    from wpot.datasets import read_test_pairs, tosca_ground_truth
    from wpot.evaluate import GeodesicDistances
    from wpot.io import load_mesh

    vtx = a.tosca / "vtx_5k"
    pairs = select_pairs(read_test_pairs(a.tosca / "test_pairs.txt"), a.limit)
    maxv = a.max_vertices or None
    tags = method_tags(a)
    if a.shard:
        i, n = (int(v) for v in a.shard.split("/"))
        pairs = pairs[i::n]
    todo = [p for p in pairs if any((tags[m], *p) not in store.done for m in a.methods)]
    log(f"{len(pairs)} pairs selected, {len(todo)} still to do for {[tags[m] for m in a.methods]}; out={out}")
    if not todo:
        return
    t_load = time.perf_counter()
    meshes = {p.stem: load_mesh(p) for p in sorted(vtx.glob("*.off"))}
    log(f"loaded {len(meshes)} meshes in {time.perf_counter() - t_load:.1f} s")
    matchers = {}
    if "fmaps" in a.methods:
        matchers["fmaps"] = FmapsMatcher(meshes)
    if any(m.startswith("wpot") for m in a.methods):
        base = WpotMatcher(meshes, signature=a.signature, transport=a.transport, max_vertices=maxv,
                           n_eigen=a.n_eigen, n_energies=a.n_energies, scale_invariant=a.scale_invariant,
                           device=a.device, log=log, pooling=a.pooling)
        if "wpot" in a.methods:
            matchers["wpot"] = base
        if "wpot-zoomout-plain" in a.methods:
            matchers["wpot-zoomout-plain"] = ZoomOutMatcher(base, orient=False)
        if "wpot-zoomout" in a.methods:
            matchers["wpot-zoomout"] = ZoomOutMatcher(base)
    for k, mt in matchers.items():
        log(f"{mt.tag} settings: {json.dumps(mt.settings())}")
    log(f"wpot code: {code_version()}")
    geo, geo_name = None, None
    t_start = time.perf_counter()
    for i, (x, y) in enumerate(todo):
        src, dst = tosca_ground_truth(vtx, x, y)
        _, sym = tosca_ground_truth(vtx, x, y, symmetric=True)
        if geo_name != y:
            geo, geo_name = GeodesicDistances(meshes[y]), y
        msg = []
        for key, mt in matchers.items():
            if (mt.tag, x, y) in store.done:
                continue
            before = dict(mt.setup_seconds)
            pred, dt, info = mt.match(x, y)
            for n, s in mt.setup_seconds.items():
                if n not in before:
                    with open(out / "shapes.jsonl", "a") as fh:
                        fh.write(json.dumps({"method": mt.tag, "shape": n, "seconds": s}) + "\n")
            t_eval = time.perf_counter()
            rec, arrays = evaluate_pair(geo, pred, src, dst, sym)
            rec.update(method=mt.tag, source=x, target=y, seconds=dt, info=info,
                       eval_seconds=time.perf_counter() - t_eval)
            store.add(rec, arrays)
            msg.append(f"{mt.tag}: AUC {rec['sqrt_area']['auc']:.3f}/{rec['shrec19']['auc']:.3f} "
                       f"flip {rec['flip']['fraction']:.2f} {dt:.1f}s")
        el = time.perf_counter() - t_start
        eta = el / (i + 1) * (len(todo) - i - 1)
        log(f"[{i + 1}/{len(todo)}] {x} -> {y}: " + "; ".join(msg) + f"  (elapsed {el / 60:.1f} min, ETA {eta / 60:.1f} min)")


if __name__ == "__main__":
    sys.exit(main())
