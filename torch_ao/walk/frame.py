"""The G-buffer flattened for gathering, and the query pixels the walk computes.

Work is done on a flat list of *query* pixels (the valid, non-background ones), so background costs
nothing and the list can be cut into chunks to bound memory. Every per-row container (``Queries``
here, ``SliceGeometry``, ``Footprint``) has one ``map_rows`` so that slicing, gathering and repeating
rows is written once.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..gbuffer import GBuffer

__all__ = ["Frame", "Queries", "take", "repeat_rows", "flat"]


@dataclass
class Queries:
    """The pixels being computed (a subset of the frame, flattened). All tensors have N rows."""

    index: torch.Tensor  # (N,) long, flat index b*H*W + v*W + u
    batch: torch.Tensor  # (N,) long
    u: torch.Tensor  # (N,) pixel column (float)
    v: torch.Tensor  # (N,) pixel row (float)
    position: torch.Tensor  # (N,3) view-space position P
    normal: torch.Tensor  # (N,3) unit normal
    view: torch.Tensor  # (N,3) unit vector toward the camera, V = normalize(-P)
    depth: torch.Tensor  # (N,) positive depth

    def __len__(self) -> int:
        return self.index.shape[0]

    def map_rows(self, fn) -> "Queries":
        """The queries with ``fn`` applied to every per-row tensor (a slice, a gather, a repeat...)."""
        return Queries(fn(self.index), fn(self.batch), fn(self.u), fn(self.v), fn(self.position), fn(self.normal),
                       fn(self.view), fn(self.depth))

    def subset(self, sl: slice) -> "Queries":
        return self.map_rows(lambda x: x[sl])

    def repeat(self, times: int) -> "Queries":
        """The rows repeated ``times`` times, block-major: row ``j * N + i`` is query ``i``."""
        return self if times == 1 else self.map_rows(functools.partial(repeat_rows, times=times))


class Frame:
    """A G-buffer flattened for gathering: buffers are ``(B*H*W, C)``, channel-last.

    Args:
        gbuffer: the validated inputs.
        normals: ``(B,3,H,W)`` unit normals to use (e.g. ``gbuffer.view_normals()``); ``None``
            uses ``gbuffer.view_normals()``.
        buffers: extra ``(B,C,H,W)`` images that samples may gather (light, normals of samples,
            object ids, per-pixel parameter maps...).

    Attributes:
        shape: ``(B, H, W)``; dtype: the depth's floating type.
        fx, fy, cx, cy: ``(B,)`` intrinsics in pixels.
        safe_depth, inverse_depth: ``(B*H*W,)`` positive depths and their reciprocals (what bilinear
            fetches interpolate); positions: ``(B*H*W, 3)`` view-space positions (the G-buffer's position
            buffer when it has one: ``has_position``); valid: ``(B*H*W,)`` bool.
        queries: the valid pixels (:class:`Queries`); every pixel under ``torch.compile`` (``all_pixels``).
    """

    def __init__(self, gbuffer: GBuffer, normals: torch.Tensor | None = None,
                 buffers: dict[str, torch.Tensor] | None = None) -> None:
        B, _, H, W = gbuffer.depth.shape
        self.shape = (B, H, W)
        self.dtype = gbuffer.depth.dtype
        cam = gbuffer.camera
        self.fx, self.fy, self.cx, self.cy = cam.fx, cam.fy, cam.cx, cam.cy  # (B,)
        self.safe_depth = flat(gbuffer.safe_depth)[:, 0]  # (BHW,)
        self.inverse_depth = self.safe_depth.reciprocal()  # (BHW,): what bilinear fetches interpolate
        self.positions = flat(gbuffer.positions())  # (BHW, 3)
        self.has_position = gbuffer.position is not None  # samples read positions, not depth
        self.valid = flat(gbuffer.valid)[:, 0]  # (BHW,)
        self.buffers = {k: flat(v) for k, v in (buffers or {}).items()}
        if normals is None:
            normals = gbuffer.view_normals()
        #: every pixel is a query under torch.compile: the list of valid ones has a data-dependent size (a
        #: graph break); :meth:`scatter` then keeps the background's fill
        self.all_pixels = torch.compiler.is_compiling()
        if self.all_pixels:
            index = torch.arange(self.valid.shape[0], device=self.valid.device)
        else:
            index = self.valid.nonzero()[:, 0]
        hw = H * W
        batch = torch.div(index, hw, rounding_mode="floor")
        rem = index - batch * hw
        v = torch.div(rem, W, rounding_mode="floor")
        u = rem - v * W
        P = self.positions[index]
        self.queries = Queries(
            index=index,
            batch=batch,
            u=u.to(self.dtype),
            v=v.to(self.dtype),
            position=P,
            normal=flat(normals)[index],
            view=F.normalize(-P, dim=-1),
            depth=self.safe_depth[index],
        )

    def intrinsics(self, batch: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(fx, fy, cx, cy)`` of each row's image ``batch`` ``(N,)``: 0-d tensors for a single image
        (broadcast, no gather), else ``(N,)``."""
        if self.shape[0] == 1:
            return self.fx[0], self.fy[0], self.cx[0], self.cy[0]
        return self.fx[batch], self.fy[batch], self.cx[batch], self.cy[batch]

    def scatter(self, values: torch.Tensor, fill: float | torch.Tensor) -> torch.Tensor:
        """Place per-query rows ``(N, C)`` into a ``(B, C, H, W)`` image, ``fill`` elsewhere."""
        B, H, W = self.shape
        C = values.shape[1]
        if isinstance(fill, torch.Tensor):  # (B,C,H,W) background image
            base = flat(fill.to(values.dtype))
        else:
            base = values.new_full((B * H * W, C), float(fill))
        if self.all_pixels:
            out = torch.where(self.valid[:, None], values, base)
        else:
            out = base.index_put((self.queries.index,), values)
        return out.view(B, H, W, C).permute(0, 3, 1, 2)


def repeat_rows(x: torch.Tensor, times: int) -> torch.Tensor:
    """``x`` ``(N, ...)`` stacked ``times`` times along the rows: ``(times * N, ...)``."""
    return x.repeat(times, *([1] * (x.dim() - 1)))


def flat(x: torch.Tensor) -> torch.Tensor:
    """``(B,C,H,W)`` -> contiguous ``(B*H*W, C)`` (row gathers from a strided view are many times slower)."""
    B, C, H, W = x.shape
    return x.permute(0, 2, 3, 1).reshape(B * H * W, C).contiguous()


def take(buf: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``buf[index]`` (rows of ``buf`` at an integer index of any shape), by ``index_select``
    (several times faster than advanced indexing on CPU)."""
    return buf.index_select(0, index.reshape(-1)).view(*index.shape, *buf.shape[1:])
