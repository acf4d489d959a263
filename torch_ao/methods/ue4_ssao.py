"""UE4's normal-less screen-space AO ("wedge" pairs), seed 004 / ``PostProcessAmbientOcclusion.usf``.

Per direction ``i`` (a slice) and step ``j`` the shader reads a symmetric pair of samples at screen
offsets ``+o`` and ``-o`` (the core's two sides of one slice at the same step), with view-space offsets
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

The halo weight ``Weight`` is what the seed calls the halo fix; the per-side ``WeightLeft/Right``
(``1 - |D| / halo``) of the seed are dead code in the shipped shader (``OPTIMIZATION_O1``) and are not
used. Improvements (named options, off by default): ``accurate_angle=True`` uses ``acos(cos)/pi``;
``flat_softness > 0`` replaces the hard flat-surface test by a logistic blend of that width (so depth
gets a gradient through it).

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
import torch.nn.functional as F

from ..gbuffer import GBuffer
from ..marching import SlicePattern, tangent_from_screen_angle
from .base import AOOutput, ScreenSpaceAO, make_parameter
from .gtao import check_choice, run_functional, with_base_signature, safe_pow

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
        unit = F.normalize(geom.pixels_per_unit, dim=-1, eps=1e-12) * side
        r_px = self.radius_px(geom) * length
        return [((j + 1) / self.steps * r_px)[:, None] * unit for j in range(self.steps)]


class WedgeAccumulator:
    def __init__(self, module: "UE4SSAO") -> None:
        self.m = module

    def begin_slice(self, q, geom):
        zero = torch.zeros_like(q.depth)
        return {"pos": {}, "x": zero, "y": zero}

    def step(self, state, q, geom, sample):
        if sample.side == 1:  # keep the +o sample until its -o partner arrives
            state["pos"][sample.step] = (sample.delta, sample.position, sample.valid)
            return state
        m = self.m
        dtype = q.depth.dtype
        dl, pl, vl = state["pos"].pop(sample.step)
        dr, pr, vr = sample.delta, sample.position, sample.valid
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


@with_base_signature
class UE4SSAO(ScreenSpaceAO):
    """UE4's normal-less SSAO (seed 004); see the module docstring for the exact formula.

    Args:
        radius: world-space sampling radius (parameter; UE4 ``AmbientOcclusionRadius``).
        fade_distance: ``D`` of the halo weight (parameter; UE4 ``AmbientOcclusionDistance``, 80 cm for
            a 200 cm radius, hence the default 0.4).
        flat_surface_bias: the flat-surface bias in world units (parameter; UE4 hard-codes 5 cm for a
            200 cm radius, hence the default 0.025).
        final_power, intensity: UE4's final ``1 - (1 - AO^final_power) * intensity`` (parameters; UE4's editor
            defaults are 2 and 0.5, these default to 1 and 1 so the output is the raw visibility).
        sample_set: ``"ue4_3"`` (default), ``"ue4_6"`` or ``"uniform"`` (``slices`` evenly spaced). With a
            UE4 set, ``slices`` is the set's size (3 or 6) whatever ``slices``/``preset`` say.
        accurate_angle: ``acos(cos)/pi`` instead of UE4's linear approximation with contrast 0.9.
        flat_softness: > 0 makes the flat-surface test a logistic blend of this width (world units).
        steps: pairs per direction (UE4 ``SAMPLE_STEPS``: 1-3). fetch/border/azimuth default
            nearest / clamp / screen.
    """

    default_slices_steps = (3, 3)
    unused_base_arguments = ("step_power", "min_step_px")

    def __init__(self, *, radius: float = 1.0, fade_distance: float = 0.4, flat_surface_bias: float = 0.025,
                 final_power: float = 1.0, intensity: float = 1.0, sample_set: str = "ue4_3", accurate_angle: bool = False,
                 flat_softness: float = 0.0, fetch: str = "nearest", border: str = "clamp", azimuth: str = "screen",
                 trainable: bool = True, **kwargs) -> None:
        self.sample_set = check_choice("sample_set", sample_set, ("ue4_3", "ue4_6", "uniform"))
        self.accurate_angle = bool(accurate_angle)
        if not (isinstance(flat_softness, (int, float)) and flat_softness >= 0):
            raise ValueError(f"flat_softness: expected a number >= 0, got {flat_softness!r}")
        self.flat_softness = float(flat_softness)
        for name in self.unused_base_arguments:
            if name in kwargs:
                raise ValueError(f"{name}: not used by UE4 SSAO (steps are at (j + 1) / steps of each offset)")
        if azimuth != "screen":
            raise ValueError(f"azimuth: UE4 SSAO rotates screen-space offsets; expected 'screen', got {azimuth!r}")
        super().__init__(radius=radius, fetch=fetch, border=border, azimuth=azimuth, trainable=trainable, **kwargs)
        make_parameter(self, "fade_distance", fade_distance, trainable=trainable, minimum=0.0)
        make_parameter(self, "flat_surface_bias", flat_surface_bias, trainable=trainable)
        make_parameter(self, "final_power", final_power, trainable=trainable, minimum=0.0)
        make_parameter(self, "intensity", intensity, trainable=trainable, minimum=0.0)
        for name in ("fade_distance", "flat_surface_bias", "final_power", "intensity"):
            if getattr(self, name).dim() != 0:
                raise ValueError(f"{name}: expected a scalar, got shape {tuple(getattr(self, name).shape)}")
        if not float(self.fade_distance.detach()) > 0:
            raise ValueError("fade_distance: expected > 0")
        if not float(self.final_power.detach()) > 0:
            raise ValueError("final_power: expected > 0")
        if self.sample_set != "uniform":
            self.slices = len(SAMPLE_SETS[self.sample_set])

    def pattern_for(self, frame):
        offsets = SAMPLE_SETS.get(getattr(self, "sample_set", "uniform"))
        return WedgePattern(self.slices, self.steps, self.radius, offsets=offsets, jitter=self.jitter, seed=self.seed,
                            fetch=self.fetch, border=self.border, azimuth="screen")

    def accumulator(self, frame):
        return WedgeAccumulator(self)

    def extra_repr(self) -> str:
        return f"sample_set={self.sample_set!r}, " + super().extra_repr()


def ue4_ssao(gbuffer: GBuffer, *, radius=1.0, fade_distance=0.4, flat_surface_bias=0.025, final_power=1.0,
             intensity=1.0, **options) -> AOOutput:
    """Functional :class:`UE4SSAO`: float arguments may be tensors (gradients flow to them)."""
    return run_functional(UE4SSAO, gbuffer, dict(radius=radius, fade_distance=fade_distance,
                                                 flat_surface_bias=flat_surface_bias, final_power=final_power,
                                                 intensity=intensity), **options)
