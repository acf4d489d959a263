"""Small validation helpers: each raises ``ValueError`` naming the argument and what was expected.

Use these instead of writing ``isinstance`` chains inline, so that every module refuses bad input
with the same wording (``"<name>: expected <what>, got <value>"``).
"""
from __future__ import annotations

import math
from typing import Iterable, TypeVar

__all__ = ["check_int", "check_float", "check_choice", "check_bool", "check_scalar_tensor", "install_hint",
           "scalar_value", "NonFiniteOutput", "check_finite_outputs"]

T = TypeVar("T")


def _fail(name: str, expected: str, value) -> ValueError:
    return ValueError(f"{name}: expected {expected}, got {value!r}")


def check_int(name: str, value, minimum: int | None = None, maximum: int | None = None) -> int:
    """``value`` as an ``int`` (``bool`` refused) within ``[minimum, maximum]`` (either bound optional)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(name, "an integer", value)
    if minimum is not None and value < minimum:
        raise _fail(name, f"an integer >= {minimum}", value)
    if maximum is not None and value > maximum:
        raise _fail(name, f"an integer <= {maximum}", value)
    return value


def check_float(name: str, value, minimum: float | None = None, maximum: float | None = None, *,
                open_minimum: bool = False, open_maximum: bool = False, finite: bool = True) -> float:
    """``value`` as a ``float`` (``bool`` refused), finite unless ``finite=False``, within the bounds
    (closed unless ``open_minimum``/``open_maximum``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(name, "a number", value)
    value = float(value)
    if math.isnan(value) or (finite and math.isinf(value)):
        raise _fail(name, "a finite number", value)
    if minimum is not None and (value <= minimum if open_minimum else value < minimum):
        raise _fail(name, f"a number {'>' if open_minimum else '>='} {minimum}", value)
    if maximum is not None and (value >= maximum if open_maximum else value > maximum):
        raise _fail(name, f"a number {'<' if open_maximum else '<='} {maximum}", value)
    return value


def check_choice(name: str, value: T, choices: Iterable[T]) -> T:
    """``value`` if it is one of ``choices``."""
    choices = tuple(choices)
    if value not in choices:
        raise _fail(name, f"one of {choices}", value)
    return value


def check_bool(name: str, value) -> bool:
    """``value`` if it is a ``bool``."""
    if not isinstance(value, bool):
        raise _fail(name, "True or False", value)
    return value


def check_scalar_tensor(name: str, value):
    """``value`` (a number or a tensor, a parameter keeps its graph) as a 0-d tensor; any other shape refused."""
    import torch

    t = torch.as_tensor(value)
    if t.dim() != 0:
        raise ValueError(f"{name}: expected a 0-d tensor, got shape {tuple(t.shape)}")
    return t


def scalar_value(value) -> float | None:
    """The float of a real number (not a bool) or a one-element tensor, else ``None`` (for a caller that
    leaves the refusal of other values to their check)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return float(value)
    if hasattr(value, "numel") and value.numel() == 1 and value.dtype.is_floating_point:
        return float(value.detach())
    return None


def to_arguments(device=None, dtype=None):
    """``(device, dtype)`` of a ``to`` call read as ``Tensor.to`` reads it: a dtype given first changes the dtype
    alone (``x.to(torch.float64)``)."""
    import torch

    if isinstance(device, torch.dtype):
        if dtype is not None:
            raise TypeError(f"to: got two dtypes, {device} and {dtype}")
        return None, device
    return device, dtype


def install_hint(extra: str, package: str) -> str:
    """How to install an optional dependency: the extra from the repository's checkout, or the package.

    ``install_hint("exr", "openexr")`` -> ``pip install -e ".[exr]" (in the torch_ao checkout) or pip
    install openexr``.
    """
    return f'pip install -e ".[{extra}]" (in the torch_ao checkout) or pip install {package}'


class NonFiniteOutput(ValueError):
    """A computation produced NaN or infinity (a defect or an input outside the library's ranges)."""


def check_finite_outputs(producer: str, outputs: dict) -> None:
    """Raise :class:`NonFiniteOutput` naming ``producer`` (a method, the tracer...) and the first output
    of ``outputs`` (``{name: tensor, array or number}``) that holds NaN or infinity, with how many of each:
    the last check of a command before it writes, so that nothing non-finite is ever returned with
    exit status 0."""
    import numpy as np

    for name, value in outputs.items():
        if value is None:
            continue
        a = value.detach().cpu().double().numpy() if hasattr(value, "detach") else np.asarray(value, dtype=np.float64)
        nan, inf = int(np.isnan(a).sum()), int(np.isinf(a).sum())
        if nan or inf:
            raise NonFiniteOutput(f"{producer}: {name} has {nan} NaN and {inf} infinite values of {a.size} "
                                  "(nothing was written; an input outside the documented ranges?)")
