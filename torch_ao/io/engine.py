"""Engine G-buffers in: OpenEXR files (Blender, Unreal, Unity) and 16-bit PNG depth, converted to the
library's conventions (the arrays of the ``.npz`` format, see :mod:`torch_ao.io.npz`).

Everything here works on numpy arrays in the ``.npz`` layout (``depth (...,H,W)``, ``normal``/``position``
/``light``/``albedo (...,H,W,3)``, ``object_id``/``mask``/``backface_depth (...,H,W)``, ``intrinsics (3,3)``), so a file read
from an engine and the same buffers stored as ``.npz`` build the same :class:`~torch_ao.GBuffer`.

Conversions, in this order (:func:`apply_engine_options`):

0. The back-face pass (``backface_depth``: a front-face-culled depth pass, for the back-face thickness model) is
   depth: steps 1 and 4 and the device-depth decoding apply to it as to depth.
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
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from ..checks import check_choice, check_float, install_hint
from ..limits import ResourceLimitError
from ..options import Option, options_by_name
from .npz import _camera_from_arrays, real_array

__all__ = ["EngineOptions", "CameraMissing", "ENGINE_OPTIONS", "CHANNEL_ALIASES", "DEPTH_ENCODINGS", "decode_device_depth", "read_engine_arrays", "apply_engine_options", "list_exr_channels",
           "parse_channels"]

DEPTH_ENCODINGS = ("linear", "device", "reverse-z")
_EXR_MISSING = f"reading OpenEXR files needs the OpenEXR package: {install_hint('exr', 'openexr')}"

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
    # A front-face-culled depth pass (the back-face thickness model's layer): same encoding and kind as depth.
    "backface_depth": (1, ("backface_depth", "BackfaceDepth", "BackDepth")),
}
_COMPONENTS = (("X", "Y", "Z"), ("R", "G", "B"))
_SCALAR_COMPONENTS = ("", "Z", "V", "R", "X", "Y")


#: The options of :class:`EngineOptions`, described once for the Python API and ``torch-ao convert``.
ENGINE_OPTIONS: tuple[Option, ...] = (
    Option("channels", None, "which channel holds each buffer: TARGET=NAME,... with TARGET one of "
           + ", ".join(CHANNEL_ALIASES) + "; NAME a channel (ViewLayer.Depth.Z), a layer whose .X/.Y/.Z or "
           ".R/.G/.B are taken (ViewLayer.Normal), or FILE.exr[:NAME] in another file. Unnamed buffers are "
           "found by the Blender, Unreal and Unity names of docs/engines.md", kind=str),
    Option("depth_kind", "z", "what linear depth holds: view-axis depth (z) or the distance from the "
           "eye (distance, converted with the camera)", kind=str, choices=("z", "distance")),
    Option("depth_encoding", "linear", "how depth is stored: linear (world units, see depth_kind); device: hardware "
           "depth d in [0, 1], 0 at near and 1 at far (D3D, Vulkan, OpenGL's window depth), "
           "z = near*far / (far - d*(far - near)); reverse-z: 1 at near and 0 at far (most engines; Unreal with far "
           "inf), z = near*far / (near + d*(far - near)). device and reverse-z need near and far", kind=str,
           choices=DEPTH_ENCODINGS),
    Option("near", None, "near plane of the projection, for device and reverse-z depth", unit="world units",
           minimum=0.0, open_minimum=True),
    Option("normal_space", None, "space of the normals (world: converted with the view matrix); when not given, "
           "world for Blender's passes (LAYER.Normal beside LAYER.Depth), else view", kind=str,
           choices=("view", "world")),
    Option("normal_encoding", None, "how normals are stored: signed (n) or unorm (0.5 n + 0.5, decoded as 2 x - 1); "
           "when not given, unorm where every component is in [0, 1] and the lengths are unit only after decoding "
           "(with a warning), else signed", kind=str, choices=("signed", "unorm")),
    Option("position_space", None, "space of the positions (world: converted with the view matrix); when not given, "
           "world for Blender's Position pass (LAYER.Position beside LAYER.Depth), else view", kind=str,
           choices=("view", "world")),
    Option("view_matrix", None, "world-to-view matrix, 16 numbers row by row (p_view = M @ (p_world, 1)); "
           "None: the file's worldToCamera header attribute", kind=str),
    Option("convention", "opengl", "view-space axes of the file: opengl (-Z forward, the library's) or "
           "directx (+Z forward: the z of normals and positions is negated)", kind=str, choices=("opengl", "directx")),
    Option("far", None, "depth at or above which a pixel is background (Cycles writes 1e10 there), and the far "
           "plane of device and reverse-z depth (inf: none); when not given, 1e9 for linear depth (device "
           "encodings need it)", unit="world units", minimum=0.0, open_minimum=True),
    Option("fov", None, "vertical field of view of a centred camera (or give intrinsics); None: the file's. A "
           "horizontal one (as Blender and Unreal show) gets a warning where the normals say so",
           unit="degrees", minimum=0.0, maximum=180.0, open_minimum=True, open_maximum=True),
    Option("intrinsics", None, "pinhole camera fx,fy,cx,cy (pixel centres at integers, row 0 at the top); "
           "None: the file's", kind=str, unit="pixels"),
    Option("depth_scale", 1.0, "16-bit PNG depth: world units per step (0.001 for millimetres)",
           unit="world units", minimum=0.0, open_minimum=True),
)
_OPTIONS = options_by_name(ENGINE_OPTIONS)
#: Background depth of linear depth when ``far`` is not given.
LINEAR_FAR = 1e9


@dataclass(frozen=True)
class EngineOptions:
    """How to read an engine's buffers (every field optional, described in :data:`ENGINE_OPTIONS`; see
    the module docstring for the order of the conversions).

    Args:
        channels: ``{target: name}`` for ``depth``, ``normal``, ``position``, ``light``, ``albedo``,
            ``object_id``, ``mask``; relative file names (``FILE.exr:NAME``) are relative to the main
            file's folder. Unnamed targets are found by :data:`CHANNEL_ALIASES`.
        depth_kind, depth_encoding, near, normal_space, normal_encoding, position_space, convention, far, fov,
            depth_scale: see :data:`ENGINE_OPTIONS`.
        view_matrix: ``(4,4)`` world-to-view matrix (column vectors, ``p_view = M @ (p, 1)``) or its 16
            numbers row by row; default: the file's ``worldToCamera`` header attribute.
        intrinsics: ``(fx, fy, cx, cy)`` in pixels.
    """

    channels: dict | None = _OPTIONS["channels"].default
    depth_kind: str = _OPTIONS["depth_kind"].default
    depth_encoding: str = _OPTIONS["depth_encoding"].default
    near: float | None = _OPTIONS["near"].default
    normal_space: str | None = _OPTIONS["normal_space"].default
    normal_encoding: str | None = _OPTIONS["normal_encoding"].default
    position_space: str | None = _OPTIONS["position_space"].default
    view_matrix: tuple | np.ndarray | None = _OPTIONS["view_matrix"].default
    convention: str = _OPTIONS["convention"].default
    far: float | None = _OPTIONS["far"].default
    fov: float | None = _OPTIONS["fov"].default
    intrinsics: tuple | None = _OPTIONS["intrinsics"].default
    depth_scale: float = _OPTIONS["depth_scale"].default

    def __post_init__(self) -> None:
        for name in ("depth_kind", "depth_encoding", "near", "normal_space", "normal_encoding", "position_space",
                     "convention", "fov", "depth_scale"):
            _OPTIONS[name].check(getattr(self, name))
        if self.far is not None:
            check_float("far", self.far, 0.0, open_minimum=True, finite=False)  # inf allowed: no far plane
        if self.depth_encoding != "linear":
            if self.near is None or self.far is None:
                raise ValueError(f"depth_encoding: {self.depth_encoding} depth needs the projection's near and far "
                                 "planes: give --near and --far (--far inf for an infinite far plane)")
            if not self.far > self.near:
                raise ValueError(f"far: expected a far plane beyond near={self.near:g}, got {self.far:g}")
            if self.depth_kind != "z":
                raise ValueError("depth_kind: device depth encodes view-axis depth; 'distance' is for linear depth")
        elif self.near is not None:
            raise ValueError("near: only for --depth-encoding device or reverse-z")
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
            check_view_matrix(m.reshape(4, 4), "view_matrix")
        for target in self.channels or {}:
            check_choice("channels", target, tuple(CHANNEL_ALIASES))


    @property
    def background_depth(self) -> float:
        """Depth at or above which a pixel is background: ``far``, or :data:`LINEAR_FAR` when not given."""
        return LINEAR_FAR if self.far is None else self.far


def check_view_matrix(m: np.ndarray, where: str) -> np.ndarray:
    """``m`` (4,4) as a world-to-view matrix for column vectors, or ``ValueError`` naming ``where``: its
    bottom row must be (0, 0, 0, 1) (a row-vector matrix, such as Unreal's ``FMatrix``, holds the
    translation there: give its transpose) and its 3x3 part invertible."""
    m = np.asarray(m, dtype=np.float64)
    scale = max(1.0, float(np.abs(m).max()))
    if not np.allclose(m[3], (0, 0, 0, 1), rtol=0, atol=1e-6 * scale):
        hint = (": it is a row-vector matrix (such as Unreal's FMatrix); give its transpose"
                if np.allclose(m[:, 3], (0, 0, 0, 1), rtol=0, atol=1e-6 * scale) else "")
        raise ValueError(f"{where}: expected a bottom row (0, 0, 0, 1) (p_view = M @ (p_world, 1)), got "
                         f"({', '.join(f'{x:g}' for x in m[3])}){hint}")
    if abs(np.linalg.det(m[:3, :3])) < 1e-12:
        raise ValueError(f"{where}: its 3x3 part is singular")
    return m


def decode_device_depth(d: np.ndarray, encoding: str, near: float, far: float) -> np.ndarray:
    """View-axis depth from hardware depth ``d`` (see :data:`ENGINE_OPTIONS`' ``depth_encoding``),
    in float64; the far plane (``d = 1`` for device, ``0`` for reverse-z) and non-finite values are
    ``inf`` (background)."""
    d = np.asarray(d, dtype=np.float64)
    if encoding == "device":
        d = 1.0 - d  # the same formula as reverse-z with the planes swapped: 1 - d is 1 at near, 0 at far
    elif encoding != "reverse-z":
        raise ValueError(f"depth_encoding: expected device or reverse-z, got {encoding!r}")
    ok = np.isfinite(d)
    if ((d[ok] < -1e-6) | (d[ok] > 1 + 1e-6)).any():
        raise ValueError(f"depth_encoding: {encoding} depth lies in [0, 1], got values in "
                         f"[{float(d[ok].min()):g}, {float(d[ok].max()):g}]; for depth in world units drop --depth-encoding")
    with np.errstate(divide="ignore", invalid="ignore"):
        z = near / d if math.isinf(far) else near * far / (near + d * (far - near))
    return np.where(ok & (d > 0), z, np.inf)


def _real(value, name: str) -> np.ndarray:

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
            if not f.parts:  # (the binding reports a truncated file on stderr and returns no parts)
                raise ValueError(f"path: {path} is not a readable OpenEXR file (no image parts: truncated?)")
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
    from ..limits import check_limit

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


def _select(channels: dict[str, np.ndarray], options: EngineOptions,
            path: Path) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """The targets found in ``channels`` (and in the other files ``options.channels`` names), and the
    channel names each was read from."""
    out: dict[str, np.ndarray] = {}
    names_read: dict[str, list[str]] = {}
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
        names_read[target] = hits if source is channels else []
    if "depth" not in out and "position" not in out:
        raise ValueError(f"channels: no depth or position channel in {path} (channels: {', '.join(sorted(channels))}); "
                         "name one with --channels depth=NAME")
    return out, names_read


def _blender_passes(names_read: dict[str, list[str]]) -> dict[str, str]:
    """``{target: layer}`` of the ``normal`` and ``position`` buffers read from Blender's multilayer
    passes: ``LAYER.Normal.X/Y/Z`` or ``LAYER.Position.X/Y/Z`` beside ``LAYER.Depth.Z`` (Blender writes
    both passes in world space)."""
    depth = names_read.get("depth") or [""]
    layer, _, rest = depth[0].rpartition(".Depth.")
    if not layer or rest.upper() != "Z":
        return {}
    return {target: f"{layer}.{word}" for target, word in (("normal", "Normal"), ("position", "Position"))
            if [n.lower() for n in names_read.get(target, [])] == [f"{layer}.{word}.{c}".lower() for c in "XYZ"]}


def _read_png_depth(path: Path, scale: float) -> np.ndarray:
    try:
        from PIL import Image
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(f"reading PNG depth needs Pillow: {install_hint('plot', 'pillow')}") from err
    from ..limits import check_limit, limit

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


class CameraMissing(ValueError):
    """An engine file that names no camera (its message gives ``torch-ao convert``'s flags, a command without
    them says how to proceed instead)."""


def read_engine_arrays(path: str | os.PathLike, **options) -> dict[str, np.ndarray]:
    """Read an OpenEXR file (``.exr``) or a 16-bit PNG depth (``.png``) into ``.npz``-layout arrays in
    the library's conventions. ``options`` are :class:`EngineOptions` fields."""

    opts = EngineOptions(**options)
    path = _existing(path)
    suffix = path.suffix.lower()
    header: dict = {}
    if suffix == ".exr":
        channels, header = _read_exr(path)
        arrays, names_read = _select(channels, opts, path)
        opts = _spaces_of_blender_passes(opts, _blender_passes(names_read), header)
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
    if "intrinsics" not in arrays and "fov_y_degrees" not in arrays and opts.fov is None and opts.intrinsics is None:
        raise CameraMissing(f"camera: {path.name} names no camera; give --fov DEGREES or --intrinsics FX,FY,CX,CY")
    arrays = apply_engine_options(arrays, opts)
    _warn_if_linear_depth_looks_like_device_depth(arrays.get("depth"), opts)
    return arrays


def _spaces_of_blender_passes(opts: EngineOptions, passes: dict[str, str], header: dict) -> EngineOptions:
    """``opts`` with ``normal_space``/``position_space`` set to world where they are not given and the
    buffer is a Blender pass (:func:`_blender_passes`); without a view matrix, one line naming the flags."""
    changes = {}
    for target, layer in passes.items():
        field = f"{target}_space"
        if getattr(opts, field) is None:
            if opts.view_matrix is None and "worldToCamera" not in header:
                raise ValueError(f"{field}: {layer} is Blender's {target.capitalize()} pass, in world space: give "
                                 f"--view-matrix (the camera's world-to-view matrix), or --{field.replace('_', '-')} "
                                 "view if it holds view-space vectors")
            changes[field] = "world"
    return replace(opts, **changes) if changes else opts


def _warn_if_linear_depth_looks_like_device_depth(depth, opts: EngineOptions) -> None:
    if depth is None or opts.depth_encoding != "linear":
        return
    d = np.asarray(depth)
    d = d[np.isfinite(d) & (d > 0)]
    if d.size and float(d.max()) <= 1.0 and float(d.max()) - float(d.min()) < 0.5:
        warnings.warn(f"depth: every depth is in [{float(d.min()):.4g}, {float(d.max()):.4g}]: if this is hardware "
                      "depth, give --depth-encoding device or reverse-z with --near and --far", stacklevel=3)


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

    try:
        camera = _camera_from_arrays(arrays, height, width, 1)
    except ValueError:
        raise ValueError("depth_kind: 'distance' needs the camera (give --fov or --intrinsics)") from None
    return camera.to(dtype=torch.float64).pixel_rays()[0].norm(dim=0).numpy()


def _view_matrix(arrays: dict, opts: EngineOptions, what: str) -> np.ndarray:
    if opts.view_matrix is not None:
        return np.asarray(opts.view_matrix, dtype=np.float64).reshape(4, 4)
    if "view_matrix" in arrays:
        return check_view_matrix(arrays["view_matrix"], "view_matrix (the file's worldToCamera header attribute)")
    raise ValueError(f"view_matrix: {what} needs the world-to-view matrix; the file has no worldToCamera "
                     "header attribute, so give --view-matrix (16 numbers, row by row)")


def apply_engine_options(arrays: dict[str, np.ndarray], opts: EngineOptions) -> dict[str, np.ndarray]:
    """Convert ``.npz``-layout ``arrays`` (top-down) from an engine's conventions to the
    library's (see the module docstring). Returns a new dict; ``view_matrix`` is consumed."""
    arrays = dict(arrays)
    H, W = _size_of(arrays)
    _set_camera(arrays, opts)
    for key in ("depth", "backface_depth"):  # (a back face at the background: no exit, inf)
        if key in arrays:
            arrays[key] = _view_depth(key, arrays, opts, H, W)
    if "depth" not in arrays and "position" in arrays and math.isfinite(opts.background_depth):  # GBuffer derives depth = -z
        p = arrays["position"]
        arrays["position"] = np.where((-p[..., 2:] >= opts.background_depth), np.nan, p).astype(p.dtype)
    if "normal" in arrays:
        arrays["normal"] = _decoded_normals(arrays, opts.normal_encoding)
    for key in ("normal", "position"):
        space = (opts.normal_space if key == "normal" else opts.position_space) or "view"
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
    if "normal" in arrays and "depth" in arrays:
        _refuse_zero_normals_at_a_far_plane(arrays)
        if opts.fov is not None and H != W:
            _warn_if_fov_looks_horizontal(arrays, opts.fov)
    return arrays


def _view_depth(key: str, arrays: dict, opts: EngineOptions, H: int, W: int) -> np.ndarray:
    """``arrays[key]`` (depth, or the back-face pass's) as view-axis depth in world units: decoded from the
    device encoding, divided by the ray length for a distance, ``inf`` at or beyond the background."""
    depth = np.asarray(arrays[key])
    if not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f"{key}: expected a floating-point channel, got {depth.dtype}")
    dtype = np.result_type(depth.dtype, np.float32)
    if opts.depth_encoding != "linear":
        depth = decode_device_depth(depth, opts.depth_encoding, opts.near, opts.far).astype(dtype)
    if opts.depth_kind == "distance":
        depth = (depth / _ray_lengths(arrays, H, W)).astype(dtype)
    if math.isfinite(opts.background_depth):
        depth = np.where(depth >= opts.background_depth, np.inf, depth).astype(depth.dtype)
    return depth


def _valid_depth(arrays: dict) -> np.ndarray:
    """``(...,H,W)`` bool: finite, positive depth (and the mask, when there is one)."""
    depth = np.asarray(arrays["depth"])
    valid = np.isfinite(depth) & (depth > 0)
    return valid & arrays["mask"] if "mask" in arrays else valid


def _decoded_normals(arrays: dict, encoding: str | None) -> np.ndarray:
    """The normals as signed vectors: decoded from ``0.5 n + 0.5`` when ``encoding="unorm"``, or when
    not given and every component on valid pixels is in [0, 1], the median length is off 1 by more
    than 5 % and after decoding within 1 % (then with a warning)."""
    n = np.asarray(arrays["normal"])
    if encoding == "signed":
        return n
    if encoding is None:
        valid = _valid_depth(arrays) if "depth" in arrays else np.isfinite(n).all(axis=-1)
        x = n[valid].astype(np.float64)
        x = x[np.isfinite(x).all(axis=-1) & (np.abs(x).sum(axis=-1) > 0)]
        if not x.size or x.min() < -1e-3 or x.max() > 1 + 1e-3:
            return n
        raw = np.median(np.abs(np.linalg.norm(x, axis=-1) - 1))
        decoded = np.median(np.abs(np.linalg.norm(2 * x - 1, axis=-1) - 1))
        if not (raw > 0.05 and decoded < 0.01):
            return n
        warnings.warn("normal_encoding: the normals are stored as 0.5 n + 0.5 (every component in [0, 1], unit "
                      f"length only after decoding: median |length - 1| {raw:.3f} as stored, {decoded:.1e} decoded); "
                      "decoded them. Give --normal-encoding unorm to say so, or signed to keep them", stacklevel=4)
    return (2 * n.astype(np.float32) - 1).astype(n.dtype)


def _refuse_zero_normals_at_a_far_plane(arrays: dict) -> None:
    """One line naming ``far`` where the valid pixels without a normal all lie beyond every other pixel
    (a far plane or sky that should be background); other zero normals are left to :class:`GBuffer`."""
    valid = _valid_depth(arrays)
    n = np.asarray(arrays["normal"], dtype=np.float64)
    zero = valid & ~(np.linalg.norm(np.nan_to_num(n), axis=-1) > 0)
    if not zero.any():
        return
    depth = np.asarray(arrays["depth"], dtype=np.float64)
    far, others = depth[zero].min(), depth[valid & ~zero]
    if not others.size or far > others.max():
        raise ValueError(f"far: {int(zero.sum())} valid pixels have zero-length normals, all at depth >= {far:.7g} "
                         f"(beyond every other pixel: a far plane or sky); give --far {far:.7g} to make them background")


def _warn_if_fov_looks_horizontal(arrays: dict, fov: float) -> None:
    """Warn when ``fov`` (read as vertical) fits the file's own normals far worse than the same angle
    read as horizontal: the median angle between the file's normals and those reconstructed from depth
    is over 2 degrees with the vertical reading and under a quarter of it with the horizontal one."""
    from ..gbuffer import normals_from_depth
    from ..camera import PinholeCamera

    depth = torch.from_numpy(np.asarray(arrays["depth"], dtype=np.float64))
    depth = depth.reshape(-1, 1, *depth.shape[-2:])
    B, _, H, W = depth.shape
    valid = torch.from_numpy(_valid_depth(arrays)).reshape(B, 1, H, W)
    if int(valid.sum()) < 64:
        return
    normals = torch.from_numpy(np.asarray(arrays["normal"], dtype=np.float64)).reshape(B, H, W, 3).permute(0, 3, 1, 2)
    fov_h = math.degrees(2 * math.atan(math.tan(math.radians(fov) / 2) * H / W))  # the vertical fov of fov read horizontally

    def error(fov_y: float) -> float:
        camera = PinholeCamera.from_fov(fov_y, H, W, batch_size=B).to(dtype=torch.float64)
        safe = torch.where(valid, depth, torch.ones_like(depth))
        cos = (normals_from_depth(safe, camera, valid=valid) * normals).sum(1, keepdim=True)
        return math.degrees(float(torch.acos(cos[valid].clamp(-1, 1)).median()))

    vertical, horizontal = error(fov), error(fov_h)
    if vertical > 2.0 and horizontal < vertical / 4:
        warnings.warn(f"fov: --fov {fov:g} is read as the vertical field of view, but the normals fit the depth far "
                      f"better when it is the horizontal one (median normal error {horizontal:.2g} against "
                      f"{vertical:.2g} degrees); Blender and Unreal show the horizontal field of view: if so, give "
                      f"--fov {fov_h:.6g}", stacklevel=4)
