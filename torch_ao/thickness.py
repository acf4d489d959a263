"""Thickness models of the visibility-bitmask family: how deep each occluder reaches behind its visible surface.

Bitmask AO treats the depth buffer as surfaces of some thickness: a sample occludes the directions
between its front point and its back point, the front point pushed ``t`` away from the camera. A
:class:`Thickness` is one small object per model that says

* which parameters it fits (:meth:`Thickness.parameters`: name -> initial value and lower bound; the AO
  module registers them as ``nn.Parameter``\\ s on itself under these names, so ``fit --params`` and
  checkpoints see flat names such as ``thickness`` or ``thickness_scale``),
* which images its samples read from the G-buffer (:meth:`Thickness.buffers`), and
* its value at a sample (:meth:`Thickness.at`), in world units.

Models (every value is ``>= 0``; ``thickness`` is always the additive term in world units):

=====================  ===========================================================  ===========================
class                  thickness of the occluder at a sample                         reads
=====================  ===========================================================  ===========================
:class:`ScalarThickness`   ``thickness`` (0-d)                                       nothing
:class:`ObjectThickness`   ``thickness[object_id]`` (a ``(K,)`` table)               ``gbuffer.object_id``
:class:`MapThickness`      ``thickness`` map ``(B,1,H,W)`` read at the sample        the map
:class:`LinearThickness`   ``thickness + thickness_slope * depth`` (SSRT3, Filament)  the sample's depth
:class:`BackfaceThickness` ``thickness_scale * (backface_depth - depth) + thickness`` ``gbuffer.backface_depth``
:class:`NetThickness`      ``scale * cnn(front G-buffer) + thickness`` (learned map)  depth and normals
=====================  ===========================================================  ===========================

Any model with ``growth`` given also multiplies by ``1 + thickness_growth * |sample - pixel|`` (world
units; this reads the sample's 3D offset, which autograd then records: about 24 more bytes per sample).
:func:`as_thickness` maps the constructor's historical forms (a float, a ``(K,)`` table, a ``(B,1,H,W)``
map, ``thickness_growth=``) onto these classes.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import torch

from .thickness_base import Parameter, Thickness, ThicknessLayer, checked_growth
from .thickness_net import NetThickness

__all__ = ["Thickness", "ScalarThickness", "ObjectThickness", "MapThickness", "LinearThickness",
           "BackfaceThickness", "NetThickness", "BoundThickness", "ThicknessLayer", "as_thickness"]

#: the back-face thickness of a pixel whose object has no exit along its camera ray (``backface_depth =
#: inf``), in world units: a finite stand-in for "as thick as the scene", so that gradients stay finite
BACKFACE_CAP = 1e6


class _TensorThickness(Thickness):
    """A model whose one parameter ``thickness`` is a tensor of ``dims`` dimensions (``expected`` says which)."""

    dims: int
    expected: str

    def __init__(self, thickness, **kwargs) -> None:
        super().__init__(**kwargs)
        self.initial = torch.as_tensor(thickness)

    def own_parameters(self):
        return {"thickness": Parameter(self.initial)}

    def check(self, name, value):
        if name != "thickness":
            return super().check(name, value)
        if value.dim() != self.dims or (self.dims == 4 and value.shape[1] != 1):
            raise ValueError(f"thickness: expected {self.expected}, got shape {tuple(value.shape)}")


class ScalarThickness(_TensorThickness):
    """One thickness ``thickness`` (world units, 0-d) for every occluder: the paper's."""

    dims, expected = 0, "a scalar"
    kernel_read = "constant"

    def __init__(self, thickness: float | torch.Tensor = 0.5, **kwargs) -> None:
        super().__init__(thickness, **kwargs)

    def layer(self, gbuffer, params):
        t = params["thickness"]
        return ThicknessLayer(None, torch.ones_like(t), t, read="constant")

    def at(self, sample, params):
        return params["thickness"].to(sample.dtype)


class ObjectThickness(_TensorThickness):
    """A thickness per object: a ``(K,)`` table indexed by ``gbuffer.object_id`` at the sample (ids beyond
    the table use its last entry)."""

    dims, expected = 1, "a (K,) per-object table"
    kernel_read = "first_tap"

    def buffers(self, gbuffer, params):
        if gbuffer.object_id is None:
            raise ValueError("gbuffer.object_id: a per-object thickness table needs an object_id buffer")
        return {"object_id": gbuffer.object_id}

    def layer(self, gbuffer, params):
        table = params["thickness"]
        ids = self.buffers(gbuffer, params)["object_id"].long().clamp(0, table.shape[0] - 1)
        one = torch.ones((), dtype=table.dtype, device=table.device)
        return ThicknessLayer(table[ids], one, torch.zeros_like(one), read="first_tap")

    def at(self, sample, params):
        table = params["thickness"]
        ids = sample.gather("object_id")[:, 0].long().clamp(0, table.shape[0] - 1)
        return table.to(sample.dtype)[ids]


class MapThickness(_TensorThickness):
    """A per-pixel thickness map ``(B,1,H,W)`` (or batch 1), read at the sample: the *occluder's* thickness.
    At ``resolution="half"`` or ``"quarter"`` the map stays at the G-buffer's full resolution, and the walk reads
    the texels the decimated G-buffer kept (:attr:`~torch_ao.gbuffer.GBuffer.decimation`)."""

    dims, expected = 4, "a (B,1,H,W) map"

    def buffers(self, gbuffer, params):
        B, _, H, W = gbuffer.depth.shape
        t = params["thickness"]
        f, full_h, full_w = gbuffer.decimation
        if f > 1 and t.dim() == 4 and t.shape[-2:] == (full_h, full_w):
            t = t[..., ::f, ::f]  # a full-resolution map, picked as the G-buffer was (resolution.downsample_gbuffer)
        if t.shape[-2:] != (H, W) or t.shape[0] not in (1, B):
            full = f" (nor its full-resolution frame, {full_h}x{full_w})" if f > 1 else ""
            raise ValueError(f"thickness: map of shape {tuple(t.shape)} does not match the G-buffer (B={B}, H={H}, W={W})"
                             + full)
        return {"thickness": t.to(gbuffer.depth.dtype).expand(B, 1, H, W)}

    kernel_read = "layer"

    def layer(self, gbuffer, params):
        t = self.buffers(gbuffer, params)["thickness"]
        one = torch.ones((), dtype=t.dtype, device=t.device)
        return ThicknessLayer(t, one, torch.zeros_like(one))

    def at(self, sample, params):
        return sample.gather("thickness")[:, 0]


class LinearThickness(Thickness):
    """``t = thickness + thickness_slope * depth`` at the sample (world units; ``thickness_slope`` is
    unitless): thicker far away, as SSRT3 and Filament's SSAO scale their thickness with depth.

    Reads the sample's own depth, so autograd records the sample's position (about 24 bytes per sample).
    """

    def __init__(self, thickness: float | torch.Tensor = 0.1, slope: float | torch.Tensor = 0.05, **kwargs) -> None:
        super().__init__(**kwargs)
        self.initial, self.slope = torch.as_tensor(thickness), torch.as_tensor(slope)

    def own_parameters(self):
        return {"thickness": Parameter(self.initial), "thickness_slope": Parameter(self.slope)}

    kernel_read = "depth"

    def layer(self, gbuffer, params):
        return ThicknessLayer(None, params["thickness_slope"], params["thickness"], read="depth")

    def at(self, sample, params):
        depth = -sample.position[:, 2]
        return params["thickness"].to(sample.dtype) + params["thickness_slope"].to(sample.dtype) * depth


class BackfaceThickness(Thickness):
    """Each occluder's own thickness from a back-face depth layer: ``t = thickness_scale * (backface_depth -
    depth) + thickness`` at the sample (``gbuffer.backface_depth`` ``(B,1,H,W)``: the depth where the camera
    ray leaves the first object it hit, as a front-face-culled depth pass renders it; ``inf`` = no exit,
    treated as :data:`BACKFACE_CAP` world units). ``thickness_scale`` (unitless, default 1) and the offset
    ``thickness`` (world units, default 0) are fitted corrections."""

    def __init__(self, scale: float | torch.Tensor = 1.0, thickness: float | torch.Tensor = 0.0, **kwargs) -> None:
        super().__init__(**kwargs)
        self.scale, self.initial = torch.as_tensor(scale), torch.as_tensor(thickness)

    def own_parameters(self):
        return {"thickness_scale": Parameter(self.scale), "thickness": Parameter(self.initial)}

    def buffers(self, gbuffer, params):
        back = getattr(gbuffer, "backface_depth", None)
        if back is None:
            raise ValueError("gbuffer.backface_depth: the back-face thickness model needs a (B,1,H,W) back-face depth layer "
                             "(an engine's front-face-culled depth pass; `torch-ao render --backface`; docs/engines.md)")
        depth = gbuffer.safe_depth
        layer = torch.where(gbuffer.valid, back - depth, torch.zeros_like(depth))
        return {"backface_thickness": layer.clamp(0.0, BACKFACE_CAP)}

    kernel_read = "layer"

    def layer(self, gbuffer, params):
        return ThicknessLayer(self.buffers(gbuffer, params)["backface_thickness"], params["thickness_scale"],
                              params["thickness"])

    def at(self, sample, params):
        layer = sample.gather("backface_thickness")[:, 0]
        return params["thickness_scale"].to(sample.dtype) * layer + params["thickness"].to(sample.dtype)


_BY_DIM = {0: ScalarThickness, 1: ObjectThickness, 4: MapThickness}


def as_thickness(thickness, growth=None) -> Thickness:
    """A :class:`Thickness` from the AO modules' ``thickness=``: a model (returned as it is, or with ``growth``
    given a shallow copy of it that carries the growth: the caller's model is left as it was, so that it can
    serve modules with and without growth), a number or 0-d tensor (:class:`ScalarThickness`), a ``(K,)`` table
    (:class:`ObjectThickness`) or a ``(B,1,H,W)`` map (:class:`MapThickness`)."""
    if isinstance(thickness, Thickness):
        if growth is not None:
            if thickness.growth is not None:
                raise ValueError("thickness_growth: given twice (as an argument and in the thickness model)")
            thickness = copy.copy(thickness)
            thickness.growth = checked_growth(growth)
        return thickness
    if isinstance(thickness, bool) or not isinstance(thickness, (int, float, torch.Tensor)):
        raise ValueError(f"thickness: expected a number, a tensor or a torch_ao.thickness.Thickness, got {thickness!r}")
    value = torch.as_tensor(thickness)
    cls = _BY_DIM.get(value.dim())
    if cls is None or (value.dim() == 4 and value.shape[1] != 1):
        raise ValueError(f"thickness: expected a scalar, a (K,) table or a (B,1,H,W) map, got shape {tuple(value.shape)}")
    return cls(value, growth=growth)


def matching(model: Thickness, value: torch.Tensor) -> Thickness:
    """``model``, or the tensor model matching ``value``'s shape when ``model`` is one of the three tensor
    forms and the module's ``thickness`` was reassigned with another shape (e.g. a map set per frame)."""
    cls = _BY_DIM.get(value.dim())
    if isinstance(model, _TensorThickness) and cls is not None and type(model) is not cls:
        return cls(value, growth=model.growth)
    return model


@dataclass
class BoundThickness:
    """A model with the AO module's current parameter values: ``bound(sample)`` is the thickness ``(rows,)``."""

    model: Thickness
    params: dict[str, torch.Tensor]

    def __call__(self, sample) -> torch.Tensor:
        return self.model.value(sample, self.params)

    def ungrown(self, sample) -> torch.Tensor:
        """The thickness ``(rows,)`` (or 0-d) before growth: a sample's on the pixel's own texel, where
        ``|sample - pixel|`` is 0 (its ``delta`` is a stand-in there)."""
        return self.model.at(sample, self.params)

    def buffers(self, gbuffer) -> dict[str, torch.Tensor]:
        return self.model.buffers(gbuffer, self.params)

    def layer(self, gbuffer) -> ThicknessLayer | None:
        """:meth:`Thickness.layer` with these parameters, and the model's growth."""
        form = self.model.layer(gbuffer, self.params)
        if form is None or self.model.growth is None:
            return form
        return dataclasses.replace(form, growth=self.params["thickness_growth"])

