"""The optional NVIDIA Warp mesh path (``mesh_backend="warp"``, PyPI ``warp-lang``): the same hits as
the torch and Embree paths, AO within Monte Carlo noise, back-face depth, a clear error without it,
and (where CUDA is available) the same render on the GPU."""
from __future__ import annotations

import pytest
import torch

from test_reference import _judge, _small_mesh_scene
from torch_ao.reference import Mesh, Scene, Tracer, embree_available, icosphere, look_at, render_reference

KW = dict(height=27, width=48, spp=32, max_distance=0.8, seed=5, progress=False)


def test_missing_warp_names_the_package(monkeypatch):
    import torch_ao.reference.warp_mesh as wm

    monkeypatch.setattr(wm, "wp", None)
    with pytest.raises(ImportError, match="warp-lang"):
        Tracer(_small_mesh_scene(), mesh_backend="warp")


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="mesh_backend: expected one of"):
        Tracer(_small_mesh_scene(), mesh_backend="optix")


@pytest.fixture(scope="module")
def warp():
    return pytest.importorskip("warp", reason="warp-lang is not installed (pip install -e '.[warp]')")


def test_warp_hits_match_the_torch_path(warp):
    scene = _small_mesh_scene()
    g = torch.Generator().manual_seed(1)
    o = torch.rand(4096, 3, generator=g) * torch.tensor([2.4, 0.8, 1.6]) - torch.tensor([1.2, 0.0, 0.8])
    d = torch.nn.functional.normalize(torch.randn(4096, 3, generator=g), dim=-1)
    a, b = Tracer(scene, mesh_backend="torch"), Tracer(scene, mesh_backend="warp")
    ha, hb = a.intersect(o, d, 0.7), b.intersect(o, d, 0.7)
    same = ha.obj == hb.obj
    assert same.double().mean() > 0.998 and ha.hit.double().mean() > 0.2
    both = same & ha.hit
    assert torch.allclose(ha.t[both], hb.t[both], rtol=1e-4, atol=1e-5)
    assert torch.allclose((ha.normal[both] * hb.normal[both]).sum(-1).abs(), torch.ones(()), atol=1e-4)
    agree = a.occluded(o, d, 0.7) == b.occluded(o, d, 0.7)
    assert agree.double().mean() > 0.998


def test_warp_render_agrees_within_monte_carlo_noise(warp):
    ref = "embree" if embree_available() else "torch"
    a = render_reference(_small_mesh_scene(), mesh_backend="warp", **KW)
    b = render_reference(_small_mesh_scene(), mesh_backend=ref, **KW)
    same = a.gbuffer.object_id == b.gbuffer.object_id
    assert same.double().mean() > 0.995
    v = a.gbuffer.valid & b.gbuffer.valid & same
    assert torch.allclose(a.gbuffer.depth[v], b.gbuffer.depth[v], rtol=1e-4)
    se = (a.ao_stderr.pow(2) + b.ao_stderr.pow(2)).sqrt()
    _judge(a.ao[v], se[v], b.ao[v].double(), KW["spp"])
    mesh_px = (a.gbuffer.object_id == 2) & v
    assert mesh_px.sum() > 50 and float(a.ao[mesh_px].mean()) < 0.95


def test_warp_backface_depth_matches_the_torch_path(warp):
    v, f = icosphere(2, radius=0.8)
    views = look_at((0.3, 0.4, 3.0), (0, 0, 0), fov_y_degrees=40, height=24, width=32)
    kw = dict(spp=2, uniform=False, backface=True, progress=False)
    a = render_reference(Scene([Mesh(vertices=v, faces=f)]), views, mesh_backend="torch", **kw)
    b = render_reference(Scene([Mesh(vertices=v, faces=f)]), views, mesh_backend="warp", **kw)
    both = a.gbuffer.valid & b.gbuffer.valid
    assert both.sum() > 100
    thickness = (b.backface_depth - b.gbuffer.depth)[both]
    assert bool((thickness > 0).all())
    assert torch.allclose(a.backface_depth[both], b.backface_depth[both], rtol=1e-4, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_warp_on_cuda_matches_the_cpu_render(warp):
    a = render_reference(_small_mesh_scene(), device="cuda", **KW)  # auto: Warp on CUDA
    b = render_reference(_small_mesh_scene(), mesh_backend="embree" if embree_available() else "torch", **KW)
    v = a.gbuffer.valid.cpu() & b.gbuffer.valid & (a.gbuffer.object_id.cpu() == b.gbuffer.object_id)
    assert v.double().mean() > 0.5
    assert torch.allclose(a.gbuffer.depth.cpu()[v], b.gbuffer.depth[v], rtol=1e-4)
    se = (a.ao_stderr.cpu().pow(2) + b.ao_stderr.pow(2)).sqrt()
    _judge(a.ao.cpu()[v], se[v], b.ao[v].double(), KW["spp"])
