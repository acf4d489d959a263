"""Command-line flags built from :class:`~torch_ao.options.Option` descriptions, and values read back.

One builder for every command: an option ``name`` becomes ``--name-with-dashes`` with its type, its
choices and ``help=Option.describe()`` (what it does, unit, range, default); a ``bool`` option becomes a
``--name``/``--no-name`` pair. Method flags are the union over methods of their ``options()``; where
methods describe a name differently, the help gives each description with the methods it belongs to,
and each method's own option checks the value. Reading back (:func:`method_kwargs`) returns only the
flags the user gave, so every other argument keeps the constructor's default.
"""
from __future__ import annotations

import argparse
import math
from typing import Iterable, Mapping

from ..cli import CommandError
from ..options import Option

__all__ = ["flag", "method_options", "add_option", "add_options", "add_progress", "given", "method_kwargs", "construct",
           "PROGRESS", "SwitchPair"]

#: Option kinds that have a command-line form (others, such as tensors or callables, are Python-only).
FLAG_KINDS = (float, int, str, bool)


class SwitchPair(argparse.BooleanOptionalAction):
    """``--name`` / ``--no-name`` with its help as given: Python 3.10's ``BooleanOptionalAction`` appends
    ``(default: ...)`` to it, where every help here says its default itself."""

    def __init__(self, *args, help: str | None = None, **kwargs) -> None:
        super().__init__(*args, help=help, **kwargs)
        self.help = help


def flag(name: str) -> str:
    """``thickness_growth`` -> ``--thickness-growth``."""
    return "--" + name.replace("_", "-")


def method_options(classes: Mapping[str, type], exclude: Iterable[str] = ()) -> dict[str, dict[str, Option]]:
    """``{option name: {method name: Option}}`` over the methods' ``options()``, leaving out ``exclude``
    and options without a command-line form."""
    skip = set(exclude)
    out: dict[str, dict[str, Option]] = {}
    for method, cls in classes.items():
        for name, opt in cls.options().items():
            if name not in skip and opt.kind in FLAG_KINDS:
                out.setdefault(name, {})[method] = opt
    return out


def _value_parser(name: str, opts: list[Option], infinite: bool = False):
    """argparse ``type=``: the kind's conversion, then the choices, then the option's own check when
    there is one option (several: each method checks its own, :func:`method_kwargs`). ``infinite``:
    ``inf`` is taken as a value above every bound (an unlimited length, say)."""
    kind = opts[0].kind
    choices = [c for o in opts for c in (o.choices or ())] if all(o.choices for o in opts) else None

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
        if choices is not None and value not in choices:
            raise argparse.ArgumentTypeError(f"unknown {name} {value!r}; expected one of {', '.join(map(str, dict.fromkeys(choices)))}")
        if infinite and value == math.inf:
            return value
        if len(opts) == 1:
            try:
                value = opts[0].check(value)
            except ValueError as err:
                raise argparse.ArgumentTypeError(str(err).split(": ", 1)[-1]) from None
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def _help(by_owner: Mapping[str, Option]) -> str:
    distinct: list[tuple[Option, list[str]]] = []
    for owner, opt in by_owner.items():
        for known, owners in distinct:
            if known == opt:
                owners.append(owner)
                break
        else:
            distinct.append((opt, [owner]))
    if len(distinct) == 1:
        return distinct[0][0].describe()
    return " | ".join(f"{', '.join(owners)}: {opt.describe()}" for opt, owners in distinct)


def add_option(parser, name: str, entry: Option | Mapping[str, Option], *, given_only: bool = True,
               switch: bool = False, infinite: bool = False, **argparse_kwargs) -> str:
    """Add the flag of one option to ``parser``; returns ``name``.

    ``entry``: an :class:`Option` or ``{owner: Option}``. ``switch``: a ``bool`` option becomes a plain
    ``--name`` switch (``store_true``) instead of a ``--name``/``--no-name`` pair. ``infinite``: a number
    flag also takes ``inf``. ``argparse_kwargs`` (``nargs``, ``const``, ``action``, ``metavar``, ``type``,
    ``default``) replace what the option gives, for flags whose form an :class:`Option` cannot say
    (a repeatable flag, an optional value); the help always stays the option's description.
    """
    by_owner = {"": entry} if isinstance(entry, Option) else dict(entry)
    opts = [o for i, o in enumerate(by_owner.values()) if o not in list(by_owner.values())[:i]]
    kinds = {o.kind for o in opts}
    if len(kinds) != 1:
        raise TypeError(f"option {name!r} has several kinds ({', '.join(k.__name__ for k in kinds)})")
    kind = kinds.pop()
    default = None if given_only else opts[0].default
    kwargs = {"dest": name, "default": default, "help": _help(by_owner).replace("%", "%%")}
    if kind is bool:
        kwargs["action"] = "store_true" if switch else SwitchPair
    else:
        kwargs.update(type=_value_parser(name, opts, infinite), metavar=name.upper())
        kwargs["type"].options = by_owner  # what the flag is built from: {owner ("" when one): Option}
    kwargs.update(argparse_kwargs)
    parser.add_argument(flag(name), **kwargs)
    return name


def add_options(parser, options: Mapping[str, Option | Mapping[str, Option]], *, given_only: bool = True) -> list[str]:
    """Add one flag per option to ``parser`` (a parser or an argument group); returns the names.

    ``options`` maps a name to an :class:`Option` or to ``{owner: Option}`` (:func:`method_options`).
    ``given_only``: the flags default to ``None`` (read back only when given); else to the option's default.
    """
    return [add_option(parser, name, entry, given_only=given_only) for name, entry in options.items()]


#: The progress flag, spelled the same on every command: ``--progress``/``--no-progress``.
PROGRESS = Option("progress", True, "progress bars on stderr (--no-progress: none)", bool)
#: Older spellings, still accepted but not shown: ``{flag: value of args.progress}``.
_PROGRESS_ALIASES = {"--quiet": False, "--no-quiet": True}


def add_progress(parser) -> str:
    """Add :data:`PROGRESS` (``args.progress``, default True) and its hidden aliases ``--quiet``
    (= ``--no-progress``) and ``--no-quiet``; returns ``"progress"``."""
    add_option(parser, PROGRESS.name, PROGRESS, given_only=False)
    for alias, value in _PROGRESS_ALIASES.items():
        parser.add_argument(alias, dest=PROGRESS.name, action="store_const", const=value, help=argparse.SUPPRESS)
    return PROGRESS.name


def given(args: argparse.Namespace, names: Iterable[str]) -> dict:
    """``{name: value}`` of the flags among ``names`` that were given (not ``None``)."""
    return {n: getattr(args, n) for n in names if getattr(args, n, None) is not None}


def method_kwargs(method: str, cls: type, values: Mapping[str, object], *, strict: bool = True) -> dict:
    """``values`` checked by ``cls.options()``; a name the method does not take is an error naming the
    flag (``strict``) or left out."""
    options = cls.options()
    out = {}
    for name, value in values.items():
        if name not in options:
            if strict:
                raise CommandError(f"{flag(name)}: not an option of method {method!r}")
            continue
        try:
            out[name] = options[name].check(value)
        except ValueError as err:
            raise CommandError(f"{flag(name)}: {str(err).split(': ', 1)[-1]}") from None
    return out


def construct(cls: type, kwargs: Mapping[str, object]):
    """``cls(**kwargs)``; a ``ValueError`` about one of ``kwargs`` names its flag."""
    try:
        return cls(**kwargs)
    except ValueError as err:
        name, _, rest = str(err).partition(": ")
        if name in kwargs:
            raise CommandError(f"{flag(name)}: {rest}") from None
        raise
