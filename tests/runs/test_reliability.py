"""Reliability of all-vs-all runs and readers (issue 22): one coordinator per run folder, damaged stores refused,
damaged cache files recomputed, edited meshes refused by name, failing and non-converging pairs recorded, and
a share of the reader fuzzing of benchmarks/fuzz_readers.py (which runs 100,000 inputs).

The measured figures (50 SIGKILLs, 100,000 fuzz inputs) come from benchmarks/fault_campaign.py and
benchmarks/fuzz_readers.py; these tests check each guarantee once, quickly."""
from __future__ import annotations

import concurrent.futures as cf
import re
import shutil
import sqlite3
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from helpers import make_dataset
from wpot.cache import Cache, CacheWarning
from wpot.runs.loop import run_all_vs_all
from wpot.runs.store import CorruptRunError, RunLockedError, RunMismatchError, RunStore, run_lock
from wpot.runs.workers import _worker_mesh, pair_task

TINY = {"n_eigen": 30, "n_energies": 30, "max_vertices": 50, "device": "cpu"}
TINY_CLI = ["--n-eigen", "30", "--n-energies", "30", "--max-vertices", "50", "--device", "cpu", "--no-progress"]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("reliability") / "data", n_per_class=2, n=60)


@pytest.fixture(scope="module")
def reference(data, tmp_path_factory) -> np.ndarray:
    """D(inf) of an uninterrupted inline run (with its cache in its own folder)."""
    with run_all_vs_all(data, tmp_path_factory.mktemp("ref") / "run", progress=False, **TINY) as s:
        return s.distance_matrix()


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "wpot.cli", *args], capture_output=True, text=True, timeout=timeout)


# ------------------------------------------------------------------------------ one coordinator per folder
@pytest.mark.slow
def test_a_second_run_on_a_locked_folder_is_refused_naming_the_folder(data, tmp_path):
    run = tmp_path / "run"
    with run_lock(run):  # another coordinator holds the folder
        with pytest.raises(RunLockedError, match=r"another wpot all-vs-all is running on the run folder .*run.*process"):
            run_all_vs_all(data, run, progress=False, **TINY)
        r = _cli("all-vs-all", str(data), "--out", str(run), *TINY_CLI)
        assert r.returncode == 2 and "another wpot all-vs-all is running on the run folder" in r.stderr
        assert str(run.resolve()) in r.stderr
        assert not (run / "wpot.sqlite").exists()  # refused before touching anything
    with run_all_vs_all(data, run, progress=False, max_pairs=1, **TINY) as s:  # released on exit
        assert len(s.done()) == 1


@pytest.mark.slow
def test_two_processes_started_at_once_cooperate_or_refuse(data, tmp_path, reference):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "wpot.cli", "all-vs-all", str(data), "--out", str(run), *TINY_CLI]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes in ([0, 0], [0, 2]), outs
    for p, (_, err) in zip(procs, outs):
        if p.returncode == 2:
            assert "another wpot all-vs-all is running on the run folder" in err
    with RunStore(run) as s:
        n = len(s.tasks())
        assert len(s.done()) == n and s.n_computations == n  # nothing lost, nothing computed twice
        np.testing.assert_array_equal(s.distance_matrix(), reference)


# ----------------------------------------------------------------------------------------- damaged store
def _big_store(folder: Path) -> Path:
    """A real store spanning many pages (60 shapes, 1770 pairs with long histories)."""
    shapes = [(f"s{k}", None, f"fp{k}", 10) for k in range(60)]
    with RunStore(folder, create=True) as s:
        s.initialize({"signature": "wks", "transport": "balanced"}, shapes, {})
        for i, j in s.tasks():
            s.commit({"i": i, "j": j, "energy": i + j / 100, "history": [[10.0**k, float(k)] for k in range(1, 12)],
                      "converged": True})
    return folder / "wpot.sqlite"


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "garbage", "zeroed pages", "empty", "other sqlite"])
def test_a_damaged_store_is_refused_by_name_never_read(tmp_path, damage):
    db = _big_store(tmp_path / "run")
    raw = db.read_bytes()
    assert len(raw) > 200_000
    if damage == "truncated":
        db.write_bytes(raw[: len(raw) // 2])
    elif damage == "garbage":
        db.write_bytes(b"this is not a database " * 100)
    elif damage == "zeroed pages":
        db.write_bytes(raw[:4096 * 3] + b"\0" * (4096 * 8) + raw[4096 * 11:])
    elif damage == "empty":
        db.write_bytes(b"")
    else:
        db.unlink()
        with sqlite3.connect(db) as con:
            con.execute("CREATE TABLE t(x)")
    with pytest.raises(CorruptRunError, match="wpot.sqlite") as exc:
        RunStore(tmp_path / "run")
    assert exc.value.path == str(db)
    r = _cli("classify", str(tmp_path / "run"))
    assert r.returncode == 2 and "wpot.sqlite" in r.stderr and "Traceback" not in r.stderr
    if damage != "empty":  # an empty file holds no run: a new run may start there
        with pytest.raises(CorruptRunError):
            RunStore(tmp_path / "run", create=True)
        assert db.stat().st_size > 0  # refused, not overwritten


def test_a_store_locked_by_another_process_is_waited_for_not_called_damaged(tmp_path):
    """A store another process is writing (its write lock held on a rollback-journal file, as a run's file is
    before its first opener switches it to WAL) is busy, not damaged: opening it waits for the lock."""
    import subprocess
    import sys
    import time

    RunStore(tmp_path / "run", create=True).close()
    db = tmp_path / "run" / "wpot.sqlite"
    with sqlite3.connect(db, isolation_level=None) as con:
        con.execute("PRAGMA journal_mode=DELETE")
    con.close()
    holder = subprocess.Popen([sys.executable, "-c", f"""
import sqlite3, time
con = sqlite3.connect({str(db)!r}, isolation_level=None)
con.execute('BEGIN IMMEDIATE')
print('held', flush=True)
time.sleep(1.0)
con.execute('COMMIT')
"""], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        t0 = time.monotonic()
        with RunStore(tmp_path / "run") as store:  # the code before this test said "damaged (database is locked)"
            assert time.monotonic() - t0 > 0.2  # it did wait for the writer
            assert store.con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    finally:
        holder.wait(timeout=30)


# ----------------------------------------------------------------------------------- damaged cache files
def test_damaged_signature_and_spectrum_cache_files_are_recomputed_to_the_same_numbers(data, tmp_path, reference):
    cache = tmp_path / "cache"
    run_all_vs_all(data, tmp_path / "run1", progress=False, cache_dir=cache, **TINY).close()
    files = sorted(cache.rglob("*.npz"))
    kinds = {p.parent.name for p in files}
    assert {"signatures", "spectrum"} <= kinds, kinds
    for k, p in enumerate(files):
        raw = bytearray(p.read_bytes())
        if k % 3 == 0:
            raw = raw[: len(raw) // 2]
        elif k % 3 == 1:
            raw[len(raw) // 2] ^= 0xFF  # one flipped byte in the array data: the zip CRC catches it
        else:
            raw = bytearray(b"garbage")
        p.write_bytes(bytes(raw))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with run_all_vs_all(data, tmp_path / "run2", progress=False, cache_dir=cache, **TINY) as s:
            np.testing.assert_array_equal(s.distance_matrix(), reference)
    # every damaged file detected, by name, and said with the shape it belongs to ("blob1: corrupt cache ...")
    named = {str(w.message).split(" (")[0].split(": ", 1)[-1] for w in caught if issubclass(w.category, CacheWarning)}
    assert {f"corrupt cache entry {p}" for p in files} <= named
    assert all(re.match(r"\w+: corrupt cache entry ", str(w.message)) for w in caught
               if issubclass(w.category, CacheWarning))


def test_a_flipped_data_byte_is_caught_by_the_checksum(tmp_path):
    c = Cache("unit", cache_dir=tmp_path)
    c.put("fp", {"k": 1}, {"x": np.arange(4096.0)})
    path = c.path_for(c.key("fp", {"k": 1}))
    raw = bytearray(path.read_bytes())
    at = raw.find(np.arange(4096.0)[2000:2001].tobytes())
    assert at > 0
    raw[at] ^= 0x01  # 2000.0 becomes another valid float: only the CRC can tell
    path.write_bytes(bytes(raw))
    with pytest.warns(CacheWarning, match="Bad CRC-32"):
        assert Cache("unit", cache_dir=tmp_path).get("fp", {"k": 1}) is None


# --------------------------------------------------------------------------------------- edited meshes
@pytest.mark.slow
def test_a_mesh_edited_between_run_and_resume_is_refused_by_name(data, tmp_path):
    d = tmp_path / "data"
    shutil.copytree(data, d)
    run = tmp_path / "run"
    run_all_vs_all(d, run, progress=False, max_pairs=2, **TINY).close()
    target = sorted(d.glob("*.off"))[1]
    text = target.read_text().splitlines()
    head = 2  # "OFF", counts; the first vertex line follows
    x, y, z = map(float, text[head].split())
    text[head] = f"{x + 1e-9!r} {y} {z}"  # a sub-nanometre edit
    target.write_text("\n".join(text) + "\n")
    with pytest.raises(RunMismatchError, match=rf"content of 1 of them changed since the run began: {target.stem}\."):
        run_all_vs_all(d, run, progress=False, **TINY)
    r = _cli("all-vs-all", str(d), "--out", str(run), *TINY_CLI)
    assert r.returncode == 2 and f"changed since the run began: {target.stem}" in r.stderr
    with RunStore(run) as s:
        assert len(s.done()) == 2  # nothing mixed in


def test_a_worker_refuses_a_file_edited_during_the_run(data, tmp_path):
    from wpot.io import load_mesh
    from wpot.runs.workers import _mesh_at

    p = tmp_path / "m.off"
    shutil.copy(sorted(data.glob("*.off"))[0], p)
    fp = load_mesh(p).fingerprint
    _mesh_at.cache_clear()  # each call below is a fresh worker reading the file
    assert _worker_mesh((str(p), fp), {}).fingerprint == fp
    p.write_text(p.read_text().replace("\n", "\n\n", 3).replace("OFF\n\n", "OFF\n", 1) + "\n")  # the same mesh
    _mesh_at.cache_clear()
    assert _worker_mesh((str(p), fp), {}).fingerprint == fp  # the content counts, not the bytes
    shutil.copy(sorted(data.glob("*.off"))[1], p)  # another mesh under the same name
    _mesh_at.cache_clear()
    with pytest.raises(ValueError, match=r"m\.off changed while the run was going"):
        _worker_mesh((str(p), fp), {})


# ------------------------------------------------------------------------------ failing and stuck pairs
class FailingExecutor(cf.ThreadPoolExecutor):
    """Runs tasks in a thread; pair ``bad`` raises what the solver raises on a NaN cost."""

    def __init__(self, bad: tuple[int, int]) -> None:
        super().__init__(max_workers=1)
        self.bad = bad

    def submit(self, fn, *args, **kwargs):
        if fn is pair_task and tuple(args[:2]) == self.bad:
            fut: cf.Future = cf.Future()
            fut.set_exception(ValueError("cost matrix has 3 non-finite entries"))
            return fut
        return super().submit(fn, *args, **kwargs)


def test_a_failing_pair_is_recorded_named_and_retried(data, tmp_path, reference):
    run = tmp_path / "run"
    with pytest.warns(UserWarning, match=r"1 pairs failed .*non-finite entries.*rerun the same command"):
        store = run_all_vs_all(data, run, progress=False, executor=FailingExecutor((0, 2)), **TINY)
    with store:
        assert store.failures() == [(0, 2, "ValueError: cost matrix has 3 non-finite entries")]
        assert (0, 2) not in store.done() and np.isnan(store.distance_matrix()[0, 2])  # missing, never a number
    with run_all_vs_all(data, run, progress=False, **TINY) as s:  # the rerun retries it
        assert s.failures() == [] and s.n_computations == len(s.tasks())
        np.testing.assert_array_equal(s.distance_matrix(), reference)


@pytest.mark.slow
def test_non_converged_pairs_are_flagged_in_the_store_and_the_report(data, tmp_path):
    run = tmp_path / "run"
    with run_all_vs_all(data, run, progress=False, solver_options={"max_iter": 1, "method": "anneal"}, **TINY) as s:
        n = len(s.tasks())
        assert s.con.execute("SELECT COUNT(*) FROM pairs WHERE converged = 0").fetchone()[0] == n
        assert not s.converged_matrix()[0, 1]
    r = _cli("classify", str(run))
    assert f"{n} of {n} pairs did not converge" in r.stdout + r.stderr


# ----------------------------------------------------------------------------------------- reader fuzzing
def _fuzzer():
    import importlib

    return importlib.import_module("benchmarks.fuzz_readers")


@pytest.mark.slow
def test_readers_raise_only_value_or_os_errors_on_generated_inputs(tmp_path):
    import signal

    fz = _fuzzer()

    def hang(signum, frame):
        raise TimeoutError("a reader ran past 10 s")

    old = signal.signal(signal.SIGALRM, hang)
    kinds: dict[str, int] = {}
    try:
        for fmt, blob in fz.generate(400, seed=12345):
            signal.alarm(10)
            try:
                kind, msg = fz.run_one(fmt, blob, tmp_path)
            finally:
                signal.alarm(0)
            assert kind not in ("other", "memory"), f"{fmt}: {msg}"
            kinds[kind] = kinds.get(kind, 0) + 1
    finally:
        signal.signal(signal.SIGALRM, old)
    assert kinds.get("ok", 0) > 0 and kinds.get("ValueError", 0) > 200  # both paths exercised


def test_a_mat_file_with_an_unknown_data_type_is_refused_not_a_crash(tmp_path):
    # scipy's loadmat dies with SIGSEGV on this (fuzz_readers.py found it); wpot walks the tags first
    import io
    import struct

    import scipy.io

    from wpot.examples import example_mesh
    from wpot.io import load_mesh

    m = example_mesh(50, seed=1)
    buf = io.BytesIO()
    scipy.io.savemat(buf, {"shape": {"VERT": m.vertices, "TRIV": (m.faces + 1).astype(np.float64)}})
    raw = bytearray(buf.getvalue())
    tag = struct.pack("<II", 9, m.vertices.nbytes)  # VERT's data: miDOUBLE, N x 3 x 8 bytes
    at = raw.find(tag)
    assert at > 128
    raw[at:at + 4] = struct.pack("<I", 0xA309)
    p = tmp_path / "bad.mat"
    p.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"bad\.mat: malformed MATLAB file: unknown MAT data type 41737"):
        load_mesh(p)
