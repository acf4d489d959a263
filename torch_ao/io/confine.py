"""Confinement: the files a scene file names stay inside the scene file's folder.

A scene file (a Mitsuba 3 ``.xml``, a glTF's buffers and images, an OBJ's material library) may name
other files. Every such reference is resolved (relative names against the scene file's folder,
symbolic links followed) and refused, before anything reads it, when it lands outside that folder
(its subfolders are inside), unless the caller allows it (``allow_outside_paths=True``,
``torch-ao render --allow-outside-paths``). The refusal names the scene file and the reference as
written, never anything read from the referenced file.
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["OutsidePathError", "confined_path", "confined_resolver"]

ALLOW_HINT = "allow_outside_paths=True or torch-ao render --allow-outside-paths allows it"


class OutsidePathError(ValueError):
    """A scene file names a file outside its folder."""


def scene_root(scene_file: str | os.PathLike) -> Path:
    """The folder a scene file's references are confined to: its parent, symbolic links resolved."""
    return Path(scene_file).absolute().parent.resolve()


def confined_path(source: str | os.PathLike, reference: str, what: str, *, root: Path,
                  base: Path | None = None, allow_outside: bool = False) -> Path:
    """The file ``reference`` (as written in ``source``, relative to ``base``, by default ``root``)
    resolved, after checking that it lies inside the folder ``root`` (:func:`scene_root`).

    Args:
        source: the file that holds the reference (named in the message).
        reference: the file name as written there.
        what: where it was written (``"<include filename>"``, ``"buffers[0].uri"``), for the message.
        allow_outside: skip the check (the path is still resolved).
    Raises:
        OutsidePathError: naming ``source``, ``what`` and ``reference``, when the resolved path is
            outside ``root`` (``..``, an absolute path, or a symbolic link that leaves it).
    """
    target = ((root if base is None else base) / os.path.expanduser(reference)).resolve()
    if not allow_outside and not target.is_relative_to(root):
        raise OutsidePathError(f"scene: {source}: {what} {reference!r} is outside the scene's folder {root}; "
                               f"files a scene names must be inside its folder ({ALLOW_HINT})")
    return target


def confined_resolver(path: Path, *, allow_outside: bool = False):
    """A trimesh resolver for ``path``'s assets (materials, textures, buffers) that refuses, with
    :class:`OutsidePathError`, every name outside ``path``'s folder (whatever trimesh's own version
    does). ``resolver.refused`` lists the messages of refused names (trimesh swallows some errors, so
    the caller raises the first one after loading)."""
    from trimesh.resolvers import Resolver

    root = scene_root(path)

    class _Confined(Resolver):
        def __init__(self, folder: Path, refused: list[str]) -> None:
            self.parent, self.refused = folder, refused
            self.file_path, self.file_name = str(path), path.name

        def get(self, name: str) -> bytes:
            try:
                target = confined_path(path, name.strip(), "asset", root=root, base=self.parent,
                                       allow_outside=allow_outside)
            except OutsidePathError as err:
                self.refused.append(str(err))
                raise
            return target.read_bytes()

        def namespaced(self, namespace: str):
            return _Confined(self.parent / namespace, self.refused)

        def keys(self):
            for folder, _, names in os.walk(self.parent):
                for name in names:
                    yield os.path.relpath(os.path.join(folder, name), self.parent)

        def write(self, name, data):
            raise OutsidePathError(f"scene: {path}: reading a scene writes no files ({name!r})")

    return _Confined(root, [])
