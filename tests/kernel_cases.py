"""One small call of each fused kernel family (backend "auto" on the CPU), with the options that make each take
its own kernel: the horizon family with its recorded takes, the SSAO family, hard cosine sectors, soft and
straight-through, the exact union with the back-face layer, indirect light, the ssilvb_glsl shader in soft mode.
Tests that every kernel call must pass a property (test_compile.py, test_kernels_first_order.py) iterate it."""
import torch_ao
from torch_ao.thickness import BackfaceThickness

KERNEL_CALLS = {
    "gtao": lambda: torch_ao.GTAO(slices=2, steps=3),
    "gtao_ue4": lambda: torch_ao.GTAO(variant="ue4", slices=2, steps=3),
    "hbao": lambda: torch_ao.HBAO(slices=2, steps=3),
    "ue4_ssao": lambda: torch_ao.UE4SSAO(slices=2, steps=3),
    "pssao": lambda: torch_ao.PSSAO(slices=2, steps=3),
    "ssao": lambda: torch_ao.SSAO(slices=2, steps=3, softness=0.05),
    "bitmask_hard_cosine": lambda: torch_ao.BitmaskAO(mode="hard", weighting="cosine", slices=2, steps=3),
    "bitmask_soft": lambda: torch_ao.BitmaskAO(mode="soft", slices=2, steps=3),
    "bitmask_straight_through": lambda: torch_ao.BitmaskAO(mode="straight_through", slices=2, steps=3),
    "bitmask_soft_exact_backface": lambda: torch_ao.BitmaskAO(variant="exact", mode="soft", slices=2, steps=3,
                                                              thickness=BackfaceThickness()),
    "ssilvb_hard_cosine": lambda: torch_ao.SSILVB(mode="hard", weighting="cosine", slices=2, steps=3),
    "ssilvb_soft": lambda: torch_ao.SSILVB(mode="soft", slices=2, steps=3),
    "glsl_soft": lambda: torch_ao.BitmaskAO(variant="ssilvb_glsl", mode="soft", slices=2, steps=3),
}
