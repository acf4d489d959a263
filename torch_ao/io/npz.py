"""The ``.npz`` G-buffer file format (read and written with ``allow_pickle=False``).

Keys (arrays are top-down: row 0 is the top of the image; ``...`` is an optional batch axis B):

=================  ==================  =====================================================
key                shape               meaning
=================  ==================  =====================================================
``depth``          ``(...,H,W)``       positive view-axis depth; ``inf``/``0``/``nan``/``>= 1e15`` = background
``normal``         ``(...,H,W,3)``     unit view-space normals (OpenGL axes, facing the camera)
``light``          ``(...,H,W,3)``     direct light leaving each pixel
``mask``           ``(...,H,W)``       bool, False = background
``object_id``      ``(...,H,W)``       integer object ids
``backface_depth`` ``(...,H,W)``       depth where the camera ray leaves the first-hit object (``inf`` = none)
``position``       ``(...,H,W,3)``     view-space positions (OpenGL axes); ``depth`` may then be absent
``intrinsics``     ``(3,3)``/``(B,3,3)`` pinhole ``K`` in pixels (pixel centres at integers)
``fov_y_degrees``  scalar or ``(B,)``  used when ``intrinsics`` is absent (centred camera)
``ao``             ``(...,H,W)``       reference visibility (1 = unoccluded)
``ao_stderr``      ``(...,H,W)``       its per-pixel Monte Carlo standard error
``max_distance``   scalar              the reference's maximum ray distance (``inf`` allowed)
``visibility``     ``(...,H,W)``       a method's output visibility
``indirect``       ``(...,H,W,3)``     a method's indirect light
=================  ==================  =====================================================

Other image-like keys (``(...,H,W)`` or ``(...,H,W,C)``) are kept and returned as ``(B,C,H,W)`` tensors.
"""
from __future__ import annotations

import glob
import os
import re
import socket
import tempfile
import time
import zipfile
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from ..camera import PinholeCamera
from ..gbuffer import GBuffer

__all__ = ["gbuffer_from_arrays", "save_npz", "read_npz", "image_to_numpy",
           "numpy_to_image", "write_text_atomic", "save_json", "write_atomic", "remove_stale_temporaries",
           "check_output_path", "STALE_TEMPORARY_SECONDS"]

# "position" is also returned among the extras (as before it was a G-buffer key; references written by
# ``torch-ao render`` carry it).
_GBUFFER_KEYS = ("depth", "normal", "light", "mask", "object_id", "backface_depth", "intrinsics", "fov_y_degrees")
# npz key -> (GBuffer argument, channels last)
_IMAGE_KEYS = {"normal": ("normals", True), "light": ("light", True), "mask": ("mask", False),
               "object_id": ("object_id", False),
               "backface_depth": ("backface_depth", False), "position": ("position", True)}


def read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz`` file, refusing pickled objects, with a clear error for bad files.

    Every member's header is read first (:func:`npz_members`): a member whose data is shorter than its
    header says is reported as truncated, and what would not fit is refused before anything is
    allocated (:mod:`torch_ao.limits`: ``array_bytes`` summed over the members, ``image_pixels`` per image).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no such file: {path}")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"path: {path} is not a valid .npz file (not a zip archive)")
    npz_members(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except ValueError as err:  # raised by numpy for object arrays when allow_pickle=False
        raise ValueError(f"path: {path} holds pickled objects, which are refused ({err})") from None
    except (zipfile.BadZipFile, OSError, EOFError) as err:
        raise ValueError(f"path: {path} is not a valid .npz file ({err})") from None


def image_pixels(shape: tuple[int, ...]) -> int:
    """Pixels of one image of an array of ``shape`` in the ``.npz`` layout: ``H*W`` of ``(...,H,W)``, or of
    ``(...,H,W,C)`` when its last axis is a few channels (at most 4); 0 for fewer than two axes."""
    if len(shape) >= 3 and shape[-1] <= 4:
        return int(shape[-3]) * int(shape[-2])
    return int(shape[-2]) * int(shape[-1]) if len(shape) >= 2 else 0


def npz_members(path: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """``{key: (shape, dtype)}`` of an ``.npz`` file from its members' headers alone (nothing else is read).

    Raises ``ValueError`` naming the file and member for a pickled (object) member, a member whose data
    is shorter than its header says (truncated), or a header numpy cannot read; and
    :class:`~torch_ao.limits.ResourceLimitError` for a member image above ``image_pixels`` or members
    above ``array_bytes`` in all (the uncompressed size: a zip bomb is refused without inflating it).
    """
    from ..limits import check_limit

    members, total = {}, 0
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                key = info.filename[:-4]
                with zf.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    shape, fortran, dtype = (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
                                             else np.lib.format.read_array_header_2_0(f))
                    header = f.tell()
                if dtype.hasobject:
                    raise ValueError(f"path: {path}: member {key!r} holds pickled objects ({dtype}), which are refused")
                pixels = image_pixels(shape)
                check_limit("image_pixels", pixels, f"path: {path}: member {key!r} of shape {shape}")
                need = int(np.prod(shape, dtype=object)) * dtype.itemsize
                if header + need > info.file_size:
                    raise ValueError(f"path: {path}: member {key!r} is truncated: its header says {shape} {dtype} "
                                     f"({need} bytes), the member holds {info.file_size - header}")
                total += info.file_size
                members[key] = (tuple(shape), dtype)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, SyntaxError) as err:
        if isinstance(err, ValueError) and str(err).startswith(f"path: {path}"):
            raise
        raise ValueError(f"path: {path} is not a valid .npz file ({type(err).__name__}: {err})") from None
    check_limit("array_bytes", total, f"path: {path} ({len(members)} arrays, uncompressed)")
    return members


def numpy_to_image(array: np.ndarray, name: str, channels_last: bool) -> torch.Tensor:
    """``(...,H,W)`` or ``(...,H,W,C)`` array -> ``(B,C,H,W)`` tensor."""
    a = np.asarray(array)
    if channels_last:
        if a.ndim not in (3, 4):
            raise ValueError(f"{name}: expected shape (H,W,C) or (B,H,W,C), got {a.shape}")
        t = torch.from_numpy(np.ascontiguousarray(a))
        t = t.unsqueeze(0) if t.dim() == 3 else t
        return t.permute(0, 3, 1, 2).contiguous()
    if a.ndim not in (2, 3):
        raise ValueError(f"{name}: expected shape (H,W) or (B,H,W), got {a.shape}")
    t = torch.from_numpy(np.ascontiguousarray(a))
    t = t.unsqueeze(0) if t.dim() == 2 else t
    return t.unsqueeze(1)


def image_to_numpy(t: torch.Tensor) -> np.ndarray:
    """``(B,C,H,W)`` tensor -> ``(B,H,W)`` (C = 1) or ``(B,H,W,C)`` array."""
    a = t.detach().cpu()
    if a.dtype in (torch.float16, torch.bfloat16):
        a = a.float()
    a = a.numpy()
    return a[:, 0] if a.shape[1] == 1 else np.moveaxis(a, 1, -1)


class FileContentError(ValueError):
    """Bad content of a file (a key or attribute of it): named by the file, never by a command-line flag."""


def real_array(value, key: str, source) -> np.ndarray:
    """``value`` as a float64 array, when it holds real numbers (integers or floats; not booleans,
    strings, complex numbers or objects): else ``ValueError`` naming ``key`` and ``source`` (the file)."""
    a = np.asarray(value)
    if a.dtype.kind not in "iuf":
        raise FileContentError(f"{key}: expected real numbers in {source}, got {a.dtype} {_preview(a)}")
    return a.astype(np.float64)


def _preview(a: np.ndarray) -> str:
    text = repr(a.reshape(-1)[:4].tolist())
    return text if len(text) <= 40 else text[:37] + "..."


def _camera_from_arrays(arrays: dict, height: int, width: int, batch: int, source="arrays") -> PinholeCamera:
    if "intrinsics" in arrays:
        K = torch.from_numpy(real_array(arrays["intrinsics"], "intrinsics", source))
        if K.shape not in ((3, 3), (batch, 3, 3), (1, 3, 3)):
            raise ValueError(f"intrinsics: expected shape (3,3) or ({batch},3,3) in {source}, got {tuple(K.shape)}")
        try:
            return PinholeCamera(K.float(), height, width)
        except ValueError as err:
            raise ValueError(f"{err} (in {source})") from None
    if "fov_y_degrees" in arrays:
        fov = real_array(arrays["fov_y_degrees"], "fov_y_degrees", source).reshape(-1)
        try:
            return PinholeCamera.from_fov(torch.from_numpy(fov).float(), height, width, batch_size=batch)
        except ValueError as err:
            raise ValueError(f"{err} (in {source})") from None
    raise ValueError(f"camera: {source} needs 'intrinsics' (3,3) or 'fov_y_degrees'")


def gbuffer_from_arrays(arrays: dict[str, np.ndarray], path: str | os.PathLike = "arrays",
                        device: torch.device | str | None = None) -> tuple[GBuffer, dict[str, torch.Tensor]]:
    """:func:`~torch_ao.io.load_gbuffer` on arrays already read (``path`` names them in errors: every error is a
    ``ValueError`` whose message names the key and ``path``)."""
    try:
        return _gbuffer_from_arrays(arrays, path, device)
    except (ValueError, TypeError) as err:
        if str(path) in str(err):
            raise
        raise ValueError(f"{err} (in {path})") from None


def _gbuffer_from_arrays(arrays, path, device):
    if "depth" not in arrays and "position" not in arrays:
        raise ValueError(f"path: {path} has no 'depth' or 'position' array (keys: {sorted(arrays)})")
    image_args = {}
    for key, (arg, chl) in _IMAGE_KEYS.items():
        if key in arrays:
            image_args[arg] = numpy_to_image(arrays[key], key, channels_last=chl)
    if "depth" in arrays:
        if not np.issubdtype(arrays["depth"].dtype, np.floating):
            raise TypeError(f"depth: expected a floating-point array, got {arrays['depth'].dtype}")
        depth = numpy_to_image(arrays["depth"], "depth", channels_last=False)
    else:
        depth = None
    B, _, H, W = (depth if depth is not None else image_args["position"]).shape
    camera = _camera_from_arrays(arrays, H, W, B, path)
    to = dict(device=device)
    gb = GBuffer(
        depth=None if depth is None else depth.to(**to),
        camera=camera.to(device=device),
        **{k: v.to(**to) for k, v in image_args.items()},
    )
    if depth is not None and gb.position is not None and _is_unprojected_depth(gb):
        gb.position = None  # (references from `torch-ao render`): the depth fetch is the same and cheaper
    extras: dict[str, torch.Tensor] = {}
    for key, value in arrays.items():
        if key in _GBUFFER_KEYS:
            continue
        a = np.asarray(value)
        if a.ndim >= 2 and a.shape[-2:] == (H, W):
            extras[key] = numpy_to_image(a, key, channels_last=False).to(**to)
        elif a.ndim >= 3 and a.shape[-3:-1] == (H, W):
            extras[key] = numpy_to_image(a, key, channels_last=True).to(**to)
        else:
            extras[key] = torch.from_numpy(a).to(**to)
    for key in ("ao", "ao_stderr"):
        if key in extras and extras[key].is_floating_point():
            bad = ~torch.isfinite(extras[key]) & gb.valid
            if bool(bad.any()):
                raise ValueError(f"{key}: {int(bad.sum())} non-finite values on valid pixels in {path}")
    return gb, extras


def _is_unprojected_depth(gb: GBuffer) -> bool:
    """Whether ``gb.position`` is its depth unprojected (to 1e-6 relative) on every valid pixel."""
    unprojected = gb.camera.unproject(gb.safe_depth)
    error = (gb.position - unprojected).norm(dim=1, keepdim=True)
    return bool((error <= 1e-6 * unprojected.norm(dim=1, keepdim=True))[gb.valid].all())


def save_npz(path: str | os.PathLike, gbuffer: GBuffer | None = None, *, keep_existing: bool = False,
             **arrays) -> Path:
    """Write a G-buffer and/or images to ``path`` atomically (a temporary file, then a rename; with
    ``keep_existing``, a file another writer put there meanwhile stands: :func:`write_atomic`).

    ``arrays`` values may be ``(B,C,H,W)`` tensors (stored top-down as ``(B,H,W[,C])``),
    numpy arrays or scalars.

    Shape:
        - gbuffer: a :class:`GBuffer` (images ``(B, C, H, W)``); arrays: ``(B, C, H, W)`` tensors, numpy arrays or scalars.
        - Output: the written path.
    """
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    if gbuffer is not None:
        depth = torch.where(gbuffer.valid, gbuffer.depth, torch.full_like(gbuffer.depth, float("inf")))
        out["depth"] = image_to_numpy(depth)
        for key, (field, _) in _IMAGE_KEYS.items():
            if getattr(gbuffer, field) is not None:
                out[key] = image_to_numpy(getattr(gbuffer, field))
        out["intrinsics"] = gbuffer.camera.intrinsics.detach().cpu().numpy()
    for key, value in arrays.items():
        if isinstance(value, torch.Tensor):
            out[key] = image_to_numpy(value) if value.dim() == 4 else value.detach().cpu().numpy()
        else:
            out[key] = np.asarray(value)
    return write_atomic(path, lambda tmp: np.savez_compressed(tmp, **out), suffix=".npz", keep_existing=keep_existing)


#: Age after which a temporary file of :func:`write_atomic` is stale even when the process that named
#: it seems alive (its PID reused, or a writer on another host): no write takes this long.
STALE_TEMPORARY_SECONDS = 24 * 3600

_HOST = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname()) or "host"


def _temporary_writer(path: Path) -> tuple[str, int] | None:
    """``(host, pid)`` of the writer a :func:`write_atomic` temporary name records, else ``None``."""
    match = re.search(r"\.([A-Za-z0-9_]+)-(\d+)\.[^.]+\.tmp(\.[^.]*)?$", path.name)
    return (match.group(1), int(match.group(2))) if match else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def write_atomic(path: str | os.PathLike, write: Callable[[str], None], *, suffix: str = "",
                 keep_existing: bool = False) -> Path:
    """Create or replace ``path`` atomically: ``write(tmp)`` fills a temporary file in the same folder,
    which is then renamed onto ``path``, so readers (and a run killed mid-write) never see a partial file.
    With ``keep_existing``, a file that another writer put at ``path`` meanwhile stands and the new one is
    dropped (linked into place, which fails where a file exists; where the file system has no links, the
    file is replaced only when absent).

    The temporary file is ``<name>.<host>-<pid>.<random>.tmp<suffix>`` (``suffix``: an extension the
    writer needs, e.g. ``.npz``), so :func:`remove_stale_temporaries` can tell a dead writer's leftover
    from a live one's file in progress; the stale leftovers of earlier writes of ``path`` are removed
    first. The file gets the usual permissions (``0666`` less the umask).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path.parent, path.name)
    fd, tmp = tempfile.mkstemp(prefix=f"{path.name}.{_HOST}-{os.getpid()}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600
        if keep_existing:
            _link_unless_present(tmp, path)
        else:
            os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _link_unless_present(tmp: str, path: Path) -> None:
    """``tmp`` published at ``path`` unless a file is there (write_atomic's ``keep_existing``)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        pass
    except OSError:  # (no hard links here)
        if not path.exists():
            os.replace(tmp, path)


def remove_stale_temporaries(folder: str | os.PathLike, name: str = "*") -> list[Path]:
    """Delete the temporary files :func:`write_atomic` left in ``folder`` (for the file ``name``; ``*``:
    any) when it was killed mid-write; returns them. A temporary file is stale when its writer (the PID
    in its name, on this host) is dead, or when it is older than :data:`STALE_TEMPORARY_SECONDS`; a
    concurrent run's file in progress is never deleted."""
    removed = []
    now = time.time()
    for tmp in Path(folder).glob(f"{name if name == '*' else glob.escape(name)}.*.tmp*"):
        writer = _temporary_writer(tmp)
        try:
            old = now - tmp.stat().st_mtime > STALE_TEMPORARY_SECONDS
        except FileNotFoundError:  # renamed or removed by its writer meanwhile
            continue
        dead = writer is not None and writer[0] == _HOST and not _alive(writer[1])
        if dead or old:
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def check_output_path(flag: str, path: str | os.PathLike, suffixes: Sequence[str] = (), *, folder: bool = False) -> Path:
    """``ValueError`` naming ``flag`` unless ``path`` can be written: a file that ends with one of
    ``suffixes`` (any when empty; compared without case) and is not a folder, or with ``folder=True``
    a folder (existing, or to be created) that is not a file; either way its nearest existing parent
    must be a writable folder. Nothing is created: call it before computing anything."""
    path = Path(path)
    if folder:
        if path.exists() and not path.is_dir():
            raise ValueError(f"{flag}: {path} is a file; expected a folder")
    else:
        if suffixes and path.suffix.lower() not in suffixes:
            raise ValueError(f"{flag}: expected a {' or '.join(suffixes)} file name, got {str(path)!r}")
        if path.is_dir():
            raise ValueError(f"{flag}: {path} is a folder; expected a file name")
    parent = path if folder and path.is_dir() else path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"{flag}: cannot write {path}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{flag}: cannot write {path}: {parent} is not writable")
    return path


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`write_atomic`)."""

    def write(tmp: str) -> None:
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            f.write(text)

    return write_atomic(path, write)


def save_json(path: str | os.PathLike, obj, **dumps_options) -> Path:
    """``json.dumps(obj, indent=2, **dumps_options)`` written atomically (:func:`write_text_atomic`)."""
    import json

    return write_text_atomic(path, json.dumps(obj, **({"indent": 2} | dumps_options)))
