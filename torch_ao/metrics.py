"""Error of a visibility image against a reference, on valid pixels (kornia's PSNR and SSIM)."""
from __future__ import annotations

import torch
from kornia.metrics import psnr, ssim

__all__ = ["error_metrics"]


@torch.no_grad()
def error_metrics(prediction: torch.Tensor, reference: torch.Tensor, valid: torch.Tensor | None = None,
                  window_size: int = 11) -> dict[str, float]:
    """MAE, RMSE, PSNR (dB, peak 1) and SSIM of ``prediction`` against ``reference``, ``(B,1,H,W)``.

    Only ``valid`` pixels count. SSIM is kornia's local SSIM map averaged over valid pixels, with
    background pixels of the prediction set to the reference so they do not disturb their neighbours.
    PSNR is capped at 100 dB for identical images.

    Shape:
        - prediction, reference: ``(B, 1, H, W)`` float in [0, 1]; valid: optional ``(B, 1, H, W)`` bool.
        - Output: ``{"mae", "rmse", "psnr", "ssim"}`` floats (PSNR in dB).
    """
    if prediction.shape != reference.shape:
        raise ValueError(f"reference: expected shape {tuple(prediction.shape)} (that of the prediction), got {tuple(reference.shape)}")
    if valid is None:
        valid = torch.ones_like(reference, dtype=torch.bool)
    pred, ref = prediction.float(), reference.float()
    if not bool(valid.any()):
        return {"mae": 0.0, "rmse": 0.0, "psnr": 100.0, "ssim": 1.0}
    diff = (pred - ref)[valid]
    mse = float(diff.square().mean())
    filled = torch.where(valid, pred, ref)
    win = max(3, min(window_size, min(ref.shape[-2:]) // 2 * 2 - 1))
    ssim_map = ssim(filled, ref, win, max_val=1.0)
    return {
        "mae": float(diff.abs().mean()),
        "rmse": mse ** 0.5,
        "psnr": 100.0 if mse == 0 else min(100.0, float(psnr(pred[valid], ref[valid], 1.0))),
        "ssim": float(ssim_map[valid].mean()),
    }
