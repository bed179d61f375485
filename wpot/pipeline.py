"""All-vs-all dataset runs (paper §4): parallel pairs, a resumable SQLite store, distance matrices D(β) and D(∞).

``run_all_vs_all(shapes, out)`` compares every unordered pair of shapes (and, for partial transport, every
shape with itself, which Eq. 27 needs) and commits each finished pair at once to ``out/wpot.sqlite``:

* table ``run``: the parameters (JSON) and their hash, the shared WKS energy grid, the wpot version;
* table ``shapes``: index, name, source path, content fingerprint, vertex count;
* table ``labels``: (shape, level, label), from file names (level "class") and/or a CSV;
* table ``pairs``: one row per pair (i ≤ j): the raw energy U (balanced: transport cost, Eq. 6; partial:
  the objective of Eq. 17), the distance (U, or SU of Eq. 27 once both self-comparisons are in; 0 on the
  diagonal), the per-β history ``[[β, U_β], ...]`` as JSON, converged flag, Newton/linear iteration
  counts, seconds, worker;
* table ``computations``: one row per pair computation ever committed (so a test can check that no pair
  was computed twice), and ``failures`` for pairs that raised.

The database runs in WAL mode and only the coordinating process writes to it. A killed run loses at most
the pairs in flight: rerunning the same command resumes, skipping every committed pair. Rerunning with
other parameters or another shape list raises `RunMismatchError`; a shape file whose content changed since
the run began is refused by name (`RunMismatchError` at the start; a pair whose worker reads a changed file
fails and is recorded in ``failures``). One run folder has one coordinator at a time: `run_all_vs_all` holds
an exclusive lock on ``out/wpot.lock`` (`fcntl.flock`, released by the OS when the process ends, however it
ends), and a second run on the same folder raises `RunLockedError` at once rather than computing pairs twice.
A store that SQLite cannot read (truncated, overwritten) raises `CorruptRunError` naming the file; it is
never read as an empty or partial run.

Execution is pluggable: ``jobs=1`` runs pairs inline; ``jobs>1`` uses a `ProcessPoolExecutor` (spawned
processes, safe with CUDA); any `concurrent.futures.Executor` can be passed instead, e.g. a Dask
cluster's ``client.get_executor()``. Workers receive self-contained tasks (mesh path or arrays, settings,
energy grid) and share an on-disk signature cache in ``out/cache``.

Dask (``scheduler=`` / ``wpot all-vs-all --scheduler``; needs ``pip install 'wpot[cluster]'``):

* ``scheduler="local"`` starts an embedded `distributed.LocalCluster` of ``jobs`` single-threaded worker
  processes; ``scheduler="tcp://host:port"`` uses a running cluster (``dask scheduler`` + ``dask worker``).
  Without ``scheduler`` nothing changes and Dask is never imported.
* The coordinator (this process) is the only writer of the store. Each pair is one Dask task; when a worker
  dies mid-pair, the scheduler hands its tasks to another worker, so the pair is computed again and only
  that pair's work is lost. A pair whose task kills its worker more than
  ``distributed.scheduler.allowed-failures`` times (Dask's default: 3) comes back as ``KilledWorker`` and is
  recorded in ``failures``, like a pair that raised; the run goes on, and rerunning the command retries it.
  Each future yields one result and `RunStore.commit` ignores a pair already stored, so a pair is committed
  once (the ``computations`` table shows it).
* Each worker picks its own Warp device when ``device`` is None (`choose_worker_device`): ``$WPOT_DEVICE``
  if set on the worker; else ``cpu`` on a worker without CUDA; else ``cuda:0`` when the worker's
  ``CUDA_VISIBLE_DEVICES`` is set (launchers such as dask-cuda give each worker its own GPU first in that
  list); else ``cuda:<rank mod n_gpus>`` from the worker's name (`LocalCluster` names its workers 0, 1, ...;
  ``dask worker --name host --nworkers 4`` gives host-0 ... host-3); else Warp's default device. The
  device a pair ran on is stored with its worker (``host:pid@device``). An explicit ``device`` is used by
  every worker.
* Workers read the meshes by path and share the signature cache through the run folder (or
  ``$WPOT_CACHE_DIR``), so on several machines the dataset and the run folder must be on a filesystem that
  every worker sees at the same path.
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import functools
import json
import os
import socket
import sqlite3
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from wpot.mesh import Mesh, MeshWarning

__all__ = [
    "CorruptRunError",
    "RunLockedError",
    "RunMismatchError",
    "RunStore",
    "ShapeSpec",
    "DaskExecutor",
    "choose_worker_device",
    "dask_executor",
    "decade_grid",
    "discover_shapes",
    "param_differences",
    "repair_mesh",
    "repair_mode",
    "repair_setting",
    "repeated_shapes",
    "warn_repeated_shapes",
    "REPAIR_MODES",
    "run_all_vs_all",
    "run_lock",
]

STORE_NAME = "wpot.sqlite"
LOCK_NAME = "wpot.lock"
SCHEMA_VERSION = 1


class RunLockedError(OSError):
    """Another process is running `run_all_vs_all` on the same run folder (it holds ``wpot.lock``).

    Two coordinators on one folder would compute the same pairs twice; the second one stops at once instead.
    The lock goes with the process that holds it (also when that process is killed), so after a crash the
    command simply reruns."""

    def __init__(self, message: str, *, folder: str | Path) -> None:
        super().__init__(message)
        self.folder = str(folder)


class CorruptRunError(ValueError):
    """A run folder's ``wpot.sqlite`` cannot be read as a wpot run (truncated, overwritten, not SQLite, or
    without the run's tables): refused, never read as an empty or partial run."""

    def __init__(self, message: str, *, path: str | Path) -> None:
        super().__init__(message)
        self.path = str(path)


class RunMismatchError(ValueError):
    """A run folder already holds a run with different parameters or shapes.

    Attributes
    ----------
    folder : the run folder
    differences : the settings that differ, as (keyword, stored, requested) (empty when the shapes differ):
        only settings whose meaning differs, each by its `wpot.Comparer` keyword (the transport solver as
        ``"method"``, its other options as ``"solver_options.<name>"``, ``"repair"`` for the mesh repair), a
        value left out of a key read as its default. The ``wpot`` command words them with its flags.
    """

    def __init__(self, message: str, *, folder: str | Path | None = None,
                 differences: Sequence[tuple[str, Any, Any]] = ()) -> None:
        super().__init__(message)
        self.folder = None if folder is None else str(folder)
        self.differences = tuple(differences)


def _key_defaults() -> dict[str, Any]:
    """What a run key's entry means when it is absent or None: the default of its keyword (signature
    options of every registered signature included; ``fps_metric`` and ``pooling`` are None in a key without
    sampling, which samples nothing and so means their defaults)."""
    from wpot.config import ComparisonConfig
    from wpot.signatures import SIGNATURES

    out: dict[str, Any] = {}
    for cls in SIGNATURES.values():
        for f in dataclasses.fields(cls.Options):
            out.setdefault(f.metadata.get("keyword", f.name), f.default)
    out.update(ComparisonConfig().keywords())
    out.pop("solver_options", None)
    out["method"] = ComparisonConfig().method
    return out


def _flat_key(params: Mapping[str, Any]) -> dict[str, Any]:
    """A run key with its solver options spread out (``method``, ``solver_options.<name>``)."""
    out = {k: v for k, v in params.items() if k != "solver_options"}
    for k, v in dict(params.get("solver_options") or {}).items():
        out["method" if k == "method" else f"solver_options.{k}"] = v
    return out


def param_differences(stored: Mapping[str, Any], requested: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """The settings whose meaning differs between two run keys, as (keyword, stored, requested).

    An absent or None entry means its default (`_key_defaults`), so a key that leaves out an option at its
    default, or names no sampling option because nothing is sampled, differs only where a setting does.
    When the signatures differ, options that only one of them has are left out: the signature itself is
    the difference."""
    from wpot.signatures import SIGNATURES

    defaults = _key_defaults()
    old, new = _flat_key(stored), _flat_key(requested)
    signature_changed = old.get("signature") != new.get("signature")
    signature_keywords = {f.metadata.get("keyword", f.name) for cls in SIGNATURES.values()
                          for f in dataclasses.fields(cls.Options)}
    out = []
    for k in sorted(set(old) | set(new), key=lambda k: (k != "signature", k != "transport", k)):
        if signature_changed and k in signature_keywords and (k not in old or k not in new):
            continue
        a = old.get(k) if old.get(k) is not None else defaults.get(k)
        b = new.get(k) if new.get(k) is not None else defaults.get(k)
        if a != b:
            out.append((k, a, b))
    return out


# ---------------------------------------------------------------------------------------------- shapes
@dataclass(frozen=True)
class ShapeSpec:
    """One shape of a dataset: its name, where it comes from (a file, or arrays), and its labels."""

    name: str
    path: str | None = None
    mesh: Mesh | None = None
    labels: Mapping[str, str] | None = None

    def load(self, *, warn: bool = True) -> Mesh:
        """The mesh (read from ``path``; ``warn=False`` reads it without the `MeshWarning` about its defects)."""
        if self.mesh is not None:
            return self.mesh
        from wpot.io import load_mesh

        return load_mesh(self.path, warn=warn)


def read_mesh_list(path: str | Path) -> list[Path]:
    """The mesh paths a list file names: one per line, ``#`` starts a comment, a relative path is relative to
    the list's folder."""
    p = Path(path)
    out = []
    for line in p.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            q = Path(line)
            out.append(q if q.is_absolute() else p.parent / q)
    return out


def discover_shapes(
    source: str | Path | Sequence[str | Path | Mesh], *, labels: str | Path | None = None
) -> list[ShapeSpec]:
    """The shapes of a dataset, in a stable order, with their labels (through `wpot.datasets.list_shapes`).

    ``source`` is a folder (mesh files in natural name order, not recursive), a text file listing one mesh
    path per line (relative paths are relative to the list; ``#`` starts a comment), or a sequence of paths
    or `Mesh` objects (meshes are named ``shape0000``, ... and have no labels). ``labels`` is a label CSV
    (`wpot.datasets.read_label_csv`); without it the level "class" comes from the file names.
    """
    from wpot.datasets import MESH_EXTENSIONS, list_shapes

    if isinstance(source, (str, Path)):
        p = Path(source)
        if p.is_file() and p.suffix.lower() in MESH_EXTENSIONS:
            raise ValueError(f"an all-vs-all needs a folder or a list of meshes, got the single mesh {str(p)!r}")
        if p.is_file():
            source = read_mesh_list(p)
        elif not p.is_dir():
            raise FileNotFoundError(f"no such folder or list file: {str(p)!r}")
    else:
        source = list(source)
    if not isinstance(source, (str, Path)) and source and all(isinstance(m, Mesh) for m in source):
        if labels is not None:
            raise ValueError("labels from a CSV need named shapes (files); got Mesh objects")
        specs = [ShapeSpec(f"shape{k:04d}", None, m, {}) for k, m in enumerate(source)]
    else:
        if not isinstance(source, (str, Path)) and any(isinstance(m, Mesh) for m in source):
            raise ValueError("give either mesh files or Mesh objects, not a mix")
        ss = list_shapes(source, labels=labels)
        specs = [
            ShapeSpec(name, str(Path(path).resolve()), None, {lv: str(lab[k]) for lv, lab in ss.labels.items()})
            for k, (name, path) in enumerate(zip(ss.names, ss.paths))
        ]
    if len(specs) < 2:
        raise ValueError(f"an all-vs-all needs at least 2 shapes, got {len(specs)}")
    return specs


# ----------------------------------------------------------------------------------------------- store
class RunStore:
    """The SQLite store of one all-vs-all run (``folder/wpot.sqlite``). See the module docstring for tables."""

    def __init__(self, folder: str | Path, *, create: bool = False) -> None:
        self.folder = Path(folder)
        self.path = self.folder / STORE_NAME
        if not create and not self.path.is_file():
            raise FileNotFoundError(f"no wpot run in {str(self.folder)!r} (missing {STORE_NAME}); run `wpot all-vs-all ... --out {self.folder}` first")
        self.folder.mkdir(parents=True, exist_ok=True)
        existed = self.path.is_file() and self.path.stat().st_size > 0
        self.con = sqlite3.connect(self.path, timeout=60.0, isolation_level=None)
        from wpot.ot import debiased

        # Eq. 27 in SQL is wpot.ot.debiased itself, so the stored distance is the one the Python API computes
        self.con.create_function("debiased", 3, debiased, deterministic=True)
        try:
            self._open(existed, create)
        except sqlite3.DatabaseError as exc:  # "file is not a database", "database disk image is malformed"
            self.con.close()
            raise CorruptRunError(
                f"the run store {str(self.path)!r} is damaged ({exc}); it cannot be resumed or read. Move it away "
                "and rerun the command to compute the run again (or restore it from a copy)", path=self.path,
            ) from None

    def _open(self, existed: bool, create: bool) -> None:
        """Check an existing file (SQLite's ``quick_check``: every page readable and consistent) and create
        the tables. Raises `sqlite3.DatabaseError` (turned into `CorruptRunError`) or `CorruptRunError`."""
        if existed:
            bad = [r[0] for r in self.con.execute("PRAGMA quick_check")]
            if bad != ["ok"]:
                raise sqlite3.DatabaseError("; ".join(map(str, bad[:3])))
            tables = {r[0] for r in self.con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if not {"run", "shapes", "pairs"} <= tables:
                raise sqlite3.DatabaseError(f"not a wpot run: its tables are {sorted(tables)}")
        elif not create:  # an empty file: a store whose run was never recorded
            raise CorruptRunError(f"the run store {str(self.path)!r} is empty; rerun `wpot all-vs-all ... --out "
                                  f"{self.folder}` to compute the run", path=self.path)
        self.con.execute("PRAGMA journal_mode=WAL")
        self.con.execute("PRAGMA synchronous=NORMAL")
        self.con.executescript(
            """
            CREATE TABLE IF NOT EXISTS run(key TEXT PRIMARY KEY, value TEXT NOT NULL);
            CREATE TABLE IF NOT EXISTS shapes(idx INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, path TEXT,
                fingerprint TEXT NOT NULL, n_vertices INTEGER NOT NULL);
            CREATE TABLE IF NOT EXISTS labels(idx INTEGER NOT NULL, level TEXT NOT NULL, label TEXT NOT NULL,
                PRIMARY KEY(idx, level));
            CREATE TABLE IF NOT EXISTS pairs(i INTEGER NOT NULL, j INTEGER NOT NULL, energy REAL NOT NULL,
                distance REAL, history TEXT NOT NULL, converged INTEGER NOT NULL, n_newton INTEGER,
                n_linear INTEGER, seconds REAL, worker TEXT, finished_at REAL, PRIMARY KEY(i, j));
            CREATE TABLE IF NOT EXISTS computations(id INTEGER PRIMARY KEY AUTOINCREMENT, i INTEGER NOT NULL,
                j INTEGER NOT NULL, finished_at REAL);
            CREATE TABLE IF NOT EXISTS failures(i INTEGER NOT NULL, j INTEGER NOT NULL, error TEXT, at REAL);
            """
        )

    def close(self) -> None:
        self.con.close()

    def __repr__(self) -> str:
        try:
            p = self.params
            n_done = int(self.con.execute("SELECT COUNT(*) FROM pairs").fetchone()[0])
            n_conv = int(self.con.execute("SELECT COUNT(*) FROM pairs WHERE converged").fetchone()[0])
            return (f"RunStore({str(self.folder)!r}: {p.get('signature')}, {p.get('transport')}, {self.n_shapes} shapes, "
                    f"{n_done} of {len(self.tasks())} comparisons done, {n_conv} converged)")
        except sqlite3.ProgrammingError:  # closed
            return f"RunStore({str(self.folder)!r}, closed)"

    def __enter__(self) -> "RunStore":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ----------------------------------------------------------------------------- run metadata
    def get(self, key: str, default: Any = None) -> Any:
        row = self.con.execute("SELECT value FROM run WHERE key=?", (key,)).fetchone()
        return default if row is None else json.loads(row[0])

    def set(self, key: str, value: Any) -> None:
        self.con.execute("INSERT OR REPLACE INTO run(key, value) VALUES (?, ?)", (key, json.dumps(value)))

    @property
    def params(self) -> dict[str, Any]:
        return self.get("params", {})

    @property
    def transport(self) -> str:
        return self.params.get("transport", "balanced")

    def signature_state(self) -> dict[str, Any] | None:
        """The signature's fitted state (`wpot.signatures.Signature.state`) stored with the run, or None.

        Each entry is stored under its own key (WKS's grid under "energies", as every run has stored it)."""
        keys = self.get("signature_state_keys")
        if keys is None:
            keys = ["energies"] if self.get("energies") is not None else []
        state = {k: self.get(k) for k in keys}
        return state or None

    def set_signature_state(self, state: Mapping[str, Any] | None) -> None:
        if not state:
            return
        with self.con:
            self.con.execute("BEGIN")
            for k, v in state.items():
                self.set(k, v)
            self.set("signature_state_keys", sorted(state))

    def initialize(self, params: Mapping[str, Any], shapes: Sequence[tuple[str, str | None, str, int]], labels: Mapping[int, Mapping[str, str]]) -> None:
        """Record a new run, or check that the stored one has the same parameters and shapes.

        ``shapes`` holds (name, path, fingerprint, n_vertices) per shape, in order.
        """
        from wpot.cache import digest

        params = json.loads(json.dumps(params))  # as stored: plain JSON types
        fps = [s[2] for s in shapes]
        if self.get("params_hash") is not None:
            if self.params != params:
                old = self.params
                diff = param_differences(old, params)
                if not diff:  # equal in meaning but not in layout: list the raw entries
                    diff = [(k, old.get(k), params.get(k)) for k in sorted(set(old) | set(params))
                            if old.get(k) != params.get(k)]
                raise RunMismatchError(
                    f"{str(self.folder)!r} holds a run with other parameters: "
                    + "; ".join(f"{k}: stored {a!r}, requested {b!r}" for k, a, b in diff)
                    + ". Use another run folder, or rerun with the stored parameters to resume.",
                    folder=self.folder, differences=diff,
                )
            old_fps = [r[0] for r in self.con.execute("SELECT fingerprint FROM shapes ORDER BY idx")]
            if old_fps != fps:
                old_names = [r[0] for r in self.con.execute("SELECT name FROM shapes ORDER BY idx")]
                new_names = [s[0] for s in shapes]
                if old_names != new_names:
                    msg = (f"{str(self.folder)!r} holds a run over other shapes (stored {len(old_names)} shapes, "
                           f"requested {len(new_names)}); use another run folder")
                else:
                    changed = [n for n, a, b in zip(new_names, old_fps, fps) if a != b]
                    msg = (f"{str(self.folder)!r} holds a run over the same shape names but the content of "
                           f"{len(changed)} of them changed since the run began: "
                           f"{', '.join(changed[:10])}{', ...' if len(changed) > 10 else ''}. Restore the files "
                           "the run was made with to resume it, or use another run folder")
                raise RunMismatchError(
                    msg,
                    folder=self.folder,
                )
            self._write_labels(labels)  # labels may be added or corrected on resume; they change no distance
            return
        with self.con:
            self.con.execute("BEGIN")
            self.set("schema_version", SCHEMA_VERSION)
            self.set("params", params)
            self.set("params_hash", digest(params, length=40))
            self.set("created_at", time.time())
            from wpot import __version__

            self.set("wpot_version", __version__)
            self.con.executemany(
                "INSERT INTO shapes(idx, name, path, fingerprint, n_vertices) VALUES (?, ?, ?, ?, ?)",
                [(k, *s) for k, s in enumerate(shapes)],
            )
        self._write_labels(labels)

    def _write_labels(self, labels: Mapping[int, Mapping[str, str]]) -> None:
        with self.con:
            self.con.execute("BEGIN")
            for idx, d in labels.items():
                for level, lab in d.items():
                    self.con.execute("INSERT OR REPLACE INTO labels(idx, level, label) VALUES (?, ?, ?)", (int(idx), level, str(lab)))

    # ----------------------------------------------------------------------------------- shapes
    @property
    def names(self) -> list[str]:
        return [r[0] for r in self.con.execute("SELECT name FROM shapes ORDER BY idx")]

    @property
    def n_shapes(self) -> int:
        return int(self.con.execute("SELECT COUNT(*) FROM shapes").fetchone()[0])

    def shape_rows(self) -> list[tuple[int, str, str | None, str, int]]:
        return list(self.con.execute("SELECT idx, name, path, fingerprint, n_vertices FROM shapes ORDER BY idx"))

    def label_levels(self) -> list[str]:
        return [r[0] for r in self.con.execute("SELECT DISTINCT level FROM labels ORDER BY level")]

    def labels(self, level: str = "class") -> list[str | None]:
        """Label of each shape (by index) at ``level``; None where a shape has none."""
        out: list[str | None] = [None] * self.n_shapes
        for idx, lab in self.con.execute("SELECT idx, label FROM labels WHERE level=?", (level,)):
            out[idx] = lab
        return out

    # ------------------------------------------------------------------------------------ pairs
    def tasks(self) -> list[tuple[int, int]]:
        """Every pair this run needs: i < j, plus (i, i) for partial transport (self-comparisons first)."""
        n = self.n_shapes
        selfs = [(i, i) for i in range(n)] if self.transport == "partial" else []
        return selfs + [(i, j) for i in range(n) for j in range(i + 1, n)]

    def done(self) -> set[tuple[int, int]]:
        return {(int(i), int(j)) for i, j in self.con.execute("SELECT i, j FROM pairs")}

    def commit(self, rec: Mapping[str, Any]) -> bool:
        """Commit one finished pair in a single transaction. Returns False (and stores nothing new in
        ``pairs``) when the pair was already there; the computation is logged either way."""
        i, j = int(rec["i"]), int(rec["j"])
        now = time.time()
        with self.con:
            self.con.execute("BEGIN IMMEDIATE")
            self.con.execute("INSERT INTO computations(i, j, finished_at) VALUES (?, ?, ?)", (i, j, now))
            try:
                self.con.execute(
                    "INSERT INTO pairs(i, j, energy, distance, history, converged, n_newton, n_linear, seconds, worker, finished_at)"
                    " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        i, j, float(rec["energy"]),
                        0.0 if i == j else (float(rec["energy"]) if self.transport == "balanced" else None),
                        json.dumps(rec["history"]), int(bool(rec["converged"])), rec.get("n_newton"),
                        rec.get("n_linear"), rec.get("seconds"), rec.get("worker"), now,
                    ),
                )
            except sqlite3.IntegrityError:
                return False
            if self.transport == "partial":  # SU (Eq. 27) for every pair whose two self-comparisons are now in
                self.con.execute(
                    "UPDATE pairs SET distance = debiased(energy,"
                    " (SELECT s.energy FROM pairs s WHERE s.i = pairs.i AND s.j = pairs.i),"
                    " (SELECT s.energy FROM pairs s WHERE s.i = pairs.j AND s.j = pairs.j))"
                    " WHERE distance IS NULL AND i <> j"
                    " AND EXISTS (SELECT 1 FROM pairs s WHERE s.i = pairs.i AND s.j = pairs.i)"
                    " AND EXISTS (SELECT 1 FROM pairs s WHERE s.i = pairs.j AND s.j = pairs.j)"
                )
            self.con.execute("DELETE FROM failures WHERE i=? AND j=?", (i, j))
        return True

    def record_failure(self, i: int, j: int, error: str) -> None:
        with self.con:
            self.con.execute("INSERT INTO failures(i, j, error, at) VALUES (?, ?, ?, ?)", (i, j, error, time.time()))

    def failures(self) -> list[tuple[int, int, str]]:
        return list(self.con.execute("SELECT i, j, error FROM failures ORDER BY at"))

    @property
    def n_computations(self) -> int:
        return int(self.con.execute("SELECT COUNT(*) FROM computations").fetchone()[0])

    def pair_rows(self) -> list[dict[str, Any]]:
        cols = ["i", "j", "energy", "distance", "history", "converged", "n_newton", "n_linear", "seconds", "worker"]
        rows = self.con.execute(f"SELECT {', '.join(cols)} FROM pairs ORDER BY i, j")
        return [dict(zip(cols, r)) for r in rows]

    # ------------------------------------------------------------------------------- matrices
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
        from wpot.history import debias_history, history_at

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


# --------------------------------------------------------------------------------------------- workers
def _worker_rank(name: Any) -> int | None:
    """A worker's index from its Dask name: 3, "3" or "host-3" give 3; anything else None."""
    if isinstance(name, bool):
        return None
    if isinstance(name, int):
        return name if name >= 0 else None
    if isinstance(name, str):
        tail = name.rsplit("-", 1)[-1]
        if tail.isdigit():
            return int(tail)
    return None


def choose_worker_device(*, worker_name: Any, cuda_count: int, env: Mapping[str, str]) -> str | None:
    """The Warp device a Dask worker uses when the run names none (a pure function of the worker's view).

    Parameters
    ----------
    worker_name : the worker's Dask name (`LocalCluster`: 0, 1, ...; ``dask worker --name h --nworkers 2``:
        "h-0", "h-1"; otherwise often its address)
    cuda_count : CUDA devices the worker's process sees (Warp's ``get_cuda_device_count()``)
    env : the worker's environment

    Returns
    -------
    ``env["WPOT_DEVICE"]`` when set (an operator's explicit choice); ``"cpu"`` without CUDA; ``"cuda:0"``
    when ``CUDA_VISIBLE_DEVICES`` is set (the launcher chose this worker's GPUs and put its own first, as
    dask-cuda does); ``"cuda:<rank mod cuda_count>"`` when the name ends in a worker rank (several workers
    of one machine then spread over its GPUs); otherwise None: Warp's default device.
    """
    explicit = (env.get("WPOT_DEVICE") or "").strip()
    if explicit:
        return explicit
    if cuda_count < 0:
        raise ValueError(f"cuda_count must be >= 0, got {cuda_count!r}")
    if cuda_count == 0:
        return "cpu"
    if (env.get("CUDA_VISIBLE_DEVICES") or "").strip():
        return "cuda:0"
    rank = _worker_rank(worker_name)
    if rank is not None:
        return f"cuda:{rank % cuda_count}"
    return None


def _dask_worker_name() -> tuple[bool, Any]:
    """(True, name) inside a Dask worker, else (False, None). Never imports Dask when it is not loaded."""
    import sys

    if "distributed" not in sys.modules:
        return False, None
    try:
        from distributed import get_worker

        return True, get_worker().name
    except (ImportError, ValueError):  # ValueError: not running in a worker
        return False, None


def _task_device(config: Mapping[str, Any]) -> str | None:
    """The device of this task: the run's ``device``; when None, the Dask worker's own choice
    (`choose_worker_device`); elsewhere (inline, process pool) Warp's default."""
    if config.get("device") is not None:
        return config["device"]
    on_dask, name = _dask_worker_name()
    if not on_dask:
        return None
    import warp as wp

    from wpot._warp import resolve_device

    resolve_device(None)  # initializes Warp
    return choose_worker_device(worker_name=name, cuda_count=wp.get_cuda_device_count(), env=os.environ)


@functools.lru_cache(maxsize=1)
def _comparer_for(config_json: str):
    """The `Comparer` a worker rebuilds from a task's configuration (memoized: one per run and process)."""
    from wpot.comparison import Comparer
    from wpot.config import ComparisonConfig

    config = json.loads(config_json)
    return Comparer(ComparisonConfig.from_dict(config["config"]), signature_state=config.get("state"),
                    cache_dir=config.get("cache_dir"), device=_task_device(config))


def _worker_comparer(config: Mapping[str, Any]):
    return _comparer_for(json.dumps(config, sort_keys=True))


@functools.lru_cache(maxsize=64)
def _mesh_at(path: str, repair: str = "none") -> Mesh:
    from wpot.io import load_mesh

    # the coordinator said the mesh's defects once, when it read the shapes
    return repair_mesh(load_mesh(path, warn=False), repair)[0]


def _worker_mesh(spec: Any, config: Mapping[str, Any]) -> Mesh:
    """A task's mesh: given, or read from its path (and repaired when the run repairs its meshes).

    A path comes with the fingerprint the coordinator read (``(path, fingerprint)``): a file edited after the
    run began raises ValueError naming it (the pair is recorded in ``failures``), so a pair is never computed
    on another mesh than the one the run's shapes table describes."""
    if isinstance(spec, Mesh):
        return spec
    path, fingerprint = spec if isinstance(spec, tuple) else (spec, None)
    mesh = _mesh_at(path, repair_mode(config.get("repair", False)))
    if fingerprint is not None and mesh.fingerprint != fingerprint:
        _mesh_at.cache_clear()
        raise ValueError(f"{path} changed while the run was going (its content is not the one the run began "
                         "with); restore it, or start a new run folder")
    return mesh


#: what ``repair`` asks for (`repair_mode`): nothing; the defects `Mesh.validate` warns about (zero-area and
#: duplicate triangles, unreferenced vertices); or those and then every connected component but the largest
#: (scans with stray pieces, TOSCA's seahorses with their two detached eyes)
REPAIR_MODES = ("none", "defects", "largest")


def repair_mode(repair: bool | str | None) -> str:
    """``repair`` as one of `REPAIR_MODES`: False or None is "none", True is "defects"."""
    if repair is None or repair is False:
        return "none"
    if repair is True:
        return "defects"
    if isinstance(repair, str) and repair in REPAIR_MODES:
        return repair
    raise ValueError(f"repair must be True, False or one of {', '.join(map(repr, REPAIR_MODES))}, got {repair!r}")


def repair_setting(repair: bool | str | None) -> bool | str:
    """``repair`` as a run stores it and a saved comparison records it: False, True or "largest" (booleans for
    the first two, so that every stored run reads the same way)."""
    mode = repair_mode(repair)
    return {"none": False, "defects": True}.get(mode, mode)


def repair_mesh(mesh: Mesh, mode: bool | str = "defects") -> tuple[Mesh, np.ndarray, str]:
    """`Mesh.cleaned` with an account of what it removed (``mode``: `repair_mode`; "none" returns the mesh).

    Returns
    -------
    mesh, index_map : as `Mesh.cleaned` (``index_map[i]`` is the input index of the repaired mesh's vertex i)
    removed : what was removed, e.g. ``"1 zero-area triangle, 2 unreferenced vertices"`` or ``"2 smaller
        components (58 vertices)"``; "" when nothing was
    """
    mode = repair_mode(mode)
    if mode == "none":
        return mesh, np.arange(mesh.n_vertices, dtype=np.int64), ""
    with warnings.catch_warnings():
        if mode == "largest":  # its components are about to go: no MeshWarning about them
            warnings.simplefilter("ignore", MeshWarning)
        fixed, index_map = mesh.cleaned()
    n_degenerate = int(mesh.degenerate_faces.size)
    counts = [
        (n_degenerate, "zero-area triangle", "zero-area triangles"),
        (mesh.n_faces - fixed.n_faces - n_degenerate, "duplicate triangle", "duplicate triangles"),
        (mesh.n_vertices - fixed.n_vertices, "unreferenced vertex", "unreferenced vertices"),
    ]
    removed = [f"{n} {one if n == 1 else many}" for n, one, many in counts if n > 0]
    if mode == "largest" and fixed.n_components > 1:
        n_pieces, n_before = fixed.n_components - 1, fixed.n_vertices
        fixed, inner = fixed.cleaned(keep_largest_component=True)
        index_map = index_map[inner]
        removed.append(f"{n_pieces} smaller component{'s' if n_pieces > 1 else ''} "
                       f"({n_before - fixed.n_vertices} vertices)")
    return fixed, index_map, ", ".join(removed)


def repeated_shapes(names: Sequence[str], fingerprints: Sequence[str]) -> list[list[str]]:
    """The groups of ``names`` whose meshes are the same (equal `Mesh.fingerprint`: the same vertices and
    triangles), in order; [] when every mesh is distinct. TOSCA's low-resolution set has two such pairs,
    victoria0 / victoria1 and victoria13 / victoria22."""
    groups: dict[str, list[str]] = {}
    for name, fp in zip(names, fingerprints):
        groups.setdefault(fp, []).append(name)
    return [g for g in groups.values() if len(g) > 1]


def warn_repeated_shapes(names: Sequence[str], fingerprints: Sequence[str]) -> None:
    """Warn about the `repeated_shapes` among ``names``: their distance is 0, so each is the other's nearest
    neighbour and classification scores come out flattered (said by `run_all_vs_all` and by `wpot classify`)."""
    groups = repeated_shapes(names, fingerprints)
    if groups:
        warnings.warn(f"these shapes are the same mesh (the same vertices and triangles): "
                      f"{'; '.join(' = '.join(g) for g in groups)}. Their distance is 0, so each is the other's "
                      "nearest neighbour, which flatters leave-one-out and one-shot scores; leave out all but one "
                      "of each", UserWarning, stacklevel=3)


def _shape_task(fn: Any, spec: Any, config: Mapping[str, Any]) -> tuple[Any, list[tuple[type, str]]]:
    """``fn(mesh, config)`` on one shape's mesh, with the warnings it raised returned beside its result rather
    than printed where it ran (a worker process prints them without saying which shape they are about):
    `_map` says each again, once, in the coordinator, prefixed with the shape's file name."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        value = fn(_worker_mesh(spec, config), config)
    said = [(w.category, str(w.message)) for w in caught]
    return value, list(dict.fromkeys(said))


def _signatures_of(mesh: Mesh, config: Mapping[str, Any]) -> int:
    """Compute (and cache on disk) one shape's signatures; returns its vertex count."""
    _worker_comparer(config).signatures(mesh)
    return mesh.n_vertices


def _fit_input_of(mesh: Mesh, config: Mapping[str, Any]) -> Any:
    """One shape's contribution to fitting the signature to the dataset (`Signature.fit_input`: for WKS, its
    eigenvalues; the eigenvectors stay in the run's spectrum cache, on disk)."""
    return _worker_comparer(config).stage.fit_input(mesh)


def _pair_task(i: int, j: int, spec_i: Any, spec_j: Any, config: Mapping[str, Any]) -> dict[str, Any]:
    """Solve one pair (raw energy U and its per-β history), self-contained so any executor can run it."""
    t0 = time.perf_counter()
    comp = _worker_comparer(config)
    a = _worker_mesh(spec_i, config)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # non-convergence is recorded in the store's `converged` column
        if i == j:
            res = comp.self_transport(a)
        else:
            res = comp.transport_plan(a, _worker_mesh(spec_j, config))
    return {
        "i": i,
        "j": j,
        "energy": float(res.objective),
        "history": res.energy_history.tolist(),
        "converged": bool(res.converged),
        "n_newton": int(res.n_newton),
        "n_linear": int(res.n_linear),
        "seconds": time.perf_counter() - t0,
        "worker": f"{socket.gethostname()}:{os.getpid()}@{comp.device}",
    }


# ------------------------------------------------------------------------------------------------ runner
@contextlib.contextmanager
def run_lock(folder: str | Path) -> Iterator[None]:
    """Hold the run folder's exclusive lock (``folder/wpot.lock``, `fcntl.flock`) for the block.

    One coordinator per run folder: a second process, or a second call in this one (flock locks belong to
    each opened file, so they conflict within a process too), gets `RunLockedError` at once, naming the folder.
    The operating system drops the lock when its process ends, also on SIGKILL, so a crashed run leaves nothing
    to clean up; the lock file itself stays (it holds the owner's host:pid, for the message only)."""
    import fcntl

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    key = str(folder.resolve())
    fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                owner = os.pread(fd, 200, 0).decode("ascii", "replace").strip()
            except OSError:
                owner = ""
            raise RunLockedError(
                f"another wpot all-vs-all is running on the run folder {key!r}"
                + (f" (process {owner})" if owner else "")
                + "; wait for it to finish (or stop it), then rerun this command to resume the run",
                folder=key,
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{socket.gethostname()}:{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the flock


def run_all_vs_all(
    shapes: str | Path | Sequence[str | Path | Mesh],
    out: str | Path,
    *,
    signature: str = "wks",
    transport: str = "balanced",
    jobs: int | None = 1,
    executor: cf.Executor | None = None,
    scheduler: str | None = None,
    labels: str | Path | Mapping[str, Mapping[str, str]] | None = None,
    device: str | None = None,
    progress: Any = True,
    max_pairs: int | None = None,
    config: Any = None,
    repair: bool | str = False,
    **comparer_options: Any,
) -> RunStore:
    """Compare every pair of ``shapes`` and store the results in the run folder ``out`` (resumable).

    Parameters
    ----------
    shapes : folder, list file, or sequence of paths / meshes (see `discover_shapes`)
    out : run folder; created if needed. An existing run with the same parameters and shapes is resumed.
    signature, transport, **comparer_options : as `wpot.comparison.Comparer` (max_vertices, mass_penalty,
        n_eigen, n_energies, ldsift_K, solver_options, ...). ``cache_dir`` (the signature and spectrum
        cache, shared by runs over the same shapes) defaults to ``$WPOT_CACHE_DIR``, else ``out/cache``.
    config : a `wpot.config.ComparisonConfig` instead of those keywords
    jobs : worker processes when ``executor`` is None (1: inline in this process; None: all CPU cores);
        with ``scheduler="local"``, the number of Dask workers. The workers are spawned, so a script that
        calls this with ``jobs != 1`` must do so under ``if __name__ == "__main__":`` (notebooks need nothing)
    executor : any `concurrent.futures.Executor` (e.g. a Dask ``client.get_executor()``); overrides ``jobs``
    scheduler : run the tasks on Dask (see `dask_executor`): ``"local"`` (an embedded `LocalCluster` of
        ``jobs`` processes) or a scheduler address ``"tcp://host:port"``. None (default): no Dask.
    labels : a label CSV (`wpot.datasets.read_label_csv`: a ``name`` column and one column per level); its
        first column is also level "class". Without it, "class" comes from the file names.
    device : Warp device every worker uses (None: Warp's default; on Dask, each worker's own choice,
        see `choose_worker_device`)
    progress : a `tqdm.auto` bar for every phase (reading the meshes, fitting the signature, the signatures, the
        pairs with their rate and ETA) on standard error: True, False, or a `wpot.progress.Progress`
    max_pairs : stop after committing this many new pairs (for tests and partial runs)
    repair : repair every mesh with `wpot.Mesh.cleaned` before it is used, here and in the workers: True (or
        "defects") removes zero-area and duplicate triangles and unreferenced vertices, "largest" also every
        connected component but the largest (`repair_mesh`); what was removed from which shape is stored with
        the run (``store.get("repairs")``: name -> what was removed) and reported. The shapes' stored
        fingerprints are those of the repaired meshes, so a resume must repair the same way.

    Returns
    -------
    RunStore : the open store; ``distance_matrix()`` and ``distance_matrices()`` read the results back.

    Raises
    ------
    RunLockedError : another process is running on ``out`` (one coordinator per run folder: `run_lock`)
    RunMismatchError : ``out`` holds a run with other parameters or shapes, or a shape file changed since
    CorruptRunError : ``out/wpot.sqlite`` is damaged

    The inputs are read and checked first, so a refused input leaves no run folder behind; the run folder's
    lock (`run_lock`) is then held for the rest of the run.
    """
    from wpot.comparison import check_mesh_size, fit_phase
    from wpot.config import ComparisonConfig
    from wpot.progress import as_progress

    if scheduler is not None:
        if executor is not None:
            raise ValueError(f"give either executor or scheduler, not both (got scheduler={scheduler!r})")
        with dask_executor(scheduler, n_workers=jobs) as ex:
            return run_all_vs_all(
                shapes, out, signature=signature, transport=transport, jobs=jobs, executor=ex, scheduler=None, labels=labels,
                device=device, progress=progress, max_pairs=max_pairs, config=config, repair=repair,
                **comparer_options,
            )
    mode = repair_mode(repair)
    reporter = as_progress(progress)
    if labels is not None and not isinstance(labels, (str, Path)):
        raise TypeError(f"labels must be a CSV path, got {type(labels).__name__}")
    specs = discover_shapes(shapes, labels=labels)
    out = Path(out)
    cache_dir = str(Path(comparer_options.pop("cache_dir", None) or os.environ.get("WPOT_CACHE_DIR") or out / "cache").resolve())
    if config is None:
        config = ComparisonConfig.from_keywords(signature=signature, transport=transport, **comparer_options)
    elif comparer_options or signature != "wks" or transport != "balanced":
        raise TypeError("give either config or the comparison keywords (signature, transport, ...), not both")
    params = config.run_key()

    # every file read and checked up front: fail before any work
    meshes, repairs = [], {}
    bar = reporter.bar(len(specs), "reading meshes", "mesh")
    try:
        for s in specs:
            m = s.load(warn=mode == "none")
            if mode != "none":
                m, _, what = repair_mesh(m, mode)
                if what:
                    repairs[s.name] = what
                    reporter.write(f"repaired {s.name}: removed {what}")
            check_mesh_size(m, config, f"shape {s.name!r}" + (f" ({s.path})" if s.path else ""))
            meshes.append(m)
            bar.update()
    finally:
        bar.close()
    shape_rows = [(s.name, s.path, m.fingerprint, m.n_vertices) for s, m in zip(specs, meshes)]
    warn_repeated_shapes([s.name for s in specs], [m.fingerprint for m in meshes])
    lab = {k: dict(s.labels or {}) for k, s in enumerate(specs)}

    with run_lock(out):
        store = RunStore(out, create=True)
        stored_repair = store.get("repair", False)
        stored_mode = repair_mode(stored_repair)
        try:
            store.initialize(params, shape_rows, lab)
        except RunMismatchError as exc:
            if exc.differences or stored_mode == mode:
                raise
            raise RunMismatchError(f"{exc} The run was made with repair={stored_repair!r}; rerun with "
                                   f"repair={stored_repair!r} to resume it.", folder=out,
                                   differences=[("repair", stored_repair, repair_setting(mode))]) from None
        store.set("repair", repair_setting(mode))
        if mode != "none":
            store.set("repairs", repairs)
        todo = [t for t in store.tasks() if t not in store.done()]
        if not todo:
            return store

        own_pool = None
        if executor is None and (jobs is None or jobs > 1):
            import multiprocessing as mp

            own_pool = cf.ProcessPoolExecutor(max_workers=jobs or os.cpu_count(), mp_context=mp.get_context("spawn"))
            executor = own_pool
        task_specs = [(s.path, m.fingerprint) if s.path is not None else m for s, m in zip(specs, meshes)]
        try:
            # what every task needs to rebuild the comparer: the configuration, the signature's fitted state
            # (paper §3.2: one WKS energy grid for the whole dataset, stored with the run), the shared caches
            task_config = {"config": config.to_dict(), "state": store.signature_state(), "cache_dir": cache_dir,
                           "device": device, "repair": mode}
            from wpot.signatures import get_signature

            stage = get_signature(config.signature)(config.signature_options)
            if stage.needs_fit and task_config["state"] is None:
                inputs = _map(executor, _shape_task, [(_fit_input_of, sp, task_config) for sp in task_specs],
                              fit_phase(stage), reporter, [s.name for s in specs])
                stage.fit_from(inputs)
                task_config["state"] = stage.state()
                store.set_signature_state(task_config["state"])
            needed = sorted({i for t in todo for i in t})
            _map(executor, _shape_task, [(_signatures_of, task_specs[i], task_config) for i in needed], "signatures",
                 reporter, [specs[i].name for i in needed])
            _run_pairs(store, executor, todo, task_specs, task_config, reporter, max_pairs)
        finally:
            if own_pool is not None:
                own_pool.shutdown(wait=True, cancel_futures=True)
        return store


class DaskExecutor(cf.Executor):
    """A `concurrent.futures.Executor` on a Dask ``distributed.Client`` that `run_all_vs_all` keeps busy
    without over-committing: it holds at most one task per worker thread in flight (`max_in_flight`).

    Each worker then holds only the pair it is computing: when a worker dies, Dask blames (counts towards
    ``allowed-failures``) only that pair, not pairs queued behind it, and the loss is that one pair. Tasks
    are impure (``pure=False``): every submission runs. A plain ``client.get_executor()`` also works
    with `run_all_vs_all`, but then every pair is submitted at once.
    """

    def __init__(self, client: Any) -> None:
        self.client = client
        self._inner = client.get_executor(pure=False)

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> cf.Future:
        return self._inner.submit(fn, *args, **kwargs)

    def max_in_flight(self) -> int:
        """Worker threads of the cluster now (at least 1, so that a run waits for workers to come back)."""
        return max(1, int(sum(self.client.nthreads().values())))

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._inner.shutdown(wait=wait and not cancel_futures)


@contextlib.contextmanager
def dask_executor(scheduler: Any, *, n_workers: int | None = None, connect_timeout: float = 30.0) -> Iterator[DaskExecutor]:
    """A `DaskExecutor` for `run_all_vs_all` (a context manager).

    Parameters
    ----------
    scheduler : ``"local"``: start an embedded `distributed.LocalCluster` of ``n_workers`` worker processes
        (one thread each; None: one per CPU core), closed on exit. ``"tcp://host:port"`` (or another Dask
        address such as ``tls://``): connect to that running scheduler; its workers are used as they are.
        A ``distributed.Client``: use it (it is left open).
    n_workers : workers of the local cluster (ignored otherwise)
    connect_timeout : seconds to wait for a remote scheduler

    Raises
    ------
    ImportError : Dask's ``distributed`` is not installed (names the extra: ``pip install 'wpot[cluster]'``)
    ValueError : ``scheduler`` is neither "local" nor an address nor a client, or ``n_workers < 1``
    OSError : the scheduler cannot be reached
    """
    is_client = type(scheduler).__name__ == "Client" and hasattr(scheduler, "get_executor")
    if not is_client and not (isinstance(scheduler, str) and (scheduler == "local" or "://" in scheduler)):
        raise ValueError(f'scheduler must be "local", a Dask address like "tcp://host:8786" or a Client, got {scheduler!r}')
    if n_workers is not None and n_workers < 1:
        raise ValueError(f"n_workers must be >= 1 or None, got {n_workers!r}")
    try:
        import dask  # noqa: F401  (checked here so that the message below names what is missing)
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise ImportError(
            f"running on a Dask cluster (scheduler={scheduler!r}) needs Dask's distributed package: "
            "pip install 'wpot[cluster]' (or 'dask[distributed]')"
        ) from exc
    with contextlib.ExitStack() as stack:
        if is_client:
            client = scheduler
        elif scheduler == "local":
            cluster = stack.enter_context(
                LocalCluster(
                    n_workers=n_workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                    dashboard_address="127.0.0.1:0",  # a free port (8787 may be taken)
                )
            )
            client = stack.enter_context(Client(cluster))
        else:
            client = stack.enter_context(Client(scheduler, timeout=connect_timeout))
        executor = DaskExecutor(client)
        try:
            yield executor
        finally:
            executor.shutdown(wait=False, cancel_futures=True)


def _completed(executor: cf.Executor, calls: Iterable[tuple[Any, Any, tuple]]) -> Iterator[tuple[Any, cf.Future]]:
    """Submit ``fn(*args)`` for each (key, fn, args) and yield (key, future) as they finish.

    An executor with ``max_in_flight()`` (`DaskExecutor`) gets no more tasks than that at a time (asked
    again every second, as workers come and go); others get every task at once. A finished future is
    dropped as soon as it has been yielded, so a cluster does not keep (or recompute) its result."""
    limit = getattr(executor, "max_in_flight", None)
    pending: dict[cf.Future, Any] = {}
    calls = iter(calls)
    exhausted = False
    try:
        if limit is None:
            for key, fn, args in calls:
                pending[executor.submit(fn, *args)] = key
            for f in cf.as_completed(list(pending)):
                yield pending.pop(f), f
            return
        while True:
            cap = limit()
            while not exhausted and len(pending) < cap:
                try:
                    key, fn, args = next(calls)
                except StopIteration:
                    exhausted = True
                    break
                pending[executor.submit(fn, *args)] = key
            if not pending:
                return
            done, _ = cf.wait(list(pending), timeout=1.0, return_when=cf.FIRST_COMPLETED)
            for f in done:
                yield pending.pop(f), f
    finally:
        for f in pending:  # max_pairs reached, or the coordinator stopped: the rest is not needed
            f.cancel()


def _map(executor: cf.Executor | None, fn: Any, arglist: list[tuple], what: str, progress: Any,
         names: Sequence[str]) -> list[Any]:
    """Run `_shape_task` (``fn`` is it) for each args (inline or on the executor), with a progress bar; returns
    the values in the order of ``arglist``, and says each task's warnings as they arrive, prefixed with the
    name of its shape (``names``, one per args)."""
    bar = progress.bar(len(arglist), what, "shape")

    def take(k: int, told: tuple[Any, list[tuple[type, str]]]) -> Any:
        value, said = told
        for category, message in said:
            warnings.warn(f"{names[k]}: {message}", category, stacklevel=3)
        bar.update()
        return value

    try:
        if executor is None:
            return [take(k, fn(*a)) for k, a in enumerate(arglist)]
        results: list[Any] = [None] * len(arglist)
        with contextlib.closing(_completed(executor, ((k, fn, a) for k, a in enumerate(arglist)))) as finished:
            for k, f in finished:
                results[k] = take(k, f.result())
        return results
    finally:
        bar.close()


def _run_pairs(store: RunStore, executor, todo, task_specs, config, progress: Any, max_pairs: int | None) -> None:
    total = len(store.tasks())
    bar = progress.bar(total, "pairs", "pair", initial=total - len(todo), leave=True)
    n_new = 0

    def handle(i: int, j: int, fut_or_rec: Any) -> None:
        nonlocal n_new
        try:
            rec = fut_or_rec.result() if isinstance(fut_or_rec, cf.Future) else fut_or_rec
        except Exception as exc:  # a failing pair is recorded and the run goes on
            store.record_failure(i, j, f"{type(exc).__name__}: {exc}")
            bar.write(f"pair ({i}, {j}) failed: {type(exc).__name__}: {exc}")
            return
        if store.commit(rec):
            n_new += 1
        bar.update()

    try:
        if executor is None:
            for i, j in todo:
                if max_pairs is not None and n_new >= max_pairs:
                    break
                try:
                    rec = _pair_task(i, j, task_specs[i], task_specs[j], config)
                except Exception as exc:
                    store.record_failure(i, j, f"{type(exc).__name__}: {exc}")
                    bar.write(f"pair ({i}, {j}) failed: {type(exc).__name__}: {exc}")
                    continue
                handle(i, j, rec)
        else:
            calls = (((i, j), _pair_task, (i, j, task_specs[i], task_specs[j], config)) for i, j in todo)
            with contextlib.closing(_completed(executor, calls)) as finished:  # closing cancels the rest
                for (i, j), f in finished:
                    handle(i, j, f)
                    if max_pairs is not None and n_new >= max_pairs:
                        break
    finally:
        bar.close()
    fails = store.failures()
    if fails:
        warnings.warn(
            f"{len(fails)} pairs failed and are not in the store (first: {fails[0]}); rerun the same command to retry them",
            stacklevel=3,
        )
