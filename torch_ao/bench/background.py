"""Background costs nothing: forward time of each method on a full frame, the same frame with half
its pixels background, and an all-background frame."""
from __future__ import annotations

import math
from typing import Mapping

import torch

from ..gbuffer import GBuffer
from ..walk import Frame
from .sweep import MethodFactory, make_method, time_calls

__all__ = ["background_frames", "background_scaling"]


def _frame_with_mask(gb: GBuffer, mask: torch.Tensor) -> GBuffer:
    base = gb.mask if gb.mask is not None else torch.ones_like(gb.valid)
    return GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, light=gb.light, mask=base & mask,
                   object_id=gb.object_id)


def background_frames(gb: GBuffer) -> dict[str, GBuffer]:
    """The same frame fully valid (``full``), with its right half background (``half``) and all
    background (``empty``), from a frame whose pixels are all valid."""
    if not bool(gb.valid.all()):
        raise ValueError("gbuffer: expected a frame with no background pixels")
    W = gb.depth.shape[-1]
    half = torch.ones_like(gb.valid)
    half[..., W // 2:] = False
    return {"full": gb, "half": _frame_with_mask(gb, half), "empty": _frame_with_mask(gb, torch.zeros_like(half))}


def background_scaling(methods: Mapping[str, MethodFactory], preset: str = "high", *, gbuffer: GBuffer | None = None,
                       height: int = 96, width: int = 128, repeats: int = 5, warmup: int = 1, device="cpu",
                       radius: float = 1.0, progress: bool = False) -> list[dict]:
    """Forward time of each method on a full frame, a half-background and an all-background frame,
    with the number of pixels the core walks (``Frame.queries``). Default frame: a tilted plane
    (:func:`~torch_ao.examples.plane_gbuffer`), which fills the image."""
    from tqdm.auto import tqdm

    from ..examples import plane_gbuffer

    device = torch.device(device)
    gb = gbuffer if gbuffer is not None else plane_gbuffer(height, width)
    if gb.light is None:  # a constant light, so that methods computing indirect light run too
        gb = GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, light=torch.full_like(gb.depth, 0.5).expand(-1, 3, -1, -1),
                     mask=gb.mask, object_id=gb.object_id)
    gb = gb.to(device)
    frames = background_frames(gb)
    rows = []
    for name, factory in tqdm(list(methods.items()), desc="background", disable=not progress, leave=False):
        module = make_method(factory, preset, radius=radius).to(device)
        full_ms = full_cpu = None
        for kind, frame in frames.items():
            with torch.no_grad():
                walked = len(Frame(frame).queries)
                ms, cpu = time_calls(lambda: module(frame), repeats=repeats, warmup=warmup, device=device)
                ms, cpu = ms * 1e3, cpu * 1e3
                vis = module(frame).visibility
            full_ms, full_cpu = (ms, cpu) if kind == "full" else (full_ms, full_cpu)
            bg = ~frame.valid
            rows.append({"method": name, "preset": preset, "frame": kind,
                         "valid_fraction": float(frame.valid.float().mean()), "walked_pixels": walked,
                         "forward_ms": ms, "time_ratio": ms / full_ms if full_ms else math.nan,
                         "forward_cpu_ms": cpu, "cpu_ratio": cpu / full_cpu if full_cpu else math.nan,
                         "background_is_one": bool((vis[bg] == 1).all()) if bool(bg.any()) else True,
                         "height": gb.depth.shape[-2], "width": gb.depth.shape[-1], "device": str(device),
                         "threads": torch.get_num_threads()})
    return rows
