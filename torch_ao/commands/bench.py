"""``torch-ao bench``: error against run time of methods x presets x scenes, with a recommendation per scene."""
from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import torch

from ..bench import DEFAULT, DEFAULT_TOLERANCE, QUICK, SIZE_OPTIONS
from ..cli import CommandError
from ..methods import METHODS, PRESETS, get_method
from ..methods.common import split_preset
from ..resolution import RESOLUTIONS
from ..options import Option
from ..reference import SCENES
from ..views import default_cache_dir
from ..io import check_output_path
from .args import parse_device
from .inputs import add_input_flags, flag_errors, input_options
from .options_cli import add_options, add_progress, flag, given, method_kwargs, method_options


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


#: The flags of ``torch-ao bench`` that are neither sweep sizes (:data:`~torch_ao.bench.SIZE_OPTIONS`) nor
#: method options.
OPTIONS = (
    Option("quick", False, f"a small sweep that finishes in minutes on a 2-core CPU: scenes {','.join(QUICK.scenes)}, "
           f"presets {','.join(QUICK.presets)}, {QUICK.width}x{QUICK.height}, {QUICK.spp} spp, {QUICK.repeats} "
           "repeats (the size flags override it)", bool),
    Option("max_distance", 1.0, "reference AO ray length R of the built-in scenes", float, unit="world units",
           minimum=0.0, open_minimum=True),
    Option("radius", None, "the methods' radius; when not given, each reference's max distance (1 where it is "
           "infinite)", float, unit="world units", minimum=0.0, open_minimum=True),
    Option("denoise", True, "also time and measure every method followed by the denoiser", bool),
    Option("backward", True, "also time forward+backward (in the mode fitting uses)", bool),
    Option("background", True, "also time a full, a half-background and an all-background frame", bool),
    Option("tolerance", DEFAULT_TOLERANCE, "recommendation: allowed MAE above the best of a scene", float,
           unit="visibility (MAE)", minimum=0.0),
    Option("cache", None, f"folder of cached references; when not given, $TORCH_AO_CACHE, else "
           f"$XDG_CACHE_HOME/torch_ao, else ~/.cache/torch_ao (here: {default_cache_dir()})", str),
    Option("out", "bench", "output folder (bench.csv, bench.md, report.json, plots)", str),
    Option("plots", True, "write the PNG plots of error against run time", bool),
    Option("device", "cpu", "torch device the methods run on, e.g. cpu or cuda", str),
    Option("threads", None, "torch CPU threads; when not given, torch's default", int, minimum=1),
    Option("seed", 0, "sampling seed of the reference renders", int, minimum=0),
)

#: Method arguments the sweep sets itself (per preset and reference), so they are not method flags here.
SWEPT = ("preset", "slices", "steps", "radius", "seed", "mode")


def _method_classes() -> dict:
    return {m: get_method(m) for m in METHODS}


def register(sub) -> None:
    p = sub.add_parser(
        "bench",
        help="error against run time of methods x presets x scenes (CSV, markdown, plots, recommendation)",
        description="Sweep methods x presets over built-in scenes (references ray-traced once and cached) or "
        "reference files, with and without the denoiser; time forward and forward+backward (median after "
        "warm-up) and measure MAE/RMSE/PSNR/SSIM against the reference on valid pixels. Writes bench.csv, "
        "bench.md, report.json (with the per-scene recommendation that `torch-ao ao --auto --report` applies) "
        "and plots of error against run time into --out.",
    )
    p.add_argument("--methods", type=_csv, metavar="A,B,...",
                   help=f"comma-separated methods, some of: {', '.join(METHODS)}. Default: all")
    p.add_argument("--presets", type=_csv, metavar="A,B,...",
                   help=f"comma-separated presets, some of: {', '.join(PRESETS)}, each optionally @{'/@'.join(RESOLUTIONS)} "
                   f"for the walk's resolution (e.g. high,high@half). Default: {','.join(DEFAULT.presets)}")
    p.add_argument("--scenes", type=_csv, metavar="A,B,...",
                   help=f"comma-separated built-in scenes, some of: {', '.join(SCENES)}, or sets of them "
                   "(procedural, meshes, fit, heldout, benchmark). "
                   f"Default: {','.join(DEFAULT.scenes)}, none when --reference is given")
    p.add_argument("--reference", nargs="+", action="extend", default=[], metavar="FILE.npz",
                   help="reference files (G-buffer + 'ao', e.g. from `torch-ao render`), named by file stem. Default: none")
    p.add_argument("--params", metavar="JSON", action="append",
                   help="per-method constructor arguments, e.g. fitted values: a `torch-ao fit` params.json, or a "
                   "JSON file or string {\"bitmask\": {\"thickness\": 0.3}} (repeatable; wins over method flags). Default: none")
    p.add_argument("--fitted", nargs="+", action="extend", default=[], metavar="PARAMS.json",
                   help="fitted pipelines (`torch-ao fit` params.json files) added as rows, each at its own preset, "
                   "radius, parameters and denoiser. Default: none")
    add_options(p, {o.name: o for o in OPTIONS}, given_only=False)
    add_progress(p)
    add_input_flags(p, "the --reference files")
    sizes = p.add_argument_group("sweep size (defaults as below, or those of --quick)")
    add_options(sizes, {o.name: o for o in SIZE_OPTIONS})
    group = p.add_argument_group("method options (each applies to the swept methods that take it; "
                                 f"{', '.join(SWEPT)} are set by the sweep)")
    names = add_options(group, method_options(_method_classes(), exclude=SWEPT))
    p.set_defaults(func=run, method_flags=names)


def _params(texts: list[str] | None) -> dict:
    """``{method: {parameter: value}}`` from JSON files or strings, either in that form or a
    ``torch-ao fit`` ``params.json`` (``{"method": ..., "parameters": {...}}``)."""
    out: dict = {}
    for text in texts or []:
        path = Path(text)
        try:
            data = json.loads(path.read_text(encoding="utf-8") if path.is_file() else text)
        except json.JSONDecodeError as err:
            raise CommandError(f"--params: {text!r} is not a JSON file or string ({err})") from None
        if isinstance(data, dict) and "method" in data and isinstance(data.get("parameters"), dict):
            data = {data["method"]: data["parameters"]}
        if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
            raise CommandError("--params: expected {method: {parameter: value}} or a `torch-ao fit` params.json")
        for method, values in data.items():
            out.setdefault(method, {}).update(values)
    return out


def _method_params(methods: dict, flags: dict, params: dict) -> dict:
    """Per method: the method flags it takes, then its ``--params`` (which win)."""
    for name in flags:
        if not any(name in cls.options() for cls in methods.values()):
            raise CommandError(f"{flag(name)}: not an option of any swept method ({', '.join(methods)})")
    out = {m: {**method_kwargs(m, cls, flags, strict=False), **params.get(m, {})} for m, cls in methods.items()}
    return {m: p for m, p in out.items() if p} | {m: p for m, p in params.items() if m not in out}


def _needs_backface(fitted) -> bool:
    """Whether any ``--fitted`` pipeline reads the G-buffer's back-face layer (its thickness model)."""
    def model(path):
        try:
            return json.loads(Path(path).read_text(encoding="utf-8")).get("options", {}).get("thickness_model")
        except (OSError, ValueError, AttributeError):
            return None  # unreadable files are refused, with their names, where the rows are built

    return any(model(f) == "backface" for f in fitted)


def run(args: argparse.Namespace) -> int:
    from ..bench import available_methods, background_scaling, environment, load_report, run_bench, write_report
    from ..views import load_bench_views

    device = parse_device(args.device)
    check_output_path("--out", args.out, folder=True)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    base = QUICK if args.quick else DEFAULT
    scenes = args.scenes if args.scenes is not None else ([] if args.reference else list(base.scenes))
    presets = args.presets or list(base.presets)
    for preset in presets:
        try:
            split_preset(preset)
        except ValueError as err:
            raise CommandError(f"--presets: {err}") from None
    if scenes:
        from ..datasets import parse_scenes

        try:
            scenes = parse_scenes(",".join(scenes))
        except ValueError as err:
            raise CommandError(str(err)) from None
    methods = available_methods(args.methods)
    if not methods:
        raise CommandError("--methods: none of the requested methods is available yet")
    params = _method_params(methods, given(args, args.method_flags), _params(args.params))
    height, width, spp, repeats, warmup = (getattr(base, o.name) if getattr(args, o.name) is None else getattr(args, o.name)
                                           for o in SIZE_OPTIONS)
    progress = args.progress
    reading = input_options(args, args.reference, "--reference files")
    start = time.perf_counter()
    with flag_errors():
        views = load_bench_views(scenes, args.reference, height=height, width=width, spp=spp,
                                 max_distance=args.max_distance, seed=args.seed, cache_dir=args.cache, device=device,
                                 progress=progress, backface=_needs_backface(args.fitted), reading=reading)
    rows = run_bench(views, methods, presets, denoise=args.denoise, backward=args.backward,
                     repeats=repeats, warmup=warmup, device=device, radius=args.radius, params=params,
                     progress=progress)
    if args.fitted:
        from ..fitted import bench_rows

        rows += bench_rows(args.fitted, views, backward=args.backward, repeats=repeats, warmup=warmup, device=device,
                           progress=progress)
    background = None
    if args.background:
        background = background_scaling(methods, "high", height=192, width=256, repeats=max(5, repeats),
                                        warmup=warmup, device=device, radius=args.radius or args.max_distance,
                                        progress=progress)
    env = environment(device)
    command = "torch-ao " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv and "torch-ao" in sys.argv[0] else None
    settings = {"scenes": scenes, "references": [str(p) for p in args.reference], "presets": presets,
                "methods": list(methods), "height": height, "width": width, "spp": spp,
                "max_distance": args.max_distance, "radius": args.radius, "repeats": repeats, "warmup": warmup,
                "denoise": args.denoise, "backward": args.backward, "params": params,
                "seconds": None}
    settings["seconds"] = round(time.perf_counter() - start, 1)
    files = write_report(args.out, rows, tolerance=args.tolerance, background=background, env=env,
                         command=command, settings=settings, plots=args.plots)
    rec = load_report(files["json"])["recommendations"]
    for scene, r in rec.items():
        print(f"{scene}: {r['method']} {r['preset']} (MAE {r['mae']:.4f}, {r['forward_ms']:.1f} ms; "
              f"best {r['best']['method']} {r['best']['preset']} MAE {r['best']['mae']:.4f})")
    print(f"{len(rows)} runs in {settings['seconds']:.0f} s on {env['device_name']} ({env['threads']} threads) -> "
          f"{Path(args.out) / 'bench.md'}")
    return 0
