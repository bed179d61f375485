"""The help of every command tells the truth: each default it states is the parser's, it says what an option does
(not how well: no measured figures), and the parser is built from functions of a readable size."""
from __future__ import annotations

import argparse
import ast
import re
from pathlib import Path

import pytest

from wpot.cli import build_parser

#: a dummy value for each positional argument, so that a command's defaults can be parsed
POSITIONALS = {"mesh_a": "a.off", "mesh_b": "b.off", "source": "data", "part": "p.off", "library": "lib",
               "run": "RUN", "runs": "RUN"}


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _defaults(name: str, p: argparse.ArgumentParser) -> argparse.Namespace:
    """The namespace the command gets with every option left out (required options given a dummy)."""
    argv = []
    for a in p._actions:
        if not a.option_strings and a.dest in POSITIONALS:
            argv.append(POSITIONALS[a.dest])
        elif a.option_strings and a.required:
            argv += [a.option_strings[0], "X"]
    return p.parse_args(argv)


#: "default X" / "default: X" (X up to a comma, a semicolon or a bracket; 10,000 kept whole)
STATED = re.compile(r"\bdefault:?\s+(\d{1,3}(?:,\d{3})+|[^,;)]+)")
#: "'auto' (default)" / "(none, default)": the default named before the word
NAMED_BEFORE = re.compile(r"'?([\w.-]+)'?,? \(?default\)")
NUMBER = re.compile(r"^-?(\d{1,3}(?:,\d{3})+|\d+(?:\.\d*)?(?:e-?\d+)?)(.*)$")


def _mismatch(stated: str, actual) -> str | None:
    """Why ``stated`` (the text after "default") is not ``actual`` (the parser's default); None when it is."""
    stated = stated.strip()
    m = NUMBER.match(stated)
    if m:
        value, rest = float(m.group(1).replace(",", "")), m.group(2).strip()
        if rest:  # "default 2: the paper's scale-free LD-SIFT": a description of another value glued to it
            return f"the default {m.group(1)} is followed by {rest!r}; say what a value means after a comma or semicolon"
        if isinstance(actual, bool) or not isinstance(actual, (int, float)) or float(actual) != value:
            return f"states {m.group(1)}, the parser's default is {actual!r}"
        return None
    word = stated.split()[0].strip("'\"")
    if isinstance(actual, str):
        return None if Path(word) == Path(actual) else f"states {word!r}, the parser's default is {actual!r}"
    if word.lower() == "none":
        return None if actual is None else f"states none, the parser's default is {actual!r}"
    if actual is None or actual is False:  # a description of what leaving it out means (resolved later)
        return None
    return f"states {stated!r}, the parser's default is {actual!r}"


@pytest.mark.parametrize("command", sorted(_commands()))
def test_every_default_stated_in_the_help_is_the_parser_s(command):
    p = _commands()[command]
    ns = _defaults(command, p)
    wrong = []
    for a in p._actions:
        if not a.help or a.help == argparse.SUPPRESS or a.dest == "help":
            continue
        text = " ".join((a.help % {"default": a.default, "prog": p.prog}).split())
        actual = getattr(ns, a.dest)
        found = [s for s in STATED.findall(text)] + [s for s in NAMED_BEFORE.findall(text)]
        for s in found:
            why = _mismatch(s, actual)
            if why:
                wrong.append(f"{a.option_strings or a.dest}: {why} ({text!r})")
    assert not wrong, "\n".join(wrong)


def test_the_check_catches_a_wrong_default():
    assert _mismatch("2: the paper's scale-free LD-SIFT", 2.0) is not None
    assert _mismatch("500", 300) is not None and _mismatch("1", None) is not None
    assert _mismatch("10,000", 10_000) is None and _mismatch("0.01", 0.01) is None
    assert _mismatch("wks", "wks") is None and _mismatch("ldsift", "wks") is not None
    assert _mismatch("./wpot-demo", "wpot-demo") is None and _mismatch("none", None) is None
    assert _mismatch("Warp's default", None) is None and _mismatch("meshes at their own size", 3) is not None
    assert NAMED_BEFORE.findall("'auto' (default) or 'exact'") == ["auto"]
    assert NAMED_BEFORE.findall("uniform masses (none, default), or") == ["none"]


def test_retrieve_states_ldsift_thickness_it_is_calibrated_for():
    """retrieve's LD-SIFT is the paper's scale-free one (thickness 0, what its probability is calibrated for), as
    compare's; its help says so."""
    from wpot.maps.retrieval import CALIBRATED_THICKNESS

    assert CALIBRATED_THICKNESS == 0
    for name in ("retrieve", "compare"):
        text = " ".join(next(a for a in _commands()[name]._actions
                             if "--ldsift-thickness" in a.option_strings).help.split())
        assert "(default 0;" in text and "0 leaves it out, the paper's scale-free LD-SIFT" in text


#: a measured figure: a percentage, or a speed ratio such as "50-180x slower"
FIGURE = re.compile(r"\d\s*%|\d\s*x (?:slower|faster)|\d+(?:-\d+)?x\b")


@pytest.mark.parametrize("command", sorted(_commands()))
def test_help_says_what_an_option_does_not_how_well_it_did(command):
    text = " ".join(_commands()[command].format_help().split())
    assert not FIGURE.findall(text), FIGURE.findall(text)


def test_all_vs_all_says_list_paths_are_relative_to_the_list():
    for command, dest in (("all-vs-all", "source"), ("retrieve", "library")):
        a = next(a for a in _commands()[command]._actions if a.dest == dest)
        assert "relative path is relative to the list's folder" in " ".join(a.help.split()), a.help


def test_no_function_of_the_command_module_exceeds_100_lines():
    import wpot.cli

    tree = ast.parse(Path(wpot.cli.__file__).read_text())
    long = {n.name: n.end_lineno - n.lineno + 1 for n in ast.walk(tree)
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.end_lineno - n.lineno + 1 > 100}
    assert not long, long
