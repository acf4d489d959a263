"""Sets of reference views of the built-in scenes, for fitting and training.

Each view is rendered once and then read from the reference cache of :mod:`torch_ao.views` (the same
files ``torch-ao bench`` uses), so a scene set is ray-traced the first time only.
"""
from __future__ import annotations

from typing import Sequence

from .views import FitView, add_backface_layer, cached_reference, default_cache_dir, load_views

__all__ = ["default_cache_dir", "reference_view", "reference_views", "train_and_holdout_views", "add_backface_layer",
           "TRAIN_SCENES", "HOLDOUT_SEED"]

#: The scenes of the default fitting/benchmark set (the ones that break screen-space AO).
TRAIN_SCENES = ("sphere_on_plane", "fence", "room_corner", "stairs", "floating", "poles")

#: Seeds of held-out views: never used for training views (those are 1, 2, ...).
HOLDOUT_SEED = 1000


def reference_view(scene: str, seed: int | None, *, height: int, width: int, spp: int, max_distance: float,
                   cache_dir=None, progress: bool = False, device=None, backface: bool = False) -> FitView:
    """One built-in scene view with its reference AO (``(B,1,H,W)``; ``max_distance`` in world units),
    named ``<scene>/<default|s<seed>>``.

    ``seed=None`` is the scene's default layout, an int a randomised variant (camera included), which
    is also the renderer's sampling seed. ``backface=True``: the G-buffer has ``backface_depth``; a cached
    file without the layer gets it added (:func:`add_backface_layer`), never used without it.
    """
    path = cached_reference(scene, height=height, width=width, spp=spp, max_distance=max_distance,
                            seed=0 if seed is None else seed, layout=seed, cache_dir=cache_dir, progress=progress)
    if backface:
        add_backface_layer(path, scene, seed)
    view = load_views([path], device=device)[0]
    view.name = f"{scene}/{'default' if seed is None else f's{seed}'}"
    return view


def reference_views(scenes: Sequence[str], seeds: Sequence[int | None], **kwargs) -> list[FitView]:
    """:func:`reference_view` for every scene and seed (scene-major order)."""
    return [reference_view(scene, seed, **kwargs) for scene in scenes for seed in seeds]


def train_and_holdout_views(scenes: Sequence[str], train_views: int, holdout_views: int = 1,
                            **kwargs) -> tuple[list[FitView], list[FitView]]:
    """Randomised training views (seeds ``1..train_views``) and held-out views (seeds from
    :data:`HOLDOUT_SEED`) of the built-in ``scenes``; ``kwargs`` as :func:`reference_view`."""
    train = reference_views(scenes, list(range(1, train_views + 1)), **kwargs)
    held = reference_views(scenes, list(range(HOLDOUT_SEED, HOLDOUT_SEED + holdout_views)), **kwargs)
    return train, held
