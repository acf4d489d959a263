"""Temporal accumulation of AO across frames, as engines run it: each frame walks with a new noise seed, the
previous result is reprojected into the current view and blended in, so that over ``frames`` frames a pixel
averages that many independent noise patterns at one frame's cost.

Per frame ``k`` (``k`` counted from the last :meth:`TemporalAO.reset`):

1. the wrapped module runs with noise seed ``seed + k mod frames`` (every walk inside it: a method, a
   :class:`~torch_ao.fitted.FittedPipeline`'s method);
2. :func:`reproject` carries the history (the accumulated outputs, their depth and their frame counts) into
   the current view: each current pixel is moved by ``current_to_previous`` (view space to the previous view
   space) or by engine motion vectors, read bilinearly, and kept where the previous depth there matches the
   moved point's (a relative ``depth_tolerance``) and all four taps were valid; elsewhere (disocclusion, off
   screen, background) it starts again;
3. ``n = min(count + 1, frames)`` and ``out = history + (current - history) / n``: the running mean of the
   last frames, an exponential average of weight ``1 / frames`` once ``n`` reaches it.

For a still camera the result after ``frames`` frames is exactly the mean over the seeds
(:func:`accumulate_still`, which a fit can differentiate through). The history is detached: gradients reach
the current frame's output (weight ``1 / n``), not the past frames.

What it gains: measured on ``torch-ao fit``'s views at ``high`` (``benchmarks/accuracy_headroom.py --study
temporal``), 8 still frames add at most 0.23 dB PSNR after the denoiser: at ``high``'s sample count the error
is the estimator's bias, not noise. Its cost per frame is one forward plus the reprojection.
"""
from __future__ import annotations

import dataclasses
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import nn

from .checks import check_float, check_int
from .gbuffer import GBuffer
from .methods.base import AOOutput, ScreenSpaceAO

__all__ = ["TemporalAO", "reproject", "accumulate_still"]


def _check_transform(name: str, T: torch.Tensor, batch: int) -> torch.Tensor:
    if not isinstance(T, torch.Tensor) or T.shape[-2:] != (4, 4) or T.dim() not in (2, 3) or (
            T.dim() == 3 and T.shape[0] not in (1, batch)):
        shape = tuple(T.shape) if isinstance(T, torch.Tensor) else type(T).__name__
        raise ValueError(f"{name}: expected a (4, 4) or (B, 4, 4) view-to-view transform with B = {batch}, got {shape}")
    return T.reshape(-1, 4, 4).expand(batch, 4, 4)


def reproject(history: torch.Tensor, history_depth: torch.Tensor, gbuffer: GBuffer, *,
              current_to_previous: torch.Tensor | None = None, motion: torch.Tensor | None = None,
              depth_tolerance: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """The previous frame's ``history`` seen from the current view, and where it is meaningful.

    Args:
        history: ``(B, C, H, W)`` values of the previous frame (any channels).
        history_depth: ``(B, 1, H, W)`` the previous frame's depth (world units; non-finite = background).
        gbuffer: the current frame (its depth, valid mask and camera, which both frames share).
        current_to_previous: ``(4, 4)`` or ``(B, 4, 4)`` transform of current view-space points into the
            previous view space (``previous_world_to_view @ inverse(current_world_to_view)``); or
        motion: ``(B, 2, H, W)`` per-pixel offsets in pixels from each current pixel to where it was in the
            previous frame (an engine's motion vectors; ``u`` right, ``v`` down). With neither, a still camera.
        depth_tolerance: the largest relative difference between the previous depth at the reprojected
            position and the moved point's depth for the history to count (disocclusion test).

    Returns:
        ``(warped, valid)``: the history read bilinearly at each current pixel's previous position (0 where
        not valid), and where the current pixel is valid, its previous position inside the image, all four
        taps valid and the depth test passed.

    Shape:
        - history: ``(B, C, H, W)``; history_depth: ``(B, 1, H, W)``; motion: ``(B, 2, H, W)``.
        - Output: warped ``(B, C, H, W)`` (the G-buffer's dtype), valid ``(B, 1, H, W)`` bool.
    """
    check_float("depth_tolerance", depth_tolerance, minimum=0.0, open_minimum=True)
    B, _, H, W = gbuffer.depth.shape
    if history.dim() != 4 or history.shape[0] != B or history.shape[-2:] != (H, W):
        raise ValueError(f"history: expected (B, C, H, W) = ({B}, C, {H}, {W}), got {tuple(history.shape)}")
    if history_depth.shape != gbuffer.depth.shape:
        raise ValueError(f"history_depth: expected {tuple(gbuffer.depth.shape)}, got {tuple(history_depth.shape)}")
    if current_to_previous is not None and motion is not None:
        raise ValueError("current_to_previous, motion: give one of them (or neither, for a still camera)")
    dtype = gbuffer.depth.dtype
    depth = torch.where(gbuffer.valid, gbuffer.depth, 1.0)
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype, device=depth.device),
                          torch.arange(W, dtype=dtype, device=depth.device), indexing="ij")
    u, v = u.expand(B, H, W), v.expand(B, H, W)
    if motion is not None:
        if motion.shape != (B, 2, H, W):
            raise ValueError(f"motion: expected (B, 2, H, W) = ({B}, 2, {H}, {W}), got {tuple(motion.shape)}")
        pu, pv, expected = u + motion[:, 0].to(dtype), v + motion[:, 1].to(dtype), depth[:, 0]
    elif current_to_previous is not None:
        T = _check_transform("current_to_previous", current_to_previous, B).to(dtype)
        P = gbuffer.camera.unproject(depth).flatten(2)  # (B, 3, HW)
        Q = (T[:, :3, :3] @ P + T[:, :3, 3:]).transpose(1, 2).reshape(B, H, W, 3)
        pu, pv, expected = gbuffer.camera.view_to_pixel(Q)
    else:
        pu, pv, expected = u, v, depth[:, 0]
    # pixel centres at integer coordinates: grid_sample's align_corners=True maps -1 and 1 to the edge centres
    grid = torch.stack((2 * pu / max(W - 1, 1) - 1, 2 * pv / max(H - 1, 1) - 1), -1)
    grid = torch.where(torch.isfinite(grid), grid, 2.0)  # (a point behind the camera: off screen)
    before = torch.isfinite(history_depth) & (history_depth > 0)
    taps = torch.cat((torch.where(before, history_depth, 0.0).to(dtype), before.to(dtype), history.to(dtype)), 1)
    read = F.grid_sample(taps, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    e = 1e-4  # (pixels: an edge pixel moved by rounding alone stays inside)
    inside = (pu >= -e) & (pu <= W - 1 + e) & (pv >= -e) & (pv <= H - 1 + e) & (expected > 0)
    all_valid = read[:, 1] > 1 - 1e-6
    agree = (read[:, 0] - expected).abs() <= depth_tolerance * expected.abs()
    valid = gbuffer.valid & (inside & all_valid & agree)[:, None]
    return torch.where(valid, read[:, 2:], 0.0), valid


@contextmanager
def _seeded(module: nn.Module, offset: int):
    """Every walk in ``module`` with its noise seed advanced by ``offset`` for the block, then restored."""
    walks = [m for m in module.modules() if isinstance(m, ScreenSpaceAO)]
    if not walks:
        raise TypeError(f"module: expected a torch_ao method or a module holding one, got {type(module).__name__}")
    saved = [m.sampling for m in walks]
    try:
        for m, s in zip(walks, saved):
            m.sampling = dataclasses.replace(s, seed=s.seed + offset)
        yield
    finally:
        for m, s in zip(walks, saved):
            m.sampling = s


def accumulate_still(module: nn.Module, gbuffer: GBuffer, frames: int) -> AOOutput:
    """A still camera's temporal accumulation after ``frames`` frames: the mean of ``module``'s visibility
    (and indirect light) over noise seeds ``seed .. seed + frames - 1``, differentiable through every frame
    (what a fit of a temporal pipeline optimises). Other outputs are the first frame's.

    Shape:
        - Input: a :class:`~torch_ao.GBuffer` ``(B, C, H, W)``.
        - Output: :class:`~torch_ao.AOOutput`: ``visibility`` ``(B, 1, H, W)``, ``indirect`` ``(B, 3, H, W)`` or ``None``.
    """
    check_int("frames", frames, minimum=1)
    outs = []
    for k in range(frames):
        with _seeded(module, k):
            outs.append(module(gbuffer))
    mean = lambda name: None if getattr(outs[0], name) is None else torch.stack([getattr(o, name) for o in outs]).mean(0)
    return dataclasses.replace(outs[0], visibility=mean("visibility"), indirect=mean("indirect"))


class TemporalAO(nn.Module):
    """``module`` accumulated over frames (see the module docstring): each call is one frame.

    Args:
        module: a torch_ao method, or a module holding one (a :class:`~torch_ao.fitted.FittedPipeline`), whose
            ``forward(gbuffer)`` returns an :class:`~torch_ao.AOOutput`.
        frames: how many frames a pixel averages at most (and how many noise seeds it cycles through);
            8 is XeGTAO's temporal sample count, and more gained nothing on the measured views.
        depth_tolerance: :func:`reproject`'s disocclusion test (relative depth; 0.05 = 5 %).

    Call :meth:`reset` on a camera cut; a change of frame size or batch resets by itself.

    Shape:
        - Input: a :class:`~torch_ao.GBuffer` ``(B, C, H, W)``; optional ``current_to_previous`` ``(B, 4, 4)`` or
          ``motion`` ``(B, 2, H, W)`` (pixels), as :func:`reproject`.
        - Output: the module's :class:`~torch_ao.AOOutput` with ``visibility`` ``(B, 1, H, W)`` (and ``indirect``
          ``(B, 3, H, W)``) accumulated.
    """

    def __init__(self, module: nn.Module, frames: int = 8, depth_tolerance: float = 0.05) -> None:
        super().__init__()
        check_int("frames", frames, minimum=1)
        check_float("depth_tolerance", depth_tolerance, minimum=0.0, open_minimum=True)
        if not any(isinstance(m, ScreenSpaceAO) for m in module.modules()):
            raise TypeError(f"module: expected a torch_ao method or a module holding one, got {type(module).__name__}")
        self.module, self.frames, self.depth_tolerance = module, int(frames), float(depth_tolerance)
        self.reset()

    def reset(self) -> None:
        """Forget the history (a camera cut)."""
        self.frame = 0
        self._history: dict | None = None

    def forward(self, gbuffer: GBuffer, current_to_previous: torch.Tensor | None = None,
                motion: torch.Tensor | None = None) -> AOOutput:
        with _seeded(self.module, self.frame % self.frames):
            out = self.module(gbuffer)
        self.frame += 1
        names = ["visibility"] + (["indirect"] if out.indirect is not None else [])
        current = torch.cat([getattr(out, n) for n in names], 1)
        h = self._history
        if h is None or h["values"].shape != current.shape:
            count = torch.zeros_like(gbuffer.depth, dtype=current.dtype)
            history, valid = current.detach(), torch.zeros_like(gbuffer.valid)
        else:
            warped, valid = reproject(torch.cat((h["values"], h["count"]), 1), h["depth"], gbuffer,
                                      current_to_previous=current_to_previous, motion=motion,
                                      depth_tolerance=self.depth_tolerance)
            history, count = warped[:, :-1], warped[:, -1:]
        n = torch.where(valid, (count + 1).clamp(max=self.frames), 1.0)
        blended = torch.where(valid, history + (current - history) / n, current)
        self._history = {"values": blended.detach(), "count": n.detach(),
                         "depth": torch.where(gbuffer.valid, gbuffer.depth, float("inf")).detach()}
        parts = dict(zip(names, blended.split([getattr(out, n).shape[1] for n in names], 1)))
        return dataclasses.replace(out, **parts)

    def extra_repr(self) -> str:
        return f"frames={self.frames}, depth_tolerance={self.depth_tolerance}"
