"""Run the SSILVB GLSL article's fragment shader on an OpenGL context (moderngl, EGL; e.g. Mesa llvmpipe).

``run_ssilvb(ctx, gbuffer, ...)`` uploads view-space position, normal and light as RGBA32F textures
(NEAREST, CLAMP_TO_EDGE, flipped so that GL's row 0 is the image's bottom row), draws a fullscreen
quad and returns the shader's ``vec4(lighting, visibility)`` as a ``(H, W, 4)`` float32 tensor with
row 0 at the top.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
SHADERS = {"jitter": "ssilvb.frag", "nojitter": "ssilvb_nojitter.frag"}


def create_context():
    """A standalone EGL context, or raise with the reason."""
    import moderngl

    return moderngl.create_context(standalone=True, backend="egl")


def _rgba(img: torch.Tensor) -> bytes:
    hw3 = img.detach().to(torch.float32).permute(1, 2, 0).numpy()
    rgba = np.concatenate([hw3, np.ones(hw3.shape[:2] + (1,), np.float32)], -1)[::-1]  # GL row 0 = bottom
    return np.ascontiguousarray(rgba, dtype="f4").tobytes()


def shader_source(jitter: bool, highp_int: bool = False) -> str:
    """The shader as published (``jitter``) or its jitter-free copy; ``highp_int`` adds
    ``precision highp int;`` (llvmpipe otherwise evaluates the ``uint`` masks in 16 bits)."""
    source = (HERE / SHADERS["jitter" if jitter else "nojitter"]).read_text()
    if highp_int:
        source = source.replace("precision highp float;\n", "precision highp float;\nprecision highp int;\n", 1)
        assert "precision highp int;" in source
    return source


def run_ssilvb(ctx, gbuffer, *, slices: int, steps: int, radius: float, thickness: float, jitter: bool = True,
               fragment_source: str | None = None, extra_uniforms: dict | None = None,
               nan_background: bool = False) -> torch.Tensor:
    """``nan_background``: the position texture holds NaN on background pixels (else the G-buffer's
    stand-in positions at depth 1), so that the shader's samples there occlude nothing, as the variant's."""
    import moderngl

    H, W = gbuffer.depth.shape[-2:]
    frag = fragment_source or shader_source(jitter)
    prog = ctx.program(vertex_shader=(HERE / "quad.vert").read_text(), fragment_shader=frag)
    positions = gbuffer.positions()[0]
    if nan_background:
        positions = torch.where(gbuffer.valid[0], positions, torch.full_like(positions, float("nan")))
    images = {"screenPosition": positions, "screenNormal": gbuffer.view_normals()[0],
              "screenLight": gbuffer.light[0]}
    textures = []
    for unit, (name, img) in enumerate(images.items()):
        tex = ctx.texture((W, H), 4, _rgba(img), dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        tex.repeat_x = tex.repeat_y = False  # CLAMP_TO_EDGE
        tex.use(unit)
        textures.append(tex)
        if name in prog:
            prog[name] = unit
    uniforms = {"sampleCount": float(steps), "sampleRadius": float(radius), "sliceCount": float(slices),
                "hitThickness": float(thickness), "screenSize": (float(W), float(H))}
    uniforms.update(extra_uniforms or {})
    for name, value in uniforms.items():
        if name in prog:
            prog[name] = value
    if "projection" in prog:
        P = gbuffer.camera.opengl_projection()[0].to(torch.float32).numpy()
        prog["projection"].write(np.ascontiguousarray(P.T, dtype="f4").tobytes())  # column-major
    out = torch.from_numpy(_draw(ctx, prog, W, H))
    for obj in textures + [prog]:
        obj.release()
    return out


def _draw(ctx, prog, W: int, H: int) -> np.ndarray:
    """Draw a full-screen quad with ``prog`` into a ``W x H`` RGBA32F target; its ``(H, W, 4)`` pixels, row 0 at the top."""
    import moderngl

    vbo = ctx.buffer(np.array([-1, -1, 1, -1, -1, 1, 1, 1], dtype="f4").tobytes())
    vao = ctx.vertex_array(prog, [(vbo, "2f", "in_vert")])
    target = ctx.texture((W, H), 4, dtype="f4")
    fbo = ctx.framebuffer([target])
    fbo.use()
    ctx.viewport = (0, 0, W, H)
    vao.render(moderngl.TRIANGLE_STRIP)
    data = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype="f4").reshape(H, W, 4)[::-1].copy()
    for obj in (target, fbo, vao, vbo):
        obj.release()
    return data


def centre_texel_pixels(gbuffer, *, slices: int, steps: int, radius: float, jitter: bool, numerics: str = "mesa") -> torch.Tensor:
    """``(H, W)`` bool: pixels whose walk (as the shader forms it) fetches its own texel at some step."""
    from torch_ao.walk import Frame, slice_geometry
    from torch_ao.methods.bitmask_glsl import GLSLPattern

    frame = Frame(gbuffer)
    pattern = GLSLPattern(slices, steps, torch.tensor(float(radius)), jitter=jitter, frame=frame, numerics=numerics)
    q = frame.queries
    hit = torch.zeros(len(q), dtype=torch.bool)
    for s in range(pattern.num_slices):
        geom = slice_geometry(frame, q, pattern, s)
        for offset in pattern.step_offsets(q, geom, -1):
            hit |= (offset == 0).all(-1)
    return frame.scatter(hit[:, None].to(gbuffer.depth.dtype), 0.0)[0, 0] > 0


_QUAD_330 = """#version 330 core
in vec2 in_vert;
void main() { gl_Position = vec4(in_vert, 0.0, 1.0); }
"""


def run_exported(ctx, gbuffer, source: str) -> torch.Tensor:
    """Draw an exported AO pass (``torch-ao export --format glsl``) over ``gbuffer`` through its fixed
    interface: ``uPosition`` (w = 1 on valid pixels, 0 on background), ``uNormal``, ``uBackfaceDepth``
    when the shader declares it, ``uProjection``, ``uResolution``. Returns its ``.r`` ``(H, W)``, row 0 at the top."""
    import moderngl

    H, W = gbuffer.depth.shape[-2:]
    prog = ctx.program(vertex_shader=_QUAD_330, fragment_shader=source)
    valid = gbuffer.valid[0].to(torch.float32)
    images = {"uPosition": torch.cat([gbuffer.positions()[0].to(torch.float32), valid], 0),
              "uNormal": torch.cat([gbuffer.view_normals()[0].to(torch.float32), torch.zeros_like(valid)], 0)}
    if "uBackfaceDepth" in prog:
        images["uBackfaceDepth"] = gbuffer.backface_depth[0].to(torch.float32)
    textures = []
    for unit, (name, img) in enumerate(images.items()):
        data = np.ascontiguousarray(img.detach().permute(1, 2, 0).numpy()[::-1], dtype="f4")  # GL row 0 = bottom
        tex = ctx.texture((W, H), img.shape[0], data.tobytes(), dtype="f4")
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        tex.use(unit)
        textures.append(tex)
        prog[name] = unit
    P = gbuffer.camera.opengl_projection()[0].to(torch.float32).numpy()
    prog["uProjection"].write(np.ascontiguousarray(P.T, dtype="f4").tobytes())  # column-major
    prog["uResolution"] = (float(W), float(H))
    out = torch.from_numpy(_draw(ctx, prog, W, H)[..., 0].copy())
    for obj in textures + [prog]:
        obj.release()
    return out
