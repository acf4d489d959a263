"""``torch-ao render``: ray-trace a G-buffer and reference AO for a built-in scene.

    torch-ao render SCENE [--eye x,y,z --target x,y,z --up x,y,z --fov DEG] [--mesh FILE]...
                    --width W --height H --spp N --max-distance R --seed S --out FILE.npz [--png FILE.png]
    torch-ao render --list
"""
from __future__ import annotations

import argparse
import math
import struct
import time
import zlib
from pathlib import Path

__all__ = ["register", "run", "write_png"]


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="ray-trace a G-buffer and reference AO of a scene",
        description="Ray-trace a G-buffer (depth, normals, light, ids, albedo) and ground-truth AO "
                    "(cosine and uniform weighted, with standard errors) of a built-in scene into an .npz file.")
    p.add_argument("scene", nargs="?", help="built-in scene name (see --list)")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    p.add_argument("--eye", help="camera position x,y,z (default: the scene's view)")
    p.add_argument("--target", help="point looked at x,y,z")
    p.add_argument("--up", help="up vector x,y,z (default 0,1,0 or the scene's)")
    p.add_argument("--fov", type=float, help="vertical field of view in degrees")
    p.add_argument("--mesh", action="append", default=[], metavar="FILE",
                   help="add a mesh file (OBJ, PLY, GLB...; needs trimesh) to the scene; repeatable")
    p.add_argument("--mesh-normalize", action="store_true",
                   help="scale each --mesh to unit size resting on y=0 at the origin (default: as stored)")
    p.add_argument("--randomize", type=int, metavar="SEED", help="a randomised variant of the scene")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=180)
    p.add_argument("--spp", type=int, default=256, help="AO samples per pixel per weighting (default 256)")
    p.add_argument("--max-distance", type=float, default=float("inf"), help="AO ray length R (default inf)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    p.add_argument("--indirect", action="store_true", help="also render one-bounce indirect light")
    p.add_argument("--no-uniform", action="store_true", help="skip uniform-weighted AO")
    p.add_argument("--mesh-backend", choices=("auto", "embree", "torch"), default="auto")
    p.add_argument("--chunk-rays", type=int, default=1 << 18)
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", help="output .npz file")
    p.add_argument("--png", help="also write a preview PNG (depth | normals | light | AO)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _vec(name: str, text: str | None):
    if text is None:
        return None
    from ..cli import CommandError

    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        raise CommandError(f"--{name}: expected x,y,z numbers, got {text!r}") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise CommandError(f"--{name}: expected three finite numbers x,y,z, got {text!r}")
    return values


def run(args: argparse.Namespace) -> int:
    from ..cli import CommandError
    from ..reference import Mesh, get_scene, list_scenes, look_at, render_reference

    if args.list:
        scenes = list_scenes()
        width = max(len(n) for n, _ in scenes)
        for name, desc in scenes:
            print(f"{name:<{width}}  {desc}")
        return 0
    if not args.scene:
        raise CommandError("SCENE: name a built-in scene (torch-ao render --list shows them)")
    if not args.out:
        raise CommandError("--out: an output .npz file is required")
    if not args.out.endswith(".npz"):
        raise CommandError(f"--out: expected a .npz file name, got {args.out!r}")
    if args.png and not args.png.lower().endswith(".png"):
        raise CommandError(f"--png: expected a .png file name, got {args.png!r}")
    for name in ("width", "height"):
        if getattr(args, name) < 1:
            raise CommandError(f"--{name}: expected a positive integer, got {getattr(args, name)}")
    try:
        scene = get_scene(args.scene, seed=args.randomize)
    except ValueError as err:
        raise CommandError(str(err).replace("scene:", "SCENE:", 1)) from None
    for path in args.mesh:
        scene = scene.add(Mesh.load(path, normalize=args.mesh_normalize))
    v = scene.view
    eye, target, up = _vec("eye", args.eye), _vec("target", args.target), _vec("up", args.up)
    fov = v.fov_y_degrees if args.fov is None else args.fov
    if not (0 < fov < 180):
        raise CommandError(f"--fov: expected degrees in (0, 180), got {fov}")
    try:
        views = look_at(eye or v.eye, target or v.target, up or v.up, fov, height=args.height, width=args.width)
    except ValueError as err:
        raise CommandError(f"--eye/--target/--up: {err}") from None
    start = time.perf_counter()
    try:
        ref = render_reference(scene, views, spp=args.spp, max_distance=args.max_distance, seed=args.seed,
                               chunk_rays=args.chunk_rays, progress=not args.quiet, indirect=args.indirect,
                               uniform=not args.no_uniform, device=args.device, mesh_backend=args.mesh_backend)
    except ValueError as err:
        msg = str(err)
        for key in ("spp", "max_distance", "seed", "chunk_rays"):
            if msg.startswith(key + ":"):
                msg = "--" + key.replace("_", "-") + msg[len(key):]
        raise CommandError(msg) from None
    elapsed = time.perf_counter() - start
    out = ref.save(args.out)
    if args.png:
        write_png(args.png, preview(ref))
    valid = ref.gbuffer.valid
    mean_ao = float(ref.ao[valid].mean()) if bool(valid.any()) else float("nan")
    print(f"rendered {args.scene} {args.width}x{args.height} at {args.spp} spp in {elapsed:.2f} s "
          f"(mean AO {mean_ao:.4f} on {int(valid.sum())} pixels) -> {out}")
    return 0


def preview(ref):
    """``(H, 4W, 3)`` uint8 panel of the first view: depth | normals | light | AO."""
    import torch

    gb = ref.gbuffer
    valid = gb.valid[0, 0]
    depth = gb.depth[0, 0].double()
    if bool(valid.any()):
        logd = torch.log(torch.where(valid, depth, 1.0))
        lo, hi = float(logd[valid].min()), float(logd[valid].max())
        dimg = torch.where(valid, 1 - (logd - lo) / max(hi - lo, 1e-9), 0.0)
    else:
        dimg = torch.zeros_like(depth)
    gray = lambda x: x[None].expand(3, -1, -1)  # noqa: E731
    normals = torch.where(valid, gb.normals[0].double() * 0.5 + 0.5, 0.0)
    light = gb.light[0].double()
    light = (light / (1 + light)).clamp(0, 1) ** (1 / 2.2)
    panel = torch.cat([gray(dimg), normals, light, gray(ref.ao[0, 0].double())], dim=2)
    return (panel.clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).cpu().numpy()


def write_png(path, rgb) -> Path:
    """Write an ``(H, W, 3)`` uint8 array as a PNG (no extra dependency), atomically."""
    import os
    import tempfile

    import numpy as np

    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)) \
        + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)
    return path
