"""torch_ao: differentiable, batched screen-space ambient occlusion for PyTorch."""
from .camera import PinholeCamera
from .gbuffer import GBuffer, normals_from_depth
from .io import load_gbuffer, save_npz
from .marching import Frame, SlicePattern, march
from .methods import METHODS, PRESETS, AOOutput, ScreenSpaceAO, get_method

__version__ = "0.1.0"

__all__ = [
    "PinholeCamera", "GBuffer", "normals_from_depth", "load_gbuffer", "save_npz",
    "Frame", "SlicePattern", "march",
    "METHODS", "PRESETS", "AOOutput", "ScreenSpaceAO", "get_method",
]
