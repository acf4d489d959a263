"""Edge-aware denoising of AO outputs: a joint bilateral filter guided by depth and normals, and an
optional temporal blend.

The spatial filter is a joint bilateral filter with a *normalised* guide (the same numbers as
kornia's :func:`~kornia.filters.joint_bilateral_blur` with ``sigma_color = 1``, reflect borders, the
l2 distance, and kornia's Gaussian window), so its range sigmas do not depend on the scene's units:

* depth enters as ``log(depth) / sigma_depth``: a difference of ``sigma_depth`` in log depth is a
  relative depth change of about ``sigma_depth`` (``0.05`` = 5 %), at any distance and any scale;
* normals (unit vectors) enter as ``normal / sigma_normal``.

The guide's channels are combined with the l2 distance and ``sigma_color = 1``, so a neighbour's
range weight is ``exp(-(dlogz^2 / sigma_depth^2 + |dn|^2 / sigma_normal^2) / 2)``.

Background pixels are excluded, not mixed in: the filter runs on ``[value * valid, valid]`` with one
kernel and divides, so a valid pixel averages only valid neighbours; background keeps its input value
(visibility 1, indirect 0). The per-pixel weights of the ``k * k`` neighbours (window x range x mask,
divided by their sum) depend on the G-buffer only, so :func:`denoise` computes them once per G-buffer
(:meth:`~torch_ao.gbuffer.GBuffer.derived`; in the graph when the G-buffer needs gradients) and each
call is a weighted sum of ``k * k`` shifted views of the padded input: a fit filters the same views
hundreds of times. The temporal blend is an exponential moving average
``alpha * current + (1 - alpha) * history`` on pixels valid in both frames (no reprojection: the
caller supplies a history already aligned with the current view, or a static camera).

Everything is differentiable (gradients flow to the AO outputs and to the guide).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from kornia.filters import get_gaussian_kernel2d
from torch.nn import functional as F

from .gbuffer import GBuffer
from .options import Option, options_by_name

__all__ = ["Denoiser", "DenoiseOutput", "denoise", "spatial_filter", "temporal_blend", "denoise_guide",
           "bilateral_weights", "apply_weights"]

GUIDES = ("depth", "normal", "depth+normal")


@dataclass
class DenoiseOutput:
    """Filtered ``visibility (B,1,H,W)`` and, when given, ``indirect (B,3,H,W)``."""

    visibility: torch.Tensor
    indirect: torch.Tensor | None = None


#: The denoiser's options (:class:`Denoiser` checks its arguments with these).
OPTIONS = options_by_name((
    Option("kernel_size", 5, "side of the square filter window (odd)", int, unit="pixels", minimum=1),
    Option("sigma_space", 1.5, "spatial sigma of the Gaussian window", float, unit="pixels", minimum=0.0,
           open_minimum=True),
    Option("sigma_depth", 0.05, "range sigma of log depth, about a relative depth change (0.05 = 5 %)", float, minimum=0.0, open_minimum=True),
    Option("sigma_normal", 0.3, "range sigma of the unit normals' difference", float, minimum=0.0, open_minimum=True),
    Option("guide", "depth+normal", "what guides the filter", str, choices=GUIDES),
    Option("alpha", 0.1, "weight of the current frame in the temporal blend", float, minimum=0.0, maximum=1.0,
           open_minimum=True),
))


def _check_options(**values) -> None:
    for name, value in values.items():
        OPTIONS[name].check(value)
    if values.get("kernel_size", 1) % 2 == 0:
        raise ValueError(f"kernel_size: expected an odd integer, got {values['kernel_size']!r}")


def denoise_guide(gbuffer: GBuffer, *, guide: str = "depth+normal", sigma_depth: float = 0.05,
                  sigma_normal: float = 0.3, normals: torch.Tensor | None = None) -> torch.Tensor:
    """The normalised guide image ``(B, C, H, W)`` (``C`` = 1, 3 or 4): ``log(depth)/sigma_depth`` and/or
    ``normal/sigma_normal``; zero on background (background is excluded by the mask anyway)."""
    if normals is None:  # then it depends on the G-buffer alone: computed once per G-buffer
        return gbuffer.derived(("denoise_guide", guide, sigma_depth, sigma_normal),
                               lambda: _guide(gbuffer, guide, sigma_depth, sigma_normal, None))
    return _guide(gbuffer, guide, sigma_depth, sigma_normal, normals)


def _guide(gbuffer: GBuffer, guide: str, sigma_depth: float, sigma_normal: float, normals) -> torch.Tensor:
    valid = gbuffer.valid
    parts = []
    if "depth" in guide:
        parts.append(torch.where(valid, torch.log(gbuffer.safe_depth), 0.0) / sigma_depth)
    if "normal" in guide:
        n = gbuffer.view_normals() if normals is None else normals
        parts.append(torch.where(valid, n.to(gbuffer.depth.dtype), 0.0) / sigma_normal)
    return torch.cat(parts, 1)


def _window(values: torch.Tensor, kernel_size: int) -> int:
    """The window side actually used for ``values (..., H, W)``: ``kernel_size``, shrunk to the largest odd
    size whose reflect padding fits in the image (1 for a 1-pixel-wide image)."""
    side = min(values.shape[-2:])
    return min(kernel_size, 2 * (side // 2) - 1) if side > 1 else 1


def _shifts(padded: torch.Tensor, k: int, shape) -> list[torch.Tensor]:
    """The ``k * k`` views ``padded[..., i:i+H, j:j+W]`` (row-major over ``i, j``) of a ``(k-1)/2``-padded image."""
    H, W = shape
    return [padded[..., i:i + H, j:j + W] for i in range(k) for j in range(k)]


def bilateral_weights(guide: torch.Tensor, kernel_size: int, sigma_space: float,
                      valid: torch.Tensor | None = None) -> torch.Tensor:
    """Normalised joint bilateral weights ``(B, k*k, H, W)`` of each pixel's ``k x k`` neighbours (tap
    ``t = i*k + j`` is the neighbour at row offset ``i - (k-1)/2``, column offset ``j - (k-1)/2``).

    Weight ``t`` of pixel ``p`` is ``s_t * exp(-|guide(p + t) - guide(p)|^2 / 2) * m(p + t)``, divided by
    the sum over ``t``: ``s`` is kornia's Gaussian window of ``sigma_space`` pixels, the guide
    ``(B, G, H, W)`` is unitless (range sigma 1), and ``m`` is ``valid (B, 1, H, W)`` (all ones when
    ``None``), all reflect-padded at the border. Without ``valid``, :func:`apply_weights` with these
    weights is kornia's ``joint_bilateral_blur(x, guide, (k, k), 1, (s, s), "reflect", "l2")``. Where
    no neighbour is valid the weights are 0. ``kernel_size`` must be odd, its half less than the image
    side (:func:`spatial_filter` shrinks it)."""
    k, p = kernel_size, kernel_size // 2
    H, W = guide.shape[-2:]
    if k % 2 == 0 or k < 1 or p >= min(H, W):
        raise ValueError(f"kernel_size: expected an odd integer with (kernel_size - 1) / 2 < {min(H, W)} "
                         f"(reflect padding of the {H}x{W} image), got {k!r}")
    space = get_gaussian_kernel2d((k, k), (sigma_space, sigma_space), device=guide.device,
                                  dtype=guide.dtype).reshape(1, k * k, 1, 1)
    padded = F.pad(guide, (p, p, p, p), mode="reflect")
    dist_sq = torch.stack([(g - guide).square().sum(1) for g in _shifts(padded, k, (H, W))], 1)
    weights = space * torch.exp(-0.5 * dist_sq)
    if valid is not None:
        m = F.pad(valid.to(guide.dtype), (p, p, p, p), mode="reflect")
        weights = weights * torch.cat(_shifts(m, k, (H, W)), 1)
    # A valid pixel always weighs itself (range weight 1), so the sum is > 0 there.
    return weights / weights.sum(1, keepdim=True).clamp_min(1e-12)


class _ShiftedSum(torch.autograd.Function):
    """``out = sum_t weights[:, t] * shift_t(padded)``: ``padded (B,C,H+k-1,W+k-1)``, ``weights (B,k*k,H,W)``,
    ``out (B,C,H,W)``. Its backward is the adjoint written out (each tap's gradient added into its
    window of a zero image), instead of autograd's ``k * k`` slice backwards, each a full-size copy."""

    @staticmethod
    def forward(ctx, padded, weights):
        k = round(weights.shape[1] ** 0.5)
        views = _shifts(padded, k, weights.shape[-2:])
        out = views[0] * weights[:, :1]
        for t in range(1, k * k):
            out.addcmul_(views[t], weights[:, t:t + 1])
        ctx.save_for_backward(padded, weights)
        return out

    @staticmethod
    def backward(ctx, grad):
        padded, weights = ctx.saved_tensors
        k = round(weights.shape[1] ** 0.5)
        grad_padded = grad_weights = None
        if ctx.needs_input_grad[0]:
            grad_padded = torch.zeros_like(padded)
            H, W = grad.shape[-2:]
            for t in range(k * k):  # each view sliced after the previous in-place add (double backward)
                i, j = divmod(t, k)
                grad_padded[..., i:i + H, j:j + W].addcmul_(grad, weights[:, t:t + 1])
        if ctx.needs_input_grad[1]:
            grad_weights = torch.stack([(grad * v).sum(1) for v in _shifts(padded, k, weights.shape[-2:])], 1)
        return grad_padded, grad_weights


def apply_weights(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``sum_t weights[:, t] * values(p + t)``: ``values (B,C,H,W)`` reflect-padded, ``weights (B,k*k,H,W)``
    from :func:`bilateral_weights` (same dtype); returns ``(B,C,H,W)``, differentiable in both."""
    k = round(weights.shape[1] ** 0.5)
    if k * k != weights.shape[1] or k % 2 == 0 or weights.shape[0] != values.shape[0] or weights.shape[-2:] != values.shape[-2:]:
        raise ValueError(f"weights: expected shape ({values.shape[0]}, k*k, {values.shape[-2]}, {values.shape[-1]}), "
                         f"got {tuple(weights.shape)}")
    p = k // 2
    return _ShiftedSum.apply(F.pad(values, (p, p, p, p), mode="reflect"), weights)


def spatial_filter(values: torch.Tensor, valid: torch.Tensor, guide: torch.Tensor, *, kernel_size: int = 5,
                   sigma_space: float = 1.5, fill: float = 0.0, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Joint bilateral filter of ``values (B,C,H,W)`` over ``valid (B,1,H,W)`` pixels only, guided by
    ``guide (B,G,H,W)`` (range sigma 1: normalise the guide first). Invalid pixels get ``fill``.
    ``weights``: this call's :func:`bilateral_weights` (``valid`` included, the window of
    :func:`_window`), when the caller keeps them; else they are computed here."""
    if values.dim() != 4 or valid.shape != (values.shape[0], 1, *values.shape[2:]):
        raise ValueError(f"values/valid: expected (B,C,H,W) and (B,1,H,W), got {tuple(values.shape)} and {tuple(valid.shape)}")
    k = _window(values, kernel_size)
    if k <= 1:
        return torch.where(valid, values, fill)
    if weights is None:
        weights = bilateral_weights(guide.to(values.dtype), k, sigma_space, valid)
    return torch.where(valid, apply_weights(torch.where(valid, values, 0.0), weights.to(values.dtype)), fill)


def temporal_blend(current: torch.Tensor, history: torch.Tensor | None, valid: torch.Tensor,
                   history_valid: torch.Tensor | None = None, alpha: float = 0.1) -> torch.Tensor:
    """``alpha * current + (1 - alpha) * history`` where both frames are valid; ``current`` elsewhere."""
    if history is None:
        return current
    _check_options(alpha=alpha)
    if history.shape != current.shape:
        raise ValueError(f"history: expected shape {tuple(current.shape)}, got {tuple(history.shape)}")
    both = valid if history_valid is None else valid & history_valid
    return torch.where(both, alpha * current + (1 - alpha) * history.to(current), current)


def denoise(visibility: torch.Tensor, gbuffer: GBuffer, *, indirect: torch.Tensor | None = None,
            kernel_size: int = 5, sigma_space: float = 1.5, sigma_depth: float = 0.05, sigma_normal: float = 0.3,
            guide: str = "depth+normal", history: DenoiseOutput | None = None,
            history_valid: torch.Tensor | None = None, alpha: float = 0.1) -> DenoiseOutput:
    """Edge-aware spatial filter of ``visibility`` (and ``indirect``), then an optional temporal blend.

    Args:
        visibility: ``(B,1,H,W)``; indirect: optional ``(B,3,H,W)``.
        gbuffer: the frame's G-buffer (its depth and normals guide the filter; its ``valid`` mask
            says which pixels are filtered and which are left as they are).
        kernel_size: odd window width in pixels; sigma_space: spatial Gaussian sigma in pixels.
        sigma_depth: range sigma in log depth (relative depth change); sigma_normal: range sigma of
            the normal difference.
        guide: ``"depth"``, ``"normal"`` or ``"depth+normal"``.
        history: the previous (denoised) output, aligned with this frame, for the temporal blend.
        history_valid: ``(B,1,H,W)`` pixels where ``history`` is meaningful (default: all).
        alpha: weight of the current frame in the blend.

    Shape:
        - visibility: ``(B, 1, H, W)``; indirect: ``(B, 3, H, W)``; history_valid: ``(B, 1, H, W)`` bool.
        - Output: ``DenoiseOutput`` with ``visibility`` ``(B, 1, H, W)`` and ``indirect`` ``(B, 3, H, W)`` (or
          ``None``), the input's dtype.
    """
    _check_options(kernel_size=kernel_size, sigma_space=sigma_space, sigma_depth=sigma_depth,
                   sigma_normal=sigma_normal, guide=guide)
    if visibility.dim() != 4 or visibility.shape[1] != 1 or visibility.shape[-2:] != gbuffer.depth.shape[-2:]:
        raise ValueError(f"visibility: expected shape {tuple(gbuffer.depth.shape)}, got {tuple(visibility.shape)}")
    valid = gbuffer.valid
    g = denoise_guide(gbuffer, guide=guide, sigma_depth=sigma_depth, sigma_normal=sigma_normal)
    channels = [visibility] if indirect is None else [visibility, indirect.to(visibility.dtype)]
    k = _window(visibility, kernel_size)
    weights = None if k <= 1 else gbuffer.derived(
        ("denoise_weights", guide, sigma_depth, sigma_normal, k, sigma_space, visibility.dtype),
        lambda: bilateral_weights(g.to(visibility.dtype), k, sigma_space, valid))
    filtered = spatial_filter(torch.cat(channels, 1), valid, g, kernel_size=kernel_size, sigma_space=sigma_space,
                              weights=weights)
    # A weighted mean lies within its inputs' range, but rounding can leave it by an ulp (1.0000001):
    # held to the input's range, so visibility in [0, 1] stays there.
    lo, hi = visibility.detach().amin(), visibility.detach().amax()
    vis = torch.where(valid, torch.minimum(torch.maximum(filtered[:, :1], lo), hi), visibility)
    ind = None if indirect is None else torch.where(valid, filtered[:, 1:], indirect.to(vis.dtype))
    if history is not None:
        vis = temporal_blend(vis, history.visibility, valid, history_valid, alpha)
        if ind is not None and history.indirect is not None:
            ind = temporal_blend(ind, history.indirect, valid, history_valid, alpha)
    return DenoiseOutput(vis, ind)


class Denoiser(nn.Module):
    """:func:`denoise` as a module; with ``temporal=True`` it keeps the previous output as history
    (detached, so gradients do not run back through past frames) and blends each new frame into it.

    Call ``reset()`` on a camera cut. The history is dropped automatically when the frame size or
    batch changes.

    Shape:
        - Input: ``visibility`` ``(B, 1, H, W)``, a :class:`~torch_ao.GBuffer` of the same frame, optional
          ``indirect`` ``(B, 3, H, W)`` (as :func:`denoise`).
        - Output: as :func:`denoise`: ``visibility`` ``(B, 1, H, W)``, ``indirect`` ``(B, 3, H, W)`` or ``None``.
    """

    def __init__(self, *, kernel_size: int = 5, sigma_space: float = 1.5, sigma_depth: float = 0.05,
                 sigma_normal: float = 0.3, guide: str = "depth+normal", temporal: bool = False,
                 alpha: float = 0.1) -> None:
        super().__init__()
        _check_options(kernel_size=kernel_size, sigma_space=sigma_space, sigma_depth=sigma_depth,
                       sigma_normal=sigma_normal, guide=guide, alpha=alpha)
        self.kernel_size, self.sigma_space = kernel_size, float(sigma_space)
        self.sigma_depth, self.sigma_normal, self.guide = float(sigma_depth), float(sigma_normal), guide
        self.temporal, self.alpha = temporal, float(alpha)
        self._history: DenoiseOutput | None = None
        self._history_valid: torch.Tensor | None = None

    def reset(self) -> None:
        """Forget the temporal history."""
        self._history, self._history_valid = None, None

    def forward(self, visibility, gbuffer: GBuffer, indirect: torch.Tensor | None = None) -> DenoiseOutput:
        """Filter ``visibility`` (a tensor, or an :class:`~torch_ao.methods.AOOutput` whose ``visibility``
        and ``indirect`` are used) guided by ``gbuffer``."""
        if hasattr(visibility, "visibility"):
            indirect = visibility.indirect if indirect is None else indirect
            visibility = visibility.visibility
        history = self._history if self.temporal else None
        if history is not None and history.visibility.shape != visibility.shape:
            history = None
        out = denoise(visibility, gbuffer, indirect=indirect, kernel_size=self.kernel_size,
                      sigma_space=self.sigma_space, sigma_depth=self.sigma_depth, sigma_normal=self.sigma_normal,
                      guide=self.guide, history=history, history_valid=self._history_valid, alpha=self.alpha)
        if self.temporal:
            self._history = DenoiseOutput(out.visibility.detach(),
                                          None if out.indirect is None else out.indirect.detach())
            self._history_valid = gbuffer.valid
        return out

    def extra_repr(self) -> str:
        return (f"kernel_size={self.kernel_size}, sigma_space={self.sigma_space}, sigma_depth={self.sigma_depth}, "
                f"sigma_normal={self.sigma_normal}, guide={self.guide!r}, temporal={self.temporal}, alpha={self.alpha}")
