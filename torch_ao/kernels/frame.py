"""What every kernel reads of a G-buffer: channel-last float32 images, the inverse depth, the intrinsics."""
from __future__ import annotations

import functools

import torch

from ..gbuffer import GBuffer

__all__ = ["LANES", "channels_last", "walk_inputs", "view_geometry", "light_input", "scale_derivative"]

#: the kernels' lane types: ``"simd"`` (the CPU's vector lanes, the default) or ``"scalar"`` (one pixel at a
#: time in float lanes: the arithmetic of the CUDA kernel, which compiles the same walk)
LANES = ("simd", "scalar")


def channels_last(x: torch.Tensor) -> torch.Tensor:
    """``(B,C,H,W)`` -> contiguous ``(B,H,W,C)`` float32."""
    return x.permute(0, 2, 3, 1).to(torch.float32).contiguous()


def walk_inputs(gbuffer: GBuffer, normals: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Channel-last positions and normals ``(B,H,W,3)``, the inverse depth and the depth (both NaN where
    invalid: the kernels read a texel's validity from the one they fetch), validity ``(B,H,W)``, and the
    intrinsics ``(B,4)`` ``(fx, fy, cx, cy)`` in pixels."""
    valid = gbuffer.valid[:, 0].contiguous()
    inverse, depth = gbuffer.derived("walk_depths", lambda: _walk_depths(gbuffer, valid))
    return (channels_last(gbuffer.positions()), channels_last(normals), inverse, depth, valid,
            _intrinsics(gbuffer).contiguous())


def _walk_depths(gbuffer: GBuffer, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    safe = gbuffer.safe_depth[:, 0].to(torch.float32)
    return torch.where(valid, safe.reciprocal(), torch.nan), torch.where(valid, safe, torch.nan)


def _intrinsics(gbuffer: GBuffer) -> torch.Tensor:
    """``(B,4)`` float32 ``(fx, fy, cx, cy)`` in pixels (a view: not contiguous)."""
    cam = gbuffer.camera
    return torch.stack((cam.fx, cam.fy, cam.cx, cam.cy), -1).to(torch.float32).expand(gbuffer.depth.shape[0], 4)


def view_geometry(gbuffer: GBuffer, method: str) -> None:
    """Compute ``gbuffer``'s positions and view normals (``gbuffer.view_normals(method)``), and :func:`walk_inputs`'
    inverse depth and depth, in one C++ pass and keep them for the rest of the call, where a kernel's call records
    gradients through the G-buffer: a CPU float32 G-buffer in :meth:`~torch_ao.GBuffer.one_call`, with normals, no
    position buffer and intrinsics that need no gradient. Else (and for a second call within one
    :meth:`~torch_ao.GBuffer.one_call`) nothing is done.

    The pass gives the tensor ops' values (``GBuffer.positions``, ``_unit_facing``) channel-last, which is
    what :func:`walk_inputs` hands the kernels, and its backward is their closed form in one pass: at 640x360, one
    thread, about 6 ms for both against 19 ms of torch ops (docs/performance.md). Not twice differentiable (the
    kernels' backwards are not either)."""
    depth, normals, cam = gbuffer.depth, gbuffer.normals, gbuffer.camera
    if (torch.compiler.is_compiling() or not torch.is_grad_enabled() or normals is None or gbuffer.position is not None
            or not (depth.requires_grad or normals.requires_grad) or cam.intrinsics.requires_grad
            or depth.device.type != "cpu" or depth.dtype != torch.float32 or normals.dtype != torch.float32):
        return
    if not gbuffer.in_call("positions", ("view_normals", method), "walk_depths"):
        return
    from .build import cpu_kernels

    cpu_kernels()  # (KernelUnavailable when it cannot be built: the caller's kernel could not run either)
    inputs = (depth.contiguous(), normals.contiguous(), gbuffer.valid.contiguous(), _intrinsics(gbuffer).contiguous())
    positions, unit, inverse, depth_nan = _ViewGeometry.apply(*inputs)
    gbuffer.keep("positions", positions.permute(0, 3, 1, 2))
    gbuffer.keep(("view_normals", method), unit.permute(0, 3, 1, 2))
    gbuffer.keep("walk_depths", (inverse, depth_nan))


def first_order(backward):
    """The decorator of a kernel Function's ``backward``: its gradients are first order. Where autograd records the
    backward (``create_graph=True``, for a second derivative), each gradient carries a node that raises when it is
    differentiated, where autograd would silently take the kernel's gradients as constants of its inputs (a
    second derivative of 0). PyTorch's ``once_differentiable`` raises only where the incoming gradients require
    one, which a gradient penalty's do not."""

    @functools.wraps(backward)
    def wrapper(ctx, *grad_outputs):
        with torch.no_grad():
            grads = backward(ctx, *grad_outputs)
        if not torch.is_grad_enabled():
            return grads
        grads = grads if isinstance(grads, tuple) else (grads,)
        inputs = [t for t in ctx.saved_tensors if t is not None and t.requires_grad]  # (the node on their paths)
        raises = torch._C._functions.DelayedError(
            b"torch_ao: a fused kernel's gradients are first order: a second derivative through the AO layer "
            b"(create_graph=True) is not supported", len(grads) + len(inputs))
        return raises(*(None if g is None else g.detach().requires_grad_(True) for g in grads), *inputs)[:len(grads)]

    return wrapper


class _ViewGeometry(torch.autograd.Function):
    """``torch_ao_kernels::view_geometry`` and its backward (geometry_cpu.cpp)."""

    @staticmethod
    def forward(ctx, depth, normals, valid, intrinsics):
        ctx.save_for_backward(depth, normals, valid, intrinsics)
        ctx.set_materialize_grads(False)  # (an output nothing read has no gradient: None, not zeros)
        return torch.ops.torch_ao_kernels.view_geometry(depth, normals, valid, intrinsics)

    @staticmethod
    @first_order
    def backward(ctx, *grads):
        depth, normals, valid, intrinsics = ctx.saved_tensors
        none = depth.new_empty(0)
        g_depth, g_in = torch.ops.torch_ao_kernels.view_geometry_backward(
            *(none if g is None else g.contiguous() for g in grads), depth, normals, valid, intrinsics)
        # (the unit normals alone carry the normals' gradient, the other outputs the depth's: where nothing read them,
        # the input has none, as through the tensor ops: UE4 SSAO's walk reads no normal)
        g_positions, g_unit, g_inverse, g_depth_nan = grads
        depth_read = any(g is not None for g in (g_positions, g_inverse, g_depth_nan))
        return (g_depth if ctx.needs_input_grad[0] and depth_read else None,
                g_in if ctx.needs_input_grad[1] and g_unit is not None else None, None, None)


def light_input(gbuffer: GBuffer, wanted: bool) -> torch.Tensor:
    """The direct light channel-last ``(B,H,W,3)``, or an empty tensor when not ``wanted``; a ``ValueError``
    naming ``gbuffer.light`` when it is wanted and missing."""
    if not wanted:
        return torch.empty(0)
    if gbuffer.light is None:
        raise ValueError("gbuffer.light: indirect light needs a (B,3,H,W) direct-light buffer")
    return channels_last(gbuffer.light)


def scalar_lanes(lanes: str) -> bool:
    """Whether ``lanes`` (one of :data:`LANES`) asks for the scalar lanes; a ``ValueError`` naming it otherwise."""
    if lanes not in LANES:
        raise ValueError(f"lanes: expected one of {LANES}, got {lanes!r}")
    return lanes == "scalar"


def scale_derivative(valid: torch.Tensor, *pairs: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """``sum(dL/dx * x)`` over ``pairs`` of a gradient and its world-unit input ``x`` (positions, depth: ``+x``;
    the inverse depth: pass ``-x``), on the ``valid`` ``(B,H,W)`` texels (elsewhere the inputs hold NaN), in
    float64: d L / d s of the scene scaled by ``s`` at ``s = 1``, which the walks' scale invariance turns into
    the radius' gradient (Euler's identity). These tensor ops are the definition; float32 CPU pairs are summed by
    ``torch_ao_kernels::scale_derivative`` (geometry_cpu.cpp) in one pass, without the float64 copies (at
    640x360, one thread: about 1 ms against 3 ms; docs/performance.md)."""
    if valid.device.type == "cpu" and all(g.dtype == x.dtype == torch.float32 for g, x in pairs):
        from .build import cpu_kernels

        return cpu_kernels().scale_derivative(valid.contiguous(), [g.contiguous() for g, _ in pairs],
                                              [x.contiguous() for _, x in pairs])
    total = torch.zeros((), dtype=torch.float64, device=valid.device)
    for g, x in pairs:
        mask = valid if g.dim() == valid.dim() else valid[..., None].expand_as(g)
        total = total + torch.where(mask, g.double() * x.double(), 0.0).sum()
    return total
