"""Reading a finished all-vs-all run: 1-NN classification (paper Table 1, Tables 2–4) and the Markdown report.

`classify_run` scores a run's distance matrices (D(∞), and D(β) at every power of ten of β); `build_report`
writes one or more runs beside the paper's Table 1, with figures. The ``wpot classify`` and ``wpot report``
commands print and save what these return.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from wpot.paper.table1 import PAPER_TABLE1
from wpot.evaluate import format_percent, leave_one_out_levels, one_shot_1nn
from wpot.plot import class_order, plot_confusion, plot_distance_matrix
from wpot.runs.store import RunStore
from wpot.signatures import SIGNATURES

__all__ = ["RunNotReadyError", "build_report", "classify_run", "confusions", "loo_misses", "loo_scores",
           "loo_text", "misses_text", "pair_counts", "signature_title"]

class RunNotReadyError(ValueError):
    """A run cannot be classified yet: pairs are missing, or its shapes have no class labels."""


def signature_title(name: str | None) -> str:
    """The printed name of a registered signature ("WKS", "LD-SIFT"); the name itself if it is not registered."""

    sig = SIGNATURES.get(name)
    return sig.title if sig is not None else str(name)


def confusions(one: Any, *, top: int = 3) -> list[str]:
    """One entry per class whose one-shot accuracy is below 100 %: its accuracy, then the (at most ``top``)
    classes it was taken for most often."""

    out = []
    for a, cls in enumerate(one.classes):
        row = one.confusion[a]
        if not np.isfinite(row).all() or row[a] >= 1.0:
            continue
        wrong = sorted(((row[b], one.classes[b]) for b in range(len(row)) if b != a and row[b] > 0), reverse=True)[:top]
        out.append(f"{cls} {format_percent(row[a])}" + (" (taken for " + ", ".join(f"{c} {format_percent(v)}" for v, c in wrong) + ")" if wrong else ""))
    return out


def loo_misses(names: Sequence[str], res: Any, labels: np.ndarray) -> list[dict[str, Any]]:
    """The shapes that leave-one-out 1-NN gets wrong (score < 1; a tie may give part credit), each with its
    nearest other shape."""
    return [{"shape": names[i], "label": str(labels[i]), "nearest": names[res.nearest[i]],
             "nearest_label": str(labels[res.nearest[i]]), "score": float(res.score[i])}
            for i in np.nonzero(res.score < 1)[0]]


def loo_scores(res: Any, labels: np.ndarray) -> dict[str, Any]:
    """What a leave-one-out accuracy (`wpot.evaluate.LeaveOneOut`) at one label level means: ``scored`` is False
    when every shape is in one group (each nearest shape then has the query's label: 100 % that says nothing);
    ``one_member`` lists the groups of a single shape, which leave-one-out cannot get right (no other member to
    find), and ``without`` is the accuracy over the other shapes (None when there are no such groups, or no
    other shapes)."""
    labels = np.asarray(labels, dtype=str)
    groups, counts = np.unique(labels, return_counts=True)
    one = [str(g) for g, k in zip(groups, counts) if k == 1]
    keep = ~np.isin(labels, one)
    without = float(res.score[keep].mean()) if one and keep.any() else None
    return {"accuracy": float(res.accuracy), "n_groups": int(res.n_groups), "scored": int(res.n_groups) > 1,
            "one_member": one, "without": without}


def loo_text(level: str, res: Any, labels: np.ndarray) -> str:
    """The line `wpot classify` prints for leave-one-out 1-NN at ``level`` (`loo_scores`)."""
    s = loo_scores(res, labels)
    n = len(labels)
    if not s["scored"]:
        return (f"leave-one-out 1-NN at level {level!r}: not scored, all {n} shapes are in one group ({labels[0]}), "
                "so every shape's nearest has its label")
    line = f"leave-one-out 1-NN at level {level!r} ({s['n_groups']} groups): {format_percent(s['accuracy'])}"
    if s["one_member"]:
        k = len(s["one_member"])
        which = ", ".join(s["one_member"][:8]) + (f" and {k - 8} more" if k > 8 else "")
        without = "n/a" if s["without"] is None else format_percent(s["without"])
        line += (f"; {without} without the {k} group{'s' if k > 1 else ''} of one shape ({which}), which "
                 "leave-one-out cannot get right: no other member to find")
    return line


def misses_text(misses: Sequence[Mapping[str, Any]], *, limit: int = 12) -> str:
    """"shape (label) -> nearest (label)" for the first ``limit`` misses, then how many more."""
    text = "; ".join(f"{m['shape']} ({m['label']}) -> {m['nearest']} ({m['nearest_label']})" for m in misses[:limit])
    return text + (f"; and {len(misses) - limit} more" if len(misses) > limit else "")


def _levels(store) -> dict[str, np.ndarray]:
    out = {}
    for lv in store.label_levels():
        lab = store.labels(lv)
        if all(x is not None for x in lab):
            out[lv] = np.asarray(lab, dtype=str)
    return out


def pair_counts(store) -> tuple[np.ndarray, int, int]:
    """D(∞), and how many of its pairs i < j are missing and how many stored ones did not converge."""
    d, conv = store.distance_matrix(), store.converged_matrix()
    upper = np.triu(np.ones(d.shape, dtype=bool), k=1)
    missing = np.isnan(d) & upper
    return d, int(missing.sum()), int((~conv & ~missing & upper).sum())


def classify_run(store, *, trials: int = 10_000, seed: int = 0) -> dict[str, Any]:
    """Table 1's one-shot 1-NN (level "class") and leave-one-out 1-NN at every label level, from D(∞),
    plus the one-shot accuracy from D(β) at every power of ten of β where every pair has a value."""

    d, missing, not_converged = pair_counts(store)
    off = ~np.eye(len(d), dtype=bool)
    if missing:
        raise RunNotReadyError(f"the run in {store.folder} is incomplete ({missing} pairs missing); finish it with the same all-vs-all command")
    levels = _levels(store)
    if "class" not in levels:
        raise RunNotReadyError(f"the run in {store.folder} has no class labels; give --labels CSV to all-vs-all")
    one = one_shot_1nn(d, levels["class"], n_trials=trials, seed=seed)
    loo = leave_one_out_levels(d, levels)
    betas, dbeta = store.distance_matrices("decades")
    per_beta = []
    for b, db in zip(betas, dbeta):
        if np.isnan(db[off]).any():
            continue
        per_beta.append((float(b), one_shot_1nn(db, levels["class"], n_trials=min(trials, 1000), seed=seed).mean))
    misses = {lv: loo_misses(store.names, res, levels[lv]) for lv, res in loo.items()}
    return {"one_shot": one, "loo": loo, "loo_misses": misses, "per_beta": per_beta, "levels": levels,
            "not_converged": not_converged}



def _loo_cells(res: Any, labels: np.ndarray) -> str:
    """The measure's tail and the "ours" cell of a leave-one-out row of the report's table (`loo_scores`)."""
    s = loo_scores(res, labels)
    if not s["scored"]:
        return "(one group) | not scored: every shape is in one group"
    cell = format_percent(s["accuracy"])
    if s["one_member"]:
        k = len(s["one_member"])
        without = "n/a" if s["without"] is None else format_percent(s["without"])
        cell += f" ({without} without the {k} group{'s' if k > 1 else ''} of one shape, which it cannot get right)"
    return f"({s['n_groups']} groups) | {cell}"


def build_report(runs: Sequence[str | Path], out: str | Path | None = None, *, trials: int = 10_000, seed: int = 0) -> Path:
    """Write a Markdown report of one or more runs beside the paper's Table 1, with a distance-matrix and a
    confusion figure per run; returns the path written (default: ``report.md`` in the first run's folder)."""

    sections: list[str] = []
    table1: dict[tuple[str, str], float] = {}
    out = Path(out) if out else Path(runs[0]) / "report.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    for run in runs:
        with RunStore(run) as store:
            p = store.params
            rows = store.pair_rows()
            total = len(store.tasks())
            key = (p.get("signature"), p.get("transport"))
            lines = [f"## Run `{run}`", ""]
            lines.append(f"- method: {signature_title(key[0])}, {key[1]} transport")
            lines.append(f"- parameters: `{json.dumps(p, sort_keys=True)}`")
            lines.append(f"- shapes: {store.n_shapes}; pairs done: {len(rows)} of {total}; "
                         f"converged: {sum(r['converged'] for r in rows)}; failures: {len(store.failures())}")
            names = store.names
            bad = [f"{names[r['i']]}–{names[r['j']]}" for r in rows if not r["converged"]]
            if bad:
                lines.append(f"- not converged ({len(bad)}; their distances may be wrong): " + ", ".join(bad[:30])
                             + (f", and {len(bad) - 30} more" if len(bad) > 30 else ""))
            secs = [r["seconds"] for r in rows if r["seconds"] is not None]
            if secs:
                lines.append(f"- solve time per pair: mean {np.mean(secs):.2f} s, median {np.median(secs):.2f} s, "
                             f"max {np.max(secs):.2f} s (wall clock in the workers)")
            try:
                r = classify_run(store, trials=trials, seed=seed)
            except RunNotReadyError as exc:
                lines += ["", f"Classification not available: {exc}", ""]
                sections.append("\n".join(lines))
                continue
            one = r["one_shot"]
            table1[key] = one.mean
            paper = PAPER_TABLE1.get(key)
            lines += ["", "| measure | ours | paper |", "|---|---|---|"]
            lines.append(f"| 1-NN, one training shape per class ({one.n_trials} trials) | {format_percent(one.mean)} "
                         f"| {f'{paper:.1f}% (Table 1, TOSCA8)' if paper is not None else 'n/a'} |")
            for lv, res in r["loo"].items():
                lines.append(f"| leave-one-out 1-NN, level `{lv}` {_loo_cells(res, r['levels'][lv])} | "
                             "Tables 2-4 (anatomical data) |")
            conf = confusions(one)
            lines += ["", "One-shot classes below 100 % (and what they were taken for): "
                      + ("; ".join(conf) if conf else "none.")]
            for lv, misses in r["loo_misses"].items():
                if misses:
                    lines += ["", f"Leave-one-out at level `{lv}` gets wrong: " + misses_text(misses)]
            if r["per_beta"]:
                lines += ["", "One-shot 1-NN accuracy from D(β) at each power of ten of β (D(∞) above):", "", "| β | accuracy |", "|---|---|"]
                lines += [f"| {b:.3g} | {format_percent(acc)} |" for b, acc in r["per_beta"]]
            fig_path = Path(run) / "distance_matrix.png"
            classes = class_order(r["levels"]["class"])[1]  # one class order in both figures
            plot_distance_matrix(store.distance_matrix(), r["levels"]["class"], names=names, classes=classes,
                                 title=f"D(inf): {key[0]}, {key[1]}", path=fig_path)
            conf_path = Path(run) / "confusion.png"
            plot_confusion(one, classes=classes, title=f"one-shot 1-NN (%): {key[0]}, {key[1]}", path=conf_path)
            lines += ["", f"![distance matrix]({os.path.relpath(fig_path.resolve(), out.parent.resolve())}) "
                      f"![one-shot confusion]({os.path.relpath(conf_path.resolve(), out.parent.resolve())})", ""]
            sections.append("\n".join(lines))
    head = ["# wpot report", "", "## Table 1: 1-NN success rate (%), one random training shape per class", "",
            "| | LD-SIFT (ours) | LD-SIFT (paper) | WKS (ours) | WKS (paper) |", "|---|---|---|---|---|"]
    for tr, name in (("balanced", "OT (balanced)"), ("partial", "OT (partial)")):
        cells = []
        for sig in ("ldsift", "wks"):
            ours = table1.get((sig, tr))
            cells += ["—" if ours is None else format_percent(ours)[:-1], f"{PAPER_TABLE1[(sig, tr)]:.1f}"]
        head.append(f"| {name} | " + " | ".join(cells) + " |")
    head += ["", "The paper's numbers are on TOSCA8 (48 shapes at ~3,400 vertices); ours are on the runs below.", ""]
    text = "\n".join(head + sections) + "\n"
    out.write_text(text)
    return out


