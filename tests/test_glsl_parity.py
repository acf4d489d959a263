"""Parity of ``variant="ssilvb_glsl"`` with seed 001's GLSL shader running on a real OpenGL (Mesa).

The shader (tests/glsl/ssilvb.frag: seed 001 with only its two missing semicolons added, and a
jitter-free copy) runs through moderngl's EGL backend on Mesa's software rasterizers, with RGBA32F
view-space position / normal / light textures (NEAREST, CLAMP_TO_EDGE). Each driver runs in a
subprocess (``GALLIUM_DRIVER`` selects it at EGL initialisation).

* **softpipe** evaluates ``mediump`` at full precision, like desktop GPUs: it is the reference.
  With ``glsl_numerics="mesa"`` (Mesa's GLSL ``acos`` polynomial) every pixel whose walk never
  fetches its own texel matches *bit for bit* (visibility) and within 4e-7 (indirect light). A
  centre-texel fetch makes the shader divide 0 by 0; whether its back-face cosine then rounds below
  -1 (NaN -> clamp -> 0: no occlusion) or not (the whole half circle occluded) depends on the driver's
  ``normalize`` rounding, so those pixels are reported separately.
* **llvmpipe** (Mesa's default) lowers ``mediump`` to 16 bits: ``randf`` (reproduced by
  ``glsl_numerics="mesa_mediump"``) and the ``uint`` masks (not reproduced: the issue asks for 32-bit
  masks, and 16-bit masks drop sectors 16..31). Its numbers are printed, not asserted.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

HERE = Path(__file__).resolve().parent
SCENES = ["floor_wall", "crease", "slat"]
SETTINGS = [  # (slices, steps, radius, thickness, jitter)
    (4, 4, 1.0, 0.5, True),
    (3, 6, 2.0, 0.2, True),
    (5, 3, 4.0, 1.0, True),
    (4, 4, 8.0, 0.5, False),
]


def scene(name: str):
    from torch_ao.camera import PinholeCamera
    from torch_ao.examples import crease_gbuffer, floor_wall_gbuffer, planes_gbuffer

    if name == "floor_wall":
        gb, _ = floor_wall_gbuffer(48, 64, light_direction=(0.3, 0.8, 0.5))
        return gb
    if name == "crease":
        gb = crease_gbuffer(40, 56)
        cam = gb.camera
        from torch_ao.gbuffer import GBuffer

        light = (gb.normals * torch.tensor([0.5, 0.6, 0.6]).view(1, 3, 1, 1)).sum(1, keepdim=True).clamp_min(0)
        return GBuffer(gb.depth, cam, normals=gb.normals, light=light.expand(-1, 3, -1, -1).contiguous())
    cam = PinholeCamera.from_fov(50.0, 40, 56)
    wall = ((0.0, 0.0, 1.0), -6.0, None)
    slat = ((0.0, 0.0, 1.0), -5.0, [((1.0, 0.0, 0.0), 0.15), ((-1.0, 0.0, 0.0), 0.15)])
    return planes_gbuffer([wall, slat], cam, light_direction=(0.2, 0.5, 0.8), albedo=[(0.9, 0.5, 0.2), (0.2, 0.6, 0.9)])


def _render_all(out_path: str) -> None:
    """Child process: render every scene x setting with the real shader, save to ``out_path``."""
    sys.path.insert(0, str(HERE / "glsl"))
    from runner import create_context, run_ssilvb

    ctx = create_context()
    results = {"renderer": ctx.info["GL_RENDERER"]}
    for name in SCENES:
        gb = scene(name)
        for i, (sl, st, r, t, jit) in enumerate(SETTINGS):
            results[f"{name}/{i}"] = run_ssilvb(ctx, gb, slices=sl, steps=st, radius=r, thickness=t, jitter=jit)
    torch.save(results, out_path)


def _render(driver: str, tmp_path) -> dict:
    out = tmp_path / f"{driver}.pt"
    env = dict(os.environ, GALLIUM_DRIVER=driver)
    proc = subprocess.run([sys.executable, __file__, "--render", str(out)], env=env, capture_output=True, text=True,
                          timeout=600)
    if proc.returncode != 0 or not out.exists():
        pytest.skip(f"no OpenGL context ({driver}): {proc.stderr.strip().splitlines()[-1] if proc.stderr else proc.returncode}")
    return torch.load(out, weights_only=True)


def _compare(rendered: dict, numerics: str):
    sys.path.insert(0, str(HERE / "glsl"))
    from runner import centre_texel_pixels

    from torch_ao.methods.bitmask import SSILVB

    rows = []
    for name in SCENES:
        gb = scene(name)
        for i, (sl, st, r, t, jit) in enumerate(SETTINGS):
            gl = rendered[f"{name}/{i}"]
            out = SSILVB(variant="ssilvb_glsl", slices=sl, steps=st, radius=r, thickness=t, jitter=jit,
                         glsl_numerics=numerics)(gb)
            vis, ind = out.visibility[0, 0], out.indirect[0].permute(1, 2, 0)
            centre = centre_texel_pixels(gb, slices=sl, steps=st, radius=r, jitter=jit, numerics=numerics)
            dv = (vis - gl[..., 3]).abs()
            di = (ind - gl[..., :3]).abs().amax(-1)
            ok = ~centre
            rows.append(dict(scene=name, setting=(sl, st, r, t, jit), centre=float(centre.float().mean()),
                             exact_all=float((dv == 0).float().mean()), exact_clean=float((dv[ok] == 0).float().mean()),
                             max_vis_clean=float(dv[ok].max()), max_vis_all=float(dv.max()),
                             max_ind_clean=float(di[ok & (dv == 0)].max()), pixels=int(ok.sum())))
    return rows


def _print(title, rows):
    print(f"\n{title}")
    print(f"{'scene':11s} {'slices,steps,R,t,jit':24s} {'centre px':>9s} {'exact all':>9s} {'exact*':>8s} "
          f"{'max|dv|*':>9s} {'max|dv|':>8s} {'max|dL|*':>9s}")
    for r in rows:
        print(f"{r['scene']:11s} {str(r['setting']):24s} {r['centre']:9.3f} {r['exact_all']:9.4f} {r['exact_clean']:8.4f} "
              f"{r['max_vis_clean']:9.2e} {r['max_vis_all']:8.3f} {r['max_ind_clean']:9.2e}")
    print("(* = pixels whose walk never fetches its own texel; dL over pixels whose visibility is exact)")


@pytest.mark.gl
def test_ssilvb_glsl_matches_the_shader_on_mesa_softpipe(tmp_path):
    rendered = _render("softpipe", tmp_path)
    for numerics in ("ieee", "mesa"):
        rows = _compare(rendered, numerics)
        _print(f"{rendered['renderer']}: ssilvb_glsl (glsl_numerics={numerics!r}) vs the shader", rows)
    clean = sum(r["exact_clean"] * r["pixels"] for r in rows) / sum(r["pixels"] for r in rows)
    print(f"overall exact (non-centre pixels, numerics='mesa'): {clean:.4f}")
    assert clean >= 0.99
    for r in rows:
        assert r["exact_clean"] >= 0.97, r
        assert r["max_ind_clean"] < 1e-5, r


@pytest.mark.gl
@pytest.mark.slow
def test_report_llvmpipe_differences(tmp_path):
    rendered = _render("llvmpipe", tmp_path)
    rows = _compare(rendered, "mesa_mediump")
    _print(f"{rendered['renderer']} (16-bit mediump uint masks, not reproduced): ssilvb_glsl "
           "(glsl_numerics='mesa_mediump') vs the shader", rows)
    assert all(r["pixels"] > 0 for r in rows)


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "--render":
    sys.path.insert(0, str(HERE.parent))
    _render_all(sys.argv[2])
