"""The walk's sampling options: the Hilbert-indexed R2 noise (``noise="hilbert_r2"``), the projected-normal slice
density (``slice_sampling="projected_normal"``) and the staggered step offsets (``stagger=True``): their
properties in closed form, and that the estimators keep their limit (the screen-space truth)."""
import math

import pytest
import torch

from torch_ao import GTAO, HBAO, BitmaskAO
from torch_ao.examples import floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.reference import get_scene, render_reference
from torch_ao.screen_truth import screen_space_truth
from torch_ao.walk import (Queries, SlicePattern, hilbert_index, hilbert_r2_noise, interleaved_gradient_noise,
                           projected_normal_azimuths, unoccluded_slice_integral)
from torch_ao.walk.frame import Frame


def _grid(size=64):
    v, u = torch.meshgrid(torch.arange(float(size)), torch.arange(float(size)), indexing="ij")
    return u.flatten(), v.flatten()


def test_hilbert_index_walks_the_64x64_tile_one_neighbour_at_a_time():
    u, v = _grid()
    index = hilbert_index(u, v)
    assert torch.equal(torch.sort(index).values, torch.arange(4096))  # a bijection of the tile
    order = torch.argsort(index)
    steps = (u[order].diff().abs() + v[order].diff().abs())
    assert torch.all(steps == 1)  # consecutive indices are 4-neighbours
    assert torch.equal(hilbert_index(u + 64, v - 128), index)  # it tiles the screen


def _blocks(values: torch.Tensor) -> torch.Tensor:
    """``(64, 64)``: the 64 aligned 8x8 blocks of a 64x64 image given flat, row-major."""
    return values.float().view(8, 8, 8, 8).permute(0, 2, 1, 3).reshape(64, 64)


def test_r2_noise_is_stratified_over_every_aligned_8x8_block():
    # an aligned 8x8 block is 64 consecutive Hilbert indices: 64 consecutive R2 points. Each value falls
    # 8 +- 2 times into each eighth of [0, 1); the pairs (slice rotation, step offset) 4 +- 2 times into
    # each of the 4x4 cells of the unit square, where IGN's two values leave cells empty
    u, v = _grid()
    a, b = hilbert_r2_noise(u, v, seed=5)
    for values in (a, b):
        counts = torch.stack([torch.histc(x, bins=8, min=0.0, max=1.0) for x in _blocks(values)])
        assert counts.min() >= 6 and counts.max() <= 10

    def cells(a, b):
        cell = (_blocks(a) * 4).long() * 4 + (_blocks(b) * 4).long()
        return torch.stack([torch.bincount(c, minlength=16) for c in cell])

    r2 = cells(a, b)
    assert r2.min() >= 2 and r2.max() <= 6
    ign = cells(interleaved_gradient_noise(u, v), interleaved_gradient_noise(u + 37, v + 59, 1))
    assert ign.min() == 0 and ign.max() >= 12


def _corr(x: torch.Tensor, y: torch.Tensor) -> float:
    x, y = x.flatten() - x.mean(), y.flatten() - y.mean()
    return float((x * y).sum() / (x.norm() * y.norm()))


def test_r2_noise_decorrelates_its_two_values_and_neighbours():
    u, v = _grid()
    a, b = (x.view(64, 64) for x in hilbert_r2_noise(u, v))
    i, j = (x.view(64, 64) for x in (interleaved_gradient_noise(u, v), interleaved_gradient_noise(u + 37, v + 59, 1)))
    # IGN's step offset is its slice rotation shifted by a constant phase: the two are coupled; R2's are not
    assert abs(_corr(a, b)) < 0.01
    assert abs(_corr(i, j)) > 0.4
    for x, y in ((a, i), (b, j)):  # neighbours (horizontal, vertical, diagonal): weaker than IGN's
        for shifted in (lambda t: (t[:, 1:], t[:, :-1]), lambda t: (t[1:], t[:-1]), lambda t: (t[1:, 1:], t[:-1, :-1])):
            assert abs(_corr(*shifted(x))) < 0.3
        assert max(abs(_corr(x[:, 1:], x[:, :-1])), abs(_corr(x[1:], x[:-1]))) < abs(_corr(y[:, 1:], y[:, :-1]))
    assert float(a.min()) >= 0 and float(a.max()) < 1
    assert not torch.equal(hilbert_r2_noise(u, v, seed=1)[0], hilbert_r2_noise(u, v, seed=0)[0])


def _queries(normal: torch.Tensor, n: int) -> Queries:
    """``n`` queries on the optical axis (V = +z, P = (0, 0, -2)) with the same ``normal``."""
    zeros = torch.zeros(n, dtype=torch.long)
    return Queries(zeros, zeros, zeros.double(), zeros.double(), torch.tensor([0.0, 0.0, -2.0]).double().expand(n, 3),
                   normal.expand(n, 3), torch.tensor([0.0, 0.0, 1.0]).double().expand(n, 3), zeros.double() + 2)


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.8, 0.0, 0.6), (0.3, -0.9, math.sqrt(1 - 0.9)), (0.0, 0.999, 0.0447)])
def test_projected_normal_density_and_weights_integrate_exactly(normal):
    n = torch.tensor(normal, dtype=torch.float64)
    n = n / n.norm()
    u = (torch.arange(20000, dtype=torch.float64) + 0.5) / 20000
    q = _queries(n, len(u))
    psi, weight = projected_normal_azimuths(q, u)
    assert float(psi.min()) >= 0 and float(psi.max()) <= math.pi
    # E_u[weight f(psi)] = (1/pi) int_0^pi f: the weighted estimator keeps the uniform slices' integral
    for f in (lambda p: torch.ones_like(p), lambda p: torch.cos(p) ** 2, lambda p: torch.sin(3 * p) + 1):
        grid = (torch.arange(20000, dtype=torch.float64) + 0.5) * math.pi / 20000
        assert float((weight * f(psi)).mean()) == pytest.approx(float(f(grid).mean()), abs=2e-3)
    # the density follows GTAO's unoccluded slice integral (mean 1 over uniform azimuths): the unoccluded
    # integral times the weight is 1 but for the tabulation's bins (within 10 %; within a factor 2 for a
    # grazing normal, whose integral nearly vanishes across it)
    e1 = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # view_basis for V = +z: e1 = +Y x V
    e2 = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    free = unoccluded_slice_integral(n[2].expand_as(psi), torch.cos(psi) * (n @ e1) + torch.sin(psi) * (n @ e2))
    assert float(free.mean()) > 0
    grid = (torch.arange(4096, dtype=torch.float64) + 0.5) * math.pi / 4096
    uniform_free = unoccluded_slice_integral(n[2].expand_as(grid), torch.cos(grid) * (n @ e1) + torch.sin(grid) * (n @ e2))
    assert float(uniform_free.mean()) == pytest.approx(1.0, abs=1e-4)
    ratio = free.clamp_min(1e-4) * weight
    spread = (0.9, 1.1) if float(n[2]) > 0.5 else (0.5, 2.0)
    assert spread[0] < float(ratio.min()) and float(ratio.max()) < spread[1]


def test_stagger_spreads_the_half_slices_over_distinct_distances():
    gb = floor_wall_gbuffer(16, 16)[0]
    frame = Frame(gb, gb.view_normals())
    q = frame.queries
    from torch_ao.walk.walk import slice_geometry

    for stagger, distinct in ((False, 3), (True, 2 * 3 * 3)):
        pattern = SlicePattern(3, 3, 1.0, jitter=False, stagger=stagger)
        dists = []
        for s in range(3):
            geom = slice_geometry(frame, q, pattern, s)
            span = (pattern.radius_px(geom) - 1.0).clamp_min(0)
            for side in (1, -1):
                for off in pattern.step_offsets(q, geom, side):
                    dists.append((off.norm(dim=-1) - 1.0) / span)  # fraction of the span, per pixel
        fractions = torch.stack(dists, -1)[0]  # one pixel
        values = torch.sort(torch.unique(torch.round(fractions * 1e5) / 1e5)).values
        assert len(values) == distinct
        if stagger:  # evenly spaced by 1 / (2 slices steps)
            assert torch.allclose(values.diff(), torch.full_like(values.diff(), 1 / 18), atol=1e-4)


def test_options_needing_view_azimuth_slices_are_refused_by_name():
    with pytest.raises(ValueError, match="slice_sampling"):
        GTAO(slice_sampling="projected_normal", azimuth="screen")
    with pytest.raises(ValueError, match="slice_sampling"):
        HBAO(slice_sampling="projected_normal")  # a full circle of directions
    with pytest.raises(ValueError, match="noise"):
        GTAO(noise="blue")


@pytest.fixture(scope="module")
def fence():
    ref = render_reference(get_scene("fence"), height=24, width=32, spp=16, max_distance=0.5, progress=False,
                           uniform=False)
    return ref.gbuffer, screen_space_truth(ref.gbuffer, 0.5, 0.25, rays=1024, fetch="edge_aware")


@pytest.mark.slow
def test_projected_normal_slices_converge_to_the_screen_space_truth(fence):
    gb, truth = fence
    valid = gb.valid
    mae = {}
    for sampling in ("uniform", "projected_normal"):
        for slices in (2, 32):
            with torch.no_grad():
                vis = BitmaskAO(variant="exact", slices=slices, steps=32, radius=0.5, thickness=0.25,
                                slice_sampling=sampling)(gb).visibility
            mae[sampling, slices] = float((vis - truth.visibility)[valid].abs().mean())
    print(mae)
    # the exact variant's limit is the truth (tests/test_bitmask_convergence.py): both densities reach it
    assert mae["projected_normal", 32] < 0.006
    assert mae["projected_normal", 32] < 0.5 * mae["projected_normal", 2]
    assert abs(mae["projected_normal", 32] - mae["uniform", 32]) < 0.003


def test_the_kernels_cover_noise_stagger_and_projected_normal_slices():
    from torch_ao.kernels import gtao_covers, kernel_covers

    gb = floor_wall_gbuffer(16, 16)[0]
    assert kernel_covers(BitmaskAO(noise="hilbert_r2", stagger=True), gb) is None
    assert gtao_covers(GTAO(noise="hilbert_r2", stagger=True), gb) is None
    assert kernel_covers(BitmaskAO(slice_sampling="projected_normal"), gb) is None
    graded = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera)
    assert kernel_covers(BitmaskAO(slice_sampling="projected_normal"), graded) is None  # (the weights' gradients)
    assert gtao_covers(GTAO(slice_sampling="projected_normal"), gb) is None
