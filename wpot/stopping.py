"""Stopping cleanly on Ctrl-C (SIGINT) and SIGTERM (what ``timeout``, systemd and SLURM send).

The ``wpot`` command runs under `stop_on_signals` (`wpot.cli.main`):

* the first SIGINT or SIGTERM writes ``wpot: stopping on ...`` to standard error at once and raises
  `Interrupted` (a `KeyboardInterrupt`) in the main thread. What runs unwinds: `wpot.run_all_vs_all` stops its
  workers without waiting for the pairs they are computing (it kills its process pool's processes; a local Dask
  cluster's workers are closed at once) and keeps every pair stored so far; the command then says what was
  stopped and what was kept, and exits with 128 + the signal's number (130 for SIGINT, 143 for SIGTERM);
* a second one (either signal) while that happens stops at once (`hard_stop`): every process this one started is
  killed (SIGKILL) and the process exits without waiting for anything. So does a first one whose stop has not
  ended `GRACE` seconds later, so that no stop hangs;
* a library that catches ``BaseException`` where the signal lands (trimesh does, around its imports) swallows
  the `Interrupted`; the run's loops call `check_stop` between steps, which raises it again. A block that must
  not be broken into (starting a local Dask cluster) runs under `deferred_stop`: the signal is said at once and
  raised when the block ends.

Nothing stored is lost either way: the run store commits each pair in one SQLite transaction (WAL), so a stop at
any moment keeps every committed pair and no part of another.

Workers leave the decision to the coordinator, since a Ctrl-C in a terminal (and SIGTERM from ``timeout`` or
SLURM) reaches every process of the group:

* process-pool workers (`pool_worker_setup`, the pool's initializer) ignore SIGINT and exit on their own when
  their parent is gone (`exit_with_parent`: a thread that polls ``os.getppid()``), so a coordinator killed with
  SIGKILL leaves no worker behind. They keep SIGTERM's default (exit): `concurrent.futures` stops a broken pool's
  workers with it;
* a local Dask cluster's workers (`dask_setup`, run as each worker's preload) ignore SIGINT and SIGTERM, so that
  their nanny does not restart a worker that a signal to the group killed while the coordinator closes the
  cluster; Dask stops them when their parent process ends.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import signal
import sys
import threading
import time
from typing import Any, Iterator

__all__ = ["GRACE", "Interrupted", "Stopping", "check_stop", "dask_setup", "deferred_stop", "exit_code",
           "exit_with_parent", "hard_stop", "kill_children", "pool_worker_setup", "signal_words", "stop_on_signals",
           "stopped_message", "worker_context"]

#: the signals that stop a command
SIGNALS = (signal.SIGINT, signal.SIGTERM)


def signal_words(signum: int) -> str:
    """How a message names a signal: ``"Ctrl-C (SIGINT)"``, ``"SIGTERM"``."""
    if signum == signal.SIGINT:
        return "Ctrl-C (SIGINT)"
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class Interrupted(KeyboardInterrupt):
    """A command or run stopped by a signal (a `KeyboardInterrupt`, so that ``except Exception`` never swallows it).

    Attributes
    ----------
    signum : the signal (`signal.SIGINT` for a plain Ctrl-C)
    detail : what was stopped and what was kept ("" when nothing needs saying), e.g. from `wpot.run_all_vs_all`:
        ``"its 2 worker processes were stopped ...; 7 of 15 pairs are stored in run/; rerun ... to resume"``
    exit_code : 128 + signum (130 for SIGINT, 143 for SIGTERM), the shell's convention
    """

    def __init__(self, signum: int = signal.SIGINT, detail: str = "") -> None:
        super().__init__(signal_words(signum) + (f": {detail}" if detail else ""))
        self.signum = int(signum)
        self.detail = detail

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def exit_code(exc: BaseException) -> int:
    """The exit code for a command stopped by ``exc``: 128 + its signal; 130 for a plain `KeyboardInterrupt`."""
    return int(getattr(exc, "exit_code", 128 + signal.SIGINT))


def stopped_message(exc: BaseException, command: str | None) -> str:
    """The line a command prints when ``exc`` stopped it: ``"wpot: compare stopped by Ctrl-C (SIGINT)"``, and
    for a run what was stopped and kept (`Interrupted.detail`). ``command`` None: stopped before it was known."""
    words = signal_words(getattr(exc, "signum", signal.SIGINT))
    detail = getattr(exc, "detail", "")
    return f"wpot: {command + ' ' if command else ''}stopped by {words}" + (f": {detail}" if detail else "")


def _say(text: str) -> None:
    """One line on standard error, written with `os.write` (safe inside a signal handler, which may run while
    the main thread is itself writing to ``sys.stderr``); on a terminal it starts on a line of its own."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, ValueError, OSError):
        fd = 2
    try:
        lead = "\n" if os.isatty(fd) else ""
        os.write(fd, f"{lead}{text}\n".encode("utf-8", "replace"))
    except OSError:
        pass


def kill_children(timeout: float = 2.0) -> int:
    """SIGKILL every descendant of this process (workers, a local Dask cluster's worker processes, ...); wait up to
    ``timeout`` seconds for them to end. Returns how many were alive."""
    import psutil

    try:
        children = psutil.Process().children(recursive=True)
    except psutil.Error:
        return 0
    for c in children:
        with contextlib.suppress(psutil.Error):
            c.kill()
    psutil.wait_procs(children, timeout=timeout)
    return len(children)


def hard_stop(signum: int, note: str = "", *, second: bool = True) -> None:
    """Stop at once (a second signal, or a first one whose stop takes too long): say so, SIGKILL every process this
    one started, `os._exit` with 128 + signum. Nothing waits: no worker, thread, cluster or exit handler."""
    _say(f"wpot: stopped at once by {'a second ' if second else ''}{signal_words(signum)}" + (f"; {note}" if note else ""))
    try:
        kill_children(timeout=1.0)
    finally:
        os._exit(128 + signum)


#: seconds a first signal's clean stop may take before the process stops at once (`hard_stop`): a first Ctrl-C
#: ends the process within about 5 s whatever happens (a clean stop takes 0.5-2 s)
GRACE = 4.0


@dataclasses.dataclass
class Stopping:
    """The state of `stop_on_signals`: what its messages say (set while the block runs, once the command is
    known), and the signal that asked for a stop (None until one came)."""

    doing: str = ""  # after "wpot: stopping on <signal>:", what the stop does
    after_hard_stop: str = ""  # what the message of a second signal adds
    signum: int | None = None
    deferred: int = 0  # depth of `deferred_stop` blocks
    late: threading.Timer | None = None  # the `GRACE` timer, started by the first signal


#: the active `stop_on_signals` (None outside one)
_active: Stopping | None = None


def check_stop() -> None:
    """Raise `Interrupted` when a signal asked for a stop under `stop_on_signals`.

    The first signal raises `Interrupted` where the main thread is; a library that catches ``BaseException``
    there (trimesh does, around its optional imports) swallows it and the work would go on. The run's loops call
    this between steps, so that the stop happens anyway; `GRACE` is the last resort."""
    if _active is not None and _active.signum is not None and not _active.deferred:
        raise Interrupted(_active.signum)


@contextlib.contextmanager
def deferred_stop() -> Iterator[None]:
    """A block that a first signal does not break into (starting a Dask cluster, which a stop half-way through
    leaves in pieces): the signal is said at once and raised (`Interrupted`) when the block ends, also when the
    block fails after it (the signal may have reached what the block starts). A second signal still stops at
    once."""
    if _active is None:
        yield
        return
    state = _active
    state.deferred += 1
    try:
        yield
    except Exception:  # a failure after a stop was asked is the stop's (the signal also reached the cluster's
        if state.signum is None:  # workers while they started)
            raise
        state.deferred -= 1
        raise Interrupted(state.signum) from None
    state.deferred -= 1
    check_stop()


@contextlib.contextmanager
def stop_on_signals(*, doing: str = "", after_hard_stop: str = "") -> Iterator[Stopping]:
    """Turn SIGINT and SIGTERM into a clean stop for the block (see the module docstring); yields the `Stopping`
    whose words the messages use.

    The first signal writes ``wpot: stopping on <signal>[: doing]; <how to stop at once>`` to standard error and
    raises `Interrupted` in the main thread (at the end of a `deferred_stop` block when in one; again at the next
    `check_stop` if something swallowed it); when the process has not ended `GRACE` seconds later, or a second
    signal comes, it stops at once (`hard_stop`, with ``after_hard_stop`` added to its message). Outside the
    main thread (where Python takes no signal handlers) the block runs unchanged, and a signal that this process
    ignores (a background job of a script ignores SIGINT) stays ignored. The previous handlers come back
    when the block ends, unless a signal stopped it: then a later one (while the interpreter ends, after the
    command said it stopped) exits at once, with the first one's code."""
    global _active
    state = Stopping(doing, after_hard_stop)
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def handle(signum: int, frame: Any) -> None:
        if state.signum is not None:
            hard_stop(signum, state.after_hard_stop)  # does not return
            return
        state.signum = signum
        again = "press Ctrl-C again" if signum == signal.SIGINT else f"a second {signal_words(signum)}"
        _say(f"wpot: stopping on {signal_words(signum)}" + (f": {state.doing}" if state.doing else "")
             + f"; {again} stops at once")
        late = threading.Timer(GRACE, lambda *a, **k: hard_stop(*a, **k), (signum, f"the stop took over {GRACE:g} s"
                                                   + (f"; {state.after_hard_stop}" if state.after_hard_stop else "")),
                               {"second": False})
        late.daemon = True
        late.start()
        state.late = late
        if not state.deferred:
            raise Interrupted(signum)

    def exiting(signum: int, frame: Any) -> None:  # the stop was said; the interpreter is ending
        os._exit(128 + state.signum)

    unraisable = sys.unraisablehook

    def swallowed(info: Any) -> None:
        # the signal landed in a finalizer (a Warp array's __del__), which Python cannot raise from: not an
        # error to print, `check_stop` raises it again at the next check
        if not isinstance(info.exc_value, Interrupted):
            unraisable(info)

    # a signal ignored from the start stays ignored (a background job of a script, nohup): as Python does for SIGINT
    previous = {s: signal.signal(s, handle) for s in SIGNALS if signal.getsignal(s) != signal.SIG_IGN}
    outer, _active = _active, state
    sys.unraisablehook = swallowed
    try:
        yield state
    finally:
        _active = outer
        sys.unraisablehook = unraisable
        for s, h in previous.items():
            signal.signal(s, exiting if state.signum is not None else h)


# ------------------------------------------------------------------------------------------------ workers
def exit_with_parent(interval: float = 0.5) -> threading.Thread:
    """Start a daemon thread that ends this process (`os._exit`) when its parent is gone (``os.getppid()``
    changes: the process was handed to init or a subreaper), checked every ``interval`` seconds. A worker whose
    coordinator was killed (SIGKILL, the OOM killer) then exits instead of waiting for tasks forever."""
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(interval)
            if os.getppid() != parent:
                os._exit(1)

    t = threading.Thread(target=watch, name="wpot-exit-with-parent", daemon=True)
    t.start()
    return t


@contextlib.contextmanager
def _sigint_ignored_by_children() -> Iterator[None]:
    """Processes started in the block (in the main thread) inherit SIGINT ignored, which Python keeps: a Ctrl-C
    that reaches them while they start (importing, before `pool_worker_setup` runs) leaves them alone. This
    process's own SIGINT is blocked meanwhile and handled after the block (Linux keeps a blocked signal pending
    even while its action is to ignore it); one that a native thread of this process (BLAS) takes in those few
    milliseconds is lost."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _process_class() -> type:
    import multiprocessing.context

    class WorkerProcess(multiprocessing.context.SpawnProcess):
        """A spawned process that starts with SIGINT ignored (`_sigint_ignored_by_children`)."""

        def start(self) -> None:
            with _sigint_ignored_by_children():
                super().start()

    WorkerProcess.__qualname__ = WorkerProcess.__name__ = "_WorkerProcess"
    return WorkerProcess


def __getattr__(name: str) -> Any:  # the process class, made when first asked for (multiprocessing is not
    if name == "_WorkerProcess":  # imported by ``wpot.stopping`` itself); a spawned child unpickles it by name
        cls = globals()["_WorkerProcess"] = _process_class()
        return cls
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def worker_context() -> Any:
    """The multiprocessing context of `wpot.run_all_vs_all`'s process pool: spawn (safe with CUDA), its processes
    started with SIGINT ignored, so that a Ctrl-C never interrupts a worker, also while it starts."""
    import multiprocessing.context

    class Context(multiprocessing.context.SpawnContext):
        Process = __getattr__("_WorkerProcess")

    return Context()


def pool_worker_setup() -> None:
    """The initializer of `wpot.run_all_vs_all`'s process-pool workers: ignore SIGINT (the coordinator decides
    when to stop, and stops them), exit when the coordinator is gone (`exit_with_parent`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    exit_with_parent()


def dask_setup(worker: Any) -> None:
    """Dask's preload hook (``LocalCluster(preload=["wpot.stopping"])``), run in each worker process's main
    thread when it starts: ignore SIGINT and SIGTERM (the coordinator closes the cluster when it stops), and say
    nothing about the tasks it cancels."""
    if threading.current_thread() is threading.main_thread():
        for s in SIGNALS:
            signal.signal(s, signal.SIG_IGN)
    # that logger's one warning is about a cancelled task, which a stopped run cancels by the dozen
    logging.getLogger("distributed.worker.state_machine").setLevel(logging.ERROR)
    # a worker busy with a pair when the stopped coordinator closes the scheduler logs its next heartbeat's failure
    # with a traceback; the scheduler of a local cluster only goes away with its coordinator, so that is no news
    logging.getLogger("distributed.worker").addFilter(_scheduler_gone_filter)


def _scheduler_gone_filter(record: logging.LogRecord) -> bool:
    """False for a worker's report that its heartbeat found the scheduler gone (a `logging` filter)."""
    return not str(record.msg).startswith("Failed to communicate with scheduler")
