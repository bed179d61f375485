"""Part retrieval on a HEAD dataset from `wpot all-vs-all` runs (paper §4.2, Fig. 7; issue 20's HEAD on TOSCA8).

For each run folder (an all-vs-all over a HEAD dataset folder written by `wpot.paper.head.build_head_dataset`,
e.g. the paper's own HEAD from TOSCA's low-resolution shapes), it prints, from the run's D(∞) matrix:
whether each head's nearest full shape is its parent (the paper: LD-SIFT partial "identifies the correct head
for each cat and each horse") and of its species, the share of heads whose parent is among the two nearest,
and the leave-one-out class accuracy over all 24 shapes (cat, cat_head, horse, horse_head). The heatmaps
are `wpot report RUN...`'s.

    python benchmarks/head_retrieval.py DATASET RUN [RUN ...]

    # building the paper's HEAD and its four runs:
    python -c "from wpot.paper.head import build_head_dataset; build_head_dataset('../shared/data/tosca_isometric_5k', 'head8', \\
        lowres='../shared/data/tosca_lowres', per_class=6)"
    wpot all-vs-all head8 --labels head8/labels.csv --pooling cell --vertices-per-sample 20 \\
        --signature ldsift --transport partial --out runs/ld_par      # and wks / balanced
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, help="the HEAD dataset folder (manifest.json, labels.csv)")
    ap.add_argument("runs", type=Path, nargs="+", help="wpot all-vs-all run folders over that dataset")
    a = ap.parse_args()
    import json

    from wpot.datasets import read_label_csv
    from wpot.evaluate import leave_one_out_1nn, part_retrieval
    from wpot.runs.store import RunStore

    manifest = json.loads((a.dataset / "manifest.json").read_text())
    parent = manifest["parent"]
    table = read_label_csv(a.dataset / "labels.csv")
    print("| run | settings | head's nearest full shape is its parent | ... of its species | parent among the two "
          "nearest | LOO 1-NN (4 groups) | heads whose nearest is not the parent |")
    print("|---|---|---|---|---|---|---|")
    for run in a.runs:
        with RunStore(run) as store:
            names = store.names
            D = store.distance_matrix()
            cfg = store.get("params") or {}
        settings = ", ".join(f"{k} {cfg[k]}" for k in ("signature", "transport") if k in cfg) or "-"
        lab = table.for_names(names)
        species, cls = lab["species"], lab["class"]
        pr = part_retrieval(D, names, species, parent)
        pos = {n: k for k, n in enumerate(names)}
        full = np.array([k for k, n in enumerate(names) if n not in parent])
        top2 = np.mean([pos[p] in full[np.argsort(D[pos[h], full])[:2]] for h, p in parent.items()])
        loo = leave_one_out_1nn(D, cls).accuracy
        wrong = [f"{h}->{pr.nearest[h]}" for h, p in parent.items() if pr.nearest[h] != p]
        print(f"| {run.name} | {settings} | {100 * pr.parent_accuracy:.0f} % | {100 * pr.class_accuracy:.0f} % | "
              f"{100 * top2:.0f} % | {100 * loo:.1f} % | {', '.join(wrong) or '-'} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
