"""The ``torch-ao`` command line: one subcommand per module in :mod:`torch_ao.commands`."""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

# Subcommand modules, each with ``register(subparsers)`` that adds its parser and sets ``func``.
_COMMANDS = ("ao", "render", "fit", "bench", "convert")


class CommandError(Exception):
    """A user error: printed as one line, exit status 2, no traceback."""


class _UsageError(CommandError):
    def __init__(self, prog: str, message: str) -> None:
        super().__init__(message)
        self.prog = prog


class _Parser(argparse.ArgumentParser):
    """Reports a bad flag like every other user error: one line naming it, exit status 2 (not the usage)."""

    def error(self, message: str):
        raise _UsageError(self.prog, message)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = _Parser(prog="torch-ao", description="Differentiable screen-space ambient occlusion.")
    parser.add_argument("--version", action="version", version=f"torch-ao {__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMANDS:
        try:
            module = importlib.import_module(f"torch_ao.commands.{name}")
        except ModuleNotFoundError as err:
            if err.name == f"torch_ao.commands.{name}":
                continue  # not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as err:
        print(f"{err.prog}: error: {err} (see {err.prog} --help)", file=sys.stderr)
        return 2
    def one_line(message, *_args, **_kwargs):  # warnings print as one line on stderr, like the errors
        return f"torch-ao {args.command}: warning: {message}\n"

    formatwarning, warnings.formatwarning = warnings.formatwarning, one_line
    try:
        return int(args.func(args) or 0)
    except (CommandError, ValueError, TypeError, FileNotFoundError, ImportError) as err:
        if os.environ.get("TORCH_AO_DEBUG"):  # the full traceback, for developers
            raise
        print(f"torch-ao {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torch-ao {args.command}: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.formatwarning = formatwarning


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
