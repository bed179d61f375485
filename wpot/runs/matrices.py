"""Reading a run's distances back (`DistanceReader`, what `RunStore` reads with): D(∞) (`distance_matrix`), the
solver's convergence per pair (`converged_matrix`), the paper's D(β) along the annealing (`distance_matrices`, on
every β reached or on the decades, `decade_grid`), and the exports for other tools (`export`)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["DistanceReader", "decade_grid"]


class DistanceReader:
    """The read-back of a run store's distances; `RunStore` is one. It reads the store's SQLite connection
    (``con``) and its shapes (``n_shapes``, ``names``, ``labels``, ``label_levels``) and ``transport``."""

    def distance_matrix(self) -> np.ndarray:
        """D(∞): (n, n) float64 symmetric distances at convergence; NaN for pairs not yet computed
        (partial: also until both self-comparisons are in). The diagonal is 0."""
        n = self.n_shapes
        d = np.full((n, n), np.nan)
        np.fill_diagonal(d, 0.0)
        for i, j, dist in self.con.execute("SELECT i, j, distance FROM pairs WHERE i <> j"):
            if dist is not None:
                d[i, j] = d[j, i] = dist
        return d

    def converged_matrix(self) -> np.ndarray:
        """(n, n) bool: the solver reported convergence for the pair (False where missing)."""
        n = self.n_shapes
        c = np.zeros((n, n), dtype=bool)
        for i, j, ok in self.con.execute("SELECT i, j, converged FROM pairs"):
            c[i, j] = c[j, i] = bool(ok)
        return c

    def distance_matrices(self, betas: "np.ndarray | Sequence[float] | str | None" = None) -> tuple[np.ndarray, np.ndarray]:
        """D(β), the paper's distance matrices along the annealing (§4.1.1: β from 1e3 to 1e11).

        Parameters
        ----------
        betas : which β to read every pair's history at.

            * None (default): every β that any pair reached. Each pair anneals from its own β0 (scaled to
              its costs), so on a large run this is thousands of values, most of them seen by one pair.
            * ``"decades"``: the powers of ten from the one at or below the smallest recorded β to the one at
              or above the largest, the grid the paper plots (`decade_grid`).
            * an increasing sequence of positive β.

        Returns
        -------
        betas : (n_β,) float64, increasing
        D : (n_β, n, n) float64; a pair that converged before β keeps its last value (the energies are
            monotone in β and settle); NaN where missing, including below a pair's first β. Partial:
            SU_β of Eq. 27, with the self energies read at the same β. Diagonal 0.
        """
        from wpot.runs.history import debias_history, history_at

        rows = self.con.execute("SELECT i, j, history FROM pairs").fetchall()
        hist = {(i, j): np.asarray(json.loads(h), dtype=np.float64).reshape(-1, 2) for i, j, h in rows}
        all_b = np.concatenate([h[:, 0] for h in hist.values()]) if hist else np.zeros(0)
        if betas is None:
            grid = _unique_logs(all_b)
        elif isinstance(betas, str):
            if betas != "decades":
                raise ValueError(f"betas must be None, 'decades' or a sequence of positive numbers, got {betas!r}")
            grid = decade_grid(all_b)
        else:
            grid = np.asarray(betas, dtype=np.float64).reshape(-1)
            if not (np.all(np.isfinite(grid)) and np.all(grid > 0) and np.all(np.diff(grid) > 0)):
                raise ValueError(f"betas must be positive, finite and increasing, got {betas!r}")
        n = self.n_shapes
        out = np.full((len(grid), n, n), np.nan)
        idx = np.arange(n)
        out[:, idx, idx] = 0.0
        partial = self.transport == "partial"
        for (i, j), h in hist.items():
            if i == j:
                continue
            if partial:
                if (i, i) not in hist or (j, j) not in hist:
                    continue
                h = debias_history(h, hist[(i, i)], hist[(j, j)])
            v = history_at(h, grid)
            out[:, i, j] = out[:, j, i] = v
        return grid, out

    def export(self, path: str | Path) -> Path:
        """Write the run's distances for other tools; the format follows the extension.

        * ``.csv``: D(∞) as an (n + 1) x (n + 1) table, shape names as the header row and first column
          (Python, R, a spreadsheet), distances to 17 significant digits, an empty cell where a pair is missing.
        * ``.npz`` (read with ``allow_pickle=False``): ``distances`` (n, n) D(∞) with NaN where missing,
          ``converged`` (n, n) bool, ``names`` (n,), ``labels_<level>`` (n,) for each label level ("" where a
          shape has none), and D(β) at the powers of ten (``betas`` (n_β,), ``distances_beta`` (n_β, n, n)).

        The caller checks completeness (`distance_matrix` has NaN for missing pairs, `converged_matrix` False
        for pairs that did not converge); `wpot export` warns about both. Returns the path written.
        """
        import csv

        path = Path(path)
        ext = path.suffix.lower()
        if ext not in (".csv", ".npz"):
            raise ValueError(f"export writes .csv or .npz, got {str(path)!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        d, names = self.distance_matrix(), self.names
        if ext == ".csv":
            with open(path, "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["", *names])
                for name, row in zip(names, d):
                    w.writerow([name, *("" if np.isnan(x) else f"{x:.17g}" for x in row)])
            return path
        betas, d_beta = self.distance_matrices("decades")
        labels = {f"labels_{lv}": np.array(["" if x is None else x for x in self.labels(lv)], dtype=str)
                  for lv in self.label_levels()}
        np.savez_compressed(path, distances=d, converged=self.converged_matrix(), names=np.array(names, dtype=str),
                            betas=betas, distances_beta=d_beta, **labels)
        return path


def decade_grid(betas: np.ndarray) -> np.ndarray:
    """Powers of ten covering ``betas``: from ``10**floor(log10(min))`` to ``10**ceil(log10(max))``
    ((0,) when ``betas`` is empty)."""
    b = np.asarray(betas, dtype=np.float64)
    b = b[np.isfinite(b) & (b > 0)]
    if b.size == 0:
        return np.zeros(0)
    lo, hi = np.floor(np.log10(b.min()) + 1e-9), np.ceil(np.log10(b.max()) - 1e-9)
    return 10.0 ** np.arange(lo, hi + 1)


def _unique_logs(b: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """The distinct finite β of ``b``, increasing (β = ∞, the exact solver's one step, is D(∞) itself)."""
    b = np.sort(b[np.isfinite(b)])
    if b.size == 0:
        return b
    keep = np.r_[True, np.diff(np.log(b)) > rtol]
    return b[keep]
