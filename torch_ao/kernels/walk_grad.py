"""The one walk with a backward: the horizon accumulators (GTAO's variants, HBAO) and the SSAO family's (UE4
SSAO, PSSAO: their forward records nothing, the backward replays every step) as a
``torch.autograd.Function`` over the walk's channel-last inputs (positions, normals, inverse depth, depth),
so that autograd chains its gradients to the G-buffer through :func:`~torch_ao.kernels.frame.walk_inputs`'
torch ops.

The forward (walk_grad.h's ``record_block``: ``torch_ao_kernels::walk_record`` on the CPU, the
``tao_record_*`` kernels on CUDA) is the walk, which also records per pixel, slice and side the steps that
changed the accumulator's state (a GTAO exact horizon's winner, HBAO's rises: a bit per step); the backward
(``grad_block``: ``torch_ao_kernels::walk_backward``, ``tao_backward_*``) replays each slice through those
steps alone in reverse lanes (lanes_rev.h: the replay records its arithmetic on a tape, swept back once per
slice), whose leaves are each pixel's own position, normal and depth, the accumulator's settings (``setting``:
GTAO's falloff or thickness, HBAO's angle bias, UE4 SSAO's fade distance, flat-surface bias and softness,
PSSAO's distance bias) and each replayed sample's fetched position, whose gradient
goes to its taps (bilinear: the inverse depth of its four taps; nearest: the tap's position; on CUDA with
atomic adds, so the sums' order, and their last bits, vary between runs). Where the intrinsics require
gradients, the camera's fx, fy, cx, cy are leaves too (the slice's screen extent, a bilinear fetch's
unprojection), their per-pixel adjoints summed per image.

The radius needs no tangent of its own: the walk is scale-invariant (scaling positions, depth and every
setting that is a length or an area by s, s^2 leaves its outputs as they are: screen positions, angles and the
falloff ratio do not change; step settings are in pixels), so for L = sum(grad * out) Euler's identity gives
``R dL/dR = -sum(dL/dP . P + dL/ddepth depth - dL/dinverse inverse) - sum_k [d_k s_k dL/ds_k]`` over the
walk's inputs, the last sum over the settings with their dimension d_k in world units (1: GTAO's falloff, UE4
SSAO's three; 2: the constant of the ue4 variant's ``rsqrt(|d|^2 + 1e-4)``, a setting for this alone).
"""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer
from .build import grad_kernels
from .frame import first_order, scalar_lanes, scale_derivative
from .launch import cuda_group_of, full_walk, launch_cuda, packed_inputs, run_packed

__all__ = ["differentiable_walk", "gbuffer_requires_grad", "wants_gradient", "replayed_fetches", "cuda_backward",
           "MAX_CUDA_STEPS"]

#: the most steps per side of the CUDA backward (walk_grad.h's kGradMaxSteps: a thread's replay is a fixed array)
MAX_CUDA_STEPS = 32
#: walk_cuda.cu's sizes of a horizon backward, smallest first: the name's suffix, the fetches a slice its thread holds
#: (``_small``: where a take replaces the state, each side's last, or 4 steps on one side, as HBAO's default 3;
#: ``_short``: 8 steps a side, or 16 on one, every preset's)
_BACKWARD_SIZES = (("_small", 4), ("_short", 16), ("", 2 * MAX_CUDA_STEPS))


def replayed_fetches(steps: int, replaces: bool, full_circle: bool = False) -> int:
    """The most fetches one slice of the backward replays, for ``steps`` per side: where a take replaces the
    accumulator's state (``replaces``: GTAO's exact variant, HBAO's ``accumulate="max"``, PSSAO) each side's last
    take alone, else every step of each side; one side a slice with ``full_circle`` (the walk's setting: HBAO, PSSAO,
    SSAO's points), else two. walk_grad.h's ``replayed_fetches`` is the rule; the CPU backward checks that this is
    at least its number, and the CUDA backward (:func:`cuda_backward`) is chosen by it."""
    sides = 1 if full_circle else 2
    return sides if replaces else sides * int(steps)


def cuda_backward(accumulator: str, fetches: int) -> str:
    """The smallest of walk_cuda.cu's backwards of ``accumulator`` whose thread's scratch holds ``fetches`` a slice
    (:func:`replayed_fetches`): ``_small`` (4), ``_short`` (16) or the full one (2 :data:`MAX_CUDA_STEPS`), of
    those the source has (UE4 SSAO's and SSAO's have no ``_small``, PSSAO's no other). The driver reserves a
    thread's local memory for every thread the GPU can hold, so the smallest is the one to run (on sm_90: 17-18,
    35-36 and 106-107 kB a thread, ``benchmarks/cuda_resources.py``)."""
    for suffix, holds in _BACKWARD_SIZES:
        name = f"tao_backward_{accumulator}{suffix}"
        if fetches <= holds and name in cuda_group_of():
            return name
    raise ValueError(f"accumulator: walk_cuda.cu has no backward of {accumulator!r} for {fetches} fetches a slice")


class _Walk(torch.autograd.Function):
    """``walk(accumulator, positions, normals, inverse, depth, ...)`` ``(B,C,H,W)`` and its backward (``full``: on
    CUDA, the full build's kernels)."""

    @staticmethod
    def forward(ctx, accumulator, positions, normals, inverse, depth, valid, intrinsics, cells, ints, floats,
                channels, scalar, radius, setting, setting_dimension, record_shape, full, fetches):
        ctx.accumulator, ctx.scalar, ctx.setting_dimension, ctx.full = accumulator, scalar, setting_dimension, full
        ctx.fetches = fetches
        frame = (positions, normals, inverse, depth, valid, intrinsics, cells)
        if record_shape is None:  # every step replayed: the plain walk, no record
            none = positions.new_empty(0)
            record = torch.empty(0, dtype=torch.int64, device=depth.device)
            out = run_packed(accumulator, frame[:6], (none, cells, none), ints, floats, channels, scalar, full=full)
        elif positions.is_cuda:
            B, H, W = depth.shape
            out = torch.empty(B, channels, H, W, device=depth.device)
            record = torch.empty(B, H, W, *record_shape, dtype=torch.int64, device=depth.device)
            launch_cuda(f"tao_record_{accumulator}", depth.device, [*frame, out, record, ints, floats], (B, H, W),
                        full=full)
        else:
            out, record = grad_kernels().walk_record(accumulator, *frame, ints, floats, channels, record_shape[0],
                                                     scalar)
        ctx.save_for_backward(*frame, ints, floats, radius, setting, record)
        return out

    @staticmethod
    @first_order
    def backward(ctx, grad):
        (positions, normals, inverse, depth, valid, intrinsics, cells, ints, floats, radius, setting,
         record) = ctx.saved_tensors
        frame = (positions, normals, inverse, depth, valid, intrinsics, cells)
        grad = grad.to(torch.float32).contiguous()
        camera = ctx.needs_input_grad[6]  # the intrinsics' gradients, per pixel (B, H, W, 4)
        if positions.is_cuda:  # the pixels' own gradients, and their taps' scattered atomically into one image
            g_pos, g_nrm, taps = torch.zeros_like(positions), torch.zeros_like(normals), torch.zeros_like(positions)
            g_depth, g_inv = torch.zeros_like(depth), torch.zeros_like(depth)
            g_setting = positions.new_zeros((*depth.shape, len(setting)))
            g_camera = positions.new_zeros((*depth.shape, 4) if camera else (0,))  # (empty: a null pointer)
            launch_cuda(cuda_backward(ctx.accumulator, ctx.fetches), depth.device,
                        [*frame, grad, record, g_pos, g_nrm, g_depth, g_setting, taps, g_inv,
                         g_camera, ints, floats], tuple(depth.shape), full=ctx.full)
            g_pos += taps
        else:
            g_pos, g_nrm, g_inv, g_depth, g_setting, g_camera = grad_kernels().walk_backward(
                ctx.accumulator, grad, *frame, ints, floats, record, ctx.fetches, len(setting), camera, ctx.scalar)
        g_intrinsics = g_camera.to(torch.float64).sum((1, 2)).to(intrinsics.dtype) if camera else None
        along_setting = g_setting.to(torch.float64).sum((0, 1, 2))  # d L / d each setting
        g_radius = None
        if ctx.needs_input_grad[12]:  # Euler's identity (module docstring); invalid texels hold NaN
            # (in float64: the terms cancel to the gradient, which may be 0 where the radius is clamped in pixels)
            along = scale_derivative(valid, (g_pos, positions), (g_depth, depth), (g_inv, -inverse))
            dimension = torch.tensor(ctx.setting_dimension, dtype=torch.float64, device=setting.device)
            along = along + (dimension * setting.to(torch.float64) * along_setting).sum()
            g_radius = (-along / radius).to(radius.dtype)
        g_out = along_setting.to(setting.dtype) if ctx.needs_input_grad[13] else None
        return (None, g_pos, g_nrm, g_inv, g_depth, None, g_intrinsics, None, None, None, None, None, g_radius, g_out,
                None, None, None, None)


def gbuffer_requires_grad(gbuffer: GBuffer) -> bool:
    """Whether the G-buffer's depth, normals, position buffer or intrinsics require gradients."""
    cam = gbuffer.camera
    return any(isinstance(t, torch.Tensor) and t.requires_grad
               for t in (gbuffer.depth, gbuffer.normals, gbuffer.position, cam.fx, cam.fy, cam.cx, cam.cy))


def wants_gradient(gbuffer: GBuffer, normals: torch.Tensor, *parameters) -> bool:
    """Whether autograd records through the walk's inputs (grad mode on, the G-buffer
    (:func:`gbuffer_requires_grad`), the normals or one of the ``parameters`` tensors requiring it)."""
    return torch.is_grad_enabled() and (gbuffer_requires_grad(gbuffer) or any(
        isinstance(t, torch.Tensor) and t.requires_grad for t in (normals, *parameters)))


def differentiable_walk(accumulator: str, gbuffer: GBuffer, normals: torch.Tensor,
                        settings: tuple[list[int], list[float]], acc_ints: list, acc_floats: list, channels: int,
                        *, radius: torch.Tensor | float, setting: tuple = (0.0,),
                        setting_dimension: tuple = (0,), replaces: bool = False,
                        lanes: str = "simd") -> torch.Tensor:
    """:func:`~torch_ao.kernels.launch.run_walk` on a CPU or CUDA G-buffer with autograd history: gradients
    reach ``gbuffer``'s depth, normals (and position buffer) through the walk's inputs (on CUDA at most
    :data:`MAX_CUDA_STEPS` steps per side). ``accumulator``: ``"gtao"`` or ``"hbao"`` (their forward records
    the steps that carry gradients), ``"pssao"`` (likewise: each slice's highest sample) or ``"wedge"`` (every step
    replayed); any fetch, either
    border. ``radius``: the 0-d tensor the walk's extent is proportional to, which receives its gradient, or
    a number. ``setting``: the accumulator's differentiable settings (its ``settings()``, in its order), 0-d
    tensors or numbers whose values ``acc_floats`` holds (GTAO's falloff in world units or thickness; HBAO's
    angle bias; UE4 SSAO's fade distance, flat-surface bias and softness; PSSAO's distance bias), which receive
    their gradients; ``setting_dimension``: per setting, its power of world units (0: none, 1: a length, 2: an
    area; the radius' gradient, Euler's identity, needs each). ``replaces``: whether a step that changes a side's
    state replaces it (:func:`replayed_fetches`; the accumulator's ``replaces()``, which the backward checks)."""
    inputs, (_, cells, _), ints, floats = packed_inputs(gbuffer, normals, settings, acc_ints, acc_floats)
    radius = torch.as_tensor(radius)
    setting = torch.stack([torch.as_tensor(v, dtype=torch.float32, device=gbuffer.depth.device) for v in setting])
    slices, steps = settings[0][0], settings[0][1]
    if gbuffer.depth.is_cuda and steps > MAX_CUDA_STEPS:
        raise ValueError(f"steps: the CUDA backward replays at most {MAX_CUDA_STEPS} steps per side, got {steps}")
    takes = accumulator in ("gtao", "hbao", "pssao")
    return _Walk.apply(accumulator, *inputs, cells, ints, floats, int(channels), scalar_lanes(lanes), radius, setting,
                       tuple(int(x) for x in setting_dimension),
                       ((int(slices) * 2 * int(steps) + 63) // 64,) if takes else None,
                       full_walk(accumulator, gbuffer, settings),
                       replayed_fetches(steps, replaces, full_circle=bool(settings[0][7])))  # (walk_settings' ints)
