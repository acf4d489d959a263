"""Buffers derived from a G-buffer (safe depth, positions, view normals, the denoiser's guide) are
computed once per G-buffer and reused, equal to a fresh computation; while a G-buffer tensor needs
gradients they are recomputed at every call, so each forward pass builds its own graph."""
from __future__ import annotations

import torch

from torch_ao.denoise import denoise_guide
from torch_ao.examples import crease_gbuffer
from torch_ao.gbuffer import GBuffer, normals_from_depth


def _depth_only(gb: GBuffer, requires_grad: bool = False) -> GBuffer:
    depth = gb.depth.clone().requires_grad_(requires_grad)
    return GBuffer(depth=depth, camera=gb.camera)


def test_derived_buffers_are_computed_once_and_equal_fresh_ones():
    gb = _depth_only(crease_gbuffer(24, 32))
    fresh = GBuffer(depth=gb.depth.clone(), camera=gb.camera)
    for get in (lambda g: g.safe_depth, lambda g: g.positions(), lambda g: g.view_normals(),
                lambda g: g.view_normals("kornia"), lambda g: denoise_guide(g)):
        first = get(gb)
        assert get(gb) is first
        assert torch.equal(first, get(GBuffer(depth=fresh.depth.clone(), camera=fresh.camera)))
    assert torch.equal(gb.view_normals(), normals_from_depth(gb.depth, gb.camera, valid=gb.valid))
    assert not torch.equal(gb.view_normals("kornia"), gb.view_normals())  # one entry per method
    normals = torch.nn.functional.normalize(torch.randn(1, 3, 24, 32), dim=1)
    assert not torch.equal(denoise_guide(gb, normals=normals), denoise_guide(gb))  # given normals: not cached


def test_buffers_needing_gradients_are_recomputed_each_call():
    gb = _depth_only(crease_gbuffer(24, 32), requires_grad=True)
    a, b = gb.view_normals(), gb.view_normals()
    assert a is not b and a.requires_grad
    assert torch.equal(a, b)
    for _ in range(2):  # a second forward's graph is its own: backward twice works
        (gb.positions().sum() + denoise_guide(gb).sum()).backward()
    assert gb.depth.grad is not None and bool(torch.isfinite(gb.depth.grad).all())


def test_one_call_computes_them_once_with_gradients_and_drops_them(monkeypatch):
    """Within a method's call (GBuffer.one_call) the positions are unprojected once even while the depth needs
    gradients (the normals from depth and the walk read the same), the gradients are those of a call without the
    cache, and the next call builds its own graph."""
    import contextlib

    import torch_ao
    from torch_ao.camera import PinholeCamera

    calls = []
    unproject = PinholeCamera.unproject
    monkeypatch.setattr(PinholeCamera, "unproject", lambda self, d: calls.append(1) or unproject(self, d))
    gb = _depth_only(crease_gbuffer(24, 32), requires_grad=True)
    with gb.one_call():
        a, b = gb.positions(), gb.positions()
        assert a is b and a.requires_grad
    assert gb.positions() is not a  # dropped at the end

    def gradient(backend):
        calls.clear()
        gb.depth.grad = None
        torch_ao.GTAO(slices=2, steps=3, backend=backend)(gb).visibility.sum().backward()
        return len(calls), gb.depth.grad.clone()

    for backend in ("kernel", "torch"):
        (once, cached), (twice, _) = gradient(backend), gradient(backend)  # (a second call: a graph of its own)
        assert once == twice == 1, backend
        with monkeypatch.context() as m:
            m.setattr(GBuffer, "one_call", lambda self: contextlib.nullcontext(self))
            uncached_calls, uncached = gradient(backend)
        assert uncached_calls > 1  # (without it, each reader unprojects again)
        scale = float(cached.abs().max())  # (float32: the two orders of summing the gradients round apart)
        assert scale > 0 and float((cached - uncached).abs().max()) <= 1e-6 * scale, backend
