"""The G-buffer input flags, one group shared by every command that reads G-buffer files (``ao``,
``bench --reference``, ``fit --reference``, ``convert``): the fields of
:class:`~torch_ao.io.engine.EngineOptions`, built from :data:`~torch_ao.io.engine.ENGINE_OPTIONS`.

:func:`add_input_flags` adds the group, :func:`input_options` reads back the fields given (the others
keep their defaults) and :func:`flag_errors` turns an ``EngineOptions`` error (``"far: ..."``) into one
naming its flag (``"--far: ..."``).
"""
from __future__ import annotations

import argparse
import contextlib

from ..io.engine import ENGINE_OPTIONS, EngineOptions
from ..io import FileContentError
from .args import allow_negative_lists, parse_float_list
from .options_cli import add_option, flag, given

__all__ = ["add_input_flags", "input_options", "flag_errors"]

_OPTIONS = {o.name: o for o in ENGINE_OPTIONS}
#: Flags that also take ``inf`` (no far plane).
_INFINITE = ("far",)
#: Comma lists: name -> (count, how the list is shown).
_LISTS = {"view_matrix": (16, "M00,M01,...,M33"), "intrinsics": (4, "fx,fy,cx,cy")}


def add_input_flags(p: argparse.ArgumentParser, what: str = "G-buffer files") -> None:
    """Add the input conventions group to ``p``; ``what`` says which files they apply to."""
    g = p.add_argument_group(f"input conventions of {what} (see docs/engines.md)")
    for name, opt in _OPTIONS.items():
        add_option(g, name, opt, infinite=name in _INFINITE)
    allow_negative_lists(p)  # --view-matrix -1,0,...


def input_options(args: argparse.Namespace, files=True, what: str = "G-buffer files") -> dict:
    """The :class:`~torch_ao.io.engine.EngineOptions` fields given on the command line (others default).

    ``files``: whether the command reads any file (else a given flag is refused: it would do nothing);
    ``what`` names those files in that message.
    """
    from ..cli import CommandError
    from ..io.engine import parse_channels

    options = given(args, _OPTIONS)
    if options and not files:
        raise CommandError(f"{flag(next(iter(options)))}: applies to {what}, and none was given")
    with flag_errors():
        if "channels" in options:
            options["channels"] = parse_channels(options["channels"])
        for name, (count, names) in _LISTS.items():
            if name in options:
                options[name] = parse_float_list(flag(name), options[name], count, names=names)
        EngineOptions(**options)  # refused here, naming the flag, before any file is read
    return options


@contextlib.contextmanager
def flag_errors():
    """Re-raise a ``ValueError`` about an :class:`EngineOptions` field as one naming its flag."""
    try:
        yield
    except FileContentError:  # a file's own key of the same name as a flag
        raise
    except ValueError as err:
        msg = str(err)
        name = msg.split(":", 1)[0]
        if name in EngineOptions.__dataclass_fields__:
            raise ValueError(flag(name) + msg[len(name):]) from None
        raise
