"""A learned per-pixel thickness: a small CNN maps the front G-buffer alone to each occluder's thickness.

A back-face depth layer (:class:`~torch_ao.thickness.BackfaceThickness`) gives every occluder its own
thickness, but an engine must render a second, front-face-culled depth pass for it. :class:`NetThickness`
predicts that thickness from what the first pass already holds -- depth, normals and their local
changes -- with a few convolutions, so one model serves thin slats and thick walls alike. Its weights are
fitted parameters of the AO module it is given to (flat names ``thickness_net_<layer>_<weight|bias>``,
beside the additive ``thickness``), so :func:`torch_ao.fit.fit`, optimisers and checkpoints see them; it
can equally be trained on its own (:meth:`NetThickness.predict`, supervised on a back-face layer) and
handed to a method afterwards.

Units: depths, ``scale`` and the predicted thickness are world units; the features are unitless.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn
from torch.func import functional_call

from .checks import check_float, check_int
from .thickness_base import Parameter, Thickness, ThicknessLayer

__all__ = ["FEATURES", "net_features", "ThicknessCNN", "NetThickness"]

#: names of the :func:`net_features` channels, in order
FEATURES = ("relative log depth", "normal x", "normal y", "normal z", "d log depth / dx", "d log depth / dy",
            "log pixel footprint / scale", "valid")
#: prefix of the CNN's weights among the AO module's parameters
PREFIX = "thickness_net_"


def net_features(gbuffer, scale: float) -> torch.Tensor:
    """``(B, 8, H, W)`` unitless inputs of the thickness CNN (:data:`FEATURES`); background pixels are 0.

    ``log(depth / median depth)`` (per image), the view normals, ``log depth``'s forward differences in
    x and y clamped to ``[-1, 1]`` (depth edges), ``log(pixel footprint / scale)`` with ``scale`` in world
    units (how many pixels ``scale`` spans: the radius R or another scene scale) and the valid mask. In the
    G-buffer's dtype.
    """
    valid = gbuffer.valid
    depth = gbuffer.safe_depth
    vf = valid.to(depth.dtype)
    log_d = torch.log(depth)
    B = depth.shape[0]
    med = torch.stack([log_d[b][valid[b]].median() if bool(valid[b].any()) else log_d.new_zeros(()) for b in range(B)])
    rel = (log_d - med.view(B, 1, 1, 1)) * vf
    normals = gbuffer.view_normals().to(depth.dtype) * vf
    gx = F.pad(log_d[..., :, 1:] - log_d[..., :, :-1], (0, 1)) * vf * F.pad(vf[..., :, 1:], (0, 1))
    gy = F.pad(log_d[..., 1:, :] - log_d[..., :-1, :], (0, 0, 0, 1)) * vf * F.pad(vf[..., 1:, :], (0, 0, 0, 1))
    fy = gbuffer.camera.intrinsics[:, 1, 1].to(depth.dtype).view(-1, 1, 1, 1)
    footprint = torch.log(depth / fy / scale) * vf
    return torch.cat([rel, normals, gx.clamp(-1, 1), gy.clamp(-1, 1), footprint, vf], 1)


def _softplus_inverse(y: float) -> float:
    return y + math.log(-math.expm1(-y))


class ThicknessCNN(nn.Module):
    """Features ``(B, 8, H, W)`` -> unitless thickness ``softplus(conv(x))`` ``(B, 1, H, W)``, ``> 0``.

    Three 3x3 convolutions with dilations 1, 2, 4 and ReLU, then a 3x3 head (receptive field 17 pixels;
    ``width`` channels, about 6k weights at 16). The head's weights start at zero and its bias at
    ``softplus^-1(init)``, so the untrained net outputs ``init`` everywhere.
    """

    def __init__(self, width: int = 16, init: float = 0.5) -> None:
        super().__init__()
        self.width = check_int("width", width, 1)
        init = check_float("init", init, 1e-6)
        layers, c = [], len(FEATURES)
        for d in (1, 2, 4):
            layers += [nn.Conv2d(c, width, 3, padding=d, dilation=d), nn.ReLU()]
            c = width
        self.body = nn.Sequential(*layers)
        self.head = nn.Conv2d(width, 1, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.constant_(self.head.bias, _softplus_inverse(init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.softplus(self.head(self.body(x)))


class NetThickness(Thickness):
    """``t = scale * cnn(net_features(gbuffer, scale)) + thickness``, a per-pixel map read at the sample.

    Args:
        scale: world units of the CNN's output and of its footprint feature (the AO radius R is a good
            choice: the net then predicts thickness in units of R, so it carries over between scenes).
        width: channels of the CNN's hidden layers.
        init: thickness (world units) the untrained net outputs everywhere.
        cnn: a trained :class:`ThicknessCNN` to start from (its weights are copied; ``width`` and
            ``init`` are then ignored).
        thickness: the additive offset (world units, ``>= 0``, default 0), fitted too.
        growth: as every :class:`~torch_ao.thickness.Thickness`.

    The AO module registers the CNN's weights as parameters named :data:`PREFIX` + the weight's name
    with dots as underscores (``thickness_net_body_0_weight``...); :meth:`weights` reads them back.
    """

    def __init__(self, scale: float = 1.0, *, width: int = 16, init: float = 0.5, cnn: ThicknessCNN | None = None,
                 thickness: float | torch.Tensor = 0.0, growth: float | torch.Tensor | None = None) -> None:
        super().__init__(growth=growth)
        self.scale = check_float("scale", scale, 1e-12)
        if cnn is None:
            cnn = ThicknessCNN(width, check_float("init", init, 1e-6) / self.scale)
        elif not isinstance(cnn, ThicknessCNN):
            raise ValueError(f"cnn: expected a torch_ao.thickness_net.ThicknessCNN, got {type(cnn).__name__}")
        self.cnn = cnn
        self.initial = torch.as_tensor(thickness)
        self._names = {PREFIX + name.replace(".", "_"): name for name, _ in cnn.named_parameters()}

    # ------------------------------------------------------------------ the Thickness interface
    def own_parameters(self) -> dict[str, Parameter]:
        out = {"thickness": Parameter(self.initial)}
        weights = dict(self.cnn.named_parameters())
        out.update({flat: Parameter(weights[name].detach().clone(), minimum=None) for flat, name in self._names.items()})
        return out

    def check(self, name, value):
        if name not in self._names:
            return super().check(name, value)
        expected = dict(self.cnn.named_parameters())[self._names[name]].shape
        if value.shape != expected:
            raise ValueError(f"{name}: expected shape {tuple(expected)}, got {tuple(value.shape)}")

    def buffers(self, gbuffer, params):
        return {"net_thickness": self.predict(gbuffer, params, offset=False)}

    kernel_read = "layer"

    def layer(self, gbuffer, params):
        t = self.buffers(gbuffer, params)["net_thickness"]
        return ThicknessLayer(t, torch.ones((), dtype=t.dtype, device=t.device), params["thickness"])

    def at(self, sample, params):
        return sample.gather("net_thickness")[:, 0] + params["thickness"].to(sample.dtype)

    # ------------------------------------------------------------------ the map itself
    def weights(self, params: dict[str, torch.Tensor] | nn.Module | None = None) -> dict[str, torch.Tensor]:
        """The CNN's state (``{cnn weight name: tensor}``) from an AO module holding this model, a dict of
        its flat parameter names, or (``None``) the model's own start weights."""
        if params is None:
            return dict(self.cnn.named_parameters())
        if isinstance(params, nn.Module):
            params = {flat: getattr(params, flat) for flat in self._names}
        return {name: params[flat] for flat, name in self._names.items()}

    def predict(self, gbuffer, params=None, *, offset: bool = True) -> torch.Tensor:
        """The thickness map ``(B,1,H,W)`` (world units, ``>= 0``; 0 on background pixels) of ``gbuffer``,
        with the weights of ``params`` (as :meth:`weights`; ``None``: the model's own, differentiable
        w.r.t. ``self.cnn``) plus, when ``offset``, the additive ``thickness`` (``params``' or the model's)."""
        weights = self.weights(params)
        dtype = next(iter(weights.values())).dtype
        x = net_features(gbuffer, self.scale).to(dtype)
        t = self.scale * functional_call(self.cnn, weights, (x,))
        if offset:
            t = t + self._offset(params).to(dtype)
        return (t * gbuffer.valid.to(dtype)).to(gbuffer.depth.dtype)

    def _offset(self, params) -> torch.Tensor:
        if params is None:
            return torch.as_tensor(self.initial)
        return params.thickness if isinstance(params, nn.Module) else params["thickness"]

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike, params: dict[str, torch.Tensor] | nn.Module | None = None) -> Path:
        """Write the model (scale, width, offset and CNN weights: those of ``params`` as :meth:`weights`,
        else its own) to ``path`` (``torch.save``; :meth:`load` reads it with ``weights_only=True``)."""
        state = {"scale": self.scale, "width": self.cnn.width, "thickness": self._offset(params).detach().cpu().clone(),
                 "growth": None if self.growth is None else float(self.growth),
                 "cnn": {k: v.detach().cpu().clone() for k, v in self.weights(params).items()}}
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(state, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "NetThickness":
        """The model :meth:`save` wrote (``ValueError`` naming ``path`` if it is not one)."""
        state = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(state, dict) or not {"scale", "width", "cnn", "thickness"} <= set(state):
            raise ValueError(f"path: {path} is not a NetThickness file (expected keys scale, width, thickness, cnn)")
        cnn = ThicknessCNN(int(state["width"])).to(next(iter(state["cnn"].values())).dtype)
        cnn.load_state_dict(state["cnn"])
        return cls(float(state["scale"]), cnn=cnn, thickness=state["thickness"], growth=state.get("growth"))

    def describe(self) -> str:
        return f"NetThickness(scale={self.scale:g}, width={self.cnn.width})" + (
            "" if self.growth is None else f"(growth={float(self.growth):g})")
