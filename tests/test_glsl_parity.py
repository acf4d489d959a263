"""Parity of ``variant="ssilvb_glsl"`` with the SSILVB GLSL article's GLSL shader running on a real OpenGL (Mesa).

The shader (tests/glsl/ssilvb.frag: the SSILVB GLSL article with only its two missing semicolons added, and a
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


# ------------------------------------------------------------------------------------------------
# Engine-sized frames on llvmpipe with 32-bit integers: the shader with one line added,
# ``precision highp int;`` (without it llvmpipe evaluates the uint masks in 16 bits). Ray-traced
# G-buffers, large radii (most samples of far-reaching steps leave the image and clamp to its edge),
# background (NaN in the position texture, which occludes nothing, as the variant's background), the
# centre-texel fetches of the shader's first step (sampleOffset 0.01), given as depth or as a
# position buffer that is not the unprojected depth.
ENGINE_CASES = {  # name: (scene, width, height, slices, steps, radius, thickness, jitter, input)
    "fence-issue15": ("fence", 320, 180, 4, 6, 2.0, 0.05, False, "depth"),
    "fence-positions": ("fence", 320, 180, 4, 6, 2.0, 0.05, False, "position"),
    "fence-640-radius8": ("fence", 640, 360, 4, 8, 8.0, 0.05, False, "depth"),
    "floating-sky-jitter": ("floating", 480, 270, 4, 6, 8.0, 0.5, True, "depth"),
    "grazing-positions": ("grazing_floor", 400, 300, 3, 8, 4.0, 0.2, True, "position"),
    "poles-radius20": ("poles", 400, 300, 2, 12, 20.0, 1.0, False, "depth"),
}
FAST_CASES = ("fence-issue15", "fence-positions")


def engine_gbuffer(name: str, folder: Path):
    """The case's G-buffer, written to ``folder/NAME.npz`` once (the shader's process reads it)."""
    from torch_ao.gbuffer import GBuffer
    from torch_ao.io import load_gbuffer, save_npz
    from torch_ao.reference import get_scene, render_reference

    path = folder / f"{name}.npz"
    if not path.exists():
        scene_name, W, H, *_, kind = ENGINE_CASES[name]
        gb = render_reference(get_scene(scene_name), height=H, width=W, spp=2, uniform=False, progress=False).gbuffer
        if kind == "position":  # positions off the pixel rays: the walk must read them, not depth
            g = torch.Generator().manual_seed(0)
            P = gb.positions() * (1 + 1e-3 * torch.randn(gb.positions().shape, generator=g))
            P = torch.where(gb.valid, P, torch.full_like(P, float("nan")))
            gb = GBuffer(None, gb.camera, normals=gb.normals, light=gb.light, position=P)
        save_npz(path, gb)
    return load_gbuffer(path)[0]


def _render_engine(folder: str, names: list[str]) -> None:
    """Child process: run the highp-int shader on each case's G-buffer, save ``folder/NAME.gl.pt``."""
    sys.path.insert(0, str(HERE / "glsl"))
    from runner import create_context, run_ssilvb, shader_source

    ctx = create_context()
    for name in names:
        _, _, _, sl, st, r, t, jit, _ = ENGINE_CASES[name]
        gb = engine_gbuffer(name, Path(folder))
        out = run_ssilvb(ctx, gb, slices=sl, steps=st, radius=r, thickness=t, jitter=jit,
                         fragment_source=shader_source(jit, highp_int=True), nan_background=True)
        torch.save({"renderer": ctx.info["GL_RENDERER"], "out": out}, Path(folder) / f"{name}.gl.pt")


def _check_engine_cases(names, tmp_path):
    from torch_ao.methods.bitmask import SSILVB

    for name in names:
        engine_gbuffer(name, tmp_path)
    env = dict(os.environ, GALLIUM_DRIVER="llvmpipe")
    proc = subprocess.run([sys.executable, __file__, "--render-engine", str(tmp_path), *names], env=env,
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        pytest.skip(f"no OpenGL context (llvmpipe): {proc.stderr.strip().splitlines()[-1] if proc.stderr else proc.returncode}")
    print(f"\n{'case':22s} {'size':>8s} {'valid px':>8s} {'|dv|<1e-3':>10s} {'exact':>7s} {'mean|dv|':>9s} "
          f"{'|dL|<1e-4':>10s} {'max|dL|':>8s}")
    for name in names:
        _, W, H, sl, st, r, t, jit, kind = ENGINE_CASES[name]
        gb = engine_gbuffer(name, tmp_path)
        gl = torch.load(tmp_path / f"{name}.gl.pt", weights_only=True)["out"]
        out = SSILVB(variant="ssilvb_glsl", slices=sl, steps=st, radius=r, thickness=t, jitter=jit,
                     glsl_numerics="mesa")(gb)
        valid = gb.valid[0, 0]
        dv = (out.visibility[0, 0].detach() - gl[..., 3]).abs()[valid]
        di = (out.indirect[0].detach().permute(1, 2, 0) - gl[..., :3]).abs().amax(-1)[valid]
        close, light_close = float((dv < 1e-3).float().mean()), float((di < 1e-4).float().mean())
        print(f"{name:22s} {W}x{H:<4d} {int(valid.sum()):8d} {close:10.5f} {float((dv == 0).float().mean()):7.4f} "
              f"{float(dv.mean()):9.2e} {light_close:10.5f} {float(di.max()):8.1e}")
        assert close >= 0.9999, name
        assert float(dv.mean()) < 1e-4, name
        assert light_close >= 0.9999, name
        if name == "fence-issue15":  # every pixel bit for bit
            assert float(dv.max()) == 0.0 and float(di.max()) < 1e-6


@pytest.mark.gl
@pytest.mark.slow
def test_ssilvb_glsl_matches_llvmpipe_with_32_bit_ints(tmp_path):
    """Issue 15's frame (a ray-traced fence, 320x180, 4 slices, 6 steps, radius 2, thickness 0.05, no
    jitter) as depth and as positions: was 83.9% within 1e-3 on an independent fence scene."""
    _check_engine_cases(FAST_CASES, tmp_path)


@pytest.mark.gl
@pytest.mark.slow
def test_ssilvb_glsl_matches_llvmpipe_on_large_frames_and_radii(tmp_path):
    _check_engine_cases([n for n in ENGINE_CASES if n not in FAST_CASES], tmp_path)


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "--render":
    sys.path.insert(0, str(HERE.parent))
    _render_all(sys.argv[2])
if __name__ == "__main__" and len(sys.argv) >= 3 and sys.argv[1] == "--render-engine":
    sys.path.insert(0, str(HERE.parent))
    _render_engine(sys.argv[2], sys.argv[3:])
