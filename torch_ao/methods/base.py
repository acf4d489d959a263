"""The module every screen-space AO method is: options in, a walk over the G-buffer, an :class:`AOOutput` out.

A method is composed of parts rather than configured through a wide base constructor:

* its options (``OPTIONS``, :class:`~torch_ao.options.Option`), the walk's it takes (``SAMPLING``, from
  :class:`~torch_ao.methods.common.Sampling`) and :data:`~torch_ao.methods.common.MODULE_OPTIONS`,
  merged by ``options()``, validated once in the constructor (``parse_options``);
* a :class:`~torch_ao.walk.SamplingPattern` (``pattern_for``; default :class:`~torch_ao.walk.SlicePattern`
  from the module's :class:`~torch_ao.methods.common.Sampling`), and a
  :class:`~torch_ao.walk.SliceAccumulator` (``accumulator``: what it keeps per step);
* optionally ``frame_buffers(gbuffer, normals)`` (images its samples gather, e.g. light) and ``walk``
  (a method that is not a slice walk, like SSAO, replaces the walk, keeping chunking and recompute).

``forward(gbuffer)`` returns an :class:`AOOutput`; background pixels get visibility 1, zero indirect
light and their own normal as bent normal, with zero gradient.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ..gbuffer import GBuffer
from ..kernels import kernel_forward
from ..limits import check_limit, walk_bytes
from ..options import Option, options_by_name
from ..resolution import reduced_forward, resolution_factor
from ..walk import Frame, SamplingPattern, SliceAccumulator, march
from .common import (DEFAULT_PRESET, MODULE_OPTIONS, PRESETS, RADIUS, Sampling, declare_signature, make_parameter, register_parameters,
                     resolve_preset, split_preset)

__all__ = ["AOOutput", "ScreenSpaceAO", "PRESETS", "resolve_preset", "make_parameter"]


@dataclass
class AOOutput:
    """Outputs of a screen-space AO module (only what was asked for is not ``None``).

    Attributes:
        visibility: ``(B,1,H,W)`` in [0, 1], 1 = unoccluded (faithful variants may document otherwise).
        indirect: ``(B,3,H,W)`` one-bounce indirect light, when requested.
        bent_normal: ``(B,3,H,W)`` unit view-space bent normals, when requested.
        ambient: ``(B,3,H,W)`` ambient light through unoccluded sectors, when requested.

    Shape:
        - ``visibility``: ``(B, 1, H, W)``; ``indirect``, ``bent_normal``, ``ambient``: ``(B, 3, H, W)`` or ``None``;
          float32 or float64 (the computation's dtype).
    """

    visibility: torch.Tensor
    indirect: torch.Tensor | None = None
    bent_normal: torch.Tensor | None = None
    ambient: torch.Tensor | None = None


@declare_signature
class ScreenSpaceAO(nn.Module):
    """Base of the horizon and bitmask modules: takes ``cls.options()`` as keyword arguments.

    Keeps the parsed options' :class:`~torch_ao.methods.common.Sampling` as ``sampling`` (its fields
    also read as attributes: ``slices``, ``steps``, ``fetch``...), registers ``radius`` when the method
    lists it, and the memory controls ``chunk_size``/``recompute`` passed to :func:`~torch_ao.walk.march`.
    A subclass registers its own fitted options after ``super().__init__`` from ``self.values``.
    """

    #: The method's own options (a subclass lists its own, ``RADIUS`` included when it searches a radius).
    OPTIONS: tuple[Option, ...] = (RADIUS,)
    #: The walk's options this method takes (all of them by default), with its defaults.
    SAMPLING: tuple[Option, ...] = Sampling.options_for()
    #: the name of this method's fused kernel in :mod:`torch_ao.kernels` (``KERNELS``; it then decides per
    #: call), or ``False``
    has_kernel: str | bool = False
    #: (slices, steps) when neither they nor a preset are given.
    default_slices_steps: tuple[int, int] = PRESETS[DEFAULT_PRESET]

    def __init__(self, **options) -> None:
        super().__init__()
        self.values: dict[str, Any] = type(self).parse_options(options)
        v = self.values
        self.sampling = Sampling.from_values(v, self.default_slices_steps)
        self.normals_method, self.chunk_size, self.recompute = v["normals"], v["chunk_size"], v["recompute"]
        self.trainable = v["trainable"]
        self.backend = v["backend"]
        preset = v.get("preset")
        #: the walk's resolution: ``"full"``, ``"half"`` or ``"quarter"`` (explicit option, else the preset's suffix)
        self.resolution = v["resolution"] or (split_preset(preset)[1] if preset is not None else None) or "full"
        #: fitted options that get no gradient with these options ``{name: why}``: buffers, not parameters
        self.no_gradient_options: dict[str, str] = self.no_gradient(v)
        if "radius" in v:
            register_parameters(self, self.options(), v, ("radius",), trainable=self.trainable,
                                frozen=self.no_gradient_options)

    @classmethod
    def options(cls) -> dict[str, Option]:
        """Every option of the method ``{name: Option}``: its own, the walk's it takes, the module's."""
        return options_by_name(cls.OPTIONS, cls.SAMPLING, MODULE_OPTIONS)

    @classmethod
    def parse_options(cls, options: dict[str, Any]) -> dict[str, Any]:
        """``options`` checked against :meth:`options` (``ValueError`` naming a bad or unknown one), with the
        defaults of those not given. Fitted options may be tensors; they are checked when registered."""
        spec = cls.options()
        for name in options:
            if name not in spec:
                raise ValueError(f"{name}: not an option of {cls.__name__}; expected one of {', '.join(spec)}")
        values = {name: opt.default for name, opt in spec.items()} | dict(options)
        for name, opt in spec.items():
            if not opt.fitted:
                values[name] = opt.check(values[name])
        return values

    # The configuration's fields, read as attributes (the bitmask family and tests read them so).
    slices = property(lambda self: self.sampling.slices)
    steps = property(lambda self: self.sampling.steps)
    step_power = property(lambda self: self.sampling.step_power)
    min_step_px = property(lambda self: self.sampling.min_step_px)
    jitter = property(lambda self: self.sampling.jitter)
    seed = property(lambda self: self.sampling.seed)
    noise = property(lambda self: self.sampling.noise)
    slice_sampling = property(lambda self: self.sampling.slice_sampling)
    stagger = property(lambda self: self.sampling.stagger)
    fetch = property(lambda self: self.sampling.fetch)
    border = property(lambda self: self.sampling.border)
    azimuth = property(lambda self: self.sampling.azimuth)

    def no_gradient(self, values: dict[str, Any]) -> dict[str, str]:
        """The fitted options whose gradient is zero everywhere with the options ``values`` (a hard
        comparison of the published shader, a value that only picks texels), ``{name: why and what makes it
        fittable}``. They are registered as buffers, not ``nn.Parameter``\\ s, so an optimizer never holds a
        parameter it cannot move. Default: none."""
        return {}

    # ---------------------------------------------------------------- parts
    def pattern_for(self, frame: Frame | None) -> SamplingPattern:
        """Where the walk over ``frame`` goes (default: :class:`~torch_ao.walk.SlicePattern` of ``sampling``)."""
        return self.sampling.pattern(self.radius)

    def accumulator(self, frame: Frame) -> SliceAccumulator:
        """What the method keeps per step of the walk over ``frame``."""
        raise TypeError(f"{type(self).__name__}: a slice method returns its SliceAccumulator here")

    def frame_buffers(self, gbuffer: GBuffer, normals: torch.Tensor) -> dict[str, torch.Tensor]:
        """``(B,C,H,W)`` images the samples gather (default none)."""
        return {}

    def chunking(self, gbuffer: GBuffer) -> tuple[int | None, bool]:
        """``(chunk_size, recompute)`` passed to :func:`~torch_ao.walk.march` for this call
        (default: the constructor's)."""
        return self.chunk_size, self.recompute

    def walk(self, frame: Frame, chunk_size: int | None, recompute: bool) -> dict[str, torch.Tensor]:
        """Per-query outputs ``{name: (N, C)}`` (``"visibility"``, and the optional outputs asked for)."""
        return march(frame, self.pattern_for(frame), self.accumulator(frame), chunk_size=chunk_size,
                     recompute=recompute)

    # ---------------------------------------------------------------- forward
    def forward(self, gbuffer: GBuffer) -> AOOutput:
        """The outputs ``(B,C,H,W)`` of :class:`AOOutput` for ``gbuffer``; at ``resolution`` half or quarter,
        walked on the decimated G-buffer and upsampled (:mod:`torch_ao.resolution`)."""
        if not isinstance(gbuffer, GBuffer):
            raise TypeError(f"gbuffer: expected a torch_ao.GBuffer, got {type(gbuffer).__name__}")
        factor = resolution_factor(self.resolution)
        with gbuffer.one_call():  # (positions and normals computed once in the call, gradients or not)
            if factor == 1:
                return self._forward_full(gbuffer)
            return reduced_forward(self._forward_full, gbuffer, factor, self.normals_method)

    def check_memory(self, gbuffer: GBuffer) -> None:
        """Refuse (:class:`~torch_ao.limits.ResourceLimitError`) a call whose estimated memory
        (:func:`~torch_ao.limits.walk_bytes`, an upper bound: the tensor-op walk's) exceeds the limit."""
        B, _, H, W = gbuffer.depth.shape
        grad = torch.is_grad_enabled() and (any(p.requires_grad for p in self.parameters()) or any(
            t is not None and t.requires_grad for t in (gbuffer.depth, gbuffer.normals, gbuffer.light, gbuffer.position)))
        chunk_size, recompute = self.chunking(gbuffer)
        need = walk_bytes(B, H, W, self.slices, self.steps, grad=grad, chunk_size=chunk_size, recompute=recompute)
        check_limit("walk_bytes", need, f"{type(self).__name__}: {B}x{H}x{W} pixels at {self.slices} slices x "
                    f"{self.steps} steps{' with gradients' if grad else ''}",
                    "or give chunk_size (and recompute=True), fewer slices or steps, or a smaller frame")

    def _forward_full(self, gbuffer: GBuffer) -> AOOutput:
        with gbuffer.one_call():  # (a reduced resolution's G-buffer is a new one)
            return self._walk_full(gbuffer)

    def _walk_full(self, gbuffer: GBuffer) -> AOOutput:
        self.check_memory(gbuffer)
        fused = kernel_forward(self, gbuffer, self.backend)  # None: the tensor-op walk below
        if fused is not None:
            return AOOutput(**fused)
        normals = gbuffer.view_normals(self.normals_method)
        frame = Frame(gbuffer, normals=normals, buffers=self.frame_buffers(gbuffer, normals))
        out = self.walk(frame, *self.chunking(gbuffer))
        return AOOutput(
            visibility=frame.scatter(out["visibility"], 1.0),
            indirect=frame.scatter(out["indirect"], 0.0) if "indirect" in out else None,
            bent_normal=frame.scatter(out["bent_normal"], normals) if "bent_normal" in out else None,
            ambient=frame.scatter(out["ambient"], 0.0) if "ambient" in out else None,
        )

    def extra_repr(self) -> str:
        res = f", resolution={self.resolution!r}" if self.resolution != "full" else ""
        return f"slices={self.slices}, steps={self.steps}, fetch={self.fetch!r}, border={self.border!r}{res}"
