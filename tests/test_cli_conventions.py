"""CLI conventions, over every subcommand: `--help` prints that subcommand's own usage and
exits 0; an unknown flag prints that subcommand's usage and exits 2; `minority --version`."""

import argparse

import pytest

from minority.cli import build_parser, main, version


def subcommands(parser: argparse.ArgumentParser, path=()) -> list[tuple[str, ...]]:
    """Every command path of the parser tree, e.g. ("oracle", "train"), ("log", "repair")."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.append((*path, name))
                out += subcommands(sub, (*path, name))
    return out


COMMANDS = [*subcommands(build_parser()), ("report", "score")]


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_help_is_the_subcommands_own(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: minority {' '.join(command)}")


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_an_unknown_flag_prints_the_subcommands_usage_and_exits_2(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--no-such-flag"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"usage: minority {' '.join(command)}" in err
    # argparse names a missing required argument before an unknown flag
    assert "--no-such-flag" in err or "arguments are required" in err


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"minority {version()}" != "minority unknown"


def test_the_top_level_help_lists_every_command(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert all(name in text for (name, *_) in COMMANDS)
