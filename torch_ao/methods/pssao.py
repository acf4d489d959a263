"""Planar screen-space AO (PSSAO), seed 003 (Codezigineer's gist), as its GLSL code computes it.

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
is in pixels, so ``radius`` is not used (it is kept, frozen, for a uniform interface).
"""
from __future__ import annotations

import math

import torch

from ..gbuffer import GBuffer
from ..marching import BORDER_MODES, FETCH_MODES, SamplingPattern, tangent_from_screen_angle
from .base import AOOutput, ScreenSpaceAO, make_parameter
from .gtao import check_choice, run_functional, with_base_signature

__all__ = ["PSSAO", "pssao", "PSSAOPattern"]


class PSSAOPattern(SamplingPattern):
    """Full-circle directions ``2 pi i / n`` (no jitter), steps at ``floor(direction * k)`` pixels."""

    sides = (1,)

    def __init__(self, slices: int, steps: int, *, fetch: str = "nearest", border: str = "drop") -> None:
        for name, value in (("slices", slices), ("steps", steps)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
        check_choice("fetch", fetch, FETCH_MODES)
        check_choice("border", border, BORDER_MODES)
        self.num_slices, self.steps, self.fetch, self.border = slices, steps, fetch, border

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


class PSSAOAccumulator:
    def __init__(self, module: "PSSAO", frame, pattern: PSSAOPattern) -> None:
        self.m, self.pattern = module, pattern
        _, self.H, self.W = frame.shape

    def begin_slice(self, q, geom):
        return {"max": torch.full_like(q.depth, -100000.0), "count": torch.zeros_like(q.depth)}

    def step(self, state, q, geom, sample):
        du, dv = self.pattern.pixel_offset(geom.index, sample.step)
        u, v = q.u + du, q.v + dv
        inside = (u >= 0) & (u <= self.W - 1) & (v >= 0) & (v <= self.H - 1)
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


@with_base_signature
class PSSAO(ScreenSpaceAO):
    """Planar SSAO (seed 003); see the module docstring.

    Args:
        slices: directions over the full circle (the gist's ``angularSteps``).
        steps: samples per direction including the pixel itself (``radiusSteps``).
        distance_bias: the ``1.0`` in ``a /= 1.0 + distance`` (parameter, > 0).
        normalize: ``"samples"`` (faithful) or ``"directions"``.
        fetch, border: default nearest / drop (offsets are integers, so the fetch does not matter
            for depth; border ``"clamp"`` would re-read edge pixels instead of skipping them).
    """

    default_slices_steps = (8, 8)
    unused_base_arguments = ("jitter", "azimuth", "step_power", "min_step_px")

    def __init__(self, *, distance_bias: float = 1.0, normalize: str = "samples", fetch: str = "nearest",
                 border: str = "drop", trainable: bool = True, **kwargs) -> None:
        self.normalize = check_choice("normalize", normalize, ("samples", "directions"))
        for name in self.unused_base_arguments:
            if name in kwargs:
                raise ValueError(f"{name}: not used by PSSAO (its walk is fixed by the gist)")
        super().__init__(fetch=fetch, border=border, jitter=False, trainable=trainable, **kwargs)
        radius = self.radius.detach().clone()
        del self.radius
        self.register_buffer("radius", radius)  # unused: the walk is in pixels
        make_parameter(self, "distance_bias", distance_bias, trainable=trainable)
        if self.distance_bias.dim() != 0 or not float(self.distance_bias.detach()) > 0:
            raise ValueError(f"distance_bias: expected a scalar > 0, got {self.distance_bias.detach().tolist()}")

    def pattern_for(self, frame):
        return PSSAOPattern(self.slices, self.steps, fetch=self.fetch, border=self.border)

    def accumulator(self, frame):
        return PSSAOAccumulator(self, frame, self.pattern_for(frame))

    def extra_repr(self) -> str:
        return f"normalize={self.normalize!r}, " + super().extra_repr()


def pssao(gbuffer: GBuffer, *, distance_bias=1.0, **options) -> AOOutput:
    """Functional :class:`PSSAO`: ``distance_bias`` may be a tensor (gradients flow to it)."""
    return run_functional(PSSAO, gbuffer, dict(distance_bias=distance_bias), **options)
