"""``torch-ao export``: a fitted pipeline's AO pass as a GLSL or HLSL shader (see :mod:`torch_ao.export`)."""
from __future__ import annotations

import argparse

from ..cli import CommandError
from ..export import FORMATS, ExportError, write_shader
from ..fitted import SCALE, load_fitted
from ..options import Option
from .options_cli import add_options

#: The flags of ``torch-ao export``.
OPTIONS = (
    Option("format", "glsl", "shader language: GLSL 330 core or HLSL (a pixel shader, entry point main)", str,
           choices=FORMATS),
    Option("out", None, "the shader file to write (default: PARAMS's name with .frag for GLSL, .hlsl for HLSL)", str),
    SCALE,
)


def register(sub) -> None:
    p = sub.add_parser(
        "export",
        help="write a fitted pipeline's AO pass as a shader",
        description="Write the AO pass of the pipeline a `torch-ao fit` params.json describes as one full-screen "
        "fragment shader with the fitted constants baked in (method, variant, thickness model, fetch, slices, "
        "steps, lengths). Inputs: uPosition (view-space position, OpenGL axes, w = 0 on background), uNormal, "
        "uBackfaceDepth (back-face thickness model only), uProjection, uResolution; visibility in .r. The "
        "denoiser is not part of the pass. See docs/engines.md for where the shader goes in each engine.",
    )
    p.add_argument("params", metavar="PARAMS", help="a params.json written by `torch-ao fit`")
    add_options(p, {o.name: o for o in OPTIONS}, given_only=False)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    scale = 1.0 if args.scale is None else args.scale
    pipeline = load_fitted(args.params, scale=scale)
    out = args.out or str(Path(args.params).with_suffix(".frag" if args.format == "glsl" else ".hlsl"))
    try:
        path = write_shader(args.params, out, args.format, scale=scale)
    except ExportError as err:
        raise CommandError(f"{args.params}: {err}") from None
    m = pipeline.method
    print(f"{pipeline.method_name} ({m.slices} slices x {m.steps} steps, fetch {m.fetch}) -> {path} ({args.format}"
          + ("" if scale == 1.0 else f", lengths x {scale:g}") + ("; denoiser excluded" if pipeline.denoiser else "")
          + ")")
    return 0
