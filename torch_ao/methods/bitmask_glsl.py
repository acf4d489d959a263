"""The ``"ssilvb_glsl"`` variant: the SSILVB GLSL article's shader, reproduced as written.

The walk (:class:`GLSLPattern`) and the per-step work (:class:`GLSLAccumulator`) follow the shader
operation by operation, in the input's float precision (float32 gives the shader's numbers; see
``tests/test_glsl_parity.py`` for a per-pixel comparison with the shader on Mesa's llvmpipe).
Quirks of the shader, all kept on purpose (a user porting it gets the same numbers):

* **Loop bounds**: ``slice < sliceCount + 0.5`` and ``currentSample < sampleCount + 0.5`` run
  ``sliceCount + 1`` slices and ``sampleCount + 1`` steps, but the sums are divided by ``sliceCount``:
  visibility can exceed 1 (up to ``(sliceCount + 1) / sliceCount``), and so can the light weights.
* **Slice rotation** ``2 pi / (sliceCount - 1)`` over the *full* circle, starting at ``pi``:
  with ``sliceCount + 1`` slices the first and last coincide (``sliceCount >= 2`` is required;
  ``sliceCount = 1`` divides by zero in the shader).
* **One side per slice**: samples go to ``fragUV - step * scale * omega * aspect`` only.
* **Occlusion mask not reset across slices**: ``occlusion`` is declared once outside the slice loop,
  so each slice's visibility counts every sector occluded by any earlier slice (in that slice's own
  sector frame), and its "newly occluded" test too.
* **Light weight** ``1 - newly/32``: the shader weights each sample's light by the share of sectors
  it does *not* newly occlude (the paper uses ``newly/32``); kept as written, looks unintended.
* **projNormal** uses the *unnormalised* ``axis = cross(direction, camera)`` (length
  ``sqrt(1 - dot(direction, camera)^2)``), so the normal is not exactly projected onto the slice.
* **Screen radius**: ``sampleScale = -radius * P[0][0] / position.z`` is in NDC units, applied to UVs
  with ``aspect = screenSize.yx / screenSize.x``: the march reaches ``2 H / W`` times the projected
  radius, isotropically in pixels.
* **Jitter** ``IGN(gl_FragCoord) - 0.5`` (GL's bottom-left origin) is shared by the slice angle and
  every step (``sampleStep = (j + jitter) / sampleCount + 0.01``), so the first step can land behind the
  pixel (negative step) or on the centre texel. A centre-texel sample (common: the first step is only
  ``0.01`` of the way, under a pixel for distant points) has ``sampleDistance = 0``: the shader divides 0
  by 0, its front horizon is NaN (clamped to 0) and its back cosine ``dot(normalize(-camera t), camera)``
  is ``-1`` (the whole half circle occluded) or, by the driver's rounding, just below ``-1`` (NaN: nothing
  occluded). With ``glsl_numerics="mesa"`` that rounding is llvmpipe's, bit for bit (see
  :class:`GLSLVectorOps`); with ``"ieee"`` the half circle is occluded whenever ``t > 0``. It adds no light.
  Its thickness is the one at zero distance (``thickness_growth`` does not grow it).
* **Cosines rounded beyond +-1** (an occluder's back point straight behind it, e.g. a back-face layer with no
  exit): ``acos`` is NaN there and the horizon 0 with ``"mesa"``, as on llvmpipe; ``"ieee"`` takes the cosine at
  +-1, the exact value, so the result does not hang on the last bit of a dot product.
* **Background** samples (``inf``/``0``/``nan`` depth or ``mask`` False) occlude nothing and add no
  light: what the shader does when its position texture holds NaN there (NaN horizons clamp to 0).
* **Texel fetch**: nearest texel ``floor(uv * size)`` with clamp-to-edge, computed from the float UVs
  as the shader forms them, so the texel choices match.
* **Driver numerics** (``glsl_numerics=``): GLSL leaves ``acos`` precision and ``mediump`` evaluation
  to the driver. Mesa's GLSL compiler emits a polynomial ``acos`` (error ~1.6e-4 rad): ``"mesa"``
  reproduces it bit for bit (:func:`mesa_asin`), with the compiler folding ``acos``'s ``pi/2`` into the
  horizon's ``+ halfPi``, and llvmpipe's ``dot``/``normalize``/``sqrt`` roundings (:class:`GLSLVectorOps`):
  99.995-100% of pixels match llvmpipe with 32-bit ints within 1e-3 (the 320x180 fence frame of
  ``tests/test_glsl_parity.py``: every pixel bit for bit; the last few pixels elsewhere are not traced yet). llvmpipe also evaluates ``mediump`` in 16 bits:
  ``randf`` (``int`` arguments, ``mediump`` by default in a fragment shader) in float16, which
  ``"mesa_mediump"`` reproduces, and the ``uint`` masks (also ``mediump``!) in 16 bits, which no option
  reproduces: on such a driver the shader as written keeps only 16 of its 32 sectors (it should declare
  ``precision highp int;``). ``"ieee"`` (default) uses exact ``acos`` and the input precision.
* **Angles**: ``acos`` of the 3D cosines ``dot(normalize(delta - t * camera), camera)``; bit masks are
  evaluated in 32 bits (``uint``); ``hitThickness`` may be any of the module's thickness forms.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..ops import clamped_gradient, safe_acos
from ..walk import Frame, Queries, Sample, SamplingPattern, SliceAccumulator, SliceGeometry
from ..sectors import SECTORS, hard_mask, popcount32, sector_union
from ..thickness import BoundThickness

__all__ = ["GLSLPattern", "GLSLAccumulator", "GLSLVectorOps", "glsl_jitter", "glsl_constants", "mesa_acos", "mesa_asin", "GLSL_NUMERICS"]

#: ``"ieee"``: every operation in the input precision with exact ``acos`` (of cosines clamped to [-1, 1]); ``"mesa"``: Mesa's GLSL
#: ``acos`` polynomial (softpipe, and desktop-like full precision elsewhere); ``"mesa_mediump"``: also
#: llvmpipe's float16 evaluation of the ``mediump`` ``randf`` (llvmpipe's 16-bit ``mediump`` uints are
#: *not* reproduced: masks are always 32-bit).
GLSL_NUMERICS = ("ieee", "mesa", "mesa_mediump")


def mesa_asin(x: torch.Tensor) -> torch.Tensor:
    """Mesa's GLSL ``asin``: the polynomial its GLSL compiler emits,
    ``sign(x) (pi/2 - sqrt(1 - |x|) (pi/2 + |x| (pi/4 - 1 + |x| (0.08132463 - 0.02363318 |x|))))``
    (max error about 1.6e-4 rad), with its constant ``M_PI_4f - 1.0f`` rounded in float and a correctly
    rounded ``sqrt``: bit for bit llvmpipe's in float32. Inputs are clamped to [-1, 1] (NaN beyond is
    handled by the caller); the gradient is made finite at ``|x| = 1``."""
    dt = x.dtype
    c = lambda v: torch.tensor(v, dtype=dt, device=x.device)  # noqa: E731
    half_pi, quarter_pi_m1 = c(math.pi / 2), c(math.pi / 4) - 1.0

    def f(v):
        ax = v.abs()
        poly = half_pi + ax * (quarter_pi_m1 + ax * (c(0.08132463) + ax * c(-0.02363318)))
        return torch.sign(v) * (half_pi - _EXACT.sqrt(c(1.0) - ax) * poly)

    return clamped_gradient(lambda v: f(v.clamp(-1.0, 1.0)), x)


def mesa_acos(x: torch.Tensor) -> torch.Tensor:
    """Mesa's GLSL ``acos``: ``pi/2 - asin(x)`` (:func:`mesa_asin`), bit for bit llvmpipe's in float32."""
    return torch.tensor(math.pi / 2, dtype=x.dtype, device=x.device) - mesa_asin(x)


class GLSLVectorOps:
    """``dot``, ``length``, ``normalize`` and ``sqrt`` as the shader's driver evaluates them.

    ``exact=True`` (``glsl_numerics="mesa"``/``"mesa_mediump"``) follows Mesa's llvmpipe bit for bit
    (found by running the operations on it, ``tests/test_glsl_parity.py``): ``dot(a, b) =
    (a.y b.y + a.z b.z) + a.x b.x`` in float32 without fused multiply-adds, ``length(v) =
    sqrt(dot(v, v))`` and ``normalize(v) = v * (1 / sqrt(dot(v, v)))``, each step rounded, with the
    correctly rounded IEEE ``sqrt`` (torch's float32 ``sqrt`` is not: it is off by one ulp on some
    inputs, so it is taken in float64 and rounded, which is exact for square roots). Its roundings decide, e.g., whether ``dot(normalize(-c t), c)`` is ``-1`` or
    falls just below (then ``acos`` is NaN). ``exact=False`` (``"ieee"``) uses torch's reductions.
    Shapes: vectors ``(..., 3)`` -> ``(...)`` (``dot``, ``length``) or ``(..., 3)``."""

    def __init__(self, exact: bool) -> None:
        self.exact = exact

    def dot(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        p = a * b
        return (p[..., 1] + p[..., 2]) + p[..., 0] if self.exact else p.sum(-1)

    def sqrt(self, x: torch.Tensor) -> torch.Tensor:
        if self.exact and x.dtype == torch.float32:
            return torch.sqrt(x.double()).float()
        return torch.sqrt(x)

    def length(self, v: torch.Tensor) -> torch.Tensor:
        return self.sqrt(self.dot(v, v)) if self.exact else v.norm(dim=-1)

    def normalize(self, v: torch.Tensor) -> torch.Tensor:
        if self.exact:
            return v * (1.0 / self.sqrt(self.dot(v, v)))[..., None]
        return F.normalize(v, dim=-1, eps=1e-12)


_EXACT = GLSLVectorOps(exact=True)


def glsl_constants(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The shader's ``pi``, ``twoPi``, ``halfPi`` (from the literal ``3.14159265359``) in ``dtype``."""
    pi = torch.tensor(3.14159265359, dtype=dtype)
    return pi, 2.0 * pi, 0.5 * pi


def _mod1(x: torch.Tensor) -> torch.Tensor:
    return x - torch.floor(x)


def glsl_jitter(q: Queries, height: int, enabled: bool = True, numerics: str = "ieee") -> torch.Tensor:
    """``randf(int(gl_FragCoord.x), int(gl_FragCoord.y)) - 0.5`` ``(N,)``; GL's row 0 is the bottom row.
    Without jitter (the test's jitter-free shader copy) it is 0.

    ``randf`` takes ``int`` arguments, whose default precision in a GLSL ES fragment shader is
    ``mediump``, so the whole expression is ``mediump``: with ``numerics="mesa_mediump"`` it is evaluated
    in float16 as llvmpipe does; otherwise in the input precision (as desktop GPUs and softpipe do)."""
    if not enabled:
        return torch.zeros_like(q.u)
    dt = torch.float16 if numerics == "mesa_mediump" else q.u.dtype
    x = q.u.detach().to(dt)
    y = ((height - 1) - q.v.detach()).to(dt)
    inner = _mod1(torch.tensor(0.06711056, dtype=dt) * x + torch.tensor(0.00583715, dtype=dt) * y)
    return _mod1(torch.tensor(52.9829189, dtype=dt) * inner).to(q.u.dtype) - 0.5


def _slice_direction(q: Queries, s: int, slice_count: int, jitter: torch.Tensor) -> torch.Tensor:
    pi, two_pi, _ = glsl_constants(q.u.dtype)
    rotation = two_pi / (slice_count - 1.0)
    phi = rotation * (s + jitter) + pi
    return torch.cos(phi), torch.sin(phi)


class GLSLPattern(SamplingPattern):
    """The shader's walk: ``sliceCount + 1`` slices, one side each, ``sampleCount + 1`` nearest-texel steps.

    Args:
        slices, steps: the shader's ``sliceCount`` (>= 2) and ``sampleCount`` (>= 1).
        radius: ``sampleRadius`` (world units; a float or 0-d tensor).
        jitter: ``False`` reproduces the jitter-free shader copy (``jitter = 0``).
        frame: the frame being walked (image size, ``P[0][0] = 2 fx / W``); may be ``None`` to validate.
    """

    sides = (-1,)
    fetch = "nearest"
    border = "clamp"

    def __init__(self, slices: int, steps: int, radius, *, jitter: bool = True, frame: Frame | None = None,
                 numerics: str = "ieee") -> None:
        if isinstance(slices, bool) or not isinstance(slices, int) or slices < 2:
            raise ValueError(f"slices: the 'ssilvb_glsl' variant needs sliceCount >= 2 (the shader rotates by "
                             f"2 pi / (sliceCount - 1)), got {slices!r}")
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"steps: expected an integer >= 1, got {steps!r}")
        self.slice_count, self.sample_count = slices, steps
        self.num_slices = slices + 1
        self.radius, self.jitter, self.frame = radius, jitter, frame
        if numerics not in GLSL_NUMERICS:
            raise ValueError(f"glsl_numerics: expected one of {GLSL_NUMERICS}, got {numerics!r}")
        self.numerics = numerics

    def slice_tangent(self, frame: Frame, q: Queries, s: int) -> torch.Tensor:
        jitter = glsl_jitter(q, frame.shape[1], self.jitter, self.numerics)
        ox, oy = _slice_direction(q, s, self.slice_count, jitter)
        direction = torch.stack((ox, oy, torch.zeros_like(ox)), -1)
        V = q.view
        ortho = direction - (direction * V).sum(-1, keepdim=True) * V
        return F.normalize(ortho, dim=-1, eps=1e-12)

    def step_offsets(self, q: Queries, geom: SliceGeometry, side: int) -> list[torch.Tensor]:
        frame = self.frame
        B, H, W = frame.shape
        dt = q.u.dtype
        jitter = glsl_jitter(q, H, self.jitter, self.numerics)
        ox, oy = _slice_direction(q, geom.index, self.slice_count, jitter)
        p00 = (2 * frame.fx / W).to(dt)[q.batch]  # projection[0][0] as camera.opengl_projection() builds it
        radius = torch.as_tensor(self.radius, dtype=dt, device=q.u.device)
        scale = (-radius * p00) / q.position[:, 2]  # the centre's position.z (-depth unless a position buffer says otherwise)
        frag_u = (q.u + 0.5) / W
        y_gl = (H - 1) - q.v
        frag_v = (y_gl + 0.5) / H
        aspect_x = torch.tensor(H, dtype=dt) / torch.tensor(W, dtype=dt)  # screenSize.yx / screenSize.x
        count = torch.tensor(float(self.sample_count), dtype=dt)
        offsets = []
        for j in range(self.sample_count + 1):
            step = (j + jitter) / count + torch.tensor(0.01, dtype=dt)
            f = step * scale
            uv_u = frag_u - (f * ox) * aspect_x
            uv_v = frag_v - (f * oy) * 1.0
            # GL nearest texel with clamp-to-edge; the offsets are whole texels, so the walk's
            # nearest fetch lands exactly on them (texel row ty counts from the bottom).
            tx = torch.floor(uv_u * W).detach().clamp(0, W - 1)
            ty = torch.floor(uv_v * H).detach().clamp(0, H - 1)
            offsets.append(torch.stack((tx - q.u, ((H - 1) - ty) - q.v), -1))
        return offsets


class GLSLAccumulator(SliceAccumulator):
    """The shader's per-step work (hard: 32-bit masks; soft/straight-through: :func:`sector_union`)."""

    def __init__(self, *, mode: str, rounding: str, tau: float, thickness: BoundThickness, indirect: bool,
                 slice_count: int, frame: Frame, jitter: bool = True, numerics: str = "ieee") -> None:
        self.mode, self.rounding, self.tau, self.thickness = mode, rounding, tau, thickness
        self.indirect, self.slice_count = indirect, slice_count
        self.height = frame.shape[1]
        self.jitter_enabled = jitter
        self.numerics = numerics
        self.gl = GLSLVectorOps(exact=numerics in ("mesa", "mesa_mediump"))

    def begin_slice(self, q: Queries, geom: SliceGeometry):
        pi, _, half_pi = glsl_constants(q.u.dtype)
        if geom.index == 0:
            n = len(q)
            self.carry = {
                "occlusion": torch.zeros(n, dtype=torch.int64, device=q.u.device) if self.mode == "hard"
                else torch.ones(n, SECTORS, dtype=q.u.dtype, device=q.u.device),
                "visibility": q.u.new_zeros(n),
                "lighting": q.u.new_zeros(n, 3),
            }
        gl = self.gl
        camera = gl.normalize(-q.position) if gl.exact else q.view
        normal = gl.normalize(q.normal)
        direction = self._direction(q, geom)
        ortho = direction - gl.dot(direction, camera)[:, None] * camera
        axis = torch.cross(direction, camera, dim=-1)  # not normalised (as written)
        proj = normal - axis * gl.dot(normal, axis)[:, None]
        proj_length = gl.length(proj)
        sign_n = torch.sign(gl.dot(ortho, proj))
        cos_n = (gl.dot(proj, camera) / proj_length).clamp(0.0, 1.0)
        n_angle = sign_n * self._acos(cos_n)
        return {"n": n_angle, "pi": pi, "half_pi": half_pi, "normal": normal, "camera": camera,
                "s": [], "w": [], "light": []}

    def _acos(self, x: torch.Tensor) -> torch.Tensor:
        if self.numerics in ("mesa", "mesa_mediump"):
            return mesa_acos(x)
        return safe_acos(x)

    def _horizon(self, cosine: torch.Tensor, n, pi, half_pi) -> torch.Tensor:
        """``clamp((acos(cosine) + n + halfPi) / pi, 0, 1)``; ``acos`` of NaN is NaN in the shader, and
        ``clamp(NaN, 0, 1)`` is 0 on llvmpipe: reproduced as 0. A cosine rounded beyond +-1 is NaN too
        with the driver's numerics (``"mesa"``); with ``"ieee"`` it is taken at +-1, the exact value,
        so that a horizon does not hang on the last bit of a dot product."""
        c = cosine.detach()
        bad = ~(c.abs() <= 1) if self.gl.exact else torch.isnan(c)
        cosine = torch.where(bad, torch.zeros_like(cosine), cosine)
        if self.gl.exact:  # Mesa folds acos's pi/2 into the + halfPi: (pi - asin(c)) + n, bit for bit
            value = ((pi - mesa_asin(cosine)) + n) / pi
        else:
            value = (self._acos(cosine) + n + half_pi) / pi
        value = value.clamp(0.0, 1.0)
        return torch.where(bad, torch.zeros_like(value), value)

    def _direction(self, q: Queries, geom: SliceGeometry) -> torch.Tensor:
        jitter = glsl_jitter(q, self.height, self.jitter_enabled, self.numerics)
        ox, oy = _slice_direction(q, geom.index, self.slice_count, jitter)
        return torch.stack((ox, oy, torch.zeros_like(ox)), -1)

    def step(self, state, q: Queries, geom: SliceGeometry, sample: Sample):
        gl, camera = self.gl, state["camera"]
        delta = sample.delta
        horizon = delta / gl.length(delta)[:, None]
        t = self.thickness(sample)
        t = t[:, None] if t.dim() == 1 else t
        front = gl.dot(horizon, camera)
        back = gl.dot(gl.normalize(delta - camera * t), camera)
        pi, half_pi, n = state["pi"], state["half_pi"], state["n"]
        x = self._horizon(front, n, pi, half_pi)
        y = self._horizon(back, n, pi, half_pi)
        # Background samples never occlude (what the shader does when its position buffer holds NaN
        # there: NaN horizons clamp to 0, an empty run); their stand-in delta -V could otherwise round
        # to a cosine beyond -1 and occlude everything.
        x = torch.where(sample.valid, x, torch.ones_like(x))
        y = torch.where(sample.valid, y, torch.ones_like(y))
        # A sample on the centre texel has sampleDistance = 0: the shader's front horizon is 0/0 = NaN,
        # and clamp(NaN, 0, 1) gives 0 on llvmpipe, so x = 0. Its back direction is -camera: y = 1 when
        # the thickness is > 0 (the whole half circle occluded) and NaN -> 0 when it is 0. With the
        # driver's roundings (exact ops) dot(normalize(-camera t), camera) may fall below -1: NaN -> 0.
        centre = sample.distance_px == 0
        if bool(centre.any()):
            x = torch.where(centre, torch.zeros_like(x), x)
            t = self.thickness.ungrown(sample)  # (|sample - pixel| = 0: no growth)
            t = t[:, None] if t.dim() == 1 else t
            if gl.exact:  # (t = 0: normalize(0) is NaN, clamped to 0; kept out of the graph, whose 0 * inf is NaN)
                thick = t > 0
                t_safe = torch.where(thick, t, torch.ones_like(t))
                y_centre = self._horizon(gl.dot(gl.normalize(-(camera * t_safe)), camera), n, pi, half_pi)
                y_centre = torch.where(thick.reshape(-1) if t.dim() == 2 else thick, y_centre, torch.zeros_like(y_centre))
            else:
                y_centre = ((t[:, 0] if t.dim() == 2 else t.expand_as(x)) > 0).to(y.dtype)
            y = torch.where(centre, y_centre, y)
        s = x * float(SECTORS)
        w = (y - x) * float(SECTORS)
        light = None
        if self.indirect:
            sample_normal = gl.normalize(sample.gather("normals"))
            light = sample.gather("light")
            c1 = gl.dot(state["normal"], horizon).clamp(0.0, 1.0)
            c2 = gl.dot(sample_normal, -horizon).clamp(0.0, 1.0) * sample.valid.to(delta.dtype)
            light = (light * c1[:, None]) * c2[:, None]
        if self.mode == "hard":
            mask = hard_mask(s, w, self.rounding)
            occ = self.carry["occlusion"]
            if light is not None:
                newly = popcount32(mask & ~occ).to(delta.dtype)
                weight = 1.0 - newly / float(SECTORS)
                self.carry["lighting"] = self.carry["lighting"] + weight[:, None] * light
            self.carry["occlusion"] = occ | mask
        else:
            state["s"].append(s)
            state["w"].append(w)
            if light is not None:
                state["light"].append(light)
        return state

    def end_slice(self, state, q: Queries, geom: SliceGeometry) -> dict[str, torch.Tensor]:
        carry = self.carry
        if self.mode == "hard":
            covered = popcount32(carry["occlusion"]).to(q.u.dtype)
        else:
            S, W = torch.stack(state["s"], 1), torch.stack(state["w"], 1)
            uniform = S.new_full((1, SECTORS), 1.0 / SECTORS).expand(S.shape[0], SECTORS)
            visible, newly = sector_union(S, W, mode=self.mode, rounding=self.rounding, tau=self.tau,
                                          weights=uniform if self.indirect else None, p0=carry["occlusion"])
            carry["occlusion"] = visible
            if self.indirect:
                carry["lighting"] = carry["lighting"] + ((1.0 - newly)[:, :, None] * torch.stack(state["light"], 1)).sum(1)
            covered = (1 - visible).sum(-1)
        carry["visibility"] = carry["visibility"] + (1.0 - covered / float(SECTORS))
        if geom.index < self.slice_count:  # not the last slice: totals come out once, in shader order
            return {}
        out = {"visibility": carry["visibility"][:, None]}
        if self.indirect:
            out["indirect"] = carry["lighting"]
        return out

    def finish(self, sums, q: Queries, num_slices: int) -> dict[str, torch.Tensor]:
        count = float(self.slice_count)
        out = {"visibility": sums["visibility"] / count}
        if self.indirect:
            out["indirect"] = sums["indirect"] / count
        return out
