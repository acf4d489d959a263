"""The base of the thickness models (:mod:`torch_ao.thickness` describes them): a model's fitted
:class:`Parameter` and the :class:`Thickness` interface, which :mod:`torch_ao.thickness` and
:mod:`torch_ao.thickness_net` both build on."""
from __future__ import annotations

import abc
from dataclasses import dataclass

import torch

from .checks import check_float

__all__ = ["Parameter", "Thickness", "ThicknessLayer", "checked_growth"]


@dataclass(frozen=True)
class Parameter:
    """A fitted parameter of a thickness model: its initial value and lower bound."""

    value: torch.Tensor
    minimum: float | None = 0.0


@dataclass(frozen=True)
class ThicknessLayer:
    """A model's thickness in the one form the fused kernels read: ``t = scale * value + offset`` at a sample.

    The value, by ``read``: ``"constant"`` none (``t = offset``); ``"layer"`` the image ``layer`` ``(B,1,H,W)``
    read at the sample as the walk reads depth (nearest, bilinear or edge-aware); ``"first_tap"`` that image at
    the footprint's first tap alone (an integer buffer's read: a per-object table looked up by ``object_id``);
    ``"depth"`` the sample's own depth (world units). ``scale`` and ``offset`` (world units) are 0-d tensors, the
    model's parameters where they are ones (their gradients then reach them). ``growth`` (a 0-d tensor, per world
    unit, or ``None``): ``t`` times ``1 + growth * |sample - pixel|``, the model's growth."""

    layer: torch.Tensor | None
    scale: torch.Tensor
    offset: torch.Tensor
    read: str = "layer"
    growth: torch.Tensor | None = None


def checked_growth(growth: float | torch.Tensor | None) -> float | torch.Tensor | None:
    """``growth`` (a number ``>= 0``, a tensor, or ``None``), checked."""
    if growth is not None and not isinstance(growth, torch.Tensor):
        growth = check_float("thickness_growth", growth, 0.0)
    return growth


class Thickness(abc.ABC):
    """Base of the thickness models (see the module docstring).

    Args:
        growth: optional ``g >= 0`` (per world unit): the thickness grows as ``1 + g * |sample - pixel|``.
    """

    def __init__(self, *, growth: float | torch.Tensor | None = None) -> None:
        self.growth = checked_growth(growth)

    def own_parameters(self) -> dict[str, Parameter]:
        """The model's own parameters (without growth)."""
        return {}

    def parameters(self) -> dict[str, Parameter]:
        """Every parameter the AO module registers for this model: name -> :class:`Parameter`."""
        out = self.own_parameters()
        if self.growth is not None:
            out["thickness_growth"] = Parameter(torch.as_tensor(self.growth))
        return out

    def check(self, name: str, value: torch.Tensor) -> None:
        """Raise ``ValueError`` if ``value`` cannot be parameter ``name`` (its shape)."""
        if value.dim() != 0:
            raise ValueError(f"{name}: expected a scalar, got shape {tuple(value.shape)}")

    def buffers(self, gbuffer, params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """``(B,C,H,W)`` images the samples read (default none); ``ValueError`` if the G-buffer lacks one."""
        return {}

    #: the ``read`` of the :class:`ThicknessLayer` that :meth:`layer` returns (``None``: the model is not of
    #: that form), known without computing it
    kernel_read: str | None = None

    def layer(self, gbuffer, params: dict[str, torch.Tensor]) -> ThicknessLayer | None:
        """The model as :class:`ThicknessLayer` (growth aside), or ``None`` when it is not of that form (the
        fused kernels then leave it to the tensor path)."""
        return None

    @abc.abstractmethod
    def at(self, sample, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """Thickness ``(rows,)`` (or 0-d) of the occluder at ``sample``, before growth, in world units."""

    def value(self, sample, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """:meth:`at`, times the growth factor when the model has one."""
        t = self.at(sample, params)
        if self.growth is not None:
            t = t * (1 + params["thickness_growth"].to(sample.dtype) * sample.distance)
        return t

    def describe(self) -> str:
        return type(self).__name__ + ("" if self.growth is None else f"(growth={float(self.growth):g})")
