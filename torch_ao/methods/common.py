"""What the methods share: the sampling configuration, option parsing, parameters, the functional twin.

Every option of a method is described once, as a :class:`~torch_ao.options.Option`: the method's own
in its ``OPTIONS``, the walk's in :attr:`Sampling.OPTIONS` (a method lists in ``SAMPLING`` which of them
it takes and may change their defaults), the memory and normals controls in :data:`MODULE_OPTIONS`.
``cls.options()`` merges them; the constructor validates with them, ``inspect.signature(cls)`` lists
them (the CLI builds its flags from them), and fitted options become parameters.
"""
from __future__ import annotations

import dataclasses
import functools
import inspect
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import nn

from ..options import Option, options_by_name
from ..resolution import RESOLUTIONS
from ..walk import AZIMUTHS, BORDER_MODES, FETCH_MODES, NOISES, SLICE_SAMPLINGS, SlicePattern

__all__ = ["PRESETS", "DEFAULT_PRESET", "PRESET_NAMES", "split_preset", "Sampling", "MODULE_OPTIONS", "RADIUS", "resolve_preset", "make_parameter",
           "register_parameters", "functional_twin", "declare_signature"]

#: Quality presets shared by every horizon/bitmask method: (slices, steps per side).
PRESETS: dict[str, tuple[int, int]] = {
    "low": (1, 2),
    "medium": (2, 2),
    "high": (3, 3),
    # high's cost in longer steps: for thin occluders steps matter more than slices (GTAO scores best at high's 3 x 3)
    "high_steps": (2, 5),
    # longer steps still, 1.6x high's fetches (3 x 5, as many fetches in more slices, loses 0.3 dB: docs/accuracy.md)
    "very_high": (2, 7),
    # one more step a side, 1.8x high's fetches: the default torch-ao fit pipeline's sampling (with staggered steps and
    # screen-spaced slices), the first split over 30 dB leave one scene out on the fit set (docs/accuracy.md)
    "very_high_steps": (2, 8),
    "ultra": (9, 3),
    "extreme": (16, 8),
    "reference": (32, 32),
}
#: The preset every command and module uses when given neither a preset nor counts: ``torch-ao ao``,
#: ``bench``, ``fit`` (and its report's default-parameter rows) and the modules themselves.
DEFAULT_PRESET = "high"

#: Largest ``slices`` and ``steps`` (per side) a method takes: 2x and 8x the ``reference`` preset's 32 x 32,
#: already far past where more samples change the result; larger counts only run for minutes or
#: exhaust memory (the walk keeps one side's steps at once, :func:`torch_ao.limits.walk_bytes`).
MAX_SLICES, MAX_STEPS = 64, 256

#: Every preset name: a quality, optionally with the resolution its walk runs at (``"high@half"``).
PRESET_NAMES: tuple[str, ...] = tuple(PRESETS) + tuple(f"{p}@{r}" for p in PRESETS for r in RESOLUTIONS)


def split_preset(preset: str) -> tuple[str, str | None]:
    """``(quality, resolution)`` of a preset name: ``"high@half"`` -> ``("high", "half")``, ``"high"`` ->
    ``("high", None)`` (``ValueError`` naming ``preset`` for an unknown one)."""
    key = str(preset).lower()
    quality, _, resolution = key.partition("@")
    if quality not in PRESETS or (resolution and resolution not in RESOLUTIONS):
        raise ValueError(f"preset: expected one of {', '.join(PRESETS)}, optionally with @{'/@'.join(RESOLUTIONS)} "
                         f"(e.g. high@half), got {preset!r}")
    return quality, resolution or None


#: The world-space radius most methods search (a method that samples in pixels does not list it).
RADIUS = Option("radius", 1.0, "Search radius: samples farther than this from the pixel do not occlude",
                unit="world units", minimum=0.0, open_minimum=True, fitted=True)

#: Options of every module, outside the walk: normals reconstruction, memory, trainability.
MODULE_OPTIONS = (
    Option("normals", "improved", "Normal reconstruction used when the G-buffer has no normals "
           "(improved: the smaller-discontinuity rule; kornia: central differences)", kind=str,
           choices=("improved", "kornia")),
    Option("chunk_size", None, "Walk at most this many pixels at a time to bound memory (default: all at once, "
           "or the method's automatic choice)", kind=int, unit="pixels", minimum=1),
    Option("recompute", False, "With autograd, recompute each chunk's walk in backward instead of keeping its "
           "graph (with chunk_size: forward+backward memory of one chunk)", kind=bool),
    Option("trainable", True, "Register the fitted options as nn.Parameters (False: frozen buffers)", kind=bool),
    Option("resolution", None, "Resolution of the walk: full, half or quarter (the G-buffer decimated 2x2 or "
           "4x4 to one texel per block, the walk on the smaller frame, a depth-aware joint bilateral upsample: "
           "about 4x or 16x cheaper, softer at edges and blind to occluders thinner than the block); default: a "
           "preset's @ suffix, else full (the walk as the method defines it)", kind=str, choices=tuple(RESOLUTIONS)),
    Option("backend", "auto", "Where the walk runs: auto (a fused kernel when one covers the call, else tensor "
           "ops), kernel (the kernel; an error for a call it does not cover), torch (tensor ops)", kind=str,
           choices=("auto", "kernel", "torch")),
)


def resolve_preset(preset: str | None, slices: int | None, steps: int | None, default: tuple[int, int]) -> tuple[int, int]:
    """Slices and steps from a preset name (its quality; see :func:`split_preset`) and/or explicit counts
    (explicit counts win)."""
    if preset is not None:
        default = PRESETS[split_preset(preset)[0]]
    return (default[0] if slices is None else slices, default[1] if steps is None else steps)


@dataclass(frozen=True)
class Sampling:
    """Where the walk goes, validated on construction (see :class:`~torch_ao.walk.SlicePattern`).

    Attributes: ``slices``, ``steps`` (counts), ``step_power``, ``min_step_px`` (pixels), ``jitter``,
    ``seed``, ``noise``, ``slice_sampling``, ``stagger``, ``fetch``, ``border``, ``azimuth``; :attr:`OPTIONS` says what each does and why its default.
    """

    slices: int = PRESETS[DEFAULT_PRESET][0]
    steps: int = PRESETS[DEFAULT_PRESET][1]
    step_power: float = 1.0
    min_step_px: float = 1.0
    jitter: bool = True
    seed: int = 0
    noise: str = "ign"
    slice_sampling: str = "uniform"
    stagger: bool = False
    fetch: str = "bilinear"
    border: str = "drop"
    azimuth: str = "view"

    OPTIONS: ClassVar[tuple[Option, ...]] = (
        Option("preset", None, f"Quality preset setting slices x steps: {', '.join(f'{k} ({a}x{b})' for k, (a, b) in PRESETS.items())}, "
               f"optionally @{'/@'.join(RESOLUTIONS)} for the walk's resolution, e.g. high@half "
               "(slices/steps/resolution given explicitly win; default: the method's own counts)", kind=str,
               choices=PRESET_NAMES),
        Option("slices", None, "Directions per pixel (default: from preset, else the method's); at most "
               "MAX_SLICES, twice the reference preset's: time grows linearly with it", kind=int, minimum=1,
               maximum=MAX_SLICES),
        Option("steps", None, "Samples per side of each direction (default: from preset, else the method's); at "
               "most MAX_STEPS, eight times the reference preset's: time and memory grow linearly with it",
               kind=int, minimum=1, maximum=MAX_STEPS),
        Option("step_power", 1.0, "Exponent of the step spacing: 1 evenly spaced, 2 denser near the pixel "
               "(where occluders matter most)", minimum=0.0, open_minimum=True),
        Option("min_step_px", 1.0, "Distance of the first step at least; 1 keeps it off the pixel's own texel",
               unit="pixels", minimum=0.0),
        Option("jitter", True, "Rotate the directions and offset the steps per pixel by noise (see noise; "
               "banding becomes noise that a denoiser removes)", kind=bool),
        Option("seed", 0, "Seed of the per-pixel noise (each seed is a new, reproducible pattern)", kind=int, minimum=0),
        Option("noise", "ign", "Per-pixel noise of the jitter: ign (interleaved gradient noise, tuned for a 3x3 "
               "window: the default) or hilbert_r2 (XeGTAO's R2 low-discrepancy sequence along a 64x64 Hilbert "
               "curve: the slice and step values decorrelated, well spread over any block of pixels)", kind=str,
               choices=NOISES),
        Option("slice_sampling", "uniform", "Slice directions: uniform around the view vector (the default), or "
               "projected_normal (drawn by the cosine-weighted density of the projected normal, GTAO's unoccluded "
               "slice integral, each slice weighted by 1/(pi p): the same limit, more slices where the normal's "
               "hemisphere has its measure; needs azimuth view and a half circle of slices)", kind=str,
               choices=SLICE_SAMPLINGS),
        Option("stagger", False, "Shift each half-slice's steps by 1/(2 slices) of a step, so that a pixel's slices "
               "sample 2 x slices x steps distinct distances instead of the same steps distances (each still "
               "uniformly jittered)", kind=bool),
        Option("fetch", "bilinear", "Depth fetch: nearest texel, perspective-correct bilinear (interpolates "
               "1/depth, so planes are reproduced exactly: the default), or edge_aware (bilinear inside a surface, "
               "the nearest texel across a depth edge: no skirts joining a near and a far surface)", kind=str,
               choices=FETCH_MODES),
        Option("border", "drop", "Samples off the image: drop them (they occlude nothing: the default, no "
               "smeared edge) or clamp them to the edge texel", kind=str, choices=BORDER_MODES),
        Option("azimuth", "view", "Direction spacing: evenly around the view vector (the slice integral is exact "
               "off-centre: the default) or evenly in screen angle (the shaders)", kind=str, choices=AZIMUTHS),
    )

    def __post_init__(self) -> None:
        spec = options_by_name(self.OPTIONS)
        for f in dataclasses.fields(self):
            spec[f.name].check(getattr(self, f.name))
        if self.slice_sampling != "uniform" and self.azimuth != "view":
            raise ValueError(f"slice_sampling: {self.slice_sampling!r} draws slices around the view vector: it needs "
                             f"azimuth='view' (got {self.azimuth!r})")

    @classmethod
    def from_values(cls, values: dict[str, Any], default_counts: tuple[int, int]) -> "Sampling":
        """The configuration of ``values`` (the names it lacks keep the dataclass defaults; ``preset``,
        ``slices`` and ``steps`` resolve against ``default_counts``)."""
        slices, steps = resolve_preset(values.get("preset"), values.get("slices"), values.get("steps"), default_counts)
        fields = {f.name: values[f.name] for f in dataclasses.fields(cls) if f.name in values and f.name not in ("slices", "steps")}
        return cls(slices=slices, steps=steps, **fields)

    def pattern(self, radius, pattern: type[SlicePattern] = SlicePattern, **extra) -> SlicePattern:
        """The walk this configuration describes with world ``radius``: a :class:`~torch_ao.walk.SlicePattern`
        (or the subclass ``pattern``, given the ``extra`` arguments it takes)."""
        return pattern(self.slices, self.steps, radius, step_power=self.step_power, min_step_px=self.min_step_px,
                       jitter=self.jitter, seed=self.seed, fetch=self.fetch, border=self.border, azimuth=self.azimuth,
                       noise=self.noise, slice_sampling=self.slice_sampling,
                       stagger=self.stagger, **extra)

    @classmethod
    def options_for(cls, names: tuple[str, ...] | None = None, **defaults) -> tuple[Option, ...]:
        """The configuration's options ``names`` (default all), with a method's own ``defaults``."""
        chosen = cls.OPTIONS if names is None else tuple(o for o in cls.OPTIONS if o.name in names)
        return tuple(dataclasses.replace(o, default=defaults[o.name]) if o.name in defaults else o for o in chosen)


def make_parameter(module: nn.Module, name: str, value, *, trainable: bool, minimum: float | None = None) -> None:
    """Register a float parameter (an ``nn.Parameter`` when ``trainable``, else a buffer).

    ``value`` may be a number or a tensor (a per-object table or a per-pixel map). Non-finite values
    and values below ``minimum`` raise a ``ValueError`` naming ``name``.
    """
    try:
        if isinstance(value, (bool, str)) or value is None:
            raise TypeError
        t = torch.as_tensor(value).detach().clone()
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{name}: expected a number or a tensor of numbers, got {value!r}"[:200]) from None
    if t.dtype == torch.bool or t.is_complex():
        raise ValueError(f"{name}: expected real numbers, got a {t.dtype} tensor")
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: expected finite values, got {t.tolist() if t.numel() < 8 else 'a tensor with non-finite entries'}")
    if minimum is not None and bool((t < minimum).any()):
        raise ValueError(f"{name}: expected values >= {minimum}, got {t.min().item()}")
    if trainable:
        setattr(module, name, nn.Parameter(t))
    else:
        module.register_buffer(name, t)


def register_parameters(module: nn.Module, options: dict[str, Option], values: dict[str, Any], names, *,
                        trainable: bool, frozen=()) -> None:
    """Register the scalar fitted options ``names`` (in that order) from ``values``: parameters when
    ``trainable`` and not in ``frozen`` (those the configuration does not use), else buffers; each value
    checked against its option's bounds (``ValueError`` naming it)."""
    for name in names:
        opt = options[name]
        make_parameter(module, name, values[name], trainable=trainable and name not in frozen)
        t = getattr(module, name)
        if t.dim() != 0:
            raise ValueError(f"{name}: expected a scalar, got shape {tuple(t.shape)}")
        opt.check(float(t.detach()))


#: The ``Shape:`` section of every method's module and functional docstring (appended to them).
METHOD_SHAPE = """
    Shape:
        - Input: a :class:`~torch_ao.GBuffer` of ``B`` views ``H x W``: ``depth`` ``(B, 1, H, W)`` (world units,
          positive along the view axis; ``inf``/``0``/``nan`` background), optional ``normals`` ``(B, 3, H, W)``
          (unit, view space), ``light`` ``(B, 3, H, W)`` (indirect light), ``mask``/``object_id`` ``(B, 1, H, W)``.
        - Output: :class:`~torch_ao.AOOutput`: ``visibility`` ``(B, 1, H, W)`` in [0, 1] (1 = unoccluded);
          ``indirect``, ``bent_normal``, ``ambient`` ``(B, 3, H, W)`` when asked for (``None`` otherwise).
        - dtype: the input's float32 or float64; float16/bfloat16 inputs are computed and returned in float32.
"""


def _with_shape(doc: str | None) -> str:
    doc = doc or ""
    return doc if "Shape:" in doc else doc.rstrip() + "\n" + METHOD_SHAPE


def declare_signature(cls=None, /, *, defaults: dict[str, Any] | None = None, extra: dict[str, Any] | None = None):
    """Class decorator: ``inspect.signature(cls)`` (and so ``help(cls)``) lists ``cls.options()`` as keyword-only
    arguments with their defaults (the constructor takes ``**options``; the CLI reads the signature).

    ``defaults`` replaces the default shown for some options (``None`` where the constructor resolves it per
    variant or per call); ``extra`` adds keyword arguments outside ``options()`` (Python objects no flag can
    give, e.g. a callable), ``{name: default}``, after them. Called as ``declare_signature(cls, ...)``."""
    if cls is None:
        return functools.partial(declare_signature, defaults=defaults, extra=extra)
    shown = {name: opt.default for name, opt in cls.options().items()} | dict(defaults or {}) | dict(extra or {})
    params = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default) for name, default in shown.items()]
    init = cls.__init__
    if "__init__" not in cls.__dict__:  # give the class its own constructor to carry the signature
        @functools.wraps(init)
        def init(self, **options):
            super(cls, self).__init__(**options)
        cls.__init__ = init
    cls.__init__.__signature__ = inspect.Signature([inspect.Parameter("self", inspect.Parameter.POSITIONAL_OR_KEYWORD)]
                                                   + params)
    cls.__doc__ = _with_shape(cls.__doc__)
    return cls


def functional_twin(cls, name: str):
    """The functional form of module ``cls``: ``twin(gbuffer, **options)`` builds ``cls`` once with its
    fitted options taken *as given* when they are tensors (not copied), so gradients flow to tensors the
    caller passes in, and returns its :class:`~torch_ao.methods.base.AOOutput`."""
    fitted = tuple(n for n, o in cls.options().items() if o.fitted)

    def twin(gbuffer, **options):
        tensors = {k: options[k] for k in fitted if isinstance(options.get(k), torch.Tensor)}
        init = {k: (v.detach() if isinstance(v, torch.Tensor) else v) for k, v in options.items()}
        module = cls(**{"trainable": False, **init})  # validates every option, the tensors' shapes too
        for key, value in tensors.items():  # the caller's tensors themselves, so their graph is kept
            setattr(module, key, value)
        return module(gbuffer)

    twin.__name__ = twin.__qualname__ = name
    twin.__doc__ = (f"Functional :class:`{cls.__name__}` ``(gbuffer, *, options...) -> AOOutput``: the keyword "
                    f"options of the module (listed in the signature, described by ``{cls.__name__}.options()``); "
                    f"{', '.join(fitted)} may be tensors (gradients flow to them).\n" + METHOD_SHAPE)
    keywords = [p.replace(default=False) if p.name == "trainable" else p
                for p in inspect.signature(cls).parameters.values()]
    twin.__signature__ = inspect.Signature(
        [inspect.Parameter("gbuffer", inspect.Parameter.POSITIONAL_OR_KEYWORD)] + keywords,
        return_annotation="AOOutput")
    return twin
