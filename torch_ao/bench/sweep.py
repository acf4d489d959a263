"""The sweep: each method at each preset on each reference view, timed and measured against the reference.

Times are medians of repeated runs after warm-up (forward, and forward+backward in the mode fitting
uses), CUDA synchronised; the error (MAE, RMSE, PSNR, SSIM on valid pixels) is always measured in
hard mode. One row per view x method x preset x (without, with the denoiser).
"""
from __future__ import annotations

import inspect
import math
import os
import statistics
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Mapping, Sequence

import torch
from torch import nn

from ..fit import set_mode
from ..gbuffer import GBuffer
from ..methods import METHODS, PRESETS, get_method
from ..methods.common import split_preset
from ..metrics import error_metrics
from ..options import Option
from ..reference.sampling import MAX_SPP
from ..views import FitView

__all__ = ["SIZE_OPTIONS", "BenchSettings", "QUICK", "DEFAULT", "COLUMNS", "MethodFactory", "available_methods", "accepted_arguments",
           "make_method", "time_call", "time_calls", "run_bench", "environment"]

#: Columns of a result row (CSV order).
COLUMNS = ("scene", "method", "preset", "slices", "steps", "resolution", "denoise", "mae", "rmse", "psnr", "ssim",
           "forward_ms", "forward_cpu_ms", "forward_backward_ms", "valid_pixels", "pixels", "batch", "height", "width",
           "radius", "device", "threads", "repeats")


#: The size of a sweep's references and timings; :class:`BenchSettings` checks its values with these.
SIZE_OPTIONS = (
    Option("height", 144, "reference height of the built-in scenes", int, unit="pixels", minimum=1),
    Option("width", 256, "reference width of the built-in scenes", int, unit="pixels", minimum=1),
    Option("spp", 256, "reference AO rays per pixel (the renderer needs at least 2, and takes at most 65536)", int,
           unit="rays", minimum=2, maximum=MAX_SPP),
    Option("repeats", 5, "timed runs per measurement (the median is reported)", int, minimum=1),
    Option("warmup", 1, "untimed runs before timing", int, minimum=0),
)


@dataclass
class BenchSettings:
    """A sweep's size (see :data:`SIZE_OPTIONS`). ``QUICK`` finishes in a few minutes on a 2-core CPU."""

    scenes: tuple[str, ...]
    presets: tuple[str, ...]
    height: int
    width: int
    spp: int
    repeats: int
    warmup: int = 1

    def __post_init__(self) -> None:
        for opt in SIZE_OPTIONS:
            opt.check(getattr(self, opt.name))


# the @half presets walk a quarter of the pixels: the sweep shows where that pays (error against time)
DEFAULT = BenchSettings(("sphere_on_plane", "room_corner", "fence", "stairs", "floating", "poles"),
                        ("low", "medium", "high", "high_steps", "very_high", "very_high_steps", "ultra", "medium@half",
                         "high@half", "ultra@half"),
                        **{o.name: o.default for o in SIZE_OPTIONS})
QUICK = BenchSettings(("sphere_on_plane", "room_corner", "fence"), ("low", "medium", "high", "high@half"), 72, 96, 64, 3)


def environment(device: torch.device | str = "cpu") -> dict:
    """Where the numbers come from: device name, thread count, library versions."""
    device = torch.device(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({os.cpu_count()} cores)"
    return {"device": str(device), "device_name": name, "threads": torch.get_num_threads(),
            "torch": torch.__version__, "cpu_count": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}


# --------------------------------------------------------------------------------------------- methods
MethodFactory = Callable[..., nn.Module]


def available_methods(names: Iterable[str] | None = None, *, log: Callable[[str], None] | None = print) -> dict[str, MethodFactory]:
    """``{name: class}`` of the named registry methods (default: all of them)."""
    out = {}
    for name in (list(METHODS) if names is None else list(names)):
        if name not in METHODS:
            raise ValueError(f"methods: unknown method {name!r}; expected some of {', '.join(METHODS)}")
        out[name] = get_method(name)
    return out


def accepted_arguments(factory: MethodFactory) -> set[str] | None:
    """The keyword arguments ``factory`` takes: the names of its ``options()`` for a method class, else
    those of its signature; ``None`` when it takes any (``**kwargs``) or its signature cannot be read."""
    if hasattr(factory, "options"):
        return set(factory.options())
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return None
    if any(p.kind == p.VAR_KEYWORD for p in params):
        return None
    return {p.name for p in params}


def make_method(factory: MethodFactory, preset: str, *, radius: float | None = None,
                params: Mapping[str, object] | None = None) -> nn.Module:
    """``factory(preset=..., radius=..., **params)`` in its hard/default mode (``mode="hard"`` where the
    module has a mode). Arguments the factory does not take (:func:`accepted_arguments`) are left out."""
    accepted = accepted_arguments(factory)
    kwargs = {"preset": preset, **({"radius": radius} if radius is not None else {}), **dict(params or {})}
    if accepted is not None and "mode" in accepted:
        kwargs.setdefault("mode", "hard")
    kwargs = {k: v for k, v in kwargs.items() if accepted is None or k in accepted}
    module = factory(**kwargs)
    set_mode(module, "hard")
    return module


# --------------------------------------------------------------------------------------------- timing
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_calls(fn: Callable[[], object], *, repeats: int = 5, warmup: int = 1, device="cpu") -> tuple[float, float]:
    """Median wall time and median process CPU time (all threads) of ``fn()`` in seconds over ``repeats``
    runs after ``warmup`` runs (CUDA synchronised). On a loaded machine the CPU time is the steadier one."""
    device = torch.device(device)
    for _ in range(max(0, warmup)):
        fn()
    _sync(device)
    wall, cpu = [], []
    for _ in range(max(1, repeats)):
        _sync(device)
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        _sync(device)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def time_call(fn: Callable[[], object], *, repeats: int = 5, warmup: int = 1, device="cpu") -> float:
    """Median wall time of ``fn()`` in seconds over ``repeats`` runs after ``warmup`` runs (CUDA synchronised)."""
    return time_calls(fn, repeats=repeats, warmup=warmup, device=device)[0]


def _with_grad_depth(gb: GBuffer) -> GBuffer:
    return GBuffer(depth=gb.depth.detach().clone().requires_grad_(True), camera=gb.camera, normals=gb.normals,
                   light=gb.light, mask=gb.mask, object_id=gb.object_id)


def _pipeline(module: nn.Module, denoiser: nn.Module | None):
    def run(gb: GBuffer):
        out = module(gb)
        vis, ind = out.visibility, getattr(out, "indirect", None)
        if denoiser is not None:
            d = denoiser(vis, gb, indirect=ind)
            vis, ind = d.visibility, d.indirect
        return vis, ind
    return run


def _forward_backward(run, gb: GBuffer) -> Callable[[], bool]:
    def step() -> bool:
        g = _with_grad_depth(gb)
        vis, ind = run(g)
        loss = vis.sum() + (ind.sum() if ind is not None else 0.0)
        if not loss.requires_grad:
            return False
        loss.backward()
        return True
    return step


# --------------------------------------------------------------------------------------------- sweep
def run_bench(views: Sequence[FitView], methods: Mapping[str, MethodFactory], presets: Sequence[str], *,
              denoise: bool = True, backward: bool = True, repeats: int = 5, warmup: int = 1, device="cpu",
              radius: float | None = None, params: Mapping[str, Mapping[str, object]] | None = None,
              denoiser: nn.Module | None = None, progress: bool = True,
              log: Callable[[str], None] | None = print) -> list[dict]:
    """One row per view x method x preset x (without, with the denoiser): error and median times.

    Args:
        views: reference views (:func:`~torch_ao.views.load_bench_views`).
        methods: ``{name: factory}``; a factory takes ``preset=``, ``radius=`` (and ``params[name]``).
        presets: names from :data:`~torch_ao.methods.PRESETS`, optionally with a resolution (``"high@half"``,
            :data:`~torch_ao.methods.common.PRESET_NAMES`).
        denoise: also run every method followed by ``denoiser`` (default :class:`~torch_ao.denoise.Denoiser()`).
        backward: also time forward+backward (gradients to depth and to the module's parameters), in the
            mode fitting uses (``mode="soft"`` for modules that have one; errors are always measured hard).
        radius: the methods' world radius (default: each view's reference ``max_distance`` when finite, else 1).
        params: per-method constructor arguments (e.g. fitted thickness).
    """
    from tqdm.auto import tqdm

    from ..denoise import Denoiser

    device = torch.device(device)
    for p in presets:
        try:
            split_preset(p)
        except ValueError as err:
            raise ValueError(f"presets: {err}") from None
    if not views:
        raise ValueError("views: nothing to benchmark (no scene and no reference file)")
    if not methods:
        raise ValueError("methods: no method available to benchmark")
    denoiser = (denoiser or Denoiser()).to(device) if denoise else None
    variants = (False, True) if denoise else (False,)
    rows: list[dict] = []
    total = len(views) * len(methods) * len(presets)
    bar = tqdm(total=total, desc="bench", unit="run", disable=not progress, leave=False)
    threads = torch.get_num_threads()
    try:
        for view in views:
            gb = view.gbuffer.to(device)
            ref = view.reference.to(device)
            valid = gb.valid
            r = radius if radius is not None else _view_radius(view)
            for name, factory in methods.items():
                for preset in presets:
                    bar.set_postfix_str(f"{view.name} {name} {preset}")
                    module = make_method(factory, preset, radius=r, params=(params or {}).get(name)).to(device)
                    quality, resolution = split_preset(preset)
                    slices, steps = getattr(module, "slices", PRESETS[quality][0]), getattr(module, "steps", PRESETS[quality][1])
                    resolution = getattr(module, "resolution", resolution or "full")
                    try:
                        with torch.no_grad():
                            module(gb)
                    except ValueError as err:  # e.g. indirect light on a G-buffer without light
                        if log is not None:
                            log(f"note: {name} {preset} skipped on {view.name}: {err}")
                        bar.update(1)
                        continue
                    for den in variants:
                        run = _pipeline(module, denoiser if den else None)
                        with torch.no_grad():
                            vis, _ = run(gb)
                            fwd, fwd_cpu = time_calls(lambda: run(gb), repeats=repeats, warmup=warmup, device=device)
                        fb = math.nan
                        if backward:
                            # Gradients need the differentiable mode (hard bitmasks have zero gradient).
                            set_mode(module, "soft")
                            step = _forward_backward(run, gb)
                            if step():
                                fb = time_call(step, repeats=repeats, warmup=max(0, warmup - 1), device=device)
                            module.zero_grad(set_to_none=True)
                            set_mode(module, "hard")
                        err = error_metrics(vis, ref, valid)
                        B, _, H, W = gb.depth.shape
                        rows.append({
                            "scene": view.name, "method": name, "preset": preset, "slices": int(slices),
                            "steps": int(steps), "resolution": resolution, "denoise": den, **err, "forward_ms": fwd * 1e3, "forward_cpu_ms": fwd_cpu * 1e3,
                            "forward_backward_ms": fb * 1e3, "valid_pixels": int(valid.sum()), "pixels": B * H * W,
                            "batch": B, "height": H, "width": W, "radius": float(r), "device": str(device),
                            "threads": threads, "repeats": repeats,
                        })
                    bar.update(1)
    finally:
        bar.close()
    return rows


def _view_radius(view: FitView) -> float:
    md = getattr(view, "max_distance", None)
    return float(md) if md is not None and math.isfinite(md) and md > 0 else 1.0


