"""``torch-ao ao``: run a screen-space AO method on a G-buffer file (or the built-in example)."""
from __future__ import annotations

import argparse
import time

import torch

from ..bench import DEFAULT_TOLERANCE
from ..checks import check_finite_outputs
from ..examples import example_gbuffer
from ..fitted import SCALE
from ..io import check_output_path, load_gbuffer, save_npz
from ..methods import METHODS, get_method
from ..options import Option
from .args import parse_device
from .auto import apply_auto
from .inputs import add_input_flags, flag_errors, input_options
from .options_cli import add_options, add_progress, construct, given, method_kwargs, method_options

#: The flags of ``torch-ao ao`` that are not method options.
OPTIONS = (
    Option("method", "gtao", "the AO method", str, choices=tuple(METHODS)),
    Option("device", "cpu", "torch device the method runs on, e.g. cpu, cuda or cuda:1", str),
    Option("out", "ao.npz", "output .npz: the G-buffer with visibility and whatever else was asked for "
           "(indirect, bent_normal, ambient)", str),
    Option("png", None, "also write a PNG of the visibility to this path (needs matplotlib)", str),
    Option("auto", False, "choose --method and --preset (and --radius when not given) by the bench recommendation: "
           "the cheapest whose MAE is within --tolerance of the best, from --report, else from a quick sweep on "
           "GBUFFER's own 'ao' reference", bool),
    Option("tolerance", None, f"with --auto: allowed MAE above the best; when not given, the report's, else "
           f"{DEFAULT_TOLERANCE:g}", float, unit="visibility (MAE)", minimum=0.0),
    Option("report", None, "with --auto: a `torch-ao bench` report.json, or the folder holding it", str),
    Option("fitted", None, "run the pipeline a `torch-ao fit` params.json describes (method, options, fitted "
           "parameters, denoiser) instead of --method and the method flags", str),
    SCALE,
    Option("denoise", False, "filter the output with the edge-aware denoiser (torch_ao.Denoiser, default "
           "settings); with --fitted, adds one when the file has none", bool),
)


def register(sub) -> None:
    p = sub.add_parser(
        "ao",
        help="run an AO method on a G-buffer .npz",
        description="Compute ambient occlusion (and, for ssilvb, indirect light) for a G-buffer file. "
        "Without GBUFFER, runs on a built-in example (a floor meeting a wall). Method flags are passed to the "
        "method's constructor only when given; a flag the chosen method does not take is an error.",
    )
    p.add_argument("gbuffer", nargs="?", metavar="GBUFFER",
                   help="input G-buffer: .npz (keys: depth, and optionally normal, light, mask, object_id, intrinsics or "
                   "fov_y_degrees; see docs/gbuffer.md), or an engine's .exr or 16-bit .png depth read with the "
                   "input conventions below. Default: the built-in example")
    add_options(p, {o.name: o for o in OPTIONS}, given_only=False)
    add_progress(p)
    add_input_flags(p, "GBUFFER")
    group = p.add_argument_group("method options (see --method; each says which methods take it when they differ)")
    p.set_defaults(func=run, method_flags=add_options(group, method_options({m: get_method(m) for m in METHODS})))


def build_method(name: str, args: argparse.Namespace) -> torch.nn.Module:
    """The module ``name`` with the method flags given on the command line."""
    cls = get_method(name)
    return construct(cls, method_kwargs(name, cls, given(args, args.method_flags)))


def run(args: argparse.Namespace) -> int:
    device = parse_device(args.device)
    check_output_path("--out", args.out, (".npz",))
    if args.png:
        from ..images import pyplot

        check_output_path("--png", args.png, (".png",))
        pyplot()  # (matplotlib, before the method runs)
    if args.auto or args.report or args.tolerance is not None:
        apply_auto(args)
    reading = input_options(args, args.gbuffer, "a GBUFFER file")
    if args.gbuffer:
        with flag_errors():
            gbuffer, _ = load_gbuffer(args.gbuffer, device=device, **reading)
    else:
        gbuffer = example_gbuffer().to(device)
    from ..fitted import cli_module

    method = cli_module(args, lambda a: build_method(a.method, a), args.method_flags).to(device)
    args.method = getattr(method, "method_name", args.method)
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
    check_finite_outputs(args.method, arrays)
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
