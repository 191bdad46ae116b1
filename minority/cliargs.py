"""What every `minority` subcommand shares (tests/test_cli_conventions.py checks them all):

- `-o/--out` names what a command writes, file or directory; a missing directory is created
  when the command writes (never before its input is checked, so a refused command leaves
  nothing behind);
- every `--help` shows each option's default, once;
- exit status 0 on success, 2 for bad usage or bad input (argparse's own status), 1 for a
  failure at run time (a file that cannot be written, a peer that cannot be reached, a
  diverged rollout).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

OK, FAILED, BAD_INPUT = 0, 1, 2  # exit statuses


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, plus "(default: X)" after an option's help when it has a default
    worth saying (not None, False or empty) and its help does not already say one in words
    (a default decided at run time, e.g. "(default: SCENE_NAME.h5)")."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (not action.option_strings or "default" in text or default is argparse.SUPPRESS
                or default is None or default is False or default == []):
            return text
        return f"{text} (default: %(default)s)"


def command(sub, name: str, *, help: str, description: str) -> argparse.ArgumentParser:
    """A subcommand's parser with the shared help formatting."""
    return sub.add_parser(name, help=help, description=description, formatter_class=HelpFormatter)


def add_out(p: argparse.ArgumentParser, what: str, *, default: Path | None = None,
            metavar: str = "FILE", **kw) -> None:
    """-o/--out: what the command writes."""
    p.add_argument("-o", "--out", type=Path, default=default, metavar=metavar, help=what, **kw)


def parent_made(path: Path) -> Path:
    """`path`, with its directory created when missing (OSError when it cannot be)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return path


def fail(command: str, exc: Exception | str, status: int = FAILED) -> int:
    """Say `minority COMMAND: error: EXC` on stderr in one line; returns `status`."""
    print(f"minority {command}: error: {exc}", file=sys.stderr)
    return status


def missing(command: str, *paths: Path | None) -> int | None:
    """BAD_INPUT, after saying so, when an input file or directory does not exist."""
    for path in paths:
        if path is not None and not Path(path).exists():
            return fail(command, f"{path}: no such file or directory", BAD_INPUT)
    return None
