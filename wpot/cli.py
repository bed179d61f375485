"""The ``wpot`` command.

    wpot demo --out DIR                        compare the two generated example shapes, save a picture
    wpot compare A B [--signature --transport --out DIR]
    wpot all-vs-all FOLDER|LIST --signature wks --transport balanced --out RUN [--jobs N] [--labels CSV]
                    [--scheduler local|tcp://HOST:PORT]
    wpot classify RUN                          1-NN one-shot (Table 1) and leave-one-out (Tables 2-4)
    wpot report RUN [RUN ...]                  Markdown summary beside the paper's tables

Errors in the input (missing files, bad options, a run folder holding other parameters) end with exit
code 2 and a one-line message; set ``WPOT_DEBUG=1`` for the traceback.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from wpot.report import signature_title

__all__ = ["main", "build_parser", "config_from_args"]
#: small settings for `wpot demo`: a few hundred vertices and a short spectrum (runs in seconds on a CPU)
DEMO = {"n": 400, "n_eigen": 100, "n_energies": 100}


class CliError(Exception):
    """A user-facing error: printed as one line, exit code 2."""


# ---------------------------------------------------------------------------------------------- parser
def _add_method_options(p: argparse.ArgumentParser, *, defaults: Mapping[str, Any] | None = None) -> None:
    """The comparison's options; the choices and the signatures' flags come from the registered stages."""
    from wpot.config import TRANSPORTS, ComparisonConfig
    from wpot.ot import SOLVERS
    from wpot.sampling import POOLINGS
    from wpot.signatures import add_signature_arguments, signature_names

    d = ComparisonConfig()  # the defaults, as in Python
    p.add_argument("--signature", choices=signature_names(), default=d.signature,
                   help=f"vertex signature (default: {d.signature})")
    p.add_argument("--transport", choices=TRANSPORTS, default=d.transport, help=f"transport (default: {d.transport})")
    p.add_argument("--max-vertices", type=int, default=None, help="subsample larger meshes by farthest-point sampling")
    p.add_argument(
        "--pooling", choices=POOLINGS, default=d.sampler.pooling,
        help="with --max-vertices or --vertices-per-sample: each sample keeps its own signature, uniform masses (none, default), or carries "
             "its cell's mean signature and size as mass (cell: better for whole shapes meshed alike, e.g. LD-SIFT "
             "classification; not for parts against wholes)",
    )
    p.add_argument(
        "--vertices-per-sample", type=float, default=None,
        help="subsample every mesh at a common density instead: round(N / this) samples per mesh of N vertices "
             "(at most --max-vertices), so cells match in size; with --pooling cell, for parts against wholes",
    )
    p.add_argument(
        "--mass-penalty", type=float, default=d.mass_penalty,
        help=("partial transport: relative chi^2 mass penalty kappa, alpha = kappa*mean(C)/(sqrt(N1*N2)*rho^2): "
              "spreading a side's mass on a fraction f of its points costs kappa*(1/f-1) mean costs "
              f"(default {d.mass_penalty:g}, chosen on HEAD: benchmarks/head_partial.py; smaller = more partial)"),
    )
    add_signature_arguments(p, defaults=dict(defaults or {}))
    p.add_argument("--device", default=None, help='Warp device, e.g. "cpu" or "cuda:0" (default: Warp\'s default)')
    p.add_argument(
        "--ot-method", choices=tuple(SOLVERS), default=d.method,
        help=("balanced transport: 'anneal' (Algorithm 1 from the first beta, D(beta) at every beta), 'ipm' "
              "(interior-point start, then Algorithm 1 from the first beta with gap <= 1e-3 U: the same D(inf), "
              "faster for large problems; see the README) or 'auto' (default: 'ipm' when both shapes have "
              "at least 2000 points, else 'anneal'); partial transport always anneals"),
    )


def _add_match_ratio(p: argparse.ArgumentParser) -> None:
    p.add_argument("--match-ratio", type=float, default=0.9,
                   help="a pair (i, j) is matched, and used for the registration, when G(i, j) > this x m1(i) "
                        "(default 0.9, the paper's)")


def _add_zoomout(p: argparse.ArgumentParser) -> None:
    p.add_argument("--zoomout", action="store_true",
                   help="also refine the correspondence by ZoomOut (spectral upsampling, wpot.zoomout; whole, "
                   "near-isometric shapes only, so not with --transport partial); saved as "
                   "correspondence_zoomout and drawn in the picture")


def _zoomout(a: argparse.Namespace, ma, mb, c: Any) -> np.ndarray | None:
    """The ZoomOut refinement of ``c.correspondence`` when ``--zoomout`` was given (printing how much moved)."""
    if not a.zoomout:
        return None
    from wpot.refine import zoomout

    refined = zoomout(ma, mb, c.correspondence)
    print(f"ZoomOut: {np.mean(refined != c.correspondence):.1%} of A's vertices changed their match")
    return refined


def _check_zoomout(a: argparse.Namespace) -> None:
    if a.zoomout and a.transport == "partial":
        raise CliError("--zoomout refines maps between whole, near-isometric shapes (their Laplace-Beltrami spectra "
                       "must match); with --transport partial, for a part against a whole, it would spread the part "
                       "over the whole. Drop --zoomout, or use --transport balanced for two whole shapes")


def config_from_args(a: argparse.Namespace) -> Any:
    """The `wpot.config.ComparisonConfig` the parsed options describe (the device is not part of it)."""
    from wpot.config import ComparisonConfig
    from wpot.sampling import SamplerOptions
    from wpot.signatures import signature_options_from_args

    if a.ot_method == "ipm" and a.transport != "balanced":
        raise CliError(f"--ot-method {a.ot_method} applies to balanced transport only (got --transport {a.transport})")
    return ComparisonConfig(
        signature=a.signature,
        signature_options=signature_options_from_args(a.signature, a),
        transport=a.transport,
        sampler=SamplerOptions(max_vertices=a.max_vertices, vertices_per_sample=a.vertices_per_sample,
                               pooling=a.pooling),
        mass_penalty=a.mass_penalty,
        method=a.ot_method if a.transport == "balanced" else "auto",  # partial transport always anneals
        match_ratio=a.match_ratio if "match_ratio" in a else 0.9,
    )


def build_parser() -> argparse.ArgumentParser:
    from wpot import __version__

    parser = argparse.ArgumentParser(prog="wpot", description="Compare 3D shapes by statistical-physics optimal transport.")
    parser.add_argument("--version", action="version", version=f"wpot {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="compare the two generated example shapes and save a picture")
    p.add_argument("--out", default="wpot-demo", help="folder for the picture (default: ./wpot-demo)")
    p.add_argument("--n", type=int, default=DEMO["n"], help=f"vertices of the example shape (default {DEMO['n']})")
    _add_method_options(p, defaults={"n_eigen": DEMO["n_eigen"], "n_energies": DEMO["n_energies"]})
    _add_match_ratio(p)
    _add_zoomout(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("compare", help="compare two mesh files")
    p.add_argument("mesh_a")
    p.add_argument("mesh_b")
    p.add_argument("--out", default=None, help="folder for comparison.json, correspondence.npz and correspondence.png")
    _add_method_options(p)
    _add_match_ratio(p)
    _add_zoomout(p)
    p.set_defaults(func=cmd_compare)

    p = sub.add_parser("all-vs-all", help="compare every pair of a dataset into a resumable run folder")
    p.add_argument("source", help="a folder of meshes, or a text file listing one mesh path per line")
    p.add_argument("--out", required=True, help="run folder (resumed if it holds the same run)")
    p.add_argument("--jobs", type=int, default=None,
                   help="worker processes (default 1; 0 = all cores); with --scheduler local, Dask workers (default: all cores)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help='run the pairs on Dask: "local" (an embedded cluster of --jobs processes) or a running '
                   "scheduler tcp://HOST:PORT; each worker uses its own GPU when it has one "
                   "(needs pip install 'wpot[cluster]')")
    p.add_argument("--labels", default=None, help="label CSV: a 'name' column and one column per label level")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_method_options(p)
    p.set_defaults(func=cmd_all_vs_all)

    p = sub.add_parser("classify", help="1-NN classification from a run's distance matrix")
    p.add_argument("run")
    p.add_argument("--trials", type=int, default=10_000, help="one-shot trials (default 10,000, as Table 1)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_classify)

    p = sub.add_parser("export", help="write a run's distance matrix as CSV (names as header) or NPZ (with D(beta))")
    p.add_argument("run")
    p.add_argument("--out", default=None, help="a .csv or .npz file (default: RUN/distances.csv)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("report", help="Markdown summary of one or more runs beside the paper's tables")
    p.add_argument("runs", nargs="+")
    p.add_argument("--out", default=None, help="Markdown file (default: RUN/report.md of the first run)")
    p.add_argument("--trials", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_report)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``wpot`` command; returns the exit code (0 success, 2 bad input, 130 interrupted)."""
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except KeyboardInterrupt:
        print("wpot: interrupted (a run resumes where it stopped when rerun with the same command)", file=sys.stderr)
        return 130
    except (CliError, OSError, ValueError) as exc:
        if os.environ.get("WPOT_DEBUG"):
            raise
        msg = " ".join(str(exc).split()) or type(exc).__name__
        if isinstance(exc, FileNotFoundError) and exc.filename and str(exc.filename) not in msg:
            msg = f"{msg}: {exc.filename}"
        print(f"wpot: error: {msg}", file=sys.stderr)
        return 2
    return 0


# ------------------------------------------------------------------------------------------- commands
def _load(path: str):
    from wpot.io import load_mesh

    if not Path(path).is_file():
        raise CliError(f"mesh file not found: {path}")
    return load_mesh(path)


def _summary_lines(c: Any, match_ratio: float) -> list[str]:
    lines = [
        f"distance: {c.distance:.6g}  ({'U, Eq. 6' if c.transport == 'balanced' else 'SU, Eq. 27'}; "
        f"{signature_title(c.signature)}, {c.transport} transport)",
        f"converged: {bool(c.result.converged)} at beta {float(c.result.beta):.3g}"
        f" ({int(c.result.n_newton)} Newton steps, {int(c.result.n_linear)} linear iterations)",
        f"matched pairs (G > {match_ratio:g} m1): {len(c.matched)} of {len(c.correspondence)} vertices",
    ]
    if c.registration is not None:
        r = c.registration
        lines.append(f"registration: scale {r.scale:.4g}, rms residual {r.rms:.4g} over {r.n_pairs} pairs")
    else:
        n1, n2 = len(c.mass1), len(c.mass2)
        why = (f"with balanced transport a point of A (mass 1/{n1}) fits in one of B (mass 1/{n2}) only when "
               f"{n2} <= {n1}/{match_ratio:g}; use --transport partial, equal --max-vertices, or a lower --match-ratio"
               if c.transport == "balanced" and n2 > n1 / match_ratio else "lower --match-ratio, or try --transport partial")
        lines.append(f"registration: none, fewer than 3 non-collinear pairs matched ({why})")
    return lines


def _save_comparison(c: Any, a, b, out: Path, extra: dict[str, Any] | None = None,
                     refined: np.ndarray | None = None) -> list[Path]:
    """comparison.json, correspondence.npz (with ``correspondence_zoomout`` when ``refined`` is given) and
    correspondence.png (of ``refined`` when given, else of the plan's correspondence)."""
    from wpot.plot import plot_correspondence

    out.mkdir(parents=True, exist_ok=True)
    info = {
        "distance": c.distance,
        "signature": c.signature,
        "transport": c.transport,
        "converged": bool(c.result.converged),
        "beta": float(c.result.beta),
        "n_matched": int(len(c.matched)),
        "self_energies": c.self_energies,
        "history": c.history.tolist(),
        "registration": None
        if c.registration is None
        else {
            "scale": c.registration.scale,
            "rotation": c.registration.rotation.tolist(),
            "translation": c.registration.translation.tolist(),
            "rms": c.registration.rms,
            "n_pairs": c.registration.n_pairs,
        },
        **(extra or {}),
    }
    files = [out / "comparison.json", out / "correspondence.npz", out / "correspondence.png"]
    files[0].write_text(json.dumps(info, indent=2))
    arrays = {} if refined is None else {"correspondence_zoomout": refined}
    np.savez(files[1], correspondence=c.correspondence, matched=c.matched, matched_weight=c.matched_weight,
             mass1=c.mass1, mass2=c.mass2, **arrays)
    title_b = "B"
    if c.registration is not None:  # draw B in A's pose: undo the fitted similarity
        b = c.registration.inverse().apply(b)
        title_b = "B, moved onto A by the inverse of the fitted registration"
    shown, what = (c.correspondence, "correspondence") if refined is None else (refined, "ZoomOut correspondence")
    plot_correspondence(a, b, shown, titles=(f"A, coloured through the {what}", title_b), path=files[2])
    return files


def cmd_demo(a: argparse.Namespace) -> None:
    from wpot.comparison import compare
    from wpot.examples import example_pair

    t0 = time.perf_counter()
    # equal vertex counts, so that a balanced plan can match vertex to vertex (G > 0.9 m1) and a
    # registration can be fitted
    pair = example_pair(a.n, seed=0, n_target=a.n)
    src, tgt = pair.source, pair.target
    config = config_from_args(a)
    _check_zoomout(a)
    c = compare(src, tgt, config=config, device=a.device)
    print(f"example shapes: {src.n_vertices} vertices each (two triangulations of one surface, B rigidly moved)")
    for line in _summary_lines(c, a.match_ratio):
        print(line)

    def median_error(corr: np.ndarray, label: str) -> float:
        """Ground truth: source vertex i is well matched when the target vertex it maps to samples a point of
        the surface near vertex i (in the source frame, in mean edge lengths). Prints and returns the median."""
        err = np.linalg.norm(pair.target_in_source_frame[corr] - src.vertices, axis=1) / src.mean_edge_length
        print(f"{label}: median {np.median(err):.2f} mean edge lengths, "
              f"{100 * np.mean(err <= 2):.0f}% of vertices within 2 edge lengths")
        return float(np.median(err))

    extra = {"median_error_edge_lengths": median_error(c.correspondence, "correspondence error vs ground truth")}
    refined = _zoomout(a, src, tgt, c)
    if refined is not None:
        extra["median_error_edge_lengths_zoomout"] = median_error(refined, "after ZoomOut")
    files = _save_comparison(c, src, tgt, Path(a.out), extra, refined=refined)
    if c.registration is not None:
        rel = c.registration.rotation @ pair.rotation.T
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))
        print(f"registration vs the true rigid motion of B: rotation off by {angle:.1f} degrees")
    print(f"saved {files[2]} ({time.perf_counter() - t0:.1f} s)")


def cmd_compare(a: argparse.Namespace) -> None:
    from wpot.comparison import compare

    config = config_from_args(a)  # option errors before any file is read
    _check_zoomout(a)
    ma, mb = _load(a.mesh_a), _load(a.mesh_b)
    c = compare(ma, mb, config=config, device=a.device)
    print(f"A: {a.mesh_a} ({ma.n_vertices} vertices)   B: {a.mesh_b} ({mb.n_vertices} vertices)")
    for line in _summary_lines(c, a.match_ratio):
        print(line)
    refined = _zoomout(a, ma, mb, c)
    if a.out:
        extra = {"mesh_a": str(a.mesh_a), "mesh_b": str(a.mesh_b), "zoomout": bool(a.zoomout)}
        files = _save_comparison(c, ma, mb, Path(a.out), extra, refined=refined)
        print("saved " + ", ".join(str(f) for f in files))


def cmd_all_vs_all(a: argparse.Namespace) -> None:
    from wpot.pipeline import run_all_vs_all

    if a.jobs is not None and a.jobs < 0:
        raise CliError(f"--jobs must be >= 0, got {a.jobs}")
    if a.scheduler is not None:
        if a.scheduler != "local" and "://" not in a.scheduler:
            raise CliError(f'--scheduler must be "local" or a Dask address like tcp://HOST:8786, got {a.scheduler!r}')
        if a.scheduler != "local" and a.jobs is not None:
            raise CliError(f"--jobs sets local processes; a running cluster ({a.scheduler}) has the workers it was started with")
    jobs = (1 if a.scheduler is None else 0) if a.jobs is None else a.jobs
    if a.labels is not None and not Path(a.labels).is_file():
        raise CliError(f"label CSV not found: {a.labels}")
    if not Path(a.source).exists():
        raise CliError(f"no such folder or list file: {a.source}")
    t0 = time.perf_counter()
    config = config_from_args(a)
    try:
        store = run_all_vs_all(
            a.source, a.out, jobs=(jobs or None), scheduler=a.scheduler, labels=a.labels,
            progress=not a.no_progress, config=config, device=a.device,
        )
    except ImportError as exc:
        if a.scheduler is None:
            raise
        raise CliError(str(exc)) from exc
    with store:
        total, done = len(store.tasks()), len(store.done())
        fails = store.failures()
        conv = sum(1 for r in store.pair_rows() if r["converged"])
    print(f"{done} of {total} pairs in {a.out} ({conv} converged), {time.perf_counter() - t0:.1f} s this session")
    if fails:
        raise CliError(f"{len(fails)} pairs failed (first: pair {fails[0][:2]}: {fails[0][2]}); rerun to retry them")


def cmd_classify(a: argparse.Namespace) -> None:
    from wpot.evaluate import format_percent
    from wpot.pipeline import RunStore
    from wpot.report import PAPER_TABLE1, classify_run, confusions, misses_text

    with RunStore(a.run) as store:
        r = classify_run(store, trials=a.trials, seed=a.seed)
        p = store.params
    one = r["one_shot"]
    key = (p.get("signature"), p.get("transport"))
    paper = PAPER_TABLE1.get(key)
    print(f"run: {a.run}  ({signature_title(key[0])}, {key[1]} transport; {len(r['levels']['class'])} shapes, {len(one.classes)} classes)")
    print(f"1-NN, one random training shape per class, {one.n_trials} trials: {format_percent(one.mean)} "
          f"(std {100 * one.std:.1f})" + (f"   paper Table 1 (TOSCA8): {paper:.1f}%" if paper is not None else ""))
    conf = confusions(one)
    if conf:
        print("  classes below 100%: " + "; ".join(conf))
    for lv, res in r["loo"].items():
        print(f"leave-one-out 1-NN at level {lv!r} ({res.n_groups} groups): {format_percent(res.accuracy)}")
        if r["loo_misses"][lv]:
            print("  wrong: " + misses_text(r["loo_misses"][lv]))
    if r["per_beta"]:
        print("one-shot 1-NN from D(β): " + ", ".join(f"β={b:.0e} {format_percent(acc)}" for b, acc in r["per_beta"]))
    if r["not_converged"]:
        n = len(r["levels"]["class"])
        print(f"warning: {r['not_converged']} of {n * (n - 1) // 2} pairs did not converge, and their D(inf) may be wrong, "
              "so these accuracies may be too; `wpot report` lists them. Rerun with other solver options "
              "(e.g. --ot-method ipm for balanced transport) in a new --out folder", file=sys.stderr)
    out = Path(a.run) / "classification.json"
    out.write_text(json.dumps({
        "one_shot": {"mean": one.mean, "std": one.std, "n_trials": one.n_trials, "seed": one.seed,
                     "classes": list(one.classes),
                     "confusion": [[None if not np.isfinite(v) else float(v) for v in row] for row in one.confusion]},
        "not_converged": r["not_converged"],
        "leave_one_out": {lv: res.accuracy for lv, res in r["loo"].items()},
        "leave_one_out_wrong": r["loo_misses"],
        "one_shot_per_beta": r["per_beta"],
    }, indent=2))


def cmd_export(a: argparse.Namespace) -> None:
    from wpot.pipeline import RunStore
    from wpot.report import pair_counts

    with RunStore(a.run) as store:
        out = store.export(Path(a.out) if a.out else Path(a.run) / "distances.csv")
        d, missing, not_conv = pair_counts(store)
        n = len(d)
    print(f"saved {out} ({n} shapes, {n * (n - 1) // 2 - missing} of {n * (n - 1) // 2} pairs)")
    if missing:
        print(f"warning: the run is incomplete: {missing} pairs are missing (empty in CSV, NaN in NPZ); finish it "
              "with the same all-vs-all command", file=sys.stderr)
    if not_conv:
        print(f"warning: {not_conv} pairs did not converge and their distances may be wrong; `wpot report` lists them",
              file=sys.stderr)


def cmd_report(a: argparse.Namespace) -> None:
    from wpot.report import build_report

    out = build_report(a.runs, a.out, trials=a.trials, seed=a.seed)
    print(out.read_text())
    print(f"saved {out}")


if __name__ == "__main__":
    sys.exit(main())
