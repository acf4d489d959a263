"""What every screen-space AO module shares: parameters, presets, the walk, and the output.

A method subclasses :class:`ScreenSpaceAO` and supplies

* ``accumulator(frame)`` -> a :class:`~torch_ao.marching.SliceAccumulator` (what it keeps per step),
* optionally ``pattern(frame)`` (where the walk goes; default :class:`~torch_ao.marching.SlicePattern`),
* optionally ``frame_buffers(gbuffer)`` (images its samples gather, e.g. light).

``forward(gbuffer)`` returns an :class:`AOOutput`; background pixels get visibility 1, zero indirect
light and their own normal as bent normal, with zero gradient.
"""
from __future__ import annotations

import abc

from dataclasses import dataclass

import torch
from torch import nn

from ..gbuffer import GBuffer
from ..marching import Frame, SamplingPattern, SliceAccumulator, SlicePattern, march

__all__ = ["AOOutput", "ScreenSpaceAO", "PRESETS", "resolve_preset", "make_parameter"]

#: Quality presets shared by every horizon/bitmask method: (slices, steps per side).
PRESETS: dict[str, tuple[int, int]] = {
    "low": (1, 2),
    "medium": (2, 2),
    "high": (3, 3),
    "ultra": (9, 3),
    "extreme": (16, 8),
    "reference": (32, 32),
}


def resolve_preset(preset: str | None, slices: int | None, steps: int | None, default: tuple[int, int]) -> tuple[int, int]:
    """Slices and steps from a preset name and/or explicit counts (explicit counts win)."""
    if preset is not None:
        key = str(preset).lower()
        if key not in PRESETS:
            raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
        default = PRESETS[key]
    return (default[0] if slices is None else slices, default[1] if steps is None else steps)


def make_parameter(module: nn.Module, name: str, value, *, trainable: bool, minimum: float | None = None) -> None:
    """Register a float parameter (an ``nn.Parameter`` when ``trainable``, else a buffer).

    ``value`` may be a number or a tensor (a per-object table or a per-pixel map). Non-finite values
    and values below ``minimum`` raise a ``ValueError`` naming ``name``.
    """
    t = torch.as_tensor(value).detach().clone()
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: expected finite values, got {t.tolist() if t.numel() < 8 else 'a tensor with non-finite entries'}")
    if minimum is not None and bool((t < minimum).any()):
        raise ValueError(f"{name}: expected values >= {minimum}, got {t.min().item()}")
    if trainable:
        setattr(module, name, nn.Parameter(t))
    else:
        module.register_buffer(name, t)


@dataclass
class AOOutput:
    """Outputs of a screen-space AO module (only what was asked for is not ``None``).

    Attributes:
        visibility: ``(B,1,H,W)`` in [0, 1], 1 = unoccluded (faithful variants may document otherwise).
        indirect: ``(B,3,H,W)`` one-bounce indirect light, when requested.
        bent_normal: ``(B,3,H,W)`` unit view-space bent normals, when requested.
        ambient: ``(B,3,H,W)`` ambient light through unoccluded sectors, when requested.
    """

    visibility: torch.Tensor
    indirect: torch.Tensor | None = None
    bent_normal: torch.Tensor | None = None
    ambient: torch.Tensor | None = None


class ScreenSpaceAO(nn.Module, abc.ABC):
    """Base of the horizon and bitmask modules.

    Args:
        slices, steps: directions per pixel and samples per side (override ``preset``).
        preset: ``"low"`` (1x2), ``"medium"`` (2x2), ``"high"`` (3x3), ``"ultra"`` (9x3), ``"extreme"``
            (16x8), ``"reference"`` (32x32).
        radius: world-space sampling radius (a trainable parameter unless ``trainable=False``).
        step_power, min_step_px, jitter, seed, fetch, border, azimuth: see :class:`~torch_ao.marching.SlicePattern`.
        normals: ``"improved"`` or ``"kornia"``: reconstruction used when the G-buffer has no normals.
        chunk_size, recompute: memory controls passed to :func:`~torch_ao.marching.march`.
    """

    default_slices_steps: tuple[int, int] = (4, 8)

    def __init__(self, *, slices: int | None = None, steps: int | None = None, preset: str | None = None,
                 radius: float = 1.0, step_power: float = 1.0, min_step_px: float = 1.0, jitter: bool = True,
                 seed: int = 0, fetch: str = "bilinear", border: str = "drop", azimuth: str = "view",
                 normals: str = "improved", chunk_size: int | None = None, recompute: bool = False,
                 trainable: bool = True) -> None:
        super().__init__()
        self.slices, self.steps = resolve_preset(preset, slices, steps, self.default_slices_steps)
        make_parameter(self, "radius", radius, trainable=trainable, minimum=0.0)
        if self.radius.dim() != 0:
            raise ValueError(f"radius: expected a scalar, got shape {tuple(self.radius.shape)}")
        if normals not in ("improved", "kornia"):
            raise ValueError(f"normals: expected 'improved' or 'kornia', got {normals!r}")
        self.step_power, self.min_step_px = step_power, min_step_px
        self.jitter, self.seed, self.fetch, self.border, self.azimuth = jitter, seed, fetch, border, azimuth
        self.normals_method = normals
        self.chunk_size, self.recompute = chunk_size, recompute
        self.pattern_for(None)  # validate the sampling options now, not at the first call

    @classmethod
    def options(cls) -> dict:
        """``{name: Option}`` of the keyword arguments the constructor takes, following ``**kwargs`` up
        the class hierarchy. TEMPORARY: derived from the signatures (kind from the default or the
        annotation, help from the class docstrings' ``Args``), until each method lists its own."""
        import inspect
        import re

        from ..options import Option

        def docs(klass) -> dict[str, str]:
            out, text = {}, inspect.getdoc(klass) or ""
            for m in re.finditer(r"^ {4}([\w, *]+): (.*(?:\n {8}.*)*)", text, re.M):
                for name in m.group(1).split(","):
                    out.setdefault(name.strip(), " ".join(m.group(2).split()))
            return out

        found: dict = {}
        for klass in cls.__mro__:
            init = klass.__dict__.get("__init__")
            if init is None:
                continue
            params = inspect.signature(init).parameters.values()
            helps = docs(klass)
            for p in params:
                if p.name == "self" or p.kind not in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) or p.name in found:
                    continue
                default = None if p.default is p.empty else p.default
                annotation = str(p.annotation)
                kind = next((k for k in (bool, int, float, str) if isinstance(default, k)), None) or next(
                    (k for k in (bool, int, float, str) if re.match(rf"{k.__name__}\b", annotation)), object)
                text = helps.get(p.name, p.name.replace("_", " "))
                said = re.search(r"\bin (sector|world|pixel|radian)s?\b|\b(world)-space", text)
                unit = {"sector": "sectors", "world": "world units", "pixel": "pixels", "radian": "radians"}[
                    next(g for g in said.groups() if g)] if said else ""
                found[p.name] = Option(p.name, default, text, kind, unit=unit)
            if not any(p.kind == p.VAR_KEYWORD for p in params):
                break
        return found

    # ---------------------------------------------------------------- hooks for subclasses
    def pattern_for(self, frame: Frame | None) -> SamplingPattern:
        return SlicePattern(self.slices, self.steps, self.radius, step_power=self.step_power,
                            min_step_px=self.min_step_px, jitter=self.jitter, seed=self.seed, fetch=self.fetch,
                            border=self.border, azimuth=self.azimuth)

    def frame_buffers(self, gbuffer: GBuffer, normals: torch.Tensor) -> dict[str, torch.Tensor]:
        """``(B,C,H,W)`` images the samples gather (default none)."""
        return {}

    def query_values(self, gbuffer: GBuffer) -> dict[str, torch.Tensor]:
        """``(B,C,H,W)`` images read once at each computed pixel (default none)."""
        return {}

    def chunking(self, gbuffer: GBuffer) -> tuple[int | None, bool]:
        """``(chunk_size, recompute)`` passed to :func:`~torch_ao.marching.march` for this call
        (default: the constructor's)."""
        return self.chunk_size, self.recompute

    @abc.abstractmethod
    def accumulator(self, frame: Frame) -> SliceAccumulator:
        """What the method keeps per step of the walk over ``frame``."""

    # ---------------------------------------------------------------- forward
    def forward(self, gbuffer: GBuffer) -> AOOutput:
        if not isinstance(gbuffer, GBuffer):
            raise TypeError(f"gbuffer: expected a torch_ao.GBuffer, got {type(gbuffer).__name__}")
        normals = gbuffer.view_normals(self.normals_method)
        frame = Frame(gbuffer, normals=normals, buffers=self.frame_buffers(gbuffer, normals),
                      query_values=self.query_values(gbuffer))
        chunk_size, recompute = self.chunking(gbuffer)
        out = march(frame, self.pattern_for(frame), self.accumulator(frame), chunk_size=chunk_size,
                    recompute=recompute)
        return AOOutput(
            visibility=frame.scatter(out["visibility"], 1.0),
            indirect=frame.scatter(out["indirect"], 0.0) if "indirect" in out else None,
            bent_normal=frame.scatter(out["bent_normal"], normals) if "bent_normal" in out else None,
            ambient=frame.scatter(out["ambient"], 0.0) if "ambient" in out else None,
        )

    def extra_repr(self) -> str:
        return f"slices={self.slices}, steps={self.steps}, fetch={self.fetch!r}, border={self.border!r}"
