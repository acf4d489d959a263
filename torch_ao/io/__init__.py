"""The file formats: G-buffers as ``.npz`` (:mod:`~torch_ao.io.npz`), engine OpenEXR/PNG buffers
(:mod:`~torch_ao.io.engine`), either by suffix (:mod:`~torch_ao.io.gbuffer_file`), atomic writes of
outputs; mesh files (:mod:`~torch_ao.io.mesh`, :mod:`~torch_ao.io.trimesh_file`), Mitsuba 3 scenes
(:mod:`~torch_ao.io.mitsuba`) and the confinement of the files a scene names (:mod:`~torch_ao.io.confine`).

The G-buffer names are importable from here (``torch_ao.io.load_gbuffer``); the mesh and scene
readers from their modules or :mod:`torch_ao.reference`.
"""
from .gbuffer_file import load_gbuffer, read_gbuffer_arrays
from .npz import (STALE_TEMPORARY_SECONDS, FileContentError, check_output_path, gbuffer_from_arrays, image_to_numpy,
                  numpy_to_image, read_npz, real_array, remove_stale_temporaries, save_json, save_npz, write_atomic,
                  write_text_atomic)

__all__ = ["load_gbuffer", "read_gbuffer_arrays", "gbuffer_from_arrays", "save_npz", "read_npz", "image_to_numpy",
           "numpy_to_image", "write_text_atomic", "save_json", "write_atomic", "remove_stale_temporaries",
           "check_output_path", "STALE_TEMPORARY_SECONDS", "FileContentError", "real_array"]
