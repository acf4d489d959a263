"""How a kernel's outputs must agree with the tensor-op walk (the specification), by tolerance.

The kernels compute the walk in their own float arithmetic (SIMD SLEEF functions, or the scalar libm
ones of the CUDA build's lanes): an angle within rounding of a sector edge can fall into the next
sector, and a horizon comparison can flip. So hard masks are identical on all but a few pixels, and
never more than one sector of one slice apart; continuous outputs agree to float rounding on all but
the pixels where such a decision flipped.
"""
import torch

#: the share of valid pixels on which the outputs must be identical (masks) or within ATOL (values)
SHARE = 0.999
ATOL = 1e-5


def _per_pixel(out: torch.Tensor, ref: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    assert out.shape == ref.shape and out.dtype == ref.dtype, (out.shape, ref.shape, out.dtype, ref.dtype)
    assert torch.isfinite(out).all()
    return (out - ref).abs().amax(1, keepdim=True)[valid]


def degenerate(options: dict) -> bool:
    """Whether ``options`` take no margin off the sector intervals (``sector_epsilon=0``): then a sample on
    the pixel's own plane gives an interval of zero width give or take rounding, which ``ceil`` makes zero
    or one sector, on each side. On planar frames both paths then decide by their rounding, so only the
    bound holds (one sector per side of each slice: ``2 * slices`` sectors in all)."""
    return options.get("sector_epsilon", 0.01) == 0


def assert_masks_agree(out: torch.Tensor, ref: torch.Tensor, valid: torch.Tensor, slices: int,
                       share: float = SHARE, sectors: int = 1) -> None:
    """Uniform hard visibility ``(B,1,H,W)``: identical on >= ``share`` of the valid pixels, and never more
    than ``sectors`` sectors of one slice (``sectors / (32 slices)``) apart; background identical."""
    d = _per_pixel(out, ref, valid)
    assert (d == 0).float().mean() >= share, (d > 0).sum()
    assert d.max() <= sectors / (32 * slices) + 1e-6, d.max()
    assert torch.equal(out[~valid.expand_as(out)], ref[~valid.expand_as(ref)])


def assert_values_agree(out: torch.Tensor, ref: torch.Tensor, valid: torch.Tensor, *, atol: float = ATOL,
                        bound: float = 1.0, share: float = SHARE) -> None:
    """Continuous outputs ``(B,C,H,W)``: within ``atol`` on >= SHARE of the valid pixels, within ``bound``
    everywhere (one flipped decision), and equal to float rounding on the background."""
    d = _per_pixel(out, ref, valid)
    assert (d <= atol).float().mean() >= share, ((d > atol).sum(), d.max())
    assert d.max() <= bound, d.max()
    background = ~valid.expand_as(out)
    assert torch.allclose(out[background], ref[background], atol=1e-6)


def position_gradients(gb0, loss) -> list[torch.Tensor]:
    """The gradients (float64) of ``loss(gbuffer, dtype, backend)`` with respect to a position buffer made of
    ``gb0``'s positions: the tensor path's in float64 (``backend="torch"``), then the kernel's in float32
    (``"kernel"``)."""
    from torch_ao.gbuffer import GBuffer

    grads = []
    for dtype, backend in ((torch.float64, "torch"), (torch.float32, "kernel")):
        g = gb0.to(dtype=dtype)
        position = g.positions().detach().clone().requires_grad_()
        gb = GBuffer(g.depth, position=position, normals=g.view_normals().detach(), camera=g.camera)
        (grad,) = torch.autograd.grad(loss(gb, dtype, backend), [position])
        grads.append(grad.double())
    return grads


def relative_error(a: torch.Tensor, b: torch.Tensor, trim: float = 0.0) -> float:
    """``|a - b| / |b|`` over ``b``'s finite entries, without the fraction ``trim`` of them that differ most."""
    finite = torch.isfinite(b)
    diff = (a - b)[finite].abs().flatten()
    if trim:
        diff = diff.sort().values[:len(diff) - int(trim * len(diff))]
    return float(diff.norm() / b[finite].norm().clamp_min(1e-30))


def use_scalar_lanes(monkeypatch, module) -> None:
    """``module``'s kernels (a :mod:`torch_ao.kernels` module with ``scalar_lanes``) walk in scalar lanes: the
    CUDA thread's body, on the CPU."""
    monkeypatch.setattr(module, "scalar_lanes", lambda lanes: True)


def use_scalar_lanes_in_every_kernel(monkeypatch) -> None:
    """:func:`use_scalar_lanes` for every kernel module a module's call may reach (the forwards' and the
    backwards')."""
    from torch_ao.kernels import bitmask, launch, soft_bitmask, soft_exact, walk_grad

    for module in (bitmask, launch, soft_bitmask, soft_exact, walk_grad):
        use_scalar_lanes(monkeypatch, module)


def central_differences(loss, base: torch.Tensor, indices, eps: float = 1e-6) -> torch.Tensor:
    """``d loss / d base`` (float64, flat) by central differences at the flat ``indices`` (0 elsewhere);
    ``loss(x)`` takes ``x`` shaped as ``base``."""
    flat = base.detach().double().flatten()
    numeric = torch.zeros_like(flat)
    for i in indices:
        step = torch.zeros_like(flat)
        step[i] = eps
        numeric[i] = (loss((flat + step).view_as(base)) - loss((flat - step).view_as(base))) / (2 * eps)
    return numeric


def assert_directional_derivatives(grads, base, forward, directions, eps: float = 1e-7, count: int = 4) -> None:
    """The kernel's ``grads`` (of a loss at the float64 leaves ``base``) along ``count`` random directions
    (``directions()``: one tensor per leaf) against central differences of the float64 ``forward(*leaves)``:
    within 1e-4 of the sum of the terms' magnitudes."""
    for _ in range(count):
        us = directions()
        with torch.no_grad():
            numerical = float(forward(*(b + eps * u for b, u in zip(base, us)))
                              - forward(*(b - eps * u for b, u in zip(base, us)))) / (2 * eps)
        terms = torch.cat([(g.double() * u)[torch.isfinite(g)].flatten() for g, u in zip(grads, us)])
        assert abs(numerical) > 1e-2
        assert abs(float(terms.sum()) - numerical) <= 1e-4 * float(terms.abs().sum()), (float(terms.sum()), numerical)


def assert_hard_gradients_agree(depth: torch.Tensor, normals: torch.Tensor, ref_depth: torch.Tensor,
                                ref_normals: torch.Tensor) -> None:
    """Hard masks' gradients, which come through the slice: the normals' within 1e-4 relative of the reference's;
    the depth's zero up to rounding in both (scaling a pixel's depth moves it along its own ray)."""
    assert ref_normals.abs().sum() > 0 and relative_error(normals, ref_normals) <= 1e-4, relative_error(normals, ref_normals)
    scale = float(ref_normals.norm())
    assert float(ref_depth[torch.isfinite(ref_depth)].norm()) <= 1e-9 * scale
    assert float(depth[torch.isfinite(depth)].norm()) <= 1e-5 * scale


def upstream_weights(out: torch.Tensor) -> torch.Tensor:
    """A fixed upstream gradient that is not uniform (every pixel and channel weighs differently)."""
    return torch.linspace(0.5, 1.5, out.numel(), dtype=out.dtype).view_as(out)


def assert_depth_gradient_matches_central_differences(make, gb, normals: torch.Tensor, every: int) -> None:
    """The kernel's float32 gradient of the weighted visibility (:func:`upstream_weights`) of ``make(backend)``'s
    module on ``gb`` with the normals given, to depth, against central differences (1e-6) of the tensor path's
    float64 forward at every ``every``-th finite pixel."""
    import dataclasses

    from torch_ao.gbuffer import GBuffer

    def loss(depth, backend):
        camera = dataclasses.replace(gb.camera, intrinsics=gb.camera.intrinsics.to(depth.dtype))
        out = make(backend)(GBuffer(depth=depth, normals=normals.to(depth.dtype), camera=camera)).visibility.double()
        return (out * upstream_weights(out)).sum()

    depth = gb.depth.detach().clone().requires_grad_(True)
    analytic = torch.autograd.grad(loss(depth, "kernel"), depth)[0].double().flatten()
    checked = torch.nonzero(torch.isfinite(gb.depth.flatten())).flatten()[::every]
    numeric = central_differences(lambda x: loss(x, "torch"), gb.depth, checked.tolist())
    assert numeric.abs().max() > 0.1
    torch.testing.assert_close(analytic[checked], numeric[checked], rtol=1e-3, atol=1e-4)
