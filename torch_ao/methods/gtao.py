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
``variant="hdrp"`` (seed 000, Unity HDRP ``GTAO.compute``)
    3D horizon cosines ``dot(delta, V) / |delta|``, HDRP's ``UpdateHorizon`` falloff
    (``cand > max ? lerp(max, cand, saturate(1 - d^2/R^2)) : max``), ``GTAOFastAcos``, horizons clamped
    with ``N + max(h - N, -pi/2)`` / ``N + min(h - N, pi/2)``, ``IntegrateArcCosWeighted``, an
    ``AnyIsNaN -> 1`` guard (a slice whose projected normal vanishes), steps at
    ``(j + 1 + offset) * R_px / (steps + 1)`` with ``R_px`` clamped to ``[steps, max_radius_px]``,
    nearest fetch, border clamp, slices evenly spaced in screen angle.
``variant="ue4"`` (seed 004, UE4 ``PostProcessAmbientOcclusion.usf``)
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

import math

import torch
import torch.nn.functional as F

from ..gbuffer import GBuffer
from ..marching import Frame, SlicePattern
from .base import AOOutput, ScreenSpaceAO, make_parameter

__all__ = ["GTAO", "gtao", "ShaderStepPattern", "arc_integral", "bent_vector", "multibounce", "run_functional",
           "with_base_signature"]

HALF_PI = 0.5 * math.pi
VARIANTS = ("exact", "hdrp", "ue4")
NORMALIZE = ("exact", "none", "ue4")


# ---------------------------------------------------------------------------------------------
# Small shared pieces (also used by the other horizon methods)
# ---------------------------------------------------------------------------------------------
def check_choice(name: str, value, choices) -> str:
    if value not in choices:
        raise ValueError(f"{name}: expected one of {tuple(choices)}, got {value!r}")
    return value


def with_base_signature(cls):
    """Class decorator: ``inspect.signature(cls.__init__)`` lists the subclass's own keyword arguments
    and then those of :class:`ScreenSpaceAO` that it forwards through ``**kwargs`` (the CLI builds
    modules from that signature), except the names in ``cls.unused_base_arguments``."""
    import inspect

    skip = set(getattr(cls, "unused_base_arguments", ()))
    own = inspect.signature(cls.__init__)
    params = [p for p in own.parameters.values() if p.kind != p.VAR_KEYWORD]
    names = {p.name for p in params}
    for p in inspect.signature(ScreenSpaceAO.__init__).parameters.values():
        if p.name not in names and p.name not in skip and p.kind == p.KEYWORD_ONLY:
            params.append(p)
            names.add(p.name)
    cls.__init__.__signature__ = own.replace(parameters=params)
    return cls


def run_functional(cls, gbuffer: GBuffer, tensors: dict, **options) -> AOOutput:
    """Run module ``cls`` once with float parameters taken from ``tensors`` *as given* (not copied),
    so gradients flow to tensors the caller passes in. Used by the functional twins."""
    init = {k: (v.detach() if isinstance(v, torch.Tensor) else v) for k, v in tensors.items()}
    module = cls(trainable=False, **init, **options)
    for name, value in tensors.items():
        if isinstance(value, torch.Tensor):
            if value.dim() != 0:
                raise ValueError(f"{name}: expected a scalar, got shape {tuple(value.shape)}")
            module._buffers[name] = value
    return module(gbuffer)


def arc_integral(h1: torch.Tensor, h2: torch.Tensor, n: torch.Tensor, cos_n: torch.Tensor,
                 sin_n: torch.Tensor) -> torch.Tensor:
    """``int_{h1}^{h2} cos(t - n) |sin t| dt`` for ``h1 <= 0 <= h2`` (HDRP's ``IntegrateArcCosWeighted``
    with its ``cos n``, ``sin n`` passed in)."""
    return 0.25 * ((-torch.cos(2 * h1 - n) + cos_n + 2 * h1 * sin_n) + (-torch.cos(2 * h2 - n) + cos_n + 2 * h2 * sin_n))


def bent_vector(h1: torch.Tensor, h2: torch.Tensor, n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Components along V and T of ``int_{h1}^{h2} (cos t, sin t) cos(t - n) |sin t| dt``."""
    cn, sn = torch.cos(n), torch.sin(n)

    def fc(t):  # antiderivative of cos t sin t cos(t - n)
        return (-torch.cos(t) ** 3 * cn + torch.sin(t) ** 3 * sn) / 3

    def fs(t):  # antiderivative of sin^2 t cos(t - n)
        return torch.sin(t) ** 3 * cn / 3 + sn * (torch.cos(t) ** 3 / 3 - torch.cos(t))

    along_v = fc(h2) + fc(h1) + 2 * cn / 3  # - 2 fc(0)
    along_t = fs(h2) + fs(h1) + 4 * sn / 3  # - 2 fs(0)
    return along_v, along_t


def multibounce(visibility: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """Jimenez et al.'s multi-bounce fit ``max(x, ((a x + b) x + c) x)``."""
    a = 2.0404 * albedo - 0.3324
    b = -4.7951 * albedo + 0.6417
    c = 2.7552 * albedo + 0.6903
    x = visibility
    return torch.maximum(x, ((x * a + b) * x + c) * x)


def fast_acos(x: torch.Tensor) -> torch.Tensor:
    """HDRP's ``GTAOFastAcos`` / UE4's ``acosFast`` (same values as :func:`torch_ao.marching.fast_acos`),
    with a finite gradient at ``|x| = 1`` (the ``sqrt`` is differentiated as 0 there, not infinity)."""
    ax = x.abs()
    y = (1 - ax).clamp_min(0)
    pos = y > 0
    root = torch.where(pos, torch.sqrt(torch.where(pos, y, torch.ones_like(y))), torch.zeros_like(y))
    res = (-0.156583 * ax + HALF_PI) * root
    return torch.where(x >= 0, res, math.pi - res)


def safe_pow(x: torch.Tensor, power: torch.Tensor) -> torch.Tensor:
    """``x ** power`` for ``x`` in [0, 1] with finite gradients (x is floored at 1e-12)."""
    return x.clamp(1e-12, 1.0) ** power


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
        xi = self._noise(q)[1]
        unit = F.normalize(geom.pixels_per_unit, dim=-1, eps=1e-12) * side
        r = torch.as_tensor(self.radius, dtype=geom.pixels_per_unit.dtype, device=geom.pixels_per_unit.device)
        r_px = (r * geom.pixels_per_unit.norm(dim=-1)).clamp_min(float(self.steps))
        if self.max_radius_px is not None:
            r_px = r_px.clamp_max(max(float(self.max_radius_px), float(self.steps)))
        dt = r_px / (self.steps + 1)
        out = []
        for j in range(self.steps):
            t = (j + 1 + xi) * dt if self.shader == "hdrp" else torch.clamp_min((j + xi) * dt, float(j + 1))
            out.append(t[:, None] * unit)
        return out


# ---------------------------------------------------------------------------------------------
# The accumulator
# ---------------------------------------------------------------------------------------------
class GTAOAccumulator:
    """Per slice: a horizon per side, then the arc integral (see the module docstring)."""

    def __init__(self, module: "GTAO", frame: Frame) -> None:
        self.m = module
        self.variant = module.variant
        dtype = frame.dtype
        self.radius = module.radius.to(dtype)
        self.falloff = module.falloff_range.to(dtype)
        self.thickness = module.thickness_heuristic.to(dtype)

    # --------------------------------------------------------------- per step
    def begin_slice(self, q, geom):
        if self.variant == "exact":
            # Smallest angle from V per side, starting at the hemisphere boundary pi/2 + s*gamma.
            g = geom.normal_angle
            return {1: HALF_PI + g, -1: HALF_PI - g}
        # HDRP and UE4 keep the largest horizon cosine, starting at cos(pi) = -1.
        minus_one = torch.full_like(q.depth, -1.0)
        return {1: minus_one, -1: minus_one}

    def step(self, state, q, geom, sample):
        s = sample.side
        best = state[s]
        if self.variant == "exact":
            bound = HALF_PI + s * geom.normal_angle
            theta = sample.angle().clamp(0.0, math.pi)
            R = self.radius
            if float(self.falloff.detach()) > 0:
                w = ((R - sample.distance) / (self.falloff * R).clamp_min(1e-12)).clamp(0.0, 1.0)
            else:
                w = (sample.distance < R).to(theta.dtype)
            w = torch.where(sample.valid, w, torch.zeros_like(w))
            cand = bound + w * (theta - bound)
            state[s] = torch.minimum(best, cand)
        elif self.variant == "hdrp":
            cand = sample.cos_view()
            falloff = (1.0 - sample.distance.square() / self.radius.square()).clamp(0.0, 1.0)
            upd = torch.where(cand > best, best + falloff * (cand - best), best)
            state[s] = torch.where(sample.valid, upd, best)
        else:  # ue4
            len_sq = sample.delta.square().sum(-1)
            ang = sample.along_view * torch.rsqrt(len_sq + 1e-4)
            falloff = (len_sq * (2.0 / self.radius.square())).clamp(0.0, 1.0)
            ang = ang + falloff * (best - ang)
            upd = torch.where(ang > best, ang, ang + self.thickness * (best - ang))
            state[s] = torch.where(sample.valid, upd, best)
        return state

    # --------------------------------------------------------------- per slice
    def _angles(self, state, geom):
        """(h1, h2, n, cos n, sin n, weight, degenerate) in the integral's convention."""
        L = geom.normal_length
        if self.variant == "exact":
            n = geom.normal_angle
            h1, h2 = -state[-1], state[1]
            return h1, h2, n, torch.cos(n), torch.sin(n), L, None
        proj_t, proj_v = self._proj_components(geom)
        safe_L = L.clamp_min(1e-12)
        nT, nV = proj_t / safe_L, proj_v / safe_L
        if self.variant == "hdrp":
            cos_n = nV.clamp(-1.0, 1.0)
            n = torch.sign(nT) * fast_acos(cos_n)
            sin_n = torch.sin(n)
            h2 = fast_acos(state[1].clamp(-1.0, 1.0))
            h1 = -fast_acos(state[-1].clamp(-1.0, 1.0))
            weight = L if self.m.projected_normal_weight else torch.ones_like(L)
            return h1, h2, n, cos_n, sin_n, weight, L < 1e-6
        # ue4: ComputeInnerIntegral with its own normalisation of n_p (|n_p| + 1e-6)
        Lp = L + 1e-6
        cos_ang = proj_t / Lp
        n = HALF_PI - fast_acos(cos_ang.clamp(-1.0, 1.0))
        cos_n = proj_v / Lp
        sin_n = cos_ang  # UE4: SinGamma = 2 * CosAng (the 2 is in the integral)
        h2 = fast_acos(state[1].clamp(-1.0, 1.0))
        h1 = -fast_acos(state[-1].clamp(-1.0, 1.0))
        return h1, h2, n, cos_n, sin_n, Lp, None

    @staticmethod
    def _proj_components(geom):
        """``(n_p . T, n_p . V)`` from the core's angle and length."""
        L, g = geom.normal_length, geom.normal_angle
        return L * torch.sin(g), L * torch.cos(g)

    def end_slice(self, state, q, geom):
        h1, h2, n, cos_n, sin_n, weight, degenerate = self._angles(state, geom)
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
            bv, bt = bent_vector(h1, h2, geom.normal_angle if self.variant == "exact" else n)
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


# ---------------------------------------------------------------------------------------------
# The module
# ---------------------------------------------------------------------------------------------
_VARIANT_DEFAULTS = {
    # fetch, border, azimuth, normalize
    "exact": ("bilinear", "drop", "view", "exact"),
    "hdrp": ("nearest", "clamp", "screen", "none"),
    "ue4": ("nearest", "clamp", "screen", "ue4"),
}


@with_base_signature
class GTAO(ScreenSpaceAO):
    """Ground-truth ambient occlusion; see the module docstring for the variants.

    Args:
        variant: ``"exact"`` (default), ``"hdrp"`` (seed 000) or ``"ue4"`` (seed 004).
        radius: world-space radius (parameter).
        Parameters a variant does not use (``falloff_range`` outside ``"exact"``, ``thickness_heuristic``
        outside ``"ue4"``, ``albedo`` without ``multibounce``) are kept as frozen buffers.
        falloff_range: ``"exact"`` only: fraction of ``radius`` over which occluders fade out linearly
            (0 = hard cut at ``radius``; XeGTAO uses 0.615). Parameter, in [0, 1].
        thickness_heuristic: ``"ue4"`` only: the thickness-heuristic blend (1 = plain maximum; UE4's
            ``r.GTAO.ThicknessBlend``). Parameter, in [0, 1].
        final_power: final power of the visibility (parameter, > 0).
        multibounce, albedo: apply Jimenez's multi-bounce fit with this albedo (parameter).
        bent_normals: also output bent normals.
        normalize: ``"exact"``, ``"none"`` or ``"ue4"``; default per variant (exact / none / ue4).
        projected_normal_weight: ``"hdrp"`` only: weight each slice by ``|n_p|`` (the paper; HDRP's
            ``WEIGHT_WITH_PROJ_N_LENGTH``). HDRP ships with it off: pass False to match.
        max_radius_px: clamp of the screen radius (HDRP ``_AOMaxRadiusInPixels``, UE4 256).
        search_scale: ``"exact"`` only: the walk covers ``search_scale * radius`` (projected at the
            pixel's depth) while occluders still count only within ``radius`` in 3D. An occluder closer
            to the camera than the pixel projects farther than the pixel's screen radius, so exact
            convergence needs ``search_scale >= depth(pixel) / depth(occluder)``; 1 (default) samples
            like the shaders do.
        fetch, border, azimuth: default per variant (exact: bilinear/drop/view; hdrp and ue4:
            nearest/clamp/screen).
        Other arguments: see :class:`~torch_ao.methods.base.ScreenSpaceAO`.
    """

    def __init__(self, *, variant: str = "exact", radius: float = 1.0, falloff_range: float = 0.0,
                 thickness_heuristic: float = 1.0, final_power: float = 1.0, multibounce: bool = False, albedo: float = 0.5, bent_normals: bool = False,
                 normalize: str | None = None, projected_normal_weight: bool = True,
                 max_radius_px: float | None = None, search_scale: float = 1.0, fetch: str | None = None, border: str | None = None,
                 azimuth: str | None = None, trainable: bool = True, **kwargs) -> None:
        self.variant = check_choice("variant", variant, VARIANTS)
        d_fetch, d_border, d_azimuth, d_norm = _VARIANT_DEFAULTS[variant]
        self.normalize = check_choice("normalize", d_norm if normalize is None else normalize, NORMALIZE)
        self.multibounce, self.bent_normals = bool(multibounce), bool(bent_normals)
        self.projected_normal_weight = bool(projected_normal_weight)
        if max_radius_px is not None and not max_radius_px > 0:
            raise ValueError(f"max_radius_px: expected > 0 or None, got {max_radius_px}")
        self.max_radius_px = max_radius_px
        if not (isinstance(search_scale, (int, float)) and search_scale >= 1.0):
            raise ValueError(f"search_scale: expected a number >= 1, got {search_scale!r}")
        self.search_scale = float(search_scale)
        super().__init__(radius=radius, fetch=d_fetch if fetch is None else fetch,
                         border=d_border if border is None else border,
                         azimuth=d_azimuth if azimuth is None else azimuth, trainable=trainable, **kwargs)
        # Parameters the chosen variant/options do not use are registered frozen (as buffers), so
        # that ``parameters()`` lists exactly what shapes the result.
        make_parameter(self, "falloff_range", falloff_range, trainable=trainable and variant == "exact", minimum=0.0)
        make_parameter(self, "thickness_heuristic", thickness_heuristic, trainable=trainable and variant == "ue4",
                       minimum=0.0)
        make_parameter(self, "final_power", final_power, trainable=trainable, minimum=0.0)
        make_parameter(self, "albedo", albedo, trainable=trainable and self.multibounce, minimum=0.0)
        for name in ("falloff_range", "thickness_heuristic", "final_power", "albedo"):
            t = getattr(self, name)
            if t.dim() != 0:
                raise ValueError(f"{name}: expected a scalar, got shape {tuple(t.shape)}")
        for name in ("falloff_range", "thickness_heuristic", "albedo"):
            if float(getattr(self, name).detach()) > 1:
                raise ValueError(f"{name}: expected a value in [0, 1], got {float(getattr(self, name).detach())}")
        if not float(self.final_power.detach()) > 0:
            raise ValueError(f"final_power: expected > 0, got {float(self.final_power.detach())}")

    def pattern_for(self, frame):
        common = dict(step_power=self.step_power, min_step_px=self.min_step_px, jitter=self.jitter, seed=self.seed,
                      fetch=self.fetch, border=self.border, azimuth=self.azimuth,
                      max_radius_px=getattr(self, "max_radius_px", None))
        if getattr(self, "variant", "exact") == "exact":
            return SlicePattern(self.slices, self.steps, self.radius * getattr(self, "search_scale", 1.0), **common)
        return ShaderStepPattern(self.slices, self.steps, self.radius, shader=self.variant, **common)

    def accumulator(self, frame):
        return GTAOAccumulator(self, frame)

    def extra_repr(self) -> str:
        return f"variant={self.variant!r}, normalize={self.normalize!r}, " + super().extra_repr()


def gtao(gbuffer: GBuffer, *, radius=1.0, falloff_range=0.0, thickness_heuristic=1.0, final_power=1.0, albedo=0.5,
         **options) -> AOOutput:
    """Functional :class:`GTAO`: float arguments may be tensors (gradients flow to them)."""
    return run_functional(GTAO, gbuffer, dict(radius=radius, falloff_range=falloff_range,
                                              thickness_heuristic=thickness_heuristic, final_power=final_power,
                                              albedo=albedo), **options)
