"""The ``wpot`` command.

    wpot demo --out DIR                        compare the two generated example shapes, save a picture
    wpot compare A B [--signature --transport --out DIR]
    wpot all-vs-all FOLDER|LIST --signature wks --transport balanced --out RUN [--jobs N] [--labels CSV]
                    [--scheduler local|tcp://HOST:PORT]
    wpot classify RUN                          1-NN one-shot (Table 1) and leave-one-out (Tables 2-4)
    wpot report RUN [RUN ...]                  Markdown summary beside the paper's tables

Errors in the input (missing files, bad options, a run folder holding other parameters) end with exit
code 2 and a one-line message; set ``WPOT_DEBUG=1`` for the traceback. Messages and warnings raised by the
library name its keywords (``max_vertices``, ``scale_invariant=True``, ``Mesh.cleaned()``); the command
words them with its own flags (``--max-vertices``, ``--scale-invariant``, ``--repair``) through `cli_words`,
whose table is read from the parser's flags and the registered signatures' option metadata.

Progress (a line per step with its time, bars for all-vs-all's phases) goes to standard error when it is a
terminal; ``--progress`` asks for it anyway, ``--no-progress`` turns it off.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence, TextIO

import numpy as np

from wpot.runs.report import signature_title

__all__ = ["main", "build_parser", "config_from_args", "cli_words", "flag_table", "progress_enabled"]
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
    p.add_argument("--max-vertices", type=int, default=None,
                   help="subsample a mesh with more vertices than this to this many farthest-point samples "
                        "(default: none, every vertex is used)")
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
    p.add_argument("--repair", action="store_true",
                   help="repair each mesh first: remove zero-area and duplicate triangles and unreferenced vertices "
                        "(wpot.Mesh.cleaned), and say what was removed; saved correspondences keep the input's "
                        "vertex numbering")
    p.add_argument("--largest-component", action="store_true",
                   help="keep only each mesh's largest connected component (stray pieces of a scan, detached "
                        "parts), after --repair's fixes, which it implies")
    p.add_argument(
        "--ot-method", choices=tuple(SOLVERS), default=d.method,
        help=("'auto' (default) or 'exact': D(inf) alone, solved exactly (the transport LP for balanced transport, "
              "the chi^2 QP for partial) and certified over every pair of points; 'anneal': Algorithm 1 from the "
              "first beta, D(beta) at every beta (much slower at full resolution); 'ipm' (balanced transport "
              "only): an interior-point start, then Algorithm 1 from the first beta with gap <= 1e-3 U"),
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


def _zoomout(a: argparse.Namespace, ma, mb, c: Any) -> Any:
    """The `wpot.maps.zoomout.ZoomOutResult` of ``c.correspondence`` when ``--zoomout`` was given (printing how
    much moved and how sure its left/right choice is), else None."""
    if not a.zoomout:
        return None
    from wpot.maps.zoomout import ORIENTATION_DOUBT, zoomout

    res = zoomout(ma, mb, c.correspondence)
    print(f"ZoomOut: {np.mean(res.map != c.correspondence):.1%} of A's vertices changed their match")
    conf = res.orientation_confidence
    if np.isnan(conf):
        print("ZoomOut: left and right were not weighed (a mesh has several components or no readable outside); "
              "the map may be mirrored")
    else:
        doubt = (f"below {ORIENTATION_DOUBT}: another left/right choice fits nearly as well, check the map"
                 if conf < ORIENTATION_DOUBT else f"at least {ORIENTATION_DOUBT}: trusted")
        print(f"ZoomOut: orientation confidence {conf:.2f} ({doubt})")
    if res.mended:
        print("ZoomOut: the chosen map was mirrored on a part (e.g. both legs), which was mended through the "
              "shape's left/right symmetry")
    if res.reanchored:
        print("ZoomOut: the chosen map had seams (a region turned round, e.g. the upper body or the legs); the "
              "regions they cut off were mapped again from the rest of the shape")
    return res


def _add_locate(p: argparse.ArgumentParser) -> None:
    p.add_argument("--locate", action="store_true",
                   help="also locate A in B by geodesic consistency (wpot.maps.locate: A a part of a shape like B, in any "
                   "pose, at the same scale; the signatures propose matches, geodesic distances choose among them); "
                   "saved as correspondence_locate, confidence_locate and region_locate (and "
                   "correspondence_locate_other_side, the map on B's other side, and "
                   "correspondence_locate_other_place, the map at the other place where the place is in doubt, when "
                   "there is one), and drawn in the picture")
    p.add_argument("--locate-edge", choices=("own", "whole"), default=None,
                   help="LD-SIFT's edge length for --locate (with --signature ldsift): own (default) each mesh's own, "
                   "the paper's; whole: B's for both, for a part meshed at another density than B (a scan, a part "
                   "re-meshed): the docs' Results page compares the two")
    p.add_argument("--locate-orient-weight", type=float, default=None, metavar="W",
                   help="how --locate chooses left from right: by default, of the maps that keep orientation about as "
                   "well as the best, the one whose signatures fit best; W: the one of least relative signature cost "
                   "less W times its orientation score (0.3 for a part meshed apart from B, with --locate-edge whole: "
                   "the docs' Results page)")
    p.add_argument("--locate-scale", default=None, metavar="SCALE",
                   help="how A's lengths compare with B's for --locate: same (default) one scale; fit: found by "
                   "--locate, for shapes normalised one by one (each scaled on its own); a number s: A's "
                   "lengths times s are B's")
    p.add_argument("--locate-aligned", action="store_true",
                   help="A is given in B's frame (scanned in one place, the same way up and facing the same way): "
                   "--locate then prefers, of its candidate maps, those that turn A least onto B, which tells "
                   "left from right and front from back where A's shape cannot. Warns when the map kept turns A "
                   "by more than 90 degrees")
    p.add_argument("--locate-landmarks", default=None, metavar="FILE",
                   help="landmarks for --locate: a text file with a vertex of A and the vertex of B that matches it "
                   "on each line (two 0-based indices into the mesh files; # starts a comment). The located map "
                   "must agree with them, which settles what A's shape leaves in doubt: which of several like "
                   "places (one leg of four), and which side")


class _Located(NamedTuple):
    """What ``--locate`` found: the `wpot.maps.locate.PartMap` of A in B, and the rigid fit of A's vertices onto their
    located images (`located_registration`; None when none could be fitted), which places B in the picture."""

    map: Any
    registration: Any


def located_registration(part: Any, whole: Any, pm: Any) -> Any:
    """The transform that takes the part's vertices onto their images in the whole under the located map ``pm``:
    `fit_similarity_robust`, each vertex weighted by its confidence, at the scale `locate_part` used
    (`PartMap.scale`: 1 unless `LocateOptions.scale` says otherwise). None when the map's confident vertices do not
    determine one (fewer than 3 with weight, or collinear)."""
    from wpot.maps.registration import fit_similarity_robust

    conf = np.asarray(pm.confidence, dtype=np.float64)
    weights = conf if np.isfinite(conf).all() and conf.sum() > 0 else None
    try:
        reg = fit_similarity_robust(part.vertices, whole.vertices[pm.correspondence], weights, scale=pm.scale)
    except ValueError:
        return None
    return reg.with_target(whole)


def _landmarks(path: str | None, ma: "_Loaded", mb: "_Loaded") -> np.ndarray | None:
    """``--locate-landmarks FILE`` read: (L, 2) indices into the meshes as the command uses them (after
    ``--repair``), each row a vertex of A and its match on B; None without the flag. Errors in the flag's words."""
    if path is None:
        return None
    if not Path(path).is_file():
        raise CliError(f"--locate-landmarks: file not found: {path}")
    rows = []
    for k, line in enumerate(Path(path).read_text().splitlines(), 1):
        words = line.split("#", 1)[0].replace(",", " ").split()
        if not words:
            continue
        if len(words) != 2 or not all(w.isdigit() for w in words):
            raise CliError(f"--locate-landmarks {path}, line {k}: expected two vertex indices (a vertex of A, then "
                           f"the vertex of B it matches; 0-based), got {line.strip()!r}")
        rows.append((k, int(words[0]), int(words[1])))
    if not rows:
        raise CliError(f"--locate-landmarks {path} holds no landmarks (two vertex indices a line)")
    out = np.zeros((len(rows), 2), dtype=np.int64)
    for j, (m, label) in enumerate(((ma, "A"), (mb, "B"))):
        given = [row[1 + j] for row in rows]
        for (k, *_), v in zip(rows, given):
            if v >= m.n_input:
                raise CliError(f"--locate-landmarks {path}, line {k}: {label} has no vertex {v} (it has "
                               f"{m.n_input}, numbered from 0)")
        out[:, j] = m.from_input(given)
        for (k, *_), v, used in zip(rows, given, out[:, j]):
            if used < 0:
                raise CliError(f"--locate-landmarks {path}, line {k}: vertex {v} of {label} was removed by "
                               "--repair; choose another")
    first = {}
    for (k, v, _), used in zip(rows, out[:, 0]):
        if int(used) in first:
            raise CliError(f"--locate-landmarks {path}: lines {first[int(used)]} and {k} both give vertex {v} of A "
                           "a match; keep one")
        first[int(used)] = k
    return out


def _locate(a: argparse.Namespace, comparer: Any, ma, mb, landmarks: np.ndarray | None = None) -> _Located | None:
    """`Comparer.locate` of A in B when ``--locate`` was given (printing what it found, its confidence and the
    transform that places it); ``landmarks``: `_landmarks`."""
    if not getattr(a, "locate", False):
        return None
    from wpot.maps.locate import PLACEMENT_DOUBT, SIDE_DOUBT, LocateOptions

    given = {k: v for k, v in (("edge", a.locate_edge), ("orient_weight", a.locate_orient_weight),
                               ("scale", _locate_scale(a.locate_scale)), ("aligned", a.locate_aligned or None))
             if v is not None}
    pm = comparer.locate(ma, mb, options=LocateOptions(**given) if given else None, landmarks=landmarks)
    if landmarks is not None:
        miss = np.linalg.norm(mb.vertices[pm.correspondence[landmarks[:, 0]]] - mb.vertices[landmarks[:, 1]], axis=1)
        print(f"landmarks: {len(landmarks)} from {a.locate_landmarks}; the map puts them a mean of "
              f"{miss.mean() / np.sqrt(mb.area):.3g} x sqrt(area of B) from their matches (straight line; largest "
              f"{miss.max() / np.sqrt(mb.area):.3g})")
    print(f"locate: {len(pm.anchors)} consistent anchor matches; median residual {np.median(pm.residual):.3g} "
          f"x sqrt(area of B); region {int(pm.region().sum())} of B's {mb.n_vertices} vertices; orientation score "
          f"{pm.orientation:.2f}")
    doubt = ""
    if pm.placement_confidence < PLACEMENT_DOUBT:
        saved = ("" if pm.other_place is None else
                 "; the map at the other place is saved as correspondence_locate_other_place")
        doubt = (f" (below {PLACEMENT_DOUBT}: another place in B fits A about as well, or none fits; check the "
                 f"region{saved})")
    print(f"placement confidence {pm.placement_confidence:.2f}: {len(pm.anchors)} anchors vouch for this place, "
          f"{len(pm.rival)} for the best other{doubt}")
    if np.isnan(pm.side_margin):
        print("side: not read (no left/right symmetry found in B, or A has no side)")
    elif np.isinf(pm.side_margin):
        print("side margin inf: no candidate map lay on B's other side")
    else:
        side = (f" (below {SIDE_DOUBT}: the mirror side fits about as well; check left from right: the map there is "
                "saved as correspondence_locate_other_side)" if pm.side_margin < SIDE_DOUBT else "")
        print(f"side margin {pm.side_margin:.3f}: how far this side of B was preferred to the mirror side{side}")
    if pm.scale != 1.0:
        print(f"scale: A's lengths times {pm.scale:.3g} are B's (--locate-scale {a.locate_scale})")
    reg = located_registration(ma, mb, pm)
    conf = f"confidence median {np.median(pm.confidence):.2f} ({np.mean(pm.confidence > 0.5):.0%} of A's vertices above 0.5)"
    if reg is None:
        print(f"located map: {conf}; no rigid fit of A onto its images (too few confident, non-collinear vertices)")
    else:
        over = f"over {reg.n_inliers} of {reg.n_pairs} vertices of A (the inliers)"
        print(f"located map: {conf}; rigid fit of A onto its images (at the scale locate used, {pm.scale:.3g}): "
              f"rms residual {reg.rms_text()} {over}, rotation {reg.rotation_degrees:.3g} degrees")
    return _Located(pm, reg)


def _locate_scale(value: str | None) -> str | float | None:
    """``--locate-scale`` as `LocateOptions.scale` takes it: "same", "fit" or a positive number (CliError else)."""
    if value is None or value in ("same", "fit"):
        return value
    try:
        s = float(value)
    except ValueError:
        s = float("nan")
    if not (np.isfinite(s) and s > 0):
        raise CliError(f"--locate-scale must be same, fit or a positive number, got {value!r}")
    return s


def _check_refinements(a: argparse.Namespace) -> None:
    """Refuse, in the CLI's words, the --zoomout and --locate settings that cannot go together."""
    if getattr(a, "locate_scale", None) is not None:
        if not getattr(a, "locate", False):
            raise CliError("--locate-scale sets the scale of --locate; add --locate, or drop --locate-scale")
        _locate_scale(a.locate_scale)
    if getattr(a, "locate_aligned", False) and not getattr(a, "locate", False):
        raise CliError("--locate-aligned tells --locate that A is in B's frame; add --locate, or drop "
                       "--locate-aligned")
    if getattr(a, "locate_landmarks", None) is not None and not getattr(a, "locate", False):
        raise CliError("--locate-landmarks gives --locate landmarks; add --locate, or drop --locate-landmarks")
    if getattr(a, "locate_edge", None) is not None and not getattr(a, "locate", False):
        raise CliError("--locate-edge sets the edge length of --locate; add --locate, or drop --locate-edge")
    w = getattr(a, "locate_orient_weight", None)
    if w is not None and not getattr(a, "locate", False):
        raise CliError("--locate-orient-weight sets how --locate tells left from right; add --locate, or drop "
                       "--locate-orient-weight")
    if w is not None and not (np.isfinite(w) and w >= 0):
        raise CliError(f"--locate-orient-weight must be a finite number >= 0, got {w:g}")
    if getattr(a, "locate_edge", None) == "whole" and a.signature != "ldsift":
        raise CliError(f"--locate-edge whole sets LD-SIFT's edge length; with --signature {a.signature} it would "
                       "change nothing: add --signature ldsift, or drop --locate-edge")
    if a.zoomout and getattr(a, "locate", False):
        raise CliError("--zoomout and --locate each give a refined correspondence; choose one (--zoomout for two "
                       "whole shapes, --locate for a part against a whole)")
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
    if a.pooling == "cell" and a.max_vertices is None and a.vertices_per_sample is None:
        raise CliError("--pooling cell averages the signatures over each sample's cell, and without --max-vertices or "
                       "--vertices-per-sample nothing is subsampled (every vertex is its own cell): give one of them, "
                       "or drop --pooling cell")
    return ComparisonConfig(
        signature=a.signature,
        signature_options=signature_options_from_args(a.signature, a),
        transport=a.transport,
        sampler=SamplerOptions(max_vertices=a.max_vertices, vertices_per_sample=a.vertices_per_sample,
                               pooling=a.pooling),
        mass_penalty=a.mass_penalty,
        method=a.ot_method,
        match_ratio=a.match_ratio if "match_ratio" in a else 0.9,
    )


def _add_progress(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--progress", dest="progress", action="store_true", default=None,
                   help="report each step with its time (bars for long loops) on stderr even when it is not a terminal")
    g.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress report (default: one on stderr when it is a terminal)")


def _formats() -> str:
    from wpot.io import MESH_FORMATS

    return ", ".join(MESH_FORMATS)


#: why `wpot compare` and `wpot all-vs-all` give the same pair different WKS distances (the compare epilog)
GRID_EPILOG = (
    "WKS compares two shapes energy by energy, on one energy grid (paper section 3.2); HKS likewise on one set of "
    "times. `wpot compare` fits that grid to the two shapes it compares; `wpot all-vs-all` fits one grid to its "
    "whole dataset, so that every pair is compared on the same energies. The same pair therefore gets a different "
    "distance inside a run than alone. The output and comparison.json say which grid was used; "
    "--energies-from RUN compares on a run's grid, and with the run's other settings gives the run's distance."
)


def _demo_parser(sub: Any) -> None:
    p = sub.add_parser("demo", help="compare the two generated example shapes and save a picture",
                       description="Compare two generated example shapes (one surface, triangulated twice, the second "
                                   "moved rigidly), score the correspondence against the known truth, save a picture.")
    p.add_argument("--out", default="wpot-demo", help="folder for the picture (default: ./wpot-demo)")
    p.add_argument("--n", type=int, default=DEMO["n"], help=f"vertices of the example shape (default {DEMO['n']})")
    _add_method_options(p, defaults={"n_eigen": DEMO["n_eigen"], "n_energies": DEMO["n_energies"]})
    _add_match_ratio(p)
    _add_zoomout(p)
    _add_progress(p)
    p.set_defaults(func=cmd_demo)


def _compare_parser(sub: Any) -> None:
    formats = _formats()
    p = sub.add_parser("compare", help="compare two mesh files", description="Compare two mesh files: distance, "
                       "correspondence, matched pairs and a fitted registration.", epilog=GRID_EPILOG)
    p.add_argument("mesh_a", help=f"the first shape, A: a mesh file ({formats})")
    p.add_argument("mesh_b", help="the second shape, B, in any of the same formats; the correspondence maps A's "
                                  "vertices to B's")
    p.add_argument("--out", default=None,
                   help="folder for comparison.json, correspondence.npz and correspondence.png (default: none, "
                        "nothing is saved); a folder that holds a comparison already is refused, unless --force")
    p.add_argument("--force", action="store_true",
                   help="overwrite the comparison the --out folder holds (default: refuse it)")
    p.add_argument("--energies-from", default=None, metavar="RUN",
                   help="compare on the WKS energy grid (HKS: times) stored in the all-vs-all run folder RUN instead "
                        "of one fitted to these two shapes; with the run's settings, the distance is the run's for "
                        "this pair (see below)")
    _add_method_options(p)
    _add_match_ratio(p)
    _add_zoomout(p)
    _add_locate(p)
    _add_progress(p)
    p.set_defaults(func=cmd_compare)


def _all_vs_all_parser(sub: Any) -> None:
    p = sub.add_parser("all-vs-all", help="compare every pair of a dataset into a resumable run folder",
                       description="Compare every pair of shapes of a dataset and store each pair as it finishes in a "
                                   "run folder (a SQLite store); rerunning the same command resumes.")
    p.add_argument("source", help=f"a folder of mesh files ({_formats()}), or a text file listing one mesh path per line "
                                  "(a relative path is relative to the list's folder; '#' starts a comment)")
    p.add_argument_group("required").add_argument(
        "--out", required=True, help="run folder (required; resumed if it holds the same run)")
    p.add_argument("--jobs", type=int, default=None,
                   help="worker processes (default: one; 0 = all cores); with --scheduler local, Dask workers (default: all "
                        "cores)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help='run the pairs on Dask: "local" (an embedded cluster of --jobs processes) or a running '
                   "scheduler tcp://HOST:PORT; each worker uses its own GPU when it has one "
                   "(needs pip install 'wpot[cluster]')")
    p.add_argument("--labels", default=None, help="label CSV: a 'name' column and one column per label level")
    _add_progress(p)
    _add_method_options(p)
    p.set_defaults(func=cmd_all_vs_all)


def _retrieve_parser(sub: Any) -> None:
    from wpot.signatures import add_signature_arguments, signature_names

    p = sub.add_parser("retrieve", help="rank the classes of a labelled library of whole shapes for a part",
                       description="Look a part up in a library of whole shapes: each vertex's cost to the nearest "
                       "signature of each whole, standardised over the library, a class scored as the union of its "
                       "--k-nearest nearest members (wpot.maps.retrieval). Prints the classes, best first. Set "
                       "WPOT_CACHE_DIR to keep the library's signatures between calls.")
    p.add_argument("part", help=f"the part: a mesh file ({_formats()})")
    p.add_argument("library", help="the whole shapes: a folder of mesh files, or a text file listing one mesh path "
                                   "per line (a relative path is relative to the list's folder; '#' starts a comment)")
    p.add_argument("--labels", default=None, help="label CSV: a 'name' column and one column per label level, the "
                   "first the class (default: each file name without its trailing digits, cat10 -> cat)")
    p.add_argument("--k-nearest", type=int, default=3,
                   help="a class is the union of this many of its members nearest to the part (default 3)")
    p.add_argument("--top", type=int, default=5, help="classes to print (default 5)")
    p.add_argument("--out", default=None,
                   help="JSON file for the whole ranking: classes, scores, the members that scored each class, "
                        "and every whole's mean cost (default: none)")
    p.add_argument("--calibration", default=None, metavar="JSON",
                   help="the library's own calibration of the printed probability: read from this file, or when it "
                        "does not exist yet, fitted on the library (--calibration-parts parts cut from its wholes, "
                        "each looked up among the others: a one-off of that many lookups, kept in JSON.lookups.jsonl "
                        "as they are made, so that a stopped calibration resumes) and saved there (default: the "
                        "shipped calibration, fitted on TOSCA)")
    p.add_argument("--calibration-parts", type=int, default=100,
                   help="parts that fit a new --calibration (default 100)")
    p.add_argument("--signature", choices=signature_names(), default="ldsift",
                   help="vertex signature (default: ldsift, without its thickness column)")
    add_signature_arguments(p)
    p.add_argument("--device", default=None, help='Warp device, e.g. "cpu" or "cuda:0" (default: Warp\'s default)')
    _add_progress(p)
    p.set_defaults(func=cmd_retrieve)


#: the positional argument of the commands that read a run
RUN_HELP = "an all-vs-all run folder (the --out of `wpot all-vs-all`)"


def _classify_parser(sub: Any) -> None:
    p = sub.add_parser("classify", help="1-NN classification from a run's distance matrix")
    p.add_argument("run", help=RUN_HELP)
    p.add_argument("--trials", type=int, default=10_000, help="one-shot trials (default 10,000, as Table 1)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the one-shot trials' random training shapes (default 0; the same seed gives the "
                        "same accuracy)")
    p.add_argument("--draws", type=int, default=0,
                   help="also score N random subsets of --per-class shapes per class (e.g. TOSCA8's 'six of each' "
                        "drawn from the full set), so that the accuracy does not hinge on one choice (default 0, none)")
    p.add_argument("--per-class", type=int, default=6,
                   help="shapes per class in each --draws subset (default 6, TOSCA8)")
    p.set_defaults(func=cmd_classify)


def _export_parser(sub: Any) -> None:
    p = sub.add_parser("export", help="write a run's distance matrix as CSV (names as header) or NPZ (with D(beta))")
    p.add_argument("run", help=RUN_HELP)
    p.add_argument("--out", default=None, help="a .csv or .npz file (default: RUN/distances.csv)")
    p.set_defaults(func=cmd_export)


def _report_parser(sub: Any) -> None:
    p = sub.add_parser("report", help="Markdown summary of one or more runs beside the paper's tables")
    p.add_argument("runs", nargs="+", metavar="run", help="one or more all-vs-all run folders, summarized side by side")
    p.add_argument("--out", default=None, help="Markdown file (default: RUN/report.md of the first run)")
    p.add_argument("--trials", type=int, default=10_000,
                   help="one-shot 1-NN trials per run, as `wpot classify --trials` (default 10,000, as Table 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the one-shot trials, as `wpot classify --seed` (default 0)")
    p.set_defaults(func=cmd_report)


#: each command's parser builder, in the order `wpot --help` lists them
COMMANDS = (_demo_parser, _compare_parser, _all_vs_all_parser, _retrieve_parser, _classify_parser, _export_parser,
            _report_parser)


def build_parser() -> argparse.ArgumentParser:
    from wpot import __version__

    parser = argparse.ArgumentParser(
        prog="wpot", description="Compare 3D shapes by statistical-physics optimal transport.",
        epilog=f"Mesh files: {_formats()} (by extension).")
    parser.add_argument("--version", action="version", version=f"wpot {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in COMMANDS:
        add(sub)
    return parser


# ------------------------------------------------------------------------------------------- messages
def flag_table() -> dict[str, str]:
    """The CLI flag of each library name: the comparison options' keywords (read from the flags
    `_add_method_options` adds, by their ``dest``), the signatures' keywords and field names (from their
    `option` metadata: ``hks_n_times`` and ``n_times`` both give ``--hks-n-times``), ``method`` for
    ``--ot-method`` and ``repair``. Names with no flag (``fps_metric``, ``ldsift_K``) are not in it."""
    import dataclasses

    from wpot.signatures import SIGNATURES

    p = argparse.ArgumentParser(add_help=False)
    _add_method_options(p)
    _add_match_ratio(p)
    table = {a.dest: a.option_strings[0] for a in p._actions if a.option_strings}
    table["method"] = table["ot_method"]
    for cls in SIGNATURES.values():
        for f in dataclasses.fields(cls.Options):
            flag = f.metadata.get("flag")
            if flag is not None:
                table.setdefault(f.metadata.get("keyword", f.name), flag)
                table.setdefault(f.name, flag)
    return table


def _switches() -> set[str]:
    """The flags that take no value (``--scale-invariant``, ``--repair``)."""
    p = argparse.ArgumentParser(add_help=False)
    _add_method_options(p)
    return {a.option_strings[0] for a in p._actions if a.option_strings and a.nargs == 0}


#: library advice with no keyword in it, and what the command offers instead
_PHRASES = (
    (r"\s*\(CLI --[\w-]+\)", ""),  # "pass scale_invariant=True (CLI --scale-invariant)": the flag is said already
    (r"Mesh\.cleaned\(keep_largest_component=True\)", "--largest-component"),
    (r"keep_largest_component=True", "--largest-component"),
    (r"(?<!wpot\.)Mesh\.cleaned\(\)", "--repair"),
    (r"`?(?<!wpot\.)Mesh\.cleaned`?(?!\()", "--repair"),
    (r" and returns the index map", ""),
    (r"another run folder", "another --out folder"),
    (r" or None, got", ", got"),
    (r"^unknown Warp device", "--device: unknown Warp device"),
)


def cli_words(message: str, table: Mapping[str, str] | None = None) -> str:
    """``message`` with the library's keywords replaced by the command's flags (`flag_table`).

    ``name=True`` of a switch becomes the flag, ``name=value`` becomes ``--flag value``; a keyword with an
    underscore (``max_vertices``) is replaced wherever it stands as a word; a one-word name (``transport``,
    ``slab``) only where it starts a sentence as the subject of a rule (``slab must be ...``), since elsewhere it
    is English (``balanced transport``).
    Advice to call ``Mesh.cleaned()`` becomes advice to pass ``--repair``."""
    table = flag_table() if table is None else table
    switches = _switches()
    for pattern, repl in _PHRASES:
        message = re.sub(pattern, repl, message)
    names = sorted(table, key=len, reverse=True)
    word = r"(?<![\w.\-'\"])({})(?![\w'\"])"

    def assigned(m: re.Match) -> str:
        flag, value = table[m.group(1)], m.group(2)
        if flag in switches:
            return flag if value == "True" else f"no {flag}"
        return f"{flag} {value.strip(chr(39))}"

    alternatives = "|".join(map(re.escape, names))
    message = re.sub(word.format(alternatives) + r"=('[^']*'|[^\s,;)]+)", assigned, message)
    message = re.sub(word.format("|".join(re.escape(n) for n in names if "_" in n)),
                     lambda m: table[m.group(1)], message)
    subject = r"(?:(?<=^)|(?<=[;.:] ))({})(?= must\b)"
    message = re.sub(subject.format(alternatives), lambda m: table[m.group(1)], message)
    return message


def _value_words(value: Any, flag: str | None, switches: set[str]) -> str:
    if flag in switches or isinstance(value, bool):
        return "on" if value else "off"
    if value is None:
        return "none"
    return str(value)


def _mismatch_words(exc: Any) -> str:
    """A `RunMismatchError` with settings that differ, worded with flags: only what differs, a setting with no
    flag by its Python keyword (it can only have been set from Python)."""
    table, switches = flag_table(), _switches()
    parts = []
    for key, stored, requested in exc.differences:
        if key == "repair" and "largest" in (stored, requested):  # two flags set this one setting
            said = {"largest": "--largest-component", True: "--repair alone", False: "neither"}
            parts.append(f"--repair/--largest-component: stored {said[stored]}, requested {said[requested]}")
            continue
        flag = table.get(key)
        name = flag if flag is not None else f"{key} (Python only, no flag)"
        parts.append(f"{name}: stored {_value_words(stored, flag, switches)}, "
                     f"requested {_value_words(requested, flag, switches)}")
    return (f"{exc.folder} holds a run with other settings: " + "; ".join(parts)
            + ". Use another --out folder, or rerun with the stored settings to resume.")


def progress_enabled(choice: bool | None, stream: TextIO) -> bool:
    """Whether the command reports progress: ``--progress``/``--no-progress`` when given (``choice``),
    else when ``stream`` is a terminal."""
    if choice is not None:
        return bool(choice)
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty()) if isatty is not None else False
    except (ValueError, OSError):  # a closed stream
        return False


def _progress(a: argparse.Namespace) -> Any:
    """The command's progress reporter (made once by `main`, which also prints warnings through it)."""
    return a.reporter


def _warning_printer(reporter: Any) -> Any:
    """A `warnings.showwarning` that prints each warning as one line in the command's words, on a line of its
    own even while a progress line is being written."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        reporter.break_line()
        out = sys.stderr if file is None else file
        out.write(f"wpot: warning: {' '.join(cli_words(str(message)).split())}\n")

    return show


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``wpot`` command; returns the exit code (0 success, 2 bad input; stopped by a signal: 128 + its
    number, 130 for Ctrl-C, 143 for SIGTERM, see `wpot.stopping`)."""
    from wpot.stopping import exit_code, stop_on_signals, stopped_message

    args = None
    try:
        with stop_on_signals() as stopping:  # from the start: building the parser takes a second or two
            from wpot.progress import Progress

            args = build_parser().parse_args(argv)
            args.reporter = Progress(enabled=progress_enabled(getattr(args, "progress", None), sys.stderr))
            if args.command == "all-vs-all":
                stopping.doing = "the stored pairs are kept, the pairs in flight dropped"
                stopping.after_hard_stop = "the stored pairs are kept; rerun the same command to resume the run"
            with warnings.catch_warnings():
                warnings.showwarning = _warning_printer(args.reporter)
                args.func(args)
    except KeyboardInterrupt as exc:  # the first Ctrl-C or SIGTERM (a second one exits at once)
        print(stopped_message(exc, getattr(args, "command", None)), file=sys.stderr)
        return exit_code(exc)
    except (CliError, OSError, ValueError) as exc:
        if os.environ.get("WPOT_DEBUG"):
            raise
        if getattr(exc, "differences", None) and getattr(exc, "folder", None):  # a RunMismatchError
            msg = _mismatch_words(exc)
        elif isinstance(exc, CliError):
            msg = str(exc)
        else:
            msg = cli_words(str(exc))
        msg = " ".join(msg.split()) or type(exc).__name__
        if isinstance(exc, FileNotFoundError) and exc.filename and str(exc.filename) not in msg:
            msg = f"{msg}: {exc.filename}"
        print(f"wpot: error: {msg}", file=sys.stderr)
        return 2
    return 0


# ------------------------------------------------------------------------------------------- commands
class _Loaded:
    """A mesh as the command uses it: read from ``path`` (and repaired with ``--repair``), with the map from its
    vertices to the file's (None when nothing was removed)."""

    def __init__(self, mesh: Any, path: str, index_map: np.ndarray | None = None, n_input: int | None = None) -> None:
        self.mesh, self.path, self.index_map = mesh, path, index_map
        self.n_input = mesh.n_vertices if n_input is None else n_input

    def from_input(self, vertices: np.ndarray) -> np.ndarray:
        """Indices of the file's vertices as indices of the used mesh (-1 for a vertex ``--repair`` removed)."""
        if self.index_map is None:
            return np.asarray(vertices)
        used = np.full(self.n_input, -1, dtype=np.int64)
        used[self.index_map] = np.arange(len(self.index_map))
        return used[np.asarray(vertices)]

    def to_input(self, vertices: np.ndarray) -> np.ndarray:
        """Vertex indices of the used mesh as indices of the file's vertices."""
        return np.asarray(vertices) if self.index_map is None else self.index_map[np.asarray(vertices)]


def _repair(a: argparse.Namespace) -> str:
    """The repair the flags ask for (`wpot.mesh.REPAIR_MODES`)."""
    return "largest" if a.largest_component else ("defects" if a.repair else "none")


def _repair_flag(mode: str) -> str:
    return "--largest-component" if mode == "largest" else "--repair"


def _repaired(mesh: Any, path: str, label: str, repair: str) -> _Loaded:
    """The mesh, repaired as ``repair`` (`_repair`) asks (printing what was removed from it)."""
    if repair == "none":
        return _Loaded(mesh, path)
    from wpot.mesh import repair_mesh

    fixed, index_map, removed = repair_mesh(mesh, repair)
    print(f"{_repair_flag(repair)} {label}: " + (f"removed {removed}" if removed else "nothing to repair"))
    if not removed:
        return _Loaded(mesh, path)
    return _Loaded(fixed, path, index_map, mesh.n_vertices)


def _load(path: str, label: str, repair: str = "none", *, folder: str = "give a mesh file") -> _Loaded:
    """The mesh file ``path`` read (and repaired); ``folder`` says what to do when ``path`` is a folder."""
    from wpot.io import load_mesh

    if Path(path).is_dir():
        raise CliError(f"{label}: {path} is a folder, not a mesh file; {folder}")
    if not Path(path).is_file():
        raise CliError(f"mesh file not found: {path}")
    return _repaired(load_mesh(path, warn=repair == "none"), path, label, repair)


def _summary_lines(c: Any, match_ratio: float) -> list[str]:
    sa, sb = getattr(c, "sample_a", None), getattr(c, "sample_b", None)
    n1, n2 = len(c.mass1), len(c.mass2)
    if sa is None and sb is None:
        points = "vertices"
        where = f"transport on every vertex: {n1} x {n2}"
    else:
        na = len(c.correspondence)
        nb = len(sb.nearest) if sb is not None else n2
        points = "samples"
        where = f"transport on {n1} x {n2} farthest-point samples of {na} x {nb} vertices"
    lines = [
        f"distance: {c.distance:.6g}  ({'U, Eq. 6' if c.transport == 'balanced' else 'SU, Eq. 27'}; "
        f"{signature_title(c.signature)}, {c.transport} transport)",
        where,
        _convergence_line(c.result),
        f"matched pairs (G > {match_ratio:g} m1): {len(c.matched)} of {n1} {points} of A",
    ]
    if c.registration is not None:
        r = c.registration
        over = f"over {r.n_inliers} of {r.n_pairs} pairs (the inliers)" if r.n_inliers != r.n_pairs else f"over {r.n_pairs} pairs"
        how = "the size ratio of the two shapes" if r.scale_from == "given" else "fitted"
        lines.append(f"registration: scale {r.scale:.4g} ({how}), rms residual {r.rms_text()} {over}, "
                     f"rotation {r.rotation_degrees:.3g} degrees")
    else:
        why = (f"with balanced transport a point of A (mass 1/{n1}) fits in one of B (mass 1/{n2}) only when "
               f"{n2} <= {n1}/{match_ratio:g}; use --transport partial, equal --max-vertices, or a lower --match-ratio"
               if c.transport == "balanced" and n2 > n1 / match_ratio else "lower --match-ratio, or try --transport partial")
        lines.append(f"registration: none, fewer than 3 non-collinear pairs matched ({why})")
    return lines


def _state_info(comparer: Any, run: str | None, n_run_shapes: int | None) -> dict[str, Any] | None:
    """What comparison.json records of the signature's fitted state (WKS's energy grid): the values, and
    whether they were fitted to this pair or read from a run. None for a signature with nothing to fit."""
    state = comparer.stage.state()
    if not comparer.stage.needs_fit or not state:
        return None
    return {"fitted_to": "this pair" if run is None else "run", "run": run,
            "n_shapes": 2 if run is None else n_run_shapes, **state}


def _state_lines(comparer: Any, info: dict[str, Any] | None) -> list[str]:
    """The printed account of the fitted state: which grid, and why it matters for the distance."""
    if info is None:
        return []
    title = comparer.stage.title
    desc = "; ".join(f"{len(info[k])} {'energies (log E)' if k == 'energies' else k} from {min(info[k]):.4g} to "
                     f"{max(info[k]):.4g}" for k in comparer.stage.state_keys)
    what = "energy grid" if "energies" in comparer.stage.state_keys else "grid"
    if info["fitted_to"] == "this pair":
        return [f"{title} {what}: fitted to this pair ({desc})",
                f"  (an all-vs-all run fits one {what} to its whole dataset, paper section 3.2, and so gives this pair "
                f"another distance; --energies-from RUN compares on that run's {what})"]
    return [f"{title} {what}: from the run {info['run']}, fitted to its {info['n_shapes']} shapes ({desc})"]


def _run_state(run: str, config: Any) -> tuple[dict[str, Any], int, list[str]]:
    """The signature state stored in the run folder ``run`` for ``config``'s signature, the run's shape count,
    and the settings (flag: run value, this value) that differ from the run's other than the signature's own,
    which must match: the grid was fitted for them."""
    import dataclasses

    from wpot.runs.store import RunStore, param_differences
    from wpot.signatures import get_signature

    sig = get_signature(config.signature)
    if not sig.needs_fit:
        raise CliError(f"--energies-from: {sig.title} has no fitted grid to take from a run (it is used as it is); "
                       "drop --energies-from")
    if not Path(run).is_dir():
        raise CliError(f"--energies-from: no such run folder: {run}")
    with RunStore(run) as store:
        state, params, n = store.signature_state(), store.params, store.n_shapes
    table, switches = flag_table(), _switches()
    own = {f.metadata.get("keyword", f.name) for f in dataclasses.fields(sig.Options)} | {"signature"}
    diffs = param_differences(params, config.run_key())
    words = [f"{table.get(k, k)}: the run's {_value_words(x, table.get(k), switches)}, here "
             f"{_value_words(y, table.get(k), switches)}" for k, x, y in diffs]
    mismatch = [w for (k, _, _), w in zip(diffs, words) if k in own]
    if mismatch:
        raise CliError(f"--energies-from {run}: its grid was fitted for other {sig.title} settings ("
                       + "; ".join(mismatch) + "); give the run's settings")
    if not state:
        raise CliError(f"--energies-from {run}: the run has not fitted its {sig.title} grid yet (rerun its all-vs-all)")
    return state, n, [w for (k, _, _), w in zip(diffs, words) if k not in own]


def _convergence_line(res: Any) -> str:
    """How the transport ended: the exact optimum with its certified gap, or the annealing's last beta."""
    if not np.isfinite(res.beta):
        # relative to what was minimized: U (balanced), U + the chi^2 penalty (partial, Eq. 17)
        of = "U" if res.objective == res.cost else "the objective, Eq. 17"
        gap = res.history[-1].gap_bound / abs(res.objective) if res.objective else res.history[-1].gap_bound
        return (f"converged: {bool(res.converged)}, the exact optimum (beta = inf; certified gap {gap:.1g} of {of}, "
                "over every entry)")
    return (f"converged: {bool(res.converged)} at beta {float(res.beta):.3g} ({int(res.n_newton)} Newton steps, "
            f"{int(res.n_linear)} linear iterations)")


def _json_beta(beta: float) -> float | None:
    """β for comparison.json: None (null) for the exact solver's β = ∞, which JSON cannot write."""
    beta = float(beta)
    return beta if np.isfinite(beta) else None


def _registration_json(r: Any) -> dict[str, Any] | None:
    """A `wpot.maps.registration.Registration` as comparison.json records it."""
    if r is None:
        return None
    return {"scale": r.scale, "rotation": r.rotation.tolist(), "translation": r.translation.tolist(), "rms": r.rms,
            "n_pairs": r.n_pairs, "n_inliers": r.n_inliers, "method": r.method, "scale_from": r.scale_from}


def _save_comparison(c: Any, a: _Loaded, b: _Loaded, out: Path, extra: dict[str, Any] | None = None,
                     refined: Any = None, located: _Located | None = None) -> list[Path]:
    """comparison.json, correspondence.npz (with ``correspondence_zoomout`` when ``refined``, a
    `wpot.maps.zoomout.ZoomOutResult`, is given, its orientation confidence in the json; and
    ``correspondence_locate``, ``confidence_locate``, ``region_locate`` when ``located`` (`_locate`) is, and
    ``correspondence_locate_other_side`` and ``correspondence_locate_other_place`` when its map has them,
    `PartMap.other_side` and `PartMap.other_place`) and
    correspondence.png (`_save_picture`).

    Vertex indices in the npz are those of the input files: with ``--repair`` a vertex of A that was removed
    maps to -1, and ``index_map_a`` / ``index_map_b`` give the file index of each vertex used."""
    out.mkdir(parents=True, exist_ok=True)
    info = {
        "distance": c.distance,
        "signature": c.signature,
        "transport": c.transport,
        "converged": bool(c.result.converged),
        "beta": _json_beta(c.result.beta),
        "n_matched": int(len(c.matched)),
        "n_points": [int(len(c.mass1)), int(len(c.mass2))],
        "n_vertices": [int(a.mesh.n_vertices), int(b.mesh.n_vertices)],
        "self_energies": c.self_energies,
        "history": [[_json_beta(b), float(d)] for b, d in c.history],
        "registration": _registration_json(c.registration),
        **(extra or {}),
    }
    if refined is not None:
        conf = refined.orientation_confidence
        info["zoomout_orientation_confidence"] = None if np.isnan(conf) else conf
        info["zoomout_mended"] = bool(refined.mended)
        info["zoomout_reanchored"] = bool(refined.reanchored)
    files = [out / "comparison.json", out / "correspondence.npz", out / "correspondence.png"]
    files[0].write_text(json.dumps(info, indent=2))

    def per_input(m, values: np.ndarray, fill) -> np.ndarray:
        """Per-vertex values of a (repaired) mesh, indexed by the input file's vertices (``fill`` where dropped)."""
        full = np.full(m.n_input, fill, dtype=np.asarray(values).dtype)
        full[m.to_input(np.arange(m.mesh.n_vertices))] = values
        return full

    def on_input(corr: np.ndarray) -> np.ndarray:
        return per_input(a, b.to_input(corr).astype(np.int64), -1)

    arrays = {} if refined is None else {"correspondence_zoomout": on_input(refined.map)}
    if located is not None:
        arrays.update(correspondence_locate=on_input(located.map.correspondence),
                      confidence_locate=per_input(a, located.map.confidence, np.nan),
                      region_locate=per_input(b, located.map.region(), False))
        for name in ("other_side", "other_place"):
            if getattr(located.map, name) is not None:
                arrays[f"correspondence_locate_{name}"] = on_input(getattr(located.map, name))
    for name, m in (("index_map_a", a), ("index_map_b", b)):
        if m.index_map is not None:
            arrays[name] = m.index_map
    matched = np.stack([a.to_input(c.matched[:, 0]), b.to_input(c.matched[:, 1])], axis=1) if len(c.matched) else c.matched
    np.savez(files[1], correspondence=on_input(c.correspondence), matched=matched, matched_weight=c.matched_weight,
             mass1=c.mass1, mass2=c.mass2, confidence=per_input(a, c.confidence, np.nan),
             region=per_input(b, c.region(), False), **arrays)
    _save_picture(c, a.mesh, b.mesh, files[2], None if refined is None else refined.map, located)
    return files


def picture_placement(c: Any, located: _Located | None) -> tuple[Any, str]:
    """The transform whose inverse draws B in A's pose in correspondence.png, and the picture's name for B: with
    ``--locate``, the fit to the located map that is drawn (`located_registration`), with its confidence; else the
    comparison's registration; (None, "B") when there is none."""
    if located is not None:
        conf = f"median confidence {np.median(located.map.confidence):.2f}"
        if located.registration is None:
            return None, f"B (no rigid fit to the located map; {conf})"
        return located.registration, f"B, moved onto A by the inverse of a rigid fit to the located map ({conf})"
    if c.registration is not None:
        return c.registration, "B, moved onto A by the inverse of the fitted registration"
    return None, "B"


def _save_picture(c: Any, ma: Any, mb: Any, path: Path, refined: np.ndarray | None, located: _Located | None) -> None:
    """correspondence.png: A coloured through the map that is reported (ZoomOut's, the located one, or the plan's),
    over B drawn in A's pose by the inverse of the transform that belongs to that map (`picture_placement`)."""
    from wpot.plot import plot_correspondence

    reg, title_b = picture_placement(c, located)
    if reg is not None:  # draw B in A's pose: undo the fitted similarity
        mb = reg.inverse().apply(mb)
    shown, what = (c.correspondence, "correspondence")
    if refined is not None:
        shown, what = refined, "ZoomOut correspondence"
    elif located is not None:
        shown, what = located.map.correspondence, "located correspondence"
    plot_correspondence(ma, mb, shown, titles=(f"A, coloured through the {what}", title_b), path=path)


def _check_out_folder(out: str | None) -> None:
    """--out names a folder: refuse a file there before any work, not after it."""
    if out is not None and Path(out).exists() and not Path(out).is_dir():
        raise CliError(f"--out {out} is a file; give a folder")


#: the files `wpot compare --out` writes
COMPARISON_FILES = ("comparison.json", "correspondence.npz", "correspondence.png")


def _check_comparison_out(out: str | None, force: bool) -> None:
    """--out of `wpot compare`: a folder, and one that holds no earlier comparison unless --force; before any work."""
    _check_out_folder(out)
    held = [name for name in COMPARISON_FILES if out is not None and (Path(out) / name).exists()]
    if held and not force:
        raise CliError(f"--out {out} already holds a comparison ({', '.join(held)}); give another --out folder, or "
                       "--force to overwrite it")


def _check_trials(a: argparse.Namespace) -> None:
    if a.trials < 1:
        raise CliError(f"--trials must be >= 1, got {a.trials}")
    if a.seed < 0:
        raise CliError(f"--seed must be >= 0, got {a.seed}")
    if getattr(a, "draws", 0) < 0:
        raise CliError(f"--draws must be >= 0, got {a.draws}")
    if getattr(a, "draws", 0) and a.per_class < 2:
        raise CliError(f"--per-class must be >= 2 (leave-one-out needs a same-class neighbour), got {a.per_class}")


def _check_size(m: _Loaded, config: Any, label: str) -> None:
    from wpot.comparison import check_mesh_size

    check_mesh_size(m.mesh, config, f"{label} ({m.path})")


def cmd_demo(a: argparse.Namespace) -> None:
    from wpot.comparison import Comparer
    from wpot.examples import example_pair
    from wpot.mesh import repair_setting

    t0 = time.perf_counter()
    config = config_from_args(a)
    _check_refinements(a)
    _check_out_folder(a.out)
    # equal vertex counts, so that a balanced plan can match vertex to vertex (G > 0.9 m1) and a
    # registration can be fitted
    try:
        pair = example_pair(a.n, seed=0, n_target=a.n)
    except ValueError as exc:  # "n must be an integer >= 50, ...": n is --n here
        raise CliError(re.sub(r"^n must", "--n must", str(exc))) from None
    repair = _repair(a)
    src = _repaired(pair.source, "example A", "A", repair)
    tgt = _repaired(pair.target, "example B", "B", repair)
    for m, label in ((src, "A"), (tgt, "B")):
        _check_size(m, config, label)
    comparer = Comparer(config, device=a.device, progress=_progress(a))
    c = comparer.compare(src.mesh, tgt.mesh)
    print(f"example shapes: {pair.source.n_vertices} vertices each (two triangulations of one surface, B rigidly moved)")
    print(f"settings: {config.describe()}")
    for line in _summary_lines(c, a.match_ratio):
        print(line)
    state = _state_info(comparer, None, None)
    for line in _state_lines(comparer, state):
        print(line)

    def median_error(corr: np.ndarray, label: str) -> float:
        """Ground truth: source vertex i is well matched when the target vertex it maps to samples a point of
        the surface near vertex i (in the source frame, in mean edge lengths). Prints and returns the median."""
        truth = pair.target_in_source_frame[tgt.to_input(corr)]
        err = np.linalg.norm(truth - pair.source.vertices[src.to_input(np.arange(src.mesh.n_vertices))], axis=1)
        err = err / pair.source.mean_edge_length
        print(f"{label}: median {np.median(err):.2f} mean edge lengths, "
              f"{100 * np.mean(err <= 2):.0f}% of vertices within 2 edge lengths")
        return float(np.median(err))

    extra = {"median_error_edge_lengths": median_error(c.correspondence, "correspondence error vs ground truth"),
             "signature_state": state, "repair": repair_setting(repair)}
    refined = _zoomout(a, src.mesh, tgt.mesh, c)
    if refined is not None:
        extra["median_error_edge_lengths_zoomout"] = median_error(refined.map, "after ZoomOut")
    files = _save_comparison(c, src, tgt, Path(a.out), extra, refined=refined)
    if c.registration is not None:
        rel = c.registration.rotation @ pair.rotation.T
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0))))
        print(f"registration vs the true rigid motion of B: rotation off by {angle:.1f} degrees, "
              f"scale {c.registration.scale:.3f} (true 1)")
    print(f"saved {files[2]} ({time.perf_counter() - t0:.1f} s)")


def cmd_compare(a: argparse.Namespace) -> None:
    from wpot.comparison import Comparer
    from wpot.mesh import repair_setting

    config = config_from_args(a)  # option errors before any file is read
    _check_refinements(a)
    _check_comparison_out(a.out, a.force)
    state, n_run, other = None, None, []
    if a.energies_from is not None:
        state, n_run, other = _run_state(a.energies_from, config)
    repair = _repair(a)
    pair = ("compare takes two mesh files (`wpot all-vs-all FOLDER --out RUN` compares every pair of a folder's "
            "shapes)")
    ma, mb = _load(a.mesh_a, "A", repair, folder=pair), _load(a.mesh_b, "B", repair, folder=pair)
    marks = _landmarks(getattr(a, "locate_landmarks", None), ma, mb)  # read before the comparison, to fail early
    for m, label in ((ma, "A"), (mb, "B")):
        _check_size(m, config, label)
    comparer = Comparer(config, device=a.device, signature_state=state, progress=_progress(a))
    c = comparer.compare(ma.mesh, mb.mesh)
    def size(m: _Loaded) -> str:
        return (f"{m.mesh.n_vertices} vertices" if m.index_map is None
                else f"{m.mesh.n_vertices} of its {m.n_input} vertices after {_repair_flag(repair)}")

    print(f"A: {a.mesh_a} ({size(ma)})   B: {a.mesh_b} ({size(mb)})")
    print(f"settings: {config.describe()}")
    for line in _summary_lines(c, a.match_ratio):
        print(line)
    info = _state_info(comparer, a.energies_from, n_run)
    for line in _state_lines(comparer, info):
        print(line)
    if other:
        print(f"  (other settings than the run's: {'; '.join(other)}; so this is not the run's distance for the pair)")
    refined = _zoomout(a, ma.mesh, mb.mesh, c)
    located = _locate(a, comparer, ma.mesh, mb.mesh, marks)
    if a.out:
        extra = {"mesh_a": str(a.mesh_a), "mesh_b": str(a.mesh_b), "zoomout": bool(a.zoomout),
                 "settings": config.describe(), "signature_state": info, "repair": repair_setting(repair)}
        if located is not None:
            pm = located.map
            extra["locate"] = {**pm.summary(), "registration": _registration_json(located.registration),
                               "landmarks": 0 if marks is None else len(marks)}
        files = _save_comparison(c, ma, mb, Path(a.out), extra, refined=refined, located=located)
        print("saved " + ", ".join(str(f) for f in files))


def _check_dataset(source: str, labels: str | None) -> None:
    """A dataset's folder or list file, and its label CSV when one is given, exist."""
    if labels is not None and not Path(labels).is_file():
        raise CliError(f"label CSV not found: {labels}")
    if not Path(source).exists():
        raise CliError(f"no such folder or list file: {source}")


def cmd_all_vs_all(a: argparse.Namespace) -> None:
    from wpot.runs.loop import run_all_vs_all

    if a.jobs is not None and a.jobs < 0:
        raise CliError(f"--jobs must be >= 0, got {a.jobs}")
    if a.scheduler is not None:
        if a.scheduler != "local" and "://" not in a.scheduler:
            raise CliError(f'--scheduler must be "local" or a Dask address like tcp://HOST:8786, got {a.scheduler!r}')
        if a.scheduler != "local" and a.jobs is not None:
            raise CliError(f"--jobs sets local processes; a running cluster ({a.scheduler}) has the workers it was started with")
    jobs = (1 if a.scheduler is None else 0) if a.jobs is None else a.jobs
    _check_dataset(a.source, a.labels)
    t0 = time.perf_counter()
    config = config_from_args(a)
    repair = _repair(a)
    try:
        store = run_all_vs_all(
            a.source, a.out, jobs=(jobs or None), scheduler=a.scheduler, labels=a.labels,
            progress=_progress(a), config=config, device=a.device, repair=repair,
        )
    except ImportError as exc:
        if a.scheduler is None:
            raise
        raise CliError(str(exc)) from exc
    with store:
        total, done = len(store.tasks()), len(store.done())
        fails = store.failures()
        conv = sum(1 for r in store.pair_rows() if r["converged"])
        repairs = store.get("repairs") or {}
    if repair != "none":
        print(f"{_repair_flag(repair)}: " + ("; ".join(f"{name}: removed {what}" for name, what in repairs.items())
                              if repairs else "nothing to repair"))
    print(f"{done} of {total} pairs in {a.out} ({conv} converged), {time.perf_counter() - t0:.1f} s this session")
    if fails:
        raise CliError(f"{len(fails)} pairs failed (first: pair {fails[0][:2]}: {cli_words(fails[0][2])}); "
                       "rerun to retry them")


def cmd_retrieve(a: argparse.Namespace) -> None:
    from wpot.comparison import Comparer
    from wpot.config import ComparisonConfig
    from wpot.datasets import MESH_EXTENSIONS, list_shapes
    from wpot.io import load_mesh
    from wpot.runs.shapes import read_mesh_list
    from wpot.maps.retrieval import CALIBRATED_THICKNESS, MARGIN_DOUBT, RetrievalOptions
    from wpot.signatures import signature_options_from_args

    if a.k_nearest < 1:
        raise CliError(f"--k-nearest must be at least 1, got {a.k_nearest}")
    if a.top < 1:
        raise CliError(f"--top must be at least 1, got {a.top}")
    _check_dataset(a.library, a.labels)
    lib = Path(a.library)
    if lib.suffix.lower() in MESH_EXTENSIONS:
        raise CliError(f"the library must be a folder of meshes or a list of them, got the single mesh {a.library}")
    shapes = list_shapes(lib if lib.is_dir() else read_mesh_list(lib), labels=a.labels)
    classes = sorted(set(map(str, shapes.labels["class"])))
    if len(classes) < 2:
        raise CliError(f"the library {a.library} holds one class ({classes[0]!r}; classes come from the file names "
                       "or --labels): a part's class can only be looked up among two or more")
    part = _load(a.part, "part", folder="the part is one mesh file (the library, a folder, comes second)").mesh
    config = ComparisonConfig(signature=a.signature, signature_options=signature_options_from_args(a.signature, a))
    reporter = _progress(a)
    comparer = Comparer(config, device=a.device, progress=reporter)
    bar = reporter.bar(len(shapes.paths), "reading meshes", "mesh")
    wholes = []
    try:
        for path in shapes.paths:
            wholes.append(load_mesh(path))
            bar.update()
    finally:
        bar.close()
    if comparer.stage.needs_fit:
        comparer.fit(wholes)
    options = RetrievalOptions(k_nearest=a.k_nearest)
    calibration = _retrieval_calibration(a, comparer, wholes, list(shapes.labels["class"]), options)
    r = comparer.retrieve(part, wholes, list(shapes.labels["class"]), options=options, calibration=calibration)
    from wpot.comparison import at_common_edge

    edge = getattr(at_common_edge(comparer, wholes).config.signature_options, "edge", None)  # what retrieve used
    at = "" if edge is None else f", at one edge length for the part and the library, {edge:.3g}"
    print(f"{a.part} against {len(wholes)} wholes of {len(r.classes)} classes ({signature_title(a.signature)}{at}):")
    for k, (cls, score, members) in enumerate(zip(r.classes, r.scores, r.members)):
        if k == a.top:
            break
        print(f"  {k + 1}. {cls}  score {score:.4g}  nearest {shapes.names[members[0]]}")
    if len(r.classes) > 1:
        whose = "the library's own calibration" if calibration is not None else "the shipped calibration"
        chance = (f"; probability that {r.label} is right {r.probability:.2f} ({whose})" if r.calibrated else
                  f" (under {MARGIN_DOUBT}: doubtful; the shipped probability is calibrated only for the default "
                  f"--k-nearest and --signature ldsift with --ldsift-thickness {CALIBRATED_THICKNESS:g}: fit the "
                  "library's own with --calibration)")
        print(f"margin {r.margin:.3g}: the second class's score less the first's{chance}")
    if a.out:
        out = {"part": str(a.part), "library": str(a.library), "k_nearest": a.k_nearest, "signature": a.signature,
               "ldsift_edge": edge,
               "classes": list(r.classes), "scores": [float(x) for x in r.scores], "margin": r.margin,
               "probability": None if np.isnan(r.probability) else r.probability,
               "calibration": None if not r.calibrated else (a.calibration or "shipped"),
               "members": [[shapes.names[j] for j in m] for m in r.members],
               "whole_costs": {n: float(c) for n, c in zip(shapes.names, r.whole_costs)}}
        Path(a.out).write_text(json.dumps(out, indent=1))
        print(f"saved {a.out}")


def _retrieval_calibration(a: argparse.Namespace, comparer: Any, wholes: list, labels: list, options: Any) -> Any:
    """`wpot retrieve --calibration`: None without it; else the calibration read from its file, or fitted on the
    library and saved there."""
    from wpot.comparison import calibration_differences
    from wpot.maps.retrieval import RetrievalCalibration, library_digest

    if a.calibration is None:
        return None
    path = Path(a.calibration)
    if path.exists():
        try:
            cal = RetrievalCalibration.from_json(path.read_text())
        except (ValueError, OSError, UnicodeDecodeError) as e:
            raise CliError(f"--calibration {a.calibration}: {e}") from None
        differ = calibration_differences(cal, comparer.config, options)
        if differ:
            raise CliError(f"--calibration {a.calibration} was fitted with other settings than these (--k-nearest, "
                           f"--signature and its options): {'; '.join(differ)}. Fit one for these settings under "
                           "another file name")
        if cal.library and cal.library != library_digest(wholes, labels):
            raise CliError(f"--calibration {a.calibration} was fitted on another library (its meshes or classes "
                           f"differ from {a.library}'s): delete it, or name another file, to fit one for this library")
        return cal
    if a.calibration_parts < 1:
        raise CliError(f"--calibration-parts must be at least 1, got {a.calibration_parts}")
    record = path.with_name(path.name + ".lookups.jsonl")  # a stopped calibration resumes from it
    try:
        cal = comparer.calibrate_retrieval(wholes, labels, n_parts=a.calibration_parts, options=options,
                                           record=record)
    except ValueError as e:
        raise CliError(f"--calibration: cannot calibrate on the library {a.library}: {e}") from None
    path.write_text(cal.to_json())
    record.unlink()
    print(f"calibrated on the library: {cal.n_right} of {cal.n_parts} parts cut from its wholes were looked up "
          f"right; saved {a.calibration}")
    return cal


def cmd_classify(a: argparse.Namespace) -> None:
    from wpot.evaluate import format_percent
    from wpot.runs.shapes import warn_repeated_shapes
    from wpot.runs.store import RunStore
    from wpot.paper.table1 import PAPER_TABLE1
    from wpot.runs.report import classify_run, confusions, loo_scores, loo_text, misses_text

    _check_trials(a)
    with RunStore(a.run) as store:
        rows = store.shape_rows()
        warn_repeated_shapes([r[1] for r in rows], [r[3] for r in rows])
        r = classify_run(store, trials=a.trials, seed=a.seed)
        p = store.params
        draws = None
        if a.draws:
            from wpot.evaluate import classification_draws

            labels = np.array(store.labels("class"), dtype=object)
            counts = {c: int((labels == c).sum()) for c in sorted(set(labels))}
            short = {c: n for c, n in counts.items() if n < a.per_class}
            if short:
                raise CliError(f"--per-class {a.per_class}: these classes of the run have fewer shapes: {short}")
            draws = classification_draws(store.distance_matrix(), labels.astype(str), per_class=a.per_class,
                                         n_draws=a.draws, seed=a.seed, n_trials=min(a.trials, 1000))
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
        print(loo_text(lv, res, r["levels"][lv]))
        if r["loo_misses"][lv]:
            print("  wrong: " + misses_text(r["loo_misses"][lv]))
    if r["per_beta"]:
        print("one-shot 1-NN from D(β): " + ", ".join(f"β={b:.0e} {format_percent(acc)}" for b, acc in r["per_beta"]))
    if draws is not None:
        print(f"over {draws.n_draws} random draws of {draws.per_class} shapes per class: one-shot "
              f"{format_percent(draws.one_shot_mean)} (std over draws {100 * draws.one_shot_std:.1f}), leave-one-out "
              f"{format_percent(draws.leave_one_out_mean)} (std {100 * draws.leave_one_out_std:.1f})")
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
        # None at a level whose shapes are all in one group: nothing to tell apart, no result
        "leave_one_out": {lv: res.accuracy if res.n_groups > 1 else None for lv, res in r["loo"].items()},
        "leave_one_out_without_one_shape_groups": {lv: loo_scores(res, r["levels"][lv])["without"]
                                                   for lv, res in r["loo"].items()},
        "leave_one_out_wrong": r["loo_misses"],
        "one_shot_per_beta": r["per_beta"],
        "draws": None if draws is None else {
            "n_draws": draws.n_draws, "per_class": draws.per_class, "seed": draws.seed,
            "one_shot": draws.one_shot.tolist(), "leave_one_out": draws.leave_one_out.tolist()},
    }, indent=2))


def cmd_export(a: argparse.Namespace) -> None:
    from wpot.runs.store import RunStore
    from wpot.runs.report import pair_counts

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
    from wpot.runs.report import build_report

    _check_trials(a)
    out = build_report(a.runs, a.out, trials=a.trials, seed=a.seed)
    print(out.read_text())
    print(f"saved {out}")


if __name__ == "__main__":
    sys.exit(main())
