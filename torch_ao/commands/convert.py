"""``torch-ao convert``: read an engine's G-buffer (OpenEXR, 16-bit PNG depth, or ``.npz``) and write the
library's ``.npz`` format, so a user can check what was read."""
from __future__ import annotations

import argparse

from .inputs import add_input_flags, flag_errors, input_options

__all__ = ["register", "run"]


def register(sub) -> None:
    p = sub.add_parser(
        "convert", help="convert an engine G-buffer (OpenEXR, 16-bit PNG depth) to the library's .npz",
        description="Read a G-buffer written by an engine or DCC tool (OpenEXR with depth, normals, positions, "
        "light, albedo, object ids; or a 16-bit PNG depth), convert it to the library's conventions (view-axis "
        "depth, OpenGL view-space normals and positions) and write it as .npz. Needs the exr extra (`pip install -e \".[exr]\"`) "
        "for OpenEXR files.")
    p.add_argument("input", help="input file: .exr, .png (16-bit depth) or .npz")
    p.add_argument("--out", help="output .npz file (required)")
    p.add_argument("--png", help="also write a preview PNG (depth | normals). Default: none")
    p.add_argument("--list-channels", action="store_true", help="print the channels of the OpenEXR file and exit")
    add_input_flags(p, "the input file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..cli import CommandError
    from ..io.engine import list_exr_channels
    from ..io import check_output_path, gbuffer_from_arrays, read_gbuffer_arrays, save_npz

    if args.list_channels:
        for name, dtype, shape in list_exr_channels(args.input):
            print(f"{name}  {dtype}  {shape[1]}x{shape[0]}")
        return 0
    if not args.out:
        raise CommandError("--out: an output .npz file is required")
    check_output_path("--out", args.out, (".npz",))
    if args.png:
        from ..images import pyplot

        check_output_path("--png", args.png, (".png",))
        pyplot()
    options = input_options(args)
    with flag_errors():
        arrays = read_gbuffer_arrays(args.input, **options)
        gbuffer, extras = gbuffer_from_arrays(arrays, args.input)
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
