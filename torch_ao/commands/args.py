"""Argparse helpers shared by the ``torch-ao`` subcommands.

Comma lists of numbers (``--eye -2,1,3``): argparse takes any token that starts with ``-`` and is
not a plain negative number (``-2``, ``-0.5``) for a flag, so ``--eye -2,1,3`` fails with
"expected one argument". :func:`allow_negative_lists` widens a parser's idea of a negative number to
comma lists of numbers, so both ``--eye -2,1,3`` and ``--eye=-2,1,3`` reach the flag;
:func:`add_float_list` registers such a flag and :func:`parse_float_list` checks its value (count and
finiteness) with a message naming the flag.
"""
from __future__ import annotations

import argparse
import math
import re

__all__ = ["allow_negative_lists", "add_float_list", "parse_float_list", "parse_device"]

# Anything that starts like a negative number ("-2", "-.5", "-2,1,3", "-2,x,1") is a value: the
# flag's own check then says what is wrong with it, instead of argparse's "expected one argument".
_NEGATIVE_LIST = re.compile(r"^-\.?\d")


def allow_negative_lists(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Let ``parser`` take tokens like ``-2,1,3`` as values, not flags; returns ``parser``.

    Argparse decides whether a token is a flag with the parser's ``_negative_number_matcher``
    (``-2`` and ``-0.5`` only); this replaces it with one that takes every token starting with
    ``-`` and a digit (or ``-.`` and a digit) for a value. The parser must not define flags that
    look like negative numbers (``-1``), which argparse would then prefer.
    """
    if not hasattr(parser, "_negative_number_matcher"):  # pragma: no cover - argparse internals moved
        raise RuntimeError("argparse: this Python's ArgumentParser has no _negative_number_matcher")
    parser._negative_number_matcher = _NEGATIVE_LIST
    return parser


def parse_float_list(flag: str, text: str | None, length: int | None = None, *,
                     names: str | None = None) -> tuple[float, ...] | None:
    """``"a,b,c"`` -> ``(a, b, c)`` as finite floats; ``None`` stays ``None``.

    Args:
        flag: the flag, for messages (``"--eye"``).
        text: the value as typed.
        length: how many numbers are expected (``None``: any number, at least one).
        names: how to show the expected list in messages (``"x,y,z"``).
    Raises:
        ValueError: naming ``flag``, what was expected and what was given.
    """
    if text is None:
        return None
    what = f"{length} comma-separated numbers" if length else "comma-separated numbers"
    if names:
        what += f" {names}"
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(f"{flag}: expected {what}, got {text!r}") from None
    if length is not None and len(values) != length:
        raise ValueError(f"{flag}: expected {what}, got {len(values)} in {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{flag}: expected finite numbers, got {text!r}")
    return values


def add_float_list(parser: argparse.ArgumentParser, flag: str, length: int, help: str, *,
                   names: str = "x,y,z", default: str | None = None) -> None:
    """Add a comma-list flag whose value may start with ``-`` (calls :func:`allow_negative_lists`).

    The value stays a string in the namespace; convert it with :func:`parse_float_list` in the
    command (so a wrong count is reported as the command's own one-line error, exit status 2).
    """
    allow_negative_lists(parser)
    parser.add_argument(flag, metavar=names.upper(), default=default,
                        help=f"{help} ({length} comma-separated numbers; may start with '-')")


def parse_device(text: str, flag: str = "--device"):
    """``torch.device(text)``, checked before anything runs on it: a ``ValueError`` naming ``flag`` for a
    malformed device, CUDA on a machine without it, or a CUDA index the machine does not have."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, TypeError):
        raise ValueError(f"{flag}: expected a torch device such as cpu, cuda or cuda:1, got {text!r}") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{flag}: CUDA is not available on this machine")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"{flag}: {text} does not exist (this machine has {torch.cuda.device_count()} CUDA devices)")
    return device
