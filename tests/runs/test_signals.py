"""Stopping with signals (issue 43): Ctrl-C twice never hangs, a first Ctrl-C stops within 5 s, SIGTERM stops the
whole run; the stored pairs are kept, no process of the run is left, and a rerun resumes to the uninterrupted run's
D(inf) bit for bit, with no pair committed twice. Real ``wpot`` subprocesses in their own process group, on small
generated meshes, signalled once a first pair is stored (`benchmarks.fault_campaign.signal_run`, which the signal
campaign, ``python benchmarks/fault_campaign.py --signals``, runs at random moments)."""
from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import make_dataset

from benchmarks.fault_campaign import signal_run, store_consistent
from wpot.runs.loop import run_all_vs_all
from wpot.runs.store import RunStore

TINY = {"n_eigen": 30, "n_energies": 30, "max_vertices": 300, "device": "cpu"}
TINY_CLI = ["--n-eigen", "30", "--n-energies", "30", "--max-vertices", "300", "--device", "cpu", "--no-progress"]
MODES = {"inline": ["--jobs", "1"], "jobs2": ["--jobs", "2"], "dask": ["--scheduler", "local", "--jobs", "2"]}

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """8 shapes of 300 vertices, 28 pairs, each transported at every vertex: the pairs after the first take about
    2 s, ten times `signal_run`'s poll, so a signal sent once the first is stored lands mid-run (with 60-vertex
    shapes they took 0.4 s, and a run once finished before the signal came)."""
    return make_dataset(tmp_path_factory.mktemp("signals") / "data", n_per_class=4, n=300)


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    """One signature cache for every run here (the signatures are the same; the runs then go straight to pairs)."""
    return tmp_path_factory.mktemp("signals-cache")


@pytest.fixture(scope="module")
def reference(data, cache, tmp_path_factory) -> np.ndarray:
    """D(inf) of an uninterrupted run."""
    with run_all_vs_all(data, tmp_path_factory.mktemp("ref") / "run", progress=False, cache_dir=str(cache), **TINY) as s:
        return s.distance_matrix()


def _env(cache: Path) -> dict[str, str]:
    return dict(os.environ, WPOT_CACHE_DIR=str(cache))


def _wpot(*args: str) -> list[str]:
    return [sys.executable, "-m", "wpot", *args]


def _check_resumes(run: Path, data: Path, cache: Path, reference: np.ndarray, pairs_before: int) -> None:
    """The stopped run's store is consistent and kept every pair stored before the signal; a rerun finishes it
    to the reference bit for bit, every pair committed once."""
    assert store_consistent(run)
    with RunStore(run) as s:
        n_stopped, n_tasks = len(s.done()), len(s.tasks())
        assert not s.failures()  # a stop is not a failure
    assert pairs_before <= n_stopped < n_tasks  # stopped mid-run; nothing stored was lost
    with run_all_vs_all(data, run, progress=False, cache_dir=str(cache), **TINY) as s:  # the rerun resumes
        np.testing.assert_array_equal(s.distance_matrix(), reference)
        assert len(s.done()) == n_tasks and s.n_computations == n_tasks  # no pair committed twice


CASES = [  # (mode, signals): each signal case in each mode, but not every pairing (the suite's time)
    ("inline", "SIGINT"), ("inline", "SIGTERM"),
    ("jobs2", "SIGINT"), ("jobs2", "SIGINT SIGINT"), ("jobs2", "SIGTERM"),
    ("dask", "SIGINT SIGINT"), ("dask", "SIGTERM"),
]


@pytest.mark.parametrize("mode,signals", CASES, ids=[f"{m}-{s.replace(' ', 'x')}" for m, s in CASES])
def test_a_signalled_run_stops_within_5_s_leaves_no_process_and_resumes_bit_for_bit(
        mode, signals, data, cache, reference, tmp_path):
    if mode == "dask":
        pytest.importorskip("distributed", reason="--scheduler local needs Dask's distributed (pip install 'wpot[cluster]')")
    sigs = tuple(getattr(signal, name) for name in signals.split())
    run = tmp_path / "run"
    st = signal_run(_wpot("all-vs-all", str(data), "--out", str(run), *TINY_CLI, *MODES[mode]), run, sigs,
                    gap=1.5, env=_env(cache))
    assert st.returncode is not None, f"hung: no exit 30 s after {signals}\n{st.stderr}"
    first = sigs[0]
    words = "Ctrl-C (SIGINT)" if first == signal.SIGINT else "SIGTERM"
    assert f"wpot: stopping on {words}" in st.stderr  # said at once, before any clean-up
    assert st.seconds < 5.0, (st.seconds, st.stderr)
    if st.sent == 1 or "stopped at once" not in st.stderr:  # the first signal's clean stop
        # (a second signal that lands while the stopped interpreter exits ends it by that signal: stopped all the same)
        assert st.returncode == 128 + first or (st.sent == 2 and st.returncode == -sigs[1]), st.stderr
        assert f"wpot: all-vs-all stopped by {words}" in st.stderr
        assert "rerun the same command to resume" in st.stderr and "Traceback" not in st.stderr
    else:  # the second one came while it stopped: at once, with the second's code
        assert st.returncode == 128 + sigs[1], st.stderr
    assert st.left == [], f"processes of the run still alive 10 s after it exited: {st.left}"
    _check_resumes(run, data, cache, reference, st.pairs_before)


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signalled_compare_says_it_stopped_without_talking_of_a_run(signame, tmp_path):
    """compare (as retrieve and every command but all-vs-all): a short line naming the signal, exit 130 / 143."""
    data = make_dataset(tmp_path / "data", n_per_class=1, n=900)
    sig = getattr(signal, signame)
    out = tmp_path / "cmp"
    st = signal_run(_wpot("compare", str(data / "blob1.off"), str(data / "flat1.off"), "--progress", "--device", "cpu",
                          "--out", str(out)), out, (sig,), ready_text="spectrum of B")  # while it computes it
    words = "Ctrl-C (SIGINT)" if sig == signal.SIGINT else "SIGTERM"
    assert st.returncode == 128 + sig and st.seconds < 5.0, st
    assert st.stderr.strip().splitlines()[-1] == f"wpot: compare stopped by {words}", st.stderr
    assert "resume" not in st.stderr and "Traceback" not in st.stderr
    assert st.left == []
