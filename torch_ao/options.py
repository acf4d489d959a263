"""One description of every user-facing option: what it does, its unit, range and default.

A method (or a configuration object it is composed of) lists its options as a tuple of
:class:`Option` in ``OPTIONS``; the constructor validates with :meth:`Option.check` and the command
line builds its flags and their help from the same tuples, so a choice list, a bound or a default is
written once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

from .checks import check_bool, check_choice, check_float, check_int

__all__ = ["Option", "options_by_name"]


@dataclass(frozen=True)
class Option:
    """A user-facing option.

    Attributes:
        name: keyword argument and (with ``-`` for ``_``) command-line flag.
        default: value used when the option is not given (``None`` = decided by another option, say so in ``help``).
        help: one line: what it does (and why the default, where that is not obvious).
        kind: ``float``, ``int``, ``str`` or ``bool``.
        unit: unit of a number (``"world units"``, ``"pixels"``, ``"sectors"``, ``"radians"``), ``""`` if none.
        choices: allowed values of a ``str`` option.
        minimum, maximum: bounds of a number (closed unless ``open_minimum``/``open_maximum``).
        fitted: a float parameter registered as an ``nn.Parameter`` (can be fitted by gradient descent).
    """

    name: str
    default: Any
    help: str
    kind: type = float
    unit: str = ""
    choices: tuple | None = None
    minimum: float | None = None
    maximum: float | None = None
    open_minimum: bool = False
    open_maximum: bool = False
    fitted: bool = False

    def check(self, value):
        """``value`` validated against this option (``ValueError`` naming it otherwise); ``None`` passes
        when the default is ``None``."""
        if value is None and self.default is None:
            return None
        if self.choices is not None:
            return check_choice(self.name, value, self.choices)
        if self.kind is bool:
            return check_bool(self.name, value)
        if self.kind is int:
            return check_int(self.name, value, self.minimum, self.maximum)
        if self.kind is float:
            return check_float(self.name, value, self.minimum, self.maximum,
                               open_minimum=self.open_minimum, open_maximum=self.open_maximum)
        return value

    def describe(self) -> str:
        """The option's help line for ``--help``: what it does, unit, range and default."""
        parts = [self.help.rstrip(".") + "."]
        if self.unit:
            parts.append(f"Unit: {self.unit}.")
        if self.minimum is not None or self.maximum is not None:
            lo = "-inf" if self.minimum is None else f"{self.minimum:g}"
            hi = "inf" if self.maximum is None else f"{self.maximum:g}"
            parts.append(f"Range: {'(' if self.open_minimum else '['}{lo}, {hi}{')' if self.open_maximum or self.maximum is None else ']'}.")
        if self.choices is not None:
            parts.append(f"One of: {', '.join(map(str, self.choices))}.")
        parts.append(f"Default: {self.default}.")
        if self.fitted:
            parts.append("Fittable.")
        return " ".join(parts)


def options_by_name(*groups: Iterable[Option]) -> dict[str, Option]:
    """Merge option tuples into ``{name: Option}``; a name given twice must be the same option."""
    out: dict[str, Option] = {}
    for group in groups:
        for opt in group:
            if opt.name in out and out[opt.name] != opt:
                raise ValueError(f"option {opt.name!r} is described twice, differently")
            out[opt.name] = opt
    return out
