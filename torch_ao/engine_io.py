"""Engine G-buffers in: OpenEXR files (Blender, Unreal, Unity) and 16-bit PNG depth, converted to the
library's conventions (the arrays of the ``.npz`` format, see :mod:`torch_ao.io`).

Everything here works on numpy arrays in the ``.npz`` layout (``depth (...,H,W)``, ``normal``/``position``
/``light``/``albedo (...,H,W,3)``, ``object_id``/``mask (...,H,W)``, ``intrinsics (3,3)``), so a file read
from an engine and the same buffers stored as ``.npz`` build the same :class:`~torch_ao.GBuffer`.

Conversions, in this order (:func:`apply_engine_options`):

1. ``depth_kind="distance"``: the depth channel holds the distance from the eye; view-axis depth is
   ``distance / |r|`` with ``r = ((u - cx)/fx, (v - cy)/fy, 1)`` the pixel's ray (needs the camera).
2. ``normal_space="world"`` / ``position_space="world"``: ``n_view = normalize(A^-T n)`` and
   ``p_view = A p + t`` with the world-to-view matrix ``M = [[A, t], [0, 1]]`` (column vectors,
   ``p_view = M @ (p, 1)``), from ``view_matrix`` or the file's ``worldToCamera`` header attribute.
3. ``convention="directx"``: the (view-space) frame is left-handed, ``+X`` right, ``+Y`` up, ``+Z``
   forward: the ``z`` component of normals and positions is negated (after step 2). Depth is the
   same positive number in both conventions; nothing else changes (row 0 is the top in both).
4. ``far``: depth at or above ``far`` is background (``inf``); Blender writes ``1e10`` there, so the
   default ``1e9`` catches it.
5. No depth channel but positions: the G-buffer's depth is ``-position.z`` (``far`` applies to it).
"""
from __future__ import annotations

import math
import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .checks import check_choice, check_float
from .limits import ResourceLimitError
from .options import Option, options_by_name

__all__ = ["EngineOptions", "ENGINE_OPTIONS", "CHANNEL_ALIASES", "read_engine_arrays", "apply_engine_options", "list_exr_channels",
           "parse_channels"]

_EXR_MISSING = "reading OpenEXR files needs the OpenEXR package: pip install 'torch-ao[exr]'"

# Target -> (number of components, candidate layer/pass names, first match wins). A channel matches a
# name when its full name is ``[LAYER.]NAME`` (one component) or ``[LAYER.]NAME.C`` with ``C`` one of
# the component letters below, case-insensitive.
CHANNEL_ALIASES: dict[str, tuple[int, tuple[str, ...]]] = {
    # Blender: ViewLayer.Depth.Z (multilayer) / Depth.V; Unreal: SceneDepth, MovieRenderQueue_WorldDepth;
    # Unity/plain files: Z, depth.
    "depth": (1, ("Depth", "SceneDepth", "MovieRenderQueue_WorldDepth", "WorldDepth", "Z")),
    # Blender: ViewLayer.Normal.X/Y/Z (world space); Unreal: WorldNormal.R/G/B; Unity AOV: Normal.
    "normal": (3, ("Normal", "WorldNormal", "N")),
    # Blender (Cycles): ViewLayer.Position.X/Y/Z (world space); Unreal: WorldPosition; plain: P.
    "position": (3, ("Position", "WorldPosition", "P")),
    "light": (3, ("Light", "DirectLight", "DiffuseLight")),
    # Blender: DiffCol (diffuse colour); Unreal: BaseColor; Unity AOV: Albedo.
    "albedo": (3, ("Albedo", "DiffCol", "BaseColor")),
    # Blender: IndexOB.X (object pass index); plain: object_id, ObjectId.
    "object_id": (1, ("object_id", "IndexOB", "ObjectId", "ObjectID")),
    "mask": (1, ("mask",)),
}
_COMPONENTS = (("X", "Y", "Z"), ("R", "G", "B"))
_SCALAR_COMPONENTS = ("", "Z", "V", "R", "X", "Y")


#: The options of :class:`EngineOptions`, described once for the Python API and ``torch-ao convert``.
ENGINE_OPTIONS: tuple[Option, ...] = (
    Option("channels", None, "which channel holds each buffer: TARGET=NAME,... with TARGET one of "
           + ", ".join(CHANNEL_ALIASES) + "; NAME a channel (ViewLayer.Depth.Z), a layer whose .X/.Y/.Z or "
           ".R/.G/.B are taken (ViewLayer.Normal), or FILE.exr[:NAME] in another file. Unnamed buffers are "
           "found by the Blender, Unreal and Unity names of docs/engines.md", kind=str),
    Option("depth_kind", "z", "what the depth channel holds: view-axis depth (z) or the distance from the "
           "eye (distance, converted with the camera)", kind=str, choices=("z", "distance")),
    Option("normal_space", "view", "space of the normals (world: converted with the view matrix)", kind=str,
           choices=("view", "world")),
    Option("position_space", "view", "space of the positions (world: converted with the view matrix)", kind=str,
           choices=("view", "world")),
    Option("view_matrix", None, "world-to-view matrix, 16 numbers row by row (p_view = M @ (p_world, 1)); "
           "None: the file's worldToCamera header attribute", kind=str),
    Option("convention", "opengl", "view-space axes of the file: opengl (-Z forward, the library's) or "
           "directx (+Z forward: the z of normals and positions is negated)", kind=str, choices=("opengl", "directx")),
    Option("far", 1e9, "depth at or above which a pixel is background (Cycles writes 1e10 there); inf keeps "
           "every finite depth", unit="world units", minimum=0.0, open_minimum=True),
    Option("fov", None, "vertical field of view of a centred camera (or give intrinsics); None: the file's",
           unit="degrees", minimum=0.0, maximum=180.0, open_minimum=True, open_maximum=True),
    Option("intrinsics", None, "pinhole camera fx,fy,cx,cy (pixel centres at integers, row 0 at the top); "
           "None: the file's", kind=str, unit="pixels"),
    Option("depth_scale", 1.0, "16-bit PNG depth: world units per step (0.001 for millimetres)",
           unit="world units", minimum=0.0, open_minimum=True),
)
_OPTIONS = options_by_name(ENGINE_OPTIONS)


@dataclass(frozen=True)
class EngineOptions:
    """How to read an engine's buffers (every field optional, described in :data:`ENGINE_OPTIONS`; see
    the module docstring for the order of the conversions).

    Args:
        channels: ``{target: name}`` for ``depth``, ``normal``, ``position``, ``light``, ``albedo``,
            ``object_id``, ``mask``; relative file names (``FILE.exr:NAME``) are relative to the main
            file's folder. Unnamed targets are found by :data:`CHANNEL_ALIASES`.
        depth_kind, normal_space, position_space, convention, far, fov, depth_scale: see :data:`ENGINE_OPTIONS`.
        view_matrix: ``(4,4)`` world-to-view matrix (column vectors, ``p_view = M @ (p, 1)``) or its 16
            numbers row by row; default: the file's ``worldToCamera`` header attribute.
        intrinsics: ``(fx, fy, cx, cy)`` in pixels.
    """

    channels: dict | None = _OPTIONS["channels"].default
    depth_kind: str = _OPTIONS["depth_kind"].default
    normal_space: str = _OPTIONS["normal_space"].default
    position_space: str = _OPTIONS["position_space"].default
    view_matrix: tuple | np.ndarray | None = _OPTIONS["view_matrix"].default
    convention: str = _OPTIONS["convention"].default
    far: float = _OPTIONS["far"].default
    fov: float | None = _OPTIONS["fov"].default
    intrinsics: tuple | None = _OPTIONS["intrinsics"].default
    depth_scale: float = _OPTIONS["depth_scale"].default

    def __post_init__(self) -> None:
        for name in ("depth_kind", "normal_space", "position_space", "convention", "fov", "depth_scale"):
            _OPTIONS[name].check(getattr(self, name))
        check_float("far", self.far, 0.0, open_minimum=True, finite=False)  # inf allowed: no far plane
        if self.fov is not None and self.intrinsics is not None:
            raise ValueError("fov: give fov or intrinsics, not both")
        if self.intrinsics is not None:
            k = _real(self.intrinsics, "intrinsics").reshape(-1)
            if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0 or k[1] <= 0:
                raise ValueError(f"intrinsics: expected four finite numbers fx,fy,cx,cy with fx, fy > 0, got {self.intrinsics!r}")
        if self.view_matrix is not None:
            m = _real(self.view_matrix, "view_matrix")
            if m.size != 16 or not np.isfinite(m).all():
                raise ValueError(f"view_matrix: expected 16 finite numbers (a 4x4 matrix), got {self.view_matrix!r}")
            if abs(np.linalg.det(m.reshape(4, 4)[:3, :3])) < 1e-12:
                raise ValueError("view_matrix: its 3x3 part is singular")
        for target in self.channels or {}:
            check_choice("channels", target, tuple(CHANNEL_ALIASES))


def _real(value, name: str) -> np.ndarray:
    from .io import real_array

    return real_array(value, name, "the engine options")


def parse_channels(text: str) -> dict[str, str]:
    """``"depth=ViewLayer.Depth.Z,normal=ViewLayer.Normal"`` -> ``{"depth": ..., "normal": ...}``."""
    out = {}
    for item in filter(None, text.split(",")):
        target, sep, name = item.partition("=")
        if not sep or not name:
            raise ValueError(f"channels: expected TARGET=NAME items separated by commas, got {item!r}")
        check_choice("channels", target.strip(), tuple(CHANNEL_ALIASES))
        out[target.strip()] = name.strip()
    return out


# ---------------------------------------------------------------------------------------- reading files
def _exr_module():
    try:
        import OpenEXR
    except ImportError as err:
        raise ImportError(_EXR_MISSING) from err
    return OpenEXR


def _read_exr(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """All channels of every part, keyed ``[PART.]CHANNEL``, and the first part's header."""
    OpenEXR = _exr_module()
    _check_exr_size(OpenEXR, path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels, header = {}, dict(f.parts[0].header)
            for part in f.parts:
                prefix = part.name() + "." if len(f.parts) > 1 and part.name() else ""
                for name, ch in part.channels.items():
                    channels[prefix + name] = np.asarray(ch.pixels)
    except (RuntimeError, OSError) as err:
        raise ValueError(f"path: {path} is not a readable OpenEXR file ({err})") from None
    return channels, header


def _check_exr_size(OpenEXR, path: Path) -> None:
    """Refuse (:mod:`torch_ao.limits`) an OpenEXR file whose parts' data windows hold more pixels, or
    more bytes (pixels x channels x 4), than the limits allow, from its headers alone."""
    from .limits import check_limit

    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            parts = [dict(part.header) for part in f.parts]
    except (RuntimeError, OSError) as err:
        raise ValueError(f"path: {path} is not a readable OpenEXR file ({err})") from None
    total = 0
    for i, header in enumerate(parts):
        lo, hi = (np.asarray(x, dtype=np.int64) for x in header.get("dataWindow", ((0, 0), (-1, -1))))
        width, height = (int(v) for v in hi - lo + 1)
        if width <= 0 or height <= 0:
            raise ValueError(f"path: {path}: part {i} has an empty data window {lo.tolist()}..{hi.tolist()}")
        check_limit("image_pixels", width * height, f"path: {path}: part {i}'s data window ({width}x{height})")
        total += width * height * max(len(header.get("channels", ())), 1) * 4
    check_limit("array_bytes", total, f"path: {path} ({len(parts)} parts, as float32)")


def list_exr_channels(path: str | os.PathLike) -> list[tuple[str, str, tuple[int, ...]]]:
    """``(name, dtype, shape)`` of every channel of an OpenEXR file."""
    channels, _ = _read_exr(_existing(path))
    return [(k, str(v.dtype), tuple(v.shape)) for k, v in sorted(channels.items())]


def _existing(path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no such file: {path}")
    return path


_VECTOR_LAYERS = {a.lower() for n, aliases in CHANNEL_ALIASES.values() if n == 3 for a in aliases}


def _match(channels: dict[str, np.ndarray], name: str, components: int) -> list[str] | None:
    """Channel names (one per component) for ``name`` (a channel or a layer), or None. ``name=""``
    takes unlayered channels (``R``, ``Z``...: a file holding one buffer)."""
    def find(full: str) -> list[str]:
        f = full.lower()
        if not name:
            return [k for k in channels if k.lower() == f]
        hits = []
        for k in channels:
            lk = k.lower()
            if lk == f or lk.endswith("." + f):
                before = lk[: -len(f) - 1].rsplit(".", 1)[-1] if lk != f else ""
                if "." not in f and before in _VECTOR_LAYERS:
                    continue  # "Z" is not "Normal.Z"
                hits.append(k)
        return hits

    if components == 1:
        for c in _SCALAR_COMPONENTS:
            if not name and not c:
                continue
            hits = find(f"{name}.{c}" if name and c else (name or c))
            if len(hits) > 1:
                raise ValueError(f"channels: {name!r} matches several channels {sorted(hits)}; name one with --channels")
            if hits:
                return hits
        return None
    for letters in _COMPONENTS:
        hits = [find(f"{name}.{c}" if name else c) for c in letters]
        if all(hits):
            if any(len(h) > 1 for h in hits):
                raise ValueError(f"channels: {name!r} matches several layers {sorted(hits[0])}; name one with --channels")
            return [h[0] for h in hits]
    return None


def _select(channels: dict[str, np.ndarray], options: EngineOptions, path: Path) -> dict[str, np.ndarray]:
    """The targets found in ``channels`` (and in the other files ``options.channels`` names)."""
    out: dict[str, np.ndarray] = {}
    other_files: dict[Path, dict[str, np.ndarray]] = {}
    given = options.channels or {}
    for target, (components, aliases) in CHANNEL_ALIASES.items():
        source, names, where = channels, aliases, str(path)
        if target in given:
            spec = given[target]
            file, sep, name = spec.rpartition(":") if ".exr:" in spec.lower() else (spec, "", "")
            if spec.lower().endswith(".exr") or sep:
                file_path = Path(file) if Path(file).is_absolute() else path.parent / file
                if file_path not in other_files:
                    other_files[file_path] = _read_exr(_existing(file_path))[0]
                source, where = other_files[file_path], str(file_path)
                names = (name if sep else "",)
            else:
                names = (spec,)
        hits = None
        if target == "depth" and target not in given:
            names = (*names, "")  # a file holding only depth (Unity writes one file per buffer): R, Z, ...
        for name in names:
            hits = _match(source, name, components)
            if hits:
                break
        if hits is None:
            if target in given:
                raise ValueError(f"channels: {target}={given[target]!r} not found in {where} "
                                 f"(channels: {', '.join(sorted(source))})")
            continue
        arrays = [source[h] for h in hits]
        out[target] = arrays[0] if components == 1 else np.stack(arrays, axis=-1)
    if "depth" not in out and "position" not in out:
        raise ValueError(f"channels: no depth or position channel in {path} (channels: {', '.join(sorted(channels))}); "
                         "name one with --channels depth=NAME")
    return out


def _read_png_depth(path: Path, scale: float) -> np.ndarray:
    try:
        from PIL import Image
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("reading PNG depth needs Pillow: pip install 'torch-ao[plot]'") from err
    from .limits import check_limit, limit

    with open(path, "rb") as f:
        head = f.read(24)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":  # its size, before anything is inflated
        width, height = struct.unpack(">II", head[16:24])
        check_limit("image_pixels", width * height, f"path: {path} ({width}x{height} PNG)")
        check_limit("array_bytes", width * height * 8, f"path: {path} ({width}x{height} PNG, as float64)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # our own limit decides
            pil_limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, limit("image_pixels")
            try:
                with Image.open(path) as im:
                    a = np.asarray(im)
            finally:
                Image.MAX_IMAGE_PIXELS = pil_limit
    except Image.DecompressionBombError as err:
        raise ResourceLimitError(f"path: {path}: {err}") from None
    except (OSError, SyntaxError, ValueError) as err:
        raise ValueError(f"path: {path} is not a readable PNG file ({err})") from None
    if a.ndim != 2 or a.dtype.itemsize < 2:
        raise ValueError(f"path: {path}: expected a single-channel 16-bit PNG depth, got {a.dtype} of shape {a.shape}")
    depth = a.astype(np.float64) * scale
    return np.where(a == 0, np.inf, depth).astype(np.float32)  # 0 = no depth (background)


def read_engine_arrays(path: str | os.PathLike, **options) -> dict[str, np.ndarray]:
    """Read an OpenEXR file (``.exr``) or a 16-bit PNG depth (``.png``) into ``.npz``-layout arrays in
    the library's conventions. ``options`` are :class:`EngineOptions` fields."""
    from .io import real_array

    opts = EngineOptions(**options)
    path = _existing(path)
    suffix = path.suffix.lower()
    header: dict = {}
    if suffix == ".exr":
        channels, header = _read_exr(path)
        arrays = _select(channels, opts, path)
    elif suffix == ".png":
        if opts.channels:
            raise ValueError("channels: a PNG depth file has one channel; --channels applies to OpenEXR files")
        arrays = {"depth": _read_png_depth(path, opts.depth_scale)}
    else:
        raise ValueError(f"path: expected an .npz, .exr or .png file, got {path.name!r}")
    for key in ("intrinsics", "fov_y_degrees"):  # torch_ao's own optional header attributes
        if key in header:
            arrays[key] = real_array(header[key], f"{key} (header attribute)", path)
    if "worldToCamera" in header:  # Imath: row vectors
        arrays["view_matrix"] = real_array(header["worldToCamera"], "worldToCamera (header attribute)", path).T
    arrays = apply_engine_options(arrays, opts)
    if "intrinsics" not in arrays and "fov_y_degrees" not in arrays:
        raise ValueError(f"camera: {path.name} names no camera; give --fov DEGREES or --intrinsics FX,FY,CX,CY")
    return arrays


# ---------------------------------------------------------------------------------------- conversions
def _size_of(arrays: dict[str, np.ndarray]) -> tuple[int, int]:
    """``(H, W)`` shared by every image of ``arrays`` (scalar ``(...,H,W)``, vector ``(...,H,W,3)``)."""
    def size(name):
        a = arrays[name]
        return tuple(a.shape[-3:-1] if CHANNEL_ALIASES[name][0] == 3 else a.shape[-2:])

    key = "depth" if "depth" in arrays else "position"
    shape = size(key)
    for name in CHANNEL_ALIASES:
        if name in arrays and size(name) != shape:
            got = size(name)
            raise ValueError(f"{name}: {got[1]}x{got[0]} pixels, but {key} is {shape[1]}x{shape[0]}")
    return shape


def _set_camera(arrays: dict, opts: EngineOptions) -> None:
    """The options' camera, if any, replaces the file's (``intrinsics`` or ``fov_y_degrees``)."""
    if opts.intrinsics is not None:
        fx, fy, cx, cy = (float(x) for x in np.asarray(opts.intrinsics).reshape(-1))
        arrays.pop("fov_y_degrees", None)
        arrays["intrinsics"] = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float32)
    elif opts.fov is not None:
        arrays.pop("intrinsics", None)
        arrays["fov_y_degrees"] = np.float32(opts.fov)


def _ray_lengths(arrays: dict, height: int, width: int) -> np.ndarray:
    """``(H,W)`` length of each pixel's ray ``((u-cx)/fx, (v-cy)/fy, 1)``: distance / length = depth."""
    from .io import _camera_from_arrays

    try:
        camera = _camera_from_arrays(arrays, height, width, 1)
    except ValueError:
        raise ValueError("depth_kind: 'distance' needs the camera (give --fov or --intrinsics)") from None
    return camera.to(dtype=torch.float64).pixel_rays()[0].norm(dim=0).numpy()


def _view_matrix(arrays: dict, opts: EngineOptions, what: str) -> np.ndarray:
    if opts.view_matrix is not None:
        return np.asarray(opts.view_matrix, dtype=np.float64).reshape(4, 4)
    if "view_matrix" in arrays:
        return arrays["view_matrix"]
    raise ValueError(f"view_matrix: {what} needs the world-to-view matrix; the file has no worldToCamera "
                     "header attribute, so give --view-matrix (16 numbers, row by row)")


def apply_engine_options(arrays: dict[str, np.ndarray], opts: EngineOptions) -> dict[str, np.ndarray]:
    """Convert ``.npz``-layout ``arrays`` (top-down) from an engine's conventions to the
    library's (see the module docstring). Returns a new dict; ``view_matrix`` is consumed."""
    arrays = dict(arrays)
    H, W = _size_of(arrays)
    _set_camera(arrays, opts)
    for key in ("normal", "position"):
        space = opts.normal_space if key == "normal" else opts.position_space
        if key in arrays and space == "world":
            M = _view_matrix(arrays, opts, f"{key}_space='world'")
            A = M[:3, :3]
            x = np.asarray(arrays[key], dtype=np.float64)
            if key == "normal":
                n = x @ np.linalg.inv(A)  # rows: (A^-T n)^T = n^T A^-1
                x = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
            else:
                x = x @ A.T + M[:3, 3]
            arrays[key] = x.astype(np.float32)
    arrays.pop("view_matrix", None)
    if opts.convention == "directx":
        for key in ("normal", "position"):
            if key in arrays:
                arrays[key] = arrays[key] * np.array([1, 1, -1], dtype=arrays[key].dtype)
    if "depth" in arrays:
        depth = np.asarray(arrays["depth"])
        if not np.issubdtype(depth.dtype, np.floating):
            raise ValueError(f"depth: expected a floating-point channel, got {depth.dtype}")
        if opts.depth_kind == "distance":
            depth = (depth / _ray_lengths(arrays, H, W)).astype(np.result_type(depth.dtype, np.float32))
        if math.isfinite(opts.far):
            depth = np.where(depth >= opts.far, np.inf, depth).astype(depth.dtype)
        arrays["depth"] = depth
    elif "position" in arrays and math.isfinite(opts.far):  # GBuffer derives depth = -z
        p = arrays["position"]
        arrays["position"] = np.where((-p[..., 2:] >= opts.far), np.nan, p).astype(p.dtype)
    if "object_id" in arrays:
        ids = np.asarray(arrays["object_id"])
        if ids.dtype.kind == "f":
            ok = np.isfinite(ids)
            if (ids[ok] != np.round(ids[ok])).any() or (ids[ok] < 0).any():
                raise ValueError("object_id: expected non-negative whole numbers")
            ids = np.where(ok, ids, 0)
        arrays["object_id"] = ids.astype(np.int64)
    if "mask" in arrays:
        arrays["mask"] = np.asarray(arrays["mask"]) != 0
    return arrays
