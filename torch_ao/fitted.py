"""Fitted pipelines: a method with its fitted parameters and an optional denoiser, as one module that
is saved to and rebuilt from a ``params.json``.

A :class:`FittedPipeline` is what ``torch-ao fit`` fits and scores (the method in hard mode, followed
by the :class:`~torch_ao.denoise.Denoiser` when it has one) and what ``torch-ao ao --fitted``,
``torch-ao bench --fitted`` and :func:`load_fitted` rebuild. The file holds everything the rebuild
needs:

* ``method``: the registry name (``"bitmask"``, ``"gtao"``, ...);
* ``options``: the constructor's other keyword arguments (variant, weighting, preset or
  slices/steps, jitter, ...), JSON values; for bitmask methods ``thickness_model`` names the
  thickness model (:data:`THICKNESS_MODELS`: ``scalar`` when absent), whose parameters are among
  ``parameters`` under the names the method registers (``thickness``, ``thickness_slope``,
  ``thickness_scale``);
* ``parameters``: every float parameter of the method (its ``nn.Parameter``\\ s, and frozen ones that
  were given as options) at its current value: a number, or ``{"shape": [...], "values": [...]}``
  for a per-object table or a per-pixel map (float32 values survive the JSON round trip exactly);
* ``denoiser``: the denoiser's settings, or ``null``;
* ``length_unit``: the unit of every length among ``options`` and ``parameters`` (the unit of the
  G-buffers it was fitted on, e.g. ``"m"``; ``"world units"`` when not said, and in files written
  before the key existed). :func:`scale_lengths` rescales them all together (``--scale``);
* ``torch_ao_version``, and whatever the writer adds (metrics, loss history) under other keys.
"""
from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn

from .denoise import Denoiser
from .gbuffer import GBuffer
from .methods import get_method
from .options import Option
from .thickness import BackfaceThickness, LinearThickness, ObjectThickness, ScalarThickness

__all__ = ["DenoisedAO", "FittedPipeline", "load_fitted", "bench_rows", "cli_module", "FORMAT", "DENOISER_SETTINGS",
           "THICKNESS_MODELS", "thickness_model", "DEFAULT_LENGTH_UNIT", "SCALE", "length_factors", "scale_lengths", "rescaled"]

#: Value of the file's ``format`` key (bumped when the layout changes).
FORMAT = "torch_ao.fitted/1"
#: The :class:`~torch_ao.denoise.Denoiser` settings stored in (and read from) the file.
DENOISER_SETTINGS = ("kernel_size", "sigma_space", "sigma_depth", "sigma_normal", "guide", "temporal", "alpha")
#: The ``length_unit`` of a file that does not say.
DEFAULT_LENGTH_UNIT = "world units"
#: How an :class:`~torch_ao.options.Option`'s unit scales with the lengths: the power of the length scale.
_LENGTH_POWERS = {"world units": 1, "1 / world units": -1}
#: The ``--scale`` flag of ``torch-ao ao --fitted`` and ``torch-ao export``.
SCALE = Option("scale", None, "with a params.json: world units of the frames it runs on per length unit of the file "
               "(e.g. 100 for a fit in metres applied to centimetres); multiplies every length parameter together "
               "(radius, thickness, biases, fade lengths); default 1", float, minimum=0.0, open_minimum=True)


#: Thickness models a pipeline's ``thickness_model`` option names: the :mod:`torch_ao.thickness` class and
#: its constructor's keyword for each parameter the method registers (the method's name -> the keyword).
THICKNESS_MODELS = {
    "scalar": (ScalarThickness, {"thickness": "thickness"}),
    "object": (ObjectThickness, {"thickness": "thickness"}),
    "linear": (LinearThickness, {"thickness": "thickness", "thickness_slope": "slope"}),
    "backface": (BackfaceThickness, {"thickness": "thickness", "thickness_scale": "scale"}),
}


def thickness_model(name: str, values: Mapping[str, Any]):
    """The :mod:`torch_ao.thickness` model ``name`` (a key of :data:`THICKNESS_MODELS`) with the parameter
    values found in ``values`` (method names such as ``thickness_scale``; missing ones take the model's
    defaults; JSON forms are decoded). ``ValueError`` names an unknown model."""
    if name not in THICKNESS_MODELS:
        raise ValueError(f"thickness_model: expected one of {', '.join(THICKNESS_MODELS)}, got {name!r}")
    cls, keywords = THICKNESS_MODELS[name]
    return cls(**{kw: _decode(values[param]) for param, kw in keywords.items() if param in values})


def length_factors(method: str) -> dict[str, int]:
    """``{name: power}`` of every option of ``method`` with a length unit (from the method's
    :class:`~torch_ao.options.Option` units: 1 for world units, -1 for 1 / world units). The thickness
    models' own parameters follow the ``thickness`` option (world units); their ``thickness_slope`` and
    ``thickness_scale`` are unitless."""
    return {name: _LENGTH_POWERS[opt.unit] for name, opt in get_method(method).options().items()
            if opt.unit in _LENGTH_POWERS}


def scale_lengths(method: str, values: Mapping[str, Any], scale: float) -> dict[str, Any]:
    """``values`` (a pipeline's options and parameters, JSON forms or tensors) with every length of
    ``method`` multiplied by ``scale`` (world units per fitted unit; ``1 / world units`` divided by it),
    so the pipeline computes on a frame ``scale`` times larger what it computed on the original.
    ``ValueError`` names a ``scale`` that is not a positive finite number."""
    import math

    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
        raise ValueError(f"scale: expected a positive number (world units per fitted unit), got {scale!r}")
    out = dict(values)
    for name, power in length_factors(method).items():
        value = out.get(name)
        if value is None or isinstance(value, (bool, str)):
            continue
        factor = float(scale) ** power
        if isinstance(value, dict) and set(value) == {"shape", "values"}:
            out[name] = {"shape": value["shape"], "values": [v * factor for v in value["values"]]}
        else:  # a number or a tensor
            out[name] = value * factor
    return out


def _encode(value: Any) -> Any:
    """A JSON value for an option or parameter: tensors of one element as numbers, larger ones as
    ``{"shape", "values"}``; tuples as lists."""
    if isinstance(value, torch.Tensor):
        t = value.detach().cpu()
        if t.numel() == 1 and t.dim() == 0:
            return t.item()
        return {"shape": list(t.shape), "values": t.flatten().tolist()}
    if isinstance(value, tuple):
        return [_encode(v) for v in value]
    return value


def _decode(value: Any) -> Any:
    if isinstance(value, dict) and set(value) == {"shape", "values"}:
        return torch.tensor(value["values"], dtype=torch.float32).reshape(value["shape"])
    return value


def _denoiser_settings(denoiser: Denoiser | Mapping | bool | None) -> dict | None:
    if denoiser is None or denoiser is False:
        return None
    if denoiser is True:
        denoiser = Denoiser()
    if isinstance(denoiser, Denoiser):
        return {k: getattr(denoiser, k) for k in DENOISER_SETTINGS}
    if isinstance(denoiser, Mapping):
        unknown = set(denoiser) - set(DENOISER_SETTINGS)
        if unknown:
            raise ValueError(f"denoiser: unknown setting(s) {', '.join(sorted(unknown))}; expected some of "
                             f"{', '.join(DENOISER_SETTINGS)}")
        return {k: getattr(Denoiser(**denoiser), k) for k in DENOISER_SETTINGS}
    raise ValueError(f"denoiser: expected a Denoiser, a dict of its settings, True, False or None, got {denoiser!r}")


class DenoisedAO(nn.Module):
    """``method`` followed by an optional ``denoiser``: ``forward(gbuffer)`` returns the method's
    :class:`~torch_ao.methods.AOOutput` with ``visibility`` ``(B,1,H,W)`` (and ``indirect``
    ``(B,3,H,W)`` when computed) filtered by the denoiser, guided by the G-buffer."""

    def __init__(self, method: nn.Module, denoiser: Denoiser | Mapping | bool | None = None) -> None:
        super().__init__()
        self.method = method
        settings = _denoiser_settings(denoiser)
        self.denoiser = None if settings is None else Denoiser(**settings)

    def forward(self, gbuffer: GBuffer):
        out = self.method(gbuffer)
        if self.denoiser is None:
            return out
        filtered = self.denoiser(out.visibility, gbuffer, indirect=out.indirect)
        return replace(out, visibility=filtered.visibility, indirect=filtered.indirect)


class FittedPipeline(DenoisedAO):
    """A screen-space AO method, named and configured so that it can be saved and rebuilt, followed
    by an optional denoiser (what ships, and what ``torch-ao fit`` fits).

    Args:
        method: registry name of the method (see :data:`torch_ao.METHODS`).
        options: the method's constructor keywords (``preset``/``slices``/``steps``, ``radius``,
            ``variant``, ``weighting``, initial parameter values, ...). Parameters may be numbers or
            tensors (a ``(K,)`` per-object table, a ``(B,1,H,W)`` map). ``thickness_model`` (bitmask
            methods): a key of :data:`THICKNESS_MODELS`; the model is built from the options named
            after its parameters (``thickness``, ``thickness_slope``, ``thickness_scale``).
        denoiser: a :class:`~torch_ao.denoise.Denoiser`, a dict of its settings, ``True`` (default
            settings) or ``None`` (no denoiser).

    The method's parameters are those of ``self.method`` (named ``method.<name>``;
    :func:`torch_ao.fit.fit` also takes the bare ``<name>``).

    Shape:
        - Input: a :class:`~torch_ao.GBuffer` (depth ``(B, 1, H, W)`` in the pipeline's length unit, normals
          ``(B, 3, H, W)``...).
        - Output: :class:`~torch_ao.AOOutput`: ``visibility`` ``(B, 1, H, W)`` in [0, 1], denoised when the
          pipeline has a denoiser.
    """

    def __init__(self, method: str, options: Mapping[str, Any] | None = None,
                 denoiser: Denoiser | Mapping | bool | None = None, *, length_unit: str = DEFAULT_LENGTH_UNIT) -> None:
        if not isinstance(length_unit, str) or not length_unit.strip():
            raise ValueError(f"length_unit: expected the name of a unit (e.g. 'm'), got {length_unit!r}")
        self_options = dict(options or {})
        kwargs = {k: _decode(v) for k, v in self_options.items()}
        model = kwargs.pop("thickness_model", None)
        if model is not None:
            kwargs = {k: v for k, v in kwargs.items() if k not in THICKNESS_MODELS.get(model, (None, {}))[1]}
            kwargs["thickness"] = thickness_model(model, self_options)
        super().__init__(get_method(method)(**kwargs), denoiser)
        self.method_name, self.options, self.length_unit = method, self_options, length_unit

    # ------------------------------------------------------------------ what is stored
    def parameter_values(self) -> dict[str, torch.Tensor]:
        """Every float parameter of the method: its ``nn.Parameter``\\ s, the frozen ones given as options
        and those without a gradient at these options (buffers), at their current values."""
        values = dict(self.method.named_parameters(recurse=False))
        frozen = set(self.options) | set(getattr(self.method, "no_gradient_options", {}))
        for name, buf in self.method.named_buffers(recurse=False):
            if name in frozen:
                values[name] = buf
        return {k: v.detach() for k, v in values.items()}

    def to_dict(self) -> dict:
        """The JSON content of ``params.json`` (see the module docstring)."""
        from .version import __version__

        params = self.parameter_values()
        options = {k: _encode(v) for k, v in self.options.items() if k not in params}
        if hasattr(self.method, "mode"):
            options["mode"] = "hard"  # what ships; soft masks are for fitting
        return {"format": FORMAT, "torch_ao_version": __version__, "method": self.method_name,
                "options": options, "parameters": {k: _encode(v) for k, v in params.items()},
                "denoiser": None if self.denoiser is None else _denoiser_settings(self.denoiser),
                "length_unit": self.length_unit, "slices": getattr(self.method, "slices", None), "steps": getattr(self.method, "steps", None)}

    def save(self, path: str | os.PathLike, **extra) -> Path:
        """Write :meth:`to_dict` (and ``extra`` keys, e.g. metrics and history) to ``path`` atomically."""
        from .io import save_json

        payload = self.to_dict()
        clash = set(extra) & set(payload)
        if clash:
            raise ValueError(f"extra: keys {', '.join(sorted(clash))} are part of the pipeline description")
        return save_json(path, {**payload, **extra})

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "params", scale: float = 1.0) -> "FittedPipeline":
        """Rebuild a pipeline from :meth:`to_dict`'s content (``source`` names it in errors), its lengths
        multiplied by ``scale`` (:func:`scale_lengths`)."""
        if not isinstance(data, Mapping) or "method" not in data:
            raise ValueError(f"{source}: expected a torch_ao fitted-pipeline description with a 'method' key")
        fmt = data.get("format", FORMAT)
        if fmt != FORMAT:
            raise ValueError(f"{source}: format {fmt!r} is not {FORMAT!r} (written by another torch_ao version?)")
        for key in ("options", "parameters"):
            if not isinstance(data.get(key) or {}, Mapping):
                raise ValueError(f"{source}: '{key}' must be an object ({{name: value}}), got "
                                 f"{type(data[key]).__name__} {_short(data[key])}")
        options, parameters = dict(data.get("options") or {}), data.get("parameters") or {}
        values = {**options, **parameters}
        if scale != 1.0:
            values = scale_lengths(data["method"], values, scale)
        try:
            return cls(data["method"], values, data.get("denoiser"),
                       length_unit=data.get("length_unit", DEFAULT_LENGTH_UNIT))
        except (TypeError, ValueError) as err:  # an option the method does not take, or a bad value
            raise ValueError(f"{source}: cannot rebuild {data['method']!r} ({err})") from None

    def extra_repr(self) -> str:
        return f"method={self.method_name!r}"


def _short(value, width: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= width else text[:width - 3] + "..."


def load_fitted(path: str | os.PathLike, device: torch.device | str | None = None, *,
                scale: float = 1.0) -> FittedPipeline:
    """The pipeline a ``params.json`` describes (written by ``torch-ao fit`` or :meth:`FittedPipeline.save`),
    in hard mode, on ``device``, with every length multiplied by ``scale`` (world units of the frames it
    will run on per length unit of the file; :func:`scale_lengths`).

    Shape:
        - Output: a :class:`FittedPipeline`: :class:`~torch_ao.GBuffer` ``(B, C, H, W)`` -> visibility ``(B, 1, H, W)``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"fitted: no such file {path}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as err:
        raise ValueError(f"fitted: {path} is not JSON ({err})") from None
    except RecursionError:
        raise ValueError(f"fitted: {path} is nested too deeply to be a params.json") from None
    pipeline = FittedPipeline.from_dict(data, source=f"fitted: {path}", scale=scale)
    return pipeline if device is None else pipeline.to(device)


def rescaled(pipeline: FittedPipeline, scale: float) -> FittedPipeline:
    """A copy of ``pipeline`` with every length multiplied by ``scale`` (:func:`scale_lengths`)."""
    return FittedPipeline.from_dict(pipeline.to_dict(), scale=scale)


def cli_module(args, build, method_flags=()) -> nn.Module:
    """The module ``torch-ao ao`` runs: ``--fitted FILE`` (a :func:`load_fitted` pipeline, its lengths
    times ``--scale``) or ``build(args)`` (the method from the flags), followed by the denoiser with ``--denoise``.
    ``method_flags``: names of the method flags, refused with ``--fitted`` when given."""
    fitted, denoise = getattr(args, "fitted", None), bool(getattr(args, "denoise", False))
    if fitted is None:
        if getattr(args, "scale", None) is not None:
            raise ValueError("--scale: scales a --fitted pipeline's lengths; give --radius (and the other lengths) "
                             "directly without --fitted")
        module = build(args)
        return DenoisedAO(module, True) if denoise else module
    clash = [f"--{k.replace('_', '-')}" for k in method_flags if getattr(args, k, None) is not None]
    if getattr(args, "auto", False):
        clash.append("--auto")
    if clash:
        raise ValueError(f"--fitted: the file fixes the method and its options; drop {', '.join(clash)}")
    scale = getattr(args, "scale", None)
    pipeline = load_fitted(fitted, scale=1.0 if scale is None else scale)
    if denoise and pipeline.denoiser is None:
        pipeline.denoiser = Denoiser()
    return pipeline


def _preset_of(pipeline: FittedPipeline, source: str) -> str:
    from .methods import PRESETS

    preset = pipeline.options.get("preset")
    counts = (getattr(pipeline.method, "slices", None), getattr(pipeline.method, "steps", None))
    resolution = getattr(pipeline.method, "resolution", "full")
    suffix = "" if resolution == "full" else f"@{resolution}"
    quality = str(preset).partition("@")[0]
    if quality in PRESETS and PRESETS[quality] == counts:
        return quality + suffix
    match = [name + suffix for name, c in PRESETS.items() if c == counts]
    if not match:
        raise ValueError(f"fitted: {source} uses {counts[0]} slices x {counts[1]} steps, which is no preset; "
                         "bench rows are per preset")
    return match[0]


def bench_rows(paths, views, **run_bench_options) -> list[dict]:
    """Rows of :func:`torch_ao.bench.run_bench` for fitted pipelines (``params.json`` files), one
    method per file named ``"<method> fitted (<name>)"`` (the file stem, or its folder for
    ``params.json``), at the file's preset, radius and parameters; with the file's denoiser when it
    has one (rows without and with it), else without."""
    from .bench import run_bench

    rows = []
    for path in paths:
        path = Path(path)
        pipeline = load_fitted(path)
        name = path.parent.name if path.stem == "params" and path.parent.name else path.stem
        label = f"{pipeline.method_name} fitted ({name})"

        def factory(_path=path, **_ignored):  # preset, radius and mode come from the file
            return load_fitted(_path).method

        options = {**run_bench_options, "denoise": pipeline.denoiser is not None, "denoiser": pipeline.denoiser}
        rows += run_bench(views, {label: factory}, [_preset_of(pipeline, str(path))], **options)
    return rows
