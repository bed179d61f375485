"""All-vs-all on a real local Dask cluster (two worker processes): a worker killed mid-pair loses only that
pair, a pair that keeps killing its worker is recorded as a failure, and the final matrix is the inline one.
Also the per-worker device choice (a pure function) and ``wpot all-vs-all --scheduler``."""
from __future__ import annotations

import concurrent.futures as cf
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import FAST, FAST_CLI, make_dataset
from wpot.runs.loop import run_all_vs_all
from wpot.runs.store import RunStore
from wpot.runs.workers import choose_worker_device, pair_task

#: a real local Dask cluster: slow (deselect with -m "not slow")
pytestmark = pytest.mark.slow

distributed = pytest.importorskip("distributed", reason="Dask's distributed is not installed (pip install 'wpot[cluster]')")


# ------------------------------------------------------------------------ device choice (pure function)
@pytest.mark.parametrize(
    "name, cuda_count, env, want",
    [
        (0, 0, {}, "cpu"),  # no GPU: the CPU, whatever the name
        ("tcp://10.0.0.5:4100", 0, {"CUDA_VISIBLE_DEVICES": "3"}, "cpu"),
        (0, 4, {}, "cuda:0"),  # LocalCluster names 0, 1, ...: spread over the machine's GPUs
        (5, 4, {}, "cuda:1"),
        ("7", 2, {}, "cuda:1"),
        ("node3-2", 4, {}, "cuda:2"),  # dask worker --name node3 --nworkers 4
        (3, 4, {"CUDA_VISIBLE_DEVICES": "2,3,0,1"}, "cuda:0"),  # the launcher chose: first visible GPU
        (3, 4, {"CUDA_VISIBLE_DEVICES": " "}, "cuda:3"),  # blank: no choice made
        ("tcp://10.0.0.5:4100", 2, {}, None),  # no rank in the name: Warp's default device
        (True, 2, {}, None),
        (1, 4, {"WPOT_DEVICE": "cpu"}, "cpu"),  # the operator's explicit choice wins
        (1, 0, {"WPOT_DEVICE": "cuda:1"}, "cuda:1"),
    ],
)
def test_worker_device_choice(name, cuda_count, env, want):
    assert choose_worker_device(worker_name=name, cuda_count=cuda_count, env=env) == want


def test_worker_device_choice_rejects_a_negative_count():
    with pytest.raises(ValueError, match="cuda_count must be >= 0, got -1"):
        choose_worker_device(worker_name=0, cuda_count=-1, env={})


def test_every_local_worker_gets_its_own_gpu():
    names = list(range(8))
    got = [choose_worker_device(worker_name=n, cuda_count=4, env={}) for n in names]
    assert got == ["cuda:0", "cuda:1", "cuda:2", "cuda:3"] * 2


# ------------------------------------------------------------------------------- a real local cluster
@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("dask-data"), n_per_class=2, n=60)  # 4 shapes, 6 pairs


@pytest.fixture(scope="module")
def inline_run(dataset, tmp_path_factory) -> RunStore:
    return run_all_vs_all(dataset, tmp_path_factory.mktemp("inline") / "run", progress=False, **FAST)


@pytest.fixture(scope="module")
def cluster():
    import dask
    from distributed import Client, LocalCluster

    # a task may be in two worker deaths and be retried; the third marks it bad (KilledWorker). Two, not one: a
    # pair killed once can be queued on the worker that the poisoned pair kills next, and then it is in two deaths
    # without a fault of its own (seen under load)
    with dask.config.set({"distributed.scheduler.allowed-failures": 2}):
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0") as lc:
            with Client(lc) as client:
                yield lc, client


def _killer(marker: str, once: bool, fn, *args):
    """Run a pair task and SIGKILL this worker process part-way through it (before it can return).

    ``once``: only when ``marker`` does not exist yet (it is created first), so the retry succeeds;
    otherwise every attempt dies. Each attempt appends this process's pid to ``marker + ".pids"``."""
    with open(marker + ".pids", "a") as f:
        f.write(f"{os.getpid()}\n")
    if once and os.path.exists(marker):
        return fn(*args)
    Path(marker).touch()
    threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGKILL)).start()
    fn(*args)
    time.sleep(60)  # the pair finished before the timer: die anyway, with its result unreturned


class KillingExecutor(cf.Executor):
    """The cluster's executor, with pair ``kill_once`` killing its worker once and ``poison`` every time."""

    def __init__(self, inner: cf.Executor, folder: Path, kill_once: tuple[int, int], poison: tuple[int, int]):
        self.inner, self.folder, self.kill_once, self.poison = inner, folder, kill_once, poison

    def submit(self, fn, *args, **kwargs):
        if fn is pair_task and tuple(args[:2]) in (self.kill_once, self.poison):
            once = tuple(args[:2]) == self.kill_once
            marker = str(self.folder / f"pair-{args[0]}-{args[1]}")
            return self.inner.submit(_killer, marker, once, fn, *args, **kwargs)
        return self.inner.submit(fn, *args, **kwargs)

    def max_in_flight(self) -> int:
        return self.inner.max_in_flight()

    def shutdown(self, wait=True, *, cancel_futures=False):
        pass


def _pids(path: Path) -> list[int]:
    return [int(x) for x in path.read_text().split()] if path.exists() else []


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _assert_committed_once(store: RunStore, n: int) -> None:
    assert len(store.pair_rows()) == n and store.n_computations == n
    dup = store.con.execute("SELECT i, j, COUNT(*) FROM computations GROUP BY i, j HAVING COUNT(*) > 1").fetchall()
    assert dup == []


def test_killed_worker_loses_only_its_pair_and_the_cli_runs_on_the_cluster(cluster, dataset, inline_run, tmp_path):
    """One test for everything that needs the cluster, so that pytest-xdist starts it once."""
    import cloudpickle

    from wpot.runs.workers import DaskExecutor

    lc, client = cluster
    marks = tmp_path / "marks"
    marks.mkdir()
    ex = KillingExecutor(DaskExecutor(client), marks, kill_once=(0, 2), poison=(1, 3))
    run = tmp_path / "run"
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import this test module
    try:
        with pytest.warns(UserWarning, match="1 pairs failed"):
            store = run_all_vs_all(dataset, run, executor=ex, progress=False, **FAST)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])

    # the worker computing pair (0, 2) died; another process computed the pair again and it was committed
    killed = _pids(marks / "pair-0-2.pids")
    # once killed, then completed; Dask computes it once more when the worker holding the finished result dies
    # (the poisoned pair may kill it) before the result reaches the client
    assert len(killed) >= 2 and killed[0] != killed[1]
    assert not _alive(killed[0])
    row = next(r for r in store.pair_rows() if (r["i"], r["j"]) == (0, 2))
    assert int(row["worker"].split("@")[0].rsplit(":", 1)[1]) in killed[1:]
    assert row["worker"].endswith("@cpu")  # the worker's own device choice: no GPU here

    # pair (1, 3) killed a worker at each of its 3 attempts (allowed-failures = 2): recorded, the run went on
    assert len(_pids(marks / "pair-1-3.pids")) == 3
    fails = store.failures()
    assert [(i, j) for i, j, _ in fails] == [(1, 3)] and "KilledWorker" in fails[0][2]
    assert store.done() == set(store.tasks()) - {(1, 3)}
    _assert_committed_once(store, 5)
    store.close()

    # rerunning on the (restarted) cluster computes only the failed pair; the matrix is the inline one
    store = run_all_vs_all(dataset, run, executor=client.get_executor(), progress=False, **FAST)  # plain: all at once
    with store:
        _assert_committed_once(store, 6)
        assert store.failures() == []
        np.testing.assert_allclose(store.distance_matrix(), inline_run.distance_matrix(), rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(store.get("energies"), inline_run.get("energies"), rtol=1e-12)
    client.wait_for_workers(2, timeout=120)  # the nannies restart killed workers (raises if they do not)

    # the CLI on the same cluster, by its address
    cli_run = tmp_path / "cli-run"
    cmd = [sys.executable, "-m", "wpot.cli", "all-vs-all", str(dataset), "--out", str(cli_run), "--no-progress", *FAST_CLI]
    r = subprocess.run([*cmd, "--scheduler", lc.scheduler_address], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "6 of 6 pairs" in r.stdout
    worker_pids = set(client.run(os.getpid).values())
    with RunStore(cli_run) as s:
        pids = {int(w["worker"].split("@")[0].rsplit(":", 1)[1]) for w in s.pair_rows()}
        assert pids <= worker_pids  # every pair ran on the cluster, none in the CLI's process
        _assert_committed_once(s, 6)
        np.testing.assert_allclose(s.distance_matrix(), inline_run.distance_matrix(), rtol=1e-10, atol=1e-14)
    # --jobs means nothing for a running cluster: refused rather than ignored
    r = subprocess.run([*cmd, "--scheduler", lc.scheduler_address, "--jobs", "4"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--jobs sets local processes" in r.stderr


def test_embedded_local_cluster_workers_choose_their_device():
    from wpot.runs.workers import _task_device, dask_executor

    assert _task_device({"device": None}) is None  # not on Dask: Warp's default, as before
    with dask_executor("local", n_workers=1) as ex:
        assert ex.submit(os.getpid).result() != os.getpid()  # a worker process, not this one
        assert ex.submit(_task_device, {"device": None}).result() == "cpu"  # its own choice: no CUDA here
        assert ex.submit(_task_device, {"device": "cpu"}).result() == "cpu"
        assert ex.max_in_flight() == 1  # one worker, one thread: one pair in flight
        # a stopped run closes the scheduler under a busy worker: its heartbeat's failure is not printed, the rest is
        passes = logging.getLogger("distributed.worker").filter  # a logger pickles by name: the worker's own
        for msg, kept in [("Failed to communicate with scheduler during heartbeat.", False),
                          ("Unexpected exception during heartbeat. Closing worker.", True)]:
            record = logging.LogRecord("distributed.worker", logging.ERROR, __file__, 1, msg, None, None)
            assert bool(ex.submit(passes, record).result()) is kept, msg
        assert passes(record)  # and this process's logger is left as it was
    with pytest.raises(ValueError, match="scheduler must be"):
        with dask_executor("localhost:8786"):
            pass


def test_cli_scheduler_errors_are_one_line(dataset, tmp_path):
    base = ["all-vs-all", str(dataset), "--out", str(tmp_path / "r"), "--no-progress", *FAST_CLI]
    r = subprocess.run([sys.executable, "-m", "wpot.cli", *base, "--scheduler", "nowhere"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--scheduler must be \"local\" or a Dask address" in r.stderr and "'nowhere'" in r.stderr
    # without Dask installed, --scheduler names the extra to install (simulated: distributed made unimportable)
    code = "import sys; sys.modules['distributed'] = None; from wpot.cli import main; sys.exit(main(sys.argv[1:]))"
    r = subprocess.run([sys.executable, "-c", code, *base, "--scheduler", "local"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "pip install 'wpot[cluster]'" in r.stderr and "Traceback" not in r.stderr
