"""wpot.runs.loop: the resumable SQLite store, parameter checks, D(β) read-back, and interrupted real runs."""
from __future__ import annotations

import json

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from wpot.runs.shapes import discover_shapes
from wpot.runs.store import RunMismatchError, RunStore
from helpers import FAST, FAST_CLI, make_dataset

SHAPES = [("a1", None, "f0", 10), ("a2", None, "f1", 10), ("b1", None, "f2", 12)]
LABELS = {0: {"class": "a"}, 1: {"class": "a"}, 2: {"class": "b"}}


def _rec(i, j, energy, history=None, converged=True):
    h = history if history is not None else [[1e3, energy * 2], [1e4, energy]]
    return {"i": i, "j": j, "energy": energy, "history": h, "converged": converged, "n_newton": 3, "n_linear": 10, "seconds": 0.1, "worker": "t"}


def _store(tmp_path, transport="partial", **extra):
    s = RunStore(tmp_path / "run", create=True)
    s.initialize({"signature": "wks", "transport": transport, **extra}, SHAPES, LABELS)
    return s


def test_partial_distance_is_debiased_whatever_the_commit_order(tmp_path):
    s = _store(tmp_path)
    assert s.tasks() == [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]
    energies = {(0, 1): 5.0, (0, 2): 9.0, (1, 2): 8.0, (0, 0): 1.0, (1, 1): 2.0, (2, 2): 4.0}
    order = [(0, 1), (2, 2), (0, 2), (0, 0), (1, 2), (1, 1)]
    for k, (i, j) in enumerate(order):
        assert s.commit(_rec(i, j, energies[(i, j)]))
        d = s.distance_matrix()
        for (a, b), e in energies.items():
            if a == b or (a, b) not in order[: k + 1]:
                continue
            ready = (a, a) in order[: k + 1] and (b, b) in order[: k + 1]
            want = e - 0.5 * (energies[(a, a)] + energies[(b, b)]) if ready else np.nan
            np.testing.assert_equal(d[a, b], want)
            np.testing.assert_equal(d[b, a], want)
    np.testing.assert_array_equal(np.diag(d), 0.0)
    assert s.done() == set(energies)


def test_balanced_store_skips_self_pairs_and_stores_u(tmp_path):
    s = _store(tmp_path, transport="balanced")
    assert s.tasks() == [(0, 1), (0, 2), (1, 2)]
    s.commit(_rec(0, 2, 3.5))
    d = s.distance_matrix()
    assert d[0, 2] == d[2, 0] == 3.5 and np.isnan(d[0, 1])
    s.commit(_rec(0, 1, 2.0, converged=False))
    assert repr(s) == f"RunStore({str(tmp_path / 'run')!r}: wks, balanced, 3 shapes, 2 of 3 comparisons done, 1 converged)"
    s.close()
    assert repr(s).endswith(", closed)")


def test_a_pair_is_stored_once_and_every_computation_is_logged(tmp_path):
    s = _store(tmp_path, transport="balanced")
    assert s.commit(_rec(0, 1, 1.0))
    assert not s.commit(_rec(0, 1, 7.0))  # a second computation of the same pair does not overwrite it
    assert s.distance_matrix()[0, 1] == 1.0
    assert s.n_computations == 2 and len(s.pair_rows()) == 1


def test_store_refuses_other_parameters_and_other_shapes(tmp_path):
    _store(tmp_path, transport="partial", mass_penalty=1.0).close()
    s = RunStore(tmp_path / "run")
    with pytest.raises(RunMismatchError, match=r"mass_penalty: stored 1\.0, requested 2\.0"):
        s.initialize({"signature": "wks", "transport": "partial", "mass_penalty": 2.0}, SHAPES, LABELS)
    with pytest.raises(RunMismatchError, match="other shapes"):
        s.initialize({"signature": "wks", "transport": "partial", "mass_penalty": 1.0}, SHAPES[:2], LABELS)
    changed = [SHAPES[0], SHAPES[1], ("b1", None, "fX", 12)]
    with pytest.raises(RunMismatchError, match=r"content of 1 of them changed since the run began: b1\. Restore"):
        s.initialize({"signature": "wks", "transport": "partial", "mass_penalty": 1.0}, changed, LABELS)
    # the same parameters resume without complaint
    s.initialize({"transport": "partial", "mass_penalty": 1.0, "signature": "wks"}, SHAPES, LABELS)


def test_opening_a_missing_run_names_the_command(tmp_path):
    with pytest.raises(FileNotFoundError, match="all-vs-all"):
        RunStore(tmp_path / "nothing")


def test_store_is_in_wal_mode_and_labels_round_trip(tmp_path):
    s = _store(tmp_path)
    assert s.con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert s.labels("class") == ["a", "a", "b"]
    assert s.names == ["a1", "a2", "b1"]


def test_distance_matrices_follow_each_pair_history_in_beta(tmp_path):
    s = _store(tmp_path)
    s.commit(_rec(0, 0, 1.0, [[1e3, 3.0], [1e4, 1.0]]))
    s.commit(_rec(1, 1, 2.0, [[1e3, 2.0]]))  # converged early: keeps its last value
    s.commit(_rec(0, 1, 5.0, [[1e3, 9.0], [1e4, 6.0], [1e5, 5.0]]))
    betas, d = s.distance_matrices()
    np.testing.assert_allclose(betas, [1e3, 1e4, 1e5])
    np.testing.assert_allclose(d[:, 0, 1], [9 - 0.5 * (3 + 2), 6 - 0.5 * (1 + 2), 5 - 0.5 * (1 + 2)])
    np.testing.assert_allclose(d[:, 1, 0], d[:, 0, 1])
    assert np.isnan(d[:, 0, 2]).all()
    np.testing.assert_allclose(d[-1, 0, 1], s.distance_matrix()[0, 1])


def test_distance_matrices_on_the_decade_grid_read_each_history_at_powers_of_ten(tmp_path):
    from wpot.runs.store import decade_grid

    s = _store(tmp_path)
    s.commit(_rec(0, 0, 1.0, [[2e3, 3.0], [2e4, 1.0]]))
    s.commit(_rec(1, 1, 2.0, [[1.5e3, 2.0]]))
    s.commit(_rec(0, 1, 5.0, [[2e3, 9.0], [2e4, 6.0], [2e5, 5.0]]))
    betas, d = s.distance_matrices("decades")
    np.testing.assert_allclose(betas, [1e3, 1e4, 1e5, 1e6])
    # 1e3: below the pair's first beta; 1e4: the values at 2e3; then each history's last value at or below
    assert np.isnan(d[0, 0, 1])
    np.testing.assert_allclose(d[1:, 0, 1], [9 - 0.5 * (3 + 2), 6 - 0.5 * (1 + 2), 5 - 0.5 * (1 + 2)])
    b2, d2 = s.distance_matrices([1e4, 3e4])
    np.testing.assert_allclose(d2[:, 0, 1], [9 - 2.5, 6 - 1.5])
    np.testing.assert_allclose(decade_grid(np.array([1e3, 1e11])), 10.0 ** np.arange(3, 12))
    assert decade_grid(np.zeros(0)).size == 0
    for bad in ("decade", [1e4, 1e3], [0.0, 1.0], [np.nan]):
        with pytest.raises(ValueError, match="betas must"):
            s.distance_matrices(bad)


def test_discover_shapes_reads_a_folder_and_a_list_file(tmp_path):
    from wpot.examples import example_mesh
    from wpot.io import save_mesh

    for name in ["cat2", "cat10", "dog1"]:
        save_mesh(example_mesh(60), tmp_path / f"{name}.off")
    specs = discover_shapes(tmp_path)
    assert [s.name for s in specs] == ["cat2", "cat10", "dog1"]
    assert [s.labels["class"] for s in specs] == ["cat", "cat", "dog"]
    lst = tmp_path / "list.txt"
    lst.write_text("dog1.off\n# comment\ncat2.off\n")
    assert [s.name for s in discover_shapes(lst)] == ["dog1", "cat2"]
    with pytest.raises(FileNotFoundError, match="no such folder"):
        discover_shapes(tmp_path / "missing")
    with pytest.raises(ValueError, match="single mesh"):
        discover_shapes(tmp_path / "cat2.off")


# --------------------------------------------------------------------------- real runs (solver + WKS)




@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="module")
def clean_run(dataset, tmp_path_factory):
    from wpot.runs.loop import run_all_vs_all

    return run_all_vs_all(dataset, tmp_path_factory.mktemp("clean") / "run", progress=False, **FAST)


def test_run_matches_pairwise_compare_with_the_shared_grid(clean_run, dataset):
    from wpot.comparison import Comparer
    from wpot.io import load_mesh

    d = clean_run.distance_matrix()
    assert d.shape == (6, 6) and not np.isnan(d).any()
    np.testing.assert_array_equal(d, d.T)
    c = Comparer(energies=clean_run.get("energies"), **FAST)
    names = clean_run.names
    a, b = load_mesh(dataset / f"{names[0]}.off"), load_mesh(dataset / f"{names[4]}.off")
    assert c.compare(a, b).distance == pytest.approx(d[0, 4], rel=1e-10)
    assert clean_run.n_computations == 15 == len(clean_run.pair_rows())
    # the default solver is the exact LP: D(inf) only, no D(beta) at any finite beta (the annealing's are
    # tested in test_cli's classify report)
    histories = [json.loads(r["history"]) for r in clean_run.pair_rows()]
    assert all(len(h) == 1 and h[0][0] == np.inf for h in histories)
    betas, dm = clean_run.distance_matrices()
    assert betas.shape == (0,) and dm.shape == (0, 6, 6)


def test_rerun_of_a_finished_run_computes_nothing(clean_run, dataset):
    from wpot.runs.loop import run_all_vs_all

    again = run_all_vs_all(dataset, clean_run.folder, progress=False, **FAST)
    assert again.n_computations == 15


def test_mismatched_parameters_are_refused(clean_run, dataset):
    from wpot.runs.loop import run_all_vs_all

    with pytest.raises(RunMismatchError, match="n_eigen: stored 30, requested 31"):
        run_all_vs_all(dataset, clean_run.folder, progress=False, n_eigen=31, n_energies=30)
    with pytest.raises(RunMismatchError, match="transport"):
        run_all_vs_all(dataset, clean_run.folder, progress=False, transport="partial", **FAST)


def _count(db: Path, table: str) -> int:
    if not db.is_file():
        return 0
    try:
        with sqlite3.connect(db, timeout=5) as con:
            return int(con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
    except sqlite3.OperationalError:  # table not created yet
        return 0


def _write_lock_after(db: Path, n: int) -> sqlite3.Connection | None:
    """The run's write lock, held on the returned connection, once at least `n` pairs are committed; None (lock
    released) before. Holding it while the run is killed makes "killed mid-run" deterministic: the coordinator
    waits on the lock (its timeout is 60 s) and cannot commit the remaining pairs however fast they are."""
    if not db.is_file():
        return None
    con = sqlite3.connect(db, timeout=5, isolation_level=None)
    try:
        con.execute("BEGIN IMMEDIATE")
        done = int(con.execute("SELECT COUNT(*) FROM pairs").fetchone()[0])
    except sqlite3.OperationalError:  # table not created yet, or the lock is busy
        con.close()
        return None
    if done >= n:
        return con
    con.close()  # rolls back, releasing the lock
    return None


@pytest.mark.slow
def test_killed_parallel_run_resumes_without_recomputing(clean_run, dataset, tmp_path):
    run = tmp_path / "run"
    db = run / "wpot.sqlite"
    def cmd(jobs: int) -> list[str]:
        return [sys.executable, "-m", "wpot.cli", "all-vs-all", str(dataset), "--out", str(run), "--jobs", str(jobs), "--no-progress", *FAST_CLI]

    proc = subprocess.Popen(cmd(2), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    lock = None
    try:
        deadline = time.time() + 300
        while lock is None and proc.poll() is None and time.time() < deadline:
            lock = _write_lock_after(db, 3)
            time.sleep(0.02)
        assert proc.poll() is None, f"the run ended before it could be killed: {proc.stderr.read().decode()[-2000:]}"
        assert lock is not None, "3 pairs were not committed within 300 s"
        os.killpg(proc.pid, signal.SIGKILL)  # the coordinator and its worker processes, mid-run
    finally:
        proc.wait(timeout=60)
        if lock is not None:
            lock.close()
    done_before = _count(db, "pairs")
    assert 3 <= done_before < 15
    # resume in one process (the parallel path was exercised above; this keeps the test short)
    r = subprocess.run(cmd(1), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    with RunStore(run) as s:
        assert len(s.pair_rows()) == 15
        assert s.n_computations == 15  # every pair computed and committed exactly once, across both sessions
        rows = s.con.execute("SELECT i, j, COUNT(*) FROM computations GROUP BY i, j HAVING COUNT(*) > 1").fetchall()
        assert rows == []
        np.testing.assert_allclose(s.distance_matrix(), clean_run.distance_matrix(), rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(s.get("energies"), clean_run.get("energies"), rtol=1e-12)


def test_shape_warnings_from_workers_are_said_once_with_the_shape_name(tmp_path):
    """A warning raised while a worker process computes one shape's spectrum reaches the caller once,
    naming that shape (a worker would print it with no name, and a rerun would not say it again)."""
    import warnings

    from wpot.examples import example_mesh
    from wpot.io import save_mesh
    from wpot.mesh import Mesh
    from wpot.runs.loop import run_all_vs_all
    from wpot.spectral import SpectralWarning

    folder = tmp_path / "data"
    folder.mkdir()
    m = example_mesh(90, seed=0)
    save_mesh(m, folder / "one.off")
    save_mesh(example_mesh(97, seed=1), folder / "other.off")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the MeshWarning about the two components, said when it is read
        twin = Mesh(np.vstack([m.vertices, m.vertices + [5.0, 0, 0]]), np.vstack([m.faces, m.faces + m.n_vertices]))
    save_mesh(twin, folder / "twin.off")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_all_vs_all(folder, tmp_path / "run", jobs=2, progress=False, cache_dir=tmp_path / "cache", **FAST)
    said = [str(w.message) for w in caught if issubclass(w.category, SpectralWarning)]
    assert len(said) == 1 and said[0].startswith("twin: ") and "2 connected components" in said[0], said


def test_a_shape_that_repeats_another_is_named(tmp_path):
    """Two files holding the same mesh make a distance of 0 that flatters any 1-NN score: the run says which."""
    import shutil
    import warnings

    from wpot.runs.loop import run_all_vs_all
    from wpot.runs.shapes import repeated_shapes

    data = make_dataset(tmp_path / "data", n_per_class=2, n=60)
    shutil.copy(data / "blob1.off", data / "blob9.off")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run = run_all_vs_all(data, tmp_path / "run", progress=False, max_pairs=1, cache_dir=tmp_path / "c", **FAST)
    said = [str(w.message) for w in caught if "the same mesh" in str(w.message)]
    assert len(said) == 1 and "mesh (the same vertices and triangles): blob1 = blob9. " in said[0], said
    assert run.names == ["blob1", "blob2", "blob9", "flat1", "flat2"]
    rows = run.shape_rows()
    assert repeated_shapes([r[1] for r in rows], [r[3] for r in rows]) == [["blob1", "blob9"]]
    assert repeated_shapes(["a", "b"], ["x", "y"]) == []
