"""Ground-truth ambient occlusion (GTAO, Jimenez et al. 2016) on the shared slice-marching core.

Three variants share one accumulator (per slice: a horizon per side, clamped to the hemisphere around
the projected normal, then the cosine-weighted arc integral):

``variant="exact"`` (default, the clean one)
    Horizons are in-plane angles from ``atan2`` (the core's :meth:`Sample.angle`), slices are uniform
    around the view vector (``azimuth="view"``), exact trigonometry. A sample occludes when its 3D
    distance is below ``radius``; ``falloff_range`` > 0 replaces that hard cut by a linear ramp over the last
    ``falloff_range * radius`` (XeGTAO style: the sample's angle is blended toward the hemisphere boundary).
    With ``falloff_range=0`` and dense sampling this converges to ray-traced cosine-weighted AO with maximum
    distance ``radius`` wherever the occluders are on screen and inside the walk (``search_scale``).
``variant="hdrp"`` (Unity HDRP's ``GTAO.compute``, as the bitmask blog ports it)
    3D horizon cosines ``dot(delta, V) / |delta|``, HDRP's ``UpdateHorizon`` falloff
    (``cand > max ? lerp(max, cand, saturate(1 - d^2/R^2)) : max``), ``GTAOFastAcos``, horizons clamped
    with ``N + max(h - N, -pi/2)`` / ``N + min(h - N, pi/2)``, ``IntegrateArcCosWeighted``, an
    ``AnyIsNaN -> 1`` guard (a slice whose projected normal vanishes), steps at
    ``(j + 1 + offset) * R_px / (steps + 1)`` with ``R_px`` clamped to ``[steps, max_radius_px]``,
    nearest fetch, border clamp, slices evenly spaced in screen angle.
``variant="ue4"`` (UE4's ``PostProcessAmbientOcclusion.usf``, as the HBAO/UE4 article gives it)
    ``SearchForLargestAngleDual``: ``Ang = dot(delta, V) * rsqrt(|delta|^2 + 1e-4)``,
    ``Ang = lerp(Ang, Best, saturate(|delta|^2 * 2 / R^2))``, thickness heuristic
    ``Best = Ang > Best ? Ang : lerp(Ang, Best, thickness_heuristic)``, ``acosFast``; UE4's
    ``ComputeInnerIntegral`` (``Gamma = acosFast(cos) - pi/2``, ``SinGamma = 2 cos``, ``|n_p| + 1e-6``);
    steps at ``max(R_px / (steps + 1) * (j + offset), j + 1)`` pixels.

Normalisation (``normalize``):

* ``"exact"``: per-slice integrals divided by the integral the same slices give with no occluder,
  ``sum_s |n_p| a(h1, h2) / sum_s |n_p| a(gamma - pi/2, gamma + pi/2)``. An unoccluded plane gives exactly
  1 with any slice count; since ``(1/pi) int |n_p| (cos g + g sin g) dphi = 1`` for slices uniform
  around V, it converges to the same limit as ``"none"``.
* ``"none"``: the mean of the per-slice integrals, as the shaders compute it (1 on an unoccluded plane
  only in the limit of many slices, and only with ``azimuth="view"``).
* ``"ue4"``: ``"none"`` times ``2/pi``, as UE4's ``GTAOCombinedPSandCS`` does (a plane facing the camera
  gives ``2/pi``).

Then, in this order: ``visibility ** final_power`` (XeGTAO's final power), Jimenez's multi-bounce fit with
``albedo`` when ``multibounce=True``, clamp to [0, 1] (only ``"none"``/multi-bounce can leave it, by
at most float noise for ``"none"`` with HDRP's ``saturate`` and ~1e-4 for the fit).

Bent normals (``bent_normals=True``, computed only then) are the normalised cosine-weighted mean
visible direction: per slice ``|n_p| int_{h1}^{h2} (cos t V + sin t T) cos(t - gamma) |sin t| dt``
in closed form, summed over slices.
"""
from __future__ import annotations

import abc

import math

import torch
import torch.nn.functional as F

from ..checks import check_choice, scalar_value
from ..ops import UE4_EPSILON, arc_integral, fast_acos, safe_pow
from ..options import Option
from ..walk import Frame, SliceAccumulator, SlicePattern, radius_px, step_direction
from .base import ScreenSpaceAO
from .common import RADIUS, Sampling, declare_signature, functional_twin, register_parameters

__all__ = ["GTAO", "gtao", "ShaderStepPattern", "ExactGTAOAccumulator", "HDRPGTAOAccumulator", "UE4GTAOAccumulator",
           "arc_integral", "bent_vector", "multibounce"]

HALF_PI = 0.5 * math.pi
VARIANTS = ("exact", "hdrp", "ue4")
NORMALIZE = ("exact", "none", "ue4")


def bent_vector(h1: torch.Tensor, h2: torch.Tensor, n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Components ``(N,)`` along V and T of ``int_{h1}^{h2} (cos t, sin t) cos(t - n) |sin t| dt``."""
    cn, sn = torch.cos(n), torch.sin(n)

    def fc(t):  # antiderivative of cos t sin t cos(t - n)
        return (-torch.cos(t) ** 3 * cn + torch.sin(t) ** 3 * sn) / 3

    def fs(t):  # antiderivative of sin^2 t cos(t - n)
        return torch.sin(t) ** 3 * cn / 3 + sn * (torch.cos(t) ** 3 / 3 - torch.cos(t))

    along_v = fc(h2) + fc(h1) + 2 * cn / 3  # - 2 fc(0)
    along_t = fs(h2) + fs(h1) + 4 * sn / 3  # - 2 fs(0)
    return along_v, along_t


def multibounce(visibility: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """Jimenez et al.'s multi-bounce fit ``max(x, ((a x + b) x + c) x)`` ``(...)``."""
    a = 2.0404 * albedo - 0.3324
    b = -4.7951 * albedo + 0.6417
    c = 2.7552 * albedo + 0.6903
    x = visibility
    return torch.maximum(x, ((x * a + b) * x + c) * x)


class ShaderStepPattern(SlicePattern):
    """:class:`SlicePattern` with the step placement of the HDRP or UE4 GTAO shaders.

    ``R_px`` (the radius in pixels) is clamped to ``[steps, max_radius_px]``, ``dt = R_px / (steps + 1)``,
    ``xi`` is the per-pixel offset in [0, 1) (0.5 without jitter), and step ``j`` lies at
    ``(j + 1 + xi) * dt`` (HDRP ``HorizonLoop``) or ``max((j + xi) * dt, j + 1)`` (UE4
    ``SearchForLargestAngleDual``) pixels. ``step_power`` is ignored.
    """

    def __init__(self, *args, shader: str = "hdrp", **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.shader = check_choice("shader", shader, ("hdrp", "ue4"))

    def step_offsets(self, q, geom, side):
        xi = self.step_noise(q, geom, side)
        unit = step_direction(geom, side)
        r_px = radius_px(self.radius, geom).clamp_min(float(self.steps))
        if self.max_radius_px is not None:
            r_px = r_px.clamp_max(max(float(self.max_radius_px), float(self.steps)))
        dt = r_px / (self.steps + 1)
        out = []
        for j in range(self.steps):
            t = (j + 1 + xi) * dt if self.shader == "hdrp" else torch.clamp_min((j + xi) * dt, float(j + 1))
            out.append(t[:, None] * unit)
        return out


# ---------------------------------------------------------------------------------------------
# The accumulators: one per published variant, sharing the slice integral and the normalisation
# ---------------------------------------------------------------------------------------------
class GTAOAccumulator(SliceAccumulator):
    """Per slice: a horizon per side (the variant's :meth:`step`), then the clamped arc integral.

    A variant gives :meth:`begin_slice`, :meth:`step` and :meth:`angles` (its horizons and projected
    normal in the integral's convention); the clamp, the integral, the bent normal and the
    normalisation (see the module docstring) are common.
    """

    def __init__(self, module: "GTAO", frame: Frame) -> None:
        self.m = module
        self.radius = module.radius.to(frame.dtype)

    @abc.abstractmethod
    def angles(self, state, geom):
        """``(h1, h2, n, cos n, sin n, weight, degenerate)`` ``(N,)`` each (``degenerate`` may be ``None``):
        the horizons ``h1 <= 0 <= h2``, the projected normal's angle and the slice's weight."""

    def end_slice(self, state, q, geom):
        h1, h2, n, cos_n, sin_n, weight, degenerate = self.angles(state, geom)
        lo, hi = n - HALF_PI, n + HALF_PI
        h1 = torch.maximum(h1, lo)  # n + max(h1 - n, -pi/2)
        h2 = torch.minimum(h2, hi)  # n + min(h2 - n, pi/2)
        integral = weight * arc_integral(h1, h2, n, cos_n, sin_n)
        free = weight * arc_integral(lo, hi, n, cos_n, sin_n)
        if degenerate is not None:  # HDRP's AnyIsNaN(...) ? 1
            integral = torch.where(degenerate, torch.ones_like(integral), integral)
            free = torch.where(degenerate, torch.ones_like(free), free)
        out = {"vis": integral[:, None], "free": free[:, None]}
        if self.m.bent_normals:
            bv, bt = bent_vector(h1, h2, n)
            out["bent"] = geom.normal_length[:, None] * (bv[:, None] * q.view + bt[:, None] * geom.tangent)
        return out

    def finish(self, sums, q, num_slices):
        m = self.m
        if m.normalize == "exact":
            vis = sums["vis"] / sums["free"].clamp_min(1e-12)
        else:
            vis = sums["vis"] / num_slices
            if m.normalize == "ue4":
                vis = vis * (2.0 / math.pi)
        vis = vis.clamp(0.0, 1.0)
        vis = safe_pow(vis, m.final_power.to(vis.dtype))
        if m.multibounce:
            vis = multibounce(vis, m.albedo.to(vis.dtype))
        out = {"visibility": vis.clamp(0.0, 1.0)}
        if m.bent_normals:
            out["bent_normal"] = F.normalize(sums["bent"], dim=-1, eps=1e-12)
        return out


class ExactGTAOAccumulator(GTAOAccumulator):
    """``variant="exact"``: in-plane horizon angles from ``atan2``, a hard cut or XeGTAO's linear falloff."""

    def __init__(self, module: "GTAO", frame: Frame) -> None:
        super().__init__(module, frame)
        self.falloff = module.falloff_range.to(frame.dtype)

    def begin_slice(self, q, geom):
        # Smallest angle from V per side, starting at the hemisphere boundary pi/2 + s*gamma.
        g = geom.normal_angle
        return {1: HALF_PI + g, -1: HALF_PI - g}

    def step(self, state, q, geom, sample):
        s = sample.side
        bound = HALF_PI + s * geom.normal_angle
        theta = sample.angle().clamp(0.0, math.pi)
        R = self.radius
        # a linear ramp over falloff x R, or the hard cut at falloff 0 (chosen by a tensor, not .item(): no
        # graph break under torch.compile)
        ramp = ((R - sample.distance) / (self.falloff * R).clamp_min(1e-12)).clamp(0.0, 1.0)
        w = torch.where(self.falloff.detach() > 0, ramp, (sample.distance < R).to(theta.dtype))
        w = torch.where(sample.valid, w, torch.zeros_like(w))
        state[s] = torch.minimum(state[s], bound + w * (theta - bound))
        return state

    def angles(self, state, geom):
        n = geom.normal_angle
        return -state[-1], state[1], n, torch.cos(n), torch.sin(n), geom.normal_length, None


class _ShaderGTAOAccumulator(GTAOAccumulator):
    """The shaders keep the largest horizon cosine per side, starting at ``cos(pi) = -1``."""

    def begin_slice(self, q, geom):
        minus_one = torch.full_like(q.depth, -1.0)
        return {1: minus_one, -1: minus_one}

    @staticmethod
    def horizons(state) -> tuple[torch.Tensor, torch.Tensor]:
        """``(h1, h2)``: the horizon cosines through ``fast_acos``, signed per side."""
        return -fast_acos(state[-1].clamp(-1.0, 1.0)), fast_acos(state[1].clamp(-1.0, 1.0))


class HDRPGTAOAccumulator(_ShaderGTAOAccumulator):
    """``variant="hdrp"``: HDRP's ``UpdateHorizon`` falloff, ``GTAOFastAcos``, the ``AnyIsNaN`` guard."""

    def step(self, state, q, geom, sample):
        best = state[sample.side]
        cand = sample.cos_view()
        falloff = (1.0 - sample.distance.square() / self.radius.square()).clamp(0.0, 1.0)
        upd = torch.where(cand > best, best + falloff * (cand - best), best)
        state[sample.side] = torch.where(sample.valid, upd, best)
        return state

    def angles(self, state, geom):
        L, g = geom.normal_length, geom.normal_angle
        safe_L = L.clamp_min(1e-12)
        nT, nV = L * torch.sin(g) / safe_L, L * torch.cos(g) / safe_L
        cos_n = nV.clamp(-1.0, 1.0)
        n = torch.sign(nT) * fast_acos(cos_n)
        h1, h2 = self.horizons(state)
        weight = L if self.m.projected_normal_weight else torch.ones_like(L)
        return h1, h2, n, cos_n, torch.sin(n), weight, L < 1e-6


class UE4GTAOAccumulator(_ShaderGTAOAccumulator):
    """``variant="ue4"``: ``SearchForLargestAngleDual`` with its thickness heuristic, ``ComputeInnerIntegral``."""

    def __init__(self, module: "GTAO", frame: Frame) -> None:
        super().__init__(module, frame)
        self.thickness = module.thickness_heuristic.to(frame.dtype)

    def step(self, state, q, geom, sample):
        best = state[sample.side]
        len_sq = sample.delta.square().sum(-1)
        ang = sample.along_view * torch.rsqrt(len_sq + UE4_EPSILON)
        falloff = (len_sq * (2.0 / self.radius.square())).clamp(0.0, 1.0)
        ang = ang + falloff * (best - ang)
        upd = torch.where(ang > best, ang, ang + self.thickness * (best - ang))
        state[sample.side] = torch.where(sample.valid, upd, best)
        return state

    def angles(self, state, geom):
        # ComputeInnerIntegral with its own normalisation of n_p (|n_p| + 1e-6)
        L, g = geom.normal_length, geom.normal_angle
        Lp = L + 1e-6
        cos_ang = L * torch.sin(g) / Lp
        n = HALF_PI - fast_acos(cos_ang.clamp(-1.0, 1.0))
        h1, h2 = self.horizons(state)
        return h1, h2, n, L * torch.cos(g) / Lp, cos_ang, Lp, None  # UE4: SinGamma = 2 CosAng (the 2 is in the integral)


ACCUMULATORS = {"exact": ExactGTAOAccumulator, "hdrp": HDRPGTAOAccumulator, "ue4": UE4GTAOAccumulator}


# ---------------------------------------------------------------------------------------------
# The module
# ---------------------------------------------------------------------------------------------
_VARIANT_DEFAULTS = {
    # fetch, border, azimuth, normalize
    "exact": ("bilinear", "drop", "view", "exact"),
    "hdrp": ("nearest", "clamp", "screen", "none"),
    "ue4": ("nearest", "clamp", "screen", "ue4"),
}


@declare_signature
class GTAO(ScreenSpaceAO):
    """Ground-truth ambient occlusion; see the module docstring for the variants and :meth:`options`
    for every argument. Parameters a variant does not use (``falloff_range`` outside ``"exact"``,
    ``thickness_heuristic`` outside ``"ue4"``, ``albedo`` without ``multibounce``) are kept as frozen
    buffers, so ``parameters()`` lists exactly what shapes the result; so is ``falloff_range`` at 0 (a
    hard cut, which has no gradient): give it a value > 0 to fit it."""

    OPTIONS = (
        Option("variant", "exact", "exact: in-plane angles, exact trigonometry; hdrp: Unity HDRP's shader; "
               "ue4: UE4's shader", kind=str, choices=VARIANTS),
        RADIUS,
        Option("falloff_range", 0.0, "exact only: fraction of radius over which occluders fade out linearly "
               "(0: a hard cut, which converges to ray-traced AO; XeGTAO uses 0.615)", minimum=0.0, maximum=1.0,
               fitted=True),
        Option("thickness_heuristic", 1.0, "ue4 only: UE4's thickness blend (1: plain maximum; "
               "r.GTAO.ThicknessBlend)", minimum=0.0, maximum=1.0, fitted=True),
        Option("final_power", 1.0, "Power applied to the visibility (XeGTAO's final power)", minimum=0.0,
               open_minimum=True, fitted=True),
        Option("multibounce", False, "Apply Jimenez's multi-bounce fit with albedo", kind=bool),
        Option("albedo", 0.5, "Surface albedo of the multi-bounce fit", minimum=0.0, maximum=1.0, fitted=True),
        Option("bent_normals", False, "Also output bent normals (cosine-weighted mean visible direction)", kind=bool),
        Option("normalize", None, "exact: divide by the unoccluded integral of the same slices (a plane gives 1); "
               "none: the shaders' mean; ue4: none times 2/pi (default per variant: exact/none/ue4)", kind=str,
               choices=NORMALIZE),
        Option("projected_normal_weight", True, "hdrp only: weight each slice by |n_p| (the paper; HDRP ships "
               "with it off: pass False to match)", kind=bool),
        Option("max_radius_px", None, "Clamp of the radius on screen (HDRP's _AOMaxRadiusInPixels, UE4 256; "
               "default none)", unit="pixels", minimum=0.0, open_minimum=True),
        Option("search_scale", 1.0, "exact only: walk search_scale x radius on screen while occluders count within "
               "radius in 3D (exact convergence needs >= depth(pixel) / depth(occluder))", minimum=1.0),
    )
    SAMPLING = Sampling.options_for(fetch=None, border=None, azimuth=None)
    has_kernel = "gtao"  # forward and backward in torch_ao.kernels (gtao_covers says which calls)

    @classmethod
    def parse_options(cls, options):
        values = super().parse_options(options)
        for key, default in zip(("fetch", "border", "azimuth", "normalize"), _VARIANT_DEFAULTS[values["variant"]]):
            if values[key] is None:
                values[key] = default
        return values

    def __init__(self, **options) -> None:
        super().__init__(**options)
        v = self.values
        self.variant, self.normalize = v["variant"], v["normalize"]
        self.multibounce, self.bent_normals = v["multibounce"], v["bent_normals"]
        self.projected_normal_weight, self.max_radius_px = v["projected_normal_weight"], v["max_radius_px"]
        self.search_scale = float(v["search_scale"])
        frozen = set(self.no_gradient_options) | ({"falloff_range"} if self.variant != "exact" else set())
        frozen |= {"thickness_heuristic"} if self.variant != "ue4" else set()
        frozen |= {"albedo"} if not self.multibounce else set()
        register_parameters(self, self.options(), v, ("falloff_range", "thickness_heuristic", "final_power", "albedo"),
                            trainable=self.trainable, frozen=frozen)

    def no_gradient(self, values):
        # (a falloff_range that is not a number is refused by name when it is registered)
        if values["variant"] == "exact" and scalar_value(values["falloff_range"]) == 0:
            return {"falloff_range": "falloff_range 0 (a hard cut) has no gradient: give it a value > 0 to fit it"}
        return {}

    def pattern_for(self, frame):
        if self.variant == "exact":
            return self.sampling.pattern(self.radius * self.search_scale, max_radius_px=self.max_radius_px)
        return self.sampling.pattern(self.radius, ShaderStepPattern, shader=self.variant, max_radius_px=self.max_radius_px)

    def accumulator(self, frame):
        return ACCUMULATORS[self.variant](self, frame)

    def extra_repr(self) -> str:
        return f"variant={self.variant!r}, normalize={self.normalize!r}, " + super().extra_repr()


gtao = functional_twin(GTAO, "gtao")
