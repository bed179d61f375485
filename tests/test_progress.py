"""The progress reporter (`wpot.progress`): into a stream that is not a terminal, bars are lines."""
from __future__ import annotations

import io

from helpers import Clock
from wpot.progress import LineBar, Progress




class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_bar_into_a_file_writes_a_line_per_step_and_no_carriage_return():
    out = io.StringIO()
    p = Progress(out, clock=Clock())
    bar = p.bar(4, "pairs", "pair")
    assert isinstance(bar, LineBar)
    for k in range(4):
        if k == 2:
            bar.write("pair (0, 2) failed: ValueError: bad")
            bar.set_postfix_str("beta 1e+03")
        bar.update()
    bar.refresh()
    bar.close()
    bar.update()  # after close: nothing
    text = out.getvalue()
    assert "\r" not in text and "\x1b" not in text
    assert text.splitlines() == [
        "pairs: 0/4 (0%), 1.0 s",
        "pairs: 1/4 (25%), 2.0 s",
        "pairs: 2/4 (50%), 3.0 s",
        "pair (0, 2) failed: ValueError: bad",
        "pairs: 3/4 (75%), 4.0 s, beta 1e+03",
        "pairs: 4/4 (100%), 5.0 s, beta 1e+03",
    ]


def test_a_resumed_loop_and_one_of_unknown_length_and_a_stage_around_it():
    out = io.StringIO()
    p = Progress(out, clock=Clock())
    with p.bar(6, "pairs", "pair", initial=4) as bar:
        bar.update(2)
    with p.bar(None, "annealing", "beta") as bar:
        bar.update()
    with p.stage("fitting"):
        with p.bar(2, "spectra", "shape") as bar:
            bar.update()
    lines = out.getvalue().splitlines()
    assert lines[:4] == ["pairs: 4/6 (67%), 1.0 s", "pairs: 6/6 (100%), 2.0 s", "annealing: 0 beta, 1.0 s",
                         "annealing: 1 beta, 2.0 s"]
    # a stage's line is ended before the bar's lines, and its time comes on a line of its own
    assert lines[4:] == ["fitting ... ", "spectra: 0/2 (0%), 1.0 s", "spectra: 1/2 (50%), 2.0 s", "fitting: 4.0 s"]
    assert "\r" not in out.getvalue()


def test_a_terminal_still_gets_a_bar_and_a_disabled_reporter_nothing():
    from tqdm.auto import tqdm

    term = Terminal()
    bar = Progress(term).bar(3, "pairs", "pair")
    assert isinstance(bar, tqdm)
    bar.update()
    bar.close()
    assert "\r" in term.getvalue()
    silent = io.StringIO()
    bar = Progress(silent, enabled=False).bar(3, "pairs")
    bar.update()
    bar.close()
    assert silent.getvalue() == ""
