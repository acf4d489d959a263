"""``torch-ao export``: the exported AO pass agrees with the tensor-op walk it transcribes.

The GLSL runs on Mesa llvmpipe through moderngl EGL (each render in a subprocess, as in
tests/test_glsl_parity.py) over ray-traced G-buffers with a back-face layer, and is compared with the
same params.json run by :func:`torch_ao.load_fitted` without its denoiser (the pass excludes it), jitter
on (both sides use interleaved gradient noise of the pixel). The HLSL is compiled by glslang's HLSL
front end (``glslangValidator -D``; Debian's glslang-tools).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from torch_ao.cli import main
from torch_ao.export import export_shader
from torch_ao.fitted import FittedPipeline, load_fitted

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
#: name: (method, options) written to a params.json; the first three are the fits of docs/targets
#: (docs/targets/regenerate.sh views2x3: bitmask, exact_backface_edge, gtao), their values copied here
PIPELINES = {
    "default": ("bitmask", {"preset": "high", "weighting": "cosine", "radius": 0.5119233131408691,
                            "thickness": 0.2210051566362381}),  # what `torch-ao fit` ships, fitted
    "exact_backface_edge": ("bitmask", {"preset": "high", "variant": "exact", "weighting": "cosine",
                                        "fetch": "edge_aware", "thickness_model": "backface",
                                        "radius": 0.6248062252998352, "thickness_scale": 0.7624487280845642,
                                        "thickness": 0.13077417016029358}),
    "gtao": ("gtao", {"preset": "high", "radius": 0.7592839598655701, "falloff_range": 0.316685289144516,
                      "final_power": 1.0825409889221191}),
    "exact_bilinear_nojitter": ("bitmask", {"preset": "high", "variant": "exact", "fetch": "bilinear", "jitter": False,
                                            "radius": 0.6, "thickness": 0.25}),
    "linear_nearest_clamp": ("bitmask", {"preset": "ultra", "thickness_model": "linear", "thickness": 0.1,
                                         "thickness_slope": 0.05, "fetch": "nearest", "border": "clamp", "seed": 3}),
    "backface_uniform_screen": ("bitmask", {"preset": "high", "weighting": "uniform", "thickness_model": "backface",
                                            "thickness_scale": 0.8, "thickness": 0.1, "azimuth": "screen"}),
    "gtao_edge_multibounce": ("gtao", {"preset": "medium", "fetch": "edge_aware", "radius": 0.7, "falloff_range": 0.3,
                                       "final_power": 1.2, "multibounce": True, "normalize": "none", "step_power": 2.0}),
    # torch-ao fit's default pipeline (staggered steps along screen slices), with a growth as --params can fit one
    "shipped_growth": ("bitmask", {"preset": "very_high_steps", "weighting": "cosine", "fetch": "edge_aware",
                                   "stagger": True, "azimuth": "screen", "thickness_model": "backface",
                                   "thickness_scale": 0.94, "thickness": 0.08, "radius": 0.6, "thickness_growth": 0.3}),
}
FAST = ("default", "exact_backface_edge")
SCENES = ("fence", "stairs", "poles", "sphere_on_plane")
FAST_SCENES = ("fence", "stairs")
WITHIN = 1 / 32


def params_file(name: str, folder: Path) -> Path:
    spec = PIPELINES[name]
    path = folder / f"{name}.json"
    if not path.exists():
        FittedPipeline(spec[0], spec[1], True).save(path)
    return path


def scene_gbuffer(name: str, folder: Path):
    """A ray-traced 160x96 view of the built-in scene with its back-face layer, cached in ``folder``."""
    from torch_ao.io import load_gbuffer, save_npz
    from torch_ao.reference import get_scene, render_reference

    path = folder / f"{name}.npz"
    if not path.exists():
        ref = render_reference(get_scene(name, seed=1000), height=96, width=160, spp=2, uniform=False,
                               progress=False, backface=True)
        save_npz(path, ref.gbuffer, backface_depth=ref.backface_depth)
    gbuffer, arrays = load_gbuffer(path)
    return replace(gbuffer, backface_depth=gbuffer.backface_depth if gbuffer.backface_depth is not None
                   else arrays["backface_depth"])


def _render(folder: str, pairs: list[str]) -> None:
    """Child process: draw each ``pipeline/scene``'s exported GLSL, save ``folder/pipeline-scene.gl.pt``."""
    sys.path.insert(0, str(HERE / "glsl"))
    from runner import create_context, run_exported

    ctx = create_context()
    for pair in pairs:
        name, scene = pair.split("/")
        source = export_shader(params_file(name, Path(folder)), "glsl")
        out = run_exported(ctx, scene_gbuffer(scene, Path(folder)), source)
        torch.save({"renderer": ctx.info["GL_RENDERER"], "out": out}, Path(folder) / f"{name}-{scene}.gl.pt")


def _parity(names, scenes, tmp_path) -> list[tuple[str, str, float, float]]:
    pairs = [f"{n}/{s}" for n in names for s in scenes]
    for n in names:
        params_file(n, tmp_path)
    for s in scenes:
        scene_gbuffer(s, tmp_path)
    env = dict(os.environ, GALLIUM_DRIVER="llvmpipe", PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, __file__, "--render", str(tmp_path), *pairs], env=env,
                          capture_output=True, text=True, timeout=900)
    if proc.returncode != 0:
        pytest.skip(f"no OpenGL context (llvmpipe): {proc.stderr.strip().splitlines()[-1] if proc.stderr else proc.returncode}")
    rows = []
    print(f"\n{'pipeline':26s} {'scene':16s} {'valid px':>8s} {'<= 1/32':>8s} {'< 1e-4':>8s} {'max |dv|':>8s}")
    for pair in pairs:
        name, scene = pair.split("/")
        gbuffer = scene_gbuffer(scene, tmp_path)
        pipeline = load_fitted(params_file(name, tmp_path))
        pipeline.denoiser = None  # the exported pass excludes it
        with torch.no_grad():
            expected = pipeline(gbuffer).visibility[0, 0]
        gl = torch.load(tmp_path / f"{name}-{scene}.gl.pt", weights_only=True)["out"]
        valid = gbuffer.valid[0, 0]
        dv = (expected - gl).abs()[valid]
        within, close = float((dv <= WITHIN).float().mean()), float((dv < 1e-4).float().mean())
        print(f"{name:26s} {scene:16s} {int(valid.sum()):8d} {within:8.5f} {close:8.5f} {float(dv.max()):8.2e}")
        assert bool(torch.isfinite(gl).all())
        assert (gl[~valid] == 1).all()  # background
        rows.append((name, scene, within, close))
    return rows


@pytest.mark.gl
@pytest.mark.slow
def test_exported_glsl_matches_the_walk_on_llvmpipe(tmp_path):
    """The default pipeline and the exact back-face one with edge-aware fetch, two scenes."""
    for name, scene, within, close in _parity(FAST, FAST_SCENES, tmp_path):
        assert within >= 0.995, (name, scene)
        assert close >= 0.99, (name, scene)


@pytest.mark.gl
@pytest.mark.slow
def test_exported_glsl_matches_the_walk_for_every_exported_option(tmp_path):
    for name, scene, within, close in _parity(tuple(PIPELINES), SCENES, tmp_path):
        assert within >= 0.995, (name, scene)


# ------------------------------------------------------------------------------------------------ compilers
def _compile(source: str, path: Path, hlsl: bool) -> subprocess.CompletedProcess:
    path.write_text(source)
    cmd = ["glslangValidator", "-S", "frag", str(path)]
    if hlsl:
        cmd = ["glslangValidator", "-D", "-V", "-e", "main", "-S", "frag", "-o", str(path.with_suffix(".spv")), str(path)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(shutil.which("glslangValidator") is None,
                    reason="glslangValidator not installed (apt-get install glslang-tools)")
@pytest.mark.parametrize("name", tuple(PIPELINES))
def test_exported_hlsl_and_glsl_compile(name, tmp_path):
    params = params_file(name, tmp_path)
    for fmt, suffix in (("glsl", ".frag"), ("hlsl", ".hlsl")):
        proc = _compile(export_shader(params, fmt), tmp_path / f"{name}{suffix}", fmt == "hlsl")
        assert proc.returncode == 0, proc.stdout + proc.stderr


def test_the_shader_bakes_the_fitted_constants_and_its_interface(tmp_path):
    exact = params_file("exact_backface_edge", tmp_path)
    source = export_shader(exact, "glsl", scale=100.0)
    data = load_fitted(exact)
    radius = float(data.method.radius.detach()) * 100
    assert source.startswith("#version 330 core\n")
    assert f"#define AO_RADIUS {float(torch.tensor(radius, dtype=torch.float32))!r}" in source
    for line in ("uniform sampler2D uPosition;", "uniform sampler2D uNormal;", "uniform sampler2D uBackfaceDepth;",
                 "uniform mat4 uProjection;", "uniform vec2 uResolution;", "layout(location = 0) out vec4 fragColor;",
                 "#define AO_FETCH 2", "#define AO_UNION_EXACT 1", "#define AO_THICKNESS_MODEL 2", "#define AO_SLICES 3"):
        assert line in source, line
    assert "denoiser is not part of this pass" in source
    # the back-face layer is declared only for the back-face model
    assert "uBackfaceDepth" not in export_shader(params_file("default", tmp_path), "glsl")


# ------------------------------------------------------------------------------------------------ the command
def test_export_command_writes_the_shader(tmp_path, capsys):
    out = tmp_path / "ao.hlsl"
    assert main(["export", str(params_file("gtao", tmp_path)), "--format", "hlsl", "--out", str(out)]) == 0
    text = out.read_text()
    assert "float4 main(float4 fragCoord : SV_Position) : SV_Target0" in text and "#define AO_METHOD 2" in text
    assert f"-> {out} (hlsl; denoiser excluded)" in capsys.readouterr().out


@pytest.mark.parametrize("method, options, message", [
    ("hbao", {"preset": "high"}, "method: 'hbao' is not exported (bitmask and gtao are)"),
    ("bitmask", {"preset": "high", "variant": "hdrp"}, "variant: bitmask AO's 'hdrp' variant is not exported (default and exact are)"),
    ("gtao", {"preset": "high", "variant": "ue4"}, "variant: GTAO's 'ue4' variant is not exported (exact is)"),
    ("gtao", {"preset": "high@half"}, "resolution: the exported pass walks the full-resolution frame (got 'half')"),
    ("bitmask", {"preset": "high", "thickness": {"shape": [3], "values": [0.1, 0.2, 0.3]}},
     "thickness_model: ObjectThickness is not exported (scalar, linear and backface are)"),
    ("ssilvb", {"preset": "high"}, "method: 'ssilvb' is not exported (bitmask and gtao are)"),
    ("bitmask", {"preset": "high", "noise": "hilbert_r2"},
     "noise: the exported pass jitters by interleaved gradient noise (got 'hilbert_r2')"),
    ("gtao", {"preset": "high", "slice_sampling": "projected_normal"}, "slice_sampling: the exported pass walks "
     "evenly spaced slices (got slice_sampling='projected_normal')"),
])
def test_export_refuses_what_it_cannot_express(method, options, message, tmp_path, capsys):
    params = tmp_path / "params.json"
    FittedPipeline(method, options).save(params)
    out = tmp_path / "ao.frag"
    assert main(["export", str(params), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == f"torch-ao export: error: {params}: {message}\n"
    assert not out.exists()


if __name__ == "__main__" and len(sys.argv) >= 3 and sys.argv[1] == "--render":
    _render(sys.argv[2], sys.argv[3:])
