"""The ``torch-ao`` command line: one subcommand per module in :mod:`torch_ao.commands`."""
from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import os
import sys
import warnings

# Subcommand modules, each with ``register(subparsers)`` that adds its parser and sets ``func``.
_COMMANDS = ("ao", "render", "fit", "bench", "convert", "export")


class CommandError(ValueError):
    """A user error a command finds: printed as one line, exit status 2, no traceback. (The library
    raises ``ValueError`` for bad input, naming the argument or file; this is one.)"""


class _UsageError(CommandError):
    def __init__(self, prog: str, message: str) -> None:
        super().__init__(message)
        self.prog = prog


class _Parser(argparse.ArgumentParser):
    """Reports a bad flag like every other user error: one line naming it, exit status 2 (not the usage)."""

    def error(self, message: str):
        raise _UsageError(self.prog, message)


def build_parser() -> argparse.ArgumentParser:
    from .version import __version__

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


def user_error(err: BaseException) -> str | None:
    """The one-line message of an error that is the input's or the machine's, not a bug; ``None`` for a bug.

    * ``ValueError`` (``CommandError`` among them): bad input, by the library's convention naming the
      argument or file; ``TypeError``: an argument of the wrong kind (e.g. an integer depth array);
      ``ImportError``: an optional dependency missing (the message says which extra installs it);
    * ``OSError``: a file that cannot be read or written (``PATH: reason``);
    * ``RecursionError``: input nested deeper than Python can read; ``MemoryError`` and torch's
      out-of-memory errors: the job does not fit in this machine's memory.
    """
    if isinstance(err, (ValueError, TypeError, ImportError)):
        return str(err)
    if isinstance(err, OSError):
        if err.filename is None or err.strerror is None:
            return str(err)
        target = err.filename if err.filename2 is None else err.filename2
        return f"{target}: {err.strerror}"
    if isinstance(err, RecursionError):
        return "the input is nested too deeply to read (Python's recursion limit)"
    if isinstance(err, MemoryError) or _out_of_memory(err):
        detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        return f"out of memory ({detail}); use a smaller size, fewer samples or another --device"
    return None


def _out_of_memory(err: BaseException) -> bool:
    """torch's allocation failures: ``torch.OutOfMemoryError`` (CUDA) or the CPU allocator's ``RuntimeError``."""
    if type(err).__name__ == "OutOfMemoryError":
        return True
    return isinstance(err, RuntimeError) and "can't allocate memory" in str(err)


@contextlib.contextmanager
def _imports_out_of_collection():
    """The objects alive when a command starts (the imported modules' several hundred thousand, which outlive it)
    left out of the garbage collector's full collections while it runs: each would traverse them all, about 80 ms
    a collection, six in a fit's run (``gc.freeze``; ``gc.unfreeze`` after, so that a caller's objects are collected
    as before)."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


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
        with _imports_out_of_collection():
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print(f"torch-ao {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - user errors become one line; anything else is a bug: re-raised
        message = user_error(err)
        if message is None or os.environ.get("TORCH_AO_DEBUG"):  # the full traceback, for developers
            raise
        print(f"torch-ao {args.command}: error: {' '.join(message.split())}", file=sys.stderr)  # one line
        return 2
    finally:
        warnings.formatwarning = formatwarning


if __name__ == "__main__":  # pragma: no cover
    # `python -m torch_ao.cli`: this file runs as __main__, a second copy of the module; the commands raise
    # torch_ao.cli's CommandError, so run torch_ao.cli's main.
    from torch_ao.cli import main as _main

    sys.exit(_main())
