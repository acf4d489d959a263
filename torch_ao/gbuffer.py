"""G-buffer: validated screen-space inputs, and normals reconstructed from depth.

A :class:`GBuffer` holds ``depth (B,1,H,W)`` and optionally ``normals (B,3,H,W)``, ``light (B,3,H,W)``,
``mask (B,1,H,W)``, ``object_id (B,1,H,W)``, ``backface_depth (B,1,H,W)`` and ``position (B,3,H,W)`` with a
:class:`~torch_ao.camera.PinholeCamera`.
Background pixels (``inf``, ``0``, ``nan`` or a depth of at least :data:`BACKGROUND_DEPTH`, or ``mask``
False) are never NaN downstream:
:attr:`GBuffer.safe_depth` replaces them with 1 so every derived quantity is finite, and methods
mask them out with :attr:`GBuffer.valid`.
"""
from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from kornia.geometry.depth import depth_to_normals

from .camera import PinholeCamera
from .checks import to_arguments
from .ops import channel_norm, normalize_channels

__all__ = ["GBuffer", "normals_from_depth", "BACKGROUND_DEPTH", "geometry_depth"]

#: Depths at or above this (world units) are background, as ``inf``, ``0`` and ``nan`` are: engines write
#: ``FLT_MAX`` (3.4e38) or other huge values for the sky. The walk squares view-space distances in
#: float32 (largest 3.4e38), and a pixel's view-space distance is up to about 3e3 times its depth
#: (fields of view up to 179.88 degrees, :data:`~torch_ao.camera.MIN_FOCAL_RATIO`), so geometry stays
#: below 1e15 world units, where squares and their gradients cannot overflow.
BACKGROUND_DEPTH = 1e15


def geometry_depth(depth: torch.Tensor) -> torch.Tensor:
    """``depth``'s geometry pixels (bool, same shape): finite, positive and below :data:`BACKGROUND_DEPTH`."""
    return torch.isfinite(depth) & (depth > 0) & (depth < BACKGROUND_DEPTH)

_FLOAT_TYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)
_POSITION_IN_FRONT = "position: expected z < 0 (in front of the camera, OpenGL axes) on valid pixels"


def _check_tensor(name: str, x, channels: int | None, like: torch.Tensor | None) -> None:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 4 or (channels is not None and x.shape[1] != channels):
        want = f"(B,{channels},H,W)" if channels else "(B,C,H,W)"
        raise ValueError(f"{name}: expected shape {want}, got {tuple(x.shape)}")
    if like is not None:
        if x.shape[0] != like.shape[0] or x.shape[-2:] != like.shape[-2:]:
            raise ValueError(
                f"{name}: batch and image size must match depth {tuple(like.shape)}, got {tuple(x.shape)}"
            )
        if x.device != like.device:
            raise ValueError(f"{name}: expected device {like.device} (that of depth), got {x.device}")


def _finite_negative(depth: torch.Tensor) -> torch.Tensor:
    """Where ``depth`` is finite and negative (``-inf`` and NaN are background)."""
    return (depth < 0) & (depth > -torch.inf)


class _ValueChecks:
    """A G-buffer's checks of its values, gathered on its device and read back once (a CUDA G-buffer waits for its
    GPU once, not once a check): each a bool tensor, true where the check fails, and the error it raises."""

    def __init__(self) -> None:
        self.failed: list[tuple[torch.Tensor, Callable[[], Exception]]] = []

    def add(self, bad: torch.Tensor, error: Callable[[], Exception]) -> None:
        self.failed.append((bad.any(), error))

    def raise_first(self) -> None:
        """Raise the error of the first check that failed, if any."""
        if self.failed and bool(torch.stack([bad for bad, _ in self.failed]).any()):
            raise next(error for bad, error in self.failed if bool(bad))()


@dataclass
class GBuffer:
    """Validated screen-space inputs of one batch of views.

    Args:
        depth: ``(B,1,H,W)`` positive linear depth along the view axis (world units);
            ``inf``/``0``/``nan`` and depths ``>=`` :data:`BACKGROUND_DEPTH` mark background. float16/bfloat16 are computed in float32.
        camera: the views' camera (batch 1 or B, image size ``H x W``).
        normals: optional ``(B,3,H,W)`` unit view-space normals facing the camera.
        light: optional ``(B,3,H,W)`` direct light (radiance leaving each pixel), for indirect light.
        mask: optional ``(B,1,H,W)`` bool, False marks background.
        object_id: optional ``(B,1,H,W)`` integer ids (for per-object parameters).
        backface_depth: optional ``(B,1,H,W)`` depth (world units) where each pixel's camera ray leaves
            the object it first hit (a front-face-culled depth pass; ``inf`` = no exit); ``>= depth`` on
            valid pixels. Read by :class:`~torch_ao.thickness.BackfaceThickness`.
        position: optional ``(B,3,H,W)`` view-space positions (OpenGL axes, world units; ``z < 0`` on
            valid pixels, anything on background), as an engine's position buffer. When given,
            :meth:`positions` returns it instead of unprojecting depth. ``depth=None`` derives the depth
            as ``-position.z`` (non-finite ``z`` is background).

    Shape:
        - ``depth``, ``backface_depth``: ``(B, 1, H, W)`` float (world units); ``normals``, ``light``, ``position``:
          ``(B, 3, H, W)`` float; ``mask``: ``(B, 1, H, W)`` bool; ``object_id``: ``(B, 1, H, W)`` integer.
        - ``valid``: ``(B, 1, H, W)`` bool; :meth:`positions`: ``(B, 3, H, W)`` (world units, view space).
        - dtype: float32 or float64 (float16/bfloat16 depth is computed in float32).
    """

    depth: torch.Tensor
    camera: PinholeCamera
    normals: torch.Tensor | None = None
    light: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    object_id: torch.Tensor | None = None
    backface_depth: torch.Tensor | None = None
    position: torch.Tensor | None = None
    _valid: torch.Tensor = field(init=False, repr=False)
    _derived: dict = field(init=False, repr=False, compare=False, default_factory=dict)
    _call: dict | None = field(init=False, repr=False, compare=False, default=None)
    _decimation: tuple[int, int, int] = field(init=False, repr=False, compare=False, default=(1, 0, 0))

    def __post_init__(self) -> None:
        checks = _ValueChecks()  # (read back once, at the end: on a GPU, one wait)
        if self.depth is None and self.position is not None:
            _check_tensor("position", self.position, 3, None)
            self.depth = -self.position[:, 2:3]
            checks.add(_finite_negative(self.depth), lambda: ValueError(_POSITION_IN_FRONT))
        _check_tensor("depth", self.depth, 1, None)
        if self.depth.dtype not in _FLOAT_TYPES:
            raise TypeError(f"depth: expected a floating-point tensor, got {self.depth.dtype}")
        if self.depth.dtype in (torch.float16, torch.bfloat16):
            self.depth = self.depth.float()
        dtype = self.depth.dtype
        if not isinstance(self.camera, PinholeCamera):
            raise TypeError(f"camera: expected a torch_ao.PinholeCamera, got {type(self.camera).__name__}")
        B, _, H, W = self.depth.shape
        if (self.camera.height, self.camera.width) != (H, W):
            raise ValueError(
                f"camera: image size {self.camera.height}x{self.camera.width} does not match depth {H}x{W}"
            )
        if self.camera.batch_size not in (1, B):
            raise ValueError(f"camera: batch of {self.camera.batch_size} views does not match depth batch {B}")
        if self.camera.intrinsics.device != self.depth.device:
            raise ValueError(f"camera: expected device {self.depth.device} (that of depth), got {self.camera.intrinsics.device}")
        self.camera = self.camera.to(dtype=dtype).expand(B)
        checks.add(_finite_negative(self.depth), lambda: ValueError(
            "depth: negative values found; depth is the positive distance along the view axis "
            "(use inf, 0 or nan for background)"))
        valid = geometry_depth(self.depth)
        if self.mask is not None:
            _check_tensor("mask", self.mask, 1, self.depth)
            if self.mask.dtype != torch.bool:
                if self.mask.is_floating_point() or self.mask.dtype in (torch.uint8, torch.int32, torch.int64):
                    checks.add((self.mask != 0) & (self.mask != 1), lambda: ValueError("mask: expected bool or 0/1 values"))
                    self.mask = self.mask != 0
                else:
                    raise TypeError(f"mask: expected a bool tensor, got {self.mask.dtype}")
            valid = valid & self.mask
        self._valid = valid
        for name in ("normals", "light", "position"):
            x = getattr(self, name)
            if x is None:
                continue
            _check_tensor(name, x, 3, self.depth)
            if x.dtype not in _FLOAT_TYPES:
                raise TypeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
            x = x.to(dtype)
            checks.add(~torch.isfinite(x) & valid,
                       lambda name=name: ValueError(f"{name}: non-finite values on valid (non-background) pixels"))
            setattr(self, name, x)
        if self.normals is not None:
            with torch.no_grad():
                short = (channel_norm(self.normals) < 1e-6) & valid
            checks.add(short, lambda: ValueError("normals: zero-length normals on valid pixels"))
        if self.position is not None:
            checks.add(~(self.position[:, 2:3] < 0) & valid, lambda: ValueError(_POSITION_IN_FRONT))
        if self.object_id is not None:
            _check_tensor("object_id", self.object_id, 1, self.depth)
            if self.object_id.is_floating_point() or self.object_id.dtype == torch.bool:
                raise TypeError(f"object_id: expected an integer tensor, got {self.object_id.dtype}")
            checks.add(self.object_id < 0, lambda: ValueError("object_id: ids must be >= 0"))
            self.object_id = self.object_id.long()
        if self.backface_depth is not None:
            _check_tensor("backface_depth", self.backface_depth, 1, self.depth)
            if self.backface_depth.dtype not in _FLOAT_TYPES:
                raise TypeError(f"backface_depth: expected a floating-point tensor, got {self.backface_depth.dtype}")
            self.backface_depth = self.backface_depth.to(dtype)
            bad = valid & ~(self.backface_depth >= self.depth)  # NaN fails too
            checks.add(bad, lambda: ValueError(
                f"backface_depth: expected values >= depth on valid pixels, {int(bad.sum())} are not"))
        checks.raise_first()

    def to(self, device=None, dtype: torch.dtype | None = None) -> "GBuffer":
        """A copy on ``device`` (and with float buffers in ``dtype``); as ``Tensor.to``, ``gbuffer.to(torch.float64)``
        changes the dtype alone."""
        device, dtype = to_arguments(device, dtype)

        def move(x, floating=True):
            if x is None:
                return None
            return x.to(device=device, dtype=dtype if floating and x.is_floating_point() else None)

        out = GBuffer(move(self.depth), self.camera.to(device=device, dtype=dtype), normals=move(self.normals),
                      light=move(self.light), mask=move(self.mask, False), object_id=move(self.object_id, False),
                      backface_depth=move(self.backface_depth), position=move(self.position))
        out._decimation = self._decimation
        return out

    # ------------------------------------------------------------------ derived buffers
    @property
    def shape(self) -> tuple[int, int, int, int]:
        return tuple(self.depth.shape)

    @property
    def decimation(self) -> tuple[int, int, int]:
        """``(1, H, W)``, or ``(f, H_full, W_full)`` for a G-buffer of every ``f``-th texel of a full-resolution one
        (:func:`~torch_ao.resolution.downsample_gbuffer`, a module's ``resolution="half"``): per-pixel maps
        given at full resolution (:class:`~torch_ao.thickness.MapThickness`) are picked alike."""
        return self._decimation if self._decimation[0] > 1 else (1, *self.depth.shape[-2:])

    @property
    def valid(self) -> torch.Tensor:
        """``(B,1,H,W)`` bool: True on pixels that have geometry."""
        return self._valid

    def derived(self, key, compute):
        """``compute()``, a buffer derived from this G-buffer, computed once per ``key`` and kept for the
        next call (a fit evaluates the same views hundreds of times) while none of the G-buffer's
        tensors needs gradients (then it is computed once per :meth:`one_call`, else every time), nor under
        ``torch.compile`` (the cache's content would be a guard: a second call on the same G-buffer would
        recompile the whole walk). Do not modify the result in place."""
        if torch.compiler.is_compiling():
            return compute()
        if any(x is not None and x.requires_grad for x in (self.depth, self.normals, self.position,
                                                           self.camera.intrinsics)):
            if self._call is None:
                return compute()
            cache = self._call
        else:
            cache = self._derived
        if key not in cache:
            cache[key] = compute()
        return cache[key]

    def in_call(self, *keys) -> bool:
        """Whether a :meth:`one_call` is open and none of ``keys`` has been derived in it yet."""
        return self._call is not None and not any(k in self._call for k in keys)

    def keep(self, key, value: torch.Tensor) -> None:
        """Make ``value`` what :meth:`derived` gives for ``key`` until the open :meth:`one_call` ends: the same
        buffer computed another way (the kernels' one-pass view geometry,
        :func:`torch_ao.kernels.frame.view_geometry`)."""
        if self._call is None:
            raise RuntimeError("GBuffer.keep: no one_call is open")
        self._call[key] = value

    @contextlib.contextmanager
    def one_call(self):
        """Within it, the buffers :meth:`derived` computes (positions, normals, ...) are computed once even where
        the G-buffer's tensors need gradients (one forward's graph may read a tensor twice) and dropped at its
        end, with their graph. A method's ``forward`` runs in it; nested calls share the outermost. Under
        ``torch.compile`` it does nothing (as :meth:`derived`: the G-buffer's state would be a guard)."""
        if self._call is not None or torch.compiler.is_compiling():
            yield self
            return
        self._call = {}
        try:
            yield self
        finally:
            self._call = None

    @property
    def safe_depth(self) -> torch.Tensor:
        """Depth with background replaced by 1 (finite everywhere; zero gradient there)."""
        return self.derived("safe_depth", lambda: torch.where(self._valid, self.depth, torch.ones_like(self.depth)))

    def positions(self) -> torch.Tensor:
        """``(B,3,H,W)`` view-space positions: the ``position`` buffer when given, else unprojected
        depth (background at depth 1 either way)."""
        return self.derived("positions", self._positions)

    def _positions(self) -> torch.Tensor:
        unprojected = self.camera.unproject(self.safe_depth)
        if self.position is None:
            return unprojected
        return torch.where(self._valid, self.position, unprojected)

    def view_normals(self, method: str = "improved") -> torch.Tensor:
        """``(B,3,H,W)`` unit normals facing the camera: given ones, else reconstructed from depth."""
        return self.derived(("view_normals", method), lambda: self._view_normals(method))

    def _view_normals(self, method: str) -> torch.Tensor:
        if self.normals is not None:
            return _unit_facing(self.normals, self.positions(), self._valid)
        return normals_from_depth(self.depth, self.camera, method=method, valid=self._valid,
                                  positions=self.positions() if self.position is None else None)


def _toward_camera(positions: torch.Tensor) -> torch.Tensor:
    return normalize_channels(-positions)


def _unit_facing(normals: torch.Tensor, positions: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``normals`` ``(B,3,H,W)`` made unit length (the direction toward the camera where not ``valid``) and
    turned to face the camera at ``positions`` ``(B,3,H,W)``."""
    n = torch.where(valid, normals, -positions)
    # A length whose square overflows (1e20 in float32) would normalise to 0: such normals are taken in units of
    # their largest component first (others as they are, bit for bit)
    largest = n.detach().abs().amax(1, keepdim=True)
    n = normalize_channels(n / torch.where((largest > 1e-15) & (largest < 1e15), 1.0, largest).clamp_min(torch.finfo(n.dtype).tiny))
    with torch.no_grad():  # (which side faces is a decision: a sign without a gradient)
        sign = torch.where((n * positions).sum(1, keepdim=True) <= 0, 1.0, -1.0).to(n.dtype)
    return n * sign


def normals_from_depth(
    depth: torch.Tensor,
    camera: PinholeCamera,
    method: str = "improved",
    valid: torch.Tensor | None = None,
    positions: torch.Tensor | None = None,
) -> torch.Tensor:
    """Unit view-space normals ``(B,3,H,W)`` reconstructed from ``depth (B,1,H,W)``, facing the camera.

    ``method="kornia"``: kornia's ``depth_to_normals`` (central differences; smears across edges).
    ``method="improved"``: per axis, take the one-sided difference on the side whose depth is better
    predicted by extrapolating the two pixels beyond it (``1/depth`` is affine across a plane, so
    ``l1*l2/(2*l2 - l1)`` predicts the centre exactly on planes); the PSSAO gist's ``computeNormalImproved``.
    Background pixels get the direction toward the camera.

    Shape:
        - depth: ``(B, 1, H, W)`` float (world units); valid: optional ``(B, 1, H, W)`` bool.
        - positions: optional ``(B, 3, H, W)``, the depth unprojected by ``camera`` with background at depth 1
          (:meth:`GBuffer.positions` of a G-buffer without a position buffer), when the caller has it.
        - Output: ``(B, 3, H, W)`` unit view-space normals, the depth's dtype.
    """
    if method not in ("improved", "kornia"):
        raise ValueError(f"method: expected 'improved' or 'kornia', got {method!r}")
    if valid is None:
        valid = geometry_depth(depth)
    d = torch.where(valid, depth, torch.ones_like(depth))
    pos = camera.unproject(d) if positions is None else positions
    if method == "kornia":
        K = camera.intrinsics.expand(depth.shape[0], 3, 3).to(d.dtype)
        n = depth_to_normals(d, K) * d.new_tensor((1.0, -1.0, -1.0)).view(1, 3, 1, 1)
    else:
        n = _improved_normals(d, pos, valid)
    return _unit_facing(n, pos, valid)


def _improved_normals(d: torch.Tensor, pos: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    nan = float("nan")
    # Pad by two with NaN so that missing neighbours (image border, background) are never chosen.
    # The choice of side is discrete, so it is made on detached depth (no NaN can reach a gradient).
    d = d.detach()
    dv = torch.where(valid, d, torch.full_like(d, nan))
    dp = F.pad(dv, (2, 2, 2, 2), value=nan)
    pp = F.pad(pos, (2, 2, 2, 2))
    H, W = d.shape[-2:]

    def shifted(t, dy, dx):
        return t[..., 2 + dy : 2 + dy + H, 2 + dx : 2 + dx + W]

    def one_axis(dy, dx):
        # Neighbours at -1/-2 and +1/+2 pixels along the axis.
        m1, m2 = shifted(dp, -dy, -dx), shifted(dp, -2 * dy, -2 * dx)
        p1, p2 = shifted(dp, dy, dx), shifted(dp, 2 * dy, 2 * dx)
        err_m = _extrapolation_error(m1, m2, d)
        err_p = _extrapolation_error(p1, p2, d)
        minus_ok = torch.isfinite(m1) & valid
        plus_ok = torch.isfinite(p1) & valid
        use_minus = minus_ok & (~plus_ok | (err_m < err_p))
        diff_minus = pos - shifted(pp, -dy, -dx)
        diff_plus = shifted(pp, dy, dx) - pos
        diff = torch.where(use_minus, diff_minus, diff_plus)
        return torch.where(minus_ok | plus_ok, diff, torch.zeros_like(diff))

    # Differences in units of the pixel's depth: the cross product's length is then about the squared pixel
    # angle at any depth, where in world units it overflows float32 (depth ~1e14: |n|^2 ~ 1e56) or falls below
    # the degeneracy threshold (depth ~1e-10). A positive scale leaves the unit normal and its gradient as they are.
    unit = d.clamp_min(torch.finfo(d.dtype).tiny)
    dpdx = one_axis(0, 1) / unit  # toward +u (right)
    dpdy = -one_axis(1, 0) / unit  # toward -v (up)
    n = torch.cross(dpdx, dpdy, dim=1)
    degenerate = channel_norm(n) < 1e-20
    return torch.where(degenerate, _toward_camera(pos), n)


def _extrapolation_error(n1: torch.Tensor, n2: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """``|n1*n2/(2*n2 - n1) - centre|``, +inf where the prediction is undefined."""
    denom = 2 * n2 - n1
    ok = torch.isfinite(n1) & torch.isfinite(n2) & (denom.abs() > 1e-12)
    safe = torch.where(ok, denom, torch.ones_like(denom))
    pred = torch.where(ok, n1 * n2 / safe, torch.full_like(denom, float("inf")))
    return torch.where(ok, (pred - centre).abs(), torch.full_like(denom, float("inf")))
