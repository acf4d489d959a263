"""Reference views of the built-in scenes, rendered once and cached on disk.

Used by ``torch-ao fit``, ``torch-ao bench`` and the training examples, so that a scene set is
ray-traced the first time and loaded from ``.npz`` files afterwards.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from .fit import FitView, load_views

__all__ = ["default_cache_dir", "reference_view", "reference_views", "TRAIN_SCENES"]

#: The scenes of the default fitting/benchmark set (the ones that break screen-space AO).
TRAIN_SCENES = ("sphere_on_plane", "fence", "room_corner", "stairs", "floating", "poles")


def default_cache_dir() -> Path:
    """``$TORCH_AO_CACHE``, else ``$XDG_CACHE_HOME/torch_ao``, else ``~/.cache/torch_ao``."""
    if os.environ.get("TORCH_AO_CACHE"):
        return Path(os.environ["TORCH_AO_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "torch_ao"


def reference_view(scene: str, seed: int | None, *, height: int, width: int, spp: int, max_distance: float,
                   cache_dir: str | os.PathLike | None = None, progress: bool = False, device=None) -> FitView:
    """One built-in scene view with its reference AO; rendered on first use, then read from the cache.

    ``seed=None`` is the scene's default layout, an int a randomised variant (camera included).
    """
    from .reference import get_scene, render_reference

    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    tag = "default" if seed is None else f"s{seed}"
    path = cache / f"{scene}-{tag}-{width}x{height}-spp{spp}-R{max_distance:g}.npz"
    if not path.exists():
        ref = render_reference(get_scene(scene, seed), height=height, width=width, spp=spp,
                               max_distance=max_distance, seed=0 if seed is None else seed, progress=progress,
                               uniform=False)
        ref.save(path)
    view = load_views([path], device=device)[0]
    view.name = f"{scene}/{tag}"
    return view


def reference_views(scenes: Sequence[str], seeds: Sequence[int | None], **kwargs) -> list[FitView]:
    """:func:`reference_view` for every scene and seed (scene-major order)."""
    return [reference_view(scene, seed, **kwargs) for scene in scenes for seed in seeds]


#: Seeds of held-out views: never used for training views (those are 1, 2, ...).
HOLDOUT_SEED = 1000


def train_and_holdout_views(scenes: Sequence[str], train_views: int, holdout_views: int = 1,
                            **kwargs) -> tuple[list[FitView], list[FitView]]:
    """Randomised training views (seeds ``1..train_views``) and held-out views (seeds from
    :data:`HOLDOUT_SEED`) of the built-in ``scenes``; ``kwargs`` as :func:`reference_view`."""
    train = reference_views(scenes, list(range(1, train_views + 1)), **kwargs)
    held = reference_views(scenes, list(range(HOLDOUT_SEED, HOLDOUT_SEED + holdout_views)), **kwargs)
    return train, held
