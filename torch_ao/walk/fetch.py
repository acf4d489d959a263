"""The depth fetch: where a sample reads the frame (:class:`Footprint`), and its hand-written backwards.

A sample reads either the nearest texel or four bilinear taps whose inverse depths are interpolated
(perspective-correct: planes are reproduced exactly), or, with the ``"edge_aware"`` fetch, the four taps
where the 2x2 cell holding the sample is one surface (:func:`continuous_cell_image`) and the nearest
texel's depth elsewhere: bilinear interpolation across a depth edge invents a surface (a "skirt") joining
the near and the far side, which a thick occluder model turns into occlusion that is not there (the
screen-space truth's ``edge_aware`` uses the same rule). The walk fetches ``slices x sides x steps``
samples per pixel, so the autograd functions keep a few floats per sample and rebuild the rest in
backward: :class:`PerspectiveBilinearDepth` here (the depth alone) and ``sample.SampleAlong`` (the two
in-slice coordinates of ``delta``, fused with the fetch).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..camera import pixels_to_view
from .frame import Frame, repeat_rows, take

__all__ = ["Footprint", "PerspectiveBilinearDepth", "GradientRows", "bilerp", "bilinear_taps",
           "EDGE_MIN_RATIO", "EDGE_SLOPE_TOLERANCE", "NEAREST_TIE", "continuous_cells", "continuous_cell_image", "cell_flags", "edge_aware_taps"]

#: The nearest texel of a screen coordinate ``x`` is ``floor(x + 0.5 - NEAREST_TIE)``: a coordinate within 1/512
#: texel above a tie between two texels (half of a GPU's 1/256 sub-texel step) reads the lower one. Slices at
#: round angles with whole-pixel steps (no jitter) put samples on exact ties, where an ulp of rounding in the
#: step's direction would pick the texel; shifted off the tie, every backend picks the same one.
NEAREST_TIE = 1.0 / 512.0
#: The ``"edge_aware"`` fetch: two neighbouring texels whose depths are within this ratio are one surface
#: whatever their neighbours (the smallest steps, e.g. a plank's edge on the floor behind it, are edges).
EDGE_MIN_RATIO = 1.02
#: ... and a larger jump in inverse depth between them is one surface when it lies within the range of the
#: jumps of the pairs beside it (one or two) widened by this fraction of itself: inverse depth is affine in
#: screen space across a plane, so a plane at any angle has equal jumps, a crease one between its two
#: sides', and a depth step (a slat before a wall, a pole before the floor) one larger than both. A pair with
#: no valid pair beside it along its row is matched, within the same fraction, to the parallel pair next to it.
EDGE_SLOPE_TOLERANCE = 0.5


def continuous_cells(inverse: torch.Tensor, edge_ratio) -> torch.Tensor:
    """``(...)`` bool: whether all four texels of a 2x2 cell with inverse depths ``inverse`` ``(..., 4)``
    (``<= 0`` where a texel is invalid) are valid and ``max(depth) <= edge_ratio * min(depth)`` (a float, or a
    tensor broadcasting to ``(...)``): the ratio rule alone, without the neighbours of
    :func:`continuous_cell_image`."""
    lo, hi = inverse.amin(-1), inverse.amax(-1)
    return (lo > 0) & (hi <= edge_ratio * lo)


def _shifted(x: torch.Tensor, by: int, dim: int, fill) -> torch.Tensor:
    """``x`` moved ``by`` (+1 or -1) along ``dim``: ``out[k] = x[k - by]``, ``fill`` where that is outside."""
    pad = torch.full_like(x.narrow(dim, 0, 1), fill)
    n = x.shape[dim]
    if by > 0:
        return torch.cat((pad, x.narrow(dim, 0, n - 1)), dim)
    return torch.cat((x.narrow(dim, 1, n - 1), pad), dim)


def _continuous_pairs(inv: torch.Tensor) -> torch.Tensor:
    """``(..., H, W-1)`` bool: whether each pair of neighbours ``(k, k+1)`` along the last axis of ``inv``
    ``(..., H, W)`` (inverse depths, ``<= 0`` where invalid) is one surface: both valid, and within
    :data:`EDGE_MIN_RATIO`, or its jump within the range of the valid neighbouring pairs' jumps along the
    row widened by :data:`EDGE_SLOPE_TOLERANCE` of itself; a pair with no valid neighbour along its row (a
    plane's corner at its horizon) when its jump is within that tolerance of the same columns' pair in the
    row above or below (inverse depth is affine on a plane, so its jump along a row is the same in every
    row)."""
    a, b = inv[..., :-1], inv[..., 1:]
    both = (a > 0) & (b > 0)
    near = torch.maximum(a, b) <= EDGE_MIN_RATIO * torch.minimum(a, b)
    jump = b - a
    has_before, before = _shifted(both, 1, -1, False), _shifted(jump, 1, -1, 0.0)
    has_after, after = _shifted(both, -1, -1, False), _shifted(jump, -1, -1, 0.0)
    # the range of the neighbours' jumps (one of them where the other is missing)
    lo = torch.where(has_before & has_after, torch.minimum(before, after), torch.where(has_before, before, after))
    hi = torch.where(has_before & has_after, torch.maximum(before, after), torch.where(has_before, before, after))
    tol = EDGE_SLOPE_TOLERANCE * jump.abs()
    follows = (has_before | has_after) & (jump >= lo - tol) & (jump <= hi + tol)
    if inv.dim() >= 2 and inv.shape[-2] > 1:
        alone = both & ~(has_before | has_after)
        for by in (1, -1):
            parallel = _shifted(both, by, -2, False) & ((_shifted(jump, by, -2, 0.0) - jump).abs() <= tol)
            follows = follows | (alone & parallel)
    return both & (near | follows)


def continuous_cell_image(inverse: torch.Tensor) -> torch.Tensor:
    """``(..., H-1, W-1)`` bool: whether the 2x2 cell of texels ``(i..i+1, j..j+1)`` of the inverse depths
    ``inverse`` ``(..., H, W)`` (``<= 0`` where invalid) is one surface: its two horizontal and two vertical
    pairs each are (``_continuous_pairs``: within :data:`EDGE_MIN_RATIO`, or continuing a neighbouring pair's
    jump; a pair alone in its row or column, matching the parallel pair beside it). The rule of the ``"edge_aware"`` fetch, in the walk and in the screen-space truth."""
    across = _continuous_pairs(inverse)  # (..., H, W-1)
    down = _continuous_pairs(inverse.transpose(-1, -2)).transpose(-1, -2)  # (..., H-1, W)
    return across[..., :-1, :] & across[..., 1:, :] & down[..., :, :-1] & down[..., :, 1:]


def cell_flags(inverse: torch.Tensor) -> torch.Tensor:
    """``(B, H, W)`` bool, per texel of the inverse depths ``inverse`` ``(B, H, W)`` (``<= 0`` where invalid):
    whether the cell whose top-left texel it is is one surface (:func:`continuous_cell_image`; False on the
    last row and column)."""
    B, H, W = inverse.shape
    with torch.no_grad():
        flags = torch.zeros(B, H, W, dtype=torch.bool, device=inverse.device)
        if H > 1 and W > 1:
            flags[:, :-1, :-1] = continuous_cell_image(inverse)
    return flags


def _cell_flags(frame: Frame) -> torch.Tensor:
    """``(B*H*W,)`` :func:`cell_flags` of the frame, computed once per frame."""
    flags = getattr(frame, "_edge_aware_cells", None)
    if flags is None:
        B, H, W = frame.shape
        # (no graph: the flags have no gradient, and a chunk's recomputation finds them cached, so it must
        # save exactly what the first computation saved)
        with torch.no_grad():
            inverse = torch.where(frame.valid, frame.inverse_depth, 0.0).view(B, H, W)
        frame._edge_aware_cells = flags = cell_flags(inverse).view(-1)
    return flags


def edge_aware_taps(frame: Frame, index: torch.Tensor, fu: torch.Tensor, fv: torch.Tensor) -> torch.Tensor:
    """The ``"edge_aware"`` fetch's taps ``(N,4)``: the bilinear taps ``index`` ``(N,4)`` where their cell is
    one surface (:func:`continuous_cell_image`; a footprint clamped at the image border, whose taps repeat,
    by the ratio rule :func:`continuous_cells` at :data:`EDGE_MIN_RATIO`), else four copies of the tap
    nearest to the fractions ``fu, fv`` ``(N,)`` (interpolating four equal taps reads that texel, and its
    gradient goes to it alone)."""
    proper = (index[:, 1] != index[:, 0]) & (index[:, 2] != index[:, 0])
    smooth = take(_cell_flags(frame), index[:, 0])
    if torch.compiler.is_compiling() or not bool(proper.all()):  # (compiled: no data-dependent branch)
        inverse = torch.where(take(frame.valid, index), take(frame.inverse_depth, index), 0.0).detach()
        smooth = torch.where(proper, smooth, continuous_cells(inverse, EDGE_MIN_RATIO))
    right, down = fu.detach() >= 0.5 + NEAREST_TIE, fv.detach() >= 0.5 + NEAREST_TIE  # (the nearest fetch's ties)
    corner = right.to(index.dtype) + 2 * down.to(index.dtype)
    nearest = index.gather(1, corner[:, None].long())
    return torch.where(smooth[:, None], index, nearest)


def bilerp(taps, fu: torch.Tensor, fv: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of the four taps ``(u0,v0), (u0+1,v0), (u0,v0+1), (u0+1,v0+1)``."""
    t0, t1, t2, t3 = taps
    return torch.lerp(torch.lerp(t0, t1, fu), torch.lerp(t2, t3, fu), fv)


class PerspectiveBilinearDepth(torch.autograd.Function):
    """Perspective-correct bilinear depth ``1 / sum_k w_k(fu, fv) / z_k`` ``(N,)`` at four taps.

    Interpolating ``1/depth`` (affine in screen space across a plane) reproduces planes exactly. The plain
    autograd path of the walk; the fused one (``sample.SampleAlong``) differentiates it by hand too.
    Inputs: ``safe_depth`` ``(P,)`` positive depths of the frame, ``index`` ``(N,4)`` taps into it,
    ``fu, fv`` ``(N,)`` fractional offsets in ``[0,1)``. A custom function because the walk fetches
    ``slices x sides x steps`` samples per pixel: plain autograd would keep the 64-bit tap indices, the
    gathered depths, the weights and their quotients for every sample (about 90 bytes each); this keeps
    32-bit indices, ``fu``, ``fv`` and the result (28 bytes) and gathers the depths again in backward.
    """

    @staticmethod
    def forward(ctx, safe_depth, index, fu, fv):
        depth = bilerp(take(safe_depth, index).reciprocal().unbind(-1), fu, fv).reciprocal()
        small = safe_depth.shape[0] < 2**31  # every tap indexes safe_depth
        ctx.save_for_backward(safe_depth, index.to(torch.int32) if small else index, fu, fv, depth)
        return depth

    @staticmethod
    def backward(ctx, grad):
        safe_depth, index, fu, fv, depth = ctx.saved_tensors
        inverse = take(safe_depth, index).reciprocal()
        # d(1/z_k) = -(1/z_k)^2 dz_k
        g_inverse, grad_fu, grad_fv = _bilerp_depth_backward(inverse, fu, fv, depth, grad)
        grad_depth = None
        if ctx.needs_input_grad[0]:
            contrib = g_inverse.mul_(inverse.square_()).neg_()
            grad_depth = torch.zeros_like(safe_depth).index_add_(0, index.reshape(-1), contrib.view(-1))
        return grad_depth, None, grad_fu, grad_fv


@dataclass
class Footprint:
    """Where a sample reads the frame: the nearest texel (``index`` ``(N,)``) or four bilinear taps
    (``index`` ``(N,4)``, fractions ``fu``, ``fv``) at screen position ``(su, sv)`` ``(N,)``;
    ``batch`` ``(N,)`` is each row's image. ``edge_aware`` is set for the ``"edge_aware"`` fetch: its
    taps are :func:`edge_aware_taps` (four copies of the nearest texel across a depth edge)."""

    batch: torch.Tensor
    su: torch.Tensor
    sv: torch.Tensor
    index: torch.Tensor
    fu: torch.Tensor | None = None
    fv: torch.Tensor | None = None
    edge_aware: bool = False

    @staticmethod
    def at(frame: Frame, batch: torch.Tensor, su: torch.Tensor, sv: torch.Tensor, fetch: str) -> tuple["Footprint", torch.Tensor]:
        """The footprint of screen positions ``(su, sv)`` and whether each lies inside the frame."""
        B, H, W = frame.shape
        base = batch * (H * W)
        if fetch == "nearest":
            iu, iv = torch.floor(su + (0.5 - NEAREST_TIE)).long(), torch.floor(sv + (0.5 - NEAREST_TIE)).long()
            inside = (iu >= 0) & (iu < W) & (iv >= 0) & (iv < H)
            index = iv.clamp(0, H - 1) * W + iu.clamp(0, W - 1)
            return Footprint(batch, su, sv, index if B == 1 else index + base), inside
        index, fu, fv = bilinear_taps(frame, batch, su, sv)
        u0, v0 = torch.floor(su), torch.floor(sv)
        inside = (u0 >= 0) & (u0 + 1 < W) & (v0 >= 0) & (v0 + 1 < H)
        if fetch == "edge_aware":
            return Footprint(batch, su, sv, edge_aware_taps(frame, index, fu, fv), fu, fv, True), inside
        return Footprint(batch, su, sv, index, fu, fv), inside

    def map_rows(self, fn) -> "Footprint":
        """The footprint with ``fn`` applied to every per-row tensor."""
        return Footprint(fn(self.batch), fn(self.su), fn(self.sv), fn(self.index),
                         None if self.fu is None else fn(self.fu), None if self.fv is None else fn(self.fv),
                         self.edge_aware)

    def on_own_texel(self, own: torch.Tensor) -> torch.Tensor:
        """``(N,)`` bool: where the ``"edge_aware"`` fetch reads the nearest texel and it is ``own``
        ``(N,)`` (the query's flat index), as the nearest fetch does on the centre texel (all False for
        other fetches)."""
        if not self.edge_aware:
            return torch.zeros_like(own, dtype=torch.bool)
        return (self.index == self.index[:, :1]).all(-1) & (self.index[:, 0] == own)

    def valid(self, frame: Frame) -> torch.Tensor:
        v = take(frame.valid, self.index)
        return v if self.fu is None else v.all(-1)

    def inputs(self, frame: Frame) -> tuple[torch.Tensor, ...]:
        """The differentiable tensors the position depends on (the frame's positions or depths, ``su``, ``sv``)."""
        if self.fu is None or frame.has_position:
            return (frame.positions, self.su, self.sv)
        return (frame.inverse_depth, self.su, self.sv)

    def fusable(self, frame: Frame) -> bool:
        """Whether ``sample.SampleAlong`` can differentiate the position (camera intrinsics without gradient;
        its bilinear backward is the depth fetch's, so not for bilinear reads of a position buffer)."""
        if self.fu is not None and frame.has_position:
            return False
        return not any(t.requires_grad for t in (frame.fx, frame.fy, frame.cx, frame.cy))

    def position(self, frame: Frame) -> torch.Tensor:
        """``(N,3)`` view-space position: the texel's, or the perspective-correct bilinear depth
        unprojected at ``(su, sv)`` clamped to the frame; with a position buffer, its four taps
        interpolated perspective-correctly (``p / depth`` and ``1 / depth`` bilinearly, then divided),
        which equals the depth fetch where the positions are the unprojected depth (so does the
        ``"edge_aware"`` fetch's nearest texel: its depth, unprojected at ``(su, sv)``)."""
        if self.fu is None:
            return take(frame.positions, self.index)
        if frame.has_position:
            taps = take(frame.positions, self.index)  # (N,4,3)
            inverse = -taps[..., 2].reciprocal()  # (N,4) 1 / depth of each tap (z < 0)
            fu, fv = self.fu[:, None], self.fv[:, None]
            scaled = bilerp((taps * inverse[..., None]).unbind(1), fu, fv)
            position = scaled / bilerp(inverse.unbind(-1), self.fu, self.fv)[:, None]
            if not self.edge_aware:
                return position
            # four equal taps interpolate to the texel's own position; the depth fetch puts its depth at (su, sv)
            single = (self.index == self.index[:, :1]).all(-1)
            tile = _unproject(frame, self.batch, self.su, self.sv, -taps[:, 0, 2])
            return torch.where(single[:, None], tile, position)
        if torch.is_grad_enabled():
            depth = PerspectiveBilinearDepth.apply(frame.safe_depth, self.index, self.fu, self.fv)
        else:  # the same values, from the frame's inverse depths
            depth = bilerp(take(frame.inverse_depth, self.index).unbind(-1), self.fu, self.fv).reciprocal()
        return _unproject(frame, self.batch, self.su, self.sv, depth)


def bilinear_taps(frame: Frame, batch: torch.Tensor, su: torch.Tensor, sv: torch.Tensor):
    """Four taps ``(N,4)`` (``(u0,v0), (u0+1,v0), (u0,v0+1), (u0+1,v0+1)``, clamped to the frame) around
    screen positions ``(su, sv)`` ``(N,)`` and the fractions ``fu, fv`` ``(N,)``."""
    B, H, W = frame.shape
    u0, v0 = torch.floor(su.detach()), torch.floor(sv.detach())  # (floor has no gradient)
    fu, fv = su - u0, sv - v0
    # 32-bit index arithmetic (3x faster) where it cannot overflow; the clamp to [-1, size] first is exact.
    itype = torch.int32 if B * H * W < 2**31 - 1 else torch.int64
    u0, v0 = u0.clamp(-1, W).to(itype), v0.clamp(-1, H).to(itype)
    c0, c1 = u0.clamp(0, W - 1), u0.add_(1).clamp_(0, W - 1)
    r0, r1 = v0.clamp(0, H - 1).mul_(W), v0.add_(1).clamp_(0, H - 1).mul_(W)
    if B > 1:
        base = batch.to(itype) * (H * W)
        r0, r1 = r0.add_(base), r1.add_(base)
    return torch.stack((r0 + c0, r0 + c1, r1 + c0, r1 + c1), -1), fu, fv


def _unproject(frame: Frame, batch: torch.Tensor, su: torch.Tensor, sv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """``(N,3)`` view-space points at screen ``(su, sv)`` (clamped to the frame) and ``depth``."""
    B, H, W = frame.shape
    return pixels_to_view(su.clamp(0, W - 1), sv.clamp(0, H - 1), depth, *frame.intrinsics(batch))


class GradientRows:
    """The rows ``(J * N,)`` (block-major over ``J`` steps of ``N`` queries) a backward works on: all of
    them, or, when at most half have a nonzero gradient in any of ``grads`` (samples that occlude
    nothing get none), only those. ``take``/``per_row`` select them, ``put`` scatters results back (zeros
    elsewhere), ``per_query`` sums them per query ``(N, ...)``."""

    def __init__(self, J: int, N: int, *grads: torch.Tensor) -> None:
        self.J, self.N = J, N
        nonzero = grads[0] != 0
        for g in grads[1:]:
            nonzero |= g != 0
        # (all rows under torch.compile: the selection has a data-dependent size, a graph break)
        sparse = not torch.compiler.is_compiling() and 2 * int(nonzero.sum()) <= J * N
        self.index = nonzero.nonzero()[:, 0] if sparse else None
        self.query = None if self.index is None else self.index.remainder(N)

    def take(self, x: torch.Tensor) -> torch.Tensor:
        return x if self.index is None else take(x, self.index)

    def put(self, x: torch.Tensor) -> torch.Tensor:
        if self.index is None:
            return x
        return x.new_zeros(self.J * self.N, *x.shape[1:]).index_copy_(0, self.index, x)

    def per_row(self, x: torch.Tensor) -> torch.Tensor:
        """Per-query ``x`` ``(N, ...)`` for each row."""
        return repeat_rows(x, self.J) if self.index is None else take(x, self.query)

    def per_query(self, x: torch.Tensor) -> torch.Tensor:
        """Sum of per-row ``x`` over each query's rows ``(N, ...)``."""
        if self.index is None:
            return x.view(self.J, self.N, *x.shape[1:]).sum(0)
        return x.new_zeros(self.N, *x.shape[1:]).index_add_(0, self.query, x)


def _bilerp_depth_backward(inverse: torch.Tensor, fu: torch.Tensor, fv: torch.Tensor, depth: torch.Tensor,
                           grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gradients of ``depth = 1 / bilerp(inverse, fu, fv)`` ``(N,)`` to the tap inverse depths ``(N,4)``,
    ``fu`` and ``fv`` given ``grad`` ``(N,)`` of ``depth``."""
    g = -grad * depth.square()  # d depth = -depth^2 dS, S the interpolated inverse depth
    i0, i1, i2, i3 = inverse.unbind(-1)
    lower, upper = g * fv, g * (1 - fv)  # S = (1 - fv) top + fv bottom
    right_up, right_low = upper * fu, lower * fu
    g_inverse = torch.stack((upper - right_up, right_up, lower - right_low, right_low), -1)
    g_fu = torch.lerp(i1 - i0, i3 - i2, fv).mul_(g)
    g_fv = (torch.lerp(i2, i3, fu) - torch.lerp(i0, i1, fu)).mul_(g)
    return g_inverse, g_fu, g_fv
