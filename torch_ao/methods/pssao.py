"""Planar screen-space AO (PSSAO), the PSSAO gist (Codezigineer), as its GLSL code computes it.

For every direction ``i`` of ``slices`` evenly spaced over the full circle (angle ``2 pi i / slices``,
no jitter) and every step ``k = 0 .. steps-1``, the sample is the pixel at the integer offset
``floor(direction * k)`` (GL pixel axes, y up). Samples outside the image are skipped. Per sample
(``calcOcclusionFromPixel``), with ``P`` the pixel, ``Q`` the sample and ``n`` the pixel's normal::

    a = dot(n, Q - P);   occlusion = 0 if a <= 0;   a /= distance_bias + |Q - P|;   occlusion = 1 - 1/(1 + a)

(the gist's prose divides by the *screen* distance, its code by ``1 + |Q - P|`` in 3D: the code is what
is implemented; ``distance_bias`` is the code's ``1.0``, a parameter). Per direction the maximum
occlusion is kept, and the directions' maxima are summed. The sum is divided (``normalize``) by

* ``"samples"`` (faithful): the number of in-bounds samples over all directions (``toInclude``,
  including each direction's ``k = 0`` sample, the pixel itself, which occludes nothing);
* ``"directions"`` (improvement): the number of directions, so the result is the mean per-direction
  maximum and no longer shrinks as ``steps`` grows.

Visibility is ``1 - occlusion``, in [0, 1] by construction (each maximum lies in [0, 1)).

Differences from the gist, by necessity: positions come from the G-buffer's camera (the gist's
``getPos`` treats depth as distance along a half-pixel-shifted ray); normals are the G-buffer's or,
when absent, reconstructed with the same improved rule as the gist's ``computeNormalImproved``;
background samples occlude nothing (the gist reads whatever the depth texture holds there). The walk
is in pixels, so there is no ``radius``.
"""
from __future__ import annotations

import math

import torch

from ..checks import check_choice, check_int
from ..options import Option
from ..walk import BORDER_MODES, FETCH_MODES, SamplingPattern, SliceAccumulator, tangent_from_screen_angle
from .base import ScreenSpaceAO
from .common import Sampling, declare_signature, functional_twin, register_parameters

__all__ = ["PSSAO", "pssao", "PSSAOPattern"]


class PSSAOPattern(SamplingPattern):
    """Full-circle directions ``2 pi i / n`` (no jitter), steps at ``floor(direction * k)`` pixels."""

    sides = (1,)

    def __init__(self, slices: int, steps: int, *, fetch: str = "nearest", border: str = "drop") -> None:
        self.num_slices, self.steps = check_int("slices", slices, 1), check_int("steps", steps, 1)
        self.fetch, self.border = check_choice("fetch", fetch, FETCH_MODES), check_choice("border", border, BORDER_MODES)

    def angle(self, s: int) -> float:
        return s / self.num_slices * 2 * math.pi

    def pixel_offset(self, s: int, k: int) -> tuple[float, float]:
        """``(du, dv)`` in image pixels (v down) of step ``k`` on direction ``s``: the gist's
        ``floor(direction * k)`` in GL axes (y up), flipped to rows."""
        a = self.angle(s)
        return float(math.floor(math.cos(a) * k)), -float(math.floor(math.sin(a) * k))

    def slice_tangent(self, frame, q, s):
        return tangent_from_screen_angle(q, torch.full_like(q.u, self.angle(s)))

    def step_offsets(self, q, geom, side):
        out = []
        for k in range(self.steps):
            du, dv = self.pixel_offset(geom.index, k)
            out.append(torch.stack((torch.full_like(q.u, du), torch.full_like(q.u, dv)), -1))
        return out


class PSSAOAccumulator(SliceAccumulator):
    """Per direction: the largest sample occlusion and the number of in-image samples (``toInclude``)."""

    def __init__(self, module: "PSSAO") -> None:
        self.m = module

    def begin_slice(self, q, geom):
        return {"max": torch.full_like(q.depth, -100000.0), "count": torch.zeros_like(q.depth)}

    def step(self, state, q, geom, sample):
        inside = sample.inside
        a = (q.normal * sample.delta).sum(-1).clamp_min(0.0)
        a = a / (self.m.distance_bias.to(a.dtype) + sample.distance)
        occ = a / (1 + a)  # 1 - 1/(1 + a)
        occ = torch.where(sample.valid, occ, torch.zeros_like(occ))
        state["max"] = torch.where(inside, torch.maximum(state["max"], occ), state["max"])
        state["count"] = state["count"] + inside.to(occ.dtype)
        return state

    def end_slice(self, state, q, geom):
        has = state["count"] > 0
        return {"sum": torch.where(has, state["max"], torch.zeros_like(state["max"]))[:, None],
                "count": state["count"][:, None], "dirs": has.to(state["count"].dtype)[:, None]}

    def finish(self, sums, q, num_slices):
        denom = sums["count"] if self.m.normalize == "samples" else sums["dirs"]
        occ = sums["sum"] / denom.clamp_min(1.0)
        return {"visibility": 1 - occ}


@declare_signature
class PSSAO(ScreenSpaceAO):
    """Planar SSAO (the PSSAO gist); see the module docstring and :meth:`options`. ``slices`` are the gist's
    ``angularSteps`` (directions over the full circle), ``steps`` its ``radiusSteps`` (including the pixel)."""

    OPTIONS = (
        Option("distance_bias", 1.0, "The 1.0 in the gist's a /= 1.0 + distance", unit="world units", minimum=0.0,
               open_minimum=True, fitted=True),
        Option("normalize", "samples", "samples: divide by the in-image samples (the gist); directions: by the "
               "directions, so the result does not shrink as steps grows", kind=str, choices=("samples", "directions")),
    )
    SAMPLING = Sampling.options_for(("preset", "slices", "steps", "fetch", "border"), fetch="nearest")
    default_slices_steps = (8, 8)
    has_kernel = "pssao"  # forward in torch_ao.kernels (pssao_covers says which calls)

    @classmethod
    def parse_options(cls, options):
        return super().parse_options(options) | {"jitter": False}  # the gist's walk is fixed

    def __init__(self, **options) -> None:
        super().__init__(**options)
        self.normalize = self.values["normalize"]
        register_parameters(self, self.options(), self.values, ("distance_bias",), trainable=self.trainable)

    def pattern_for(self, frame):
        return PSSAOPattern(self.slices, self.steps, fetch=self.fetch, border=self.border)

    def accumulator(self, frame):
        return PSSAOAccumulator(self)

    def extra_repr(self) -> str:
        return f"normalize={self.normalize!r}, " + super().extra_repr()


pssao = functional_twin(PSSAO, "pssao")
