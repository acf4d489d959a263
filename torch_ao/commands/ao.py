"""``torch-ao ao``: run a screen-space AO method on a G-buffer file (or the built-in example)."""
from __future__ import annotations

import argparse
import inspect
import time

import torch

from ..cli import CommandError
from ..examples import example_gbuffer
from ..io import load_gbuffer, save_npz
from ..methods import METHODS, PRESETS, get_method

# Flags that map one-to-one onto constructor arguments (only passed when given).
_FLOAT_FLAGS = ("radius", "thickness", "tau", "falloff_range", "final_power", "bias", "albedo",
                "thickness_heuristic", "thickness_growth", "step_power", "min_step_px", "angle_bias", "fade_distance",
                "flat_surface_bias", "intensity", "distance_bias", "search_scale", "softness")
_CHOICE_FLAGS = {
    "variant": None, "mode": ("hard", "soft", "straight_through"), "rounding": ("ceil", "round", "floor"),
    "weighting": ("uniform", "cosine"), "fetch": ("nearest", "bilinear"), "border": ("clamp", "drop"),
    "azimuth": ("view", "screen"), "normals": ("improved", "kornia"),
    "falloff": ("linear", "quadratic"), "accumulate": ("incremental", "max"), "elevation": ("image", "view"),
    "normalize": ("exact", "none", "ue4", "samples", "directions"), "sample_set": ("ue4_3", "ue4_6", "uniform"),
    "glsl_numerics": ("ieee", "mesa", "mesa_mediump"),
}


def register(sub) -> None:
    p = sub.add_parser(
        "ao",
        help="run an AO method on a G-buffer .npz",
        description="Compute ambient occlusion (and, for ssilvb, indirect light) for a G-buffer file. "
        "Without GBUFFER, runs on a built-in example (a floor meeting a wall).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("gbuffer", nargs="?", help="input .npz (keys: depth, normal, light, intrinsics or fov_y_degrees...)")
    p.add_argument("--method", default="gtao", help=f"one of: {', '.join(sorted(METHODS))}")
    p.add_argument("--preset", choices=sorted(PRESETS), help="quality preset (slices x steps); --slices/--steps override it")
    p.add_argument("--slices", type=int, help="directions per pixel")
    p.add_argument("--steps", type=int, help="samples per side of each slice")
    for name in _FLOAT_FLAGS:
        p.add_argument("--" + name.replace("_", "-"), dest=name, type=float, help=f"method parameter {name} (world units where lengths)")
    for name, choices in _CHOICE_FLAGS.items():
        p.add_argument("--" + name.replace("_", "-"), dest=name, choices=choices, help=f"method option {name}")
    p.add_argument("--no-jitter", action="store_true", help="no per-pixel noise (exact, repeatable comparisons)")
    p.add_argument("--seed", type=int, help="noise seed")
    p.add_argument("--indirect", action="store_true", help="also compute indirect light (methods that support it)")
    p.add_argument("--no-indirect", action="store_true", help="ssilvb: visibility only")
    p.add_argument("--bent-normals", action="store_true", help="also compute bent normals (methods that support it)")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--out", required=False, default="ao.npz", help="output .npz (visibility, and what else was asked)")
    p.add_argument("--png", help="also write a PNG of the visibility")
    p.add_argument("--auto", action="store_true", help="choose --method and --preset by the bench recommendation: the "
                   "cheapest whose MAE is within --tolerance of the best (from --report, else a quick sweep on GBUFFER's 'ao')")
    p.add_argument("--tolerance", type=float, help="with --auto: allowed MAE above the best; when not given, the report's, else 0.01")
    p.add_argument("--report", help="with --auto: a `torch-ao bench` report.json (or its folder)")
    p.add_argument("--fitted", metavar="PARAMS.json", help="run the pipeline a `torch-ao fit` params.json describes "
                   "(method, options, fitted parameters, denoiser) instead of --method and its flags")
    p.add_argument("--denoise", action="store_true", help="filter the output with the edge-aware denoiser "
                   "(torch_ao.Denoiser, default settings)")
    p.set_defaults(func=run)


def _constructor_arguments(cls) -> set[str]:
    """Keyword arguments a class accepts, following ``**kwargs`` up the class hierarchy."""
    names: set[str] = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        params = inspect.signature(init).parameters.values()
        names |= {p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and p.name != "self"}
        if not any(p.kind == p.VAR_KEYWORD for p in params):
            break
    return names


def build_method(name: str, args: argparse.Namespace) -> torch.nn.Module:
    """The module ``name`` with the constructor arguments given on the command line."""
    if name not in METHODS:
        raise CommandError(f"--method: unknown method {name!r}; expected one of {', '.join(sorted(METHODS))}")
    cls = get_method(name)
    accepted = _constructor_arguments(cls)
    kwargs = {}
    given = {k: getattr(args, k, None) for k in ("preset", "slices", "steps", "seed", *_FLOAT_FLAGS, *_CHOICE_FLAGS)}
    if getattr(args, "no_jitter", False):
        given["jitter"] = False
    if getattr(args, "indirect", False):
        given["indirect"] = True
    if getattr(args, "no_indirect", False):
        given["indirect"] = False
    if getattr(args, "bent_normals", False):
        given["bent_normals"] = True
    for key, value in given.items():
        if value is None:
            continue
        if key not in accepted:
            raise CommandError(f"--{key.replace('_', '-')}: not an option of method {name!r}")
        kwargs[key] = value
    return cls(**kwargs)


def run(args: argparse.Namespace) -> int:
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise CommandError("--device: CUDA is not available on this machine")
    if args.auto or args.report or args.tolerance is not None:
        from ..bench_auto import apply_auto

        apply_auto(args)
    if args.gbuffer:
        gbuffer, _ = load_gbuffer(args.gbuffer, device=device)
    else:
        gbuffer = example_gbuffer().to(device)
    from ..fitted import cli_module

    method = cli_module(args, lambda a: build_method(a.method, a)).to(device)
    if args.fitted:
        args.method = method.method_name
    with torch.no_grad():
        method(gbuffer)  # warm-up, so the time printed is the steady state
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        out = method(gbuffer)
        if device.type == "cuda":
            torch.cuda.synchronize()
        elapsed = time.perf_counter() - start
    arrays = {"visibility": out.visibility}
    for key in ("indirect", "bent_normal", "ambient"):
        if getattr(out, key) is not None:
            arrays[key] = getattr(out, key)
    path = save_npz(args.out, gbuffer, **arrays)
    B, _, H, W = gbuffer.depth.shape
    vis = out.visibility[gbuffer.valid]
    mean = float(vis.mean()) if vis.numel() else 1.0
    print(f"{args.method}: {B}x{H}x{W} in {elapsed * 1000:.1f} ms on {device}; mean visibility {mean:.4f} -> {path}")
    if args.png:
        from ..images import save_png

        save_png(args.png, out.visibility)
        print(f"wrote {args.png}")
    return 0
