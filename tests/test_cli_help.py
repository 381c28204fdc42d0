"""The CLI explains itself: every option of every (sub-)command has help, and its help names any default worth
naming (a flag's False and an unset None are said in words, if at all)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator

import pytest

from main import build_parser


def walk(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> Iterator[tuple[str, argparse.Action,
                                                                                      argparse.ArgumentParser]]:
    """(command path, action, its parser) for every argument of the whole tree, sub-sub-commands included."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from walk(child, (*path, name))
        elif not isinstance(action, argparse._HelpAction):
            yield " ".join(path), action, parser


def shown_help(action: argparse.Action, parser: argparse.ArgumentParser) -> str:
    return parser._get_formatter()._expand_help(action)


ARGUMENTS = list(walk(build_parser()))


def test_the_tree_is_walked_down_to_each_benchmark():
    commands = {path for path, _, _ in ARGUMENTS}
    assert {"run", "bench peg-in-hole", "bench planning", "bench drivers", "tune", "status"} <= commands


def test_every_argument_has_help():
    missing = [f"{path} {'/'.join(a.option_strings) or a.dest}" for path, a, _ in ARGUMENTS if not a.help]
    assert not missing, "arguments without help:\n" + "\n".join(missing)


def test_every_default_worth_naming_is_shown():
    hidden = []
    for path, a, parser in ARGUMENTS:
        d = a.default
        if d is None or d is argparse.SUPPRESS or isinstance(d, bool) or not a.help:
            continue
        if str(d) not in shown_help(a, parser):
            hidden.append(f"{path} {'/'.join(a.option_strings) or a.dest} = {d!r}")
    assert not hidden, "defaults the help does not show:\n" + "\n".join(hidden)


def test_a_default_is_appended_once():
    helps = {path: shown_help(a, p) for path, a, p in ARGUMENTS if a.option_strings == ["--trials"]}
    assert helps["bench peg-in-hole"].endswith("(default: 50)")
    peg_diameter = next(shown_help(a, p) for path, a, p in ARGUMENTS
                        if path == "bench peg-in-hole" and a.dest == "peg_diameter_mm")
    assert "(default:" not in peg_diameter.replace("default: the plant", "")


@pytest.mark.parametrize("name, own, foreign", [
    ("peg-in-hole", "--trials", "--impacts"),
    ("collision", "--impacts", "--trials"),
    ("drivers", "--n", "--seed"),
    ("planning", "--ppo-updates", "--calls"),
    ("model", "--calls", "--paths"),
])
def test_each_benchmark_takes_only_its_own_options(name, own, foreign):
    options = {o for path, a, _ in ARGUMENTS if path == f"bench {name}" for o in a.option_strings}
    assert own in options and foreign not in options


def test_old_bench_invocations_parse_as_before():
    args = build_parser().parse_args(["bench", "peg-in-hole", "--trials", "3", "--only", "1", "--seed", "2"])
    assert (args.what, args.trials, args.only, args.seed, args.force_source) == ("peg-in-hole", 3, [1], 2, "virtual")
    args = build_parser().parse_args(["bench", "drivers", "--n", "20", "--json"])
    assert (args.what, args.n, args.json, args.seed) == ("drivers", 20, True, None)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "sim", "--trials", "3"])
