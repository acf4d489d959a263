"""Writing images for people to look at (PNG through matplotlib, an optional dependency)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

__all__ = ["save_png", "to_display", "pyplot"]

from .checks import install_hint


def to_display(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """``(B,C,H,W)``/``(C,H,W)``/``(H,W)`` -> ``(H, B*W, 3)`` float array in [0, 1] (batch side by side)."""
    a = image.detach().float().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = a[None, None]
    elif a.ndim == 3:
        a = a[None]
    if a.shape[1] == 1:
        a = np.repeat(a, 3, axis=1)
    a = np.concatenate(list(np.moveaxis(a[:, :3], 1, -1)), axis=1)
    return np.clip(np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend; ``ImportError`` saying how to install it (a command
    calls it before computing anything when it will write a PNG)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError(f"--png needs matplotlib: {install_hint('plot', 'matplotlib')}") from err
    return plt


def save_png(path: str | Path, image) -> Path:
    """Save an image (see :func:`to_display`) as PNG, atomically. Needs matplotlib (the ``plot`` extra)."""
    from .io import write_atomic

    plt = pyplot()
    display = to_display(image)
    return write_atomic(path, lambda tmp: plt.imsave(tmp, display, format="png"))
