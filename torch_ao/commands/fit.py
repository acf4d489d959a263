"""``torch-ao fit``: fit an AO pipeline (method + denoiser) to ray-traced references (the main job).

With no arguments: render (or load from the cache) randomised views of the built-in train scenes
(:data:`~torch_ao.datasets.FIT_SCENES`: procedural scenes and real meshes), fit bitmask AO's parameters
(thickness and radius) followed by the denoiser on the training views, keep the parameters that are
best in hard mode, and compare on held-out views (other cameras of the train scenes, and the held-out
scenes :data:`~torch_ao.datasets.HELDOUT_SCENES` that fitting never sees), per view, the defaults,
the engine defaults (thickness 0.25, 0.5, 1.0), GTAO with default parameters and the fitted pipeline.

``--leave-one-out`` adds, for each of ``--scenes``, a fit on the other scenes scored on the one left out
(its held-out views): a score on scenes the fit has not seen, per scene and mean, in report.md.
"""
from __future__ import annotations

import argparse
import contextlib
import itertools
import math
import os
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from ..checks import check_finite_outputs
from ..cli import CommandError
from .. import distributed
from ..datasets import HOLDOUT_SEED, default_cache_dir, parse_scenes, reference_views, train_and_holdout_views
from ..fit import (LOSSES, CheckpointMismatch, FitConfig, checkpoint_settings_differences, evaluate, fit,
                   fittable_parameters, set_mode)
from ..fit_data import ViewFiles, reference_files, view_names
from ..fitted import THICKNESS_MODELS, FittedPipeline
from ..io import check_output_path, read_npz, write_text_atomic
from ..methods import DEFAULT_PRESET, get_method
from ..options import Option, options_by_name
from .ao import OPTIONS as AO_OPTIONS
from .args import parse_device
from .inputs import add_input_flags, flag_errors, input_options
from .options_cli import SwitchPair, add_option, add_progress
from .render import OPTIONS as RENDER_OPTIONS

#: Parameters in world units: their learning rate is ``--lr`` times R, so a fit moves them by the
#: same fraction of R whatever the scene's scale.
LENGTHS = ("radius", "thickness", "fade_distance")
#: Start values replacing a default where the default has no gradient (GTAO's falloff range 0 is a
#: hard cut: neither radius nor falloff has a gradient there).
NO_GRADIENT_START = {"falloff_range": 0.25}
BITMASK = ("bitmask", "ssilvb")
#: The fetch of a bitmask pipeline fitted without --fetch and --variant: the edge-aware one scored best of
#: the candidate pipelines on the fit set's training views (benchmarks/pipeline_candidates.py, docs/fitting.md)
BITMASK_FETCH = "edge_aware"
#: The preset of the default pipeline (bitmask, default variant, back-face thickness) fitted without --preset:
#: 2 slices x 8 steps, with DEFAULT_PIPELINE_SAMPLING the first over 30 dB leave one scene out on the fit set, at
#: 1.8x GTAO high's time (docs/accuracy.md)
DEFAULT_PIPELINE_PRESET = "very_high_steps"
#: The default pipeline's sampling, whatever its preset: each half-slice's steps shifted (a pixel's two slices sample
#: 32 distances instead of 8) and slices spaced evenly on screen; +0.18 dB leave one scene out at 2 x 7
DEFAULT_PIPELINE_SAMPLING = {"stagger": True, "azimuth": "screen"}
#: Smallest width and height of the built-in views (``--size``).
MIN_SIZE = 4
#: Flags that do not change the fit (where it writes, how it reports, the held-out views it is scored on
#: afterwards): every other flag is in the checkpoint's fingerprint, so a resumed fit is the same fit.
NOT_IN_CHECKPOINT = ("out", "restart", "cache", "progress", "holdout", "holdout_views", "holdout_scenes",
                     "leave_one_out")
#: Folder of the leave-one-out fits' checkpoints inside ``--out`` (one ``<scene>.pt`` each).
LEAVE_ONE_OUT = "leave_one_out"


def _method_option(method: str, name: str) -> Option:
    return get_method(method).options()[name]


#: The flags of ``torch-ao fit``: what each does, its unit, range and default (the flags' help). Defaults
#: that a :class:`~torch_ao.fit.FitConfig` field also has are read from it; the renderer's sampling
#: flags and ``torch-ao ao``'s method choice are reused with this command's defaults.
OPTIONS = (
    Option("reference", None, "your own G-buffers with an 'ao' reference (and 'max_distance', the method's radius "
           "R): files, folders (their .npz and .exr files), glob patterns or .txt lists of paths, read as each "
           "step uses them; when not given, randomised views of the built-in --scenes", str),
    Option("holdout", None, "held-out references (same forms as --reference); when not given, the last third of "
           "--reference", str),
    replace(options_by_name(AO_OPTIONS)["method"], default="bitmask", help="method to fit"),
    Option("variant", None, "the method's variant; when not given, the method's default", str),
    Option("params", None, "comma-separated parameters to fit jointly, e.g. thickness,radius (thickness_growth, for "
           "a bitmask method: the thickness grows as 1 + g |sample - pixel|, from g = 0); when not given, every "
           "float parameter the method and variant use", str),
    Option("thickness", None, "thickness model of a bitmask method (torch_ao.thickness): one scalar; one per "
           "object id (a table over the views' ids); linear in depth (thickness + thickness_slope * depth); the "
           "back-face layer (thickness_scale * (backface_depth - depth) + thickness: the built-in views are rendered "
           "with it, --reference files must hold backface_depth); when not given, backface for bitmask where every view "
           "holds a back-face layer (it scores best on the fit set, docs/fitting.md), else scalar", str,
           choices=tuple(THICKNESS_MODELS)),
    Option("init", None, "start values, e.g. thickness=0.5,radius=1.2 (lengths in world units; a bare number is the "
           "thickness); when not given, the method's defaults", str),
    replace(_method_option("bitmask", "preset"), default=None, help="quality preset of the fitted method (the report's "
            f"GTAO and engine-default rows run at it too); when not given, {DEFAULT_PRESET}, or {DEFAULT_PIPELINE_PRESET} "
            "for the default pipeline (a bitmask method's default variant with the back-face thickness model: longer "
            "steps, staggered and along screen directions, over 30 dB leave one scene out on the fit set within 2x "
            f"GTAO's time; its rows of other methods stay at {DEFAULT_PRESET})"),
    replace(_method_option("bitmask", "weighting"), default="cosine", help="sector weighting of bitmask methods "
            "(cosine matches the cosine-weighted reference)"),
    replace(_method_option("bitmask", "fetch"), default=None, help="depth fetch of the fitted method's walk (see "
            f"`torch-ao ao --help`); when not given, {BITMASK_FETCH} for a bitmask method's default variant (the "
            "best on the fit set), else the method's default"),
    replace(_method_option("bitmask", "stagger"), default=None, help="shift each half-slice's steps by 1/(2 slices) "
            "of a step (--no-stagger: the method's own steps); when not given, on for the default pipeline, else off"),
    replace(_method_option("bitmask", "azimuth"), default=None, help="slice directions spaced evenly around the view "
            "vector (view) or on screen (screen); when not given, screen for the default pipeline, else view"),
    Option("no_denoise", False, "fit and score the method alone, without the denoiser", bool),
    Option("radius", None, "the method's radius R; when not given, the references' max_distance", float,
           unit="world units", minimum=0.0, open_minimum=True),
    Option("length_unit", "world units", "the unit of the G-buffers' lengths (e.g. m, cm), recorded in params.json as "
           "the unit of its lengths (`ao --fitted --scale` and `export --scale` convert to another)", str),
    Option("scenes", "fit", "comma-separated built-in scenes to fit on (without --reference), or sets of them: "
           "procedural, meshes (assimp-testmodels), fit (both), heldout, benchmark", str),
    Option("holdout_scenes", "heldout", "built-in scenes that are only scored, never fitted on (same forms as "
           "--scenes; 'none' for none; scenes also in --scenes are left out)", str),
    Option("leave_one_out", False, "also fit once per --scenes scene on the others and score it on the one left out "
           "(report.md: held-out PSNR per scene and mean)", bool),
    Option("train_views", 2, "randomised training views per scene", int, minimum=1),
    Option("holdout_views", 1, "held-out views per scene (seeds 1000, 1001, ...; never trained on)", int, minimum=1),
    Option("size", "160x96", f"render size WxH of the built-in views (at least {MIN_SIZE}x{MIN_SIZE})", str,
           unit="pixels"),
    options_by_name(RENDER_OPTIONS)["spp"],
    replace(options_by_name(RENDER_OPTIONS)["max_distance"], default=1.0,
            help="reference AO ray length R of the built-in views (finite)"),
    Option("steps", 60, "optimizer steps; a fit still improving at the last step (its best hard-mode score the "
           "latest, or --hard-patience not run out) goes on, up to --max-steps", int, minimum=0),
    Option("plateau", 0.01, "with --hard-patience, stop only once the soft loss has plateaued too: its mean over the "
           "last --hard-every steps less than this fraction below the mean over the ones before (0 = hard scores alone)",
           float, minimum=0.0),
    Option("max_steps", 300, "largest number of steps a fit still improving at --steps may take (0 = --steps)", int,
           minimum=0),
    Option("lr", FitConfig.lr, "Adam learning rate (times R for parameters in world units)", float, minimum=0.0,
           open_minimum=True),
    Option("hard_every", FitConfig.hard_every, "score the parameters in hard mode every N steps and keep the best "
           "(0 = keep the best soft-mode loss)", int, unit="steps", minimum=0),
    Option("hard_patience", 2, "stop once this many hard-mode scores in a row have not improved on the best "
           "(0 = run all --steps)", int, minimum=0),
    Option("batch_views", FitConfig.batch_views, "training views per step (0 = all)", int, minimum=0),
    Option("loss", FitConfig.loss, "loss against the reference: l1 or mse per pixel, or psnr (each view's 10 log10 MSE, so views count in dB as the report averages them)", str, choices=LOSSES),
    Option("seed", FitConfig.seed, "seed of the fit's randomness (view batches, jitter)", int, minimum=0),
    Option("cache", None, f"reference cache folder; when not given, {default_cache_dir()}", str),
    Option("out", "fit-out", "output folder (params.json, report.md, comparison.png, checkpoint.pt)", str),
    Option("restart", False, "discard --out's checkpoint.pt and fit from the start (else a run with the same settings "
           "resumes it, and one with other settings is refused)", bool),
    Option("device", "cpu", "torch device of the fit and of the reference renders, e.g. cpu or cuda", str),
)

#: Flags whose form an Option cannot say: argparse keywords replacing the option's own.
_FORMS = {
    "reference": dict(nargs="+", metavar="FILE|DIR|GLOB|LIST.txt"),
    "holdout": dict(nargs="+", metavar="FILE|DIR|GLOB|LIST.txt"),
    "stagger": dict(action=SwitchPair),  # (unset: the pipeline's own choice)
}


def register(sub) -> None:
    p = sub.add_parser(
        "fit",
        help="fit an AO pipeline's parameters (method + denoiser) to ray-traced references",
        description="Fit a method's float parameters by gradient descent against ray-traced reference AO, "
        "scoring the pipeline that ships (method in hard mode + denoiser), then compare on held-out views. "
        "Without --reference, uses randomised views of the built-in scenes (rendered once, then cached). "
        "Re-running the same command resumes an interrupted fit; one with other settings is refused while --out holds "
        "the first one's checkpoint (give another --out, or --restart).",
    )
    for opt in OPTIONS:
        add_option(p, opt.name, opt, given_only=False, switch=True, **_FORMS.get(opt.name, {}))
    add_progress(p)
    add_input_flags(p, "the --reference and --holdout files")
    p.set_defaults(func=run)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise CommandError(f"--size: expected WxH such as 160x96, got {text!r}") from None
    if w < MIN_SIZE or h < MIN_SIZE:
        raise CommandError(f"--size: expected at least {MIN_SIZE}x{MIN_SIZE}, got {text!r}")
    return w, h


def reference_radius(paths, override: float | None) -> float:
    """R of reference files: their common ``max_distance``; files that disagree are refused (named),
    ``override`` wins with a warning when it differs. Under ``torchrun`` each rank reads its shard of the files."""
    read = {}
    for part in distributed.gather_objects(_radii(distributed.shard(list(paths)))):
        read.update(part)
    found = {str(p): read[str(p)] for p in paths if str(p) in read}
    values = sorted(set(found.values()))
    if override is not None:
        if not (math.isfinite(override) and override > 0):
            raise CommandError(f"--radius: expected a finite value > 0, got {override}")
        if values and values != [float(np.float32(override))]:
            warnings.warn(f"--radius {override:g} overrides the references' max_distance "
                          f"({', '.join(f'{v:g}' for v in values)}): the method fits a different problem than the files hold",
                          stacklevel=2)
        return override
    if len(values) > 1:
        groups = {v: [p for p, x in found.items() if x == v] for v in values}
        detail = "; ".join(f"R={v:g}: {', '.join(ps)}" for v, ps in groups.items())
        raise CommandError(f"--reference: the files disagree on max_distance ({detail}); fit them separately or give --radius")
    missing = [str(p) for p in paths if str(p) not in found]
    if not values:
        raise CommandError(f"--reference: no finite max_distance in {', '.join(missing)}; give the method's radius with --radius")
    if missing:
        raise CommandError(f"--reference: {', '.join(missing)} has no finite max_distance (the others have R={values[0]:g}); "
                           "give --radius")
    return values[0]


def _radii(paths) -> dict[str, float]:
    """``{path: max_distance}`` of the files holding a finite one > 0, at float32 (files store float32 or float64)."""
    found = {}
    for path in paths:
        md = read_npz(path).get("max_distance")
        if md is not None and md.size == 1 and math.isfinite(float(md)) and float(md) > 0:
            found[str(path)] = float(np.float32(md))
    return found


def _check_files(sources, backface: bool) -> list[str]:
    """Read each file of the view sequences ``sources`` once (each rank its shard under ``torchrun``), so
    that a bad one is named before the fit starts, one at a time (memory does not grow with their number);
    returns the names of the views without a ``backface_depth`` layer (with ``backface``, ``CommandError``
    naming them)."""
    missing = []
    for views in sources:
        for i in distributed.shard(list(range(len(views)))):
            view = views[i]
            if view.gbuffer.backface_depth is None:
                missing.append(view.name)
            del view  # (before the next read)
    missing = [name for part in distributed.gather_objects(missing) for name in part]
    if backface and missing:
        raise CommandError(f"--thickness backface: {', '.join(missing)} has no backface_depth layer; render it with "
                           "`torch-ao render --backface` (or choose another --thickness)")
    return missing


def _chosen_thickness(method: str, missing: list[str]) -> str:
    """``--thickness`` when not given: ``backface`` for bitmask AO whose views all hold a back-face layer
    (``missing`` names those that do not), else ``scalar`` (SSILVB too: the choice was measured for AO alone);
    says which, and why, when it matters."""
    if method != "bitmask":
        return "scalar"
    if missing:
        print(f"note: --thickness scalar: {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''} has no "
              "backface_depth layer (the back-face model, which scores best on the built-in fit set, needs it in "
              "every view: `torch-ao render --backface`, or your engine's front-face-culled depth pass)")
        return "scalar"
    return "backface"


def _default_pipeline(args) -> bool:
    """Whether the flags choose the default pipeline: bitmask AO, its default variant, the back-face thickness."""
    return args.method == "bitmask" and args.variant is None and args.thickness == "backface"


def _chosen_preset(args) -> str:
    """``--preset`` when not given: :data:`DEFAULT_PIPELINE_PRESET` for the default pipeline, else the default preset."""
    return DEFAULT_PIPELINE_PRESET if _default_pipeline(args) else DEFAULT_PRESET


def _views(args) -> tuple[list, list, float]:
    device = torch.device(args.device)
    reading = input_options(args, args.reference, "--reference files")
    if args.reference:
        try:
            files = reference_files(args.reference, "--reference")
            held_files = reference_files(args.holdout, "--holdout") if args.holdout else None
        except ValueError as err:
            raise CommandError(str(err)) from None
        train = ViewFiles(files, device=device, reading=reading)
        held = ViewFiles(held_files, device=device, reading=reading) if held_files else None
        with flag_errors():
            missing = _check_files([train, held or []], args.thickness == "backface")
        if args.thickness is None:
            args.thickness = _chosen_thickness(args.method, missing)
        radius = reference_radius([*files, *(held_files or [])], args.radius)
        if held is not None:
            return train, held, radius
        if len(train) == 1:
            print("note: one reference file; held-out scores are on the training view itself")
            return train, train, radius
        n_hold = max(1, len(train) // 3)
        return train[:-n_hold], train[-n_hold:], radius
    scenes, held_scenes = _scene_names(args)
    w, h = _size(args.size)
    if args.thickness is None:
        args.thickness = _chosen_thickness(args.method, [])  # (the built-in views are rendered with the layer)
    common = dict(height=h, width=w, spp=args.spp, max_distance=args.max_distance, cache_dir=args.cache,
                  progress=args.progress, device=device, backface=args.thickness == "backface")
    print(f"references: {len(scenes)} scenes x ({args.train_views} training + {args.holdout_views} held-out) views"
          + (f", {len(held_scenes)} held-out scenes x {args.holdout_views} views" if held_scenes else "")
          + f" at {w}x{h}, {args.spp} spp")
    train, held = train_and_holdout_views(scenes, args.train_views, args.holdout_views, **common)
    held += reference_views(held_scenes, list(range(HOLDOUT_SEED, HOLDOUT_SEED + args.holdout_views)), **common)
    radius = args.max_distance
    if args.radius is not None:
        radius = reference_radius([], args.radius)
        if radius != args.max_distance:
            warnings.warn(f"--radius {radius:g} overrides the references' max_distance {args.max_distance:g}", stacklevel=2)
    return train, held, radius


def _scene_names(args) -> tuple[list[str], list[str]]:
    """``--scenes`` and ``--holdout-scenes`` (less those in ``--scenes``), checked (:func:`~torch_ao.datasets.parse_scenes`)."""
    try:
        scenes = parse_scenes(args.scenes, "--scenes")
        text = args.holdout_scenes or "none"
        held = [] if text.strip() == "none" else parse_scenes(text, "--holdout-scenes")
    except ValueError as err:
        raise CommandError(str(err)) from None
    return scenes, [s for s in held if s not in scenes]


def scene_of(view) -> str:
    """The built-in scene of a view named ``<scene>/<layout>``."""
    return view.name.split("/", 1)[0]


def _init_values(text: str | None) -> dict[str, float]:
    if not text:
        return {}
    try:
        return {"thickness": float(text)}
    except ValueError:
        pass
    values = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        try:
            values[key.strip()] = float(value)
        except ValueError:
            raise CommandError(f"--init: expected name=value pairs such as thickness=0.5,radius=1.2, got {item!r}") from None
        if not sep or not key.strip():
            raise CommandError(f"--init: expected name=value pairs such as thickness=0.5,radius=1.2, got {item!r}")
    return values


def pipeline_options(args, radius: float, **values) -> dict:
    """Constructor options of the fitted method: preset, radius, variant, weighting (bitmask), fetch, ``values``."""
    options = {"preset": args.preset}
    if "radius" in get_method(args.method).options():  # (PSSAO walks in pixels)
        options["radius"] = radius
    if args.variant is not None:
        options["variant"] = args.variant
    if args.method in BITMASK:
        options["weighting"] = args.weighting
    if args.fetch is not None:
        options["fetch"] = args.fetch
    elif args.method in BITMASK and args.variant is None:
        options["fetch"] = BITMASK_FETCH
    for name, default in DEFAULT_PIPELINE_SAMPLING.items():  # (the flag, else the default pipeline's choice)
        value = getattr(args, name, None)
        value = default if value is None and _default_pipeline(args) else value
        if value is not None and name in get_method(args.method).options():
            options[name] = value
    options.update(values)
    return options


def thickness_options(args, views, init: dict[str, float]) -> dict:
    """Options choosing ``--thickness``'s model (none for ``scalar``, the historical form); for ``object``
    the ``(K,)`` table over the ids of ``views`` (``K`` = largest id + 1), every entry the initial
    thickness (``--init``'s, else the method's default). Refuses a model on a method without one."""
    if args.thickness == "scalar":
        return {}
    if args.method not in BITMASK:
        raise CommandError(f"--thickness {args.thickness}: {args.method} has no thickness model (only "
                           f"{', '.join(BITMASK)} do)")
    options = {"thickness_model": args.thickness}
    if args.thickness == "object":
        missing, K = [], 0
        for v in views:  # (one pass: views may be read from files as they come)
            if v.gbuffer.object_id is None:
                missing.append(v.name)
            else:
                K = max(K, int(v.gbuffer.object_id.max()) + 1)
        if missing:
            raise CommandError("--thickness object: " + ", ".join(missing) + " has no object_id layer")
        t = init.pop("thickness", _method_option(args.method, "thickness").default)
        options["thickness"] = torch.full((K,), float(t))
    return options


def run(args: argparse.Namespace) -> int:
    """The command; under ``torchrun`` each process is a rank of one data-parallel fit (only rank 0 prints
    and writes files)."""
    parse_device(args.device)
    started = distributed.init_from_environment(args.device)
    quiet = open(os.devnull, "w") if not distributed.is_main() else None  # noqa: SIM115
    completed = False
    try:
        with contextlib.redirect_stdout(quiet) if quiet else contextlib.nullcontext():
            code = _run(args)
        completed = True
        return code
    finally:
        if quiet:
            quiet.close()
        if started:
            distributed.finish(completed)


def _run(args: argparse.Namespace) -> int:
    init = _init_values(args.init)
    out = check_output_path("--out", args.out, folder=True)
    if args.leave_one_out and args.reference:
        raise CommandError("--leave-one-out: applies to the built-in --scenes, not to --reference files")
    checkpoint, settings = _checkpoint(args)
    args.device = str(distributed.rank_device(args.device))  # (after the settings: every rank's are the same)
    main = distributed.is_main()
    denoise = not args.no_denoise
    train, held, radius = _views(args)
    if args.leave_one_out and len({scene_of(v) for v in train}) < 2:
        raise CommandError("--leave-one-out: expected at least two --scenes (each is scored by a fit on the others)")
    model = thickness_options(args, itertools.chain(train, held), init)
    args.compare_preset = args.preset or DEFAULT_PRESET  # (the report's other methods: their best split of the cost)
    args.preset = args.preset or _chosen_preset(args)
    default, module, params = _pipelines(args, radius, model, init, denoise)
    denoised = " + denoiser" if denoise else ""
    ranks = f" on {distributed.world_size()} ranks" if distributed.is_distributed() else ""
    print(f"fitting {args.method}{denoised} {', '.join(params)} (R = {radius:g}) on {len(train)} views{ranks}, "
          f"evaluating on {len(held)} held-out views")

    cfg = FitConfig(params=params, steps=args.steps, lr=args.lr, loss=args.loss, batch_views=args.batch_views,
                    seed=args.seed, hard_every=args.hard_every, hard_patience=args.hard_patience,
                    plateau=args.plateau, max_steps=max(args.max_steps, args.steps), param_lr={k: args.lr * radius for k in params if k in LENGTHS})
    result = _fit(module, train, cfg, args, checkpoint, settings)
    check_finite_outputs(f"{args.method} fit", {f"fitted {k}": v for k, v in result.parameters.items()})

    rows = {}
    if args.method in BITMASK:
        for t in (0.25, 0.5, 1.0):
            engine = FittedPipeline(args.method, {"preset": args.compare_preset, "radius": radius, "thickness": t,
                                                  "weighting": "uniform"}, denoiser=denoise)
            rows[f"{args.method} thickness={t:g} (engine default: uniform sectors, {args.compare_preset}){denoised}"] = evaluate(engine, held, per_view=True, distributed=True)
    if args.method != "gtao":
        rows[f"gtao (default parameters, {args.compare_preset}){denoised}"] = evaluate(_gtao(args, radius, denoise), held, per_view=True, distributed=True)
    default_label = f"{args.method} default ({_describe(default, params)}){denoised}"
    rows[default_label] = before = evaluate(default, held, per_view=True, distributed=True)
    fitted_label = f"{args.method} fitted ({_describe(module, params)}){denoised}"
    rows[fitted_label] = after = evaluate(module, held, per_view=True, distributed=True)
    if denoise:
        rows[f"{args.method} fitted, without the denoiser"] = evaluate(module.method, held, per_view=True, distributed=True)
    train_start, train_best = _train_losses(result)

    table = _table(rows)
    scenes = _scene_table(held, rows[default_label], after,
                          next((r for k, r in rows.items() if k.startswith("gtao (default")), None))
    print(table)
    print()
    print(scenes)
    loo_md, loo = "", None
    if args.leave_one_out:
        loo = _leave_one_out(args, train, held, radius, model, init, denoise, cfg, settings, out)
        loo_md = "\n\n" + _leave_one_out_table(loo)
        print()
        print(loo_md.strip())
    if not main:
        return 0
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "report.md", f"Held-out views: {len(held)}; training views: {len(train)}; steps: "
                      f"{result.steps_done}; R = {radius:g}; hard mode{denoised}\n\n{_convergence(result, cfg)}\n\n"
                      f"{table}\n\nPer held-out view:\n\n{scenes}{loo_md}\n")
    module.save(out / "params.json", fitted=list(params), before=_summary(before), after=_summary(after),
                loss=args.loss, train_loss_start=train_start, train_loss_fitted=train_best,
                per_view={"default": before["views"], "fitted": after["views"]},
                comparison={k: _summary(v) for k, v in rows.items()}, steps_done=result.steps_done,
                best_step=result.best_step, converged=result.converged, step_limit=result.step_limit,
                fit_seconds=result.seconds, history=result.history,
                hard_history=result.hard_history, train_views=view_names(train), holdout_views=view_names(held),
                **({"leave_one_out": loo} if loo is not None else {}))
    _comparison_png(out / "comparison.png", held[0], default, module)
    print(f"wrote {out / 'params.json'}, {out / 'report.md'}, {out / 'comparison.png'}")
    return 0


def _pipelines(args, radius: float, model: dict, init: dict, denoise: bool):
    """``(default pipeline, pipeline to fit, fitted parameter names)``: the fitted one starts at the
    defaults, ``--init``'s values and :data:`NO_GRADIENT_START` where a default has no gradient."""
    default = FittedPipeline(args.method, pipeline_options(args, radius, **model), denoiser=denoise).to(args.device)
    # a default without a gradient is a buffer: fittable once moved to its start value
    moved = {k: v for k, v in NO_GRADIENT_START.items() if k in default.method.options()
             and float(getattr(default.method, k).detach()) == 0.0}
    # a thickness growth is fitted where --params or --init names it: the model grows one, from 0
    asked = set(init) | {p.strip() for p in (args.params or "").split(",")}
    if "thickness_growth" in asked and "thickness_growth" in default.method.options():
        moved["thickness_growth"] = 0.0
    fitted_method = FittedPipeline(args.method, pipeline_options(args, radius, **model, **moved), denoiser=denoise).method
    fittable = fittable_parameters(fitted_method)
    params = (tuple(p.strip() for p in args.params.split(",") if p.strip()) if args.params else fittable)
    if not params:
        raise CommandError(f"--params: {args.method} has no float parameter to fit with these options")
    for name in params:
        if name not in fittable:
            why = getattr(fitted_method, "no_gradient_options", {}).get(name)
            raise CommandError(f"--params: {name!r} is not a fitted parameter of {args.method}"
                               f"{' (' + args.variant + ')' if args.variant else ''}"
                               + (f" with these options: {why}" if why else f"; available: {', '.join(fittable)}"))
    start = {k: v for k, v in moved.items() if k in params}
    start.update(init)
    unknown = set(start) - set(params)
    if unknown:
        raise CommandError(f"--init: {', '.join(sorted(unknown))} not among the fitted parameters ({', '.join(params)})")
    module = FittedPipeline(args.method, pipeline_options(args, radius, **model, **start), denoiser=denoise,
                            length_unit=args.length_unit).to(args.device)
    return default, module, params


def _gtao(args, radius: float, denoise: bool) -> FittedPipeline:
    return FittedPipeline("gtao", {"preset": args.compare_preset, "radius": radius}, denoiser=denoise)


def _leave_one_out(args, train, held, radius, model, init, denoise, cfg, settings, out: Path) -> dict:
    """For each scene of ``train``: a fit on the other scenes' training views, scored (hard mode) on the
    scene's held-out views; each fold checkpointed in ``--out/leave_one_out/<scene>.pt`` (resumable as
    the main fit). Returns ``{scene: {"default", "fitted", "gtao": PSNR, "steps", "best_step",
    "converged", "parameters"}}``."""
    folds = {}
    scenes = list(dict.fromkeys(scene_of(v) for v in train))
    for i, scene in enumerate(scenes):
        others = [v for v in train if scene_of(v) != scene]
        mine = [v for v in held if scene_of(v) == scene]
        print(f"leave-one-out {i + 1}/{len(scenes)}: fitting without {scene} ({len(others)} views)")
        default, module, _ = _pipelines(args, radius, model, dict(init), denoise)
        path = out / LEAVE_ONE_OUT / f"{scene}.pt"
        if args.restart:
            path.unlink(missing_ok=True)
        fold_settings = {**settings, "left_out": scene}
        _refuse_checkpoint(args, path, fold_settings, checkpoint_settings_differences(path, fold_settings))
        result = _fit(module, others, cfg, args, path, fold_settings)
        check_finite_outputs(f"{args.method} fit without {scene}", {f"fitted {k}": v for k, v in result.parameters.items()})
        folds[scene] = {"default": evaluate(default, mine, distributed=True)["psnr"],
                        "fitted": evaluate(module, mine, distributed=True)["psnr"],
                        "gtao": evaluate(_gtao(args, radius, denoise), mine, distributed=True)["psnr"], "steps": result.steps_done,
                        "best_step": result.best_step, "converged": result.converged, "parameters": result.parameters}
    return folds


def _leave_one_out_table(folds: dict) -> str:
    """Markdown: per left-out scene, held-out PSNR of the default, of the fit on the other scenes and of
    default GTAO, the fit's steps and convergence, then the means."""
    lines = ["Leave one scene out (each row: fitted on the other scenes, scored on this scene's held-out views; "
             "PSNR in dB):", "",
             "| left-out scene | default PSNR | fitted on the others PSNR | gtao PSNR | steps (best) | converged |",
             "| --- | ---: | ---: | ---: | ---: | --- |"]
    for scene, f in folds.items():
        lines.append(f"| {scene} | {f['default']:.2f} | {f['fitted']:.2f} | {f['gtao']:.2f} | {f['steps']} "
                     f"({f['best_step']}) | {'yes' if f['converged'] else 'no'} |")
    mean = {k: float(np.mean([f[k] for f in folds.values()])) for k in ("default", "fitted", "gtao")}
    lines.append(f"| **mean** | {mean['default']:.2f} | {mean['fitted']:.2f} | {mean['gtao']:.2f} | | "
                 f"{sum(f['converged'] for f in folds.values())}/{len(folds)} |")
    return "\n".join(lines)


def _convergence(result, cfg: FitConfig) -> str:
    """One sentence: whether the fit converged, or stopped at its step limit (and where its best step is)."""
    if result.converged:
        return (f"Converged: yes (best hard-mode score at step {result.best_step}; {cfg.hard_patience} scores "
                f"without improvement after it and the soft loss within {cfg.plateau:g} of its previous mean; "
                f"{result.steps_done} steps).")
    where = "at the limit (more steps would likely improve it)" if result.best_at_limit else f"at step {result.best_step}"
    return (f"Converged: no (stopped at the step limit {result.step_limit}: --steps {cfg.steps}, --max-steps "
            f"{cfg.max_steps or cfg.steps}; best hard-mode score {where}).")


def _checkpoint(args: argparse.Namespace) -> tuple[Path, dict]:
    """``--out``'s checkpoint path (removed with ``--restart``) and the settings its fingerprint holds
    (every flag that changes the fit); a checkpoint of other settings is refused by name here, before
    any reference is rendered."""
    checkpoint = Path(args.out) / "checkpoint.pt"
    if args.restart:
        checkpoint.unlink(missing_ok=True)  # (the leave-one-out folds' are removed as each is reached)
    settings = {k: v for k, v in sorted(vars(args).items()) if k not in NOT_IN_CHECKPOINT and k not in ("command", "func")}
    _refuse_checkpoint(args, checkpoint, settings, checkpoint_settings_differences(checkpoint, settings))
    return checkpoint, settings


def _refuse_checkpoint(args, checkpoint: Path, settings: dict, differences) -> None:
    """``CommandError`` naming ``differences`` (flags, or what else differs) when there are any."""
    if not differences:
        return
    from .options_cli import flag

    what = {"module": "the method's start values", "views": "the training views' data",
            "torch_ao_version": "another torch_ao version"}
    named = [flag(k) if k in settings else what.get(k, k) for k in differences]
    raise CommandError(f"--out {args.out}: {checkpoint} belongs to a fit with other settings ({', '.join(named)}); "
                       "give another --out, or --restart to discard it")


def _fit(module, train, cfg: FitConfig, args: argparse.Namespace, checkpoint: Path, settings: dict):
    """:func:`~torch_ao.fit.fit` with ``--out``'s checkpoint, refused by name when it belongs to other settings."""
    try:
        return fit(module, train, cfg, checkpoint=checkpoint, progress=args.progress, settings=settings)
    except CheckpointMismatch as err:
        _refuse_checkpoint(args, checkpoint, settings, err.differences)


def _train_losses(result) -> tuple[float | None, float | None]:
    """Training loss (``--loss``, mean over the training views, hard mode) of the start and of the kept parameters,
    from the fit's own records (no extra forward passes)."""
    records = result.hard_history or result.history
    if not records:
        return None, None
    kept = next((r for r in records if r["step"] == result.best_step), records[-1])
    return records[0]["loss"], kept["loss"]


def _describe(pipeline: FittedPipeline, params) -> str:
    values = pipeline.parameter_values()
    parts = []
    for name in params:
        v = values[name] if name in values else getattr(pipeline.method, name)  # a default frozen at 0
        if v is None:  # (a thickness growth the default has not)
            parts.append(f"{name}=none")
            continue
        v = v.detach()
        parts.append(f"{name}={v.item():.3g}" if v.numel() == 1 else f"{name}=<{v.numel()} values>")
    if "weighting" in pipeline.options:
        parts.append(f"{pipeline.options['weighting']} sectors")
    if "thickness_model" in pipeline.options:
        parts.append(f"{pipeline.options['thickness_model']} thickness")
    method = pipeline.method
    if getattr(method, "slices", None) is not None:  # (the report's rows may run at other presets)
        parts.append(f"{pipeline.options.get('preset', 'explicit')} {method.slices}x{method.steps}")
    if pipeline.options.get("stagger"):
        parts.append("staggered steps")
    if pipeline.options.get("azimuth") == "screen":
        parts.append("screen slices")
    return ", ".join(parts)


def _summary(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if k != "views"}


def _table(rows) -> str:
    lines = ["| pipeline | MAE | RMSE | PSNR (dB) | SSIM | time (ms) |", "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for name, m in rows.items():
        lines.append(f"| {name} | {m['mae']:.4f} | {m['rmse']:.4f} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['seconds'] * 1000:.1f} |")
    return "\n".join(lines)


def _scene_table(views, default: dict, fitted: dict, gtao: dict | None) -> str:
    """Per held-out view: MAE and PSNR of the default and the fitted pipeline (and default GTAO)."""
    head = "| view | default MAE | fitted MAE | default PSNR | fitted PSNR |" + (" gtao MAE | gtao PSNR |" if gtao else "")
    lines = [head, "| --- |" + " ---: |" * (head.count("|") - 2)]
    for name in view_names(views):
        d, f = default["views"][name], fitted["views"][name]
        cells = [f"{d['mae']:.4f}", f"{f['mae']:.4f}", f"{d['psnr']:.2f}", f"{f['psnr']:.2f}"]
        if gtao:
            g = gtao["views"][name]
            cells += [f"{g['mae']:.4f}", f"{g['psnr']:.2f}"]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


@torch.no_grad()
def _comparison_png(path: Path, view, before_module, after_module) -> None:
    """reference | before | after | |after - reference| (x4) for one held-out view."""
    try:
        from ..images import save_png
    except ImportError:
        return
    set_mode(before_module, "hard")
    set_mode(after_module, "hard")
    before = before_module(view.gbuffer).visibility
    after = after_module(view.gbuffer).visibility
    err = ((after - view.reference).abs() * 4).clamp(0, 1)
    panel = torch.cat([view.reference[:1], before[:1], after[:1], err[:1]], dim=-1)
    try:
        save_png(path, panel)
    except ImportError as e:  # matplotlib missing: the numbers are still written
        print(f"note: no PNG ({e})")
