"""Error against run time: sweeps of methods x presets x scenes, the per-scene recommendation, and
the cost of background.

* :func:`load_bench_views` renders (and caches) references of built-in scenes, or loads reference files.
* :func:`run_bench` times each method at each preset (median of repeated runs after warm-up, forward
  and forward+backward, CUDA synchronised) with and without the :mod:`~torch_ao.denoise` filter and
  measures its error (MAE, RMSE, PSNR, SSIM on valid pixels) against the reference.
* :func:`recommend` picks, per scene, the cheapest method and preset whose MAE is within a tolerance
  of the best.
* :func:`background_scaling` shows that background costs nothing: an all-background frame is nearly
  free, a half-background frame walks half the pixels.
* :mod:`torch_ao.bench_report` writes the CSV, markdown, JSON and plots; :mod:`torch_ao.bench_auto`
  applies a recommendation (``torch-ao ao --auto``).
"""
from __future__ import annotations

import inspect
import math
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import torch
from torch import nn

from .fit import FitView, load_views, set_mode
from .gbuffer import GBuffer
from .walk import Frame
from .methods import METHODS, PRESETS, get_method
from .metrics import error_metrics

__all__ = [
    "BenchSettings", "BenchView", "QUICK", "DEFAULT", "COLUMNS", "default_cache_dir", "available_methods", "make_method",
    "load_bench_views", "reference_path", "time_call", "run_bench", "recommend", "pareto_front", "time_calls", "aggregate_rows", "background_frames",
    "background_scaling", "environment",
]

#: Columns of a result row (CSV order).
COLUMNS = ("scene", "method", "preset", "slices", "steps", "denoise", "mae", "rmse", "psnr", "ssim",
           "forward_ms", "forward_cpu_ms", "forward_backward_ms", "valid_pixels", "pixels", "batch", "height", "width",
           "radius", "device", "threads", "repeats")


@dataclass
class BenchSettings:
    """A sweep's size. ``QUICK`` finishes in a few minutes on a 2-core CPU."""

    scenes: tuple[str, ...]
    presets: tuple[str, ...]
    height: int
    width: int
    spp: int
    repeats: int
    warmup: int = 1


DEFAULT = BenchSettings(("sphere_on_plane", "room_corner", "fence", "stairs", "floating", "poles"),
                        ("low", "medium", "high", "ultra"), 144, 256, 256, 5)
QUICK = BenchSettings(("sphere_on_plane", "room_corner", "fence"), ("low", "medium", "high"), 72, 96, 64, 3)


def default_cache_dir() -> Path:
    """``$TORCH_AO_CACHE``, else ``~/.cache/torch_ao``."""
    env = os.environ.get("TORCH_AO_CACHE")
    return Path(env).expanduser() if env else Path("~/.cache/torch_ao").expanduser()


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


def make_method(factory: MethodFactory, preset: str, *, radius: float | None = None,
                params: Mapping[str, object] | None = None) -> nn.Module:
    """``factory(preset=..., radius=..., **params)`` in its hard/default mode (``mode="hard"`` where the
    module has a mode). Arguments the factory does not take are left out."""
    try:
        accepted = inspect.signature(factory).parameters
        takes_all = any(p.kind == p.VAR_KEYWORD for p in accepted.values())
    except (TypeError, ValueError):
        accepted, takes_all = {}, True
    kwargs = {"preset": preset, **({"radius": radius} if radius is not None else {}), **dict(params or {})}
    if "mode" in accepted:
        kwargs.setdefault("mode", "hard")
    kwargs = {k: v for k, v in kwargs.items() if takes_all or k in accepted}
    module = factory(**kwargs)
    set_mode(module, "hard")
    return module


# --------------------------------------------------------------------------------------------- references
@dataclass
class BenchView(FitView):
    """A reference view with the reference's maximum ray distance (the methods' default radius)."""

    max_distance: float = math.inf


def _load_view(path: str | os.PathLike, name: str, device=None) -> BenchView:
    from .io import read_npz

    v = load_views([path], device=device)[0]
    md = read_npz(path).get("max_distance")
    md = float(md) if md is not None and md.size == 1 else math.inf
    return BenchView(v.gbuffer, v.reference, v.stderr, name=name, max_distance=md)


def reference_path(cache_dir: str | os.PathLike, scene: str, height: int, width: int, spp: int,
                   max_distance: float, seed: int = 0) -> Path:
    """The cache file of a built-in scene's reference at these settings."""
    r = "inf" if math.isinf(max_distance) else f"{max_distance:g}"
    return Path(cache_dir) / "references" / f"{scene}_{width}x{height}_spp{spp}_R{r}_seed{seed}.npz"


def load_bench_views(scenes: Sequence[str] = (), files: Sequence[str | os.PathLike] = (), *, height: int = 72,
                     width: int = 96, spp: int = 64, max_distance: float = 1.0, seed: int = 0,
                     cache_dir: str | os.PathLike | None = None, device=None, progress: bool = True,
                     log: Callable[[str], None] | None = print) -> list[FitView]:
    """Reference views: built-in ``scenes`` (rendered once, then read from ``cache_dir``) and reference
    ``files`` (``.npz`` with an ``ao`` array). Each view is named after its scene or file stem."""
    from .reference import get_scene, render_reference

    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    views = []
    for name in scenes:
        path = reference_path(cache, name, height, width, spp, max_distance, seed)
        if not path.exists():
            if log is not None:
                log(f"rendering reference {name} ({width}x{height}, {spp} spp, R={max_distance:g}) -> {path}")
            ref = render_reference(get_scene(name), height=height, width=width, spp=spp, max_distance=max_distance,
                                   seed=seed, uniform=False, progress=progress)
            path.parent.mkdir(parents=True, exist_ok=True)
            ref.save(path)
        views.append(_load_view(path, name, device))
    for f in files:
        views.append(_load_view(f, Path(f).stem, device))
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise ValueError(f"reference: two views share a name ({', '.join(names)}); rename the files")
    return views


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
        views: reference views (:func:`load_bench_views`).
        methods: ``{name: factory}``; a factory takes ``preset=``, ``radius=`` (and ``params[name]``).
        presets: names from :data:`~torch_ao.methods.PRESETS`.
        denoise: also run every method followed by ``denoiser`` (default :class:`~torch_ao.denoise.Denoiser()`).
        backward: also time forward+backward (gradients to depth and to the module's parameters), in the
            mode fitting uses (``mode="soft"`` for modules that have one; errors are always measured hard).
        radius: the methods' world radius (default: each view's reference ``max_distance`` when finite, else 1).
        params: per-method constructor arguments (e.g. fitted thickness).
    """
    from tqdm.auto import tqdm

    from .denoise import Denoiser

    device = torch.device(device)
    for p in presets:
        if p not in PRESETS:
            raise ValueError(f"presets: unknown preset {p!r}; expected some of {', '.join(PRESETS)}")
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
                    slices, steps = getattr(module, "slices", PRESETS[preset][0]), getattr(module, "steps", PRESETS[preset][1])
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
                            "steps": int(steps), "denoise": den, **err, "forward_ms": fwd * 1e3, "forward_cpu_ms": fwd_cpu * 1e3,
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


# --------------------------------------------------------------------------------------------- analysis
def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points ``(cost, error)`` not dominated by another (lower or equal in both, lower in
    one), sorted by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        c, e = points[i]
        if math.isnan(c) or math.isnan(e):
            continue
        if e < best:
            front.append(i)
            best = e
    return front


def aggregate_rows(rows: Sequence[dict], metric: str = "mae", cost: str = "forward_ms") -> list[dict]:
    """Mean ``metric`` and ``cost`` over scenes per (method, preset, denoise), for configurations run on
    every scene; rows named ``scene="all"``."""
    scenes = {r["scene"] for r in rows}
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["method"], r["preset"], bool(r["denoise"])), []).append(r)
    out = []
    for (method, preset, den), rs in groups.items():
        if {r["scene"] for r in rs} != scenes:
            continue
        row = {"scene": "all", "method": method, "preset": preset, "denoise": den,
               "slices": rs[0].get("slices"), "steps": rs[0].get("steps")}
        for key in ("mae", "rmse", "psnr", "ssim", "forward_ms", "forward_cpu_ms", "forward_backward_ms"):
            vals = [float(r[key]) for r in rs if key in r]
            row[key] = statistics.fmean(vals) if vals else math.nan
        out.append(row)
    return out


def recommend(rows: Sequence[dict], tolerance: float = 0.01, *, metric: str = "mae", cost: str = "forward_ms",
              denoise: bool | None = False, include_all: bool = True) -> dict[str, dict]:
    """Per scene, the cheapest configuration whose ``metric`` (lower is better; MAE by default) is within
    ``tolerance`` (absolute) of the scene's best.

    Args:
        rows: result rows (:func:`run_bench`, or built by hand: ``scene``, ``method``, ``preset``,
            ``metric`` and ``cost`` keys are enough).
        tolerance: allowed excess error over the best (``0`` = the best configuration).
        denoise: only rows with this ``denoise`` flag (``None`` = all rows).
        include_all: add ``"all"``, the same choice on the mean over scenes (for frames not in the sweep).

    Returns:
        ``{scene: {"method", "preset", "denoise", metric, cost, "best": {...}, "tolerance"}}``.
    """
    if not (isinstance(tolerance, (int, float)) and tolerance >= 0 and math.isfinite(tolerance)):
        raise ValueError(f"tolerance: expected a finite number >= 0, got {tolerance!r}")
    use = [r for r in rows if denoise is None or bool(r.get("denoise", False)) == denoise]
    use = [r for r in use if not (math.isnan(float(r[metric])) or math.isnan(float(r[cost])))]
    by_scene: dict[str, list[dict]] = {}
    for r in use:
        by_scene.setdefault(str(r["scene"]), []).append(r)
    if include_all and len(by_scene) > 0:
        agg = aggregate_rows(use, metric, cost)
        if agg:
            by_scene["all"] = agg
    out = {}
    for scene, rs in by_scene.items():
        best = min(rs, key=lambda r: (float(r[metric]), float(r[cost])))
        limit = float(best[metric]) + tolerance
        ok = [r for r in rs if float(r[metric]) <= limit + 1e-12]
        pick = min(ok, key=lambda r: (float(r[cost]), float(r[metric])))
        out[scene] = {
            "method": pick["method"], "preset": pick["preset"], "denoise": bool(pick.get("denoise", False)),
            metric: float(pick[metric]), cost: float(pick[cost]),
            "best": {"method": best["method"], "preset": best["preset"], "denoise": bool(best.get("denoise", False)),
                     metric: float(best[metric]), cost: float(best[cost])},
            "tolerance": float(tolerance), "metric": metric, "cost": cost,
        }
    return out


# --------------------------------------------------------------------------------------------- background
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

    from .examples import plane_gbuffer

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


