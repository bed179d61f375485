"""wpot.stopping: the first SIGINT or SIGTERM says "stopping" at once and raises `Interrupted`; a second one, or a
stop that takes over GRACE seconds, stops at once; a swallowed stop is raised again by `check_stop`; a
`deferred_stop` block is not broken into; the process pool's workers start with SIGINT ignored. Real signals sent
to this process (the hard stop itself is replaced by a recorder); the subprocess runs are in tests/runs/test_signals.py."""
from __future__ import annotations

import concurrent.futures as cf
import os
import signal
import time

import pytest

from wpot import stopping
from wpot.stopping import (
    Interrupted,
    check_stop,
    deferred_stop,
    exit_code,
    stop_on_signals,
    stopped_message,
    worker_context,
)


@pytest.fixture
def hard_stops(monkeypatch) -> list[tuple]:
    """The hard stops asked for (instead of ending the test process), and this process's handlers put back."""
    calls: list[tuple] = []
    monkeypatch.setattr(stopping, "hard_stop", lambda signum, note="", **kw: calls.append((signum, note, kw)))
    previous = {s: signal.getsignal(s) for s in stopping.SIGNALS}
    yield calls
    for s, h in previous.items():
        signal.signal(s, h)


def _signal(signum: int) -> None:
    os.kill(os.getpid(), signum)
    time.sleep(0.05)  # the handler runs in this (the main) thread at its next instruction


@pytest.mark.parametrize("signum,code,words", [(signal.SIGINT, 130, "Ctrl-C (SIGINT)"), (signal.SIGTERM, 143, "SIGTERM")])
def test_the_first_signal_says_stopping_at_once_and_raises_interrupted(signum, code, words, hard_stops, capfd):
    with pytest.raises(Interrupted) as exc:
        with stop_on_signals(doing="the stored pairs are kept") as state:
            _signal(signum)
            pytest.fail("not interrupted")
    state.late.cancel()
    assert exc.value.signum == signum and exit_code(exc.value) == code
    err = capfd.readouterr().err
    assert f"wpot: stopping on {words}: the stored pairs are kept; " in err and "stops at once" in err
    assert stopped_message(exc.value, "compare") == f"wpot: compare stopped by {words}"
    assert stopped_message(Interrupted(signum, "2 of 6 pairs stored"), None) == f"wpot: stopped by {words}: 2 of 6 pairs stored"
    assert exit_code(KeyboardInterrupt()) == 130 and hard_stops == []


def test_a_second_signal_stops_at_once_with_its_own_code(hard_stops):
    with stop_on_signals(after_hard_stop="rerun to resume") as state:
        try:
            _signal(signal.SIGINT)
        except Interrupted:  # the stop is under way (a clean-up that takes its time) when the second one comes
            _signal(signal.SIGTERM)
    state.late.cancel()
    assert hard_stops == [(signal.SIGTERM, "rerun to resume", {})]


def test_after_a_stop_a_signal_while_the_interpreter_ends_exits_with_the_first_code(hard_stops, monkeypatch):
    exits = []
    monkeypatch.setattr(stopping.os, "_exit", exits.append)
    with pytest.raises(Interrupted), stop_on_signals() as state:
        _signal(signal.SIGTERM)
    state.late.cancel()
    _signal(signal.SIGINT)  # the command said it stopped; the interpreter is ending
    assert exits == [143] and hard_stops == []


def test_a_stop_that_takes_longer_than_grace_ends_at_once(hard_stops, monkeypatch):
    monkeypatch.setattr(stopping, "GRACE", 0.2)
    with pytest.raises(Interrupted):
        with stop_on_signals(after_hard_stop="rerun to resume"):
            _signal(signal.SIGTERM)
    time.sleep(0.5)
    assert hard_stops == [(signal.SIGTERM, "the stop took over 0.2 s; rerun to resume", {"second": False})]


def test_a_swallowed_stop_is_raised_again_by_check_stop(hard_stops):
    check_stop()  # outside stop_on_signals: nothing to do
    with pytest.raises(Interrupted):
        with stop_on_signals() as state:
            try:  # a library that catches BaseException (trimesh around its imports)
                _signal(signal.SIGINT)
            except BaseException:
                pass
            check_stop()
    state.late.cancel()


def test_a_stop_that_lands_in_a_finalizer_is_not_printed_and_is_raised_again(hard_stops, monkeypatch):
    """Python cannot raise from a __del__ (a Warp array freed while the signal arrives): it hands the exception
    to sys.unraisablehook, which prints a traceback. Inside the block an `Interrupted` is kept from that hook
    (`check_stop` raises it again); anything else still reaches it, and the hook comes back after."""
    import sys

    seen: list = []
    monkeypatch.setattr(sys, "unraisablehook", lambda info: seen.append(type(info.exc_value)))
    before = sys.unraisablehook

    class Freed:
        def __del__(self):
            _signal(signal.SIGINT)

    class Broken:
        def __del__(self):
            raise ValueError("a real error in a finalizer")

    with pytest.raises(Interrupted):
        with stop_on_signals() as state:
            Freed()  # dropped at once: the signal's Interrupted is raised inside __del__
            Broken()
            assert seen == [ValueError]
            check_stop()
    state.late.cancel()
    assert sys.unraisablehook is before


def test_a_deferred_block_is_not_broken_into_and_stops_when_it_ends(hard_stops, capfd):
    done = []
    with pytest.raises(Interrupted):
        with stop_on_signals() as state:
            with deferred_stop():
                _signal(signal.SIGINT)
                assert "wpot: stopping on Ctrl-C (SIGINT)" in capfd.readouterr().err  # said at once
                done.append(True)  # the block goes on
            pytest.fail("not stopped when the block ended")
    state.late.cancel()
    assert done == [True]
    with pytest.raises(Interrupted):  # a block that fails after the signal (it reached what the block started)
        with stop_on_signals() as state:
            with deferred_stop():
                _signal(signal.SIGTERM)
                raise RuntimeError("Nanny failed to start")
    state.late.cancel()
    with pytest.raises(RuntimeError), stop_on_signals():  # without a signal a failure is a failure
        with deferred_stop():
            raise RuntimeError("no signal")


def test_the_process_pool_workers_start_with_sigint_ignored():
    before = signal.getsignal(signal.SIGINT)
    with cf.ProcessPoolExecutor(max_workers=1, mp_context=worker_context()) as pool:
        assert pool.submit(signal.getsignal, signal.SIGINT).result(timeout=60) == signal.SIG_IGN
    assert signal.getsignal(signal.SIGINT) is before  # this process's own handler is back


def test_a_signal_ignored_from_the_start_stays_ignored(hard_stops):
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job of a script, as bash starts it
    with stop_on_signals() as state:
        _signal(signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    assert state.signum is None and hard_stops == []
