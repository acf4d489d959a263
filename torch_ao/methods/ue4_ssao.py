"""UE4's normal-less screen-space AO ("wedge" pairs), as the HBAO/UE4 article gives ``PostProcessAmbientOcclusion.usf``.

Per direction ``i`` (a slice) and step ``j`` the shader reads a symmetric pair of samples at screen
offsets ``+o`` and ``-o`` (the walk's two sides of one slice at the same step, taken together:
``paired_sides``), with view-space offsets
``DL``, ``DR`` from the pixel and depths ``zL``, ``zR`` (the pixel's: ``zc``). ``WedgeNoNormal``::

    NormAngle = saturate((1 - cos(DL, DR)) * 0.5 * 0.9)        # acosApproxNormAngle, "contrast tweak" 0.9
    NormAngle = 1  if (zc - zL) + (zc - zR) < flat_surface_bias # flat or concave-away pair: no occlusion
    Weight    = saturate(1 - (zc - zL)/D) * saturate(1 - (zc - zR)/D)   # halo weight, D = fade_distance
    x         = (1 - NormAngle) / (Weight + 0.001)

combined over the steps of a direction as ``acc = lerp(acc, (max(acc.x, x), 1), Weight)`` (starting at
``(0, 0)``), and over directions as ``AO = (1e-4 + sum_i (1 - acc_i.x)^2 acc_i.y) / (1e-4 + sum_i acc_i.y)``.
That ``AO`` is the visibility (1 = unoccluded; a pair spanning a straight angle gives ``x = 0``), finally
``1 - (1 - AO^final_power) * intensity`` as UE4's user adjustment, clamped to [0, 1] (``acc.x`` can exceed
1 when small weights amplify ``x``, and the square then leaves [0, 1] for ``acc.x > 2``).

The halo weight ``Weight`` is what the article calls the halo fix; the per-side ``WeightLeft/Right``
(``1 - |D| / halo``) of the article are dead code in the shipped shader (``OPTIMIZATION_O1``) and are not
used. Improvements (named options, off by default): ``accurate_angle=True`` uses ``acos(cos)/pi``;
``flat_softness > 0`` replaces the hard flat-surface test by a logistic blend of that width (so depth
gets a gradient through it). Without it ``flat_surface_bias`` has no gradient, nor has ``radius`` with the
default nearest fetch (it only picks texels): both are then buffers rather than parameters.

Sampling: ``sample_set="ue4_3"`` (default; UE4's 3 spiral offsets, ``SHADER_QUALITY`` 0-3) or
``"ue4_6"`` (6 offsets, quality 4) fix the directions and their lengths (``slices`` is then the set
size) and the whole set is rotated per pixel by interleaved gradient noise (UE4 reads a 4x4 random
texture); ``"uniform"`` spaces ``slices`` directions evenly. Step ``j`` is at ``(j + 1) / steps`` of the
direction's length times ``radius`` (projected at the pixel). A pair with an invalid sample
(background, or dropped at the border) is skipped (weight 0).
"""
from __future__ import annotations

import math

import torch

from ..ops import safe_pow
from ..options import Option
from ..walk import SliceAccumulator, SlicePattern, radius_px, step_direction, tangent_from_screen_angle
from .base import ScreenSpaceAO
from .common import RADIUS, Sampling, declare_signature, functional_twin, register_parameters

__all__ = ["UE4SSAO", "ue4_ssao", "WedgePattern", "SAMPLE_SETS"]

#: UE4's ``OcclusionSamplesOffsets`` (2D offsets on the unit disc, spiral order).
SAMPLE_SETS: dict[str, tuple[tuple[float, float], ...]] = {
    "ue4_3": ((0.0, -0.43), (0.58 * 0.7, 0.814 * 0.7), (-0.58, 0.814)),
    "ue4_6": ((0.000, 0.200), (0.325, 0.101), (0.272, -0.396), (-0.385, -0.488), (-0.711, 0.274), (0.060, 0.900)),
}


class WedgePattern(SlicePattern):
    """Half-circle slices (both sides = the pair), steps at ``(j + 1) / steps`` of each direction's length."""

    def __init__(self, slices, steps, radius, *, offsets=None, **kwargs) -> None:
        if offsets is not None:
            slices = len(offsets)
        super().__init__(slices, steps, radius, **kwargs)
        self.offsets = offsets

    def _direction(self, s: int) -> tuple[float, float]:
        if self.offsets is None:
            return s * math.pi / self.num_slices, 1.0
        x, y = self.offsets[s]
        return math.atan2(y, x), math.hypot(x, y)

    def slice_tangent(self, frame, q, s):
        angle, _ = self._direction(s)
        return tangent_from_screen_angle(q, angle + 2 * math.pi * self._noise(q)[0])

    def step_offsets(self, q, geom, side):
        _, length = self._direction(geom.index)
        unit = step_direction(geom, side)
        r_px = radius_px(self.radius, geom) * length
        return [((j + 1) / self.steps * r_px)[:, None] * unit for j in range(self.steps)]


class WedgeAccumulator(SliceAccumulator):
    """Per direction, UE4's ``WedgeNoNormal`` of each symmetric pair of samples (both sides of a step)."""

    paired_sides = True

    def __init__(self, module: "UE4SSAO") -> None:
        self.m = module

    def begin_slice(self, q, geom):
        zero = torch.zeros_like(q.depth)
        return {"x": zero, "y": zero}

    def step_pair(self, state, q, geom, plus, minus):
        m = self.m
        dtype = q.depth.dtype
        dl, pl, vl = plus.delta, plus.position, plus.valid
        dr, pr, vr = minus.delta, minus.position, minus.valid
        denom = (dl.square().sum(-1) * dr.square().sum(-1)).clamp_min(1e-30).sqrt()
        cos = ((dl * dr).sum(-1) / denom).clamp(-1.0, 1.0)
        if m.accurate_angle:
            norm_angle = torch.acos(cos.clamp(-1 + 1e-7, 1 - 1e-7)) / math.pi
        else:
            norm_angle = ((1 - cos) * 0.45).clamp(0.0, 1.0)
        zc = q.depth
        left, right = zc - (-pl[:, 2]), zc - (-pr[:, 2])
        bias = m.flat_surface_bias.to(dtype)
        if m.flat_softness > 0:
            flat = torch.sigmoid((bias - (left + right)) / m.flat_softness)
            norm_angle = norm_angle + flat * (1 - norm_angle)
        else:
            # A step: zero (not missing) gradient to the bias.
            norm_angle = torch.where(left + right < bias, torch.ones_like(norm_angle), norm_angle) + 0 * bias
        D = m.fade_distance.to(dtype).clamp_min(1e-30)
        weight = (1 - left / D).clamp(0.0, 1.0) * (1 - right / D).clamp(0.0, 1.0)
        weight = torch.where(vl & vr, weight, torch.zeros_like(weight))
        x = (1 - norm_angle) / (weight + 0.001)
        state["x"] = state["x"] + weight * (torch.maximum(state["x"], x) - state["x"])
        state["y"] = state["y"] + weight * (1 - state["y"])
        return state

    def end_slice(self, state, q, geom):
        x, y = state["x"], state["y"]
        return {"num": ((1 - x).square() * y)[:, None], "den": y[:, None]}

    def finish(self, sums, q, num_slices):
        m = self.m
        ao = (1e-4 + sums["num"]) / (1e-4 + sums["den"])
        ao = safe_pow(ao.clamp(0.0, 1.0), m.final_power.to(ao.dtype))
        vis = 1 - (1 - ao) * m.intensity.to(ao.dtype)
        return {"visibility": vis.clamp(0.0, 1.0)}


@declare_signature
class UE4SSAO(ScreenSpaceAO):
    """UE4's normal-less SSAO (the HBAO/UE4 article); see the module docstring and :meth:`options`.
    ``steps`` is UE4's ``SAMPLE_STEPS`` (1-3: pairs per direction); directions are rotated in screen space."""

    OPTIONS = (
        RADIUS,
        Option("fade_distance", 0.4, "D of the halo weight (UE4's AmbientOcclusionDistance: 80 cm for a 200 cm "
               "radius, hence 0.4)", unit="world units", minimum=0.0, open_minimum=True, fitted=True),
        Option("flat_surface_bias", 0.025, "Pairs this close to flat or concave-away do not occlude (UE4 hard-codes "
               "5 cm for a 200 cm radius, hence 0.025)", unit="world units", fitted=True),
        Option("final_power", 1.0, "UE4's 1 - (1 - AO^final_power) x intensity (the editor uses 2; 1 keeps the raw "
               "visibility)", minimum=0.0, open_minimum=True, fitted=True),
        Option("intensity", 1.0, "UE4's intensity in 1 - (1 - AO^final_power) x intensity (the editor uses 0.5)",
               minimum=0.0, fitted=True),
        Option("sample_set", "ue4_3", "ue4_3 / ue4_6: UE4's 3 or 6 spiral offsets (slices is then the set's size); "
               "uniform: slices evenly spaced", kind=str, choices=("ue4_3", "ue4_6", "uniform")),
        Option("accurate_angle", False, "acos(cos)/pi instead of UE4's linear approximation with contrast 0.9",
               kind=bool),
        Option("flat_softness", 0.0, "> 0: the flat-surface test becomes a logistic blend of this width, so depth "
               "gets a gradient through it", unit="world units", minimum=0.0),
    )
    SAMPLING = Sampling.options_for(("preset", "slices", "steps", "jitter", "seed", "fetch", "border"),
                                    fetch="nearest", border="clamp")
    default_slices_steps = (3, 3)
    has_kernel = "ue4_ssao"  # forward in torch_ao.kernels (ue4_ssao_covers says which calls)

    @classmethod
    def parse_options(cls, options):
        values = super().parse_options(options) | {"azimuth": "screen"}
        if values["sample_set"] != "uniform":
            values["slices"] = len(SAMPLE_SETS[values["sample_set"]])
        return values

    def __init__(self, **options) -> None:
        super().__init__(**options)
        v = self.values
        self.sample_set, self.accurate_angle, self.flat_softness = v["sample_set"], v["accurate_angle"], float(v["flat_softness"])
        register_parameters(self, self.options(), v, ("fade_distance", "flat_surface_bias", "final_power", "intensity"),
                            trainable=self.trainable, frozen=self.no_gradient_options)

    def no_gradient(self, values):
        out = {}
        if values["fetch"] == "nearest":
            out["radius"] = "with fetch='nearest' the radius only picks texels (no gradient): use fetch='bilinear' to fit it"
        if float(values["flat_softness"]) == 0:
            out["flat_surface_bias"] = ("the hard flat-surface test (flat_softness 0) has no gradient: give "
                                        "flat_softness > 0 to fit it")
        return out

    def pattern_for(self, frame):
        return self.sampling.pattern(self.radius, WedgePattern, offsets=SAMPLE_SETS.get(self.sample_set))

    def accumulator(self, frame):
        return WedgeAccumulator(self)

    def extra_repr(self) -> str:
        return f"sample_set={self.sample_set!r}, " + super().extra_repr()


ue4_ssao = functional_twin(UE4SSAO, "ue4_ssao")
