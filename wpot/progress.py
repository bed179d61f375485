"""Progress reports for the long steps of a comparison or a run: a line per stage with its time, bars for loops.

`Progress` is the one object that long-running code is handed (`wpot.Comparer(progress=...)`,
`wpot.compare(..., progress=True)`, `wpot.run_all_vs_all(progress=...)`, the ``wpot`` command): the code
names its stages and loops, the reporter decides whether and where they are shown. Nothing is global, so a
test or a notebook passes its own reporter (`as_progress` turns ``True``/``False`` into one).

* ``stage(what)``: a context manager around one step (a spectrum, the signatures, the transport): its
  name is written when it starts and its wall time when it ends, ``"spectrum of A (300 vertices) ... 1.2 s"``;
* ``bar(total, desc, unit)``: a `tqdm.auto` bar for a loop (shapes, pairs), which Jupyter shows as a widget;
  into a stream that is not a terminal (a log file), a line per step instead (``"pairs: 3/6 (50%), 1.2 s"``),
  never a bar redrawn with carriage returns;
* ``write(text)``: one line that does not break a running bar.

A disabled reporter (``Progress(enabled=False)``, what ``progress=False`` gives) shows nothing and costs
nothing; its bars are tqdm's disabled bars, so callers never branch on whether progress is on.
"""
from __future__ import annotations

import contextlib
import sys
import time
from typing import Any, Callable, Iterator, TextIO

__all__ = ["LineBar", "Progress", "as_progress"]


class Progress:
    """Reports stages and loops to a text stream (default: standard error).

    Parameters
    ----------
    stream : where lines and bars go (None: ``sys.stderr`` at the time of writing)
    enabled : False shows nothing
    clock : seconds, for the stage times (the seam that lets a test give fixed times)
    """

    def __init__(self, stream: TextIO | None = None, *, enabled: bool = True,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self._stream = stream
        self.enabled = bool(enabled)
        self.clock = clock
        self._open = False  # a stage's line is written up to its "..." and waits for its time

    @property
    def stream(self) -> TextIO:
        return sys.stderr if self._stream is None else self._stream

    def __repr__(self) -> str:
        return f"Progress({'on' if self.enabled else 'off'})"

    @property
    def live(self) -> bool:
        """Whether a bar redrawn in place can be shown: the stream is a terminal, or this is a Jupyter kernel
        (where `tqdm.auto` draws a widget). Bars inside a stage (the annealing's betas) are shown only then, so
        that a log file gets one line per stage."""
        if not self.enabled:
            return False
        isatty = getattr(self.stream, "isatty", None)
        return bool(isatty is not None and isatty()) or _in_jupyter()

    def write(self, text: str) -> None:
        """One line (through tqdm, so that a bar being drawn is redrawn below it)."""
        if not self.enabled:
            return
        from tqdm.auto import tqdm

        self.break_line()
        tqdm.write(text, file=self.stream)

    def break_line(self) -> None:
        """End a running stage's line, so that other output (a warning) starts on a line of its own; the stage's
        time then comes on a line of its own too, with its name."""
        if self._open:
            self.stream.write("\n")
            self._open = False

    @contextlib.contextmanager
    def stage(self, what: str) -> Iterator[None]:
        """Write ``what`` when the step starts and its wall time when it ends (also when it raises)."""
        if not self.enabled:
            yield
            return
        out = self.stream
        out.write(f"{what} ... ")
        out.flush()
        self._open = True
        t0 = self.clock()
        ok = False
        try:
            yield
            ok = True
        finally:
            took = f"{self.clock() - t0:.1f} s{'' if ok else ' (stopped)'}"
            out.write(f"{took}\n" if self._open else f"{what}: {took}\n")
            out.flush()
            self._open = False

    def bar(self, total: int | None, desc: str, unit: str = "it", *, initial: int = 0, leave: bool = False) -> Any:
        """A bar for a loop of ``total`` steps (None: unknown); close it when done. Where a bar can be redrawn in
        place (`live`) a `tqdm.auto.tqdm` bar (``leave``: kept on screen when closed); into another stream (a
        log file) a `LineBar`, a line per step; a disabled tqdm bar when this reporter is disabled."""
        from tqdm.auto import tqdm

        if self.enabled and not self.live:
            return LineBar(self, total, desc, unit, initial=initial)
        return tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=not self.enabled, leave=leave,
                    dynamic_ncols=True, file=self.stream)


class LineBar:
    """What `Progress.bar` gives for a stream that is not a terminal: a line when the loop starts and one per
    step, ``"pairs: 3/6 (50%), 1.2 s"`` (the time since the start), with the last ``set_postfix_str`` text after
    it. It takes the calls code makes on a tqdm bar (``update``, ``write``, ``set_postfix_str``, ``refresh``,
    ``close``, and use as a context manager)."""

    def __init__(self, reporter: Progress, total: int | None, desc: str, unit: str = "it", *,
                 initial: int = 0) -> None:
        self.reporter, self.total, self.desc, self.unit = reporter, total, desc, unit
        self.n = int(initial)
        self.postfix = ""
        self.closed = False
        self._t0 = reporter.clock()
        self._line()

    def _line(self) -> None:
        if self.total:
            count = f"{self.n}/{self.total} ({100 * self.n / self.total:.0f}%)"
        else:
            count = f"{self.n} {self.unit}" if self.total is None else f"{self.n}/{self.total}"
        took = self.reporter.clock() - self._t0
        self.reporter.break_line()
        out = self.reporter.stream
        out.write(f"{self.desc}: {count}, {took:.1f} s" + (f", {self.postfix}" if self.postfix else "") + "\n")
        out.flush()

    def update(self, n: int = 1) -> None:
        """``n`` more steps done: a line."""
        if not self.closed:
            self.n += int(n)
            self._line()

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        """Text shown after the count from the next line on."""
        self.postfix = str(s)

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        self.desc = "" if desc is None else str(desc)

    def refresh(self) -> None:
        """Nothing to redraw: every step has its line."""

    def write(self, text: str) -> None:
        """A line of its own."""
        self.reporter.write(text)

    def close(self) -> None:
        self.closed = True

    def __enter__(self) -> "LineBar":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _in_jupyter() -> bool:
    """True inside a running Jupyter kernel (not merely with ipykernel imported, as a test runner may have it)."""
    ipython = sys.modules.get("IPython")
    if ipython is None:
        return False
    try:
        shell = ipython.get_ipython()
    except Exception:  # an IPython without a usable get_ipython: not a kernel we can draw in
        return False
    return type(shell).__name__ == "ZMQInteractiveShell"


def as_progress(progress: "bool | Progress | None") -> Progress:
    """The reporter for a ``progress=`` argument: a `Progress` as it is; True: one on standard error;
    False or None: a disabled one."""
    if isinstance(progress, Progress):
        return progress
    if progress is None or isinstance(progress, bool):
        return Progress(enabled=bool(progress))
    raise TypeError(f"progress must be True, False or a wpot.progress.Progress, got {type(progress).__name__}")
