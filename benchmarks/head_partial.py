"""Calibrate partial transport's mass penalty on the HEAD dataset (paper §4.2, §5.1, Fig. 1 and 7).

Builds HEAD (`wpot.paper.head.build_head_dataset`) into ``--out`` (never into the repository), then compares
heads against full shapes with partial transport (WKS and LD-SIFT) for a sweep of relative mass penalties κ
(`wpot.comparison.solver_mass_penalty`, ``penalty_scale="relative"``) and, for contrast, the paper's
``α = 1/ρ²`` (``penalty_scale="paper", mass_penalty=1``). Both meshes are subsampled to ``--max-vertices``
points by farthest-point sampling (signatures are computed on the full meshes first).

Per (signature, penalty) it reports, averaged over the heads (head → its parent unless said otherwise):

* ``head_mass``: the fraction of the head's transported mass that lands on the true head region of its
  parent (the parent's vertices the head was cut from; ``ref`` is the fraction of the parent's samples in
  that region, which is what balanced transport would give);
* ``f_eff``: the size of the matched region of the parent, as the participation ratio 1/(n Σ m2²) of the
  parent's received masses (the fraction of its samples that effectively receive mass; 1 = balanced,
  ``ref`` = exactly the head region uniformly); ``f_eff_head``: the same for the head's sent masses (1 = all
  of the head is used);
* ``matched``: number of matched pairs G(i, j) > 0.9 m1(i) (of n head samples);
* ``err``: median distance between the predicted and the true parent vertex of each head vertex, over
  √area(parent) (the paper's normalization of §4.1.3; Euclidean, which is close to geodesic at these
  scales on the same pose);
* retrieval: whether the nearest full shape (smallest SU, Eq. 27) of each head has its class (``class``)
  and is its very parent (``parent``).

Writes ``results_<signature>.json``, ``results.md`` and ``head_partial.png`` (how the matched region and the
classification change with the penalty) into ``--out``.

Usage (2 busy CPU cores: ~30 min for the default sweep; ``--confirm K`` then runs all heads against all
full shapes at κ = K; ``--lowres`` builds the paper's own HEAD from TOSCA's low-resolution shapes):

    python benchmarks/head_partial.py --out /tmp/head_partial
    python benchmarks/head_partial.py --out /tmp/head_partial --confirm 0.01 --signatures ldsift
    python benchmarks/head_partial.py --out /tmp/head8 --lowres ../shared/data/tosca_lowres --per-class 6 \
        --confirm 0.01 --signatures ldsift --pooling cell --vertices-per-sample 20
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

DEFAULT_HEADS = ("cat_head0", "cat_head4", "cat_head8", "horse_head0", "horse_head6", "horse_head14")
DEFAULT_KAPPAS = (3.0, 1.0, 0.3, 0.1, 0.03, 0.01, 0.003)


def _tosca(default: Path) -> Path:
    return default if default.is_dir() else Path(__file__).resolve().parents[2] / "shared" / "data" / "tosca_isometric_5k"


def head_region(ds, full: str) -> np.ndarray:
    """Vertices of full shape ``full`` that form its head (the vertices its own head was cut from)."""
    for h, p in ds.parent.items():
        if p == full:
            return ds.parent_map[h]
    raise ValueError(f"{full!r} has no head in the dataset")


def pair_metrics(ds, head: str, full: str, comp) -> dict:
    """Metrics of one head-vs-full comparison (see the module docstring)."""
    mf = ds.mesh(full)
    sub_b = comp.sample_b
    jb = np.arange(mf.n_vertices) if sub_b is None else sub_b.indices
    in_head = np.isin(jb, head_region(ds, full))
    m1 = comp.mass1 / comp.mass1.sum()
    m2 = comp.mass2 / comp.mass2.sum()
    out = {
        "distance": comp.distance,
        "head_mass": float(m2[in_head].sum()),
        "ref": float(in_head.mean()),
        "f_eff": float(1.0 / (len(m2) * np.sum(m2 * m2))),
        "f_eff_head": float(1.0 / (len(m1) * np.sum(m1 * m1))),
        "matched": int(len(comp.matched)),
        "n_head_samples": int(len(m1)),
        "converged": bool(comp.result.converged),
    }
    if ds.parent[head] == full:
        truth = ds.parent_map[head]
        d = np.linalg.norm(mf.vertices[comp.correspondence] - mf.vertices[truth], axis=1) / math.sqrt(mf.area)
        out["err"] = float(np.median(d))
    return out


def run_setting(base, ds, heads, fulls, label: str, log) -> dict:
    """All head × full comparisons with one Comparer; returns metrics per pair and retrieval."""
    pairs = {}
    t0 = time.perf_counter()
    for h in heads:
        for f in fulls:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                comp = base.compare(ds.mesh(h), ds.mesh(f))
            pairs[f"{h}|{f}"] = pair_metrics(ds, h, f, comp)
    d = np.array([[pairs[f"{h}|{f}"]["distance"] for f in fulls] for h in heads])
    species = {n: s for n, s in zip(ds.names, ds.species)}
    nearest = [fulls[int(np.argmin(row))] for row in d]
    ok_class = [species[n] == species[h] for h, n in zip(heads, nearest)]
    ok_parent = [n == ds.parent[h] for h, n in zip(heads, nearest)]
    par = [pairs[f"{h}|{ds.parent[h]}"] for h in heads]
    summary = {
        "setting": label,
        "head_mass": float(np.mean([p["head_mass"] for p in par])),
        "head_mass_min": float(np.min([p["head_mass"] for p in par])),
        "ref": float(np.mean([p["ref"] for p in par])),
        "f_eff": float(np.mean([p["f_eff"] for p in par])),
        "f_eff_head": float(np.mean([p["f_eff_head"] for p in par])),
        "matched": float(np.mean([p["matched"] for p in par])),
        "err": float(np.median([p["err"] for p in par])),
        "class_acc": float(np.mean(ok_class)),
        "parent_acc": float(np.mean(ok_parent)),
        "not_converged": int(sum(not p["converged"] for p in pairs.values())),
        "seconds": time.perf_counter() - t0,
        "nearest": dict(zip(heads, nearest)),
    }
    log(f"  {label:>14}: head_mass {summary['head_mass']:.3f} (min {summary['head_mass_min']:.3f}, ref {summary['ref']:.3f}) "
        f"f_eff {summary['f_eff']:.3f} f_eff_head {summary['f_eff_head']:.3f} matched {summary['matched']:.0f} "
        f"err {summary['err']:.3f} class {summary['class_acc']:.2f} parent {summary['parent_acc']:.2f} "
        f"({summary['seconds']:.0f} s, {summary['not_converged']} not converged)")
    return {"summary": summary, "pairs": pairs, "distances": d.tolist(), "heads": list(heads), "fulls": list(fulls)}


def base_comparer(a, sig: str, ds, names: list[str], out: Path):
    """The partial-transport `Comparer` of a run (its WKS energy grid fitted to ``names``)."""
    from wpot.comparison import Comparer

    base = Comparer(signature=sig, transport="partial", max_vertices=a.max_vertices, device=a.device,
                    n_eigen=a.n_eigen, n_energies=a.n_energies, pooling=a.pooling, vertices_per_sample=a.vertices_per_sample,
                    ldsift_slab=a.ldsift_slab, cache_dir=out / "cache")
    if sig == "wks":
        base.fit_energies([ds.mesh(n) for n in names])
    return base


def paper_kappa(base, ds, heads, fulls) -> float:
    """The relative κ that the paper's α = 1/ρ² amounts to, √(N1 N2)/mean(C), median over the parent pairs."""
    from wpot.comparison import cost_scale
    from wpot.cost import cost_matrix

    ks = []
    for h in heads:
        sa = base.points(ds.mesh(h)).signatures
        sb = base.points(ds.mesh(ds.parent[h])).signatures
        c = cost_matrix(sa, sb, metric=base.stage.metric, device=base.device)
        ks.append(math.sqrt(len(sa) * len(sb)) / cost_scale(c))
    return float(np.median(ks))


def table(results: dict) -> str:
    lines = []
    for sig, rows in results.items():
        lines.append(f"\n### {sig} (partial, heads vs full shapes)\n")
        lines.append("| penalty | κ | head mass on parent's head | min | ref | f_eff parent | f_eff head | matched | err | class | parent |")
        lines.append("|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            s = r["summary"]
            lines.append(
                f"| {s['setting']} | {r['kappa']:.3g} | {s['head_mass']:.3f} | {s['head_mass_min']:.3f} | {s['ref']:.3f} | "
                f"{s['f_eff']:.3f} | {s['f_eff_head']:.3f} | {s['matched']:.0f} | {s['err']:.3f} | "
                f"{s['class_acc']:.2f} | {s['parent_acc']:.2f} |"
            )
    return "\n".join(lines) + "\n"


def figure(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    colours = {"wks": "tab:blue", "ldsift": "tab:red"}
    for sig, rows in results.items():
        rel = sorted((r for r in rows if r["scale"] == "relative"), key=lambda r: r["kappa"])
        pap = [r for r in rows if r["scale"] == "paper"]
        k = [r["kappa"] for r in rel]
        c = colours.get(sig, "k")
        get = lambda key, rs: [r["summary"][key] for r in rs]  # noqa: E731
        axes[0].plot(k, get("head_mass", rel), "o-", c=c, label=f"{sig}")
        axes[0].plot(k, get("ref", rel), ":", c=c, lw=1)
        axes[1].plot(k, get("f_eff", rel), "o-", c=c, label=f"{sig}: parent")
        axes[1].plot(k, get("f_eff_head", rel), "s--", c=c, mfc="none", label=f"{sig}: head")
        axes[1].plot(k, get("ref", rel), ":", c=c, lw=1)
        axes[2].plot(k, get("class_acc", rel), "o-", c=c, label=f"{sig}: class")
        axes[2].plot(k, get("parent_acc", rel), "s--", c=c, mfc="none", label=f"{sig}: parent")
        axes[3].plot(k, get("err", rel), "o-", c=c, label=sig)
        for r in pap:
            kp = r["kappa"]
            axes[0].plot([kp], [r["summary"]["head_mass"]], "*", c=c, ms=12)
            axes[1].plot([kp], [r["summary"]["f_eff"]], "*", c=c, ms=12)
            axes[2].plot([kp], [r["summary"]["class_acc"]], "*", c=c, ms=12)
            axes[2].plot([kp], [r["summary"]["parent_acc"]], "*", c=c, ms=8, mfc="none")
            axes[3].plot([kp], [r["summary"]["err"]], "*", c=c, ms=12)
    titles = ["head's mass landing on the parent's head\n(dotted: fraction of samples in the head)",
              "matched region size (participation ratio)\n(dotted: the head's share of the full shape)",
              "nearest full shape: right class / the parent", "median correspondence error / √area"]
    for ax, t in zip(axes, titles):
        ax.set_xscale("log")
        ax.set_xlabel("relative mass penalty κ  (★ = paper's α = 1/ρ²)")
        ax.set_title(t, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(0, 1.02)
    axes[1].set_ylim(0, 1.02)
    axes[2].set_ylim(-0.02, 1.02)
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def mass_figure(base, ds, head: str, kappas, path: Path, log) -> None:
    """The parent of ``head`` coloured by the mass it receives from the head (relative to uniform, n·m2,
    spread over each sample's cell), one panel per κ, with the share landing on the true head."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from wpot.plot import plot_vertex_scalar

    full = ds.parent[head]
    mf = ds.mesh(full)
    fig, axes = plt.subplots(1, len(kappas), figsize=(4.6 * len(kappas), 3.8))
    for ax, k in zip(np.atleast_1d(axes), kappas):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            comp = base.with_options(mass_penalty=k).compare(ds.mesh(head), mf)
        m2 = comp.mass2 / comp.mass2.sum()
        dens = m2 * len(m2)
        per_vertex = dens if comp.sample_b is None else comp.sample_b.extend(dens)
        pm = pair_metrics(ds, head, full, comp)
        plot_vertex_scalar(mf, np.minimum(per_vertex, 10.0), vmin=0, vmax=10.0, cmap="magma", ax=ax, elev=20, azim=-60,
                           label="received mass / uniform (clipped at 10)",
                           title=f"κ={k:g}: {pm['head_mass']:.0%} on the head, f_eff={pm['f_eff']:.2f}")
        log(f"mass figure {head} -> {full}, kappa={k:g}: head_mass {pm['head_mass']:.3f} f_eff {pm['f_eff']:.3f}")
    fig.suptitle(f"{base.signature}: mass the full shape {full} receives from {head} (partial transport)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tosca", type=Path, default=_tosca(Path("/work/shared/data/tosca_isometric_5k")))
    ap.add_argument("--out", type=Path, required=True, help="output folder (not inside the repository)")
    ap.add_argument("--lowres", type=Path, default=None,
                    help="tosca_lowres folder: the paper's HEAD, the low-resolution shapes (~3,400 vertices) and their "
                         "heads (~700), with --per-class 6 TOSCA8's cats and six horses (build_head_dataset(lowres=))")
    ap.add_argument("--per-class", type=int, default=None, help="full shapes per class (default: all)")
    ap.add_argument("--signatures", nargs="+", default=["wks", "ldsift"], choices=["wks", "ldsift"])
    ap.add_argument("--heads", nargs="+", default=None,
                    help=f"heads of the sweep (default: those of {', '.join(DEFAULT_HEADS)} in the dataset)")
    ap.add_argument("--extra-full", nargs="*", default=[], help="full shapes besides the heads' parents")
    ap.add_argument("--kappas", nargs="+", type=float, default=list(DEFAULT_KAPPAS))
    ap.add_argument("--no-paper", action="store_true", help="skip the paper's alpha = 1/rho^2 row")
    ap.add_argument("--max-vertices", type=int, default=250)
    ap.add_argument("--n-eigen", type=int, default=200, help="WKS eigenpairs (paper 500; fewer to run here)")
    ap.add_argument("--n-energies", type=int, default=100, help="WKS energies (paper 200)")
    ap.add_argument("--confirm", type=float, nargs="+", default=None,
                    help="instead of the sweep: every head against every full shape at these kappas "
                         "(and the paper's alpha unless --no-paper)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--pooling", default="none", choices=["none", "cell"], help="how samples stand for a mesh (Comparer)")
    ap.add_argument("--vertices-per-sample", type=float, default=None,
                    help="sample every mesh at this common density instead of --max-vertices each (Comparer)")
    ap.add_argument("--ldsift-slab", type=float, default=1.0, help="LD-SIFT depth slab half-thickness in units of S(v) (Comparer)")
    ap.add_argument("--report-only", action="store_true", help="only rebuild the table and figure from --out")
    ap.add_argument("--mass-figure", default=None, metavar="HEAD",
                    help="instead: draw HEAD's parent coloured by received mass at each of --kappas")
    a = ap.parse_args(argv)
    repo = Path(__file__).resolve().parents[1]
    out = a.out.resolve()
    if out == repo or repo in out.parents:
        raise SystemExit(f"--out must be outside the repository ({repo}), got {out}")
    out.mkdir(parents=True, exist_ok=True)
    logf = open(out / ("confirm.log" if a.confirm is not None else "sweep.log"), "a")

    def log(msg: str) -> None:
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    from wpot.paper.head import build_head_dataset, load_head_dataset

    dsdir = out / "head_dataset"
    ds = load_head_dataset(dsdir) if (dsdir / "manifest.json").is_file() else \
        build_head_dataset(a.tosca, dsdir, lowres=a.lowres, per_class=a.per_class)
    if a.confirm is not None:
        heads = [n for n in ds.names if n in ds.parent]
        fulls = [n for n in ds.names if n not in ds.parent]
        settings = [("relative", k) for k in sorted(a.confirm, reverse=True)]
        if not a.no_paper:
            settings.append(("paper", 1.0))
    else:
        heads = [h for h in DEFAULT_HEADS if h in ds.parent] if a.heads is None else list(a.heads)
        missing = [h for h in heads if h not in ds.parent]
        if missing:
            raise SystemExit(f"--heads: {missing} not in this HEAD dataset; its heads: {sorted(ds.parent)}")
        fulls = list(dict.fromkeys([ds.parent[h] for h in heads] + list(a.extra_full)))
        settings = [("relative", k) for k in sorted(a.kappas, reverse=True)]
        if not a.no_paper:
            settings.append(("paper", 1.0))
    log(f"HEAD: {len(heads)} heads x {len(fulls)} full shapes, max_vertices={a.max_vertices}, settings={settings}"
        + (f", ldsift_slab={a.ldsift_slab:g}" if a.ldsift_slab != 1.0 else ""))
    if a.mass_figure is not None:
        for sig in a.signatures:
            base = base_comparer(a, sig, ds, heads + fulls, out)
            path = out / f"mass_{sig}_{a.mass_figure}.png"
            mass_figure(base, ds, a.mass_figure, a.kappas, path, log)
            log(f"figure: {path}")
        return 0
    stem = "confirm" if a.confirm is not None else "results"
    for sig in ([] if a.report_only else a.signatures):
        results_path = out / f"{stem}_{sig}.json"  # one file per signature: two processes can share --out
        results = json.loads(results_path.read_text()) if results_path.is_file() else {}
        t0 = time.perf_counter()
        base = base_comparer(a, sig, ds, heads + fulls, out)
        for n in heads + fulls:
            base.signatures(ds.mesh(n))
            base.subsample(ds.mesh(n))
        log(f"{sig}: signatures and samples of {len(heads) + len(fulls)} shapes in {time.perf_counter() - t0:.0f} s")
        kp = paper_kappa(base, ds, heads, fulls)
        log(f"{sig}: the paper's alpha = 1/rho^2 is kappa = {kp:.3g} here (median over the parent pairs)")
        rows = [r for r in results.get(sig, []) if (r["scale"], r["kappa_arg"]) not in settings]
        for scale, k in settings:
            c = base.with_options(mass_penalty=k, penalty_scale=scale)
            label = f"paper a={k:g}" if scale == "paper" else f"kappa={k:g}"
            r = run_setting(c, ds, heads, fulls, label, log)
            r.update(scale=scale, kappa_arg=k, kappa=(kp * k if scale == "paper" else k), max_vertices=a.max_vertices)
            rows.append(r)
            results[sig] = rows
            results_path.write_text(json.dumps(results, indent=1))
    results = {}
    for path in sorted(out.glob(f"{stem}_*.json")):
        results.update(json.loads(path.read_text()))
    md = table(results)
    (out / f"{stem}.md").write_text(md)
    log(md)
    if a.confirm is None:
        figure(results, out / "head_partial.png")
        log(f"figure: {out / 'head_partial.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
