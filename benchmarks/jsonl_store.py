"""A resumable, append-only result store for the benchmarks (`correspondence.py`, `partial_poses.py`).

``pairs.jsonl`` holds one JSON record per computed item, and ``<folder>/<method>/<a>__<b>.npz`` its arrays;
a record is appended only after its npz is in place (written to a temporary name, then renamed), so every
recorded item is complete, and a line cut by a kill is skipped on reading (that item is computed again).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


class JsonlStore:
    """Records keyed by ``(rec["method"], rec[keys[0]], rec[keys[1]])``, arrays under ``out / folder``."""

    def __init__(self, out: Path, *, keys: tuple[str, str], folder: str) -> None:
        self.out = out
        self.keys = keys
        self.folder = folder
        self.path = out / "pairs.jsonl"
        self.records: list[dict] = []
        if self.path.is_file():
            for line in self.path.read_text().splitlines():
                if line.strip():
                    try:
                        self.records.append(json.loads(line))
                    except json.JSONDecodeError:  # a line cut by a kill: that item is redone
                        pass
        self.done = {self._key(r) for r in self.records}

    def _key(self, rec: dict) -> tuple[str, str, str]:
        return rec["method"], rec[self.keys[0]], rec[self.keys[1]]

    def npz_path(self, method: str, a: str, b: str) -> Path:
        return self.out / self.folder / method / f"{a}__{b}.npz"

    def add(self, rec: dict, arrays: dict | None) -> None:
        """Store ``arrays`` (if any) and then append ``rec``."""
        if arrays is not None:
            p = self.npz_path(*self._key(rec))
            p.parent.mkdir(parents=True, exist_ok=True)
            tmp = p.with_name(p.stem + ".tmp.npz")
            np.savez(tmp, **arrays)
            os.replace(tmp, p)
        with open(self.path, "a") as fh:
            fh.write(json.dumps(rec) + "\n")
        self.records.append(rec)
        self.done.add(self._key(rec))


def results_folder(out: Path):
    """``out`` resolved and created (it must lie outside the repository), and a logger that prints a line and
    appends it to ``out/run.log``."""
    repo = Path(__file__).resolve().parents[1]
    out = out.resolve()
    if out == repo or repo in out.parents:
        raise SystemExit(f"--out must be outside the repository ({repo}), got {out}")
    out.mkdir(parents=True, exist_ok=True)
    logf = open(out / "run.log", "a")

    def log(msg: str) -> None:
        print(msg, flush=True)
        logf.write(msg + "\n")
        logf.flush()

    return out, log


def stored_run(a, keys: tuple[str, str], run, report) -> int:
    """A resumable benchmark's main steps: ``a.out``'s store (`results_folder`, `JsonlStore` keyed by ``keys``),
    ``run(a, store, log)`` unless ``a.report_only``, then ``report(store, a, log)``. Returns the exit code, 0."""
    out, log = results_folder(a.out)
    store = JsonlStore(out, keys=keys, folder="arrays")
    if not a.report_only:
        run(a, store, log)
    report(store, a, log)
    return 0
