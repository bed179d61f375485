"""The run store: one SQLite file per run folder (`RunStore`), the run's key (its parameters), and the lock that
keeps one coordinator per folder (`run_lock`). See `wpot.runs.loop` for the tables and how a run uses them."""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import socket
import sqlite3
import time
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from wpot.runs.matrices import DistanceReader, decade_grid

__all__ = ["CorruptRunError", "LOCK_NAME", "RunLockedError", "RunMismatchError", "RunStore", "SCHEMA_VERSION", "STORE_NAME", "decade_grid", "param_differences", "run_lock"]


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


#: how long opening a run store waits for another process's lock before giving up (`RunBusyError`)
BUSY_SECONDS = 60.0


class RunBusyError(OSError):
    """A run folder's ``wpot.sqlite`` stayed locked by another process while it was being opened."""


def _busy(exc: sqlite3.OperationalError) -> bool:
    return "locked" in str(exc) or "busy" in str(exc)


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


# ----------------------------------------------------------------------------------------------- store


class RunStore(DistanceReader):
    """The SQLite store of one all-vs-all run (``folder/wpot.sqlite``). See `wpot.runs.loop` for its tables; the
    distances are read back with the methods of `DistanceReader` (``distance_matrix``, ``distance_matrices``, ...)."""

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
        deadline = time.monotonic() + BUSY_SECONDS
        while True:
            try:
                self._open(existed, create)
                break
            except sqlite3.OperationalError as exc:
                # "database is locked": another process holds it (a journal-mode switch does not wait on the
                # busy timeout); a lock is no damage, so wait for it
                if not _busy(exc):
                    raise self._damaged(exc) from None
                if time.monotonic() > deadline:
                    self.con.close()
                    raise RunBusyError(f"the run store {str(self.path)!r} stayed locked by another process for "
                                       f"{BUSY_SECONDS:.0f} s ({exc}): is another wpot run writing to "
                                       f"{str(self.folder)!r}?") from None
                time.sleep(0.05)
            except sqlite3.DatabaseError as exc:  # "file is not a database", "database disk image is malformed"
                raise self._damaged(exc) from None

    def _damaged(self, exc: Exception) -> "CorruptRunError":
        self.con.close()
        return CorruptRunError(
            f"the run store {str(self.path)!r} is damaged ({exc}); it cannot be resumed or read. Move it away "
            "and rerun the command to compute the run again (or restore it from a copy)", path=self.path)

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


# ------------------------------------------------------------------------------------------------ lock


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
