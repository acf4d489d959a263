"""``torch-ao convert``: read an engine's G-buffer (OpenEXR, 16-bit PNG depth, or ``.npz``) and write the
library's ``.npz`` format, so a user can check what was read."""
from __future__ import annotations

import argparse
import re

from ..engine_io import CHANNEL_ALIASES, EngineOptions

__all__ = ["register", "run", "add_engine_flags", "engine_options"]

_DEFAULTS = EngineOptions()


def add_engine_flags(p: argparse.ArgumentParser) -> None:
    """The flags of :class:`~torch_ao.engine_io.EngineOptions` (for any command that reads engine files)."""
    g = p.add_argument_group("engine conventions (see docs/engines.md)")
    g.add_argument("--channels", metavar="T=NAME,...",
                   help="which channel holds each buffer, T one of " + ", ".join(CHANNEL_ALIASES) + "; NAME a "
                   "channel (ViewLayer.Depth.Z), a layer whose .X/.Y/.Z or .R/.G/.B are taken (ViewLayer.Normal), "
                   "or FILE.exr[:NAME] in another file; default: the Blender/Unreal/Unity names in docs/engines.md")
    g.add_argument("--depth-kind", choices=("z", "distance"), default=_DEFAULTS.depth_kind,
                   help="depth channel holds view-axis depth (z) or distance from the eye (converted with the "
                   "camera); default %(default)s")
    g.add_argument("--normal-space", choices=("view", "world"), default=_DEFAULTS.normal_space,
                   help="space of the normals; world needs the view matrix; default %(default)s")
    g.add_argument("--position-space", choices=("view", "world"), default=_DEFAULTS.position_space,
                   help="space of the positions; world needs the view matrix; default %(default)s")
    g.add_argument("--view-matrix", metavar="M00,M01,...,M33",
                   help="world-to-view matrix, 16 numbers row by row (p_view = M @ (p_world, 1)); default: the "
                   "file's worldToCamera header attribute")
    g.add_argument("--convention", choices=("opengl", "directx"), default=_DEFAULTS.convention,
                   help="view-space axes of the file: opengl (-Z forward, the library's) or directx (+Z forward: "
                   "z of normals and positions is negated); default %(default)s")
    g.add_argument("--far", type=float, default=_DEFAULTS.far,
                   help="depth (world units) at or above which a pixel is background; default %(default)g "
                   "(Blender writes 1e10 there); inf keeps every finite depth")
    g.add_argument("--fov", type=float, help="vertical field of view in degrees, in (0, 180) (centred camera)")
    g.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                   help="pinhole camera in pixels (pixel centres at integers, row 0 at the top)")
    g.add_argument("--depth-scale", type=float, default=_DEFAULTS.depth_scale,
                   help="16-bit PNG depth: world units per step (0.001 for millimetres); default %(default)g")


def engine_options(args: argparse.Namespace) -> dict:
    """The :class:`~torch_ao.engine_io.EngineOptions` fields the command line sets (others default)."""
    from ..engine_io import parse_channels, parse_numbers

    options = {"depth_kind": args.depth_kind, "normal_space": args.normal_space,
               "position_space": args.position_space, "convention": args.convention, "far": args.far,
               "fov": args.fov, "depth_scale": args.depth_scale}
    if args.channels:
        options["channels"] = parse_channels(args.channels)
    if args.view_matrix:
        options["view_matrix"] = parse_numbers("view_matrix", args.view_matrix, 16)
    if args.intrinsics:
        options["intrinsics"] = parse_numbers("intrinsics", args.intrinsics, 4)
    return {k: v for k, v in options.items() if v != getattr(_DEFAULTS, k)}


def register(sub) -> None:
    p = sub.add_parser(
        "convert", help="convert an engine G-buffer (OpenEXR, 16-bit PNG depth) to the library's .npz",
        description="Read a G-buffer written by an engine or DCC tool (OpenEXR with depth, normals, positions, "
        "light, albedo, object ids; or a 16-bit PNG depth), convert it to the library's conventions (view-axis "
        "depth, OpenGL view-space normals and positions) and write it as .npz. Needs `pip install torch-ao[exr]` "
        "for OpenEXR files.")
    p.add_argument("input", help="input file: .exr, .png (16-bit depth) or .npz")
    p.add_argument("--out", help="output .npz file")
    p.add_argument("--png", help="also write a preview PNG (depth | normals)")
    p.add_argument("--list-channels", action="store_true", help="print the channels of the OpenEXR file and exit")
    add_engine_flags(p)
    # "--view-matrix -1,0,..." : take a comma list starting with a negative number for a value, not a flag.
    p._negative_number_matcher = re.compile(r"^-\.?\d")
    p.set_defaults(func=run)


def _rename_option_error(err: ValueError) -> ValueError:
    msg = str(err)
    name = msg.split(":", 1)[0]
    if name in EngineOptions.__dataclass_fields__:
        msg = "--" + name.replace("_", "-") + msg[len(name):]
    return ValueError(msg)


def run(args: argparse.Namespace) -> int:
    from ..cli import CommandError
    from ..engine_io import list_exr_channels
    from ..io import gbuffer_from_arrays, read_gbuffer_arrays, save_npz

    if args.list_channels:
        for name, dtype, shape in list_exr_channels(args.input):
            print(f"{name}  {dtype}  {shape[1]}x{shape[0]}")
        return 0
    if not args.out or not args.out.endswith(".npz"):
        raise CommandError(f"--out: expected a .npz file name, got {args.out!r}")
    if args.png and not args.png.lower().endswith(".png"):
        raise CommandError(f"--png: expected a .png file name, got {args.png!r}")
    try:
        arrays = read_gbuffer_arrays(args.input, **engine_options(args))
        gbuffer, extras = gbuffer_from_arrays(arrays, args.input)
    except ValueError as err:
        raise _rename_option_error(err) from None
    path = save_npz(args.out, gbuffer, **extras)
    if args.png:
        _preview(args.png, gbuffer)
    B, _, H, W = gbuffer.depth.shape
    valid = gbuffer.valid
    found = [k for k in ("normals", "position", "light", "object_id", "mask") if getattr(gbuffer, k) is not None]
    depth = gbuffer.depth[valid]
    span = f"depth {float(depth.min()):.4g}..{float(depth.max()):.4g}" if depth.numel() else "no valid pixels"
    print(f"{args.input}: {W}x{H}, {int(valid.sum())} valid pixels ({span}); "
          f"{', '.join(found + sorted(extras)) or 'depth only'} -> {path}")
    return 0


def _preview(path: str, gbuffer) -> None:
    """depth (near bright) | normals, side by side."""
    import torch

    from ..images import save_png

    valid = gbuffer.valid
    inv = torch.where(valid, 1 / gbuffer.safe_depth, torch.zeros_like(gbuffer.depth))
    near = inv / inv.amax(dim=(2, 3), keepdim=True).clamp_min(1e-30)
    normals = torch.where(valid, gbuffer.view_normals() * 0.5 + 0.5, torch.zeros_like(gbuffer.depth))
    save_png(path, torch.cat([near.expand(-1, 3, -1, -1), normals], dim=3)[:1])
