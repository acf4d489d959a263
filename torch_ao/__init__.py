"""torch_ao: differentiable, batched screen-space ambient occlusion for PyTorch.

What users call is here: the methods (modules and functional twins), the G-buffer and camera, io,
fitting, denoising and metrics. The API to write a new method (``SliceAccumulator``,
``SamplingPattern``, ``Sample``, ``march``...) is :mod:`torch_ao.walk`; see ``docs/architecture.md``.
"""
from .camera import PinholeCamera
from .denoise import Denoiser, denoise
from .fit import FitConfig, FitView, evaluate, fit, load_views
from .fit_data import ViewFiles
from .fitted import FittedPipeline, load_fitted
from .gbuffer import GBuffer, normals_from_depth
from .io import load_gbuffer, save_npz
from .methods import METHODS, PRESETS, AOOutput, ScreenSpaceAO, get_method
from .methods.bitmask import SSILVB, BitmaskAO, bitmask_ao, ssilvb
from .methods.gtao import GTAO, gtao
from .methods.hbao import HBAO, hbao
from .methods.pssao import PSSAO, pssao
from .methods.ssao import SSAO, ssao
from .methods.ue4_ssao import UE4SSAO, ue4_ssao
from .metrics import error_metrics
from .temporal import TemporalAO, accumulate_still

from .version import __version__  # noqa: F401  (torch_ao.__version__)

__all__ = [
    "PinholeCamera", "GBuffer", "normals_from_depth", "load_gbuffer", "save_npz",
    "METHODS", "PRESETS", "AOOutput", "ScreenSpaceAO", "get_method",
    "SSAO", "ssao", "HBAO", "hbao", "UE4SSAO", "ue4_ssao", "GTAO", "gtao", "PSSAO", "pssao",
    "BitmaskAO", "bitmask_ao", "SSILVB", "ssilvb",
    "Denoiser", "denoise", "FitConfig", "FitView", "fit", "evaluate", "load_views", "ViewFiles", "error_metrics",
    "FittedPipeline", "load_fitted", "TemporalAO", "accumulate_still",
]
