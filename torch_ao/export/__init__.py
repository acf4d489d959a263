"""A fitted pipeline's AO pass as a shader: GLSL 330 core or HLSL, the fitted constants baked in.

:func:`export_shader` turns a :class:`~torch_ao.fitted.FittedPipeline` (or a ``params.json``) into the
source of one full-screen fragment pass that computes the pipeline's visibility per pixel, as the
tensor-op walk does (the transcription is :mod:`torch_ao.export.body`; the walk is its
specification). The denoiser is not part of the pass: run your engine's own bilateral blur after it,
or none.

The interface (the same in both languages):

* ``uPosition``: RGBA32F view-space position (OpenGL axes: x right, y up, the camera looking down
  ``-z``), ``w = 0`` marks background; ``uNormal``: RGBA32F view-space unit normal (``xyz``);
  ``uBackfaceDepth``: R32F view-axis depth where the pixel's camera ray leaves the object (a
  front-face-culled depth pass; infinity where there is no exit), present only when the thickness
  model is the back-face layer;
* ``uProjection``: the OpenGL projection matrix of the camera (its intrinsics are read from it);
  ``uResolution``: the render target's size in pixels;
* the output: visibility (1 = unoccluded) in ``.r`` (GLSL: ``layout(location = 0) out vec4 fragColor``;
  HLSL: ``SV_Target0``).

GLSL is drawn with ``gl_FragCoord`` (row 0 at the bottom, textures uploaded bottom row first as
OpenGL does); HLSL with ``SV_Position`` (row 0 at the top, D3D's texture layout).

What cannot be expressed is refused with a :class:`ExportError` naming it: methods other than bitmask
AO and GTAO, the ``hdrp``/``ssilvb_glsl`` bitmask variants, GTAO's ``hdrp``/``ue4`` variants, per-object or
per-pixel thickness, soft masks, outputs beyond visibility, a reduced walk resolution.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

from ..walk.fetch import EDGE_MIN_RATIO, EDGE_SLOPE_TOLERANCE, NEAREST_TIE
from ..walk.sample import MIN_OFFSET
from .body import BODY

__all__ = ["ExportError", "FORMATS", "export_shader", "write_shader", "shader_defines", "NOISE_SPLIT_BITS"]

#: Shader languages :func:`export_shader` writes.
FORMATS = ("glsl", "hlsl")
#: The noise's inner product ``a x`` is split as ``AH x + AL x`` with ``AH`` a multiple of ``2**-15``, so
#: that ``AH x`` is exact in float32 for pixel coordinates below 4096.
NOISE_SPLIT_BITS = 15
_NOISE_A, _NOISE_B, _NOISE_SEED_SHIFT = 0.06711056, 0.00583715, 5.588238  # walk/patterns.py


class ExportError(ValueError):
    """A pipeline the exporter cannot express (the message names the option)."""


def _literal(x: float) -> str:
    """A float literal both languages read (``1.0``, ``0.25``, ``1e-06``)."""
    if not math.isfinite(x):
        raise ExportError(f"a constant of the pipeline is not finite ({x!r})")
    text = repr(float(x))
    return text if any(c in text for c in ".e") else text + ".0"


def _split(a: float) -> tuple[float, float]:
    high = math.floor(a * 2**NOISE_SPLIT_BITS) / 2**NOISE_SPLIT_BITS
    return high, a - high


def _phase(x_offset: float, y_offset: float) -> float:
    """``frac(a x0 + b y0)`` of the noise's constant pixel offset, in double precision."""
    return math.modf(_NOISE_A * x_offset + _NOISE_B * y_offset)[0]


def _scalar(module, name: str) -> float:
    value = getattr(module, name)
    if value.dim() != 0:
        raise ExportError(f"{name}: a per-object table or per-pixel map cannot be baked into a shader "
                          "(use a scalar)")
    return float(value.detach())


def _walk_defines(m) -> dict[str, str]:
    """The walk's constants (:class:`~torch_ao.methods.common.Sampling` of module ``m``)."""
    if m.resolution != "full":
        raise ExportError(f"resolution: the exported pass walks the full-resolution frame (got {m.resolution!r})")
    if m.jitter and m.noise != "ign":
        raise ExportError(f"noise: the exported pass jitters by interleaved gradient noise (got {m.noise!r})")
    if m.slice_sampling != "uniform":
        raise ExportError("slice_sampling: the exported pass walks evenly spaced slices "
                          f"(got slice_sampling={m.slice_sampling!r})")
    seed = int(m.seed)
    ah, al = _split(_NOISE_A)
    bh, bl = _split(_NOISE_B)
    shift = _NOISE_SEED_SHIFT
    return {
        "AO_SLICES": str(int(m.slices)), "AO_STEPS": str(int(m.steps)),
        "AO_STEP_POWER": _literal(m.step_power), "AO_STEP_POWER_ONE": str(int(m.step_power == 1.0)),
        "AO_MIN_STEP_PX": _literal(m.min_step_px), "AO_JITTER": str(int(bool(m.jitter))),
        "AO_STAGGER": str(int(bool(m.stagger))),
        "AO_NOISE_AH": _literal(ah), "AO_NOISE_AL": _literal(al), "AO_NOISE_BH": _literal(bh), "AO_NOISE_BL": _literal(bl),
        # SlicePattern._noise: seed for the slice angle, (u + 37, v + 59) and seed + 1 for the step offset
        "AO_NOISE_PHASE_SLICE": _literal(_phase(shift * seed, shift * seed)),
        "AO_NOISE_PHASE_STEP": _literal(_phase(37.0 + shift * (seed + 1), 59.0 + shift * (seed + 1))),
        "AO_FETCH": str({"nearest": 0, "bilinear": 1, "edge_aware": 2}[m.fetch]),
        "AO_NEAREST_TIE": _literal(NEAREST_TIE),
        "AO_EDGE_MIN_RATIO": _literal(EDGE_MIN_RATIO), "AO_EDGE_SLOPE_TOLERANCE": _literal(EDGE_SLOPE_TOLERANCE),
        "AO_BORDER_DROP": str(int(m.border == "drop")), "AO_AZIMUTH_VIEW": str(int(m.azimuth == "view")),
        "AO_MIN_OFFSET": _literal(MIN_OFFSET),
    }


def _bitmask_defines(m) -> dict[str, str]:
    from ..thickness import BACKFACE_CAP, BackfaceThickness, LinearThickness, ScalarThickness

    if m.variant not in ("default", "exact"):
        raise ExportError(f"variant: bitmask AO's {m.variant!r} variant is not exported (default and exact are)")
    if m.mode != "hard":
        raise ExportError(f"mode: the shader computes hard sector masks (got {m.mode!r})")
    if m.want_indirect or m.want_bent or m.ambient is not None or getattr(m, "ambient_constant", None) is not None:
        raise ExportError("indirect/bent_normals/ambient: the exported pass writes visibility only")
    model = m.bound_thickness().model
    kinds = {ScalarThickness: 0, LinearThickness: 1, BackfaceThickness: 2}
    if type(model) not in kinds:
        raise ExportError(f"thickness_model: {type(model).__name__} is not exported (scalar, linear and backface are)")
    out = {
        "AO_METHOD": "1", "AO_RADIUS": _literal(_scalar(m, "radius")), "AO_WALK_RADIUS": "AO_RADIUS",
        "AO_WEIGHTING_COSINE": str(int(m.weighting == "cosine")), "AO_UNION_EXACT": str(int(m.union == "exact")),
        "AO_CLIP_TO_RADIUS": str(int(bool(m.clip_to_radius))),
        "AO_THICKNESS_DEPTH": str(int(m.thickness_direction == "depth")),
        "AO_SAMPLE_EXTENT_SPHERE": str(int(m.sample_extent == "sphere")),
        "AO_SECTOR_EPSILON": _literal(m.sector_epsilon),
        "AO_ROUNDING": str({"ceil": 0, "round": 1, "floor": 2}[m.rounding]),
        "AO_THICKNESS_MODEL": str(kinds[type(model)]), "AO_THICKNESS": _literal(_scalar(m, "thickness")),
        "AO_BACKFACE_CAP": _literal(BACKFACE_CAP),
    }
    if isinstance(model, LinearThickness):
        out["AO_THICKNESS_SLOPE"] = _literal(_scalar(m, "thickness_slope"))
    if isinstance(model, BackfaceThickness):
        out["AO_THICKNESS_SCALE"] = _literal(_scalar(m, "thickness_scale"))
    if model.growth is not None:
        out["AO_THICKNESS_GROWTH"] = _literal(_scalar(m, "thickness_growth"))
    return out


def _gtao_defines(m) -> dict[str, str]:
    if m.variant != "exact":
        raise ExportError(f"variant: GTAO's {m.variant!r} variant is not exported (exact is)")
    if m.bent_normals:
        raise ExportError("bent_normals: the exported pass writes visibility only")
    falloff, power = _scalar(m, "falloff_range"), _scalar(m, "final_power")
    out = {
        "AO_METHOD": "2", "AO_RADIUS": _literal(_scalar(m, "radius")),
        "AO_WALK_RADIUS": _literal(_scalar(m, "radius") * m.search_scale),
        "AO_FALLOFF_ON": str(int(falloff > 0)), "AO_FALLOFF_RANGE": _literal(falloff),
        "AO_FINAL_POWER": _literal(power), "AO_FINAL_POWER_ONE": str(int(power == 1.0)),
        "AO_NORMALIZE": str({"exact": 0, "none": 1, "ue4": 2}[m.normalize]),
        "AO_MULTIBOUNCE": str(int(bool(m.multibounce))), "AO_ALBEDO": _literal(_scalar(m, "albedo")),
        "AO_THICKNESS_MODEL": "0",
    }
    if m.max_radius_px is not None:
        out["AO_MAX_RADIUS_PX"] = _literal(m.max_radius_px)
    return out


def shader_defines(pipeline) -> dict[str, str]:
    """The ``#define`` constants of ``pipeline``'s AO pass (:class:`~torch_ao.fitted.FittedPipeline`);
    :class:`ExportError` names what cannot be exported."""
    name = pipeline.method_name
    m = pipeline.method
    if name == "bitmask":
        specific = _bitmask_defines(m)
    elif name == "gtao":
        specific = _gtao_defines(m)
    else:
        raise ExportError(f"method: {name!r} is not exported (bitmask and gtao are)")
    return {**_walk_defines(m), **specific}


_GLSL_PRELUDE = """#version 330 core
// GLSL names for the shared body's HLSL ones
#define float2 vec2
#define float3 vec3
#define float4 vec4
#define atan2 atan
#define frac fract
#define rsqrt inversesqrt

uniform sampler2D uPosition;       // RGBA32F view-space position (OpenGL axes), w = 0: background
uniform sampler2D uNormal;         // RGBA32F view-space unit normal
{backface_uniform}uniform mat4 uProjection;
uniform vec2 uResolution;
layout(location = 0) out vec4 fragColor;  // visibility in .r

// texel (x, y) with row 0 at the top of the image (OpenGL textures hold the bottom row first)
vec4 aoPosition(int x, int y) {{ return texelFetch(uPosition, ivec2(x, int(uResolution.y) - 1 - y), 0); }}
vec3 aoNormal(int x, int y) {{ return texelFetch(uNormal, ivec2(x, int(uResolution.y) - 1 - y), 0).xyz; }}
{backface_loader}float aoProjection(int row, int col) {{ return uProjection[col][row]; }}
vec2 aoSize() {{ return uResolution; }}
"""

_GLSL_MAIN = """
void main()
{
    int px = int(gl_FragCoord.x);
    int py = int(uResolution.y) - 1 - int(gl_FragCoord.y);
    fragColor = vec4(aoVisibility(px, py), 0.0, 0.0, 1.0);
}
"""

_HLSL_PRELUDE = """// HLSL (Shader Model 4+ pixel shader, entry point main)
#define roundEven round

Texture2D<float4> uPosition : register(t0);   // RGBA32F view-space position (OpenGL axes), w = 0: background
Texture2D<float4> uNormal : register(t1);     // RGBA32F view-space unit normal
{backface_uniform}cbuffer AOConstants : register(b0)
{{
    float4x4 uProjection;  // the OpenGL projection matrix (row r, column c is uProjection[r][c])
    float2 uResolution;
}};

// texel (x, y) with row 0 at the top of the image
float4 aoPosition(int x, int y) {{ return uPosition.Load(int3(x, y, 0)); }}
float3 aoNormal(int x, int y) {{ return uNormal.Load(int3(x, y, 0)).xyz; }}
{backface_loader}float aoProjection(int row, int col) {{ return uProjection[row][col]; }}
float2 aoSize() {{ return uResolution; }}
"""

_HLSL_MAIN = """
float4 main(float4 fragCoord : SV_Position) : SV_Target0
{
    int px = int(fragCoord.x);
    int py = int(fragCoord.y);
    return float4(aoVisibility(px, py), 0.0, 0.0, 1.0);
}
"""

_BACKFACE = {
    "glsl": ("uniform sampler2D uBackfaceDepth;  // R32F view-axis depth where the camera ray leaves the object\n",
             "float aoBackface(int x, int y) { return texelFetch(uBackfaceDepth, ivec2(x, int(uResolution.y) - 1 - y), 0).r; }\n"),
    "hlsl": ("Texture2D<float> uBackfaceDepth : register(t2);  // R32F view-axis depth where the camera ray leaves the object\n",
             "float aoBackface(int x, int y) { return uBackfaceDepth.Load(int3(x, y, 0)); }\n"),
}


def _summary(pipeline, scale: float) -> str:
    """Comment lines describing what the pass computes."""
    from ..version import __version__

    m = pipeline.method
    lines = [f"torch_ao {__version__} export: {pipeline.method_name} AO pass, {m.slices} slices x {m.steps} steps, "
             f"fetch {m.fetch}, border {m.border}, azimuth {m.azimuth}, jitter {bool(m.jitter)} (seed {m.seed})"]
    if pipeline.method_name == "bitmask":
        lines.append(f"variant {m.variant}, weighting {m.weighting}, union {m.union}, thickness model "
                     f"{m.bound_thickness().model.describe()}, thickness direction {m.thickness_direction}")
    else:
        lines.append(f"variant {m.variant}, normalize {m.normalize}")
    unit = getattr(pipeline, "length_unit", "world units")
    lines.append(f"lengths in {unit}" if scale == 1.0 else f"lengths: the file's {unit} x {scale:g} (--scale)")
    lines.append("The denoiser is not part of this pass" + (" (the pipeline's denoiser is excluded: run a depth- "
                 "and normal-aware blur after it)" if pipeline.denoiser is not None else "") + ".")
    lines.append("Interface: uPosition, uNormal" + (", uBackfaceDepth" if "AO_THICKNESS_SCALE" in shader_defines(pipeline)
                 else "") + ", uProjection, uResolution; visibility in .r.")
    return "".join(f"// {line}\n" for line in lines)


def export_shader(pipeline, format: str = "glsl", *, scale: float = 1.0) -> str:
    """The source of ``pipeline``'s AO pass in ``format`` (``"glsl"`` or ``"hlsl"``).

    Args:
        pipeline: a :class:`~torch_ao.fitted.FittedPipeline`, or the path of its ``params.json``.
        format: one of :data:`FORMATS`.
        scale: world units of the engine per length unit of the pipeline (every length parameter is
            multiplied by it; :func:`torch_ao.fitted.scale_lengths`).

    Raises :class:`ExportError` (a ``ValueError``) naming an option the shader cannot express.
    """
    from ..fitted import FittedPipeline, load_fitted, rescaled

    if format not in FORMATS:
        raise ExportError(f"format: expected one of {', '.join(FORMATS)}, got {format!r}")
    if isinstance(pipeline, (str, os.PathLike)):
        pipeline = load_fitted(pipeline, scale=scale)
    elif not isinstance(pipeline, FittedPipeline):
        raise ExportError(f"pipeline: expected a FittedPipeline or a params.json path, got {type(pipeline).__name__}")
    elif scale != 1.0:
        pipeline = rescaled(pipeline, scale)
    defines = shader_defines(pipeline)
    backface = "AO_THICKNESS_SCALE" in defines
    uniform, loader = _BACKFACE[format] if backface else ("", "")
    prelude = (_GLSL_PRELUDE if format == "glsl" else _HLSL_PRELUDE).format(backface_uniform=uniform,
                                                                             backface_loader=loader)
    header, _, rest = prelude.partition("\n") if format == "glsl" else ("", "", prelude)
    consts = "".join(f"#define {k} {v}\n" for k, v in defines.items())
    main = _GLSL_MAIN if format == "glsl" else _HLSL_MAIN
    parts = [header + "\n" if header else "", _summary(pipeline, scale), rest, "\n// the fitted constants\n", consts,
             BODY, main]
    return "".join(parts)


def write_shader(pipeline, path: str | os.PathLike, format: str = "glsl", *, scale: float = 1.0) -> Path:
    """:func:`export_shader` written to ``path`` (atomically)."""
    from ..io import write_text_atomic

    source = export_shader(pipeline, format, scale=scale)
    return write_text_atomic(path, source)

