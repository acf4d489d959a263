"""``torch-ao fit``: fit an AO method's parameters to ray-traced references (the main job).

With no arguments: render (or load from the cache) randomised views of the built-in scene set,
fit bitmask AO's thickness on the training views, and compare on held-out views the engine
defaults (thickness 0.25, 0.5, 1.0), GTAO with default parameters and the fitted bitmask.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

from ..cli import CommandError
from ..datasets import TRAIN_SCENES, default_cache_dir, train_and_holdout_views
from ..fit import FitConfig, evaluate, fit, load_views, set_mode
from ..io import save_json, write_text_atomic
from ..methods import METHODS, get_method


def register(sub) -> None:
    p = sub.add_parser(
        "fit",
        help="fit AO parameters (bitmask thickness by default) to ray-traced references",
        description="Fit a method's float parameters by gradient descent against ray-traced reference AO, "
        "then compare on held-out views. Without --reference, uses randomised views of the built-in scenes "
        "(rendered once, then cached). Re-running the same command resumes an interrupted fit.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--reference", nargs="+", metavar="FILE.npz", help="your own G-buffers with an 'ao' reference")
    p.add_argument("--holdout", nargs="+", metavar="FILE.npz", help="held-out references (default: the last third of --reference)")
    p.add_argument("--method", default="bitmask", help=f"method to fit: one of {', '.join(sorted(METHODS))}")
    p.add_argument("--params", default="thickness", help="comma-separated parameters to fit, e.g. thickness,radius")
    p.add_argument("--preset", default="high", help="quality preset of the fitted method")
    p.add_argument("--scenes", default=",".join(TRAIN_SCENES), help="built-in scenes (without --reference)")
    p.add_argument("--train-views", type=int, default=2, help="randomised training views per scene")
    p.add_argument("--size", default="160x96", help="render size WxH of built-in views")
    p.add_argument("--spp", type=int, default=256, help="reference rays per pixel")
    p.add_argument("--max-distance", type=float, default=1.0, help="reference AO distance R (also the method's radius)")
    p.add_argument("--steps", type=int, default=60, help="optimizer steps")
    p.add_argument("--lr", type=float, default=0.05, help="Adam learning rate")
    p.add_argument("--batch-views", type=int, default=0, help="training views per step (0 = all)")
    p.add_argument("--weighting", choices=("uniform", "cosine"), default="cosine",
                   help="sector weighting of the fitted bitmask method (cosine matches the cosine-weighted reference)")
    p.add_argument("--loss", choices=("l1", "mse"), default="l1")
    p.add_argument("--init", type=float, default=1.0, help="initial thickness")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cache", default=None, help=f"reference cache folder (default {default_cache_dir()})")
    p.add_argument("--out", default="fit-out", help="output folder (params.json, report.md, comparison.png, checkpoint.pt)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise CommandError(f"--size: expected WxH such as 160x96, got {text!r}") from None
    if w < 4 or h < 4:
        raise CommandError(f"--size: expected at least 4x4, got {text!r}")
    return w, h


def _views(args) -> tuple[list, list]:
    device = torch.device(args.device)
    if args.reference:
        train = load_views(args.reference, device=device)
        if args.holdout:
            return train, load_views(args.holdout, device=device)
        if len(train) == 1:
            print("note: one reference file; held-out scores are on the training view itself")
            return train, train
        n_hold = max(1, len(train) // 3)
        return train[:-n_hold], train[-n_hold:]
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    from ..reference import SCENES

    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        raise CommandError(f"--scenes: unknown scene(s) {', '.join(unknown)}; see `torch-ao render --list`")
    w, h = _size(args.size)
    common = dict(height=h, width=w, spp=args.spp, max_distance=args.max_distance, cache_dir=args.cache,
                  progress=not args.no_progress, device=device)
    print(f"references: {len(scenes)} scenes x ({args.train_views} training + 1 held-out) views at {w}x{h}, {args.spp} spp")
    return train_and_holdout_views(scenes, args.train_views, 1, **common)


def _build(name: str, args, **kwargs):
    cls = get_method(name)
    radius = {"radius": args.max_distance} if "radius" in cls.options() else {}  # (PSSAO walks in pixels)
    return cls(preset=args.preset, **radius, **kwargs).to(args.device)


def run(args: argparse.Namespace) -> int:
    if args.method not in METHODS:
        raise CommandError(f"--method: unknown method {args.method!r}; expected one of {', '.join(sorted(METHODS))}")
    if args.steps < 0:
        raise CommandError(f"--steps: expected >= 0, got {args.steps}")
    params = tuple(p.strip() for p in args.params.split(",") if p.strip())
    out = Path(args.out)
    train, held = _views(args)
    print(f"fitting {args.method} {', '.join(params)} on {len(train)} views, evaluating on {len(held)} held-out views")

    bitmask = args.method in ("bitmask", "ssilvb")
    init = {"thickness": args.init, "weighting": args.weighting} if bitmask else {}
    module = _build(args.method, args, **init)
    before = evaluate(module, held)
    cfg = FitConfig(params=params, steps=args.steps, lr=args.lr, loss=args.loss, batch_views=args.batch_views, seed=args.seed)
    result = fit(module, train, cfg, checkpoint=out / "checkpoint.pt", progress=not args.no_progress)
    after = evaluate(module, held, repeats=3)

    rows = []
    if bitmask:
        for t in (0.25, 0.5, 1.0):
            engine = _build(args.method, args, thickness=t, weighting="uniform")
            rows.append((f"{args.method} thickness={t:g} (engine default: uniform sectors)", evaluate(engine, held, repeats=3)))
    rows.append(("gtao (default parameters)", evaluate(_build("gtao", args), held, repeats=3)))
    fitted = ", ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in result.parameters.items())
    label = f"{args.method} fitted ({fitted}" + (f", {args.weighting} sectors)" if bitmask else ")")
    rows.append((label, after))
    table = _table(rows)
    print(table)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "report.md", f"Held-out views: {len(held)}; training views: {len(train)}; steps: {result.steps_done}\n\n{table}\n")
    payload = {"method": args.method, "preset": args.preset, "radius": args.max_distance, "parameters": result.parameters,
               "before": before, "after": after, "steps": result.steps_done, "fit_seconds": result.seconds,
               "history": [{k: v for k, v in r.items()} for r in result.history]}
    save_json(out / "params.json", payload)
    _comparison_png(out / "comparison.png", held[0], _build(args.method, args, **init), module)
    print(f"wrote {out / 'params.json'}, {out / 'report.md'}, {out / 'comparison.png'}")
    return 0


def _table(rows) -> str:
    lines = ["| method | MAE | RMSE | PSNR (dB) | SSIM | time (ms) |", "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for name, m in rows:
        lines.append(f"| {name} | {m['mae']:.4f} | {m['rmse']:.4f} | {m['psnr']:.2f} | {m['ssim']:.4f} | {m['seconds'] * 1000:.1f} |")
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
