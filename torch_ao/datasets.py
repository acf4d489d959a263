"""Sets of reference views of the built-in scenes, for fitting and training.

Each view is rendered once and then read from the reference cache of :mod:`torch_ao.views` (the same
files ``torch-ao bench`` uses), so a scene set is ray-traced the first time only.
"""
from __future__ import annotations

import warnings
from typing import Sequence

from .views import FitView, add_backface_layer, cached_reference, default_cache_dir, load_views

__all__ = ["default_cache_dir", "reference_view", "reference_views", "train_and_holdout_views", "add_backface_layer",
           "TRAIN_SCENES", "MESH_TRAIN_SCENES", "FIT_SCENES", "HELDOUT_SCENES", "BENCHMARK_SCENES", "HOLDOUT_SEED",
           "SCENE_SETS", "parse_scenes"]

#: The procedural scenes that break screen-space AO (the original fitting set).
TRAIN_SCENES = ("sphere_on_plane", "fence", "room_corner", "stairs", "floating", "poles")

#: Real meshes (assimp-testmodels) that fitting may use.
MESH_TRAIN_SCENES = ("mesh_empty_mat", "mesh_sphere_hole", "mesh_3dsmax", "mesh_box_longline", "mesh_concave")

#: Train scenes: the scenes ``torch-ao fit`` fits on by default (procedural and real meshes).
FIT_SCENES = TRAIN_SCENES + MESH_TRAIN_SCENES

#: Held-out scenes: never fitted on, only scored (real meshes and procedural scenes of other kinds).
HELDOUT_SCENES = ("mesh_regr01", "mesh_clearcoat", "mesh_on_floor", "grazing_floor")

#: The whole benchmark set: train scenes, then held-out scenes.
BENCHMARK_SCENES = FIT_SCENES + HELDOUT_SCENES

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


#: Names standing for a set of scenes in :func:`parse_scenes` (``--scenes``).
SCENE_SETS = {"procedural": TRAIN_SCENES, "meshes": MESH_TRAIN_SCENES, "fit": FIT_SCENES, "heldout": HELDOUT_SCENES,
              "benchmark": BENCHMARK_SCENES}


def parse_scenes(text: str, flag: str = "--scenes") -> list[str]:
    """Comma-separated built-in scene names and set names (:data:`SCENE_SETS`, expanded in place;
    repeats dropped); ``ValueError`` naming ``flag`` for an unknown name, or for a mesh scene whose
    file is missing (with the package to install). A set stands for those of its scenes whose files
    are here: the others are left out with a warning naming the package (refused when none is here)."""
    from .reference import SCENES, scene_unavailable

    names, left_out = [], []
    for item in (x.strip() for x in str(text).split(",")):
        if item in SCENE_SETS:  # a set: those of its scenes this machine has (mesh files may be missing)
            for name in SCENE_SETS[item]:
                (left_out if scene_unavailable(name) else names).append(name)
        elif item:
            names.append(item)
    if left_out and names:
        warnings.warn(f"{flag}: {len(left_out)} mesh scene(s) of the set left out ({scene_unavailable(left_out[0])})",
                      RuntimeWarning, stacklevel=2)
    elif left_out:
        names = left_out  # (refused below, naming the package)
    unknown = [s for s in names if s not in SCENES]
    if unknown:
        raise ValueError(f"{flag}: unknown scene(s) {', '.join(unknown)}; built-in scenes: {', '.join(SCENES)}; "
                         f"sets: {', '.join(SCENE_SETS)}")
    missing = [why for why in map(scene_unavailable, dict.fromkeys(names)) if why]
    if missing:
        raise ValueError(f"{flag}: {missing[0]}" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
    if not names:
        raise ValueError(f"{flag}: expected at least one scene name")
    return list(dict.fromkeys(names))
