"""``torch-ao bench``: error against run time of methods x presets x scenes, with a recommendation per scene."""
from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

import torch

from ..cli import CommandError


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows defaults, except empty ones and those the help text already states."""

    def _get_help_string(self, action):
        if action.default in (None, False, []) or "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def register(sub) -> None:
    from ..bench import DEFAULT, QUICK
    from ..methods import METHODS, PRESETS

    p = sub.add_parser(
        "bench",
        help="error against run time of methods x presets x scenes (CSV, markdown, plots, recommendation)",
        description="Sweep methods x presets over built-in scenes (references ray-traced once and cached) or "
        "reference files, with and without the denoiser; time forward and forward+backward (median after "
        "warm-up) and measure MAE/RMSE/PSNR/SSIM against the reference on valid pixels. Writes bench.csv, "
        "bench.md, report.json (with the per-scene recommendation that `torch-ao ao --auto --report` applies) "
        "and plots of error against run time into --out.",
        formatter_class=_HelpFormatter,
    )
    p.add_argument("--quick", action="store_true",
                   help=f"a small sweep that finishes in minutes on a 2-core CPU: scenes {','.join(QUICK.scenes)}, "
                   f"presets {','.join(QUICK.presets)}, {QUICK.width}x{QUICK.height}, {QUICK.spp} spp, {QUICK.repeats} repeats")
    p.add_argument("--methods", type=_csv, help=f"comma-separated, default all available: {','.join(METHODS)}")
    p.add_argument("--presets", type=_csv, help=f"comma-separated from {','.join(PRESETS)} (default {','.join(DEFAULT.presets)})")
    p.add_argument("--scenes", type=_csv,
                   help=f"comma-separated built-in scenes (default {','.join(DEFAULT.scenes)}; none when --reference is given)")
    p.add_argument("--reference", nargs="+", action="extend", default=[], metavar="FILE.npz",
                   help="reference files (G-buffer + 'ao', e.g. from `torch-ao render`); named by file stem")
    p.add_argument("--height", type=int, help=f"reference height for built-in scenes (default {DEFAULT.height})")
    p.add_argument("--width", type=int, help=f"reference width (default {DEFAULT.width})")
    p.add_argument("--spp", type=int, help=f"reference samples per pixel (default {DEFAULT.spp})")
    p.add_argument("--max-distance", type=float, default=1.0, help="reference AO ray length R for built-in scenes")
    p.add_argument("--radius", type=float, help="methods' world radius (default: each reference's max distance, else 1)")
    p.add_argument("--params", metavar="JSON", action="append", help="per-method constructor arguments replacing the "
                   "defaults, e.g. fitted values: a `torch-ao fit` params.json, or a JSON file or string "
                   "{\"bitmask\": {\"thickness\": 0.3}} (repeatable)")
    p.add_argument("--fitted", nargs="+", default=[], metavar="PARAMS.json", help="fitted pipelines (`torch-ao fit` "
                   "params.json files) added as rows, at their own preset, radius, parameters and denoiser")
    p.add_argument("--repeats", type=int, help=f"timed runs per measurement (default {DEFAULT.repeats})")
    p.add_argument("--warmup", type=int, default=1, help="untimed runs before timing")
    p.add_argument("--no-denoise", action="store_true", help="skip the runs followed by the denoiser")
    p.add_argument("--no-backward", action="store_true", help="skip forward+backward timing")
    p.add_argument("--no-background", action="store_true", help="skip the full / half / all-background timing")
    p.add_argument("--tolerance", type=float, default=0.01, help="recommendation: allowed MAE above the best")
    p.add_argument("--cache", help="folder for cached references (default $TORCH_AO_CACHE or ~/.cache/torch_ao)")
    p.add_argument("--out", default="bench", help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    p.add_argument("--seed", type=int, default=0, help="reference sampling seed")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def _params(texts: list[str] | None) -> dict:
    """``{method: {parameter: value}}`` from JSON files or strings, either in that form or a
    ``torch-ao fit`` ``params.json`` (``{"method": ..., "parameters": {...}}``)."""
    out: dict = {}
    for text in texts or []:
        path = Path(text)
        try:
            data = json.loads(path.read_text() if path.is_file() else text)
        except json.JSONDecodeError as err:
            raise CommandError(f"--params: {text!r} is not a JSON file or string ({err})") from None
        if isinstance(data, dict) and "method" in data and isinstance(data.get("parameters"), dict):
            data = {data["method"]: data["parameters"]}
        if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
            raise CommandError("--params: expected {method: {parameter: value}} or a `torch-ao fit` params.json")
        for method, values in data.items():
            out.setdefault(method, {}).update(values)
    return out


def run(args: argparse.Namespace) -> int:
    from ..bench import DEFAULT, QUICK, available_methods, background_scaling, environment, load_bench_views, run_bench
    from ..bench_report import write_report
    from ..methods import PRESETS

    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise CommandError("--device: CUDA is not available on this machine")
    if args.threads is not None:
        if args.threads < 1:
            raise CommandError("--threads: expected an integer >= 1")
        torch.set_num_threads(args.threads)
    base = QUICK if args.quick else DEFAULT
    scenes = args.scenes if args.scenes is not None else ([] if args.reference else list(base.scenes))
    presets = args.presets or list(base.presets)
    for preset in presets:
        if preset not in PRESETS:
            raise CommandError(f"--presets: unknown preset {preset!r}; expected some of {', '.join(PRESETS)}")
    from ..reference import SCENES

    for s in scenes:
        if s not in SCENES:
            raise CommandError(f"--scenes: unknown scene {s!r}; built-in scenes: {', '.join(SCENES)}")
    for name, value in (("height", args.height), ("width", args.width), ("spp", args.spp), ("repeats", args.repeats)):
        if value is not None and value < 1:
            raise CommandError(f"--{name}: expected an integer >= 1, got {value}")
    if not (args.max_distance > 0):
        raise CommandError(f"--max-distance: expected a value > 0, got {args.max_distance}")
    if args.tolerance < 0 or not math.isfinite(args.tolerance):
        raise CommandError(f"--tolerance: expected a finite value >= 0, got {args.tolerance}")
    methods = available_methods(args.methods)
    if not methods:
        raise CommandError("--methods: none of the requested methods is available yet")
    params = _params(args.params)
    height, width = args.height or base.height, args.width or base.width
    spp, repeats = args.spp or base.spp, args.repeats or base.repeats
    progress = not args.quiet
    start = time.perf_counter()
    views = load_bench_views(scenes, args.reference, height=height, width=width, spp=spp,
                             max_distance=args.max_distance, seed=args.seed, cache_dir=args.cache, device=device,
                             progress=progress)
    rows = run_bench(views, methods, presets, denoise=not args.no_denoise, backward=not args.no_backward,
                     repeats=repeats, warmup=args.warmup, device=device, radius=args.radius, params=params,
                     progress=progress)
    if args.fitted:
        from ..fitted import bench_rows

        rows += bench_rows(args.fitted, views, backward=not args.no_backward, repeats=repeats, warmup=args.warmup,
                           device=device, progress=progress)
    background = None
    if not args.no_background:
        background = background_scaling(methods, "high", height=192, width=256, repeats=max(5, repeats),
                                        warmup=args.warmup, device=device, radius=args.radius or args.max_distance,
                                        progress=progress)
    env = environment(device)
    command = "torch-ao " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv and "torch-ao" in sys.argv[0] else None
    settings = {"scenes": scenes, "references": [str(p) for p in args.reference], "presets": presets,
                "methods": list(methods), "height": height, "width": width, "spp": spp,
                "max_distance": args.max_distance, "radius": args.radius, "repeats": repeats, "warmup": args.warmup,
                "denoise": not args.no_denoise, "backward": not args.no_backward, "params": params,
                "seconds": None}
    settings["seconds"] = round(time.perf_counter() - start, 1)
    files = write_report(args.out, rows, tolerance=args.tolerance, background=background, env=env,
                         command=command, settings=settings, plots=not args.no_plots)
    from ..bench_report import load_report

    rec = load_report(files["json"])["recommendations"]
    for scene, r in rec.items():
        print(f"{scene}: {r['method']} {r['preset']} (MAE {r['mae']:.4f}, {r['forward_ms']:.1f} ms; "
              f"best {r['best']['method']} {r['best']['preset']} MAE {r['best']['mae']:.4f})")
    print(f"{len(rows)} runs in {settings['seconds']:.0f} s on {env['device_name']} ({env['threads']} threads) -> "
          f"{Path(args.out) / 'bench.md'}")
    return 0
