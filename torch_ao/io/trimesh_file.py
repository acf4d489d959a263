"""Reading one mesh file with trimesh, with the library's errors and with the files it names
confined to its folder (:mod:`~torch_ao.io.confine`); no scene types, so that
:class:`~torch_ao.scene.Mesh` and :mod:`torch_ao.io.mesh` both build on it."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import torch

from ..checks import install_hint
from .confine import ALLOW_HINT, OutsidePathError, confined_path, confined_resolver, scene_root

__all__ = ["read_trimesh", "check_gltf_uris", "normalize_vertices", "gltf_json", "one_line", "GLTF_SUFFIXES"]

GLTF_SUFFIXES = (".gltf", ".glb")


def one_line(err: Exception) -> str:
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def read_trimesh(path: Path, *, allow_outside_paths: bool = False, **kwargs):
    """``trimesh.load(path, **kwargs)`` with the library's errors (no such file, no trimesh,
    unreadable file), each one line naming the file. The files ``path`` names (materials, textures,
    glTF buffers) are confined to its folder unless ``allow_outside_paths``
    (:mod:`~torch_ao.io.confine`)."""
    if not path.is_file():
        raise FileNotFoundError(f"mesh: no such file: {path}")
    try:
        import trimesh
    except ImportError:
        raise ImportError(f"mesh: loading mesh files needs trimesh: {install_hint('mesh', 'trimesh')}") from None
    if path.suffix.lower() in GLTF_SUFFIXES:
        check_gltf_uris(path, gltf_json(path), allow_outside_paths=allow_outside_paths)
    resolver = confined_resolver(path, allow_outside=allow_outside_paths)
    try:
        loaded = trimesh.load(str(path), resolver=resolver, **kwargs)
    except Exception as err:  # trimesh raises many kinds for bad or unsupported files
        if resolver.refused:
            raise OutsidePathError(resolver.refused[0]) from None
        raise ValueError(f"mesh: cannot read {path} ({one_line(err)})") from None
    if resolver.refused:  # trimesh skipped the asset (a material, say): still refused
        raise OutsidePathError(resolver.refused[0])
    return loaded


def check_gltf_uris(path: Path, header: dict, *, allow_outside_paths: bool = False) -> None:
    """Refuse (:class:`~torch_ao.io.confine.OutsidePathError`) a glTF whose ``buffers`` or
    ``images`` name a file outside its folder, or any URI with a scheme but ``data:``, before trimesh
    reads anything."""
    from urllib.parse import unquote, urlsplit

    root = scene_root(path)
    for kind in ("buffers", "images"):
        entries = header.get(kind, [])
        if not isinstance(entries, list):
            raise ValueError(f"mesh: {path}: {kind}: expected a list, got {type(entries).__name__}")
        for i, entry in enumerate(entries):
            uri = entry.get("uri") if isinstance(entry, dict) else None
            if uri is None:
                continue
            if not isinstance(uri, str):
                raise ValueError(f"mesh: {path}: {kind}[{i}].uri: expected a string, got {type(uri).__name__}")
            if uri.startswith("data:"):
                continue
            if len(urlsplit(uri).scheme) > 1 and not allow_outside_paths:  # (a one-letter scheme is a drive, c:/)
                raise OutsidePathError(f"scene: {path}: {kind}[{i}].uri {uri!r} is a URL, outside the scene's folder "
                                       f"{root}; files a scene names must be inside its folder ({ALLOW_HINT})")
            confined_path(path, unquote(uri), f"{kind}[{i}].uri", root=root, allow_outside=allow_outside_paths)


def normalize_vertices(v: torch.Tensor, path: Path) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Scale and shift ``(V,3)`` vertices to a largest extent of 1, resting on ``y = 0`` and centred
    on the ``y`` axis. Returns ``(normalised, offset (3,), scale)`` with ``v = normalised * scale + offset``."""
    lo, hi = v.min(0).values, v.max(0).values
    scale = float((hi - lo).max())
    if scale <= 0:
        raise ValueError(f"mesh: {path} is degenerate (zero extent)")
    centre = (lo + hi) / 2
    offset = torch.stack([centre[0], lo[1], centre[2]])
    return (v - offset) / scale, offset, scale


def gltf_json(path: Path) -> dict:
    """The JSON part of a ``.gltf`` or ``.glb`` file."""
    data = path.read_bytes()
    try:
        if data[:4] == b"glTF":
            length, kind = struct.unpack_from("<II", data, 12)
            if kind != 0x4E4F534A:  # "JSON"
                raise ValueError("the first GLB chunk is not JSON")
            return json.loads(data[20:20 + length])
        return json.loads(data)
    except (ValueError, struct.error, UnicodeDecodeError) as err:
        raise ValueError(f"mesh: cannot read {path} as glTF ({one_line(err)})") from None
