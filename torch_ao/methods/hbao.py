"""Horizon-based ambient occlusion (HBAO, Bavoil & Sainz 2008) as the HBAO/UE4 article describes it.

``N`` screen directions over the full circle (``slices``, one side each, rotated per pixel by
interleaved gradient noise) with ``steps`` jittered samples each. Per direction, with ``t`` the
elevation of the surface tangent along the direction plus ``angle_bias`` and ``h`` the horizon
elevation of the samples within ``radius``::

    AO = 1 - (1/N) sum_directions  W(r) (sin h - sin t)          (the HBAO/UE4 article)

Weights ``W(r) = max(0, 1 - r/R)`` (``falloff="linear"``) or ``max(0, 1 - r^2/R^2)``
(``falloff="quadratic"``), ``r`` the 3D distance of the horizon sample. How the sum is formed
(``accumulate``):

* ``"incremental"`` (default, the original HBAO's per-step form): starting at ``sin t``, each sample
  within ``R`` that rises above the running horizon adds ``W(r_i) (sin h_i - sin h_{i-1})`` and becomes
  the new horizon. Without falloff this telescopes to ``sin h - sin t``.
* ``"max"`` (the article's literal reading): the highest sample only, ``W(r*) (sin h* - sin t)``.

Elevations (``elevation``): ``"image"`` (default, the article's ``tan = z / sqrt(x^2 + y^2)``: the angle
above the view-space image plane, 3D) or ``"view"`` (in the slice plane, from the plane orthogonal
to the view vector: rotation-invariant around V). The tangent comes from the normals (the G-buffer's,
or those reconstructed from depth with the PSSAO gist's smaller-discontinuity rule, which is the
article's ``minDis`` choice). The angle bias is added to the tangent *angle* (``t + angle_bias``, capped at
``pi/2``); the original NVIDIA sample adds ``tan(bias)`` to ``tan t``, which differs at steep tangents.

Per direction ``sin h - sin t`` can exceed 1 on tilted surfaces (up to ``1 + sin |t|``), so the
visibility is clamped to [0, 1]. Directions are evenly spaced in screen angle (``azimuth="screen"``)
as in the article. The article does not fix the depth fetch; the default is bilinear with border drop,
because a nearest fetch puts the 1-pixel first step up to ~27 degrees off the direction, and on a
plane tilted 70 degrees that alone darkens it to ~0.81 (``fetch="nearest", border="clamp"`` is
available).
"""
from __future__ import annotations

import math

import torch

from ..options import Option
from ..walk import SliceAccumulator
from .base import ScreenSpaceAO
from .common import RADIUS, Sampling, declare_signature, functional_twin, register_parameters

__all__ = ["HBAO", "hbao"]

HALF_PI = 0.5 * math.pi


class HBAOAccumulator(SliceAccumulator):
    """Per direction: the running horizon ``sin h`` above the tangent ``sin t`` and its weighted rise."""

    def __init__(self, module: "HBAO") -> None:
        self.m = module
    def begin_slice(self, q, geom):
        m = self.m
        bias = m.angle_bias.to(q.depth.dtype)
        if m.elevation == "view":
            t = -geom.normal_angle  # the hemisphere boundary on side +1 sits at angle pi/2 + gamma from V
        else:
            theta_b = HALF_PI + geom.normal_angle
            tangent = torch.cos(theta_b)[:, None] * q.view + torch.sin(theta_b)[:, None] * geom.tangent
            t = torch.asin(tangent[:, 2].clamp(-1 + 1e-7, 1 - 1e-7))
        sin_t = torch.sin(torch.clamp(t + bias, max=HALF_PI))
        zero = torch.zeros_like(sin_t)
        return {"sin_t": sin_t, "sin_h": sin_t, "ao": zero, "w": zero}

    def step(self, state, q, geom, sample):
        m = self.m
        R = m.radius.to(sample.distance.dtype)
        if m.elevation == "view":
            sin_s = torch.cos(sample.angle())
        else:
            sin_s = sample.delta[:, 2] / sample.distance.clamp_min(1e-30)
        r = sample.distance / R.clamp_min(1e-30)
        w = (1 - r) if m.falloff == "linear" else (1 - r.square())
        w = w.clamp_min(0.0)
        rise = sample.valid & (r < 1) & (sin_s > state["sin_h"])
        if m.accumulate == "incremental":
            state["ao"] = torch.where(rise, state["ao"] + w * (sin_s - state["sin_h"]), state["ao"])
        else:
            state["w"] = torch.where(rise, w, state["w"])
        state["sin_h"] = torch.where(rise, sin_s, state["sin_h"])
        return state

    def end_slice(self, state, q, geom):
        if self.m.accumulate == "incremental":
            ao = state["ao"]
        else:
            ao = state["w"] * (state["sin_h"] - state["sin_t"])
        return {"ao": ao[:, None]}

    def finish(self, sums, q, num_slices):
        return {"visibility": (1 - sums["ao"] / num_slices).clamp(0.0, 1.0)}


@declare_signature
class HBAO(ScreenSpaceAO):
    """Horizon-based AO (the HBAO/UE4 article); see the module docstring and :meth:`options`.
    ``slices`` are directions over the full circle, ``steps`` samples per direction."""

    OPTIONS = (
        RADIUS,
        Option("angle_bias", math.radians(10.0), "Added to the tangent angle so that flat surfaces do not "
               "self-occlude (default 10 degrees)", unit="radians", minimum=0.0, maximum=HALF_PI,
               open_maximum=True, fitted=True),
        Option("falloff", "linear", "Weight of a horizon sample at distance r: linear 1 - r/R or quadratic "
               "1 - r^2/R^2", kind=str, choices=("linear", "quadratic")),
        Option("accumulate", "incremental", "incremental: each rise of the horizon weighted at its own distance "
               "(the original HBAO); max: the highest sample only", kind=str, choices=("incremental", "max")),
        Option("elevation", "image", "image: elevation above the view-space image plane (the article); view: "
               "in the slice plane, rotation-invariant around V", kind=str, choices=("image", "view")),
    )
    # (directions over the full circle: no projected-normal slice density, which covers a half circle)
    SAMPLING = Sampling.options_for(tuple(o.name for o in Sampling.OPTIONS if o.name != "slice_sampling"),
                                    azimuth="screen")
    has_kernel = "hbao"  # forward and backward in torch_ao.kernels (hbao_covers says which calls)

    def __init__(self, **options) -> None:
        super().__init__(**options)
        v = self.values
        self.falloff, self.accumulate, self.elevation = v["falloff"], v["accumulate"], v["elevation"]
        register_parameters(self, self.options(), v, ("angle_bias",), trainable=self.trainable)

    def pattern_for(self, frame):
        return self.sampling.pattern(self.radius, full_circle=True)

    def accumulator(self, frame):
        return HBAOAccumulator(self)

    def extra_repr(self) -> str:
        return f"falloff={self.falloff!r}, accumulate={self.accumulate!r}, elevation={self.elevation!r}, " + super().extra_repr()


hbao = functional_twin(HBAO, "hbao")
