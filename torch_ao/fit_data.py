"""Views read on access: a fit over hundreds of frames holds a few of them in memory, not all.

* :class:`ViewFiles` is a sequence of reference views backed by files (G-buffer + ``ao`` reference, as
  :func:`~torch_ao.views.load_views` reads them): ``views[i]`` reads file ``i`` (or takes it from a small
  cache of the most recently read ones), and the view is dropped once nothing uses it. :func:`~torch_ao.fit.fit`
  and :func:`~torch_ao.fit.evaluate` take it wherever they take a list of views, with the same result.
* :func:`reference_files` expands what a user names (files, folders, glob patterns, ``.txt`` lists of
  paths) into the list of files.
"""
from __future__ import annotations

import glob
import os
import weakref
from collections import OrderedDict
from pathlib import Path
from typing import Iterable, Sequence

from .views import FitView, load_views

__all__ = ["ViewFiles", "reference_files", "view_names", "REFERENCE_SUFFIXES"]

#: Suffixes of the files a folder or glob contributes: G-buffer files that can hold an ``ao`` reference.
REFERENCE_SUFFIXES = (".npz", ".exr")
_GLOB = set("*?[")


class ViewFiles(Sequence[FitView]):
    """Reference views of ``paths``, each read when it is accessed (:func:`~torch_ao.views.load_views`).

    Args:
        paths: G-buffer files holding an ``ao`` array (``.npz``; ``.exr`` with the ``reading`` options).
        names: the views' names (default: the paths, as :func:`~torch_ao.views.load_views` names them).
        device: where the views' tensors go.
        cache_size: how many of the most recently read views are kept (0: none; each access reads the file).
        reading: how to read the files (:func:`~torch_ao.views.load_views`' options).

    ``views[i:j]`` is a :class:`ViewFiles` of those files (own cache). :attr:`reads` counts the files read,
    :attr:`resident` the views of this sequence still in memory, :attr:`peak_resident` its largest value
    at any read.

    Shape:
        - Output: ``views[i]``, a :class:`~torch_ao.FitView` whose ``gbuffer`` images are ``(B, C, H, W)`` and
          ``reference``/``stderr`` ``(B, 1, H, W)``, as :func:`~torch_ao.views.load_views` gives.
    """

    def __init__(self, paths: Iterable[str | os.PathLike], *, names: Sequence[str] | None = None, device=None,
                 cache_size: int = 2, reading: dict | None = None) -> None:
        self.paths = [Path(p) for p in paths]
        self.names = [str(p) for p in self.paths] if names is None else [str(n) for n in names]
        if len(self.names) != len(self.paths):
            raise ValueError(f"names: expected one name per path ({len(self.paths)}), got {len(self.names)}")
        if cache_size < 0:
            raise ValueError(f"cache_size: expected an integer >= 0, got {cache_size}")
        self.device, self.cache_size, self.reading = device, int(cache_size), dict(reading or {})
        self._cache: OrderedDict[int, FitView] = OrderedDict()
        self._live = 0
        self.reads = 0
        self.peak_resident = 0

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return ViewFiles(self.paths[index], names=self.names[index], device=self.device,
                             cache_size=self.cache_size, reading=self.reading)
        i = range(len(self))[index]  # (negative indices; IndexError past the end)
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        view = load_views([self.paths[i]], device=self.device, **self.reading)[0]
        view.name = self.names[i]
        self.reads += 1
        self._live += 1
        weakref.finalize(view, self._dropped)
        self.peak_resident = max(self.peak_resident, self._live)
        if self.cache_size:
            self._cache[i] = view
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return view

    @property
    def resident(self) -> int:
        """Views read by this sequence that are still in memory (cached or in use)."""
        return self._live

    def _dropped(self) -> None:
        self._live -= 1

    def __repr__(self) -> str:
        return f"ViewFiles({len(self)} files, cache_size={self.cache_size})"


def view_names(views: Sequence[FitView]) -> list[str]:
    """The views' names, without reading any file of a :class:`ViewFiles`."""
    return list(views.names) if isinstance(views, ViewFiles) else [v.name for v in views]


def reference_files(items: Iterable[str | os.PathLike], what: str = "reference") -> list[Path]:
    """The files ``items`` name, in order: a file is itself; a folder, its ``.npz`` and ``.exr`` files
    (sorted by name); a pattern with ``*``, ``?`` or ``[``, the matching files (sorted); a ``.txt`` file,
    the paths it lists, one a line (relative to its folder; blank lines and ``#`` comments skipped).
    ``ValueError`` (naming ``what``) for a folder, pattern or list that yields no file."""
    files: list[Path] = []
    for item in items:
        text = str(item)
        path = Path(text)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in REFERENCE_SUFFIXES)
            if not found:
                raise ValueError(f"{what}: folder {text} holds no {' or '.join(REFERENCE_SUFFIXES)} file")
            files += found
        elif _GLOB & set(text) and not path.exists():
            found = sorted(Path(p) for p in glob.glob(text) if Path(p).is_file())
            if not found:
                raise ValueError(f"{what}: no file matches {text!r}")
            files += found
        elif path.suffix.lower() == ".txt":
            if not path.is_file():
                raise ValueError(f"{what}: list file {text} does not exist")
            lines = [line.split("#", 1)[0].strip() for line in path.read_text(encoding="utf-8").splitlines()]
            listed = [path.parent / line for line in lines if line]
            if not listed:
                raise ValueError(f"{what}: list file {text} names no file")
            files += reference_files(listed, what)
        else:
            files.append(path)  # (a missing file is named when it is read)
    return files
