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

from ..checks import check_finite_outputs
from ..io.mesh import UP_AXES
from ..reference.sampling import MAX_SPP
from ..reference.tracer import MESH_BACKENDS
from ..options import Option
from ..io import check_output_path
from .args import add_float_list, allow_negative_lists, parse_device, parse_float_list
from .options_cli import add_option, add_progress, flag

__all__ = ["register", "run", "write_png"]

_AUTO = "auto"  # --ground-plane without a height: under the meshes


def _ground_height(text: str):
    return text if text == _AUTO else float(text)


#: The flags of ``torch-ao render``: what each does, its unit, range and default (the flags' help).
OPTIONS = (
    Option("list", False, "list the built-in scenes and exit", bool),
    Option("eye", None, "camera position; when not given, the scene's view, a glTF camera of the mesh files, or a "
           "view framing the meshes", str, unit="world units"),
    Option("target", None, "point looked at; when not given, the view's, or the centre of the meshes", str,
           unit="world units"),
    Option("up", None, "up direction (any length); when not given, the view's, usually 0,1,0", str),
    Option("fov", None, "vertical field of view at the rendered size; when not given, the view's (60 for framed "
           "meshes; a file camera's refitted to --width/--height on its fov_axis)", float,
           unit="degrees", minimum=0.0, maximum=180.0, open_minimum=True, open_maximum=True),
    Option("mesh", None, "a mesh file (OBJ, PLY, STL, OFF, glTF/GLB...; needs trimesh): one object id per file, per "
           "node for glTF; added to SCENE, or rendered alone without SCENE; repeatable; when not given, SCENE alone", str),
    Option("allow_outside_paths", False, "let scene and mesh files name files (Mitsuba includes and shapes, glTF "
           "buffers and images, materials) outside their own folder; by default those are refused", bool),
    Option("up_axis", "y", "the --mesh files' up direction (z for most STL files and Z-up OBJ exports): each file "
           "is turned so that it points up (+y), keeping handedness; not for Mitsuba scene files", str, choices=UP_AXES),
    Option("mesh_normalize", False, "scale each --mesh file to unit size resting on y=0 at the origin (else as stored)",
           bool),
    Option("ground_plane", None, "add a ground plane y=HEIGHT; without HEIGHT, at the lowest point of the scene's "
           "bounded objects (e.g. under the meshes); when not given, none", float, unit="world units"),
    Option("randomize", None, "seed of a randomised variant of the built-in scene; when not given, the scene as "
           "defined", int),
    Option("width", None, "image width; when not given, the width of a Mitsuba scene file's film, else 320. Given, it "
           "overrides the film's, and the file camera's field of view is kept on its fov_axis (Mitsuba's default: the "
           "horizontal one), as when Mitsuba renders the film at that size", int, unit="pixels", minimum=1),
    Option("height", None, "image height; when not given, the height of a Mitsuba scene file's film, else 180. Given, "
           "it overrides the film's, the field of view kept as for --width", int, unit="pixels", minimum=1),
    Option("spp", 256, "AO rays per pixel for each weighting (needs a divisor in [2, 16]); at most 65536, where the "
           "standard error is about 0.002: more only runs for hours", int, unit="rays", minimum=2, maximum=MAX_SPP),
    Option("max_distance", float("inf"), "AO ray length R (inf: unlimited)", float, unit="world units",
           minimum=0.0, open_minimum=True),
    Option("seed", 0, "sampling seed (same seed, same image, whatever --chunk-rays and --device)", int, minimum=0),
    Option("indirect", False, "also render one-bounce indirect light", bool),
    Option("no_uniform", False, "skip uniform-weighted AO", bool),
    Option("backface", False, "also write backface_depth: the view-axis depth at which each pixel's camera ray leaves "
           "the object it hit first (inf on background and planes; the front depth on open surfaces)", bool),
    Option("mesh_backend", "auto", "triangle tracer: auto = Warp on a CUDA --device when warp-lang is installed, else "
           "Embree when installed, else the pure-torch one (small meshes only)", str, choices=MESH_BACKENDS),
    Option("chunk_rays", 1 << 18, "rays traced at once (memory is proportional to it)", int, unit="rays", minimum=1),
    Option("device", "cpu", "torch device of the tracer, e.g. cpu or cuda", str),
    Option("out", None, "output .npz file (required)", str),
    Option("png", None, "also write a preview PNG (depth | normals | light | AO) to this path", str),
)

#: Flags whose form an Option cannot say: argparse keywords replacing the option's own.
_FORMS = {
    "mesh": dict(action="append", default=[], metavar="FILE"),
    "ground_plane": dict(nargs="?", const=_AUTO, type=_ground_height, metavar="HEIGHT"),
    "randomize": dict(metavar="SEED"),
    "fov": dict(metavar="DEG"),
}
_VECTORS = ("eye", "target", "up")
#: The image size without --width/--height and without a file camera's film.
_DEFAULT_SIZE = (320, 180)
_FOV = next(o for o in OPTIONS if o.name == "fov")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="ray-trace a G-buffer and reference AO of a scene or of mesh files",
        description="Ray-trace a G-buffer (depth, normals, light, ids, albedo) and ground-truth AO "
                    "(cosine and uniform weighted, with standard errors) of a built-in scene, or of mesh "
                    "files on their own, into an .npz file.")
    allow_negative_lists(p)
    p.add_argument("scene", nargs="?", help="built-in scene name (see --list), or a Mitsuba 3 scene file (.xml, needs "
                                            "mitsuba); omit it to render --mesh files alone")
    for opt in OPTIONS:
        if opt.name in _VECTORS:
            add_float_list(p, flag(opt.name), 3, opt.describe())
        else:
            add_option(p, opt.name, opt, given_only=False, switch=True, infinite=opt.name == "max_distance",
                       **_FORMS.get(opt.name, {}))
    add_progress(p)
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
        try:
            return mesh_scene(files, ground_plane=ground, normalize=args.mesh_normalize, up_axis=args.up_axis,
                              progress=args.progress, allow_outside_paths=args.allow_outside_paths)
        except ValueError as err:  # the keyword arguments' messages restated with their flags; file errors as they are
            msg = _flag_message(str(err), {"normalize": "mesh_normalize", "up_axis": "up_axis"})
            if msg == str(err):
                raise
            raise CommandError(msg) from None
    try:
        scene = get_scene(args.scene, seed=args.randomize)
    except ValueError as err:
        raise CommandError(str(err).replace("scene:", "SCENE:", 1)) from None
    for path in args.mesh:
        for mesh in load_mesh_file(path, normalize=args.mesh_normalize, up_axis=args.up_axis,
                                   allow_outside_paths=args.allow_outside_paths)[0]:
            scene = scene.add(mesh)
    if ground is not None:
        box = scene.bounds()
        height = ground if ground is not True else (float(box[0][1]) if box is not None else 0.0)
        scene = scene.add(Plane(point=(0.0, height, 0.0), normal=(0.0, 1.0, 0.0)))
    return scene


def _flag_message(msg: str, keys: dict) -> str:
    """A library message starting ``"keyword:"`` (a key of ``keys``) restated with the flag of the
    option ``keys[keyword]`` (``"spp: ..."`` -> ``"--spp: ..."``)."""
    for key, option in keys.items():
        if msg.startswith(key + ":"):
            return flag(option) + msg[len(key):]
    return msg


def _views(args, scene):
    from ..cli import CommandError
    from ..reference import look_at
    from ..io.mesh import frame_view

    v = scene.view
    eye, target, up = (parse_float_list(flag(k), getattr(args, k), 3, names="x,y,z") for k in _VECTORS)
    if _files_only(args) and eye is not None and target is None:
        # a new eye without a target looks at the meshes, not along the file's camera
        v = frame_view(*scene.bounds(), v.fov_y_at(args.width, args.height))
    fov = v.fov_y_at(args.width, args.height) if args.fov is None else args.fov
    try:  # the view's own field of view (a glTF or Mitsuba camera) is held to the flag's bounds
        _FOV.check(fov)
    except ValueError as err:
        raise CommandError(f"--fov: {str(err).split(': ', 1)[-1]} (the view's field of view)") from None
    try:
        return look_at(eye or v.eye, target or v.target, up or v.up, fov, height=args.height, width=args.width,
                       principal_offset=v.principal_offset)
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
    check_output_path("--out", args.out, (".npz",))
    if args.png:
        check_output_path("--png", args.png, (".png",))
    parse_device(args.device)
    for name in _VECTORS:  # check the flags before loading (big) mesh files
        parse_float_list(flag(name), getattr(args, name), 3, names="x,y,z")
    scene = _scene(args)
    film = scene.view.film or _DEFAULT_SIZE  # a flag given replaces its side only
    args.width, args.height = args.width or film[0], args.height or film[1]
    views = _views(args, scene)
    start = time.perf_counter()
    try:
        ref = render_reference(scene, views, spp=args.spp, max_distance=args.max_distance, seed=args.seed,
                               chunk_rays=args.chunk_rays, progress=args.progress, indirect=args.indirect,
                               uniform=not args.no_uniform, backface=args.backface, device=args.device,
                               mesh_backend=args.mesh_backend)
    except ValueError as err:
        raise CommandError(_flag_message(str(err), {k: k for k in ("spp", "max_distance", "seed", "chunk_rays")})) from None
    elapsed = time.perf_counter() - start
    check_finite_outputs("the tracer", {k: getattr(ref, k, None) for k in ("ao", "ao_stderr", "ao_uniform", "indirect")})
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
    import numpy as np

    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)) \
        + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    from ..io import write_atomic

    return write_atomic(path, lambda tmp: Path(tmp).write_bytes(data))
