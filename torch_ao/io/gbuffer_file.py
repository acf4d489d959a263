"""G-buffer files of every format the library reads: ``.npz`` (:mod:`torch_ao.io.npz`), OpenEXR and
16-bit PNG depth (:mod:`torch_ao.io.engine`), chosen by the file's suffix."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ..gbuffer import GBuffer
from .engine import EngineOptions, apply_engine_options, read_engine_arrays
from .npz import gbuffer_from_arrays, read_npz

__all__ = ["read_gbuffer_arrays", "load_gbuffer"]


def read_gbuffer_arrays(path: str | os.PathLike, **options) -> dict[str, np.ndarray]:
    """The arrays of a G-buffer file in the ``.npz`` layout and the library's conventions.

    ``.npz`` files are read as they are; ``.exr`` (OpenEXR) and ``.png`` (16-bit depth) files through
    :func:`torch_ao.io.engine.read_engine_arrays`. ``options`` (:class:`torch_ao.io.engine.EngineOptions`
    fields: ``channels``, ``depth_kind``, ``normal_space``, ``position_space``, ``view_matrix``,
    ``convention``, ``far``, ``fov``, ``intrinsics``, ``depth_scale``) convert an engine's conventions;
    for ``.npz`` files every option but ``channels`` applies too.
    """
    if Path(path).suffix.lower() in (".exr", ".png"):
        return read_engine_arrays(path, **options)
    arrays = read_npz(path)
    if not options:
        return arrays
    opts = EngineOptions(**options)
    if opts.channels:
        raise ValueError("channels: .npz files have fixed keys; --channels applies to OpenEXR files")
    return apply_engine_options(arrays, opts)


def load_gbuffer(path: str | os.PathLike, device: torch.device | str | None = None,
                 **options) -> tuple[GBuffer, dict[str, torch.Tensor]]:
    """Load a G-buffer file (``.npz``, ``.exr`` or 16-bit ``.png`` depth; see :func:`read_gbuffer_arrays`
    for ``options``). Returns the :class:`GBuffer` and the other arrays.

    Image-like extras (``ao``, ``ao_stderr``, ``albedo``, ``visibility``, ``indirect``...) come back as
    ``(B,C,H,W)`` tensors; scalars such as ``max_distance`` as 0-d tensors.

    Shape:
        - Output: ``(GBuffer, {name: tensor})``: the G-buffer's images ``(B, C, H, W)`` (depth in the file's world
          units), float32 unless the file holds float64; extras ``(B, C, H, W)`` or 0-d.
    """
    return gbuffer_from_arrays(read_gbuffer_arrays(path, **options), path, device)
