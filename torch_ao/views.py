"""Reference views: a G-buffer with its ray-traced reference visibility, and the on-disk cache of
renders of the built-in scenes.

* :class:`FitView` is what fitting and evaluation take; :class:`BenchView` adds the reference's
  maximum ray distance (the methods' default radius in a sweep).
* :func:`load_views` reads reference files (``.npz`` with an ``ao`` array, e.g. from ``torch-ao render``).
* :func:`cached_reference` renders a built-in scene once and reads it from the cache afterwards;
  :func:`reference_path` names the file, so ``torch-ao fit``, ``torch-ao bench`` and the training
  examples share the renders they have in common.

The cache folder (:func:`default_cache_dir`) is ``$TORCH_AO_CACHE`` when set, else
``$XDG_CACHE_HOME/torch_ao``, else ``~/.cache/torch_ao``; renders live in its ``references/`` folder.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np
import torch

from .gbuffer import GBuffer

__all__ = ["FitView", "BenchView", "load_views", "load_bench_views", "default_cache_dir", "reference_path",
           "add_backface_layer",
           "cached_reference"]


@dataclass
class FitView:
    """One reference view: its G-buffer, reference visibility ``(B,1,H,W)`` and optional stderr.

    Shape:
        - ``gbuffer``: a :class:`~torch_ao.GBuffer` (images ``(B, C, H, W)``, world units).
        - ``reference``, ``stderr``: ``(B, 1, H, W)`` float, visibility in [0, 1] and its standard error.
    """

    gbuffer: GBuffer
    reference: torch.Tensor
    stderr: torch.Tensor | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.gbuffer, GBuffer):
            raise TypeError(f"gbuffer: expected a torch_ao.GBuffer, got {type(self.gbuffer).__name__}")
        shape = tuple(self.gbuffer.depth.shape)
        for key in ("reference", "stderr"):
            x = getattr(self, key)
            if x is None:
                continue
            if not isinstance(x, torch.Tensor) or tuple(x.shape) != shape:
                got = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
                raise ValueError(f"{key}: expected shape {shape} (that of depth), got {got}")
            bad = ~torch.isfinite(x) & self.gbuffer.valid
            if bool(bad.any()):
                raise ValueError(f"{key}: {int(bad.sum())} non-finite values on valid pixels of view {self.name or '?'}")


@dataclass
class BenchView(FitView):
    """A reference view with the reference's maximum ray distance in world units (``inf`` when the
    file does not say)."""

    max_distance: float = math.inf


def load_views(paths: Iterable[str | os.PathLike], device=None, **options) -> list[BenchView]:
    """Reference views from G-buffer files that hold an ``ao`` array (and optionally ``ao_stderr`` and
    ``max_distance``), named by their path. ``options``: how to read the files
    (:class:`~torch_ao.io.engine.EngineOptions` fields, see :func:`~torch_ao.io.read_gbuffer_arrays`).

    Shape:
        - Output: views whose ``gbuffer`` images are ``(B, C, H, W)`` and ``reference``/``stderr`` ``(B, 1, H, W)``.
    """
    from .io import load_gbuffer

    views = []
    for path in paths:
        gb, extras = load_gbuffer(path, device=device, **options)
        if "ao" not in extras:
            raise ValueError(f"reference: {path} has no 'ao' array; render one with `torch-ao render`")
        md = extras.get("max_distance")
        md = float(md) if md is not None and md.numel() == 1 else math.inf
        views.append(BenchView(gb, extras["ao"].to(gb.depth.dtype), extras.get("ao_stderr"), name=str(path),
                               max_distance=md))
    return views


def default_cache_dir() -> Path:
    """``$TORCH_AO_CACHE``, else ``$XDG_CACHE_HOME/torch_ao``, else ``~/.cache/torch_ao`` (``~`` expanded)."""
    if os.environ.get("TORCH_AO_CACHE"):
        return Path(os.environ["TORCH_AO_CACHE"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base).expanduser() / "torch_ao"


def reference_path(cache_dir: str | os.PathLike | None, scene: str, height: int, width: int, spp: int,
                   max_distance: float, seed: int = 0, *, layout: int | None = None) -> Path:
    """The cache file of a built-in scene's reference.

    ``references/<scene>[_s<layout>]_<W>x<H>_spp<spp>_R<max_distance>_seed<seed>_v<version>-t<tracer>.npz``:
    ``layout`` is the scene's randomisation seed (``None``: its default layout), ``seed`` the sampling
    seed of the renderer, ``max_distance`` written exactly (``repr``: ``0.5000001`` is not ``0.5``),
    ``version`` and ``tracer`` the library's version and
    :data:`~torch_ao.reference.render.TRACER_VERSION`; ``cache_dir=None`` is :func:`default_cache_dir`.
    """
    from .version import __version__
    from .reference.render import TRACER_VERSION

    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    r = repr(float(max_distance))
    tag = "" if layout is None else f"_s{layout}"
    return cache / "references" / (f"{scene}{tag}_{width}x{height}_spp{spp}_R{r}_seed{seed}"
                                   f"_v{__version__}-t{TRACER_VERSION}.npz")


def _cached_file_matches(path: Path, height: int, width: int, spp: int, max_distance: float, seed: int) -> bool:
    """Whether the cached file ``path`` holds what its name promises: its size, ``spp``, ``max_distance``,
    ``seed`` and tracer version (a planted, renamed or older file does not)."""
    from .reference.render import TRACER_VERSION

    want = {"spp": spp, "max_distance": float(max_distance), "seed": seed, "tracer_version": TRACER_VERSION}
    try:
        with np.load(path, allow_pickle=False) as data:  # (reads only these members)
            stored = {k: data[k] for k in want if k in data.files}
            shape = data["depth"].shape
    except Exception:  # noqa: BLE001 - whatever makes the file unreadable, it is rendered again
        return False
    return (tuple(shape[-2:]) == (height, width) and set(stored) == set(want)
            and all(stored[k].size == 1 and float(stored[k]) == float(v) for k, v in want.items()))


def cached_reference(scene: str, *, height: int, width: int, spp: int, max_distance: float, seed: int = 0,
                     layout: int | None = None, cache_dir: str | os.PathLike | None = None, progress: bool = False,
                     log: Callable[[str], None] | None = None) -> Path:
    """The path of the reference of built-in ``scene`` (see :func:`reference_path`), ray-traced and
    written there first when it is not in the cache yet, or when the file there does not hold this
    request (another size, spp, max_distance, seed or tracer version: it is rendered again). Temporary
    files that runs killed while writing to the cache left are removed (never a live run's)."""
    from .io import remove_stale_temporaries

    path = reference_path(cache_dir, scene, height, width, spp, max_distance, seed, layout=layout)

    def matches() -> bool:  # (the file there holds this request)
        return path.exists() and _cached_file_matches(path, height, width, spp, max_distance, seed)

    if not matches():
        from .reference import get_scene, render_reference

        if path.parent.is_dir():
            remove_stale_temporaries(path.parent)
        other = path.exists()  # (a file of another request: replaced)
        if log is not None:
            redo = " (the cached file holds another render)" if other else ""
            log(f"rendering reference {scene} ({width}x{height}, {spp} spp, R={max_distance:g}){redo} -> {path}")
        ref = render_reference(get_scene(scene, layout), height=height, width=width, spp=spp,
                               max_distance=max_distance, seed=seed, uniform=False, progress=progress)
        # A concurrent run that rendered the same request meanwhile may have given its file more layers
        # (add_backface_layer): its file stands
        if not matches():
            ref.save(path, keep_existing=not other)
    return path


def add_backface_layer(path: str | os.PathLike, scene: str, layout: int | None) -> bool:
    """Give the cached reference ``path`` of built-in ``scene`` (randomised with ``layout``; ``None``: its
    default layout) a ``backface_depth`` layer ``(B,1,H,W)`` if it has none; returns whether it was added.

    Only the camera rays are traced again (the layer depends on nothing else), and the file is rewritten
    atomically with all its arrays kept. The new depth must equal the file's bit for bit, else the file
    is not this scene's view and ``ValueError`` names it.
    """
    from .io import image_to_numpy, read_npz, save_npz
    from .reference import get_scene, render_reference

    path = Path(path)
    arrays = read_npz(path)
    if "backface_depth" in arrays:
        return False
    depth = arrays["depth"]
    height, width = depth.shape[-2:]
    # 2 AO rays per pixel (the fewest the renderer takes) at the file's R: the AO is thrown away.
    ref = render_reference(get_scene(scene, layout), height=height, width=width, spp=2,
                           max_distance=float(arrays["max_distance"]), uniform=False, backface=True, progress=False)
    new_depth = image_to_numpy(ref.gbuffer.depth)
    if new_depth.shape != depth.shape or not np.array_equal(new_depth, depth):
        raise ValueError(f"reference: {path} does not hold the depth of scene {scene!r} (layout {layout}); "
                         "delete it to render it again")
    arrays["backface_depth"] = image_to_numpy(ref.backface_depth)
    save_npz(path, **arrays)
    return True


def load_bench_views(scenes: Sequence[str] = (), files: Sequence[str | os.PathLike] = (), *, height: int = 72,
                     width: int = 96, spp: int = 64, max_distance: float = 1.0, seed: int = 0,
                     cache_dir: str | os.PathLike | None = None, device=None, progress: bool = True,
                     log: Callable[[str], None] | None = print, backface: bool = False,
                     reading: dict | None = None) -> list[BenchView]:
    """Reference views of built-in ``scenes`` (default layout; :func:`cached_reference`) and of
    reference ``files``; each named after its scene or file stem (names must differ). ``backface=True``
    gives the built-in scenes' views their back-face depth layer (added to the cached file once:
    :func:`add_backface_layer`), for pipelines with the back-face thickness model.
    ``reading``: how to read the reference ``files`` (:func:`load_views`' options)."""
    views = []
    for name in scenes:
        path = cached_reference(name, height=height, width=width, spp=spp, max_distance=max_distance, seed=seed,
                                cache_dir=cache_dir, progress=progress, log=log)
        if backface:
            add_backface_layer(path, name, None)
        views.append(_named(path, name, device))
    for f in files:
        views.append(_named(f, Path(f).stem, device, reading or {}))
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise ValueError(f"reference: two views share a name ({', '.join(names)}); rename the files")
    return views


def _named(path: str | os.PathLike, name: str, device, reading: dict | None = None) -> BenchView:
    view = load_views([path], device=device, **(reading or {}))[0]
    view.name = name
    return view
