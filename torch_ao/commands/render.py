"""``torch-ao render``: ray-trace a G-buffer and reference AO for a built-in scene or mesh files.

    torch-ao render SCENE [--eye x,y,z --target x,y,z --up x,y,z --fov DEG] [--mesh FILE]...
                    --width W --height H --spp N --max-distance R --seed S --out FILE.npz [--png FILE.png]
    torch-ao render --mesh FILE [--mesh FILE]... [--ground-plane [HEIGHT]] [--backface] ... --out FILE.npz
    torch-ao render --list
"""
from __future__ import annotations

import argparse
import struct
import time
import zlib
from pathlib import Path

from ..reference.tracer import MESH_BACKENDS
from .args import add_float_list, allow_negative_lists, parse_float_list

__all__ = ["register", "run", "write_png"]

_AUTO = "auto"  # --ground-plane without a height: under the meshes


def _ground_height(text: str):
    return text if text == _AUTO else float(text)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="ray-trace a G-buffer and reference AO of a scene or of mesh files",
        description="Ray-trace a G-buffer (depth, normals, light, ids, albedo) and ground-truth AO "
                    "(cosine and uniform weighted, with standard errors) of a built-in scene, or of mesh "
                    "files on their own, into an .npz file.")
    allow_negative_lists(p)
    p.add_argument("scene", nargs="?", help="built-in scene name (see --list), or a Mitsuba 3 scene file (.xml, needs "
                                            "mitsuba); omit it to render --mesh files alone")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    add_float_list(p, "--eye", 3, "camera position in world units (default: the scene's view, a glTF "
                   "camera of the mesh files, or a view framing the meshes)")
    add_float_list(p, "--target", 3, "point looked at, world units (default: the scene's, or the centre of the meshes)")
    add_float_list(p, "--up", 3, "up vector (default: the view's, usually 0,1,0)")
    p.add_argument("--fov", type=float, metavar="DEG", help="vertical field of view in degrees, in (0, 180) "
                   "(default: the view's, 60 for framed meshes)")
    p.add_argument("--mesh", action="append", default=[], metavar="FILE",
                   help="a mesh file (OBJ, PLY, STL, OFF, glTF/GLB...; needs trimesh): one object id per file, "
                        "per node for glTF; added to SCENE, or rendered alone without SCENE; repeatable")
    p.add_argument("--mesh-normalize", action="store_true",
                   help="scale each --mesh file to unit size resting on y=0 at the origin (default: as stored)")
    p.add_argument("--ground-plane", nargs="?", const=_AUTO, type=_ground_height,
                   metavar="HEIGHT", help="add a ground plane y=HEIGHT (world units; without HEIGHT: at the lowest "
                                          "point of the scene's bounded objects, e.g. under the meshes)")
    p.add_argument("--randomize", type=int, metavar="SEED", help="a randomised variant of the built-in scene")
    p.add_argument("--width", type=int, default=320, help="image width in pixels (default 320)")
    p.add_argument("--height", type=int, default=180, help="image height in pixels (default 180)")
    p.add_argument("--spp", type=int, default=256, help="AO samples per pixel per weighting (default 256; "
                                                        "needs a divisor in [2, 16])")
    p.add_argument("--max-distance", type=float, default=float("inf"),
                   help="AO ray length R in world units, > 0 (default inf)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed, >= 0 (default 0)")
    p.add_argument("--indirect", action="store_true", help="also render one-bounce indirect light")
    p.add_argument("--no-uniform", action="store_true", help="skip uniform-weighted AO")
    p.add_argument("--backface", action="store_true",
                   help="also write backface_depth: the view-axis depth at which each pixel's camera ray leaves "
                        "the object it hit first (inf on background and planes; the front depth on open surfaces)")
    p.add_argument("--mesh-backend", choices=MESH_BACKENDS, default="auto",
                   help="triangle tracer: auto = Warp on a CUDA --device when warp-lang is installed, else Embree "
                        "when installed, else the pure-torch one (small meshes only)")
    p.add_argument("--chunk-rays", type=int, default=1 << 18, help="rays traced at once (memory; default 262144)")
    p.add_argument("--device", default="cpu", help="torch device of the tracer (default cpu)")
    p.add_argument("--out", help="output .npz file")
    p.add_argument("--png", help="also write a preview PNG (depth | normals | light | AO)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _files_only(args) -> bool:
    """No built-in scene: --mesh files alone, or SCENE is a Mitsuba 3 scene file."""
    return not args.scene or args.scene.lower().endswith(".xml")


def _scene(args):
    """The built-in scene (with --mesh files and --ground-plane added) or a scene of files alone."""
    from ..cli import CommandError
    from ..reference import Plane, get_scene, load_mesh_file, mesh_scene

    if args.ground_plane is None:
        ground = None
    else:
        ground = True if args.ground_plane == _AUTO else args.ground_plane
    if _files_only(args):
        if args.randomize is not None:
            raise CommandError("--randomize: only for built-in scenes")
        files = ([args.scene] if args.scene else []) + args.mesh
        return mesh_scene(files, ground_plane=ground, normalize=args.mesh_normalize, progress=not args.quiet)
    try:
        scene = get_scene(args.scene, seed=args.randomize)
    except ValueError as err:
        raise CommandError(str(err).replace("scene:", "SCENE:", 1)) from None
    for path in args.mesh:
        for mesh in load_mesh_file(path, normalize=args.mesh_normalize)[0]:
            scene = scene.add(mesh)
    if ground is not None:
        box = scene.bounds()
        height = ground if ground is not True else (float(box[0][1]) if box is not None else 0.0)
        scene = scene.add(Plane(point=(0.0, height, 0.0), normal=(0.0, 1.0, 0.0)))
    return scene


def _views(args, scene):
    from ..cli import CommandError
    from ..reference import look_at
    from ..reference.meshfile import frame_view

    v = scene.view
    eye, target, up = (parse_float_list(f"--{k}", getattr(args, k), 3, names="x,y,z") for k in ("eye", "target", "up"))
    if _files_only(args) and eye is not None and target is None:
        # a new eye without a target looks at the meshes, not along the file's camera
        v = frame_view(*scene.bounds(), v.fov_y_degrees)
    fov = v.fov_y_degrees if args.fov is None else args.fov
    if not (0 < fov < 180):
        raise CommandError(f"--fov: expected degrees in (0, 180), got {fov}")
    try:
        return look_at(eye or v.eye, target or v.target, up or v.up, fov, height=args.height, width=args.width)
    except ValueError as err:
        raise CommandError(f"--eye/--target/--up: {err}") from None


def run(args: argparse.Namespace) -> int:
    from ..cli import CommandError
    from ..reference import list_scenes, render_reference

    if args.list:
        scenes = list_scenes()
        width = max(len(n) for n, _ in scenes)
        for name, desc in scenes:
            print(f"{name:<{width}}  {desc}")
        return 0
    if not args.scene and not args.mesh:
        raise CommandError("SCENE: name a built-in scene (torch-ao render --list shows them) or give --mesh FILE")
    if not args.out:
        raise CommandError("--out: an output .npz file is required")
    if not args.out.endswith(".npz"):
        raise CommandError(f"--out: expected a .npz file name, got {args.out!r}")
    if args.png and not args.png.lower().endswith(".png"):
        raise CommandError(f"--png: expected a .png file name, got {args.png!r}")
    for name in ("width", "height"):
        if getattr(args, name) < 1:
            raise CommandError(f"--{name}: expected a positive integer, got {getattr(args, name)}")
    for flag in ("eye", "target", "up"):  # check the flags before loading (big) mesh files
        parse_float_list(f"--{flag}", getattr(args, flag), 3, names="x,y,z")
    scene = _scene(args)
    views = _views(args, scene)
    start = time.perf_counter()
    try:
        ref = render_reference(scene, views, spp=args.spp, max_distance=args.max_distance, seed=args.seed,
                               chunk_rays=args.chunk_rays, progress=not args.quiet, indirect=args.indirect,
                               uniform=not args.no_uniform, backface=args.backface, device=args.device,
                               mesh_backend=args.mesh_backend)
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
    triangles = sum(o.faces.shape[0] for o in scene.objects if hasattr(o, "faces"))
    what = scene.name + (f" ({triangles} triangles)" if triangles else "")
    print(f"rendered {what} {args.width}x{args.height} at {args.spp} spp in {elapsed:.2f} s "
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
