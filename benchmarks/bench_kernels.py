"""Candidate technologies for a fused hard-bitmask walk, measured side by side on this CPU.

The computation is ``BitmaskAO(variant="default", mode="hard")`` (two-sided walk, uniform sectors,
bilinear fetch, off-screen samples dropped) on ``torch_ao.examples.example_gbuffer`` (a floor meeting a
wall). Candidates:

* ``torch``: the library's tensor-op walk (the reference).
* ``kernel``: ``torch_ao.kernels.bitmask_hard``, C++ with ATen's ``Vectorized<float>`` (SLEEF, as
  torch's CPU kernels) built with ``torch.utils.cpp_extension``.
* ``pointwise``: the same walk as ``(B, H, W)`` tensor ops, slice and step loops unrolled in Python,
  one gather of the four depth taps per sample, int32 bit operations and a SWAR popcount, background
  masked (no list of valid pixels); ``pointwise-compiled`` is it under ``torch.compile`` (Inductor's
  vectorised C++), whose compile time is reported separately.
* ``numba``: a per-pixel loop in registers, ``@njit(parallel=True)`` (``pip install numba``).
* ``warp``: the same loop as an NVIDIA Warp kernel (``pip install warp-lang``; one source for CPU and CUDA).
* ``drjit``: the pointwise walk's operations on Dr.Jit's LLVM arrays, traced into one vectorised kernel
  (``pip install drjit``; it needs LLVM 16 or later: on Debian 12, ``apt install libllvm19`` and
  ``DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so``; with the system's LLVM 15 its ``atan2`` and
  ``clip`` fail to compile, ``fmaximum`` / ``fminimum`` not selectable).

Each candidate runs in its own subprocess (honest peak memory: peak RSS minus RSS before the first
call). Reported: best and median wall time of ``--repeat`` calls after a warm-up, CPU time per call,
first-call time (compile/build), peak MB, and the fraction of pixels identical to ``torch`` and the
maximum difference. The machine may be shared: read the ratios of one run.

    python benchmarks/bench_kernels.py --threads 1
    python benchmarks/bench_kernels.py --size 320x180 --only kernel pointwise numba
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CANDIDATES = ("torch", "kernel", "pointwise", "pointwise-compiled", "numba", "warp", "drjit")


# ------------------------------------------------------------------------------- pointwise torch
def _ign(u: torch.Tensor, v: torch.Tensor, seed: int) -> torch.Tensor:
    from torch_ao.walk import interleaved_gradient_noise

    return interleaved_gradient_noise(u, v, seed).to(torch.float32)


def _pixel_noise(H: int, W: int) -> torch.Tensor:
    """``(2, H, W)``: each pixel's slice rotation and step offset (SlicePattern's interleaved gradient noise)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    return torch.stack((_ign(u, v, 0), _ign(u + 37.0, v + 59.0, 1)))


def slice_frame(c, sn, e1x, e1z, e2x, e2y, e2z, Vx, Vy, Vz, Nx, Ny, Nz, Px, Py, depth, fx, fy):
    """One slice's tangent ``T`` (from its angle's ``cos``, ``sin`` and the basis ``e1``, ``e2`` around V),
    the projected normal's components along ``T`` and ``V``, and the screen motion ``(du, dv)`` per world
    unit along ``T``. Only arithmetic operators: it runs on tensors (pointwise) and, jitted, on floats (numba)."""
    Tx, Ty, Tz = c * e1x + sn * e2x, sn * e2y, c * e1z + sn * e2z
    ax, ay, az = Ty * Vz - Tz * Vy, Tz * Vx - Tx * Vz, Tx * Vy - Ty * Vx
    nd = Nx * ax + Ny * ay + Nz * az
    qx, qy, qz = Nx - ax * nd, Ny - ay * nd, Nz - az * nd
    du = fx * (Tx + Px * Tz / depth) / depth
    dv = -fy * (Ty + Py * Tz / depth) / depth
    return Tx, Ty, Tz, qx * Tx + qy * Ty + qz * Tz, qx * Vx + qy * Vy + qz * Vz, du, dv


def pointwise_walk(P, N, inv, depth, valid, K, slices: int, steps: int, radius: float, thickness: float,
                   epsilon: float) -> torch.Tensor:
    """Hard bitmask visibility ``(B,1,H,W)`` from channel-last ``P``, ``N`` ``(B,H,W,3)``, ``inv`` (inverse
    depth, NaN where invalid), ``depth``, ``valid`` ``(B,H,W)`` and ``K`` ``(B,4)`` (fx, fy, cx, cy)."""
    B, H, W, _ = P.shape
    fx, fy, cx, cy = (K[:, i].view(B, 1, 1) for i in range(4))
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    u, v = u.expand(B, H, W), v.expand(B, H, W)
    a, xi = _pixel_noise(H, W).unbind(0)
    Px, Py, Pz = P.unbind(-1)
    Nx, Ny, Nz = N.unbind(-1)
    n = torch.sqrt(Px * Px + Py * Py + Pz * Pz).clamp_min(1e-12)
    Vx, Vy, Vz = -Px / n, -Py / n, -Pz / n
    n1 = torch.sqrt(Vz * Vz + Vx * Vx).clamp_min(1e-12)
    e1x, e1z = Vz / n1, -Vx / n1
    e2x, e2y, e2z = Vy * e1z, Vz * e1x - Vx * e1z, -Vy * e1x
    flat = inv.reshape(B, H * W)
    base = (torch.arange(B) * (H * W)).view(B, 1, 1)
    visible = torch.zeros(B, H, W, dtype=torch.int32)
    for s in range(slices):
        psi = (a + s) * (math.pi / slices)
        Tx, Ty, Tz, along_t, along_v, du, dv = slice_frame(torch.cos(psi), torch.sin(psi), e1x, e1z, e2x, e2y, e2z,
                                                           Vx, Vy, Vz, Nx, Ny, Nz, Px, Py, depth, fx, fy)
        shift = (math.pi / 2 - torch.atan2(along_t, along_v)) / math.pi
        length = torch.sqrt(du * du + dv * dv)
        uu, uv = du / length.clamp_min(1e-12), dv / length.clamp_min(1e-12)
        span = (radius * length - 1.0).clamp_min(0)
        occ = torch.zeros(B, H, W, dtype=torch.int32)
        for side in (1, -1):
            for j in range(steps):
                dist = 1.0 + span * ((j + xi) / steps)
                su, sv = u + dist * (side * uu), v + dist * (side * uv)
                u0, v0 = torch.floor(su), torch.floor(sv)
                fu, fv = su - u0, sv - v0
                iu, iv = u0.clamp(-1, W).to(torch.int32), v0.clamp(-1, H).to(torch.int32)
                c0, c1 = iu.clamp(0, W - 1), (iu + 1).clamp(0, W - 1)
                r0, r1 = iv.clamp(0, H - 1) * W, (iv + 1).clamp(0, H - 1) * W
                taps = torch.stack((r0 + c0, r0 + c1, r1 + c0, r1 + c1), -1).view(B, -1) + base.view(B, 1)
                t = flat.view(-1)[taps.view(-1)].view(B, H, W, 4)
                ok = ~torch.isnan(t).any(-1) & (u0 >= 0) & (u0 + 1 < W) & (v0 >= 0) & (v0 + 1 < H)
                t0, t1, t2, t3 = t.unbind(-1)
                ds = 1.0 / torch.lerp(torch.lerp(t0, t1, fu), torch.lerp(t2, t3, fu), fv)
                dx = (su.clamp(0, W - 1) - cx) / fx * ds - Px
                dy = -(sv.clamp(0, H - 1) - cy) / fy * ds - Py
                dz = -ds - Pz
                ok = ok & (dx * dx + dy * dy + dz * dz > 1e-20 * depth * depth)
                dx, dy, dz = torch.where(ok, dx, -Vx), torch.where(ok, dy, -Vy), torch.where(ok, dz, -Vz)
                av = dx * Vx + dy * Vy + dz * Vz
                at = side * (dx * Tx + dy * Ty + dz * Tz)
                xf = (shift + torch.atan2(at, av) * (side / math.pi)).clamp(0, 1)
                xb = (shift + torch.atan2(at, av - thickness) * (side / math.pi)).clamp(0, 1)
                lo, hi = (xf, xb) if side > 0 else (xb, xf)
                k0 = torch.floor(lo * 32).clamp(0, 32).to(torch.int32)
                k1 = (k0 + torch.ceil((hi - lo) * 32 - epsilon).clamp(0, 32).to(torch.int32)).clamp_max(32)
                low = lambda k: torch.where(k >= 32, -1, (1 << k.clamp_max(31)) - 1)  # noqa: E731
                occ = occ | (low(k1) & ~low(k0))
        x = occ - ((occ >> 1) & 0x55555555)
        x = (x & 0x33333333) + ((x >> 2) & 0x33333333)
        x = (x + (x >> 4)) & 0x0F0F0F0F
        visible = visible + (32 - ((x * 0x01010101) >> 24))
    vis = visible.to(torch.float32) / 32 / slices
    return torch.where(valid, vis, 1.0).unsqueeze(1)


# ------------------------------------------------------------------------------------- numba
def numba_walk():
    import numba
    import numpy as np

    f32 = np.float32
    frame = numba.njit(slice_frame)

    @numba.njit(parallel=True, cache=True)
    def walk(P, Nrm, inv, depth, valid, K, slices, steps, radius, thickness, epsilon, noise, out):
        B, H, W, _ = P.shape
        pi = f32(math.pi)
        for r in numba.prange(B * H):
            b, v = r // H, r % H
            fx, fy, cx, cy = K[b, 0], K[b, 1], K[b, 2], K[b, 3]
            for u in range(W):
                if not valid[b, v, u]:
                    out[b, 0, v, u] = 1.0
                    continue
                px, py, pz = P[b, v, u, 0], P[b, v, u, 1], P[b, v, u, 2]
                nx, ny, nz = Nrm[b, v, u, 0], Nrm[b, v, u, 1], Nrm[b, v, u, 2]
                d = depth[b, v, u]
                n = max(math.sqrt(px * px + py * py + pz * pz), f32(1e-12))
                vx, vy, vz = -px / n, -py / n, -pz / n
                n1 = max(math.sqrt(vz * vz + vx * vx), f32(1e-12))
                e1x, e1z = vz / n1, -vx / n1
                e2x, e2y, e2z = vy * e1z, vz * e1x - vx * e1z, -vy * e1x
                a, xi = noise[0, b, v, u], noise[1, b, v, u]
                visible = 0
                for s in range(slices):
                    psi = (a + f32(s)) * (pi / f32(slices))
                    tx, ty, tz, along_t, along_v, du, dv = frame(math.cos(psi), math.sin(psi), e1x, e1z, e2x, e2y, e2z,
                                                                 vx, vy, vz, nx, ny, nz, px, py, d, fx, fy)
                    shift = (pi / f32(2) - math.atan2(along_t, along_v)) / pi
                    length = math.sqrt(du * du + dv * dv)
                    uu, uv = du / max(length, f32(1e-12)), dv / max(length, f32(1e-12))
                    span = max(radius * length - f32(1), f32(0))
                    occ = np.uint32(0)
                    for side in (1, -1):
                        sg = f32(side)
                        for j in range(steps):
                            dist = f32(1) + span * ((f32(j) + xi) / f32(steps))
                            su, sv = f32(u) + dist * sg * uu, f32(v) + dist * sg * uv
                            u0, v0 = math.floor(su), math.floor(sv)
                            if u0 < 0 or u0 + 1 >= W or v0 < 0 or v0 + 1 >= H:
                                continue
                            iu, iv = int(u0), int(v0)
                            t0, t1 = inv[b, iv, iu], inv[b, iv, iu + 1]
                            t2, t3 = inv[b, iv + 1, iu], inv[b, iv + 1, iu + 1]
                            if math.isnan(t0) or math.isnan(t1) or math.isnan(t2) or math.isnan(t3):
                                continue
                            fu, fv = f32(su - u0), f32(sv - v0)
                            top, bottom = t0 + fu * (t1 - t0), t2 + fu * (t3 - t2)
                            ds = f32(1) / (top + fv * (bottom - top))
                            dx = (su - cx) / fx * ds - px
                            dy = -(sv - cy) / fy * ds - py
                            dz = -ds - pz
                            if not dx * dx + dy * dy + dz * dz > f32(1e-20) * d * d:
                                continue
                            av = dx * vx + dy * vy + dz * vz
                            at = sg * (dx * tx + dy * ty + dz * tz)
                            xf = min(max(shift + math.atan2(at, av) * (sg / pi), f32(0)), f32(1))
                            xb = min(max(shift + math.atan2(at, av - thickness) * (sg / pi), f32(0)), f32(1))
                            lo, hi = (xf, xb) if side > 0 else (xb, xf)
                            k0 = min(max(int(math.floor(lo * f32(32))), 0), 32)
                            k1 = min(k0 + min(max(int(math.ceil((hi - lo) * f32(32) - epsilon)), 0), 32), 32)
                            occ |= np.uint32(((np.uint64(1) << np.uint64(k1)) - np.uint64(1))
                                             & ~((np.uint64(1) << np.uint64(k0)) - np.uint64(1)))
                    x = occ
                    count = 0
                    while x:
                        x &= x - np.uint32(1)
                        count += 1
                    visible += 32 - count
                out[b, 0, v, u] = f32(visible) / f32(32) / f32(slices)

    def run(P, N, inv, depth, valid, K, slices, steps, radius, thickness, epsilon):
        B, H, W, _ = P.shape
        noise = _pixel_noise(H, W).unsqueeze(1).expand(2, B, H, W)
        out = np.empty((B, 1, H, W), dtype=np.float32)
        walk(P.numpy(), N.numpy(), inv.numpy(), depth.numpy(), valid.numpy(), K.numpy(), slices, steps, f32(radius),
             f32(thickness), f32(epsilon), noise.contiguous().numpy(), out)
        return torch.from_numpy(out)

    return run


# ------------------------------------------------------------------------------------- warp
def warp_walk():
    """The walk as a NVIDIA Warp kernel (``pip install warp-lang``): numba's per-pixel loop, one Warp thread a
    pixel. Warp compiles it to C++ for the CPU (one thread, no SIMD across pixels) and to PTX for CUDA."""
    import warp as wp

    wp.config.quiet = True
    wp.init()

    @wp.func
    def low_bits(k: int):
        if k >= 32:
            return wp.uint32(0xFFFFFFFF)
        return (wp.uint32(1) << wp.uint32(k)) - wp.uint32(1)

    @wp.kernel
    def walk(P: wp.array3d(dtype=wp.vec3), Nrm: wp.array3d(dtype=wp.vec3), inv: wp.array3d(dtype=float),
             depth: wp.array3d(dtype=float), valid: wp.array3d(dtype=wp.int32), K: wp.array2d(dtype=float),
             slices: int, steps: int, radius: float, thickness: float, epsilon: float,
             noise: wp.array4d(dtype=float), out: wp.array3d(dtype=float)):
        b, v, u = wp.tid()
        H, W = inv.shape[1], inv.shape[2]
        if valid[b, v, u] == 0:
            out[b, v, u] = 1.0
            return
        pi = 3.14159265358979
        fx, fy, cx, cy = K[b, 0], K[b, 1], K[b, 2], K[b, 3]
        p, nrm, d = P[b, v, u], Nrm[b, v, u], depth[b, v, u]
        n = wp.max(wp.length(p), 1e-12)
        vx, vy, vz = -p[0] / n, -p[1] / n, -p[2] / n
        n1 = wp.max(wp.sqrt(vz * vz + vx * vx), 1e-12)
        e1x, e1z = vz / n1, -vx / n1
        e2x, e2y, e2z = vy * e1z, vz * e1x - vx * e1z, -vy * e1x
        a, xi = noise[0, b, v, u], noise[1, b, v, u]
        visible = int(0)
        for s in range(slices):
            psi = (a + float(s)) * (pi / float(slices))
            c, sn = wp.cos(psi), wp.sin(psi)
            tx, ty, tz = c * e1x + sn * e2x, sn * e2y, c * e1z + sn * e2z
            ax, ay, az = ty * vz - tz * vy, tz * vx - tx * vz, tx * vy - ty * vx
            nd = nrm[0] * ax + nrm[1] * ay + nrm[2] * az
            qx, qy, qz = nrm[0] - ax * nd, nrm[1] - ay * nd, nrm[2] - az * nd
            du = fx * (tx + p[0] * tz / d) / d
            dv = -fy * (ty + p[1] * tz / d) / d
            shift = (pi / 2.0 - wp.atan2(qx * tx + qy * ty + qz * tz, qx * vx + qy * vy + qz * vz)) / pi
            length = wp.sqrt(du * du + dv * dv)
            uu, uv = du / wp.max(length, 1e-12), dv / wp.max(length, 1e-12)
            span = wp.max(radius * length - 1.0, 0.0)
            occ = wp.uint32(0)
            for side in range(2):
                sg = 1.0 - 2.0 * float(side)
                for j in range(steps):
                    dist = 1.0 + span * ((float(j) + xi) / float(steps))
                    su, sv = float(u) + dist * sg * uu, float(v) + dist * sg * uv
                    u0, v0 = wp.floor(su), wp.floor(sv)
                    if u0 < 0.0 or u0 + 1.0 >= float(W) or v0 < 0.0 or v0 + 1.0 >= float(H):
                        continue
                    iu, iv = int(u0), int(v0)
                    t0, t1 = float(inv[b, iv, iu]), float(inv[b, iv, iu + 1])
                    t2, t3 = float(inv[b, iv + 1, iu]), float(inv[b, iv + 1, iu + 1])
                    if wp.isnan(t0) or wp.isnan(t1) or wp.isnan(t2) or wp.isnan(t3):
                        continue
                    fu, fv = su - u0, sv - v0
                    top, bottom = t0 + fu * (t1 - t0), t2 + fu * (t3 - t2)
                    ds = 1.0 / (top + fv * (bottom - top))
                    dx = (su - cx) / fx * ds - p[0]
                    dy = -(sv - cy) / fy * ds - p[1]
                    dz = -ds - p[2]
                    if not (dx * dx + dy * dy + dz * dz > 1e-20 * d * d):
                        continue
                    av = dx * vx + dy * vy + dz * vz
                    at = sg * (dx * tx + dy * ty + dz * tz)
                    xf = wp.clamp(shift + wp.atan2(at, av) * (sg / pi), 0.0, 1.0)
                    xb = wp.clamp(shift + wp.atan2(at, av - thickness) * (sg / pi), 0.0, 1.0)
                    lo, hi = xf, xb
                    if side == 1:
                        lo, hi = xb, xf
                    k0 = wp.clamp(int(wp.floor(lo * 32.0)), 0, 32)
                    k1 = wp.min(k0 + wp.clamp(int(wp.ceil((hi - lo) * 32.0 - epsilon)), 0, 32), 32)
                    occ = occ | (low_bits(k1) & ~low_bits(k0))
            count = int(0)
            for k in range(32):
                count += int((occ >> wp.uint32(k)) & wp.uint32(1))
            visible += 32 - count
        out[b, v, u] = float(visible) / 32.0 / float(slices)

    def run(P, N, inv, depth, valid, K, slices, steps, radius, thickness, epsilon):
        B, H, W, _ = P.shape
        noise = _pixel_noise(H, W).unsqueeze(1).expand(2, B, H, W).contiguous()
        out = torch.empty(B, H, W)
        wp.launch(walk, dim=(B, H, W), device="cpu",
                  inputs=[wp.from_torch(P, dtype=wp.vec3), wp.from_torch(N, dtype=wp.vec3), wp.from_torch(inv),
                          wp.from_torch(depth), wp.from_torch(valid.to(torch.int32)), wp.from_torch(K), slices, steps,
                          float(radius), float(thickness), float(epsilon), wp.from_torch(noise), wp.from_torch(out)])
        return out.unsqueeze(1)

    return run


# ------------------------------------------------------------------------------------ Dr.Jit
def drjit_walk():
    """The walk in Dr.Jit's LLVM backend (``pip install drjit``; LLVM 16 or later, ``DRJIT_LIBLLVM_PATH``):
    the pointwise walk's operations on Dr.Jit arrays of every pixel, traced in Python and compiled into one
    vectorised loop over the pixels on Dr.Jit's own threads. ``@dr.freeze`` records the first call's kernel and
    replays it: unfrozen, the traced kernel's hash changed from call to call and most calls compiled it again
    (0.3-0.4 s each)."""
    import drjit as dr
    from drjit.llvm import Float, Int, UInt32

    dr.set_thread_count(torch.get_num_threads())

    @dr.freeze
    def walk(Px, Py, Pz, Nx, Ny, Nz, d, inv_flat, live, a, xi, H, W, fx, fy, cx, cy, slices, steps, radius, thickness,
             epsilon):
        live = live > 0.5
        idx = dr.arange(UInt32, H * W)
        u, v = Float(idx % W), Float(idx // W)
        n = dr.maximum(dr.sqrt(Px * Px + Py * Py + Pz * Pz), 1e-12)
        Vx, Vy, Vz = -Px / n, -Py / n, -Pz / n
        n1 = dr.maximum(dr.sqrt(Vz * Vz + Vx * Vx), 1e-12)
        e1x, e1z = Vz / n1, -Vx / n1
        e2x, e2y, e2z = Vy * e1z, Vz * e1x - Vx * e1z, -Vy * e1x
        visible = Int(0)
        for s in range(slices):
            psi = (a + s) * (math.pi / slices)
            Tx, Ty, Tz, along_t, along_v, du, dv = slice_frame(dr.cos(psi), dr.sin(psi), e1x, e1z, e2x, e2y, e2z, Vx,
                                                               Vy, Vz, Nx, Ny, Nz, Px, Py, d, fx, fy)
            shift = (math.pi / 2 - dr.atan2(along_t, along_v)) / math.pi
            length = dr.sqrt(du * du + dv * dv)
            uu, uv = du / dr.maximum(length, 1e-12), dv / dr.maximum(length, 1e-12)
            span = dr.maximum(radius * length - 1.0, 0.0)
            occ = UInt32(0)
            for side in (1, -1):
                for j in range(steps):
                    dist = 1.0 + span * ((j + xi) / steps)
                    su, sv = u + dist * (side * uu), v + dist * (side * uv)
                    u0, v0 = dr.floor(su), dr.floor(sv)
                    ok = live & (u0 >= 0) & (u0 + 1 < W) & (v0 >= 0) & (v0 + 1 < H)
                    base = UInt32(Int(v0)) * W + UInt32(Int(u0))
                    t0, t1 = dr.gather(Float, inv_flat, base, ok), dr.gather(Float, inv_flat, base + 1, ok)
                    t2, t3 = dr.gather(Float, inv_flat, base + W, ok), dr.gather(Float, inv_flat, base + W + 1, ok)
                    ok &= ~(dr.isnan(t0) | dr.isnan(t1) | dr.isnan(t2) | dr.isnan(t3))
                    fu, fv = su - u0, sv - v0
                    top, bottom = t0 + fu * (t1 - t0), t2 + fu * (t3 - t2)
                    ds = 1.0 / (top + fv * (bottom - top))
                    dx = (su - cx) / fx * ds - Px
                    dy = -(sv - cy) / fy * ds - Py
                    dz = -ds - Pz
                    ok &= dx * dx + dy * dy + dz * dz > 1e-20 * d * d
                    av = dx * Vx + dy * Vy + dz * Vz
                    at = side * (dx * Tx + dy * Ty + dz * Tz)
                    xf = dr.clip(shift + dr.atan2(at, av) * (side / math.pi), 0.0, 1.0)
                    xb = dr.clip(shift + dr.atan2(at, av - thickness) * (side / math.pi), 0.0, 1.0)
                    lo, hi = (xf, xb) if side > 0 else (xb, xf)
                    k0 = dr.clip(Int(dr.floor(lo * 32)), 0, 32)
                    k1 = dr.minimum(k0 + dr.clip(Int(dr.ceil((hi - lo) * 32 - epsilon)), 0, 32), 32)
                    low = lambda k: dr.select(k >= 32, UInt32(0xFFFFFFFF),  # noqa: E731
                                              (UInt32(1) << UInt32(dr.minimum(k, 31))) - 1)
                    occ = dr.select(ok, occ | (low(k1) & ~low(k0)), occ)
            visible += 32 - Int(dr.popcnt(occ))
        return dr.select(live, Float(visible) / 32 / slices, 1.0)

    def run(P, N, inv, depth, valid, K, slices, steps, radius, thickness, epsilon):
        B, H, W, _ = P.shape
        if B != 1:
            raise ValueError(f"drjit: expected one image, got a batch of {B}")
        flat = lambda x: Float(x.reshape(-1).numpy())  # noqa: E731
        vis = walk(*(flat(P[..., c]) for c in range(3)), *(flat(N[..., c]) for c in range(3)), flat(depth), flat(inv),
                   flat(valid.float()), *(flat(x) for x in _pixel_noise(H, W)), H, W,
                   *(float(K[0, i]) for i in range(4)), slices, steps, float(radius), float(thickness), float(epsilon))
        dr.eval(vis)
        return torch.from_numpy(vis.numpy()).view(1, 1, H, W)

    return run


# ------------------------------------------------------------------------------------ harness
def _inputs(gb):
    depth = gb.safe_depth[:, 0].contiguous()
    valid = gb.valid[:, 0].contiguous()
    cam = gb.camera
    return (gb.positions().permute(0, 2, 3, 1).contiguous(), gb.view_normals().permute(0, 2, 3, 1).contiguous(),
            torch.where(valid, depth.reciprocal(), torch.nan), depth, valid,
            torch.stack((cam.fx, cam.fy, cam.cx, cam.cy), -1).to(torch.float32).contiguous())


def child(spec: dict) -> dict:
    import torch_ao
    from torch_ao.examples import example_gbuffer

    torch.set_num_threads(spec["threads"])
    W, H = spec["size"]
    gb = example_gbuffer(H, W)
    slices, steps = spec["setting"]
    module = torch_ao.BitmaskAO(mode="hard", slices=slices, steps=steps, radius=1.0, thickness=0.5, backend="torch")
    settings = (slices, steps, 1.0, 0.5, module.sector_epsilon)
    name = spec["candidate"]
    if name == "torch":
        fn = lambda: module(gb).visibility  # noqa: E731
    elif name == "kernel":
        from torch_ao.kernels import bitmask_hard

        normals = gb.view_normals()
        fn = lambda: bitmask_hard(gb, normals, slices=slices, steps=steps, radius=1.0, thickness=0.5)  # noqa: E731
    else:
        inputs = _inputs(gb)
        walk = {"pointwise": pointwise_walk}.get(name)
        if name == "numba":
            import numba

            numba.set_num_threads(spec["threads"])
        if name in ("numba", "warp", "drjit"):
            walk = {"numba": numba_walk, "warp": warp_walk, "drjit": drjit_walk}[name]()
        elif name == "pointwise-compiled":
            walk = torch.compile(pointwise_walk, dynamic=False)
        fn = lambda: walk(*inputs, *settings)  # noqa: E731
    baseline = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with torch.no_grad():
        t0 = time.perf_counter()
        out = fn()  # first call: compile / build / warm-up
        first = time.perf_counter() - t0
        walls, cpus = [], []
        for _ in range(spec["repeat"]):
            t0, c0 = time.perf_counter(), time.process_time()
            out = fn()
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with torch.no_grad():
        reference = module(gb).visibility
    walls.sort()
    return {"best_ms": 1e3 * walls[0], "median_ms": 1e3 * walls[len(walls) // 2], "cpu_ms": 1e3 * min(cpus),
            "first_s": first, "peak_mb": (peak - baseline) / 1024, "identical": float((out == reference).float().mean()),
            "max_diff": float((out - reference).abs().max())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x360", help="WxH")
    ap.add_argument("--settings", nargs="+", default=["4x4"], help="SLICESxSTEPS")
    ap.add_argument("--only", nargs="+", choices=CANDIDATES, default=list(CANDIDATES))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return 0
    size = tuple(map(int, args.size.split("x")))
    print(f"{args.size}, {args.threads} threads, torch {torch.__version__}, CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}")
    print("| candidate | slices x steps | best ms | median ms | CPU ms/call | first call s | peak MB | identical | max diff |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for setting in args.settings:
        for name in args.only:
            spec = {"candidate": name, "size": size, "setting": tuple(map(int, setting.split("x"))),
                    "repeat": args.repeat, "threads": args.threads}
            proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)], capture_output=True,
                                  text=True, env={**os.environ, "OMP_NUM_THREADS": str(args.threads)})
            if proc.returncode:
                print(f"| {name} | {setting} | failed: {proc.stderr.strip().splitlines()[-1]} |", flush=True)
                continue
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            print(f"| {name} | {setting} | {r['best_ms']:.1f} | {r['median_ms']:.1f} | {r['cpu_ms']:.1f} | "
                  f"{r['first_s']:.1f} | {r['peak_mb']:.0f} | {r['identical']:.6f} | {r['max_diff']:.3g} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
